"""Dense float64 torch rasteriser: the tests' reference for values and gradients.

Every Gaussian is evaluated at every pixel and composited in depth order, with the rules of
core/render/kernels.py (EWA + eps2d, gsplat's Jacobian clamp, near culling, alpha in
[1/255, 0.99], stop before T would drop below 1e-4). Autograd gives the gradients.
Memory is O(N * H * W): small scenes only.
"""

from __future__ import annotations

import torch
from ..geometry.rotations import quat_to_rotmat

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


def project(means, quats, scales, camera, near=0.01, eps2d=0.3):
    """(uv [N,2], conic [N,3] as (a, b, c), z [N], valid [N] bool) with the kernels' rules."""
    dt = means.dtype
    Rc = torch.as_tensor(camera.R, dtype=dt)
    tc = torch.as_tensor(camera.t, dtype=dt)
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    W, H = camera.width, camera.height
    pc = means @ Rc.T + tc
    x, y, z = pc.unbind(-1)
    valid = z >= near
    zs = torch.where(valid, z, torch.ones_like(z))  # keeps culled rows finite (no NaN gradients)
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    kx = torch.clamp(x / zs, -(cx / fx + 0.3 * tan_x), (W - cx) / fx + 0.3 * tan_x)
    ky = torch.clamp(y / zs, -(cy / fy + 0.3 * tan_y), (H - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / zs, zero, -fx * kx / zs, zero, fy / zs, -fy * ky / zs], -1).reshape(-1, 2, 3)
    M = Rc @ quat_to_rotmat(quats) * scales[:, None, :]
    A = J @ M
    cov = A @ A.transpose(1, 2) + eps2d * torch.eye(2, dtype=dt)
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    valid = valid & (det > 0)
    det = torch.where(valid, det, torch.ones_like(det))
    conic = torch.stack([c / det, -b / det, a / det], -1)
    uv = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    return uv, conic, z, valid


def render_reference(
    means, quats, scales, opacities, colors, camera, background=None, *, near=0.01, eps2d=0.3, means2d=None
):
    """Returns (image [H,W,C], alpha [H,W], contrib [N]); ``means2d`` [N,2] is added to the 2D means."""
    dt = means.dtype
    W, H = camera.width, camera.height
    uv, conic, z, valid = project(means, quats, scales, camera, near, eps2d)
    if means2d is not None:
        uv = uv + means2d
    jj, ii = torch.meshgrid(torch.arange(H, dtype=dt), torch.arange(W, dtype=dt), indexing="ij")
    px = (ii.reshape(-1) + 0.5)[None, :]
    py = (jj.reshape(-1) + 0.5)[None, :]
    dx = px - uv[:, :1]
    dy = py - uv[:, 1:]
    power = -0.5 * (conic[:, :1] * dx * dx + conic[:, 2:] * dy * dy) - conic[:, 1:2] * dx * dy
    power = torch.where(valid[:, None], power, torch.full_like(power, -1e30))
    alpha = torch.clamp(opacities[:, None] * torch.exp(power), max=ALPHA_MAX)
    alpha = torch.where(alpha < ALPHA_MIN, torch.zeros_like(alpha), alpha)
    order = torch.sort(torch.where(valid, z, torch.full_like(z, float("inf"))), stable=True).indices
    alpha = alpha[order]
    # A pixel stops before the Gaussian that would take T below T_MIN: T is non-increasing, so
    # "T after this Gaussian >= T_MIN" keeps exactly the composited prefix.
    t_after = torch.cumprod(1.0 - alpha, dim=0)
    alpha = torch.where(t_after.detach() >= T_MIN, alpha, torch.zeros_like(alpha))
    T = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1.0 - alpha[:-1]], 0), dim=0)
    weight = alpha * T  # [N, P]
    t_final = T[-1] * (1.0 - alpha[-1]) if len(alpha) else torch.ones(H * W, dtype=dt)
    image = weight.T @ colors[order]
    if background is not None:
        image = image + t_final[:, None] * background[None, :]
    contrib = torch.zeros(len(z), dtype=dt).index_copy(0, order, weight.sum(1).detach())
    return image.reshape(H, W, -1), (1.0 - t_final).reshape(H, W), contrib
