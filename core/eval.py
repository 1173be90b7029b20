"""Budget sweeps and reports: quality against bytes for a progressive avatar.

An avatar here is in STREAM ORDER (core.stream.read_stream), so the Gaussians of a budget
are a prefix: faces [0, count). Metrics are PSNR/SSIM inside the foreground mask and on the
whole image (core.metrics), on the dataset's val (novel view, NVS) and test (novel
expression, NES) splits.
"""

from __future__ import annotations

import time

import numpy as np

from . import metrics
from .avatar import Avatar, sh_to_rgb, sigmoid
from .binding import compose, evaluate


class SplitRenderer:
    """Renders face subsets of one avatar on the views of one dataset split."""

    def __init__(self, avatar: Avatar, dataset, max_views: int | None = 32):
        from .importance import view_subset

        self.avatar, self.dataset = avatar, dataset
        self.views = view_subset(len(dataset), max_views)
        self.weights = avatar.forest.weights()
        self.opac = sigmoid(avatar.opacity_logit)
        self.rgb = sh_to_rgb(avatar.f_dc)
        self.bg = np.asarray(dataset.background, np.float32)

    def render(self, view: int, ids: np.ndarray, with_alpha: bool = False):
        """(image, seconds) of faces `ids` on a view, plus the alpha [H,W] with `with_alpha`.
        No faces (a budget inside the header): the background, alpha 0."""
        from .render import render_numpy

        info = self.dataset.frame_info(int(view))
        ids = np.asarray(ids, np.int64)
        if len(ids) == 0:
            cam = info.camera
            image = np.broadcast_to(self.bg, (cam.height, cam.width, len(self.bg))).astype(np.float32)
            alpha = np.zeros((cam.height, cam.width), np.float32)
            return (image, 0.0, alpha) if with_alpha else (image, 0.0)
        verts = self.dataset.vertices_at(info.timestep_index)
        av = self.avatar
        geo = evaluate(av.forest, verts, ids=ids, weights=self.weights)
        means, scales, quats = compose(geo.t, geo.r, geo.s, av.d_mu[ids], av.d_log_scale[ids], av.d_rot[ids])
        t0 = time.perf_counter()
        image, alpha, _ = render_numpy(means, quats, scales, self.opac[ids], self.rgb[ids], info.camera, self.bg)
        seconds = time.perf_counter() - t0
        return (image, seconds, alpha) if with_alpha else (image, seconds)

    def score(self, ids: np.ndarray, ssim: bool = True) -> dict:
        """Mean over the views: PSNR/SSIM in the mask and on the whole image, and mask
        coverage: the fraction of ground-truth mask pixels (mask >= 0.5) whose rendered alpha
        is >= 0.5 (a hole in a prefix shows here even where the background matches)."""
        psnr_m, ssim_m, psnr_w, ssim_w, ms, cov = [], [], [], [], [], []
        for v in self.views:
            image, seconds, alpha = self.render(v, ids, with_alpha=True)
            s = self.dataset[int(v)]
            psnr_m.append(metrics.psnr(image, s.image, s.mask))
            psnr_w.append(metrics.psnr(image, s.image))
            if ssim:
                ssim_m.append(metrics.ssim(image, s.image, s.mask))
                ssim_w.append(metrics.ssim(image, s.image))
            inside = np.asarray(s.mask) >= 0.5
            cov.append(float(np.count_nonzero(alpha[inside] >= 0.5)) / max(int(np.count_nonzero(inside)), 1))
            ms.append(seconds * 1e3)
        nan = float("nan")
        return {"psnr": float(np.mean(psnr_m)), "ssim": float(np.mean(ssim_m)) if ssim else nan,
                "psnr_full_image": float(np.mean(psnr_w)), "ssim_full_image": float(np.mean(ssim_w)) if ssim else nan,
                "coverage": float(np.mean(cov)), "views": len(self.views), "render_ms": float(np.median(ms))}


def random_within_levels(level: np.ndarray, seed: int = 0) -> np.ndarray:
    """A stream order with each level's faces shuffled (the paper's 'W/ Random' ablation).

    Levels still go in order, so parents still precede children.
    """
    rng = np.random.default_rng(seed)
    keys = rng.random(len(level))
    return np.lexsort((keys, level))


def importance_only(importance: np.ndarray) -> np.ndarray:
    """Faces by descending importance ignoring levels (the 'importance-only' ablation)."""
    return np.argsort(-importance, kind="stable")
