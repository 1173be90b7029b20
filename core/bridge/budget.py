"""Avatars and budgets for the Blender preview: an avatar loaded from a stream or npz file, and
``Budget`` (Gaussians / bytes / level reached for a budget percent, taken from the stream's own
``count_for_percent`` when the avatar came from a stream). Blender tier (numpy).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ..avatar.avatar import Avatar


def _stream_module():
    try:
        from ..stream import format as stream
    except ImportError:
        return None
    return stream


def typed_percent(value: float) -> float:
    """The percent as typed, from a value Blender kept in 32 bits (a FloatProperty: 16.1 reads
    back as 16.100000381...): the shortest decimal that float32 holds. The stream's budget rule
    floors p/100 of the bytes exactly, so the stored value could show one Gaussian more or fewer
    than a viewer given the same percent."""
    return float(str(np.float32(value)))


def fraction_count(total: int, percent: float) -> int:
    """The same fraction of ``total`` Gaussians, rounded (files without a byte layout to follow)."""
    p = float(min(max(percent, 0.0), 100.0))
    return int(min(total, math.floor(total * p / 100.0 + 0.5)))


@dataclass
class Budget:
    """How much of an avatar a budget percent includes.

    ``info`` is the stream's header object when the avatar was read from a stream (its
    ``count_for_percent`` is the single definition of a percent); plain avatar files fall
    back to the same fraction of Gaussians (there is no byte layout to follow).
    """

    total: int
    levels: np.ndarray  # int8 [N], stream order (Budget.for_avatar)
    file_bytes: int
    info: object | None = None

    def __post_init__(self):
        # deepest level among the first k records (a version 5 stream interleaves the levels)
        self._reached = np.maximum.accumulate(np.asarray(self.levels)) if len(self.levels) else self.levels

    @classmethod
    def for_avatar(cls, avatar: Avatar, file_bytes: int, info=None) -> "Budget":
        f = avatar.forest
        return cls(avatar.num_gaussians, f.level[f.stream_order()], file_bytes, info)

    def count_for_percent(self, percent: float) -> int:
        p = float(min(max(percent, 0.0), 100.0))
        if self.info is not None and hasattr(self.info, "count_for_percent"):
            return int(min(max(int(self.info.count_for_percent(p)), 0), self.total))
        return fraction_count(self.total, p)

    def count_for_slider(self, value: float) -> int:
        """``count_for_percent`` of a budget slider's value, read back as typed (typed_percent)."""
        return self.count_for_percent(typed_percent(value))

    def bytes_for_count(self, count: int) -> int:
        if self.info is not None and hasattr(self.info, "bytes_for_count"):
            return int(self.info.bytes_for_count(int(count)))
        return int(round(self.file_bytes * count / max(self.total, 1)))

    def level_reached(self, count: int) -> int:
        return int(self._reached[min(count, self.total) - 1]) if count > 0 else -1

    def max_level(self) -> int:
        """Deepest level of the whole avatar: a stream's header knows it even when the
        stream was cut, so depth colours keep their meaning at any prefix."""
        n = getattr(self.info, "num_levels", None)
        if n:
            return int(n) - 1
        return int(self.levels.max()) if len(self.levels) else 0

    def max_depth(self, forest=None) -> int:
        """Deepest subdivision depth below the template of the whole avatar (the depth colours'
        scale): the deepest level less the coarse levels above the template."""
        k = getattr(self.info, "num_coarse_levels", None)
        if k is None:
            k = getattr(forest, "num_coarse_levels", 0) if forest is not None else 0
        return max(self.max_level() - int(k), 0)


def load_avatar(path, template_faces=None) -> tuple[Avatar, Budget]:
    """An avatar from a stream file (.pavs, recognised by its magic) or an avatar .npz, and its
    budget. A face's stream position is ``avatar.forest.stream_rank()`` (its index unless the
    stream interleaved roots with deeper faces); .npz files keep what the forest recorded. A stream cut anywhere (even inside the template level)
    gives the Gaussians it holds whole; ``template_faces`` (the mesh's) stand in for a
    template the stream does not embed."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: file not found")
    stream = _stream_module()
    size = os.path.getsize(path)
    if size == 0:
        raise ValueError(f"{path}: the file is empty (0 bytes), not an avatar stream or avatar .npz")
    with open(path, "rb") as fh:
        head = fh.read(8)
    info = None
    if stream is not None and head == stream.MAGIC:
        try:
            info = stream.read_header(path)
        except ValueError as exc:  # a stream cut inside its header
            raise ValueError(f"{exc}; no Gaussian arrived (the stream's records start after its header)") from None
        tmpl = None if info.template_embedded else template_faces
        from ..stream.reader import read_stream

        try:
            avatar = read_stream(path, template_faces=tmpl)
        except stream.TemplateMismatch as exc:  # the mesh's; name the file it was checked against
            raise stream.TemplateMismatch(f"{path}: {exc}") from None
        if avatar is None:
            raise ValueError(
                f"{path}: the stream holds no complete Gaussian record ({size} of "
                f"{info.total_bytes} bytes arrived; the first record ends at byte "
                f"{info.bytes_for_count(1)})"
            )
    elif head[:2] == b"PK":  # zip container: numpy's .npz
        try:
            avatar = Avatar.load(path)
        except (ValueError, KeyError, OSError) as exc:
            msg = str(exc).replace(f"{path}: ", "")
            raise ValueError(
                f"{path}: not an avatar file (a ProgressiveAvatars stream .pavs or avatar .npz): {msg}"
            ) from None
    else:
        raise ValueError(
            f"{path}: not a ProgressiveAvatars stream or avatar .npz (the file starts with "
            f"{bytes(head[:8])!r}; streams start with {stream.MAGIC if stream else 'their magic'!r})"
        )
    budget = Budget.for_avatar(avatar, os.path.getsize(path), info)
    return avatar, budget


def check_mesh(avatar: Avatar, budget: Budget, faces) -> None:
    """Refuse a mesh the avatar was not made for (vertex indices / the stream's template hash)."""
    faces = np.asarray(faces)
    need = int(avatar.forest.template_faces.max()) + 1
    if faces.size and int(faces.max()) + 1 < need:
        raise ValueError(f"the mesh has {int(faces.max()) + 1} vertices in use; the avatar's template needs {need}")
    if budget.info is not None:
        _stream_module().check_template(budget.info, faces)
    elif faces.shape != avatar.forest.template_faces.shape or not np.array_equal(faces, avatar.forest.template_faces):
        raise ValueError(
            f"the mesh's faces {faces.shape} are not the avatar's template {avatar.forest.template_faces.shape}"
        )
