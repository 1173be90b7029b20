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


def _fused(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Whether the fused CPU kernels take this pair (else the torch composition does)."""
    return not (
        a.is_cuda
        or a.dtype != torch.float32
        or b.dtype != torch.float32
        or b.requires_grad
        or a.dim() != 3
        or a.shape != b.shape
        or min(a.shape[:2]) < 11
    )


class TargetWindow:
    """The window sums of a constant [H, W, C] target that SSIM needs (its local mean and mean
    square), computed on first use and then shared by every image compared with it; ``moments``
    is None where the fused kernels do not apply (photometric falls back to torch there)."""

    def __init__(self, target: torch.Tensor):
        self.target = target
        self._moments = None
        self._done = False

    @property
    def moments(self):
        if not self._done:
            self._done = True
            if _fused(self.target, self.target):
                g = _gauss1d(torch.device("cpu"), torch.float32).numpy()
                self._moments = _target_moments(_rows(self.target), g, self.target.shape[2])
        return self._moments


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H,W,C] images (valid window positions, as core.train.metrics.ssim).

    On the CPU (b constant, as the training target is) one fused numba pass per row computes
    the image's three local moments with the separable window (b's two come from TargetWindow),
    SSIM and its derivatives in the moments; the backward is the window's transpose applied to
    those (_Photometric). Elsewhere: ssim_torch.
    """
    if not _fused(a, b):
        return ssim_torch(a, b)
    return _Photometric.apply(a, b, 0.0, 1.0, TargetWindow(b).moments)


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


def photometric(
    image: torch.Tensor, target: torch.Tensor, lambda_ssim: float = 0.2, target_window: TargetWindow | None = None
) -> torch.Tensor:
    """(1 - λ)·L1 + λ·(1 - SSIM). ``target_window`` (TargetWindow(target)) saves the target's
    share of the window sums when several images meet one target (the levels of a step)."""
    if target_window is not None and target_window.target is not target:
        raise ValueError("photometric: target_window was made for another target")
    if _fused(image, target):  # both terms in one pass over the images (_Photometric)
        tw = target_window if target_window is not None else TargetWindow(target)
        return lambda_ssim + _Photometric.apply(image, target, 1.0 - lambda_ssim, -lambda_ssim, tw.moments)
    l1 = (image - target).abs().mean()
    return (1 - lambda_ssim) * l1 + lambda_ssim * (1 - ssim(image, target))


def position_reg(d_mu: torch.Tensor, threshold: float = 1.0) -> torch.Tensor:
    return torch.relu(torch.linalg.vector_norm(d_mu, dim=-1) - threshold).mean()


def scale_reg(d_log_scale: torch.Tensor, threshold: float = 0.6) -> torch.Tensor:
    return torch.relu(torch.exp(d_log_scale) - threshold).mean()


# ----------------------------------------------------------------------------- CPU kernels
# The kernels read the [H, W, C] images as they are, each row one run of W*C floats: the vertical
# pass of the window is then one loop over the whole row and the horizontal pass steps by C
# (channel c of column j is element j*C + c), so neither needs a channel-first copy.
_SSIM_ROWS = 8  # output rows per parallel work item
_FAST = dict(fastmath=True, cache=True)


@njit(parallel=True, **_FAST)
def _target_moments(y, g, n_ch):
    """The window's mean of y and of y² at every valid position, [2, H-10, (W-10)*C], y [H, W*C]."""
    H, WC = y.shape
    h, wc = H - 10, WC - 10 * n_ch
    out = np.empty((2, h, wc), np.float32)
    for i in prange(h):
        V = np.zeros((2, WC), np.float32)
        for t in range(11):
            gt = g[t]
            yr = y[i + t]
            for j in range(WC):
                yv = yr[j]
                V[0, j] += gt * yv
                V[1, j] += gt * yv * yv
        for k in range(2):
            o = out[k, i]
            for j in range(wc):
                o[j] = 0.0
            for t in range(11):
                gt = g[t]
                vt = V[k, t * n_ch : t * n_ch + wc]  # a view: indices that cannot wrap vectorise
                for j in range(wc):
                    o[j] += gt * vt[j]
    return out


@njit(parallel=True, **_FAST)
def _photometric_forward(x, y, ty, g, n_ch):
    """x, y [H, W*C] float32 (HWC rows), ty y's _target_moments. Returns the sum of the SSIM map
    over valid positions, the sum of |x - y| over all pixels, and per valid position
    d ssim / d (mu_x, E[x²], E[xy]) [3, H-10, (W-10)*C]."""
    H, WC = x.shape
    h, wc = H - 10, WC - 10 * n_ch
    d = np.empty((3, h, wc), np.float32)
    blocks = (h + _SSIM_ROWS - 1) // _SSIM_ROWS
    partial = np.zeros(blocks)
    c1 = np.float32(0.01**2)
    c2 = np.float32(0.03**2)
    for job in prange(blocks):
        r0 = job * _SSIM_ROWS
        V = np.empty((3, WC), np.float32)
        M = np.empty((3, wc), np.float32)
        tot = 0.0
        for i in range(r0, min(h, r0 + _SSIM_ROWS)):
            for k in range(3):
                for j in range(WC):
                    V[k, j] = 0.0
            for t in range(11):
                gt = g[t]
                xr = x[i + t]
                yr = y[i + t]
                for j in range(WC):
                    xv = xr[j]
                    V[0, j] += gt * xv
                    V[1, j] += gt * xv * xv
                    V[2, j] += gt * xv * yr[j]
            for k in range(3):
                for j in range(wc):
                    M[k, j] = 0.0
                for t in range(11):
                    gt = g[t]
                    vt = V[k, t * n_ch : t * n_ch + wc]  # a view: indices that cannot wrap vectorise
                    for j in range(wc):
                        M[k, j] += gt * vt[j]
            my_row = ty[0, i]
            eyy_row = ty[1, i]
            row = 0.0
            for j in range(wc):
                mx = M[0, j]
                my = my_row[j]
                a1 = 2 * mx * my + c1
                a2 = 2 * (M[2, j] - mx * my) + c2
                b1 = mx * mx + my * my + c1
                b2 = (M[1, j] - mx * mx) + (eyy_row[j] - my * my) + c2
                den = b1 * b2
                s = (a1 * a2) / den
                row += s
                # Quotient rule on s = a1 a2 / (b1 b2), never dividing by a2 = 2 cov + C2, which
                # crosses 0 where a window's x and y are anticorrelated (s/a2 was 0/0 there).
                d[0, i, j] = (2 * my * (a2 - a1) - 2 * mx * s * (b2 - b1)) / den
                d[1, i, j] = -s / b2
                d[2, i, j] = 2 * a1 / den
            tot += row
        partial[job] = tot
    l1_rows = np.zeros(H)
    for i in prange(H):
        acc = 0.0
        for j in range(WC):
            acc += abs(x[i, j] - y[i, j])
        l1_rows[i] = acc
    total = 0.0
    for k in range(blocks):
        total += partial[k]
    l1 = 0.0
    for i in range(H):
        l1 += l1_rows[i]
    return total, l1, d


@njit(parallel=True, **_FAST)
def _photometric_backward(x, y, g, d, n_ch, s_ssim, s_l1):
    """s_ssim * d (sum of the SSIM map) / dx + s_l1 * d (sum |x - y|) / dx, [H, W*C] like x:
    the window's transpose on d (along the rows, then down the columns), then the chain through
    mu_x = <x>, E[x²] = <x²>, E[xy] = <xy>; sign(x - y) (0 where equal, as torch) for L1."""
    H, WC = x.shape
    h, wc = H - 10, WC - 10 * n_ch
    U = np.empty((3, h, WC), np.float32)  # the window's transpose along the rows
    for job in prange(3 * h):
        k = job // h
        i = job % h
        ur = U[k, i]
        dr = d[k, i]
        # Gathered: U[J] = sum_t g[t] d[J - t C] over 0 <= J - t C < wc. Every tap lies inside
        # from J = 10 C to wc - 1 (unsigned indices there: numba then adds no negative-index
        # wrap, and the loop vectorises); fewer taps at the edges, first.
        n_lo = min(10 * n_ch, WC)  # columns [0, n_lo) and [hi, WC): some taps fall outside
        hi = max(wc, 10 * n_ch)
        for e in range(n_lo + WC - hi):
            J = e if e < n_lo else hi + e - n_lo
            acc = np.float32(0.0)
            for t in range(11):
                src = J - t * n_ch
                if 0 <= src < wc:
                    acc += g[t] * dr[src]
            ur[J] = acc
        c = np.uint64(n_ch)
        for J0 in range(np.uint64(max(wc - 10 * n_ch, 0))):  # J = J0 + 10 C
            acc = np.float32(0.0)
            for t2 in range(np.uint64(11)):
                acc += g[np.uint64(10) - t2] * dr[J0 + t2 * c]
            ur[J0 + np.uint64(10) * c] = acc
    out = np.empty((H, WC), np.float32)
    for i in prange(H):
        xr = x[i]
        yr = y[i]
        orow = out[i]
        if i >= 10 and i < h:  # every tap inside: registers, one pass
            ub = U[:, i - 10 : i + 1]  # rows i - 10 .. i: tap t = 10 - t2 on row t2
            for j in range(WC):
                p0 = np.float32(0.0)
                p1 = np.float32(0.0)
                p2 = np.float32(0.0)
                for t2 in range(11):
                    gt = g[10 - t2]
                    p0 += gt * ub[0, t2, j]
                    p1 += gt * ub[1, t2, j]
                    p2 += gt * ub[2, t2, j]
                e = xr[j] - yr[j]
                sgn = np.float32(e > 0) - np.float32(e < 0)  # sign(e), 0 at 0; no branch
                orow[j] = s_ssim * (p0 + 2 * xr[j] * p1 + yr[j] * p2) + s_l1 * sgn
        else:
            P = np.zeros((3, WC), np.float32)
            for t in range(11):
                src = i - t
                if src < 0 or src >= h:
                    continue
                gt = g[t]
                for k in range(3):
                    ur = U[k, src]
                    pr = P[k]
                    for j in range(WC):
                        pr[j] += gt * ur[j]
            for j in range(WC):
                e = xr[j] - yr[j]
                sgn = np.float32(e > 0) - np.float32(e < 0)  # sign(e), 0 at 0; no branch
                orow[j] = s_ssim * (P[0, j] + 2 * xr[j] * P[1, j] + yr[j] * P[2, j]) + s_l1 * sgn
    return out


def _rows(t: torch.Tensor) -> np.ndarray:
    """An [H, W, C] float32 tensor as [H, W*C] rows (no copy when it is contiguous)."""
    a = np.ascontiguousarray(t.detach().numpy())
    return a.reshape(a.shape[0], -1)


class _Photometric(torch.autograd.Function):
    """w_l1 * mean |a - b| + w_ssim * mean SSIM(a, b) of [H, W, C] float32 images, b constant
    (its window sums given: TargetWindow)."""

    @staticmethod
    def forward(ctx, a, b, w_l1, w_ssim, target_moments):
        x, y = _rows(a), _rows(b)
        n_ch = a.shape[2]
        g = _gauss1d(torch.device("cpu"), torch.float32).numpy()
        total, l1, d = _photometric_forward(x, y, target_moments, g, n_ch)
        n_ssim = n_ch * (a.shape[0] - 10) * (a.shape[1] - 10)
        n_l1 = x.size
        ctx.saved = (x, y, g, d, n_ch, w_l1 / n_l1, w_ssim / n_ssim)
        ctx.kind = (a.shape, a.dtype, a.device)
        return torch.tensor(w_l1 * l1 / n_l1 + w_ssim * total / n_ssim, dtype=a.dtype)

    @staticmethod
    def backward(ctx, grad):
        x, y, g, d, n_ch, s_l1, s_ssim = ctx.saved
        gv = float(grad)
        gx = _photometric_backward(x, y, g, d, n_ch, np.float32(gv * s_ssim), np.float32(gv * s_l1))
        shape, dtype, device = ctx.kind
        return torch.from_numpy(gx.reshape(shape)).to(device=device, dtype=dtype), None, None, None, None
