"""The preview's point attributes, flat and C-contiguous for ``foreach_set``: the point layout,
per-Gaussian values that do not change with the frame (linear colours from sRGB), and the
per-frame evaluator the frame-change handler calls. Blender tier (numpy).
"""

from __future__ import annotations

import os

import numpy as np

from ..avatar import binding
from ..avatar.avatar import Avatar, sh_to_rgb, sigmoid


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values (what the avatar learned from PNG images) to linear light."""
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def without_behind(g: dict) -> tuple[dict, int]:
    """(Gaussians, how many left out): the arrays of ``g`` less the Gaussians its ``behind``
    mask draws behind every other (retired backdrop stand-ins, docs/FORMAT.md 2.4), which a
    depth-sorted 3DGS PLY cannot express; ``g`` itself when it has no mask."""
    behind = g.get("behind")
    if behind is None:
        return g, 0
    behind = np.asarray(behind, bool)
    return {k: v[~behind] for k, v in g.items() if k != "behind"}, int(behind.sum())


def preview_order(avatar: Avatar) -> np.ndarray:
    """The face of each preview point, point by point: Gaussians grouped by root face, the
    layout the per-frame evaluator fills without scattering (2.6x faster per frame than
    stream order at 170k Gaussians). The budget still selects by stream rank (the points'
    "rank" attribute), so the layout is free."""
    return binding.root_grouped(avatar.forest)


def static_attributes(avatar: Avatar, order=None) -> dict:
    """Per-Gaussian values that do not change with the frame: activated opacity, RGBA
    colour (linear, as Blender's colour attributes are), level, rank (stream position) and
    retire (a coarse stand-in hides from that many records on, Forest.shown_until + 1; 0:
    never), for the Gaussians ``order`` (default: all, in stream order)."""
    sel = np.arange(avatar.num_gaussians) if order is None else np.asarray(order, np.int64)
    rank = avatar.forest.stream_rank()
    until = avatar.forest.shown_until()
    retire = np.zeros(len(sel), np.int32)
    if until is not None:
        u = until[sel]
        retire = np.where(u < np.iinfo(np.int32).max, u + 1, 0).astype(np.int32)
    rgba = np.ones((len(sel), 4), np.float32)
    rgba[:, :3] = srgb_to_linear(sh_to_rgb(avatar.f_dc[sel]))
    return {
        "opacity": np.ascontiguousarray(sigmoid(avatar.opacity_logit[sel]), np.float32),
        "color": rgba.ravel(),
        "level": avatar.forest.level[sel].astype(np.int32),
        "rank": rank[sel].astype(np.int32),
        "retire": retire,
    }


# Threads of the frame handler's evaluator (GaussianEvaluator's threads): two were faster than
# one at the paper's scale (old against new in the commit that added them); more were not measured.
PREVIEW_THREADS = min(2, os.cpu_count() or 1)


def splat_evaluator(
    avatar: Avatar, count: int | None = None, weights=None, order=None, threads=None
) -> binding.GaussianEvaluator:
    """Per-frame world Gaussians of the faces of the first ``count`` stream records, written at
    their points' rows of the layout ``order`` (faces; default: face order). Outputs are sized for the
    whole avatar so the frame handler can foreach_set full attributes without copies. ``threads``
    (default PREVIEW_THREADS): GaussianEvaluator's, the same bits for any number."""
    total = avatar.num_gaussians
    n = total if count is None else int(min(max(count, 0), total))
    order = np.arange(total) if order is None else np.asarray(order, np.int64)
    rows = None
    if n < total:
        rows = np.flatnonzero(avatar.forest.stream_rank()[order] < n)
        order = order[rows]
    # weights: forest.weights() computed once by the caller; evaluators are rebuilt when the
    # budget changes and the forest walk is the costly part of building one.
    threads = PREVIEW_THREADS if threads is None else threads
    return avatar.evaluator(ids=order, weights=weights, capacity=total, rows=rows, threads=threads)
