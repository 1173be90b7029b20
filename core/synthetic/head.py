"""The embedded default dataset: a procedural, rigged, textured head rendered from 16 views.

Everything the product trains, measures and tests on by default comes from here, so the
data has to exercise the method the way NeRSemble + FLAME do:

- the template is watertight and unevenly tessellated (dense eyes and mouth, coarse scalp
  and neck), so adaptive subdivision has to compensate for the tessellation;
- the appearance mixes smooth skin with high-frequency regions (hair strands, stubble,
  sharp eyes and lips, a striped collar and text-like marks) and is defined in the
  template's canonical coordinates, so it sticks to the surface under animation;
- a small rig (jaw, blink, smile/pucker, head rotation and translation) drives ten
  sequences, the last of which mixes expressions no training sequence shows;
- ground truth is ray cast with supersampling, so images and coverage masks are
  anti-aliased and exact for the mesh the dataset ships.

The layout written by `make_dataset` is the GaussianAvatars/VHAP one in mesh mode (see
docs/ARCHITECTURE.md and the shared design's "Data conventions").
numpy + trimesh (embree through `embreex` when installed); PIL/tqdm only when writing.
"""

from __future__ import annotations

import functools
import json
import os
import time

import numpy as np
import trimesh

from ..geometry.camera import Camera

# Aspect ratio of NeRSemble frames (width:height = 550:802).
ASPECT = 550.0 / 802.0

# Canonical landmarks shared by the shape, the texture and the rig (metres, +y up, face +z).
EYE_CENTERS = ((0.032, 0.018), (-0.032, 0.018))  # (x, y) of each eye
EYE_HALF_WIDTH = 0.0135
EYE_HALF_OPENING = 0.0058
MOUTH_Y = -0.0625  # height of the lip contact line
MOUTH_HALF_WIDTH = 0.024
JAW_PIVOT = np.array([0.0, -0.025, -0.02])
NECK_PIVOT = np.array([0.0, -0.12, -0.012])
NECK_AXIS_Z = -0.012  # the neck cylinder's axis sits slightly behind the head centre
LIGHT_DIR = np.array([0.45, 0.55, 0.75]) / np.linalg.norm([0.45, 0.55, 0.75])
AMBIENT = 0.38
DIFFUSE = 0.72

# The paper-scale head (make_dataset(detail="paper")): octahedron subdivisions of the tracked
# template (8 * 4^5 = 8192 faces) and further subdivisions of the imaged surface (16x the faces).
PAPER_TEMPLATE_LEVELS = 5
PAPER_SURFACE_LEVELS = 2

# Radial shape search: rays from this interior point cross the surface once.
_SHAPE_CENTER = np.array([0.0, -0.06, 0.0])
_SHAPE_RMAX = 0.42


# --------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------


def _smoothstep(e0, e1, x):
    t = np.clip((np.asarray(x, np.float64) - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _normalize(v, axis=-1):
    n = np.linalg.norm(v, axis=axis, keepdims=True)
    return v / np.maximum(n, 1e-12)


def _rotation_xyz(yaw, pitch, roll):
    """Head rotation: roll about z, then pitch about x, then yaw about y (radians)."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return Ry @ Rx @ Rz


# --------------------------------------------------------------------------------------
# shape: an implicit head (smooth union of ellipsoids and cylinders), meshed by pushing a
# warped icosphere out along rays from an interior point
# --------------------------------------------------------------------------------------


def _sd_ellipsoid(p, c, r):
    # Quilez's bound: close to a true distance near the surface, which keeps the smooth
    # unions' blend widths meaningful in metres.
    q = (p - np.asarray(c)) / np.asarray(r)
    k0 = np.linalg.norm(q, axis=-1)
    k1 = np.linalg.norm(q / np.asarray(r), axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _sd_vertical_cylinder(p, cz, rx, rz, y0, y1, round_=0.0):
    """Elliptic cylinder along y; rx, rz may be arrays (a slowly varying radius)."""
    q = np.stack([p[..., 0] / rx, (p[..., 2] - cz) / rz], -1)
    radial = (np.linalg.norm(q, axis=-1) - 1.0) * np.minimum(rx, rz) + round_
    vertical = np.maximum(y0 - p[..., 1], p[..., 1] - y1) + round_
    outside = np.sqrt(np.maximum(radial, 0) ** 2 + np.maximum(vertical, 0) ** 2)
    return outside + np.minimum(np.maximum(radial, vertical), 0.0) - round_


def _smin(a, b, k):
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smax(a, b, k):
    return -_smin(-a, -b, k)


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


# --------------------------------------------------------------------------------------
# rig
# --------------------------------------------------------------------------------------

RIG_KEYS = ("jaw", "blink", "smile", "rotation", "translation")


def neutral_params() -> dict:
    return {"jaw": 0.0, "blink": 0.0, "smile": 0.0, "rotation": (0.0, 0.0, 0.0), "translation": (0.0, 0.0, 0.0)}


def pose_head(template_vertices, params) -> np.ndarray:
    """The rig: canonical vertices [V,3] + params -> posed vertices float32 [V,3].

    params (missing keys = neutral):
      jaw          0..1, opens the mouth (lower face rotates up to 12 degrees about the jaw axis)
      blink        0..1 (or a pair (left, right)), upper lids close over the eyes
      smile        -1..1, mouth corners out and up (> 0) or pucker in and forward (< 0)
      rotation     (yaw, pitch, roll) degrees; pitch > 0 looks down; the neck blends to
                   the unrotated collar
      translation  (3,) metres, moves everything
    All weights are smooth functions of the canonical position, so nearby vertices move
    alike (no tearing) whatever the tessellation.
    """
    P = np.asarray(template_vertices, np.float64)
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    out = P.copy()
    jaw = float(params.get("jaw", 0.0))
    blink = params.get("blink", 0.0)
    blink = (float(blink), float(blink)) if np.ndim(blink) == 0 else tuple(float(b) for b in blink)
    smile = float(params.get("smile", 0.0))
    yaw, pitch, roll = (np.radians(float(a)) for a in params.get("rotation", (0.0, 0.0, 0.0)))
    translation = np.asarray(params.get("translation", (0.0, 0.0, 0.0)), np.float64).reshape(3)

    front = _smoothstep(0.0, 0.05, z)
    ax = np.abs(x)

    # Smile / pucker act on the mouth region before the jaw, so the lips follow the jaw.
    if smile > 0:
        for sx in (1.0, -1.0):
            g = np.exp(-((x - sx * MOUTH_HALF_WIDTH) ** 2 + (y - MOUTH_Y) ** 2) / (2 * 0.013**2)) * front
            out[:, 0] += sx * 0.0065 * smile * g
            out[:, 1] += 0.0055 * smile * g
            out[:, 2] -= 0.002 * smile * g
            cheek = np.exp(-((x - sx * 0.042) ** 2 + (y + 0.03) ** 2) / (2 * 0.016**2)) * front
            out[:, 1] += 0.003 * smile * cheek
            out[:, 2] += 0.003 * smile * cheek
    elif smile < 0:
        pucker = -smile
        g = np.exp(-(x**2 / (2 * 0.022**2) + (y - MOUTH_Y) ** 2 / (2 * 0.013**2))) * front
        out[:, 0] -= 0.32 * pucker * x * g
        out[:, 2] += 0.008 * pucker * g

    # Blink: skin between the lower lid and the brow slides down, squeezing the eye
    # opening toward the lower lid (the texture is glued to the surface, so the iris
    # vanishes into a thin line, as under a closing lid).
    for (ex, ey), amount in zip(EYE_CENTERS, blink):
        if amount == 0.0:
            continue
        v = y - ey
        low, up = -EYE_HALF_OPENING, EYE_HALF_OPENING + 0.0008
        # smooth in v (no kinks a coarse triangle could not follow), ~0 at the lower lid,
        # full at the upper lid, back to 0 below the brow
        shift = (
            0.92
            * amount
            * (up - low)
            * _smoothstep(low - 0.002, up, v)
            * (1.0 - _smoothstep(up + 0.001, up + 0.009, v))
        )
        window = 1.0 - _smoothstep(0.9, 1.45, np.abs(x - ex) / EYE_HALF_WIDTH)
        out[:, 1] -= shift * window * _smoothstep(0.04, 0.065, z)

    # Jaw: the lower face rotates about a left-right axis. The weight is a sharp step at
    # the lip contact line between the mouth corners (the lips part there) and a soft one
    # over the cheeks; it fades toward the back and down the throat.
    if jaw != 0.0:
        width = 0.0016 + 0.014 * _smoothstep(MOUTH_HALF_WIDTH - 0.006, MOUTH_HALF_WIDTH + 0.018, ax)
        below = 1.0 / (1.0 + np.exp(-(MOUTH_Y - y) / width))
        w = below * _smoothstep(-0.05, 0.03, z) * _smoothstep(-0.175, -0.115, y)
        angle = np.radians(12.0) * jaw
        c, s = np.cos(angle), np.sin(angle)
        R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        rel = out - JAW_PIVOT
        out = out + w[:, None] * (rel @ R.T + JAW_PIVOT - out)

    # Head rotation about the neck, blended to zero at the collar.
    if yaw or pitch or roll:
        R = _rotation_xyz(yaw, pitch, roll)
        w = _smoothstep(-0.205, -0.11, y)
        rel = out - NECK_PIVOT
        out = out + w[:, None] * (rel @ R.T + NECK_PIVOT - out)

    out = out + translation
    return out.astype(np.float32)


# Expression mixes of the training sequences. Each entry: parameter -> (amplitude, cycles
# over the sequence). One-sided parameters (jaw, blink) swing 0..amplitude, signed ones
# -amplitude..amplitude. The novel mix of the test sequence combines motions no single
# training sequence combines, with its own amplitudes.
_TRAIN_MIXES = (
    {"jaw": (1.0, 1), "pitch": (6.0, 1)},
    {"smile": (1.0, 1), "blink": (1.0, 2)},
    {"smile": (-1.0, 1), "yaw": (24.0, 1)},
    {"blink": (1.0, 1), "pitch": (15.0, 1), "ty": (0.01, 1)},
    {"jaw": (0.7, 2), "smile": (0.8, 1), "roll": (10.0, 1)},
    {"yaw": (25.0, 1), "tx": (0.02, 1), "blink": (0.6, 2)},
    {"smile": (-0.9, 2), "jaw": (0.4, 1), "pitch": (-10.0, 1)},
    {"blink": (1.0, 3), "smile": (0.6, 1), "tz": (0.02, 1), "yaw": (-12.0, 1)},
    {"jaw": (0.5, 1), "smile": (0.5, 2), "yaw": (10.0, 1), "pitch": (6.0, 2), "roll": (-6.0, 1)},
)
_TEST_MIX = {
    "jaw": (0.85, 1),
    "smile": (-0.8, 1),
    "blink": (0.9, 2),
    "yaw": (-20.0, 1),
    "roll": (12.0, 1),
    "pitch": (-8.0, 2),
    "tx": (-0.015, 1),
    "ty": (0.01, 1),
}
_ONE_SIDED = ("jaw", "blink")
_MIX_NAMES = (
    "jaw",
    "smile-blink",
    "pucker-yaw",
    "blink-nod",
    "talk-roll",
    "turn",
    "pucker-talk",
    "blink-smile-dolly",
    "mixed",
)


def sequence_params(sequence: int, frame: int, frames: int, sequences: int = 10, seed: int = 0) -> dict:
    """Rig parameters of one frame; the last sequence is the novel-expression test mix."""
    is_test = sequence == sequences - 1
    mix = _TEST_MIX if is_test else _TRAIN_MIXES[sequence % len(_TRAIN_MIXES)]
    rng = np.random.default_rng([int(seed), int(sequence)])
    t = frame / max(frames, 1)
    vals = {}
    for key in sorted(mix):
        amp, cycles = mix[key]
        phase = rng.uniform(0, 2 * np.pi)
        if key in _ONE_SIDED:
            vals[key] = amp * (0.5 - 0.5 * np.cos(2 * np.pi * cycles * t + phase))
        else:
            vals[key] = amp * np.sin(2 * np.pi * cycles * t + phase)
    p = neutral_params()
    p["jaw"] = float(np.clip(vals.get("jaw", 0.0), 0.0, 1.0))
    p["blink"] = float(np.clip(vals.get("blink", 0.0), 0.0, 1.0))
    p["smile"] = float(np.clip(vals.get("smile", 0.0), -1.0, 1.0))
    p["rotation"] = (float(vals.get("yaw", 0.0)), float(vals.get("pitch", 0.0)), float(vals.get("roll", 0.0)))
    p["translation"] = (float(vals.get("tx", 0.0)), float(vals.get("ty", 0.0)), float(vals.get("tz", 0.0)))
    return p


def sequence_name(sequence: int, sequences: int = 10) -> str:
    if sequence == sequences - 1:
        return f"EXP-{sequence}-novel"
    return f"EXP-{sequence}-{_MIX_NAMES[sequence % len(_MIX_NAMES)]}"


# --------------------------------------------------------------------------------------
# appearance: a procedural albedo of the canonical point
# --------------------------------------------------------------------------------------

_M1 = np.uint64(0x9E3779B97F4A7C15)
_M2 = np.uint64(0xC2B2AE3D27D4EB4F)
_M3 = np.uint64(0x165667B19E3779F9)
_F1 = np.uint64(0xFF51AFD7ED558CCD)
_F2 = np.uint64(0xC4CEB9FE1A85EC53)
_S33 = np.uint64(33)


def _hash01(ix, iy, iz, seed):
    """Integer lattice -> uniform [0,1): a 64-bit mix (wrapping multiplications)."""
    h = (np.asarray(ix, np.int64).view(np.uint64) * _M1) ^ (np.asarray(iy, np.int64).view(np.uint64) * _M2)
    h = h ^ (np.asarray(iz, np.int64).view(np.uint64) * _M3) ^ np.uint64(seed * 0x27D4EB2F + 1)
    h = (h ^ (h >> _S33)) * _F1
    h = (h ^ (h >> _S33)) * _F2
    h = h ^ (h >> _S33)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def _value_noise(q, seed):
    """Smooth value noise in [0,1] at points q [N,3] (lattice spacing 1)."""
    f = np.floor(q)
    i = f.astype(np.int64)
    t = q - f
    w = t * t * (3.0 - 2.0 * t)
    out = np.zeros(len(q))
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wx * wy * wz * _hash01(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return out


def _fbm(q, octaves, seed):
    total, amp, norm = np.zeros(len(q)), 1.0, 0.0
    for o in range(octaves):
        total += amp * _value_noise(q * (2.0**o), seed + 17 * o)
        norm += amp
        amp *= 0.5
    return total / norm


def _mix(col, other, weight):
    w = np.asarray(weight, np.float64)[:, None]
    return col * (1.0 - w) + np.asarray(other, np.float64) * w


def _edge(signed, softness):
    """Crisp 0..1 step of a signed distance (inside < 0), a fraction of a millimetre wide."""
    return _smoothstep(softness, -softness, signed)


SKIN = np.array([0.86, 0.66, 0.55])
BLUSH = np.array([0.86, 0.50, 0.46])
HAIR = np.array([0.23, 0.15, 0.10])
LIP = np.array([0.72, 0.33, 0.35])
MOUTH_INSIDE = np.array([0.16, 0.04, 0.05])
SCLERA = np.array([0.94, 0.92, 0.89])
IRIS = np.array([0.22, 0.44, 0.52])
PUPIL = np.array([0.03, 0.03, 0.04])
SHIRT = np.array([0.10, 0.16, 0.38])
WHITE = np.array([0.96, 0.96, 0.95])
INK = np.array([0.05, 0.05, 0.06])


def albedo(points) -> np.ndarray:
    """Procedural reflectance [N,3] in [0,1] at canonical surface points [N,3] (metres)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    n = len(p)

    # smooth skin: low-frequency mottling, warmer cheeks, lighter forehead
    col = np.tile(SKIN, (n, 1)) * (0.92 + 0.14 * _fbm(p * 22.0, 2, 1))[:, None]
    col += (0.035 * _smoothstep(0.0, 0.09, y))[:, None] * np.array([1.0, 0.95, 0.8])
    col *= (1.0 - 0.10 * _smoothstep(-0.12, -0.2, y))[:, None]  # neck a shade darker
    for sx in (1.0, -1.0):
        g = np.exp(-((x - sx * 0.046) ** 2 + (y + 0.022) ** 2) / (2 * 0.019**2)) * _smoothstep(0.02, 0.06, z)
        col = _mix(col, BLUSH, 0.45 * g)
    front = z > 0.04

    # stubble: crisp dark dots on chin, jaw and upper lip (3D cell dots cut by the surface)
    beard = (
        _smoothstep(-0.036, -0.046, y)
        * _smoothstep(-0.128, -0.112, y)
        * _smoothstep(-0.02, 0.02, z)
        * (1.0 - _smoothstep(0.055, 0.07, ax) * _smoothstep(-0.07, -0.06, y))
    )
    sel = np.nonzero(beard > 0.01)[0]
    if len(sel):
        cell = 0.0024
        q = p[sel] / cell
        ci = np.floor(q).astype(np.int64)
        jitter = np.stack([_hash01(ci[:, 0], ci[:, 1], ci[:, 2], 31 + k) for k in range(3)], 1)
        d = np.linalg.norm(q - ci - 0.25 - 0.5 * jitter, axis=1)
        present = _hash01(ci[:, 0], ci[:, 1], ci[:, 2], 37) < 0.75
        dots = _edge(d - 0.36, 0.06) * present
        col[sel] *= (1.0 - 0.55 * dots * beard[sel])[:, None]
        col[sel] *= (1.0 - 0.12 * beard[sel])[:, None]  # shadow of the shaved beard area

    # lips with a crisp outline and a dark mouth interior along the contact line
    sel = np.nonzero(front & (np.abs(y - MOUTH_Y) < 0.014) & (ax < 0.03))[0]
    if len(sel):
        xs, dy = x[sel], y[sel] - MOUTH_Y
        u = np.clip(1.0 - (xs / 0.025) ** 2, 0.0, 1.0)
        upper_h = 0.0082 * np.sqrt(u) - 0.0016 * np.exp(-(xs**2) / (2 * 0.0035**2)) * np.sqrt(u)
        lower_h = 0.0098 * np.sqrt(np.clip(1.0 - (xs / 0.0235) ** 2, 0.0, 1.0))
        inside = np.where(dy >= 0, dy - upper_h, -dy - lower_h)
        lip = _edge(inside, 0.00025)
        creases = 0.93 + 0.07 * np.sin(xs / 0.0009)
        lipcol = LIP * creases[:, None]
        c = _mix(col[sel], 0.8 * LIP, _edge(np.abs(inside) - 0.0003, 0.0002))  # lip line
        c = _mix(c, lipcol, lip)
        gap = _edge(np.abs(dy) - 0.0018, 0.0002) * _edge(ax[sel] - 0.021, 0.0008)
        c = _mix(c, MOUTH_INSIDE, gap)
        col[sel] = c

    # nostrils
    for sx in (1.0, -1.0):
        d = _sd_ellipsoid(p, (sx * 0.0085, -0.037, 0.095), (0.0045, 0.0035, 0.0055))
        col = _mix(col, np.array([0.30, 0.14, 0.12]), _edge(d, 0.0004))

    # eyes: almond opening with sclera, iris with radial streaks, pupil, highlight, lashes
    for ex, ey in EYE_CENTERS:
        sel = np.nonzero(front & (np.abs(x - ex) < 0.022) & (np.abs(y - ey) < 0.016))[0]
        if not len(sel):
            continue
        dx, dy = x[sel] - ex, y[sel] - ey
        u = np.clip(1.0 - (dx / EYE_HALF_WIDTH) ** 2, 0.0, 1.0)
        half = EYE_HALF_OPENING * u**0.75
        lid_up = dy - half
        opening = np.maximum(lid_up, -dy - 0.85 * half)
        r = np.hypot(dx, dy)
        ang = np.arctan2(dy, dx)
        streak = _value_noise(np.stack([ang * 9.0, r / 0.0012, np.zeros_like(r)], 1), 41 + int(ex > 0))
        iris = IRIS[None, :] * (0.6 + 0.8 * streak)[:, None]
        iris = _mix(iris, 0.35 * IRIS, _smoothstep(0.0042, 0.0056, r))  # limbal ring
        eye = np.tile(SCLERA, (len(sel), 1)) * (1.0 - 0.15 * (1.0 - u))[:, None]
        eye = _mix(eye, iris, _edge(r - 0.0056, 0.0002))
        eye = _mix(eye, PUPIL, _edge(r - 0.0023, 0.0002))
        eye = _mix(eye, WHITE, _edge(np.hypot(dx - 0.0016, dy - 0.0017) - 0.0008, 0.0002))
        c = _mix(col[sel], eye, _edge(opening, 0.00025))
        lash = _edge(np.abs(lid_up - 0.0005) - 0.0006, 0.0002) * _edge(np.abs(dx) - EYE_HALF_WIDTH - 0.0015, 0.0004)
        c = _mix(c, INK, lash)
        col[sel] = c

    # eyebrows: arched bands of short dark strokes
    for ex, ey in EYE_CENTERS:
        sel = np.nonzero(front & (np.abs(x - ex) < 0.026) & (y > ey + 0.008) & (y < ey + 0.032))[0]
        if not len(sel):
            continue
        s = (x[sel] - ex) * np.sign(ex)  # along the brow, toward the temple
        centre = ey + 0.0185 + 0.005 * (1.0 - (s / 0.02) ** 2) - 0.002 * (s > 0.01) * (s - 0.01) / 0.01
        thick = 0.0034 * (1.0 - 0.55 * _smoothstep(-0.015, 0.022, s))
        band = _edge(np.abs(y[sel] - centre) - thick, 0.0004) * _edge(np.abs(s) - 0.022, 0.002)
        strokes = _value_noise(
            np.stack([(s + 0.4 * (y[sel] - centre)) / 0.0007, (y[sel] - centre) / 0.004, np.zeros_like(s)], 1), 53
        )
        browcol = HAIR[None, :] * (0.6 + 0.7 * strokes)[:, None]
        col[sel] = _mix(col[sel], browcol, band * (0.75 + 0.25 * strokes))

    # hair: strands running down from the crown, an irregular hairline, skin on the ears
    hc = p - np.array([0.0, 0.015, -0.012])
    phi = np.arctan2(hc[:, 0], hc[:, 2])
    aphi = np.degrees(np.abs(phi))
    hairline = np.interp(
        aphi, [0, 35, 62, 80, 88, 96, 112, 140, 180], [0.074, 0.068, 0.05, 0.03, -0.012, 0.034, 0.03, -0.04, -0.072]
    )
    sel = np.nonzero(y > hairline - 0.01)[0]
    if len(sel):
        ps, phs = p[sel], phi[sel]
        theta = np.arccos(np.clip(hc[sel, 1] / np.maximum(np.linalg.norm(hc[sel], axis=1), 1e-9), -1, 1))
        jag = 0.006 * (_value_noise(np.stack([phs * 40.0, ps[:, 1] * 0.0, np.zeros(len(sel))], 1), 61) - 0.5)
        hairmask = _edge(hairline[sel] + jag - ps[:, 1], 0.0008)
        for sx in (1.0, -1.0):  # ears stay skin
            hairmask *= 1.0 - _edge(_sd_ellipsoid(ps, (sx * 0.079, 0.004, -0.010), (0.013, 0.031, 0.021)), 0.001)
        arc = phs * 0.09 * np.sin(np.clip(theta, 0.3, np.pi))  # metres across the strands
        along = theta * 0.1
        q1 = np.stack([arc / 0.0021, along / 0.018, np.zeros(len(sel))], 1)
        q2 = np.stack([arc / 0.0055, along / 0.03, np.ones(len(sel)) * 7.0], 1)
        strands = 0.55 * _value_noise(q1, 71) + 0.45 * _value_noise(q2, 73)
        shine = np.exp(-(((theta - 0.75) / 0.18) ** 2))  # a soft sheen band across the top
        haircol = HAIR[None, :] * (0.35 + 1.3 * strands)[:, None] + (0.10 * shine * strands)[:, None]
        col[sel] = _mix(col[sel], haircol, hairmask)

    # neck: a choker band with text-like marks above a striped shirt collar
    nphi = np.arctan2(x, z - NECK_AXIS_Z)
    sel = np.nonzero(y < -0.183)[0]
    if len(sel):
        ys, ph = y[sel], nphi[sel]
        c = col[sel]
        arc = ph * 0.052
        band = _edge(np.abs(ys + 0.1915) - 0.0068, 0.0002)
        c = _mix(c, WHITE, band)
        # glyphs: 3 columns x 5 rows of bits per character, a blank column between characters
        gx = np.floor(arc / 0.0011).astype(np.int64)
        gy = np.floor((ys + 0.1955) / 0.0011).astype(np.int64)
        char = np.floor_divide(gx, 4)
        colk = gx - 4 * char
        bit = _hash01(char, colk, gy, 83) < 0.55
        word_gap = _hash01(char, 0, 0, 89) < 0.18
        ink = bit & (colk < 3) & (gy >= 0) & (gy < 5) & ~word_gap & (np.abs(ph) < 2.2)
        c = _mix(c, INK, ink * band)
        shirt = _edge(ys + 0.206, 0.0003)
        stripes = np.floor(arc / 0.0042).astype(np.int64) % 2 == 0
        shirtcol = np.where(stripes[:, None], SHIRT[None, :], WHITE[None, :])
        piping = _edge(np.abs(ys + 0.2075) - 0.0012, 0.0002)
        shirtcol = _mix(shirtcol, INK, piping)
        col[sel] = _mix(c, shirtcol, shirt)

    return np.clip(col, 0.0, 1.0)


def face_detail(vertices, faces, order: int = 6, albedo_fn=None) -> np.ndarray:
    """Per-face appearance detail: the variance of the albedo over a barycentric grid.

    float32 [F]; summed over RGB. Smooth skin scores near zero; hair, eyes, lips, stubble
    and the collar score high.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    i, j = np.meshgrid(np.arange(order), np.arange(order), indexing="ij")
    keep = i + j < order
    b1 = (i[keep] + 1.0 / 3.0) / order
    b2 = (j[keep] + 1.0 / 3.0) / order
    bary = np.stack([1.0 - b1 - b2, b1, b2], 1)  # [S,3], inside every face
    tri = v[f]  # [F,3,3]
    pts = np.einsum("sk,fkd->fsd", bary, tri).reshape(-1, 3)
    col = (albedo if albedo_fn is None else albedo_fn)(pts).reshape(len(f), len(bary), 3)
    return col.var(axis=1).sum(axis=1).astype(np.float32)


# --------------------------------------------------------------------------------------
# cameras and ray-cast ground truth
# --------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------
# the dataset
# --------------------------------------------------------------------------------------


def _to_u8(a):
    return np.clip(np.round(np.asarray(a) * 255.0), 0, 255).astype(np.uint8)


def _frame_record(cam: Camera, T: int, C: int, S: int) -> dict:
    name = f"{T:05d}_{C:02d}.png"
    return {
        "file_path": f"images/{name}",
        "fg_mask_path": f"fg_masks/{name}",
        "transform_matrix": cam.c2w_opengl().tolist(),
        "fl_x": float(cam.fx),
        "fl_y": float(cam.fy),
        "cx": float(cam.cx),
        "cy": float(cam.cy),
        "w": int(cam.width),
        "h": int(cam.height),
        "timestep_index": int(T),
        "camera_index": int(C),
        "mesh_path": f"meshes/{T:05d}.npz",
        "sequence": int(S),
    }


_JOB = None  # what forked generation workers render (set by make_dataset)


def _write_timestep(job, s, f, stats):
    """Pose, ray cast and write one timestep: its mesh, and an image and a mask per camera."""
    from PIL import Image

    out, frames = job["out"], job["frames"]
    T = s * frames + f
    params = sequence_params(s, f, frames, job["sequences"], job["seed"])
    tv, rv = job["tv"], job["rv"]
    verts = pose_head(tv, params)
    np.savez(os.path.join(out, "meshes", f"{T:05d}.npz"), vertices=verts)
    shown = verts if rv.shape == tv.shape else pose_head(rv, params)
    images, masks = render_views(
        shown,
        job["rf"],
        job["cams"],
        canonical=rv,
        supersample=job["supersample"],
        stats=stats,
        albedo_fn=job["albedo_fn"],
    )
    for C in range(len(job["cams"])):
        name = f"{T:05d}_{C:02d}.png"
        Image.fromarray(_to_u8(images[C]), "RGB").save(os.path.join(out, "images", name))
        Image.fromarray(_to_u8(masks[C]), "L").save(os.path.join(out, "fg_masks", name))


def _timestep_from_job(step):
    stats: dict = {}
    _write_timestep(_JOB, *step, stats=stats)
    return stats.get("rays", 0), stats.get("hits", 0), stats.get("intersector", "none")


def make_dataset(
    out,
    resolution: int = 128,
    cameras: int = 16,
    sequences: int = 10,
    frames: int = 8,
    seed: int = 0,
    progress: bool = True,
    supersample: int = 2,
    template_subdivisions: int = 4,
    detail: str = "default",
    workers: int = 1,
    surface_levels: int = PAPER_SURFACE_LEVELS,
) -> dict:
    """Write the synthetic mesh-mode dataset into ``out``; returns a summary dict.

    Global timestep T = sequence * frames + frame. Splits: the last sequence is the test
    (novel expression) sequence, camera ``cameras // 2`` the held-out (novel view) camera.

    ``template_subdivisions`` sets the tracked mesh written to the dataset (4: 5120 faces,
    3: 1280). The images are always ray-cast from a mesh of at least 4 subdivisions, so a
    coarser template is a chord approximation of the imaged surface, as a tracked FLAME
    mesh is of a real head; both come from the same pointwise rig, so they move together.

    ``detail="paper"``: the paper-scale head instead (``paper_head``: an 8192-face template
    with FLAME-like uneven density, images ray-cast from a 16x finer displaced surface with
    ``paper_albedo``); ``template_subdivisions`` is then ignored, ``surface_levels`` sets how
    much finer the imaged surface is (each level 4x the faces). ``workers`` > 1 renders
    timesteps in that many forked processes (the files are the same).
    """
    if detail not in ("default", "paper"):
        raise ValueError(f"make_dataset: detail must be 'default' or 'paper', got {detail!r}")
    from PIL import Image

    if sequences < 2 or cameras < 2 or frames < 1:
        raise ValueError("make_dataset needs at least 2 sequences, 2 cameras and 1 frame")
    t0 = time.perf_counter()
    out = os.fspath(out)
    for sub in ("images", "fg_masks", "meshes"):
        os.makedirs(os.path.join(out, sub), exist_ok=True)
    if detail == "paper":
        tv, tf, rv, rf = paper_head(surface_levels=surface_levels)
        albedo_fn = paper_albedo
    else:
        tv, tf = head_template(template_subdivisions)
        rv, rf = head_template(max(4, int(template_subdivisions)))
        albedo_fn = None
    np.savez(os.path.join(out, "canonical_mesh.npz"), vertices=tv, faces=tf)
    np.savez(os.path.join(out, "detail.npz"), face_detail=face_detail(tv, tf, albedo_fn=albedo_fn))
    cams = make_cameras(cameras, resolution)
    held = held_out_camera(cameras)
    test_seq = sequences - 1
    seq_info = [
        {
            "index": s,
            "name": sequence_name(s, sequences),
            "split": "test" if s == test_seq else "train",
            "timestep_start": s * frames,
            "num_timesteps": frames,
        }
        for s in range(sequences)
    ]
    splits = {"train": [], "val": [], "test": []}
    everything = []
    stats: dict = {}
    steps = [(s, f) for s in range(sequences) for f in range(frames)]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(steps), desc="synthetic head", unit="timestep")
    job = dict(
        out=out,
        frames=frames,
        sequences=sequences,
        seed=seed,
        tv=tv,
        rv=rv,
        rf=rf,
        cams=cams,
        supersample=supersample,
        albedo_fn=albedo_fn,
    )
    for s, f in steps:
        T = s * frames + f
        for C, cam in enumerate(cams):
            rec = _frame_record(cam, T, C, s)
            everything.append(rec)
            if s == test_seq:
                splits["test"].append(rec)
            elif C == held:
                splits["val"].append(rec)
            else:
                splits["train"].append(rec)
    if int(workers) > 1 and len(steps) > 1:
        # fork: the workers share the surface built above instead of rebuilding it
        import multiprocessing as mp

        global _JOB
        _JOB = job
        with mp.get_context("fork").Pool(min(int(workers), len(steps))) as pool:
            for rays, hits, kind in pool.imap_unordered(_timestep_from_job, steps):
                stats["rays"] = stats.get("rays", 0) + rays
                stats["hits"] = stats.get("hits", 0) + hits
                stats["intersector"] = kind
                if bar is not None:
                    bar.update(1)
        _JOB = None
    else:
        for step in steps:
            _write_timestep(job, *step, stats=stats)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()

    def write(name, recs, seqs):
        doc = {
            "background": [1.0, 1.0, 1.0],
            "mode": "mesh",
            "canonical_mesh_path": "canonical_mesh.npz",
            "sequences": [seq_info[i] for i in seqs],
            "timestep_indices": sorted({r["timestep_index"] for r in recs}),
            "camera_indices": sorted({r["camera_index"] for r in recs}),
            "frames": recs,
        }
        with open(os.path.join(out, name), "w") as fh:
            json.dump(doc, fh, indent=1)

    train_seqs = list(range(sequences - 1))
    write("transforms_train.json", splits["train"], train_seqs)
    write("transforms_val.json", splits["val"], train_seqs)
    write("transforms_test.json", splits["test"], [test_seq])
    write("transforms.json", everything, list(range(sequences)))
    seconds = time.perf_counter() - t0
    w, h = image_size(resolution)
    summary = {
        "out": out,
        "width": w,
        "height": h,
        "cameras": cameras,
        "sequences": sequences,
        "frames": frames,
        "timesteps": len(steps),
        "images": len(everything),
        "train": len(splits["train"]),
        "val": len(splits["val"]),
        "test": len(splits["test"]),
        "held_out_camera": held,
        "test_sequence": test_seq,
        "vertices": int(len(tv)),
        "faces": int(len(tf)),
        "supersample": supersample,
        "rays": int(stats.get("rays", 0)),
        "detail": detail,
        "imaged_faces": int(len(rf)),
        "intersector": stats.get("intersector", "none"),
        "seconds": seconds,
        "rays_per_second": stats.get("rays", 0) / max(seconds, 1e-9),
    }
    with open(os.path.join(out, "summary.json"), "w") as fh:
        json.dump(summary, fh, indent=1)
    return summary


def contact_sheet(dataset_dir, path, rows: int = 4) -> str:
    """All cameras (columns) x ``rows`` timesteps from different sequences, labelled."""
    from PIL import Image, ImageDraw

    with open(os.path.join(dataset_dir, "transforms.json")) as fh:
        doc = json.load(fh)
    seqs = doc["sequences"]
    n_seq = len(seqs)
    picks = sorted({int(round(k * (n_seq - 1) / max(rows - 1, 1))) for k in range(rows)})
    by_key = {(r["timestep_index"], r["camera_index"]): r for r in doc["frames"]}
    cams = sorted({r["camera_index"] for r in doc["frames"]})
    chosen = []
    for si in picks:
        info = seqs[si]
        n = info["num_timesteps"]
        # the frame of strongest expression, so rows differ visibly
        best = max(range(n), key=lambda f: _activity(sequence_params(si, f, n, n_seq)))
        chosen.append((info, info["timestep_start"] + best))
    first = by_key[(chosen[0][1], cams[0])]
    w, h = first["w"], first["h"]
    left, top = 96, 14
    sheet = Image.new("RGB", (left + w * len(cams), top + h * len(chosen)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for ci, C in enumerate(cams):
        draw.text((left + ci * w + 2, 1), f"cam {C}", fill=(0, 0, 0))
    for ri, (info, T) in enumerate(chosen):
        draw.text((2, top + ri * h + 2), f"t={T}", fill=(0, 0, 0))
        draw.text((2, top + ri * h + 14), info["name"][:15], fill=(0, 0, 0))
        draw.text((2, top + ri * h + 26), info["split"], fill=(0, 0, 0))
        for ci, C in enumerate(cams):
            rec = by_key[(T, C)]
            tile = Image.open(os.path.join(dataset_dir, rec["file_path"])).convert("RGB")
            sheet.paste(tile, (left + ci * w, top + ri * h))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    sheet.save(path)
    return path


def _activity(p):
    return p["jaw"] + p["blink"] + abs(p["smile"]) + sum(abs(a) for a in p["rotation"]) / 25.0


def render_closeup(path, height: int = 384, supersample: int = 3, detail: str = "default") -> str:
    """A frontal close-up strip: neutral, jaw open + blink, smile, pucker + turn (``detail="paper"``:
    the paper-scale head's imaged surface and albedo)."""
    from PIL import Image

    if detail == "paper":
        _, _, tv, tf = paper_head()
    else:
        tv, tf = head_template()
    albedo_fn = paper_albedo if detail == "paper" else None
    w = int(round(height * 0.8))
    f = height / 0.30
    cam = Camera.look_at((0.0, 0.0, 1.0), (0.0, -0.01, 0.0), (0.0, 1.0, 0.0), f, f, w / 2.0, height / 2.0, w, height)
    poses = [
        neutral_params(),
        {"jaw": 1.0, "blink": 1.0},
        {"smile": 1.0},
        {"smile": -1.0, "rotation": (20.0, 0.0, 0.0)},
    ]
    tiles = []
    for p in poses:
        img, _ = render_views(pose_head(tv, p), tf, [cam], canonical=tv, supersample=supersample, albedo_fn=albedo_fn)
        tiles.append(_to_u8(img[0]))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    Image.fromarray(np.concatenate(tiles, axis=1), "RGB").save(path)
    return path


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


TEETH = np.array([0.93, 0.90, 0.82])
TONGUE = np.array([0.62, 0.26, 0.28])
BUTTON = np.array([0.90, 0.88, 0.80])


def paper_albedo(points) -> np.ndarray:
    """The default albedo plus detail at the paper's pixel size, mostly where a FLAME-like
    template is coarse: fine hair strands with dark gaps and sheen, fine stubble, ear folds,
    a woven shirt with buttons and a seam, teeth and a tongue in the mouth."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    col = albedo(p)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    sel, hair, theta, phi = _hairline_mask(p)
    if len(sel):
        fine = _strands(p[sel], theta, phi, 0.0006, 0.012, 111)
        gaps = _smoothstep(0.25, 0.08, _strands(p[sel], theta, phi, 0.0009, 0.03, 113))
        mult = (0.55 + 0.9 * fine) * (1.0 - 0.6 * gaps)
        sheen = 0.12 * np.exp(-(((theta - 0.8) / 0.12) ** 2)) * fine
        c = col[sel] * mult[:, None] + sheen[:, None]
        col[sel] = _mix(col[sel], c, hair)
    # fine stubble between the coarse dots
    beard = (
        _smoothstep(-0.036, -0.046, y)
        * _smoothstep(-0.128, -0.112, y)
        * _smoothstep(-0.02, 0.02, z)
        * (1.0 - _smoothstep(0.055, 0.07, ax) * _smoothstep(-0.07, -0.06, y))
    )
    sel = np.nonzero(beard > 0.01)[0]
    if len(sel):
        q = p[sel] / 0.0011
        ci = np.floor(q).astype(np.int64)
        jitter = np.stack([_hash01(ci[:, 0], ci[:, 1], ci[:, 2], 131 + k) for k in range(3)], 1)
        dd = np.linalg.norm(q - ci - 0.25 - 0.5 * jitter, axis=1)
        dots = _edge(dd - 0.3, 0.08) * (_hash01(ci[:, 0], ci[:, 1], ci[:, 2], 137) < 0.6)
        col[sel] *= (1.0 - 0.45 * dots * beard[sel])[:, None]
    # ear folds: shadowed creases along the ridges of paper_displacement
    near_ear = np.nonzero((ax > 0.06) & (np.abs(y - 0.004) < 0.032) & (np.abs(z + 0.010) < 0.022))[0]
    for sx in (1.0, -1.0):
        r, w = _ear_coords(p[near_ear], sx)
        keep = np.nonzero(w > 0.01)[0]
        sel = near_ear[keep]
        r, w = r[keep], w[keep]
        if len(sel):
            rs = r
            crease = (
                np.exp(-(((rs - 0.66) / 0.035) ** 2))
                + np.exp(-(((rs - 0.93) / 0.03) ** 2))
                + 0.8 * (1.0 - _smoothstep(0.25, 0.36, rs))
            )
            col[sel] *= (1.0 - 0.45 * np.clip(crease, 0, 1) * w)[:, None]
    # shirt: a fine weave, a placket seam and buttons with four holes
    sel = np.nonzero(y < -0.205)[0]
    if len(sel):
        ps = p[sel]
        ys = ps[:, 1]
        arc = np.arctan2(ps[:, 0], ps[:, 2] - NECK_AXIS_Z) * 0.052
        shirt = _edge(ys + 0.206, 0.0003)
        weave = 0.5 + 0.5 * np.sign(np.sin(arc / 0.00045 * np.pi)) * np.sign(np.sin(ys / 0.00045 * np.pi))
        c = col[sel] * (0.8 + 0.3 * weave)[:, None]
        seam = _edge(np.abs(ps[:, 0] - 0.006) - 0.00035, 0.0001) * (ys < -0.212) * (ps[:, 2] > 0.0)
        c = _mix(c, INK, 0.8 * seam)
        bd, front = _buttons(ps)
        button = _edge(bd - 0.0036, 0.0002) * front
        holes = np.zeros(len(ps))
        for by in _BUTTON_Y:
            for hx, hy in ((-0.0009, -0.0009), (0.0009, -0.0009), (-0.0009, 0.0009), (0.0009, 0.0009)):
                holes = np.maximum(holes, _edge(np.hypot(ps[:, 0] - hx, ys - by - hy) - 0.00045, 0.0001))
        rim = _edge(np.abs(bd - 0.003) - 0.0003, 0.0001)
        bcol = _mix(_mix(np.tile(BUTTON, (len(ps), 1)), 0.6 * BUTTON, rim), INK, holes)
        c = _mix(c, bcol, button)
        col[sel] = _mix(col[sel], c, shirt)
    # mouth interior: upper and lower teeth with gaps, the tongue behind
    sel = np.nonzero((z > 0.04) & (np.abs(y - MOUTH_Y) < 0.004) & (ax < 0.025))[0]
    if len(sel):
        xs, dy = x[sel], y[sel] - MOUTH_Y
        gap = _edge(np.abs(dy) - 0.0018, 0.0002) * _edge(ax[sel] - 0.021, 0.0008)
        tooth = np.abs(((xs + 0.0021) / 0.0042) % 1.0 - 0.5) < 0.42
        teeth = _edge(np.abs(dy) - 0.0011, 0.00015) * _edge(np.abs(dy) - 0.0004, -0.00015) * tooth
        inside = _mix(np.tile(MOUTH_INSIDE, (len(sel), 1)), TONGUE, _edge(np.abs(dy) - 0.0006, 0.0002))
        inside = _mix(inside, TEETH, teeth * (ax[sel] < 0.016))
        col[sel] = _mix(col[sel], inside, gap)
    return np.clip(col, 0.0, 1.0)


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
