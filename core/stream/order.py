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
    first 1, 2, 4, 8, ... roots: each block spread over the head) with every block sorted by
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
    then sends every other face, template faces included, as soon as its parent has been sent,
    in the order that brings the most importance per record under "parent before child". The
    stream order of version 5 (docs/FORMAT.md).

    A face's worth is its importance, but a face worth nothing can open a subtree worth much:
    after training, a parent whose children took over its region is nearly transparent (with
    the opacity reset most inner faces end so), and ranking it by its own importance (as the
    first version 5 writer did, by ``min(importance, the parent's key)``) held its whole subtree
    to the end of the stream. So faces are sent in *units* (Horn's rule for sequencing under a
    tree precedence): bottom-up, a face's unit takes its children's units in descending ratio
    (importance per record) while each one's ratio beats the unit's so far; units then go by
    descending ratio, a unit never before the one that holds its parent (its ratio capped by
    that one's; ties: the shallower unit first), and inside a unit the face first, then its
    merged children's units in the order they were taken, depth first. Levels are few, so the
    loops here run per level, vectorised over its faces."""
    key = _importance(importance, forest.num_faces, "interleaved_order")
    N = forest.num_faces
    lead = max(forest.num_coarse_levels, 1)
    level = forest.level.astype(np.int64)
    parent = forest.parent
    head = stream_order(forest, key, root_key)[: int(np.count_nonzero(level < lead))]  # they lead it too
    top = int(level.max(initial=lead))
    w = np.maximum(key, 0.0)  # a unit's importance and records
    n = np.ones(N)
    merged = np.zeros(N, bool)  # taken into its parent's unit
    rank = np.zeros(N, np.int64)  # the order it was taken in
    for lv in range(top, lead, -1):  # children's units are final before their parents'
        ids = np.flatnonzero(level == lv)
        par = parent[ids]
        o = np.lexsort((ids, -(w[ids] / n[ids]), par))  # per parent, by descending ratio
        ids, par = ids[o], par[o]
        start = np.r_[True, par[1:] != par[:-1]] if len(ids) else np.zeros(0, bool)
        first = np.flatnonzero(start)
        group = np.cumsum(start) - 1
        cw, cn = np.cumsum(w[ids]), np.cumsum(n[ids])
        before_w = cw - w[ids] - np.r_[0.0, cw][first][group]  # the earlier siblings' sums
        before_n = cn - n[ids] - np.r_[0.0, cn][first][group]
        beats = w[ids] * (n[par] + before_n) > (w[par] + before_w) * n[ids]
        fails = np.cumsum(~beats)
        take = fails == np.r_[0, fails][first][group]  # until the first sibling that does not beat it
        merged[ids] = take
        rank[ids] = np.arange(len(ids)) - first[group]
        np.add.at(w, par[take], w[ids[take]])
        np.add.at(n, par[take], n[ids[take]])
    unit = np.arange(N)  # the face heading each face's unit
    # Depth-first position inside the unit: one digit per level below the lead (0: not on the
    # path, else the rank among the merged siblings + 1), compared shallow first. (A base-4
    # number in int64 overflowed 33 levels down and put a child before its parent.)
    path = np.zeros((N, max(top - lead, 0)), np.int8)
    ratio = w / n
    for lv in range(lead + 1, top + 1):
        ids = np.flatnonzero(level == lv)
        m = ids[merged[ids]]
        unit[m] = unit[parent[m]]
        path[m] = path[parent[m]]
        path[m, lv - lead - 1] = rank[m] + 1
        h = ids[~merged[ids]]
        ratio[h] = np.minimum(ratio[h], ratio[unit[parent[h]]])
    rest = np.flatnonzero(level >= lead)
    u = unit[rest]
    digits = [path[rest, c] for c in range(path.shape[1] - 1, -1, -1)]  # lexsort: last key first
    rest = rest[np.lexsort((*digits, u, level[u], -ratio[u]))]
    return np.concatenate([head, rest]).astype(np.int64)
