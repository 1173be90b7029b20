"""A trained avatar: the forest plus one Gaussian per face (numpy only: runs inside Blender).

Per-face residual parameters, in the forest's face order:
  d_mu [N,3] face-local position offset (units of the face scale), d_log_scale [N,3],
  d_rot [N,4] wxyz (unnormalised), opacity_logit [N], f_dc [N,3] (SH DC colour),
  f_rest [N,K,3] (higher SH bands, K = 0, 3, 8 or 15 for degree 0..3; core/geometry/sh.py).
Stored as .npz (never pickle).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import binding
from ..geometry import sh
from ..io.atomic import atomic_savez
from .forest import Forest
from ..geometry.sh import SH_C0
from ..io.safe_io import check_npz, loads_json, npz_read_errors

PARAM_NAMES = ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc")
PARAM_WIDTH = {"d_mu": 3, "d_log_scale": 3, "d_rot": 4, "opacity_logit": None, "f_dc": 3}
# exp(88.73) overflows float32: a residual log-scale at or above this is an infinite scale.
LOG_SCALE_MAX = float(np.log(np.finfo(np.float32).max))


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def sh_to_rgb(f_dc):
    return np.maximum(0.5 + SH_C0 * f_dc, 0.0)


@dataclass
class Avatar:
    forest: Forest
    d_mu: np.ndarray
    d_log_scale: np.ndarray
    d_rot: np.ndarray
    opacity_logit: np.ndarray
    f_dc: np.ndarray
    meta: dict = field(default_factory=dict)
    f_rest: np.ndarray | None = None

    def __post_init__(self):
        N = self.forest.num_faces
        rest = np.zeros((N, 0, 3), np.float32) if self.f_rest is None else np.asarray(self.f_rest, np.float32)
        if rest.ndim != 3 or rest.shape[0] != N or rest.shape[2] != 3:
            raise ValueError(f"Avatar: f_rest has shape {rest.shape}, expected [{N},K,3]")
        sh.degree_of(rest.shape[1])
        if not np.all(np.isfinite(rest)):
            raise ValueError("Avatar: f_rest contains NaN or inf")
        self.f_rest = rest
        for name in PARAM_NAMES:
            arr = np.asarray(getattr(self, name), np.float32)
            width = PARAM_WIDTH[name]
            expected = (N,) if width is None else (N, width)
            if arr.shape != expected:
                raise ValueError(f"Avatar: {name} has shape {arr.shape}, expected {expected}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"Avatar: {name} contains NaN or inf")
            setattr(self, name, arr)
        if self.d_log_scale.size and self.d_log_scale.max() >= LOG_SCALE_MAX:
            i = int(np.argmax(self.d_log_scale.max(axis=1)))
            raise ValueError(
                f"Avatar: d_log_scale of face {i} is {float(self.d_log_scale[i].max()):g}, at or above "
                f"{LOG_SCALE_MAX:.2f} (its scale would be infinite)"
            )

    @classmethod
    def from_verified(cls, forest: Forest, params: dict, meta: dict) -> "Avatar":
        """An Avatar from float32 arrays of the right shapes known to be finite and in range:
        what ``__post_init__`` checks with a full pass over every array, which the stream
        reader has already done record by record. Degree-0 colour only. Equal to
        ``Avatar(forest, **params, meta=meta)`` (tests/test_stream.py)."""
        av = cls.__new__(cls)
        av.forest = forest
        for name in PARAM_NAMES:
            setattr(av, name, params[name])
        av.meta = meta
        av.f_rest = np.zeros((forest.num_faces, 0, 3), np.float32)
        return av

    @classmethod
    def initial(cls, forest: Forest, color=(0.5, 0.5, 0.5), opacity=0.9, log_scale=0.0) -> "Avatar":
        N = forest.num_faces
        rot = np.zeros((N, 4), np.float32)
        rot[:, 0] = 1
        f_dc = (np.asarray(color, np.float32) - 0.5) / SH_C0
        logit = np.log(opacity / (1 - opacity))
        return cls(forest, np.zeros((N, 3)), np.full((N, 3), log_scale), rot, np.full(N, logit), np.tile(f_dc, (N, 1)))

    @property
    def num_gaussians(self) -> int:
        return self.forest.num_faces

    @property
    def sh_degree(self) -> int:
        rest = getattr(self, "f_rest", None)  # (stream-built avatars may not set it)
        return 0 if rest is None else sh.degree_of(rest.shape[1])

    def colors(self, ids=None, means=None, camera_center=None) -> np.ndarray:
        """RGB [n,3] of faces ``ids``: view-dependent when the avatar has SH bands and the
        Gaussians' means and a camera centre are given, else the DC colour."""
        sel = slice(None) if ids is None else np.asarray(ids)
        if self.sh_degree == 0 or means is None or camera_center is None:
            return sh_to_rgb(self.f_dc[sel]).astype(np.float32)
        d = np.asarray(means, np.float64) - np.asarray(camera_center, np.float64).reshape(1, 3)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        rgb = sh.sh_rgb(self.f_dc[sel].astype(np.float64), self.f_rest[sel].astype(np.float64), d, np.stack)
        return np.maximum(rgb, 0.0).astype(np.float32)

    def subset(self, ids) -> dict:
        return {name: getattr(self, name)[ids] for name in PARAM_NAMES}

    def evaluator(self, ids=None, weights=None, capacity=None, rows=None, threads=1) -> binding.GaussianEvaluator:
        """A per-frame evaluator of this avatar's Gaussians (faces `ids`, default all; output
        rows `rows`, default 0..n-1; `threads`: GaussianEvaluator's)."""
        return binding.GaussianEvaluator(
            self.forest,
            self.d_mu,
            self.d_log_scale,
            self.d_rot,
            ids=ids,
            weights=weights,
            capacity=capacity,
            rows=rows,
            threads=threads,
        )

    def gaussians(self, vertices: np.ndarray, ids=None, weights=None, camera_center=None) -> dict:
        """World-space, activated Gaussians for one frame's mesh vertices [V,3] (faces ``ids``;
        default: those that render, Forest.drawn).

        Returns means, quats (wxyz), scales, opacities, colors (RGB) as float32 numpy; colours
        are seen from ``camera_center`` when the avatar has SH bands (DC otherwise).
        """
        if ids is None and self.forest.stand_ins:
            ids = self.forest.drawn()  # the finished avatar (or this prefix) without retired stand-ins
        sel = slice(None) if ids is None else np.asarray(ids)
        means, quats, scales = self.evaluator(ids=ids, weights=weights)(vertices)
        return {
            "means": means.copy(),
            "quats": quats.copy(),
            "scales": scales.copy(),
            "opacities": sigmoid(self.opacity_logit[sel]).astype(np.float32),
            "colors": self.colors(ids, means, camera_center),
        }

    # -- persistence ----------------------------------------------------------------------
    def save(self, path) -> None:
        arrays = self.forest.state()
        arrays.update({name: getattr(self, name) for name in PARAM_NAMES})
        if self.sh_degree:
            arrays["f_rest"] = self.f_rest
        import json

        arrays["meta_json"] = np.array(json.dumps(self.meta))
        atomic_savez(path, **arrays)

    @classmethod
    def load(cls, path) -> "Avatar":
        check_npz(path, allow_text=("meta_json",))  # bounded before numpy allocates
        with npz_read_errors(path), np.load(path, allow_pickle=False) as data:
            forest = Forest.from_state(data, source=str(path))
            missing = [n for n in PARAM_NAMES if n not in data]
            if missing:
                raise ValueError(f"{path}: not an avatar file, missing {missing}")
            meta = loads_json(str(data["meta_json"]), f"{path}: meta_json") if "meta_json" in data else {}
            try:
                return cls(
                    forest,
                    *(data[n] for n in PARAM_NAMES),
                    meta=meta,
                    f_rest=data["f_rest"] if "f_rest" in data else None,
                )
            except ValueError as exc:
                raise ValueError(f"{path}: {exc}") from None
