"""Face importance W_i = Σ_views Σ_pixels α·T of the face's Gaussian (DESIGN.md §5).

The rasteriser's forward pass returns the per-Gaussian contribution directly, so ranking
needs no autograd: numpy + the compiled CPU kernels (or any render_numpy backend).
"""

from __future__ import annotations

import numpy as np

from ..avatar.avatar import Avatar, sh_to_rgb, sigmoid


def view_subset(n_views: int, max_views: int | None) -> np.ndarray:
    """Evenly spread view indices (deterministic), all of them when max_views is None."""
    if max_views is None or max_views >= n_views:
        return np.arange(n_views)
    return np.unique(np.linspace(0, n_views - 1, max_views).round().astype(int))


def face_importance(avatar: Avatar, dataset, max_views: int | None = 120, progress: bool = True) -> np.ndarray:
    """Importance per face [N] (float64) summed over (a spread subset of) the dataset's views."""
    from tqdm import tqdm

    from .rasterize import render_numpy

    evaluator = avatar.evaluator()
    opac = sigmoid(avatar.opacity_logit)
    rgb = sh_to_rgb(avatar.f_dc)
    W = np.zeros(avatar.num_gaussians)
    bg = np.asarray(dataset.background, np.float32)
    for i in tqdm(view_subset(len(dataset), max_views), desc="importance", disable=not progress):
        info = dataset.frame_info(int(i))
        means, quats, scales = evaluator(dataset.vertices_at(info.timestep_index))
        _, _, contrib = render_numpy(means, quats, scales, opac, rgb, info.camera, bg)
        W += contrib
    return W
