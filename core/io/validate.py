"""Whole-dataset validation before training: every problem of every file, in one report.

``Dataset`` checks what it needs to index a split (the JSON, that listed files exist) and
decodes pixels and meshes lazily, when a frame is first sampled: fine for previews, but a
training run would meet a truncated PNG or a NaN mesh hours in. :func:`validate_dataset`
walks a split once (with a progress bar): it decodes every image and mask and checks their
sizes and pixel formats, loads every timestep's mesh (vertex count, NaN, missing file),
checks every camera (a rotation, finite intrinsics, principal point) and that timestep and
camera indices are whole numbers. Problems are collected, not raised one by one; the
DataError lists each with its file and field.
"""

from __future__ import annotations

import os

import numpy as np

from .dataset import Dataset
from .sequences import DataError
from .safe_io import loads_json

__all__ = ["validate_dataset", "dataset_problems"]

# PIL modes the loader decodes correctly (16-bit greyscale is rescaled, see data._to_8bit).
_IMAGE_MODES = {"RGB", "RGBA", "L", "LA", "P", "I;16", "I;16L", "I;16B", "I"}
_MAX_LISTED = 40


def _frame_rows(ds: Dataset) -> list:
    with open(ds.json_path, "rb") as fh:
        meta = loads_json(fh.read(), ds.json_path)
    return meta.get("frames", [])


def _whole(value) -> bool:
    return (
        isinstance(value, int)
        and not isinstance(value, bool)
        or (isinstance(value, float) and np.isfinite(value) and value.is_integer())
    )


def _camera_problems(cam, where: str) -> list:
    out = []
    R = np.asarray(cam.R)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or abs(np.linalg.det(R) - 1.0) > 1e-3:
        out.append(
            f"{where}: transform_matrix: the rotation part is not a rotation (det {np.linalg.det(R):.3g}; "
            "an all-zero or scaled matrix?)"
        )
    for name in ("fx", "fy", "cx", "cy"):
        v = getattr(cam, name)
        if not np.isfinite(v):
            out.append(f"{where}: {'principal point' if name[0] == 'c' else 'focal length'} {name} is {v}")
    return out


def _image_problems(path: str, what: str, full: tuple, target: tuple) -> list:
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()  # decodes every byte: a truncated file fails here
            size, mode = im.size, im.mode
    except Exception as exc:  # PIL raises many types for broken files
        return [f"{path}: {what}: cannot be decoded ({type(exc).__name__}: {exc})"]
    out = []
    if size != tuple(full) and size != tuple(target):
        out.append(f"{path}: {what}: size {size[0]}x{size[1]}, the dataset says {full[0]}x{full[1]}")
    if mode not in _IMAGE_MODES:
        out.append(f"{path}: {what}: pixel format {mode!r} is not supported (8-bit RGB/RGBA/L or 16-bit L)")
    return out


def dataset_problems(ds: Dataset, progress: bool = True) -> list:
    """Every problem found in split ``ds`` as 'file: field: problem' strings (empty: fine)."""
    from tqdm import tqdm

    problems = []
    rows = _frame_rows(ds)
    for i, fr in enumerate(rows):
        for key in ("timestep_index", "camera_index"):
            if key in fr and not _whole(fr[key]):
                problems.append(f"{ds.json_path}: frames[{i}].{key} is {fr[key]!r}, not a whole number")
    for ts in tqdm(
        ds.timesteps.tolist(), desc=f"checking {ds.split or 'all'} meshes", disable=not progress, leave=False
    ):
        try:
            ds.vertices_at(ts)
        except (DataError, OSError, ValueError, KeyError) as exc:
            problems.append(f"{exc}" if os.sep in str(exc) else f"timestep {ts}: {exc}")
    for info in tqdm(ds.frames, desc=f"checking {ds.split or 'all'} images", disable=not progress, leave=False):
        problems.extend(_camera_problems(info.camera, f"{ds.json_path}: frames[{info.index}]"))
        target = (info.camera.width, info.camera.height)
        problems.extend(_image_problems(info.image_path, "image", info.full_size, target))
        if info.mask_path is not None:
            problems.extend(_image_problems(info.mask_path, "mask", info.full_size, target))
    return problems


def validate_dataset(ds: Dataset, progress: bool = True) -> None:
    """Raise one DataError listing every problem of split ``ds`` (see module doc)."""
    problems = dataset_problems(ds, progress)
    if problems:
        listed = "\n  ".join(problems[:_MAX_LISTED])
        more = f"\n  ... and {len(problems) - _MAX_LISTED} more" if len(problems) > _MAX_LISTED else ""
        raise DataError(
            f"{ds.root}: the '{ds.split}' split has {len(problems)} problem(s); fix them before "
            f"training:\n  {listed}{more}"
        )
