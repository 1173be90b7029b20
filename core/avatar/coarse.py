"""Coarse levels above the template, and spread-out orders inside a level (numpy only).

Coarse levels (DESIGN.md 7): triangle meshes coarser than the template whose vertices are a
*subset of the template's vertices*, so every coarse triangle is three template vertices and
moves with the tracked mesh exactly like a template face (same face-local binding). They are
built once, when training starts; the stream carries the triangles (the receiver never
decimates).

Decimation here is a Voronoi-dual remesh on the template's own vertices: pick seed vertices
spread evenly in space (one per occupied voxel, the voxel size found by bisection for the
wanted count), grow geodesic Voronoi cells over the mesh's edge graph from the seeds
(scipy's Dijkstra, compiled), and keep every template triangle whose three corners fall in
three different cells, mapped to those cells' seeds (the dual triangulation of the cells:
one triangle where three cells meet, with the original triangle's winding). Cells grow along
the surface, so lips or eyelids that touch in space are not merged as a voxel clustering
would; the result covers the surface like the template but with about 2 faces per seed.

Spread-out order: `spread_order` ranks points along a Z-order (Morton) curve and then visits
curve positions in bit-reversed order (van der Corput), so every prefix of the order samples
the whole curve, hence the whole head, evenly: no prefix is a patch.
"""

from __future__ import annotations

import numpy as np

# Coarse level sizes as fractions of the template's face count, coarsest first.
DEFAULT_FRACTIONS = (1 / 32, 1 / 16)


def _edge_graph(vertices, faces):
    from scipy.sparse import coo_matrix

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    w = np.maximum(w, 1e-12)  # (scipy drops explicit zeros: keep coincident vertices connected)
    V = len(vertices)
    g = coo_matrix(
        (np.concatenate([w, w]), (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]]))), shape=(V, V)
    )
    return g.tocsr()


def _voxel_seeds(vertices, used, cell):
    """One used vertex per occupied voxel of size `cell`: the one nearest the voxel's mean."""
    v = vertices[used]
    key = np.floor((v - v.min(0)) / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    k = inv.max() + 1
    mean = np.zeros((k, 3))
    np.add.at(mean, inv, v)
    mean /= np.bincount(inv, minlength=k)[:, None]
    d = np.linalg.norm(v - mean[inv], axis=1)
    order = np.lexsort((d, inv))
    first = order[np.r_[True, inv[order][1:] != inv[order][:-1]]]
    return used[first]


def _seeds_for(vertices, used, count):
    """About `count` seed vertices spread evenly in space (voxel size by bisection)."""
    ext = np.ptp(vertices[used], axis=0).max()
    if not ext > 0:  # every vertex in one point: one seed, so no coarse triangle
        return used[:1]
    lo, hi = ext / 4096, ext
    best = None
    for _ in range(40):
        mid = np.sqrt(lo * hi)
        s = _voxel_seeds(vertices, used, mid)
        if best is None or abs(len(s) - count) < abs(len(best) - count):
            best = s
        if len(s) == count:
            break
        if len(s) > count:
            lo = mid
        else:
            hi = mid
    return best


def decimate(vertices, faces, target_faces: int) -> np.ndarray:
    """Triangles [C,3] over a subset of the template's vertices, C about `target_faces`."""
    from scipy.sparse.csgraph import dijkstra

    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    used = np.unique(faces)
    g = _edge_graph(vertices, faces)
    seeds = _seeds_for(vertices, used, max(4, int(round(target_faces / 2))))
    _, _, src = dijkstra(g, directed=False, indices=seeds, min_only=True, return_predecessors=True)
    lab = src[faces]  # seed vertex owning each corner (-9999: unreachable from any seed)
    ok = (lab >= 0).all(1) & (lab[:, 0] != lab[:, 1]) & (lab[:, 1] != lab[:, 2]) & (lab[:, 0] != lab[:, 2])
    tri = lab[ok]
    _, first = np.unique(np.sort(tri, axis=1), axis=0, return_index=True)  # one per vertex set (folds too)
    return np.ascontiguousarray(tri[np.sort(first)], np.int32)


def spread_order(points) -> np.ndarray:
    """Permutation of points [n,3] whose every prefix is spread over the points' extent."""
    p = np.asarray(points, np.float64)
    n = len(p)
    if n <= 1:
        return np.arange(n, dtype=np.int64)
    lo, span = p.min(0), np.maximum(np.ptp(p, axis=0), 1e-30)
    q = np.minimum((p - lo) / span * 1024, 1023).astype(np.uint64)  # 10 bits per axis
    code = np.zeros(n, np.uint64)
    for b in range(10):  # Morton interleave, per bit (10 passes over all points)
        for k in range(3):
            code |= ((q[:, k] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + k)
    along = np.empty(n, np.int64)
    along[np.lexsort((np.arange(n), code))] = np.arange(n)  # position on the curve
    bits = int(n - 1).bit_length()
    rev = np.zeros(n, np.int64)
    for b in range(bits):  # bit reversal of the curve position (van der Corput)
        rev |= ((along >> b) & 1) << (bits - 1 - b)
    return np.argsort(rev, kind="stable").astype(np.int64)


def centroids(vertices, tris) -> np.ndarray:
    v = np.asarray(vertices, np.float64)
    return v[np.asarray(tris, np.int64)].mean(axis=1)


def _same_triangles(a, b) -> bool:
    key = lambda t: np.unique(np.sort(np.asarray(t, np.int64), axis=1), axis=0)  # noqa: E731
    return len(a) == len(b) and np.array_equal(key(a), key(b))


def build_coarse(vertices, faces, fractions=DEFAULT_FRACTIONS):
    """(coarse_faces [C,3], counts per coarse level) for a template, coarsest level first;
    each level's rows in spread-out order. Empty fractions: no coarse levels."""
    faces = np.asarray(faces, np.int64)
    tris, counts = [], []
    for fr in sorted(float(f) for f in fractions):
        if not 0 < fr < 1:
            raise ValueError(f"coarse level fractions must be in (0, 1), got {fr}")
        t = decimate(vertices, faces, max(4, int(round(fr * len(faces)))))
        # A level no coarser than the template, or the same triangles as the level before (tiny
        # templates: both fractions round to the minimum), would only repeat Gaussians.
        if len(t) == 0 or len(t) >= len(faces) or (tris and _same_triangles(t, tris[-1])):
            continue
        t = t[spread_order(centroids(vertices, t))]
        tris.append(t)
        counts.append(len(t))
    if not tris:
        return np.zeros((0, 3), np.int32), ()
    return np.concatenate(tris).astype(np.int32), tuple(counts)


def stand_in_regions(vertices, coarse_faces, coarse_counts, template_faces) -> np.ndarray:
    """[F0, K] the coarse row (index into ``coarse_faces``) whose region holds each template
    face, per coarse level: the level's triangle with the nearest centroid on the rest-pose
    ``vertices``. A stand-in makes way once every template face of its region has arrived."""
    v = np.asarray(vertices, np.float64)
    tc = centroids(v, template_faces)
    starts = np.concatenate([[0], np.cumsum(np.asarray(coarse_counts, np.int64))])
    out = np.empty((len(tc), len(coarse_counts)), np.int64)
    for k in range(len(coarse_counts)):
        cc = centroids(v, np.asarray(coarse_faces)[starts[k] : starts[k + 1]])
        for a in range(0, len(tc), 4096):  # [4096, C_k] distances at a time
            d = ((tc[a : a + 4096, None, :] - cc[None, :, :]) ** 2).sum(-1)
            out[a : a + 4096, k] = starts[k] + np.argmin(d, axis=1)
    return out
