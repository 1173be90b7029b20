"""Face importance W_i = Σ_views Σ_pixels α·T of the face's Gaussian (DESIGN.md §5).

The stream orders faces by W inside each level, so W matters only for prefixes that end inside
a face's level: those render every coarser level and part of the face's own, never the finer
ones. By default W_i is therefore measured on the render of the levels up to face i's own
("per level"), not on the whole avatar (the paper's): in the whole avatar a coarse face is
partly hidden and partly replaced by its descendants, which ranks low exactly the coarse faces
a short prefix needs most (docs/BENCHMARKS.md, issue 16 sections: "ranking inside levels").
The whole-avatar importance stays available (``per_level=False``) for the paper's
importance-only ablation, whose ranking crosses levels.

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


def face_importance(
    avatar: Avatar, dataset, max_views: int | None = 120, progress: bool = True, per_level: bool = True
) -> np.ndarray:
    """Importance per face [N] (float64) summed over (a spread subset of) the dataset's views:
    each face's α·T in the render of the levels up to its own (``per_level``, one render per
    level and view), or in the render of the whole avatar."""
    from tqdm import tqdm

    from .rasterize import render_numpy

    evaluator = avatar.evaluator()
    opac = sigmoid(avatar.opacity_logit)
    rgb = sh_to_rgb(avatar.f_dc)
    W = np.zeros(avatar.num_gaussians)
    bg = np.asarray(dataset.background, np.float32)
    level = avatar.forest.level
    # (faces rendered, which of them are scored) per render: levels <= l and level l.
    if per_level and avatar.num_gaussians:
        renders = [(np.flatnonzero(level <= lv), level[level <= lv] == lv) for lv in np.unique(level)]
    else:
        renders = [(np.arange(avatar.num_gaussians), np.ones(avatar.num_gaussians, bool))]
    for i in tqdm(view_subset(len(dataset), max_views), desc="importance", disable=not progress):
        info = dataset.frame_info(int(i))
        means, quats, scales = evaluator(dataset.vertices_at(info.timestep_index))
        for faces, scored in renders:
            _, _, contrib = render_numpy(
                means[faces], quats[faces], scales[faces], opac[faces], rgb[faces], info.camera, bg
            )
            W[faces[scored]] += contrib[scored]
    return W
