"""Scalar fields the synthetic head is built from: smooth steps, signed distances and smooth
unions, rotations, hashed value noise. Reporting tier (numpy).
"""

import numpy as np


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
