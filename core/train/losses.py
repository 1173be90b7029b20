"""Training losses in torch: L1, SSIM (same window as core.train.metrics), regularisers."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from numba import njit, prange

_C1, _C2 = 0.01**2, 0.03**2
_windows: dict = {}


def _gauss1d(device, dtype):
    key = (device, dtype)
    if key not in _windows:
        x = torch.arange(11, dtype=torch.float64) - 5
        g = torch.exp(-(x**2) / (2 * 1.5**2))
        _windows[key] = (g / g.sum()).to(device=device, dtype=dtype)
    return _windows[key]


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H,W,C] images (valid window positions, as core.train.metrics.ssim).

    On the CPU (b constant, as the training target is) one fused numba pass per row computes
    the five local moments with the separable window, SSIM and its derivatives in the moments;
    the backward is the window's transpose applied to those. Elsewhere: ssim_torch.
    """
    if (
        a.is_cuda
        or a.dtype != torch.float32
        or b.requires_grad
        or a.dim() != 3
        or a.shape != b.shape
        or min(a.shape[:2]) < 11
    ):
        return ssim_torch(a, b)
    return _SSIM.apply(a, b)


def ssim_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H,W,C] images (valid window positions, as core.train.metrics.ssim).

    The 11x11 Gaussian window is separable: the five local moments (x, y, x², y², xy) of all
    channels go through one depthwise 11-tap pass down the columns and one along the rows
    (22 taps per pixel instead of 121, and two convolutions instead of five).
    """
    x = a.permute(2, 0, 1)
    y = b.permute(2, 0, 1)
    C = x.shape[0]
    g = _gauss1d(x.device, x.dtype)
    maps = torch.cat([x, y, x * x, y * y, x * y])[None]  # [1, 5C, H, W]
    k = 5 * C
    maps = F.conv2d(maps, g.view(1, 1, 11, 1).expand(k, 1, 11, 1), groups=k)
    maps = F.conv2d(maps, g.view(1, 1, 1, 11).expand(k, 1, 1, 11), groups=k)
    mu_x, mu_y, exx, eyy, exy = maps[0].split(C)
    sxx = exx - mu_x**2
    syy = eyy - mu_y**2
    sxy = exy - mu_x * mu_y
    m = ((2 * mu_x * mu_y + _C1) * (2 * sxy + _C2)) / ((mu_x**2 + mu_y**2 + _C1) * (sxx + syy + _C2))
    return m.mean()


def photometric(image: torch.Tensor, target: torch.Tensor, lambda_ssim: float = 0.2) -> torch.Tensor:
    """(1 - λ)·L1 + λ·(1 - SSIM)."""
    l1 = (image - target).abs().mean()
    return (1 - lambda_ssim) * l1 + lambda_ssim * (1 - ssim(image, target))


def position_reg(d_mu: torch.Tensor, threshold: float = 1.0) -> torch.Tensor:
    return torch.relu(torch.linalg.vector_norm(d_mu, dim=-1) - threshold).mean()


def scale_reg(d_log_scale: torch.Tensor, threshold: float = 0.6) -> torch.Tensor:
    return torch.relu(torch.exp(d_log_scale) - threshold).mean()


# ----------------------------------------------------------------------------- CPU kernels
_SSIM_ROWS = 8  # output rows per parallel work item
_FAST = dict(fastmath=True, cache=True)


@njit(parallel=True, **_FAST)
def _ssim_forward(x, y, g):
    """x, y [C,H,W] float32. Returns the sum of the SSIM map over valid positions and, per
    valid position, d ssim / d (mu_x, E[x²], E[xy]) [3,C,H-10,W-10]."""
    C, H, W = x.shape
    h, w = H - 10, W - 10
    d = np.empty((3, C, h, w), np.float32)
    blocks = (h + _SSIM_ROWS - 1) // _SSIM_ROWS
    partial = np.zeros(C * blocks)
    c1 = np.float32(0.01**2)
    c2 = np.float32(0.03**2)
    for job in prange(C * blocks):
        c = job // blocks
        r0 = (job % blocks) * _SSIM_ROWS
        V = np.empty((5, W), np.float32)
        M = np.empty((5, w), np.float32)
        tot = 0.0
        for i in range(r0, min(h, r0 + _SSIM_ROWS)):
            for k in range(5):
                for j in range(W):
                    V[k, j] = 0.0
            for t in range(11):
                gt = g[t]
                xr = x[c, i + t]
                yr = y[c, i + t]
                for j in range(W):
                    xv = xr[j]
                    yv = yr[j]
                    V[0, j] += gt * xv
                    V[1, j] += gt * yv
                    V[2, j] += gt * xv * xv
                    V[3, j] += gt * yv * yv
                    V[4, j] += gt * xv * yv
            for k in range(5):
                for j in range(w):
                    M[k, j] = 0.0
                for t in range(11):
                    gt = g[t]
                    for j in range(w):
                        M[k, j] += gt * V[k, j + t]
            row = 0.0
            for j in range(w):
                mx = M[0, j]
                my = M[1, j]
                a1 = 2 * mx * my + c1
                a2 = 2 * (M[4, j] - mx * my) + c2
                b1 = mx * mx + my * my + c1
                b2 = (M[2, j] - mx * mx) + (M[3, j] - my * my) + c2
                den = b1 * b2
                s = (a1 * a2) / den
                row += s
                # Quotient rule on s = a1 a2 / (b1 b2), never dividing by a2 = 2 cov + C2, which
                # crosses 0 where a window's x and y are anticorrelated (s/a2 was 0/0 there).
                d[0, c, i, j] = (2 * my * (a2 - a1) - 2 * mx * s * (b2 - b1)) / den
                d[1, c, i, j] = -s / b2
                d[2, c, i, j] = 2 * a1 / den
            tot += row
        partial[job] = tot
    total = 0.0
    for k in range(partial.shape[0]):
        total += partial[k]
    return total, d


@njit(parallel=True, **_FAST)
def _ssim_backward(x, y, g, d, scale):
    """d (mean SSIM) / dx [C,H,W] times scale: the window's transpose on d, then the chain
    through mu_x = <x>, E[x²] = <x²>, E[xy] = <xy>."""
    C, H, W = x.shape
    h, w = H - 10, W - 10
    U = np.empty((3, C, h, W), np.float32)  # the window's transpose along the rows
    for job in prange(C * h):
        c = job // h
        i = job % h
        for k in range(3):
            ur = U[k, c, i]
            dr = d[k, c, i]
            # Gathered: U[J] = sum_t g[t] d[J - t] over 0 <= J - t < w; every tap inside from
            # column 10 to w - 1, fewer at the edges.
            for J in range(min(10, W)):
                s = np.float32(0.0)
                for t in range(max(0, J - w + 1), J + 1):
                    s += g[t] * dr[J - t]
                ur[J] = s
            for J0 in range(w - 10):  # J = J0 + 10: taps t = 10 - t2 on d[J0 + t2]
                s = np.float32(0.0)
                for t2 in range(11):
                    s += g[10 - t2] * dr[J0 + t2]
                ur[J0 + 10] = s
            for J in range(max(w, 10), W):
                s = np.float32(0.0)
                for t in range(J - w + 1, 11):
                    s += g[t] * dr[J - t]
                ur[J] = s
    out = np.empty((C, H, W), np.float32)
    for job in prange(C * H):
        c = job // H
        i = job % H
        xr = x[c, i]
        yr = y[c, i]
        orow = out[c, i]
        if i >= 10 and i < h:  # every tap inside: registers, one pass
            ub = U[:, c, i - 10 : i + 1]  # rows i - 10 .. i: tap t = 10 - t2 on row t2
            for j in range(W):
                p0 = np.float32(0.0)
                p1 = np.float32(0.0)
                p2 = np.float32(0.0)
                for t2 in range(11):
                    gt = g[10 - t2]
                    p0 += gt * ub[0, t2, j]
                    p1 += gt * ub[1, t2, j]
                    p2 += gt * ub[2, t2, j]
                orow[j] = scale * (p0 + 2 * xr[j] * p1 + yr[j] * p2)
        else:
            P = np.zeros((3, W), np.float32)
            for t in range(11):
                src = i - t
                if src < 0 or src >= h:
                    continue
                gt = g[t]
                for k in range(3):
                    ur = U[k, c, src]
                    pr = P[k]
                    for j in range(W):
                        pr[j] += gt * ur[j]
            for j in range(W):
                orow[j] = scale * (P[0, j] + 2 * xr[j] * P[1, j] + yr[j] * P[2, j])
    return out


class _SSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b):
        x = np.ascontiguousarray(a.detach().numpy().transpose(2, 0, 1), np.float32)
        y = np.ascontiguousarray(b.detach().numpy().transpose(2, 0, 1), np.float32)
        g = _gauss1d(torch.device("cpu"), torch.float32).numpy()
        total, d = _ssim_forward(x, y, g)
        count = x.shape[0] * (x.shape[1] - 10) * (x.shape[2] - 10)
        ctx.saved = (x, y, g, d, count)
        ctx.kind = (a.dtype, a.device)
        return torch.tensor(total / count, dtype=a.dtype)

    @staticmethod
    def backward(ctx, grad):
        x, y, g, d, count = ctx.saved
        gx = _ssim_backward(x, y, g, d, np.float32(float(grad) / count))
        dtype, device = ctx.kind
        return torch.from_numpy(gx.transpose(1, 2, 0)).to(device=device, dtype=dtype), None
