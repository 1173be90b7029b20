"""Rotations in one place: quaternions (wxyz, Hamilton product, rotating column vectors),
rotation matrices and axis-angle vectors, for numpy arrays and torch tensors alike.

Each function takes numpy arrays or torch tensors and returns the same kind. torch is never
imported here: a tensor argument brings its own module, so this stays Blender tier. The torch
paths are differentiable and keep finite gradients at the singular points (zero quaternion,
zero angle, Shepperd's pivot switch).
"""

from __future__ import annotations

import numpy as np

__all__ = ["quat_normalize", "quat_multiply", "quat_to_rotmat", "rotmat_to_quat", "axis_angle_to_matrix", "quat_rows"]


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def _torch():
    import torch

    return torch


def _stack(xs, axis, like):
    return _torch().stack(xs, dim=axis) if _is_torch(like) else np.stack(xs, axis=axis)


def _parts(a):
    return a.unbind(-1) if _is_torch(a) else tuple(np.moveaxis(a, -1, 0))


def quat_normalize(q):
    """Unit quaternions, scaled by the largest component first so a norm of 1e154 (whose square
    overflows) or 1e-200 (underflows) still normalises to the right rotation. numpy: only an
    exactly zero quaternion, which has no direction, becomes the identity; torch: it stays zero
    (which quat_to_rotmat maps to the identity) with a finite gradient."""
    if _is_torch(q):
        torch = _torch()
        m = q.detach().abs().amax(-1, keepdim=True)
        m = torch.where(m > 0, m, torch.ones_like(m))  # not a tiny floor: 1/tiny overflows the gradient
        u = q / m
        return u / torch.linalg.vector_norm(u, dim=-1, keepdim=True).clamp_min(1e-12)
    q = np.asarray(q)
    m = np.max(np.abs(q), axis=-1, keepdims=True)
    u = q / np.where(m > 0, m, 1)
    n = np.linalg.norm(u, axis=-1, keepdims=True)
    identity = np.zeros_like(q)
    identity[..., 0] = 1
    return np.where(n > 0, u / np.where(n > 0, n, 1), identity)


def quat_multiply(a, b):
    aw, ax, ay, az = _parts(a)
    bw, bx, by, bz = _parts(b)
    return _stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
        a,
    )


def quat_to_rotmat(q):
    """Rotation matrices [...,3,3] of quaternions [...,4] (normalised here)."""
    w, x, y, z = _parts(quat_normalize(q))
    m = _stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        -1,
        q,
    )
    return m.reshape(tuple(q.shape[:-1]) + (3, 3))


def quat_rows(R) -> np.ndarray:
    """Shepperd's method on matrix entries given as numpy arrays R[i][j] (any shape, any float
    dtype; component-major rows work too): unit wxyz quaternions [4,...] with w >= 0. Of the
    four algebraic forms it uses the one whose pivot component is largest, so no division by a
    near-zero component ever happens."""
    tr = R[0][0] + R[1][1] + R[2][2]
    piv = np.stack(
        [1 + tr, 1 + R[0][0] - R[1][1] - R[2][2], 1 - R[0][0] + R[1][1] - R[2][2], 1 - R[0][0] - R[1][1] + R[2][2]]
    )
    k = np.argmax(piv, axis=0)
    p = 0.5 * np.sqrt(np.maximum(np.take_along_axis(piv, k[None], 0)[0], 1e-30))
    inv = 0.25 / p
    a, b, c = R[2][1] - R[1][2], R[0][2] - R[2][0], R[1][0] - R[0][1]
    d, e, f = R[0][1] + R[1][0], R[0][2] + R[2][0], R[1][2] + R[2][1]
    cand = np.stack(
        [
            [p, a * inv, b * inv, c * inv],
            [a * inv, p, d * inv, e * inv],
            [b * inv, d * inv, p, f * inv],
            [c * inv, e * inv, f * inv, p],
        ]
    )  # [4 pivots, 4, ...]
    q = np.take_along_axis(cand, k[None, None], 0)[0]
    q *= np.where(q[0] < 0, -1, 1).astype(q.dtype)
    q /= np.sqrt(np.sum(q * q, axis=0))
    return q


def rotmat_to_quat(R):
    """Rotation matrices [...,3,3] -> unit quaternions wxyz [...,4] with w >= 0 (Shepperd)."""
    if not _is_torch(R):
        q = quat_rows([[R[..., i, j] for j in range(3)] for i in range(3)])
        return np.ascontiguousarray(np.moveaxis(q, 0, -1))
    torch = _torch()
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    piv = torch.stack([1 + tr, 1 + 2 * m[..., 0, 0] - tr, 1 + 2 * m[..., 1, 1] - tr, 1 + 2 * m[..., 2, 2] - tr], -1)
    k = torch.argmax(piv.detach(), dim=-1, keepdim=True)
    p = 0.5 * torch.sqrt(torch.gather(piv, -1, k)[..., 0].clamp_min(1e-30))
    inv = 0.25 / p
    a = m[..., 2, 1] - m[..., 1, 2]
    b = m[..., 0, 2] - m[..., 2, 0]
    c = m[..., 1, 0] - m[..., 0, 1]
    d = m[..., 0, 1] + m[..., 1, 0]
    e = m[..., 0, 2] + m[..., 2, 0]
    f = m[..., 1, 2] + m[..., 2, 1]
    cand = torch.stack(
        [
            torch.stack([p, a * inv, b * inv, c * inv], -1),
            torch.stack([a * inv, p, d * inv, e * inv], -1),
            torch.stack([b * inv, d * inv, p, f * inv], -1),
            torch.stack([c * inv, e * inv, f * inv, p], -1),
        ],
        -2,
    )
    q = torch.gather(cand, -2, k[..., None].expand(k.shape[:-1] + (1, 4)))[..., 0, :]
    q = torch.where(q[..., :1] < 0, -q, q)
    return quat_normalize(q)


def axis_angle_to_matrix(r):
    """Rotation matrices [...,3,3] from axis-angle vectors [...,3] (Rodrigues).

    The sin/cos coefficients switch to their Taylor series near zero so tiny angles are exact
    to rounding, in numpy and torch alike (which keeps the two in agreement); torch gets a
    harmless 1 under sqrt/sin where the series is used, so no NaN gradient leaks from the
    unused branch."""
    if _is_torch(r):
        torch = _torch()
        th2 = (r * r).sum(-1)[..., None, None]
        small = th2 < 1e-8
        th2_safe = torch.where(small, torch.ones_like(th2), th2)
        th = torch.sqrt(th2_safe)
        a = torch.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, torch.sin(th) / th)
        b = torch.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - torch.cos(th)) / th2_safe)
        eye = torch.eye(3, dtype=r.dtype, device=r.device)
    else:
        r = np.asarray(r, dtype=np.float64)
        th2 = np.sum(r * r, axis=-1)[..., None, None]
        small = th2 < 1e-8
        th = np.sqrt(np.where(small, 1.0, th2))
        a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(th) / th)
        b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(th)) / np.where(small, 1.0, th2))
        eye = np.eye(3)
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    o = x * 0
    K = _stack([o, -z, y, z, o, -x, -y, x, o], -1, r).reshape(tuple(r.shape[:-1]) + (3, 3))
    return eye + a * K + b * (K @ K)
