"""Stream order: the roots level by level in a chosen order, then each level by descending
importance (versions 2-4), or the coarse levels and then every face by importance once its
parent is sent (version 5). Numpy only: runs in Blender."""

from __future__ import annotations

import numpy as np

from ..avatar.forest import Forest


ROOT_ORDERS = ("forest", "spatial", "importance", "both", "auto")


def root_keys(forest: Forest, how: str = "forest", importance=None, vertices=None):
    """Sort key (ascending) of each root inside its level, or None for the forest's order.

    forest: as the forest holds them (trained avatars: spread-out, core/avatar/coarse.py; older ones:
    template order). spatial: spread-out order of the roots' centroids on `vertices` (a rest
    pose). importance: descending importance. both: the spatial order's dyadic blocks (the
    first 1, 1, 2, 4, 8, ... roots: each block spread over the head) with every block sorted by
    descending importance. auto: importance in every root level when it is given, else
    spatial. Measured in docs/BENCHMARKS.md (issue 16, "Order of the roots"): with importance
    measured per level (core/render/importance.py: level 0's on level 0 alone) it beats the
    spatial order also in level 0, in PSNR and in coverage, on the three heads measured; with
    whole-avatar importance, level 0 had been better spatial."""
    if how not in ROOT_ORDERS:
        raise ValueError(f"root order must be one of {ROOT_ORDERS}, got {how!r}")
    if how == "forest":
        return None
    R = forest.num_roots
    lv = forest.level[:R]
    if how == "auto":
        how = "spatial" if importance is None else "importance"
    if how in ("spatial", "both"):
        rank = np.arange(R, dtype=np.float64)
        if vertices is not None:
            from ..avatar.coarse import centroids, spread_order

            cen = centroids(vertices, forest.root_faces)
            for level in np.unique(lv):  # per root level
                ids = np.flatnonzero(lv == level)
                rank[ids[spread_order(cen[ids])]] = np.arange(len(ids))
        else:  # the forest's order within each level
            for level in np.unique(lv):
                ids = np.flatnonzero(lv == level)
                rank[ids] = np.arange(len(ids))
        if how == "spatial":
            return rank
    if importance is None:
        raise ValueError(f"root order {how!r} needs the faces' importance")
    imp = np.asarray(importance, np.float64)[:R]
    top = max(float(imp.max()), 1e-300) if R else 1.0
    if how == "importance":
        return -imp
    return np.floor(np.log2(rank + 1.0)) + 0.999 * (1.0 - np.clip(imp / top, 0.0, 1.0))


def _importance(importance, n: int, who: str) -> np.ndarray:
    key = np.asarray(importance, np.float64).reshape(-1)
    if len(key) != n:
        raise ValueError(f"{who}: importance has {len(key)} values for {n} faces")
    if not np.all(np.isfinite(key)):
        raise ValueError(f"{who}: importance contains NaN or inf")
    return key


def stream_order(forest: Forest, importance=None, root_key=None) -> np.ndarray:
    """Permutation (new position -> old face): the roots level by level (coarse levels, then
    the template level), each by ascending `root_key` (default: the forest's order), then each
    further level by descending importance, ties by face index. Parents precede children
    since levels do."""
    N = forest.num_faces
    key = np.zeros(N) if importance is None else _importance(importance, N, "stream_order")
    R = forest.num_roots
    key = -key
    key[:R] = 0.0 if root_key is None else np.asarray(root_key, np.float64)[:R]
    idx = np.arange(N)
    return np.lexsort((idx, key, forest.level)).astype(np.int64)


def interleaved_order(forest: Forest, importance, root_key=None) -> np.ndarray:
    """Permutation (new position -> face) that opens with the coarse levels (the template
    level when there are none), level by level by ascending `root_key` as stream_order, and
    then sends every other face, template faces included, by descending importance as soon as
    its parent has been sent: the greedy order under "parent before child", i.e. descending
    ``min(importance, the parent's key)`` (ties: lower level, then face index). The coarse
    levels keep every prefix a whole head, so unimportant template faces can wait behind the
    important faces of the levels below them. The stream order of version 5 (docs/FORMAT.md)."""
    key = _importance(importance, forest.num_faces, "interleaved_order")
    lead = max(forest.num_coarse_levels, 1)
    level = forest.level.astype(np.int64)
    head = stream_order(forest, key, root_key)[: int(np.count_nonzero(level < lead))]  # they lead it too
    eff = key.copy()
    for lv in range(lead + 1, int(level.max(initial=lead)) + 1):  # parents' keys are final before their children's
        ids = np.flatnonzero(level == lv)
        eff[ids] = np.minimum(key[ids], eff[forest.parent[ids]])
    rest = np.flatnonzero(level >= lead)
    rest = rest[np.lexsort((rest, level[rest], -eff[rest]))]
    return np.concatenate([head, rest]).astype(np.int64)
