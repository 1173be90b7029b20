"""Small shape and forest builders for tests and benchmarks (meshes and forests made here, not shipped)."""

import numpy as np


def sphere_mesh(n_lat=24, n_lon=32, radius=0.1):
    """A closed UV sphere (poles as single vertices), metres; faces wound outward."""
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    ring = np.stack([np.sin(la) * np.cos(lo), np.cos(la), np.sin(la) * np.sin(lo)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]]) * radius
    idx = 1 + np.arange((n_lat - 1) * n_lon).reshape(n_lat - 1, n_lon)
    nxt = np.roll(idx, -1, axis=1)
    top = np.stack([np.zeros(n_lon, int), nxt[0], idx[0]], -1)
    bottom = np.stack([np.full(n_lon, len(verts) - 1), idx[-1], nxt[-1]], -1)
    a, b, c, d = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    quads = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return verts.astype(np.float64), np.concatenate([top, quads, bottom]).astype(np.int32)


def random_forest(faces, rng, depth=3, frac=0.5, logit_scale=1.0, coarse_from=None, stand_ins=False):
    """A forest grown by splitting a random fraction of leaves per level, random logits.
    With `coarse_from` (the vertices) it also has two coarse levels (core/avatar/coarse.py) and its
    template roots in spread-out order, as a trained avatar; `stand_ins`: those coarse faces are
    stand-ins (Forest.drawn), as training makes them by default, rather than cumulative levels."""
    from ..avatar.forest import Forest

    if coarse_from is None:
        forest = Forest(faces)
    else:
        from ..avatar import coarse

        cf, counts = coarse.build_coarse(coarse_from, faces, (0.25, 0.5))
        assert len(counts) == 2
        ref = np.concatenate([np.arange(len(cf)), len(cf) + coarse.spread_order(coarse.centroids(coarse_from, faces))])
        forest = Forest(faces, coarse_faces=cf, coarse_counts=counts, root_ref=ref, stand_ins=stand_ins)
    for _ in range(depth):
        leaves = forest.splittable()
        leaves = leaves[forest.level[leaves] == forest.max_level]
        pick = leaves[rng.random(len(leaves)) < frac]
        if len(pick) == 0:
            pick = leaves[:1]
        forest.split(pick)
    forest.split_logits[:] = rng.normal(0, logit_scale, forest.split_logits.shape)
    return forest


def depth6_precision(rng, n_roots=40):
    """float32 against float64 on the finest faces of a depth-6 forest over a FLAME-sized
    sphere (metres): max errors relative to each face's own scale, and the median scale."""
    from ..avatar import binding
    from ..avatar.forest import Forest

    verts, faces = sphere_mesh(70, 72, radius=0.1)  # ~5k vertices, ~10k faces
    forest = Forest(faces)
    current = rng.choice(len(faces), n_roots, replace=False)
    for _ in range(6):
        current = forest.split(current).ravel()
    forest.split_logits[:] = rng.normal(0, 1.0, forest.split_logits.shape)
    finest = np.flatnonzero(forest.level == 6)
    v32 = (verts + rng.normal(0, 1e-3, verts.shape)).astype(np.float32)
    W = forest.weights()
    g32 = binding.evaluate(forest, v32, ids=finest, weights=W, dtype=np.float32, with_vertices=True)
    g64 = binding.evaluate(forest, v32.astype(np.float64), ids=finest, weights=W, dtype=np.float64, with_vertices=True)
    scale = g64.s
    return {
        "edges": float((np.abs(g32.edges - g64.edges).max(axis=(1, 2)) / scale).max()),
        "frames": float(np.abs(g32.r - g64.r).max()),
        "scales": float((np.abs(g32.s - g64.s) / scale).max()),
        "median_scale": float(np.median(scale)),
        "roots": len(faces),
    }
