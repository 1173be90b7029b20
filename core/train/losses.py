"""Training losses in torch: L1, SSIM (same window as core.train.metrics), regularisers."""

from __future__ import annotations

import torch
import torch.nn.functional as F

_C1, _C2 = 0.01**2, 0.03**2
_windows: dict = {}


def _window(channels: int, device, dtype):
    key = (channels, device, dtype)
    if key not in _windows:
        x = torch.arange(11, dtype=dtype, device=device) - 5
        g = torch.exp(-(x**2) / (2 * 1.5**2))
        g = g / g.sum()
        _windows[key] = (g[:, None] * g[None, :]).expand(channels, 1, 11, 11).contiguous()
    return _windows[key]


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H,W,C] images (valid window positions, as core.train.metrics.ssim)."""
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    C = x.shape[1]
    w = _window(C, x.device, x.dtype)
    mu_x = F.conv2d(x, w, groups=C)
    mu_y = F.conv2d(y, w, groups=C)
    sxx = F.conv2d(x * x, w, groups=C) - mu_x**2
    syy = F.conv2d(y * y, w, groups=C) - mu_y**2
    sxy = F.conv2d(x * y, w, groups=C) - mu_x * mu_y
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
