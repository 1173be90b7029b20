"""Image metrics in numpy: PSNR and SSIM (11x11 Gaussian window, sigma 1.5), whole image or
inside a foreground mask. numpy only, so evaluation can run anywhere."""

from __future__ import annotations

import numpy as np

_C1, _C2 = 0.01**2, 0.03**2


def _gauss_kernel(size=11, sigma=1.5):
    x = np.arange(size) - size // 2
    k = np.exp(-(x**2) / (2 * sigma**2))
    return k / k.sum()


def _blur(img: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Separable 'valid' filtering over the first two axes of [H,W,C]."""
    n = len(k)
    H, W = img.shape[:2]
    if H < n or W < n:
        raise ValueError(f"SSIM needs images of at least {n}x{n}, got {W}x{H}")
    cols = sum(k[i] * img[i : H - n + 1 + i] for i in range(n))  # n taps, not a pixel loop
    return sum(k[i] * cols[:, i : W - n + 1 + i] for i in range(n))


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SSIM per valid pixel [H-10, W-10], averaged over channels."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    k = _gauss_kernel()
    mu_a, mu_b = _blur(a, k), _blur(b, k)
    saa = _blur(a * a, k) - mu_a**2
    sbb = _blur(b * b, k) - mu_b**2
    sab = _blur(a * b, k) - mu_a * mu_b
    m = ((2 * mu_a * mu_b + _C1) * (2 * sab + _C2)) / ((mu_a**2 + mu_b**2 + _C1) * (saa + sbb + _C2))
    return m.mean(axis=-1)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (peak 1), in the mask when one is given: NaN for an empty mask, which has nothing
    to score (it read as a perfect 120 dB and lifted every mean it went into)."""
    diff = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is None:
        mse = diff.mean()
    else:
        w = np.asarray(mask, np.float64)[..., None] * np.ones(diff.shape[-1])
        if not w.sum() > 0:
            return float("nan")
        mse = (diff * w).sum() / w.sum()
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM, mask-weighted over the windows' centres when a mask is given: NaN when no
    window centre lies in it."""
    m = ssim_map(a, b)
    if mask is None:
        return float(m.mean())
    crop = np.asarray(mask, np.float64)[5:-5, 5:-5]
    if not crop.sum() > 0:
        return float("nan")
    return float((m * crop).sum() / crop.sum())


def defined_mean(values) -> float:
    """The mean of the values that are defined (views with nothing in their mask give NaN);
    NaN when none is."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else float("nan")
