"""Arrays the Blender preview needs, computed here so blender_addon/ holds no maths.

numpy only (runs inside Blender's own Python). Everything returns flat, C-contiguous float32
or int32 arrays shaped for ``foreach_set``:
- ``splat_evaluator``: core's GaussianEvaluator sized for foreach_set (the frame-change
  handler calls it every frame);
- ``Budget``: Gaussians / bytes / level reached for a budget percent, taken from the
  stream's own ``count_for_percent`` when the avatar came from a stream;
- depth colours and legend for the per-face subdivision depth display;
- conversions between ``core.geometry.camera.Camera`` and Blender camera settings;
- ``render_job``: the out-of-Blender side of "Render splats" (needs core.render / numba).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ..avatar import binding
from ..avatar.avatar import Avatar, sh_to_rgb, sigmoid

# Blender is Z-up; FLAME/dataset space is Y-up (head looks to +z). Rotating +90° about x
# maps dataset y to Blender z, so the head stands up and looks to Blender -y (the front view).
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


# -- avatars and budgets -------------------------------------------------------------------
def _stream_module():
    try:
        from ..stream import format as stream
    except ImportError:
        return None
    return stream


@dataclass
class Budget:
    """How much of an avatar a budget percent includes.

    ``info`` is the stream's header object when the avatar was read from a stream (its
    ``count_for_percent`` is the single definition of a percent); plain avatar files fall
    back to the same fraction of Gaussians (there is no byte layout to follow).
    """

    total: int
    levels: np.ndarray  # int8 [N], stream order
    file_bytes: int
    info: object | None = None

    def count_for_percent(self, percent: float) -> int:
        p = float(min(max(percent, 0.0), 100.0))
        if self.info is not None and hasattr(self.info, "count_for_percent"):
            return int(min(max(int(self.info.count_for_percent(p)), 0), self.total))
        return int(min(self.total, math.floor(self.total * p / 100.0 + 0.5)))

    def bytes_for_count(self, count: int) -> int:
        info = self.info
        for name in ("bytes_for_count", "size_for_count"):
            if info is not None and hasattr(info, name):
                return int(getattr(info, name)(int(count)))
        return int(round(self.file_bytes * count / max(self.total, 1)))

    def level_reached(self, count: int) -> int:
        return int(self.levels[count - 1]) if count > 0 else -1

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
    """An avatar in stream order from a stream file (.pavs, recognised by its magic) or an
    avatar .npz, and its budget. Avatar .npz files are taken to be in stream order already
    (a face's rank is its index). A stream cut anywhere (even inside the template level)
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

        avatar = read_stream(path, template_faces=tmpl)
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
    budget = Budget(avatar.num_gaussians, avatar.forest.level.copy(), os.path.getsize(path), info)
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


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values (what the avatar learned from PNG images) to linear light."""
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def preview_order(avatar: Avatar) -> np.ndarray:
    """The stream rank of each preview point, point by point: Gaussians grouped by root face,
    the layout the per-frame evaluator fills without scattering (2.6x faster per frame than
    stream order at 170k Gaussians). The budget still selects by rank, so order is free."""
    return binding.root_grouped(avatar.forest)


def static_attributes(avatar: Avatar, order=None) -> dict:
    """Per-Gaussian values that do not change with the frame: activated opacity, RGBA
    colour (linear, as Blender's colour attributes are), level and rank (stream position),
    for the Gaussians ``order`` (default: all, in stream order)."""
    sel = np.arange(avatar.num_gaussians) if order is None else np.asarray(order, np.int64)
    rgba = np.ones((len(sel), 4), np.float32)
    rgba[:, :3] = srgb_to_linear(sh_to_rgb(avatar.f_dc[sel]))
    return {
        "opacity": np.ascontiguousarray(sigmoid(avatar.opacity_logit[sel]), np.float32),
        "color": rgba.ravel(),
        "level": avatar.forest.level[sel].astype(np.int32),
        "rank": sel.astype(np.int32),
    }


# -- per-frame evaluation ------------------------------------------------------------------
def splat_evaluator(avatar: Avatar, count: int | None = None, weights=None, order=None) -> binding.GaussianEvaluator:
    """Per-frame world Gaussians of the first ``count`` faces (stream order), written at their
    points' rows of the layout ``order`` (default: stream order). Outputs are sized for the
    whole avatar so the frame handler can foreach_set full attributes without copies."""
    total = avatar.num_gaussians
    n = total if count is None else int(min(max(count, 0), total))
    order = np.arange(total) if order is None else np.asarray(order, np.int64)
    rows = None
    if n < total:
        rows = np.flatnonzero(order < n)
        order = order[rows]
    # weights: forest.weights() computed once by the caller; evaluators are rebuilt when the
    # budget changes and the forest walk is the costly part of building one.
    return avatar.evaluator(ids=order, weights=weights, capacity=total, rows=rows)


# -- subdivision depth display -------------------------------------------------------------
# A perceptual ramp (dark blue → teal → yellow), sampled at depth / max(max_depth, 1).
_RAMP = np.array(
    [
        [0.050, 0.030, 0.280],
        [0.150, 0.300, 0.620],
        [0.100, 0.600, 0.600],
        [0.450, 0.800, 0.300],
        [0.990, 0.900, 0.150],
    ],
    np.float32,
)


NOT_ARRIVED = -1  # depth of a face none of whose Gaussians has arrived
# Neutral light grey: off the ramp (no ramp colour is grey) and unlike the dark depth 0.
NOT_ARRIVED_COLOR = np.array([0.55, 0.55, 0.55, 1.0], np.float32)


def depth_colors(depth: np.ndarray, max_depth: int | None = None) -> np.ndarray:
    """Linear RGBA colours [F,4] float32 for integer depths (0 = darkest); NOT_ARRIVED
    (negative) depths get NOT_ARRIVED_COLOR."""
    depth = np.asarray(depth, np.float32)
    top = float(max(depth.max() if depth.size else 0, 1) if max_depth is None else max(max_depth, 1))
    x = np.clip(depth / top, 0, 1) * (len(_RAMP) - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), len(_RAMP) - 2)
    w = (x - i0)[:, None]
    rgb = _RAMP[i0] * (1 - w) + _RAMP[i0 + 1] * w
    out = np.concatenate([rgb, np.ones((len(rgb), 1), np.float32)], axis=1).astype(np.float32)
    out[depth < 0] = NOT_ARRIVED_COLOR
    return out


def per_corner(values: np.ndarray, loop_totals: np.ndarray) -> np.ndarray:
    """Repeat per-face rows for each of the face's corners (Blender's corner domain)."""
    return np.repeat(np.asarray(values), np.asarray(loop_totals, np.int64), axis=0)


def depth_legend(depth_per_face: np.ndarray, max_depth: int | None = None) -> list[tuple[int, int, tuple]]:
    """(depth, number of template faces, RGB) for every depth 0..max, led by
    (NOT_ARRIVED, count, its colour) when some faces have no Gaussian yet."""
    depth = np.asarray(depth_per_face, np.int64)
    top = int(max(depth.max(), 0)) if depth.size else 0
    top = top if max_depth is None else max(int(max_depth), 0)
    hist = np.bincount(depth[depth >= 0], minlength=top + 1)
    cols = depth_colors(np.arange(top + 1), top)
    out = [(d, int(hist[d]), tuple(float(c) for c in cols[d, :3])) for d in range(top + 1)]
    missing = int(np.count_nonzero(depth < 0))
    if missing:
        out.insert(0, (NOT_ARRIVED, missing, tuple(float(c) for c in NOT_ARRIVED_COLOR[:3])))
    return out


def depth_per_face(forest, num_template_faces: int, count: int | None = None) -> np.ndarray:
    """Deepest level among the first ``count`` Gaussians (all if None) under each of the
    mesh's ``num_template_faces`` faces, int32; NOT_ARRIVED where none of them lies under
    the face (a stream cut inside the template level, or a budget below it)."""
    n = forest.num_faces if count is None else int(min(max(count, 0), forest.num_faces))
    depth = np.full(int(num_template_faces), NOT_ARRIVED, np.int32)
    # A face's root is a row of the root table: coarse triangles first (they sit above the
    # template and cover no single template face), then template faces in any order.
    coarse = int(getattr(forest, "num_coarse", 0))
    ref = getattr(forest, "root_ref", None)
    root = forest.root[:n] if ref is None else np.asarray(ref)[forest.root[:n]] - coarse
    keep = root >= 0
    if keep.any() and int(root[keep].max()) >= len(depth):
        raise ValueError(f"the avatar has {len(forest.template_faces)} template faces, the mesh {len(depth)}")
    below = forest.level[:n].astype(np.int32) - int(getattr(forest, "num_coarse_levels", 0))
    np.maximum.at(depth, root[keep], below[keep])
    return depth


# -- cameras -------------------------------------------------------------------------------
def blender_camera(camera, z_up: bool = True, sensor_width: float = 36.0) -> dict:
    """Blender camera settings reproducing a pinhole ``Camera`` (OpenCV intrinsics).

    Blender cameras look down -z with +y up (the OpenGL convention the dataset's c2w uses).
    Focal length and shifts are expressed against the larger image side (sensor_fit AUTO
    semantics); non-square pixels (fx ≠ fy) become a pixel aspect ratio.
    """
    w, h = camera.width, camera.height
    big = float(max(w, h))
    c2w = camera.c2w_opengl()
    if z_up:
        c2w = Y_UP_TO_Z_UP @ c2w
    # Blender scales x by pixel_aspect_x / pixel_aspect_y; keep fx as the reference.
    aspect_y = camera.fx / camera.fy
    f_big = camera.fx if w >= h else camera.fy * aspect_y
    return {
        "matrix_world": c2w,
        "lens": f_big / big * sensor_width,
        "sensor_width": sensor_width,
        "sensor_fit": "AUTO",
        "shift_x": (w / 2.0 - camera.cx) / big,
        "shift_y": (camera.cy - h / 2.0) / big,
        "resolution": (int(w), int(h)),
        "pixel_aspect": (1.0, float(aspect_y)),
    }


def camera_from_blender(matrix_world, lens, sensor_width, shift_x, shift_y, width, height, z_up: bool = True):
    """The core ``Camera`` seeing what a Blender camera (sensor_fit AUTO, square pixels) sees."""
    from ..geometry.camera import Camera

    c2w = np.asarray(matrix_world, np.float64).reshape(4, 4)
    if z_up:
        c2w = np.linalg.inv(Y_UP_TO_Z_UP) @ c2w
    # Remove object scale so R is a rotation.
    c2w = c2w.copy()
    c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0, keepdims=True)
    big = float(max(width, height))
    f = lens / sensor_width * big
    cx = width / 2.0 - shift_x * big
    cy = height / 2.0 + shift_y * big
    return Camera.from_c2w_opengl(c2w, f, f, cx, cy, int(width), int(height))


# -- render job (runs in the configured Python, outside Blender) ---------------------------
def render_job(job_path: str, out_path: str) -> None:
    """Render the Gaussians saved by the add-on in ``job_path`` (npz) to ``out_path`` (.npy
    RGBA float32 [H,W,4]) with the core rasteriser."""
    from ..geometry.camera import Camera
    from ..render.rasterize import render_numpy

    with np.load(job_path, allow_pickle=False) as d:
        cam = Camera(d["R"], d["t"], *[float(x) for x in d["intr"]], int(d["size"][0]), int(d["size"][1]))
        # 3DGS clamps SH colours at 0 (PLY splats keep their exact, possibly negative, DC for export).
        out = render_numpy(
            d["means"], d["quats"], d["scales"], d["opacities"], np.maximum(d["colors"], 0), cam, d["background"]
        )
    image, alpha = out[0], out[1]
    rgba = np.concatenate([np.asarray(image, np.float32), np.asarray(alpha, np.float32)[..., None]], -1)
    np.save(out_path, rgba)


def transform_gaussians(matrix, means, quats, scales):
    """Gaussians carried by an object transform (rotation, uniform scale, translation):
    Blender object space → world space for export and rendering."""
    M = np.asarray(matrix, np.float64).reshape(4, 4)
    A = M[:3, :3]
    s = float(np.cbrt(abs(np.linalg.det(A)))) or 1.0
    Rm = A / s
    q_obj = binding.rotmat_to_quat(Rm[None])[0]
    means_w = (np.asarray(means, np.float64) @ A.T + M[:3, 3]).astype(np.float32)
    quats_w = binding.quat_multiply(q_obj[None], np.asarray(quats, np.float64)).astype(np.float32)
    return means_w, quats_w, (np.asarray(scales, np.float32) * s).astype(np.float32)
