"""Mesh sequences and the sequence readers Blender's importers call (layout: docs/DATASET.md).

Sequence readers turn the tracked-geometry formats users have into one ``MeshSequence``
(fixed faces, per-frame vertices), evaluating only the frames asked for:
- GaussianAvatars/VHAP per-frame folder ``flame_param/*.npz`` (needs a FLAME model),
- VHAP ``tracked_flame_params_*.npz`` (T-stacked; needs a FLAME model),
- NeRSemble benchmark FLAME tracking npz (needs a FLAME model),
- mesh npz (``vertices`` [T,V,3] + ``faces``), a folder of OBJ/PLY frames (core/io/mesh_io.py),
- a dataset root (``transforms_*.json``): its tracked geometry, through ``dataset.Dataset``.

Every reader takes ``progress``, a callable or None (the default: nothing is called). A
1000-frame folder takes seconds (Blender's importer shows its progress), so the readers call
``progress(done, total)`` after each step: a file read, or a chunk of frames evaluated by FLAME
(:func:`flame_forward`'s chunks). ``total`` is fixed for the call, ``done`` grows, and on success
the last call is ``(total, total)``: per-frame folders make one step per file (a FLAME folder
evaluated: as many again for its frames), one file one step (a FLAME file evaluated: one more
per frame). A selection of no frames from a folder makes no steps and no call.

Blender tier: numpy only (this module runs inside Blender).
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..flame.model import FlameModel, flame_forward, load_flame_model
from .safe_io import check_npz


__all__ = [
    "DataError",
    "MissingFileError",
    "MeshSequence",
    "read_sequence",
    "read_flame_track",
    "FlameTrack",
    "read_flame_param_folder",
    "read_vhap_tracked",
    "read_nersemble_tracking",
    "read_mesh_npz",
    "read_mesh_folder",
    "natural_key",
]

_MESH_EXTS = (".obj", ".ply")


class DataError(ValueError):
    """Input data is malformed: the message names the file and the problem."""


class MissingFileError(DataError, FileNotFoundError):
    """A file the data refers to does not exist (the message names it)."""


def natural_key(name: str):
    """Sort key that orders 'frame2' before 'frame10'."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", os.path.basename(name))]


def _check_vertices(v: np.ndarray, source: str, n_vertices: int | None = None) -> np.ndarray:
    v = np.asarray(v)
    if v.ndim < 2 or v.shape[-1] != 3:
        raise DataError(f"{source}: vertices must be [...,V,3], got shape {v.shape}")
    if n_vertices is not None and v.shape[-2] != n_vertices:
        raise DataError(f"{source}: {v.shape[-2]} vertices, but the template has {n_vertices}")
    v = v.astype(np.float32, copy=False)
    if not np.all(np.isfinite(v)):
        bad = np.argwhere(~np.isfinite(v).all(axis=-1))[0]
        raise DataError(f"{source}: vertices contain NaN or inf (first at index {tuple(int(i) for i in bad)})")
    return v


def _check_faces(f, source: str, n_vertices: int) -> np.ndarray:
    f = np.asarray(f)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise DataError(f"{source}: faces must be an integer [F,3] array, got {f.dtype} {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= n_vertices):
        raise DataError(f"{source}: faces index vertices outside 0..{n_vertices - 1}")
    return f.astype(np.int32)


@dataclass
class MeshSequence:
    """A fixed-topology mesh animation: faces int32 [F,3], vertices float32 [T,V,3]."""

    faces: np.ndarray
    vertices: np.ndarray
    frame_ids: np.ndarray
    flame_params: dict | None = None
    source: str = ""

    def __post_init__(self):
        src = self.source or "mesh sequence"
        self.vertices = _check_vertices(self.vertices, src)
        if self.vertices.ndim != 3:
            raise DataError(f"{src}: vertices must be [T,V,3], got {self.vertices.shape}")
        self.faces = _check_faces(self.faces, src, self.vertices.shape[1])
        self.frame_ids = np.asarray(self.frame_ids, dtype=np.int64).reshape(-1)
        if self.frame_ids.shape[0] != self.vertices.shape[0]:
            raise DataError(f"{src}: {self.frame_ids.shape[0]} frame ids for {self.vertices.shape[0]} frames")

    @property
    def n_frames(self) -> int:
        return self.vertices.shape[0]

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[1]


@dataclass
class FlameTrack:
    """FLAME parameters of a tracked sequence, not evaluated: what a rig is built from.
    ``params`` as :func:`flame.flame_forward` takes them (NeRSemble files add their
    placement: ``rotation_matrices`` [T,3,3], ``translation`` [T,3], ``scale``)."""

    params: dict
    frame_ids: np.ndarray
    source: str = ""

    @property
    def n_frames(self) -> int:
        return len(self.frame_ids)


# --------------------------------------------------------------------------------------
# Readers


def _select(n: int, frames, source: str) -> np.ndarray:
    """Positions 0..n-1 asked for (None: all), validated."""
    if frames is None:
        return np.arange(n)
    idx = np.asarray(list(frames) if not isinstance(frames, (np.ndarray, range)) else frames, dtype=np.int64).reshape(
        -1
    )
    if idx.size and (idx.min() < -n or idx.max() >= n):
        raise DataError(f"{source}: frame index out of range for a sequence of {n} frames: {idx.tolist()[:10]}")
    return np.where(idx < 0, idx + n, idx)


def _npz(path: str) -> dict:
    if not os.path.isfile(path):
        raise MissingFileError(f"{path}: file not found")
    try:
        check_npz(path)  # headers first: a forged element count is refused before allocation
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:
        raise DataError(f"{path}: not a readable npz of plain arrays ({type(exc).__name__}: {exc})") from exc


def _need_model(flame_model, source: str) -> FlameModel:
    if flame_model is None:
        raise DataError(
            f"{source}: FLAME parameters need a FLAME model file (your own generic_model.pkl / "
            "flame2023.pkl): set the FLAME model in the add-on preferences or the importer, or "
            "pass --flame-model to the scripts"
        )
    return load_flame_model(flame_model)


def _ids_from(values, n: int, source: str = "", key: str = "") -> np.ndarray:
    """Integer frame ids from stored ids (ints, whole floats, or strings with digits), else 0..n-1.
    Stored ids whose count is not the frame count are refused (they belong to other frames)."""
    if values is None:
        return np.arange(n)
    vals = np.asarray(values).reshape(-1)
    if vals.shape[0] != n:
        raise DataError(f"{source}: '{key}' holds {vals.shape[0]} frame ids for {n} frames")
    if np.issubdtype(vals.dtype, np.integer):
        return vals.astype(np.int64)
    if np.issubdtype(vals.dtype, np.floating):
        if np.all(np.isfinite(vals)) and np.all(vals == np.round(vals)) and np.abs(vals).max(initial=0) < 2**53:
            return vals.astype(np.int64)
        return np.arange(n)
    digits = [re.findall(r"\d+", str(v)) for v in vals.tolist()]
    if all(digits):
        return np.array([int(d[-1]) for d in digits], dtype=np.int64)
    return np.arange(n)


# Accepted spellings: VHAP writes *_pose, some exports and ANCHORS shorten them.
_ALIASES = {
    "rotation": ("rotation", "global_pose", "root_pose"),
    "translation": ("translation", "transl"),
    "neck_pose": ("neck_pose", "neck"),
    "jaw_pose": ("jaw_pose", "jaw"),
    "eyes_pose": ("eyes_pose", "eyes", "eye_pose"),
    "shape": ("shape", "betas", "shape_params"),
    "expr": ("expr", "expression", "expression_params"),
    "static_offset": ("static_offset",),
    "dynamic_offset": ("dynamic_offset",),
}
# What a per-frame FLAME parameter file (VHAP, GaussianAvatars) must hold; the offsets are optional.
REQUIRED_FLAME_KEYS = ("shape", "expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")


def check_frame_keys(d: dict, path: str) -> None:
    """A per-frame FLAME parameter file holds every required key (as zeros a missing rotation
    or shape would move the head silently, by up to 10 cm)."""
    missing = [k for k in REQUIRED_FLAME_KEYS if k not in d]
    if missing:
        raise DataError(
            f"{path}: FLAME parameters lack {', '.join(missing)} (each file needs "
            f"{', '.join(REQUIRED_FLAME_KEYS)}; static_offset and dynamic_offset are optional)"
        )


_PER_FRAME = ("rotation", "translation", "neck_pose", "jaw_pose", "eyes_pose", "expr", "dynamic_offset")


def _flame_keys(d: dict) -> dict:
    out = {}
    for key, names in _ALIASES.items():
        for n in names:
            if n in d:
                out[key] = np.asarray(d[n])
                break
    return out


def _evaluate_flame(params: dict, model: FlameModel, source: str, progress=None) -> np.ndarray:
    try:
        return flame_forward(model, **params, progress=progress)
    except ValueError as exc:
        raise DataError(f"{source}: {exc}") from exc


def read_flame_param_folder(
    path, frames=None, flame_model=None, evaluate=True, *, progress: Callable[[int, int], None] | None = None
):
    """GaussianAvatars/VHAP per-frame FLAME parameters: ``path/*.npz`` (or ``path/flame_param/*.npz``).

    Each file holds translation (1,3), rotation (1,3), neck_pose (1,3), jaw_pose (1,3),
    eyes_pose (1,6), shape (300), expr (1,100), static_offset (1,V,3). Frame ids come from
    the digits in the file names. Only the files of the frames asked for are opened.
    ``evaluate=False`` returns the parameters (:class:`FlameTrack`) without a model.
    """
    path = os.fspath(path)
    folder = os.path.join(path, "flame_param") if os.path.isdir(os.path.join(path, "flame_param")) else path
    files = sorted((f for f in os.listdir(folder) if f.endswith(".npz")), key=natural_key)
    if not files:
        raise DataError(f"{folder}: no .npz FLAME parameter files")
    model = _need_model(flame_model, folder) if evaluate else None
    sel = _select(len(files), frames, folder)
    n = len(sel)
    total = 2 * n if evaluate else n  # each file read, then each frame evaluated
    params = {k: [] for k in _ALIASES}
    for j, i in enumerate(sel.tolist()):  # one small file per asked frame; the FLAME evaluation below is batched
        fp = os.path.join(folder, files[i])
        d = _flame_keys(_npz(fp))
        if "expr" not in d and "shape" not in d:
            raise DataError(f"{fp}: no FLAME parameters (expected keys {', '.join(_ALIASES)})")
        check_frame_keys(d, fp)
        for k in _ALIASES:
            params[k].append(d.get(k))
        if progress is not None:
            progress(j + 1, total)
    names = [files[i] for i in sel.tolist()]
    stacked = {}
    for k, vals in params.items():
        present = [v for v in vals if v is not None]
        if not present:
            continue
        if len(present) != len(vals):
            raise DataError(f"{folder}: '{k}' is present in some parameter files but not all")
        for name, v in zip(names[1:], present[1:]):
            if np.size(v) != np.size(present[0]):
                raise DataError(
                    f"{os.path.join(folder, name)}: '{k}' has {np.size(v)} values, "
                    f"{names[0]} has {np.size(present[0])} (every frame's file must hold the same)"
                )
            if k in ("shape", "static_offset") and not np.array_equal(v, present[0]):
                raise DataError(
                    f"{os.path.join(folder, name)}: '{k}' differs from {names[0]}'s; it describes the "
                    "subject and must be the same in every frame's file"
                )
        if k in ("shape", "static_offset"):
            stacked[k] = np.asarray(present[0])  # per subject, identical across frames (checked)
        elif k == "dynamic_offset":
            stacked[k] = np.concatenate([v.reshape((-1,) + v.shape[-2:])[:1] for v in present])
        else:
            stacked[k] = np.concatenate([v.reshape(1, -1) for v in present])
    ids = _ids_from(names, len(sel))
    if not evaluate:
        return FlameTrack(stacked, ids, folder)
    evaluated = None if progress is None else (lambda done, _: progress(n + done, total))
    verts = _evaluate_flame(stacked, model, folder, evaluated) if n else np.zeros((0, model.n_vertices, 3), np.float32)
    return MeshSequence(model.faces, verts, ids, stacked, folder)


def _read_flame_stacked(path: str, d: dict, frames, flame_model, frame_key: str | None, evaluate=True, progress=None):
    p = _flame_keys(d)
    per_frame = [k for k in _PER_FRAME if k in p and p[k].ndim >= 2]
    if not per_frame:
        raise DataError(f"{path}: no per-frame FLAME parameters (expected some of {', '.join(_PER_FRAME)})")
    # The frame count is the longest key's: any key may be one row shared by every frame.
    longest = max(per_frame, key=lambda k: p[k].shape[0])
    T = p[longest].shape[0]
    for k in per_frame:
        if p[k].shape[0] not in (1, T):
            raise DataError(f"{path}: '{k}' has {p[k].shape[0]} frames, '{longest}' has {T}")
    model = _need_model(flame_model, path) if evaluate else None
    sel = _select(T, frames, path)
    params = {}
    for k, v in p.items():
        params[k] = v[sel] if k in per_frame and v.shape[0] == T else v
    ids = _ids_from(d.get(frame_key) if frame_key else None, T, path, frame_key)[sel]
    total = 1 + len(sel) if evaluate else 1  # the file, then each frame evaluated
    if progress is not None:
        progress(1, total)
    if not evaluate:
        return FlameTrack(params, ids, path)
    evaluated = None if progress is None else (lambda done, _: progress(1 + done, total))
    verts = (
        _evaluate_flame(params, model, path, evaluated) if len(sel) else np.zeros((0, model.n_vertices, 3), np.float32)
    )
    return MeshSequence(model.faces, verts, ids, params, path)


def read_vhap_tracked(
    path, frames=None, flame_model=None, evaluate=True, *, progress: Callable[[int, int], None] | None = None
):
    """VHAP ``tracked_flame_params_*.npz``: rotation, translation, neck_pose, jaw_pose (T,3),
    eyes_pose (T,6), shape (300), expr (T,100), static_offset (1,V,3), optional timestep_id."""
    path = os.fspath(path)
    return _read_flame_stacked(path, _npz(path), frames, flame_model, "timestep_id", evaluate, progress)


def _euler_xyz(angles: np.ndarray) -> np.ndarray:
    """Intrinsic X-Y-Z Euler angles [T,3] -> rotation matrices [T,3,3] (R = Rx Ry Rz)."""
    a = np.asarray(angles, np.float64).reshape(-1, 3)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros(len(a)), np.ones(len(a))
    rx = np.stack([i, o, o, o, c[:, 0], -s[:, 0], o, s[:, 0], c[:, 0]], -1).reshape(-1, 3, 3)
    ry = np.stack([c[:, 1], o, s[:, 1], o, i, o, -s[:, 1], o, c[:, 1]], -1).reshape(-1, 3, 3)
    rz = np.stack([c[:, 2], -s[:, 2], o, s[:, 2], c[:, 2], o, o, o, i], -1).reshape(-1, 3, 3)
    return rx @ ry @ rz


def read_nersemble_tracking(
    path, frames=None, flame_model=None, evaluate=True, *, progress: Callable[[int, int], None] | None = None
):
    """NeRSemble benchmark FLAME tracking npz: shape (1,300), expression (T,100), jaw, neck
    (T,3), eyes (T,6), rotation (T,3, Euler XYZ), rotation_matrices (T,3,3), translation (T,3),
    scale, frames (T,). FLAME is evaluated without global rotation/translation; the head is
    then placed by x_world = scale * R x + translation (the benchmark's model-to-world)."""
    path = os.fspath(path)
    d = _npz(path)
    if "expression" not in d:
        raise DataError(f"{path}: not a NeRSemble FLAME tracking file (no 'expression' key; has {sorted(d)})")
    if d["expression"].ndim not in (1, 2):
        raise DataError(f"{path}: 'expression' must be [T,E] (or [E], one frame), got {d['expression'].shape}")
    if d["expression"].ndim == 1:
        d["expression"] = d["expression"][None]
    T = d["expression"].shape[0]
    sel = _select(T, frames, path)
    model = _need_model(flame_model, path) if evaluate else None

    def rows(key, width):
        if key not in d:
            return None
        v = np.asarray(d[key], np.float64)
        v = v.reshape(1, -1) if v.ndim <= 1 else v.reshape(v.shape[0], -1)
        if v.shape[1] != width:
            raise DataError(f"{path}: '{key}' must have {width} values per frame, got shape {d[key].shape}")
        if v.shape[0] not in (1, T):
            raise DataError(f"{path}: '{key}' has {v.shape[0]} rows, expected 1 or {T}")
        return v[sel] if v.shape[0] == T else np.broadcast_to(v, (len(sel), width))

    params = {
        "shape": np.asarray(d["shape"]).reshape(-1, np.asarray(d["shape"]).shape[-1])[:1] if "shape" in d else None,
        "expr": rows("expression", d["expression"].shape[-1]),
        "jaw_pose": rows("jaw", 3),
        "neck_pose": rows("neck", 3),
        "eyes_pose": rows("eyes", 6),
    }
    params = {k: v for k, v in params.items() if v is not None}
    if "rotation_matrices" in d:
        R = np.asarray(d["rotation_matrices"], np.float64).reshape(-1, 3, 3)
        if R.shape[0] != T:
            raise DataError(f"{path}: rotation_matrices has {R.shape[0]} frames, expression {T}")
        R = R[sel]
    elif "rotation" in d:
        R = _euler_xyz(rows("rotation", 3))
    else:
        R = np.broadcast_to(np.eye(3), (len(sel), 3, 3))
    t = rows("translation", 3)
    t = np.zeros((len(sel), 3)) if t is None else t
    scale = 1.0
    if "scale" in d:
        sv = np.asarray(d["scale"], np.float64).reshape(-1)
        if sv.size < 1:
            raise DataError(f"{path}: 'scale' is empty")
        if np.all(np.isfinite(sv)) and np.any(sv != sv[0]):  # non-finite: the placement check below
            raise DataError(f"{path}: 'scale' must be one value for the sequence, got {sv.size} values that differ")
        scale = float(sv[0]) if np.all(np.isfinite(sv)) else float("nan")
    # The placement is checked here, not only through the evaluated vertices: a FLAME rig keeps
    # it as keyframes and would carry NaN (or float32 overflow) into Blender unseen.
    for key, v in (("rotation", R), ("translation", t), ("scale", np.float64(scale))):
        if not (np.all(np.isfinite(v)) and np.abs(v).max(initial=0.0) <= 1e30):
            raise DataError(f"{path}: '{key}' placement values must be finite numbers within ±1e30")
    if not scale > 0:
        raise DataError(f"{path}: 'scale' must be positive (it sizes the head in the world), got {scale}")
    # A rotation, not any matrix: the rig keeps R as a bone's rotation and would part from the
    # mesh (which applies the matrix as it is) on a sheared or mirrored one.
    off = np.abs(np.einsum("tba,tbc->tac", R, R) - np.eye(3)).max(initial=0.0)
    if off > 1e-4 or (len(R) and np.linalg.det(R).min() <= 0):
        raise DataError(
            f"{path}: 'rotation_matrices' must be rotations (orthonormal, determinant +1); "
            f"worst |R^T R - I| entry {off:.2g}"
        )
    ids = _ids_from(d.get("frames"), T, path, "frames")[sel]
    total = 1 + len(sel) if evaluate else 1  # the file, then each frame evaluated
    if progress is not None:
        progress(1, total)
    if not evaluate:
        return FlameTrack(dict(params, rotation_matrices=R, translation=t, scale=scale), ids, path)
    evaluated = None if progress is None else (lambda done, _: progress(1 + done, total))
    local = (
        _evaluate_flame(params, model, path, evaluated).astype(np.float64)
        if len(sel)
        else np.zeros((0, model.n_vertices, 3))
    )
    verts = scale * np.einsum("tab,tvb->tva", R, local) + t[:, None, :]
    params.update(rotation_matrices=R, translation=t, scale=scale)
    return MeshSequence(model.faces, verts, ids, params, path)


def read_mesh_npz(path, frames=None, *, progress: Callable[[int, int], None] | None = None) -> MeshSequence:
    """Mesh npz: ``vertices`` [T,V,3] (or [V,3], one frame), ``faces`` [F,3], optional ``frame_ids``."""
    path = os.fspath(path)
    d = _npz(path)
    for key in ("vertices", "faces"):
        if key not in d:
            raise DataError(f"{path}: mesh npz needs '{key}' (has {sorted(d)})")
    v = d["vertices"]
    v = v[None] if v.ndim == 2 else v
    if v.ndim != 3:
        raise DataError(f"{path}: 'vertices' must be [T,V,3] or [V,3], got {d['vertices'].shape}")
    sel = _select(v.shape[0], frames, path)
    key = "frame_ids" if "frame_ids" in d else "frames"
    ids = _ids_from(d.get(key), v.shape[0], path, key)[sel]
    seq = MeshSequence(d["faces"], _check_vertices(v[sel], path), ids, None, path)
    if progress is not None:
        progress(1, 1)
    return seq


def _load_mesh_file(path: str, reuse: dict | None = None):
    from .mesh_io import read_mesh  # numpy readers: no trimesh inside Blender

    if not os.path.isfile(path):
        raise MissingFileError(f"{path}: file not found")
    try:
        return read_mesh(path, reuse)
    except (ValueError, OSError) as exc:
        msg = str(exc)
        raise DataError(msg if path in msg else f"{path}: cannot read mesh ({msg})") from exc


def read_mesh_folder(path, frames=None, *, progress: Callable[[int, int], None] | None = None) -> MeshSequence:
    """A folder of per-frame OBJ/PLY meshes with identical topology, in natural name order.
    Faces come from the first frame read; only the asked files are opened."""
    path = os.fspath(path)
    files = sorted((f for f in os.listdir(path) if f.lower().endswith(_MESH_EXTS)), key=natural_key)
    if not files:
        raise DataError(f"{path}: no .obj or .ply files")
    sel = _select(len(files), frames, path)
    verts, faces = [], None
    reuse = {}  # OBJ frames with the first one's face lines are not parsed again
    for j, i in enumerate(sel.tolist()):  # one file per asked frame
        fp = os.path.join(path, files[i])
        v, f = _load_mesh_file(fp, reuse)
        if faces is None:
            faces = f
        elif v.shape[0] != verts[0].shape[0]:
            raise DataError(f"{fp}: {v.shape[0]} vertices, but {files[sel[0]]} has {verts[0].shape[0]}")
        elif f.shape != faces.shape or not np.array_equal(f, faces):
            raise DataError(f"{fp}: faces differ from {files[sel[0]]}: frames must share one topology")
        verts.append(_check_vertices(v, fp))
        if progress is not None:
            progress(j + 1, len(sel))
    if not verts:
        v0, faces = _load_mesh_file(os.path.join(path, files[0]))
        verts_arr = np.zeros((0, v0.shape[0], 3), np.float32)
    else:
        verts_arr = np.stack(verts)
    ids = _ids_from([files[i] for i in sel.tolist()], len(sel))
    return MeshSequence(faces, verts_arr, ids, None, path)


def _read_mesh_npz_folder(path: str, files: list, frames, progress=None) -> MeshSequence:
    """A folder of mesh npz files, one frame each ([V,3] or [1,V,3] vertices), in name order."""
    sel = _select(len(files), frames, path)
    parts = []
    for j, i in enumerate(sel.tolist()):  # one file per frame
        parts.append(read_mesh_npz(os.path.join(path, files[i])))
        if progress is not None:
            progress(j + 1, len(sel))
    if not parts:
        first = read_mesh_npz(os.path.join(path, files[0]))
        return MeshSequence(first.faces, first.vertices[:0], np.zeros(0, np.int64), None, path)
    for i, p in zip(sel.tolist(), parts):
        if p.n_frames != 1:
            raise DataError(
                f"{os.path.join(path, files[i])}: holds {p.n_frames} frames; a folder of mesh npz "
                "files needs one frame per file (or import that file alone)"
            )
        if p.faces.shape != parts[0].faces.shape or not np.array_equal(p.faces, parts[0].faces):
            raise DataError(
                f"{os.path.join(path, files[i])}: faces differ from {files[sel[0]]}: frames must share one topology"
            )
    verts = np.concatenate([p.vertices for p in parts])
    return MeshSequence(parts[0].faces, verts, _ids_from([files[i] for i in sel.tolist()], len(sel)), None, path)


def read_sequence(
    path, frames=None, flame_model=None, *, progress: Callable[[int, int], None] | None = None
) -> MeshSequence:
    """Read any supported sequence format, detected from the path and the keys it holds.

    ``frames``: positions (0-based, in file/sequence order) to read; None reads all.
    ``flame_model``: path to the user's FLAME model or a FlameModel (FLAME formats only).
    ``progress``: called with (done, total) as the reading goes (the module's docstring).
    """
    return _read(path, frames, flame_model, True, progress)


def read_flame_track(path, frames=None, *, progress: Callable[[int, int], None] | None = None) -> FlameTrack:
    """The FLAME parameters of a VHAP, GaussianAvatars (flame_param folder) or NeRSemble
    tracking file, unevaluated; a clear error for mesh sequences and datasets."""
    return _read(path, frames, None, False, progress)


def _not_flame(path):
    raise DataError(
        f"{path}: holds meshes, not FLAME parameters; a rig needs a VHAP, GaussianAvatars "
        "flame_param or NeRSemble tracking file"
    )


def _read(path, frames, flame_model, evaluate, progress=None):
    path = os.fspath(path)
    if not os.path.exists(path):
        raise MissingFileError(f"{path}: file or folder not found")
    if os.path.isdir(path):
        names = os.listdir(path)
        for js in ("transforms.json", "transforms_train.json", "transforms_val.json", "transforms_test.json"):
            if js in names:  # a dataset root: its tracked geometry over the split's timesteps
                if not evaluate:
                    raise DataError(
                        f"{path}: a dataset folder; for FLAME parameters point to its flame_param "
                        "folder or a tracked-parameter npz"
                    )
                split = None if js == "transforms.json" else js[len("transforms_") : -len(".json")]
                from .dataset import Dataset  # dataset.py builds on this module's readers

                return Dataset(path, split, flame_model=flame_model).sequence(frames, progress=progress)
        npz = sorted((n for n in names if n.endswith(".npz")), key=natural_key)
        if (
            npz
            and not os.path.isdir(os.path.join(path, "flame_param"))
            and "vertices" in _npz(os.path.join(path, npz[0]))
        ):
            if not evaluate:
                _not_flame(path)
            return _read_mesh_npz_folder(path, npz, frames, progress)
        if os.path.isdir(os.path.join(path, "flame_param")) or npz:
            return read_flame_param_folder(path, frames, flame_model, evaluate, progress=progress)
        if any(n.lower().endswith(_MESH_EXTS) for n in names):
            if not evaluate:
                _not_flame(path)
            return read_mesh_folder(path, frames, progress=progress)
        raise DataError(f"{path}: folder holds neither flame_param/ or *.npz FLAME parameters nor .obj/.ply frames")
    low = path.lower()
    if not evaluate and low.endswith(_MESH_EXTS):
        _not_flame(path)
    if low.endswith(_MESH_EXTS):
        v, f = _load_mesh_file(path)
        sel = _select(1, frames, path)
        seq = MeshSequence(
            f, _check_vertices(v, path)[None][sel], _ids_from([os.path.basename(path)], 1)[sel], None, path
        )
        if progress is not None:
            progress(1, 1)
        return seq
    if low.endswith(".npz"):
        d = _npz(path)
        if "vertices" in d:
            if not evaluate:
                _not_flame(path)
            return read_mesh_npz(path, frames, progress=progress)
        if "expression" in d and ("rotation_matrices" in d or "jaw" in d):
            return read_nersemble_tracking(path, frames, flame_model, evaluate, progress=progress)
        if _flame_keys(d):
            return _read_flame_stacked(path, d, frames, flame_model, "timestep_id", evaluate, progress)
        raise DataError(
            f"{path}: unrecognised npz (keys {sorted(d)}): expected a mesh npz (vertices, faces), "
            "VHAP/GaussianAvatars FLAME parameters or a NeRSemble FLAME tracking file"
        )
    raise DataError(f"{path}: unsupported sequence format (expected .npz, .obj, .ply or a folder of them)")
