"""Face importance W_i = Σ_views Σ_pixels α·T of the face's Gaussian (DESIGN.md §5).

The stream orders faces by W inside each level, so W matters only for prefixes that end inside
a face's level: those render every coarser level and part of the face's own, never the finer
ones. By default W_i is therefore measured on the render of the levels up to face i's own
("per level"), not on the whole avatar (the paper's): in the whole avatar a coarse face is
partly hidden and partly replaced by its descendants, which ranks low exactly the coarse faces
a short prefix needs most (docs/BENCHMARKS.md, issue 16 sections: "ranking inside levels").
The whole-avatar importance stays available (``per_level=False``) for the paper's
importance-only ablation, whose ranking crosses levels.

Per level, each pixel's α·T is by default weighted by what the coarser prefix gets wrong there
(``weighting="residual"``: the mean absolute difference between the ground-truth image and the
render of the levels below the face's own; level 0 against the bare background). A face that
repeats what the coarser levels already show ranks below one that fixes what they miss. Against
plain α·T per level (``weighting="alpha"``), measured on the default, the coarse-template and the
paper-scale head (docs/BENCHMARKS.md, "ranking inside levels"): +0.3 to +0.9 dB at 3 % of the
stream, up to +1.1 dB at 1-2 %, nothing lost at the level ends.

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


WEIGHTINGS = ("residual", "alpha")


def face_importance(
    avatar: Avatar,
    dataset,
    max_views: int | None = 120,
    progress: bool = True,
    per_level: bool = True,
    weighting: str = "residual",
) -> np.ndarray:
    """Importance per face [N] (float64) summed over (a spread subset of) the dataset's views:
    each face's α·T in the render of the levels up to its own (``per_level``, one render per
    level and view; ``weighting`` "residual": each pixel weighted by the error of the levels
    below, which needs the dataset's images), or in the render of the whole avatar (plain α·T)."""
    from tqdm import tqdm

    from .rasterize import render_numpy

    if weighting not in WEIGHTINGS:
        raise ValueError(f"importance weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    residual = per_level and weighting == "residual"
    evaluator = avatar.evaluator()
    opac = sigmoid(avatar.opacity_logit)
    rgb = sh_to_rgb(avatar.f_dc)
    W = np.zeros(avatar.num_gaussians)
    bg = np.asarray(dataset.background, np.float32)
    level = avatar.forest.level
    # (faces rendered, which of them are scored) per render: levels <= l and level l.
    # Per level, coarse stand-ins (Forest.drawn) stay in every render, as cumulative coarse
    # levels do: a face sent early arrives while the stand-ins of its region still show.
    # (Leaving them out of the subdivision levels' renders measured no better: 5 % of the
    # coarse-template head's stream 21.49 against 21.53 dB, seed 0, 16 views, stand-ins retired
    # with their region's last template face.) The whole avatar, the paper's importance, leaves
    # them out as the finished avatar does, or keeps them behind the rest (Forest.render_set).
    if per_level and avatar.num_gaussians:
        renders = [(np.flatnonzero(level <= lv), level[level <= lv] == lv, None) for lv in np.unique(level)]
    else:
        faces, behind = avatar.forest.render_set()
        renders = [(faces, np.ones(len(faces), bool), behind)]
    for i in tqdm(view_subset(len(dataset), max_views), desc="importance", disable=not progress):
        info = dataset.frame_info(int(i))
        means, quats, scales = evaluator(dataset.vertices_at(info.timestep_index))
        if residual:
            target = np.asarray(dataset[int(i)].image, np.float64)
            below = np.broadcast_to(bg.astype(np.float64), target.shape)  # nothing rendered yet
        for faces, scored, behind in renders:
            weight = np.abs(target - below).mean(-1) if residual else None
            image, _, contrib = render_numpy(
                means[faces], quats[faces], scales[faces], opac[faces], rgb[faces], info.camera, bg, pixel_weight=weight,
                behind=behind,
            )  # fmt: skip
            W[faces[scored]] += contrib[scored]
            if residual:
                below = image.astype(np.float64)
    return W
