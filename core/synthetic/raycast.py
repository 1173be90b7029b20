"""Cameras around the synthetic head and its ray-cast ground truth (supersampled, shaded).
Reporting tier (numpy, trimesh; embree through `embreex` when installed).
"""

from __future__ import annotations

import numpy as np
import trimesh

from ..geometry.camera import Camera

from .fields import _normalize
from .surface import head_template, vertex_normals
from .texture import albedo

# Aspect ratio of NeRSemble frames (width:height = 550:802).
ASPECT = 550.0 / 802.0
LIGHT_DIR = np.array([0.45, 0.55, 0.75]) / np.linalg.norm([0.45, 0.55, 0.75])
AMBIENT = 0.38
DIFFUSE = 0.72


CAMERA_TARGET = np.array([0.0, -0.055, 0.0])
_ELEVATIONS = (3.0, 12.0, -5.0, 7.0)


def image_size(resolution: int) -> tuple[int, int]:
    """(width, height) for an image ``resolution`` pixels high at NeRSemble's aspect."""
    h = int(resolution)
    return max(1, int(round(h * ASPECT))), h


def held_out_camera(cameras: int) -> int:
    """Index of the novel-view camera: the near-frontal middle one (8 of 16)."""
    return int(cameras) // 2


def make_cameras(
    cameras: int = 16,
    resolution: int = 128,
    distance: float = 1.0,
    spread_deg: float = 65.0,
    frame_height_m: float = 0.42,
) -> list[Camera]:
    """A frontal arc like NeRSemble's: azimuth -spread..spread, alternating elevations.

    ``frame_height_m``: the height of the world slice (at the target) the image spans, so
    the head and neck fill most of the frame at any resolution.
    """
    w, h = image_size(resolution)
    f = h * distance / frame_height_m
    az = np.radians(np.linspace(-spread_deg, spread_deg, cameras)) if cameras > 1 else np.zeros(1)
    out = []
    for k in range(cameras):
        el = np.radians(_ELEVATIONS[k % len(_ELEVATIONS)])
        eye = CAMERA_TARGET + distance * np.array([np.sin(az[k]) * np.cos(el), np.sin(el), np.cos(az[k]) * np.cos(el)])
        out.append(Camera.look_at(eye, CAMERA_TARGET, (0.0, 1.0, 0.0), f, f, w / 2.0, h / 2.0, w, h))
    return out


def make_intersector(mesh: trimesh.Trimesh):
    """Embree (embreex) when installed, else trimesh's rtree intersector (much slower)."""
    try:
        from trimesh.ray import ray_pyembree

        if getattr(ray_pyembree, "_embree_version", None) is not None or _has_embreex():
            return ray_pyembree.RayMeshIntersector(mesh), "embree"
    except Exception:  # no embreex, or an incompatible build
        pass
    from trimesh.ray import ray_triangle

    return ray_triangle.RayMeshIntersector(mesh), "rtree"


def _has_embreex():
    try:
        import embreex  # noqa: F401

        return True
    except ImportError:
        return False


def camera_rays(camera: Camera, supersample: int = 1):
    """World-space ray origins and unit directions [H*s, W*s, 3] through sub-pixel centres.

    With s samples per axis the samples of pixel (i, j) sit at i + (a + 0.5) / s, so s = 1 is
    the pixel centre (i + 0.5, j + 0.5) and a box filter over the s x s block anti-aliases.
    """
    s = int(supersample)
    offs = (np.arange(s) + 0.5) / s
    xs = (np.arange(camera.width)[:, None] + offs[None, :]).ravel()
    ys = (np.arange(camera.height)[:, None] + offs[None, :]).ravel()
    X, Y = np.meshgrid(xs, ys)
    d_cam = np.stack([(X - camera.cx) / camera.fx, (Y - camera.cy) / camera.fy, np.ones_like(X)], -1)
    dirs = _normalize(d_cam @ camera.R)  # camera -> world: R^T d, as rows
    origins = np.broadcast_to(camera.center, dirs.shape)
    return origins, dirs


def _hit_barycentrics(origins, dirs, tri):
    """Möller-Trumbore for ray/triangle pairs known to hit: barycentrics [N,3] on the simplex."""
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    pvec = np.cross(dirs, e2)
    det = np.einsum("nd,nd->n", e1, pvec)
    inv = 1.0 / np.where(np.abs(det) > 1e-18, det, 1e-18)
    tvec = origins - tri[:, 0]
    u = np.einsum("nd,nd->n", tvec, pvec) * inv
    qvec = np.cross(tvec, e1)
    v = np.einsum("nd,nd->n", dirs, qvec) * inv
    b = np.clip(np.stack([1.0 - u - v, u, v], 1), 0.0, None)  # embree may hit a hair outside
    return b / np.maximum(b.sum(1, keepdims=True), 1e-12)


def shade(albedo_rgb, normals, view_dirs):
    """Lambert + ambient under the fixed light; normals face the viewer."""
    flip = np.einsum("nd,nd->n", normals, view_dirs) > 0
    n = np.where(flip[:, None], -normals, normals)
    lam = np.clip(n @ LIGHT_DIR, 0.0, None)
    return np.clip(albedo_rgb * (AMBIENT + DIFFUSE * lam)[:, None], 0.0, 1.0)


def render_views(
    vertices,
    faces,
    cameras,
    canonical=None,
    supersample: int = 2,
    background=(1.0, 1.0, 1.0),
    stats: dict | None = None,
    albedo_fn=None,
):
    """Ray-cast ground truth of a posed mesh from each camera.

    vertices [V,3] posed; canonical [V,3] where the texture is evaluated (default: the head
    template when V matches, else ``vertices`` itself). Returns images float32 [C,H,W,3]
    composited over ``background`` and masks float32 [C,H,W] (coverage of the s x s
    samples). ``stats`` (a dict) collects ray counts and the intersector used. ``albedo_fn``:
    reflectance of canonical points (default ``albedo``; the paper-scale head's is ``paper_albedo``).
    """
    albedo_fn = albedo if albedo_fn is None else albedo_fn
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    if canonical is None:
        tv, tf = head_template()
        canonical = tv if tv.shape == vertices.shape else vertices
    canonical = np.asarray(canonical, np.float64)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    intersector, kind = make_intersector(mesh)
    vn = vertex_normals(vertices, faces)
    bg = np.asarray(background, np.float64)
    s = int(supersample)
    images, masks = [], []
    for cam in cameras:
        origins, dirs = camera_rays(cam, s)
        o = origins.reshape(-1, 3)
        d = dirs.reshape(-1, 3)
        tri = np.asarray(intersector.intersects_first(o, d), np.int64)
        hit = np.nonzero(tri >= 0)[0]
        color = np.broadcast_to(bg, d.shape).copy()
        if len(hit):
            ft = faces[tri[hit]]
            b = _hit_barycentrics(o[hit], d[hit], vertices[ft])
            p_can = np.einsum("nk,nkd->nd", b, canonical[ft])
            n = _normalize(np.einsum("nk,nkd->nd", b, vn[ft]))
            color[hit] = shade(albedo_fn(p_can), n, d[hit])
        cov = np.zeros(len(d))
        cov[hit] = 1.0
        H, W = cam.height, cam.width
        images.append(color.reshape(H, s, W, s, 3).mean(axis=(1, 3)).astype(np.float32))
        masks.append(cov.reshape(H, s, W, s).mean(axis=(1, 3)).astype(np.float32))
        if stats is not None:
            stats["rays"] = stats.get("rays", 0) + len(d)
            stats["hits"] = stats.get("hits", 0) + len(hit)
            stats["intersector"] = kind
    return np.stack(images), np.stack(masks)
