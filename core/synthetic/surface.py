"""The synthetic head's surface: an implicit head (smooth union of ellipsoids and cylinders), meshed
by pushing a warped icosphere out along rays from an interior point; the canonical landmarks
shared by the shape, the texture and the rig; the paper-scale head's displaced surface.
Reporting tier (numpy, trimesh).
"""

from __future__ import annotations

import functools

import numpy as np
import trimesh

from .fields import _edge, _normalize, _sd_ellipsoid, _sd_vertical_cylinder, _smax, _smin, _smoothstep, _value_noise

# Canonical landmarks shared by the shape, the texture and the rig (metres, +y up, face +z).
EYE_CENTERS = ((0.032, 0.018), (-0.032, 0.018))  # (x, y) of each eye
EYE_HALF_WIDTH = 0.0135
EYE_HALF_OPENING = 0.0058
MOUTH_Y = -0.0625  # height of the lip contact line
MOUTH_HALF_WIDTH = 0.024
NECK_AXIS_Z = -0.012  # the neck cylinder's axis sits slightly behind the head centre

# The paper-scale head (make_dataset(detail="paper")): octahedron subdivisions of the tracked
# template (8 * 4^5 = 8192 faces) and further subdivisions of the imaged surface (16x the faces).
PAPER_TEMPLATE_LEVELS = 5
PAPER_SURFACE_LEVELS = 2

# Radial shape search: rays from this interior point cross the surface once.
_SHAPE_CENTER = np.array([0.0, -0.06, 0.0])
_SHAPE_RMAX = 0.42


def head_sdf(p):
    """Signed distance (approximate, metres) of the canonical head: negative inside."""
    p = np.asarray(p, np.float64)
    d = _sd_ellipsoid(p, (0.0, 0.015, -0.012), (0.080, 0.108, 0.098))  # cranium
    d = _smin(d, _sd_ellipsoid(p, (0.0, -0.045, 0.022), (0.060, 0.070, 0.074)), 0.02)  # face mass
    d = _smin(d, _sd_ellipsoid(p, (0.0, -0.078, 0.030), (0.048, 0.045, 0.060)), 0.02)  # jaw
    d = _smin(d, _sd_ellipsoid(p, (0.0, -0.101, 0.066), (0.021, 0.017, 0.020)), 0.012)  # chin
    for sx in (1.0, -1.0):
        d = _smin(d, _sd_ellipsoid(p, (sx * 0.040, -0.004, 0.055), (0.022, 0.016, 0.027)), 0.012)  # cheekbone
        d = _smin(d, _sd_ellipsoid(p, (sx * 0.079, 0.004, -0.010), (0.011, 0.029, 0.019)), 0.006)  # ear
    d = _smin(d, _sd_ellipsoid(p, (0.0, 0.040, 0.070), (0.066, 0.016, 0.022)), 0.02)  # brow ridge
    # nose: bridge, tip, wings
    d = _smin(d, _sd_ellipsoid(p, (0.0, 0.000, 0.090), (0.0095, 0.032, 0.016)), 0.008)
    d = _smin(d, _sd_ellipsoid(p, (0.0, -0.027, 0.104), (0.011, 0.010, 0.011)), 0.008)
    for sx in (1.0, -1.0):
        d = _smin(d, _sd_ellipsoid(p, (sx * 0.011, -0.031, 0.094), (0.0085, 0.0075, 0.008)), 0.005)
    # eye sockets carved out, eyeballs put back
    for ex, ey in EYE_CENTERS:
        d = _smax(d, -_sd_ellipsoid(p, (ex, ey, 0.091), (0.019, 0.012, 0.013)), 0.01)
        d = _smin(d, _sd_ellipsoid(p, (ex, ey, 0.0725), (0.0135, 0.0125, 0.0125)), 0.002)
    # lips meet at MOUTH_Y, leaving a crease
    d = _smin(d, _sd_ellipsoid(p, (0.0, -0.0560, 0.0895), (0.024, 0.0075, 0.011)), 0.003)
    d = _smin(d, _sd_ellipsoid(p, (0.0, -0.0695, 0.0875), (0.022, 0.0085, 0.011)), 0.003)
    # neck flaring gently into a shirt collar; the flare stays shallower than the view
    # from _SHAPE_CENTER, so every ray from there still crosses the surface once
    flare = 0.009 * _smoothstep(-0.19, -0.235, p[..., 1])
    d = _smin(d, _sd_vertical_cylinder(p, NECK_AXIS_Z, 0.050 + flare, 0.054 + flare, -0.25, 0.0, 0.005), 0.02)
    return d


def _radial_distance(dirs, steps=90, refine=20):
    """Distance along each unit direction from _SHAPE_CENTER to the outermost surface crossing."""
    dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
    r = np.linspace(_SHAPE_RMAX, 0.0, steps)
    inside = np.empty((len(dirs), steps), bool)
    for k0 in range(0, len(dirs), 4096):  # bounded memory
        d = dirs[k0 : k0 + 4096]
        pts = _SHAPE_CENTER + d[:, None, :] * r[None, :, None]
        inside[k0 : k0 + 4096] = head_sdf(pts) < 0
    first = np.argmax(inside, axis=1)  # first step (from outside) that is inside
    if not np.all(inside[np.arange(len(dirs)), first]):
        raise RuntimeError("synthetic head: a ray from the centre never enters the shape")
    hi = r[np.maximum(first - 1, 0)]  # outside
    lo = r[first]  # inside
    for _ in range(refine):
        mid = 0.5 * (hi + lo)
        ins = head_sdf(_SHAPE_CENTER + dirs * mid[:, None]) < 0
        lo = np.where(ins, mid, lo)
        hi = np.where(ins, hi, mid)
    return 0.5 * (hi + lo)


def _spherical(dirs):
    """Polar angle from +y and azimuth about y (0 toward +z, +pi/2 toward +x)."""
    theta = np.arccos(np.clip(dirs[:, 1], -1.0, 1.0))
    phi = np.arctan2(dirs[:, 0], dirs[:, 2])
    return theta, phi


def _from_spherical(theta, phi):
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), s * np.cos(phi)], -1)


def _meridian_interp(theta, phi, xp, fp):
    """Per-meridian piecewise-linear map theta -> value, blended linearly in azimuth.

    xp, fp: [n_phi + 1, n] monotone tables on the azimuth grid -pi..pi. Blending two
    increasing maps gives an increasing map, so remapped meshes stay embedded.
    """
    n_phi = xp.shape[0] - 1
    fj = (phi + np.pi) / (2 * np.pi) * n_phi
    j0 = np.clip(np.floor(fj).astype(int), 0, n_phi - 1)
    a = fj - j0
    v0 = np.empty_like(theta)
    v1 = np.empty_like(theta)
    for j in range(n_phi + 1):  # a few dozen meridians, not per vertex
        s0 = j0 == j
        s1 = (j0 + 1) == j
        if s0.any():
            v0[s0] = np.interp(theta[s0], xp[j], fp[j])
        if s1.any():
            v1[s1] = np.interp(theta[s1], xp[j], fp[j])
    return (1 - a) * v0 + a * v1


@functools.lru_cache(maxsize=1)
def _arclength_tables(n_phi=36):
    """Polar angle (geometric, from the shape centre) vs normalised arclength along meridians.

    The radial map stretches the neck (a long surface seen under a small angle from the
    centre); meshing in the arclength parameter instead keeps its triangles from becoming
    slivers, and makes parameter-space distances roughly surface distances.
    """
    # finer toward the bottom, where the neck and the collar step are seen under small angles
    theta_grid = np.concatenate([np.linspace(0.0, 0.75 * np.pi, 110), np.linspace(0.75 * np.pi, np.pi, 150)[1:]])
    phi_grid = np.linspace(-np.pi, np.pi, n_phi + 1)
    T, P = np.meshgrid(theta_grid, phi_grid)  # [n_phi+1, n_theta]
    grid_dirs = _from_spherical(T.ravel(), P.ravel())
    pts = grid_dirs * _radial_distance(grid_dirs, steps=90, refine=14)[:, None]
    pts = pts.reshape(n_phi + 1, len(theta_grid), 3)
    seg = np.linalg.norm(np.diff(pts, axis=1), axis=-1)
    arc = np.concatenate([np.zeros((n_phi + 1, 1)), np.cumsum(seg, axis=1)], axis=1)
    arc = arc / arc[:, -1:] * np.pi
    return np.broadcast_to(theta_grid, arc.shape).copy(), arc


def _geometric_to_parameter(dirs):
    theta, phi = _spherical(dirs)
    geo, par = _arclength_tables()
    return _from_spherical(_meridian_interp(theta, phi, geo, par), phi)


def _parameter_to_geometric(dirs):
    theta, phi = _spherical(dirs)
    geo, par = _arclength_tables()
    return _from_spherical(_meridian_interp(theta, phi, par, geo), phi)


def _contract(dirs, target, strength, sigma):
    """Pull unit vectors toward ``target`` along great circles (denser sampling there).

    Angle d -> d (1 - strength exp(-d^2 / 2 sigma^2)) is strictly increasing for
    strength < 1, so the warp is a bijection of the sphere and keeps the mesh embedded.
    """
    a = _normalize(np.asarray(target, np.float64))
    cosd = np.clip(dirs @ a, -1.0, 1.0)
    d = np.arccos(cosd)
    tangent = dirs - cosd[:, None] * a
    tn = np.linalg.norm(tangent, axis=1)
    ok = tn > 1e-9
    e = np.where(ok[:, None], tangent / np.maximum(tn, 1e-12)[:, None], 0.0)
    d_new = d * (1.0 - strength * np.exp(-d * d / (2 * sigma * sigma)))
    out = np.cos(d_new)[:, None] * a + np.sin(d_new)[:, None] * e
    return np.where(ok[:, None], out, dirs)


def _direction_to(point):
    return _normalize(np.asarray(point, np.float64) - _SHAPE_CENTER)


@functools.lru_cache(maxsize=2)
def _template_cached(subdivisions):
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    dirs = _normalize(np.asarray(sphere.vertices, np.float64))
    faces = np.asarray(sphere.faces, np.int64)

    # Uneven tessellation like FLAME: in the arclength parameter (where angles are roughly
    # surface distances), a broad pull toward the face and strong pulls toward the eyes and
    # the mouth; the scalp and the neck keep what remains (coarse).
    def toward(point):
        return _geometric_to_parameter(_direction_to(point)[None])[0]

    dirs = _contract(dirs, toward((0.0, -0.02, 0.10)), 0.6, 0.9)
    dirs = _contract(dirs, toward((0.0, MOUTH_Y, 0.09)), 0.7, 0.12)
    for ex, ey in EYE_CENTERS:
        dirs = _contract(dirs, toward((ex, ey, 0.085)), 0.62, 0.09)
    dirs = _parameter_to_geometric(dirs)
    r = _radial_distance(dirs)
    verts = _SHAPE_CENTER + dirs * r[:, None]
    return verts.astype(np.float32), faces.astype(np.int32)


def head_template(subdivisions: int = 4):
    """The neutral head: (vertices float32 [V,3] metres, faces int32 [F,3]), outward winding.

    Watertight, 5120 faces at the default subdivision, densest at the eyes and mouth.
    """
    v, f = _template_cached(int(subdivisions))
    return v.copy(), f.copy()


def vertex_normals(vertices, faces):
    """Area-weighted unit vertex normals [V,3]."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        for d in range(3):
            vn[:, d] += np.bincount(f[:, k], weights=fn[:, d], minlength=len(v))
    return _normalize(vn)


# --------------------------------------------------------------------------------------
# the paper-scale head (make_dataset(detail="paper")): a FLAME-sized tracked template with
# FLAME-like uneven density, imaged from a much finer, displaced surface with detail the
# template cannot represent, most of it where the template is coarse
# --------------------------------------------------------------------------------------


def _octahedron():
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.int64)
    return v, f


def _sphere_levels(levels):
    """Octahedron subdivided ``levels`` times on the unit sphere; each subdivision appends its
    midpoints after the existing vertices, so a coarser level's vertices are a prefix of a finer one's."""
    v, f = _octahedron()
    out = [(v, f)]
    for _ in range(levels):
        v, f = trimesh.remesh.subdivide(v, f)
        v = _normalize(v)
        out.append((v, f))
    return out


def _paper_warp(dirs):
    """Uneven tessellation like FLAME's, stronger than the default head's: pulls toward the face,
    the eyes, the mouth and the nose (in the arclength parameter); the scalp, the back of the head
    and the neck keep what remains."""

    def toward(point):
        return _geometric_to_parameter(_direction_to(point)[None])[0]

    # widths well above the base spacing (~0.06 rad), or a pull only moves a face or two
    dirs = _contract(dirs, toward((0.0, -0.02, 0.10)), 0.6, 0.9)
    dirs = _contract(dirs, toward((0.0, MOUTH_Y, 0.09)), 0.75, 0.2)
    dirs = _contract(dirs, toward((0.0, -0.025, 0.105)), 0.6, 0.15)  # nose
    for ex, ey in EYE_CENTERS:
        dirs = _contract(dirs, toward((ex, ey, 0.085)), 0.8, 0.18)
    return _parameter_to_geometric(dirs)


def _hairline_mask(p):
    """(indices of points near or above the hairline, their hair coverage 0..1, polar angle
    from the crown, azimuth): albedo's hairline, with ears left bare."""
    hc = p - np.array([0.0, 0.015, -0.012])
    phi = np.arctan2(hc[:, 0], hc[:, 2])
    aphi = np.degrees(np.abs(phi))
    hairline = np.interp(
        aphi, [0, 35, 62, 80, 88, 96, 112, 140, 180], [0.074, 0.068, 0.05, 0.03, -0.012, 0.034, 0.03, -0.04, -0.072]
    )
    sel = np.nonzero(p[:, 1] > hairline - 0.01)[0]
    ps, hs, phi = p[sel], hc[sel], phi[sel]
    theta = np.arccos(np.clip(hs[:, 1] / np.maximum(np.linalg.norm(hs, axis=1), 1e-9), -1, 1))
    jag = 0.006 * (_value_noise(np.stack([phi * 40.0, np.zeros(len(sel)), np.zeros(len(sel))], 1), 61) - 0.5)
    mask = _edge(hairline[sel] + jag - ps[:, 1], 0.0008)
    for sx in (1.0, -1.0):
        mask = mask * (1.0 - _edge(_sd_ellipsoid(ps, (sx * 0.079, 0.004, -0.010), (0.013, 0.031, 0.021)), 0.001))
    return sel, mask, theta, phi


def _strands(p, theta, phi, width, length, seed):
    """Value noise stretched along the hair's flow (down from the crown): thin strands."""
    arc = phi * 0.09 * np.sin(np.clip(theta, 0.3, np.pi))
    q = np.stack([arc / width, theta * 0.1 / length, np.full(len(p), float(seed % 7))], 1)
    return _value_noise(q, seed)


def _ear_coords(p, sx):
    """(normalised radius in the ear's side plane, inside-ear weight) for the ear on side sx."""
    c = np.array([sx * 0.079, 0.004, -0.010])
    q = (p - c) / np.array([0.011, 0.029, 0.019])
    r = np.hypot(q[:, 1], q[:, 2])
    side = _smoothstep(0.3, 0.8, q[:, 0] * sx)  # the outer face of the ear
    return r, side * (1.0 - _smoothstep(0.9, 1.05, r))


_BUTTON_Y = (-0.2165, -0.2320, -0.2475)
_NECK_RZ = 0.054  # the neck cylinder's radius along z, for where its front surface is


def _buttons(p):
    """(distance to the nearest shirt button's centre in metres, on-front weight)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    d = np.full(len(p), np.inf)
    for by in _BUTTON_Y:
        d = np.minimum(d, np.hypot(x, y - by))
    return d, _smoothstep(0.02, 0.04, z - NECK_AXIS_Z)


def paper_displacement(points, normals) -> np.ndarray:
    """Displacement (metres, along the outward normal) of the imaged paper-scale surface: hair
    volume with strand ridges and a stepped hairline, ear folds, a raised shirt collar with
    buttons, a recessed mouth interior. None of it is in the tracked template."""
    p = np.asarray(points, np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    d = np.zeros(len(p))
    sel, hair, theta, phi = _hairline_mask(p)
    if len(sel):
        s1 = _strands(p[sel], theta, phi, 0.0016, 0.02, 101)
        s2 = _strands(p[sel], theta, phi, 0.006, 0.04, 103)
        d[sel] += hair * (0.0022 + 0.0009 * (s1 - 0.5) + 0.0012 * (s2 - 0.5))
    for sx in (1.0, -1.0):
        r, w = _ear_coords(p, sx)
        # helix rim, antihelix ridge, the concha's hollow
        folds = (
            0.0016 * np.exp(-(((r - 0.8) / 0.07) ** 2))
            + 0.0011 * np.exp(-(((r - 0.5) / 0.06) ** 2))
            - 0.0022 * (1.0 - _smoothstep(0.2, 0.38, r))
        )
        d += w * folds
    collar = _edge(np.abs(y + 0.2095) - 0.0032, 0.0004)  # a folded collar band stands out
    d += 0.0022 * collar
    bd, front = _buttons(p)
    d += 0.0011 * front * np.sqrt(np.clip(1.0 - (bd / 0.0036) ** 2, 0.0, 1.0))
    sel = np.nonzero((z > 0.04) & (np.abs(y - MOUTH_Y) < 0.006) & (np.abs(x) < 0.03))[0]
    if len(sel):
        gap = _edge(np.abs(y[sel] - MOUTH_Y) - 0.0018, 0.0003) * _edge(np.abs(x[sel]) - 0.021, 0.0008)
        d[sel] -= 0.0025 * gap
    return d


@functools.lru_cache(maxsize=1)
def _paper_cached(template_levels, surface_levels):
    levels = _sphere_levels(template_levels + surface_levels)
    tdirs, tf = levels[template_levels]
    sdirs, sf = levels[-1]
    dirs = _paper_warp(sdirs)
    verts = _SHAPE_CENTER + dirs * _radial_distance(dirs, steps=60, refine=18)[:, None]
    fine = verts.copy()
    n = vertex_normals(verts, sf)
    fine += n * paper_displacement(verts, n)[:, None]
    tv = verts[: len(tdirs)]
    return (tv.astype(np.float32), tf.astype(np.int32), fine.astype(np.float32), sf.astype(np.int32))


def paper_head(template_levels: int = PAPER_TEMPLATE_LEVELS, surface_levels: int = PAPER_SURFACE_LEVELS):
    """(template vertices, template faces, imaged vertices, imaged faces) of the paper-scale head.

    The template (8192 faces at the defaults) is what the dataset ships as the tracked mesh;
    its vertices are the first vertices of the imaged surface before displacement, so it is a
    chord approximation of the imaged head that the same pointwise rig moves.
    """
    return tuple(a.copy() for a in _paper_cached(int(template_levels), int(surface_levels)))
