"""Small shared builders for tests (meshes and forests made here, not shipped)."""

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


def random_forest(faces, rng, depth=3, frac=0.5, logit_scale=1.0):
    """A forest grown by splitting a random fraction of leaves per level, random logits."""
    from progressive_avatars.core.forest import Forest

    forest = Forest(faces)
    for _ in range(depth):
        leaves = forest.leaves()
        leaves = leaves[forest.level[leaves] == forest.max_level]
        pick = leaves[rng.random(len(leaves)) < frac]
        if len(pick) == 0:
            pick = leaves[:1]
        forest.split(pick)
    forest.split_logits[:] = rng.normal(0, logit_scale, forest.split_logits.shape)
    return forest
