"""Budget sweeps and reports: quality against bytes for a progressive avatar.

An avatar here is in STREAM ORDER (core.stream.read_stream), so the Gaussians of a budget
are a prefix: faces [0, count). Metrics are PSNR/SSIM inside the foreground mask and on the
whole image (core.train.metrics), on the dataset's val (novel view, NVS) and test (novel
expression, NES) splits.
"""

from __future__ import annotations

import time

import numpy as np

from ..train import metrics
from ..avatar.avatar import Avatar, sh_to_rgb, sigmoid
from ..avatar.binding import compose, evaluate


class SplitRenderer:
    """Renders face subsets of one avatar on the views of one dataset split."""

    def __init__(self, avatar: Avatar, dataset, max_views: int | None = 32):
        from ..render.importance import view_subset

        self.avatar, self.dataset = avatar, dataset
        self.views = view_subset(len(dataset), max_views)
        self.weights = avatar.forest.weights()
        self.opac = sigmoid(avatar.opacity_logit)
        self.rgb = sh_to_rgb(avatar.f_dc)
        self.bg = np.asarray(dataset.background, np.float32)

    def render(self, view: int, ids: np.ndarray):
        from ..render.rasterize import render_numpy

        info = self.dataset.frame_info(int(view))
        verts = self.dataset.vertices_at(info.timestep_index)
        av = self.avatar
        geo = evaluate(av.forest, verts, ids=ids, weights=self.weights)
        means, scales, quats = compose(geo.t, geo.r, geo.s, av.d_mu[ids], av.d_log_scale[ids], av.d_rot[ids])
        t0 = time.perf_counter()
        image, _, _ = render_numpy(means, quats, scales, self.opac[ids], self.rgb[ids], info.camera, self.bg)
        return image, time.perf_counter() - t0

    def score(self, ids: np.ndarray) -> dict:
        psnr_m, ssim_m, psnr_w, ssim_w, ms = [], [], [], [], []
        for v in self.views:
            image, seconds = self.render(v, ids)
            s = self.dataset[int(v)]
            psnr_m.append(metrics.psnr(image, s.image, s.mask))
            ssim_m.append(metrics.ssim(image, s.image, s.mask))
            psnr_w.append(metrics.psnr(image, s.image))
            ssim_w.append(metrics.ssim(image, s.image))
            ms.append(seconds * 1e3)
        return {"psnr": float(np.mean(psnr_m)), "ssim": float(np.mean(ssim_m)),
                "psnr_full_image": float(np.mean(psnr_w)), "ssim_full_image": float(np.mean(ssim_w)),
                "views": len(self.views), "render_ms": float(np.median(ms))}


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
