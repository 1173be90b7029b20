"""Whole-dataset validation before training: every problem of every file, in one report.

``Dataset`` checks what it needs to index a split (the JSON and its fields) and opens
images, masks and meshes lazily, when a frame is first sampled: fine for previews, but a
training run would meet a missing image, a truncated PNG or a NaN mesh hours in.
:func:`validate_dataset` walks a split once (with a progress bar): it checks that every
listed image and mask exists, decodes it and checks its size and pixel format (the loader's
own check, ``dataset._to_8bit``), loads every timestep's mesh (vertex count, NaN, missing file),
checks every camera (a rotation, finite intrinsics, principal point, and that it sees some of
its timestep's mesh), that the canonical mesh has an area, and that timestep and camera
indices are whole numbers. Problems are collected, not raised one by one; the
DataError lists each with its file and field.
"""

from __future__ import annotations

import os

import numpy as np

from .dataset import _listing, _not_found, _to_8bit, Dataset
from .sequences import DataError
from .safe_io import loads_json

__all__ = ["validate_dataset", "dataset_problems"]


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


_MAX_ABS = 1e30  # beyond it a camera value means nothing (and overflows float32 in Blender)


def camera_problems(cam, where: str) -> list:
    """What makes ``cam`` project garbage (empty when nothing): a rotation part that is not a
    rotation, intrinsics that are not finite (camera_angle_x 0 gives fx = inf), absurd values."""
    return [f"{where}: {p}" for p in _camera_faults(cam)]


def _camera_faults(cam) -> list:
    """camera_problems without the place (a camera's, whichever frames it serves)."""
    out = []
    R = np.asarray(cam.R)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or abs(np.linalg.det(R) - 1.0) > 1e-3:
        out.append(
            f"transform_matrix: the rotation part is not a rotation (det {np.linalg.det(R):.3g}; "
            "an all-zero or scaled matrix?)"
        )
    if np.abs(np.asarray(cam.t)).max() > _MAX_ABS:
        out.append(f"transform_matrix: the camera is placed beyond ±{_MAX_ABS:g}")
    for name in ("fx", "fy", "cx", "cy"):
        v = getattr(cam, name)
        if not np.isfinite(v) or abs(v) > _MAX_ABS:
            out.append(f"{'principal point' if name[0] == 'c' else 'focal length'} {name} is {v}")
    return out


def sees_mesh(cam, vertices: np.ndarray) -> bool:
    """Whether any vertex lies in front of ``cam`` and inside its image."""
    uv, z = cam.project(np.asarray(vertices, np.float64))
    with np.errstate(invalid="ignore"):
        inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < cam.width) & (uv[..., 1] >= 0) & (uv[..., 1] < cam.height)
    return bool(inside.any())


def _template_problems(ds: Dataset) -> list:
    """A canonical mesh with no area binds every Gaussian to a point or a line: training
    then ends "successfully" with nothing learnt."""
    v, f = np.asarray(ds.canonical_vertices, np.float64), ds.faces
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum() / 2
    if area > 0:
        return []
    return [f"{ds.root}: the canonical mesh has no area (its vertices coincide or lie on one line)"]


def _image_problems(path: str, what: str, full: tuple, target: tuple, json_path: str) -> list:
    from PIL import Image

    if not os.path.isfile(path):
        return [_not_found(path, what, json_path)]
    out = []
    try:
        with Image.open(path) as im:
            im.load()  # decodes every byte: a truncated file fails here
            size = im.size
            try:
                _to_8bit(im, path, what)  # the pixel formats (and 16-bit range) the loader reads
            except DataError as exc:
                out.append(str(exc))
    except Exception as exc:  # PIL raises many types for broken files
        return [f"{path}: {what}: cannot be decoded ({type(exc).__name__}: {exc})"]
    if size != tuple(full) and size != tuple(target):
        out.insert(0, f"{path}: {what}: size {size[0]}x{size[1]}, the dataset says {full[0]}x{full[1]}")
    return out


def dataset_problems(ds: Dataset, progress: bool = True, share: tuple[int, int] = (0, 1)) -> list:
    """Every problem found in split ``ds`` as 'file: field: problem' strings (empty: fine).
    ``share`` (k, n): only every n-th timestep and frame from the k-th, so n processes check a
    split together in 1/n of the time (the JSON's index fields are checked by share 0)."""
    from tqdm import tqdm

    k, n = int(share[0]), int(share[1])
    if not 0 <= k < n:
        raise ValueError(f"dataset_problems: share must be (k, n) with 0 <= k < n, got {share}")
    problems = []
    if k == 0 and ds.canonical_vertices is not None:
        problems.extend(_template_problems(ds))
    rows = _frame_rows(ds) if k == 0 else []
    for i, fr in enumerate(rows):
        for key in ("timestep_index", "camera_index"):
            if key in fr and not _whole(fr[key]):
                problems.append(f"{ds.json_path}: frames[{i}].{key} is {fr[key]!r}, not a whole number")
    for ts in tqdm(
        ds.timesteps.tolist()[k::n], desc=f"checking {ds.split or 'all'} meshes", disable=not progress, leave=False
    ):
        try:
            ds.vertices_at(ts)
        except (DataError, OSError, ValueError, KeyError) as exc:
            problems.append(f"{exc}" if os.sep in str(exc) else f"timestep {ts}: {exc}")
    blind = []
    faults = {}  # per camera: the frames of one camera share it (Dataset), 16 in a 16-camera split
    for info in tqdm(ds.frames[k::n], desc=f"checking {ds.split or 'all'} images", disable=not progress, leave=False):
        cam_faults = faults.get(id(info.camera))
        if cam_faults is None:
            cam_faults = faults[id(info.camera)] = _camera_faults(info.camera)
        bad_camera = [f"{ds.json_path}: frames[{info.index}]: {p}" for p in cam_faults]
        problems.extend(bad_camera)
        if not bad_camera and ds.canonical_vertices is not None:
            try:
                verts = ds.vertices_at(info.timestep_index)  # (cached by the meshes' pass)
            except (DataError, OSError, ValueError, KeyError):
                verts = None  # reported there
            if verts is not None and not sees_mesh(info.camera, verts):
                blind.append(f"frames[{info.index}] ({os.path.basename(info.image_path)})")
        target = (info.camera.width, info.camera.height)
        problems.extend(_image_problems(info.image_path, "image", info.full_size, target, ds.json_path))
        if info.mask_path is not None:
            problems.extend(_image_problems(info.mask_path, "mask", info.full_size, target, ds.json_path))
    if blind:  # one entry: a convention mistake makes every frame blind
        shown = ", ".join(blind[:8]) + (f" and {len(blind) - 8} more" if len(blind) > 8 else "")
        problems.append(
            f"{ds.json_path}: {len(blind)} frame(s) whose camera sees none of its timestep's mesh (every vertex "
            f"behind it or outside the image): {shown}; a camera looking away, or a transform_matrix in other "
            "axes than OpenGL's (x right, y up, looking down -z; docs/DATASET.md)"
        )
    return problems


def validate_dataset(ds: Dataset, progress: bool = True, share: tuple[int, int] = (0, 1)) -> None:
    """Raise one DataError listing every problem of split ``ds`` (see module doc; ``share``:
    :func:`dataset_problems`'s)."""
    problems = dataset_problems(ds, progress, share)
    if problems:
        raise DataError(
            f"{ds.root}: the '{ds.split}' split has {len(problems)} problem(s); fix them before "
            f"training:{_listing(problems)}"
        )
