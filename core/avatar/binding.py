"""Face-local frames and Gaussian binding (numpy only: runs inside Blender).

For a triangle (v0, v1, v2) (GaussianAvatars' convention):
  x = normalize(v1 - v0); y = normalize(x × (v2 - v0)) (the normal); z = x × y
  (= -normalize(y × x)); r = [x | y | z] (columns); s = (|v1 - v0| + |z · (v2 - v0)|) / 2;
  t = centroid.
A Gaussian bound to the face: μ = s·r·Δμ + t, S = s·exp(ΔS_log), R = r ⊗ ΔR.
Quaternions are wxyz (Hamilton product, rotating column vectors).

Degenerate faces get deterministic fallbacks: a zero first edge takes the second edge (or
the world x axis) as x; a zero normal takes the world axis least aligned with x to build y.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .forest import Forest
from ..geometry.gaussians import Gaussians
from ..geometry.rotations import quat_multiply, quat_normalize, quat_rows as _quat_rows, quat_to_rotmat, rotmat_to_quat  # noqa: F401

MIN_SCALE = 1e-10  # metres; keeps degenerate faces' Gaussians valid (positive scale)
MIN_EDGE = 1e-15  # metres; shorter edges count as zero (their direction, and its gradient, is noise)


# -- quaternions --------------------------------------------------------------------------


# -- face frames --------------------------------------------------------------------------
def _unit(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    return v / np.where(n > 0, n, 1)[..., None]


def _unit_norm(v: np.ndarray):
    """(unit vector, length), scaled by the largest component first so tiny vectors (whose
    squares underflow in float32) still normalise to length 1."""
    m = np.max(np.abs(v), axis=-1)
    u = v / np.where(m > 0, m, 1)[..., None]
    n = np.sqrt(np.sum(u * u, axis=-1))
    return _unit(u, n), n * m


def frames_from_edges(e1: np.ndarray, e2: np.ndarray, normal: np.ndarray | None = None, eps: float | None = None):
    """Face frames r [...,3,3] and scales s [...] from edges e1 = v1 - v0, e2 = v2 - v0.

    `normal` (unnormalised) may be supplied when it is known more precisely than x × e2:
    every descendant of a root face is coplanar with it and has the root's normal, which
    stays well conditioned when the small face is a sliver. `eps`: the flatness bound
    (default 8 eps of the edges' precision).
    """
    dtype = e1.dtype
    if eps is None:
        eps = 8 * np.finfo(dtype).eps
    u1, n1 = _unit_norm(e1)
    u2, n2 = _unit_norm(e2)
    axis_x = np.zeros_like(e1)
    axis_x[..., 0] = 1
    x = np.where((n1 > MIN_EDGE)[..., None], u1, np.where((n2 > MIN_EDGE)[..., None], u2, axis_x))
    own_hat, own_n = _unit_norm(np.cross(x, e2))
    own_flat = (n2 <= MIN_EDGE) | (own_n <= eps * n2)
    if normal is None:
        y, flat = own_hat, own_flat
    else:
        # Remove the tiny out-of-plane part rounding leaves in x, so r stays orthonormal.
        n_hat, nn = _unit_norm(normal)
        good = nn > MIN_EDGE * MIN_EDGE
        x_in = x - np.sum(x * n_hat, axis=-1, keepdims=True) * n_hat
        x = np.where(good[..., None], _unit_norm(x_in)[0], x)
        # A face whose edges vanish inside a good root still takes the root's normal.
        y = np.where(good[..., None], n_hat, own_hat)
        flat = ~good & own_flat
    # Fallback normal: perpendicular to x, built from the world axis least aligned with x.
    least = np.argmin(np.abs(x), axis=-1)
    helper = np.zeros_like(x)
    np.put_along_axis(helper, least[..., None], 1, axis=-1)
    alt = _unit_norm(np.cross(x, helper))[0]
    y = np.where(flat[..., None], alt, y)
    z = np.cross(x, y)
    r = np.stack([x, y, z], axis=-1)
    s = 0.5 * (n1 + np.abs(np.sum(z * e2, axis=-1)))
    return r, np.maximum(s, MIN_SCALE).astype(dtype)


def face_frames(v0: np.ndarray, v1: np.ndarray, v2: np.ndarray):
    """(t, r, s) for triangles given by their vertices [...,3] (world-space formula)."""
    r, s = frames_from_edges(v1 - v0, v2 - v0)
    return (v0 + v1 + v2) / 3, r, s


@dataclass
class FaceGeometry:
    t: np.ndarray  # [T,n,3] centroids
    r: np.ndarray  # [T,n,3,3] frames (columns x, normal, z)
    s: np.ndarray  # [T,n] scales
    vertices: np.ndarray | None = None  # [T,n,3,3] the faces' vertices, when asked for
    edges: np.ndarray | None = None  # [T,n,2,3] v1 - v0, v2 - v0 (precise), with the vertices


def _scaled_norm_rows(v, out, tmp):
    """Column lengths of component-major rows v [3,n] into out [n], squaring v / max|v|
    (tmp [3,n] is scratch) so that neither huge nor tiny vectors over- or underflow."""
    np.abs(v, out=tmp)
    m = tmp.max(axis=0)
    m_safe = np.where(m > 0, m, 1)
    np.divide(v, m_safe, out=tmp)
    np.einsum("ij,ij->j", tmp, tmp, out=out)
    np.sqrt(out, out=out)
    out *= m


def _cross_rows(a, b, out, tmp):
    """out = a × b for component-major [3,n] rows, with a scratch row tmp [n]."""
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(a[i], b[j], out=out[k])
        np.multiply(a[j], b[i], out=tmp)
        out[k] -= tmp


def root_grouped(forest: Forest, ids=None) -> np.ndarray:
    """Face ids (all, or the given ones) stably reordered so faces of one root are adjacent:
    the fast gather order for FaceEvaluator (GaussianEvaluator uses it internally)."""
    ids = np.arange(forest.num_faces) if ids is None else np.asarray(ids, np.int64)
    return ids[np.argsort(forest.root[ids], kind="stable")]


class _PlaneEvaluator:
    """What both evaluators share: each face worked out in its root's plane.

    Every descendant lies in its root's plane and shares its normal, so per frame there is
    one pass over the root faces (origin v0, axes x, normal, z, and the root triangle's 2D
    shape |E1|, E2·x, E2·z) and then a few scalar operations per face on contiguous rows:
    the face's first edge direction in the plane (cos, sin), its scale s and its centroid's
    plane coordinates. Edges come from weight differences times root edges, so deep (tiny)
    faces keep float32 precision. Faces under degenerate roots, and faces whose own first
    edge vanishes, are flagged for the general 3D path.

    Faces are worked on in chunks whose scratch rows stay in cache (32k faces ran 10 % faster
    than whole 170k-face rows; 8k was slower from per-call overhead). When the faces come
    grouped by root the per-root rows are gathered with np.repeat, several times faster than
    np.take. Threads (GaussianEvaluator's ``threads``) pay only with chunks of ~40k faces and
    more: with 32k-face chunks the GIL hand-overs between passes took what they saved.
    """

    CHUNK = 32768
    ROOT_ROWS = 15  # v0, x, normal, z (3 each), |E1|, E2·x, E2·z
    SCRATCH_ROWS = 26

    def __init__(self, forest: Forest, ids=None, weights=None, dtype=np.float32, chunk=None):
        self.forest = forest
        self.dtype = np.dtype(dtype)
        W = forest.weights() if weights is None else np.asarray(weights)
        root = forest.root
        if ids is not None:
            ids = np.asarray(ids, np.int64)
            W, root = W[ids], root[ids]
        self.root = np.ascontiguousarray(root)
        self.W = W.astype(self.dtype)
        self._W64 = np.asarray(W, np.float64)  # faces under degenerate roots (_exact)
        self._vt = None  # the last frame's vertices [3,V] (_roots)
        n = len(self.root)
        self.n = n
        # Per face, in units of its root's edges E1, E2: the two edges and the centroid.
        Wd = np.asarray(W, np.float64)
        centroid = Wd[:, 0, 1:] + (Wd[:, 1, 1:] + Wd[:, 2, 1:]) / 3
        self._coef = np.ascontiguousarray(
            np.stack([Wd[:, 1, 1], Wd[:, 1, 2], Wd[:, 2, 1], Wd[:, 2, 2], centroid[:, 0], centroid[:, 1]]), self.dtype
        )
        self._tri = np.ascontiguousarray(np.asarray(forest.root_faces, np.int64).T)  # [3,R]: coarse and template roots
        self._pack = None
        chunk = int(chunk or self.CHUNK)
        grouped = n > 0 and bool(np.all(self.root[1:] >= self.root[:-1]))
        self._chunks = []
        for a in range(0, n, chunk):
            b = min(a + chunk, n)
            runs = None
            if grouped:
                first = int(self.root[a])
                runs = (first, np.bincount(self.root[a:b] - first))
            self._chunks.append((slice(a, b), runs))
        self._scratch = np.empty((self.SCRATCH_ROWS, min(chunk, n)), self.dtype)

    def _roots(self, verts):
        """Per root face, component-major rows (see ROOT_ROWS) in a reused buffer, whether the
        root is a proper triangle, and its v0, E1, E2 [F0,3]."""
        verts = np.asarray(verts, dtype=self.dtype)
        if verts.ndim != 2 or verts.shape[1] != 3:
            raise ValueError(f"{type(self).__name__}: vertices must be [V,3], got {np.shape(verts)}")
        tri = self._tri
        if tri.size and tri.max() >= len(verts):
            raise ValueError(f"{type(self).__name__}: template needs {tri.max() + 1} vertices, got {len(verts)}")
        F0 = tri.shape[1]
        if self._pack is None:
            self._pack = np.empty((self.ROOT_ROWS, F0), self.dtype)
            self._root_tmp = np.empty((3, F0), self.dtype)
            self._root_scr = np.empty((3, F0), self.dtype)
        pack, (t0, t1, t2), scr = self._pack, self._root_tmp, self._root_scr
        eps = 8 * np.finfo(self.dtype).eps
        vt = self._vt = np.ascontiguousarray(verts.T)  # [3,V]: rows are contiguous, so are the gathers below
        v0, xr, nh, zr = pack[0:3], pack[3:6], pack[6:9], pack[9:12]
        L, a, b = pack[12], pack[13], pack[14]
        for k in range(3):
            np.take(vt[k], tri[0], out=v0[k])
        E1 = np.take(vt, tri[1], axis=1)
        E1 -= v0
        E2 = np.take(vt, tri[2], axis=1)
        E2 -= v0
        _cross_rows(E1, E2, nh, t0)  # the normal, unnormalised
        # Lengths scaled by the largest component before squaring, as in the torch path: the
        # normal is quadratic in the edges, so at absurd unit scales its square over- or
        # underflows float32 (1e20 m edges: inf; 1e-12 m: 0) and the frame would be garbage.
        _scaled_norm_rows(E1, L, scr)
        _scaled_norm_rows(nh, t1, scr)  # |normal|
        _scaled_norm_rows(E2, t2, scr)  # |E2|
        t2 *= eps
        # |normal| > eps |E1| |E2|, divided through by |E1| so the product cannot overflow.
        # (the thresholds of training's binding_kernels._root_frame, so both bind the same roots)
        good = (L > MIN_EDGE) & (t1 > MIN_EDGE * MIN_EDGE) & (t1 / np.where(L > 0, L, 1) > t2)
        L_safe = L
        if not good.all():
            L_safe = np.where(good, L, 1)
            t1[~good] = 1
        np.divide(E1, L_safe, out=xr)
        np.divide(nh, t1, out=nh)
        _cross_rows(xr, nh, zr, t0)
        np.einsum("ij,ij->j", E2, xr, out=a)
        np.einsum("ij,ij->j", E2, zr, out=b)
        return pack, good, v0.T, E1.T, E2.T

    def _gather(self, pack, sl, runs, out):
        """Rows of pack for faces sl: a fresh block from np.repeat, or gathered into out."""
        if runs is not None:
            first, counts = runs
            return np.repeat(pack[:, first : first + len(counts)], counts, axis=1)
        root = self.root[sl]
        for row in range(len(pack)):  # 1-D takes are far faster than one 2-D take along axis 1
            np.take(pack[row], root, out=out[row])
        return out

    def _plane(self, g, sl, scratch, s):
        """From gathered root rows g: cos, sin of the face's first edge against the root's x
        axis, the centroid's plane coordinates (cx along x, cz along z), and s (written into
        s). A first edge too short to have a direction (<= MIN_EDGE) takes its second edge's,
        in the root's plane (or the root's x axis), as training does (binding_kernels.
        _plane_face): in inference's general 3D path it took one from rounding noise, so the
        viewer showed a face scale training never had. Uses scratch rows 0-7."""
        p1, q1, p2, q2, u, v, cx, cz = scratch[:8]
        L, a, b = g[12], g[13], g[14]
        c11, c12, c21, c22, cc1, cc2 = (c[sl] for c in self._coef)
        # 2D coordinates (along the root's x, along its z) of the edges: p = c1·L + c2·a, q = c2·b
        np.multiply(c11, L, out=p1)
        np.multiply(c12, a, out=u)
        p1 += u
        np.multiply(c12, b, out=q1)
        np.multiply(c21, L, out=p2)
        np.multiply(c22, a, out=u)
        p2 += u
        np.multiply(c22, b, out=q2)
        length = s  # becomes s below
        np.multiply(p1, p1, out=u)
        np.multiply(q1, q1, out=v)
        np.add(u, v, out=length)
        np.sqrt(length, out=length)
        degenerate = length <= MIN_EDGE
        if degenerate.any():
            l2 = np.hypot(p2[degenerate], q2[degenerate])
            has2 = l2 > MIN_EDGE
            p1[degenerate] = np.where(has2, p2[degenerate], 1)
            q1[degenerate] = np.where(has2, q2[degenerate], 0)
            norm = length.copy()
            norm[degenerate] = np.where(has2, l2, 1)
        else:
            norm = length
        np.divide(p1, norm, out=u)  # cos
        np.divide(q1, norm, out=v)  # sin
        # s = (length + |cos·q2 - sin·p2|) / 2
        np.multiply(u, q2, out=p1)
        np.multiply(v, p2, out=q1)
        p1 -= q1
        np.abs(p1, out=p1)
        length += p1
        length *= 0.5
        np.maximum(length, MIN_SCALE, out=length)
        np.multiply(cc1, L, out=cx)
        np.multiply(cc2, a, out=p1)
        cx += p1
        np.multiply(cc2, b, out=cz)
        return u, v, cx, cz

    def _bad_rows(self, good):
        """Rows under degenerate roots, which take the general 3D path (None if none)."""
        return None if good.all() else np.flatnonzero(~good[self.root])

    def _face_vertices(self, rv0, E1, E2):
        """Every row's v0, e1, e2 (the evaluator's precision)."""
        W, root = self.W, self.root
        gE1, gE2 = E1[root], E2[root]
        e1 = W[:, 1, 1:2] * gE1 + W[:, 1, 2:3] * gE2
        e2 = W[:, 2, 1:2] * gE1 + W[:, 2, 2:3] * gE2
        return rv0[root] + W[:, 0, 1:2] * gE1 + W[:, 0, 2:3] * gE2, e1, e2

    def _exact(self, bad):
        """v0, e1, e2 and the flatness bound of the rows ``bad``, in float64 from the vertices as
        given: training's kernel (binding_kernels._general_frame) frames these faces in float64,
        and deep faces' edges come from near-cancelling weights, so in float32 the rounding alone
        could pass the flatness test and give a frame training never had."""
        W, tri, vt = self._W64[bad], self._tri[:, self.root[bad]], self._vt
        v0 = vt[:, tri[0]].T.astype(np.float64)
        E1 = vt[:, tri[1]].T.astype(np.float64) - v0
        E2 = vt[:, tri[2]].T.astype(np.float64) - v0
        e1 = W[:, 1, 1:2] * E1 + W[:, 1, 2:3] * E2
        e2 = W[:, 2, 1:2] * E1 + W[:, 2, 2:3] * E2
        return v0 + W[:, 0, 1:2] * E1 + W[:, 0, 2:3] * E2, e1, e2, 8 * np.finfo(self.dtype).eps


class FaceEvaluator(_PlaneEvaluator):
    """Centroids t, frames r and scales s of a fixed set of forest faces, frame after frame.

    Rows follow the ids given (default: all faces in forest order); ids from `root_grouped`
    evaluate fastest. The returned arrays are views of reused buffers, overwritten by the
    next call.
    """

    def __init__(self, forest: Forest, ids=None, weights=None, dtype=np.float32, chunk=None):
        super().__init__(forest, ids, weights, dtype, chunk)
        n = self.n
        self._r = np.empty((3, 3, n), self.dtype)
        self._t = np.empty((3, n), self.dtype)
        self._s = np.empty(n, self.dtype)

    def __call__(self, vertices, with_vertices: bool = False) -> "FaceGeometry":
        pack, good, rv0, E1, E2 = self._roots(vertices)
        for sl, runs in self._chunks:
            m = sl.stop - sl.start
            scratch = self._scratch[:, :m]
            g = self._gather(pack, sl, runs, scratch[11:26])
            u, v, cx, cz = self._plane(g, sl, scratch, self._s[sl])
            x, nrm, z, v0 = g[3:6], g[6:9], g[9:12], g[0:3]
            tmp3, r, t = scratch[8:11], self._r[..., sl], self._t[:, sl]
            # x' = cos·x + sin·z, normal, z' = cos·z - sin·x, t = v0 + cx·x + cz·z ([3,m] blocks)
            r[:, 1] = nrm
            np.multiply(x, u, out=r[:, 0])
            np.multiply(z, v, out=tmp3)
            r[:, 0] += tmp3
            np.multiply(z, u, out=r[:, 2])
            np.multiply(x, v, out=tmp3)
            r[:, 2] -= tmp3
            np.multiply(x, cx, out=t)
            t += v0
            np.multiply(z, cz, out=tmp3)
            t += tmp3
        rv = np.moveaxis(self._r, 2, 0)  # [n,3,3] view
        tv, sv = self._t.T, self._s
        bad = self._bad_rows(good)
        if bad is not None:
            b_base, b_e1, b_e2, eps = self._exact(bad)
            r_bad, s_bad = frames_from_edges(b_e1, b_e2, eps=eps)
            rv[bad], sv[bad] = r_bad, s_bad
            tv[bad] = b_base + (b_e1 + b_e2) / 3
        fv = fe = None
        if with_vertices:
            base, e1, e2 = self._face_vertices(rv0, E1, E2)
            fv = np.stack([base, base + e1, base + e2], axis=1)
            fe = np.stack([e1, e2], axis=1)
        return FaceGeometry(tv, rv, sv, fv, fe)


class GaussianEvaluator(_PlaneEvaluator):
    """World Gaussians (means, wxyz quats, scales) of a fixed set of faces, frame after frame.

    The same result as `compose` on `FaceEvaluator` output, without forming the face frames:
    a face's frame is its root's frame turned about the normal by the in-plane angle φ of its
    first edge, so μ = v0 + R_root·((cx, 0, cz) + s·Ry(φ)·Δμ) and R = q_root ⊗ q_y(φ) ⊗ ΔR,
    with the root quaternions computed once per frame on the (few) root faces. Faces are
    evaluated in root-grouped order and written to their rows; rows follow the ids given.
    Outputs are row-major [capacity,3]/[capacity,4] views of reused buffers whose first n
    rows hold this frame (Blender's foreach_set wants whole attributes, so a larger capacity
    lets callers hand them over without copying).

    ``threads`` > 1 splits the face chunks between the calling thread and threads - 1 pool
    threads (numpy releases the GIL inside each pass), each with its own scratch rows; the
    bits are those of one thread (each face's arithmetic does not depend on its chunk). With
    the default chunk size such an evaluator of at least THREADED_MIN faces takes two chunks
    a thread: every pass then runs long enough between GIL hand-overs, where 32k-face chunks
    spent the gain on them (old against new in the commit that added the threads). Fewer faces
    run on the calling thread alone.
    """

    ROOT_ROWS = 19  # the 15 plane rows, then the root frame's quaternion (wxyz)
    SCRATCH_ROWS = 40
    THREADED_MIN = 65536

    def __init__(
        self,
        forest: Forest,
        d_mu,
        d_log_scale,
        d_rot,
        ids=None,
        weights=None,
        capacity=None,
        chunk=None,
        rows=None,
        threads=1,
    ):
        given = np.arange(forest.num_faces) if ids is None else np.asarray(ids, np.int64)
        order = np.argsort(forest.root[given], kind="stable")
        threads = max(1, int(threads))
        if chunk is None and threads > 1:
            if len(given) >= self.THREADED_MIN:
                chunk = -(-len(given) // (2 * threads))
            else:
                threads = 1
        super().__init__(forest, given[order], weights, np.float32, chunk)
        n = self.n
        self.threads = min(threads, len(self._chunks)) or 1
        self._scratches = [self._scratch] + [np.empty_like(self._scratch) for _ in range(self.threads - 1)]
        out_rows = np.arange(n) if rows is None else np.asarray(rows, np.int64)
        if out_rows.shape != (n,):
            raise ValueError(f"GaussianEvaluator: rows must give one output row per face ({n}), got {out_rows.shape}")
        if n and (out_rows.min() < 0 or len(np.unique(out_rows)) != n):
            raise ValueError("GaussianEvaluator: rows must be distinct non-negative row numbers")
        self.rows = np.ascontiguousarray(out_rows[order])  # output row of each evaluated face
        # Writes go to a slice where a chunk's rows are consecutive (root-grouped ids in
        # output order: the Blender preview's layout), else they scatter (much slower when the
        # rows are spread out: cache misses on every row).
        self._targets = [_as_run(self.rows[sl]) for sl, _ in self._chunks]
        self._reorder = None
        if not all(isinstance(t, slice) for t in self._targets):
            # Spread-out rows (e.g. forest order, or the Blender layout below 100 %: its rows of
            # the shown ranks): chunks write to staging arrays in evaluation order, then each
            # output takes its rows in one move of whole 12/16-byte records (_move_records).
            perm = np.argsort(self.rows, kind="stable")
            if np.array_equal(perm, np.arange(n)):
                perm = None  # already in row order (the Blender layout's subsets)
            dest = _as_run(self.rows if perm is None else self.rows[perm])
            stage = (np.empty((n, 3), np.float32), np.empty((n, 4), np.float32), np.empty((n, 3), np.float32))
            self._reorder = (perm, dest, stage)
            self._targets = [sl for sl, _ in self._chunks]
        sel = given[order]
        self.d_mu = np.ascontiguousarray(np.asarray(d_mu)[sel].T, np.float32)
        self.exp_scale = np.ascontiguousarray(np.exp(np.asarray(d_log_scale, np.float64)[sel]).T, np.float32)
        self.q_res = np.ascontiguousarray(quat_normalize(np.asarray(d_rot, np.float64)[sel]).T, np.float32)
        top = int(self.rows.max()) + 1 if n else 0
        cap = max(top, n if capacity is None else int(capacity))
        self.means = np.zeros((cap, 3), np.float32)
        self.scales = np.zeros((cap, 3), np.float32)
        self.quats = np.zeros((cap, 4), np.float32)
        self.quats[:, 0] = 1

    def __call__(self, vertices):
        """Returns ``Gaussians`` (means, quats, scales) for mesh vertices [V,3]; this frame's
        Gaussians are in the rows given (default [0, n)); other rows keep what they held."""
        if self.n == 0:
            return Gaussians(self.means, self.quats, self.scales)
        pack, good, rv0, E1, E2 = self._roots(vertices)
        R = [[pack[3 + 3 * j + i] for j in range(3)] for i in range(3)]  # columns x, normal, z
        _root_quats(R, pack[15:19])
        outputs = (self.means, self.quats, self.scales) if self._reorder is None else self._reorder[2]
        jobs = list(zip(self._chunks, self._targets))
        k = self.threads

        def faces(t):  # chunks t, t + k, ... with scratch t
            for (sl, runs), target in jobs[t::k]:
                m = sl.stop - sl.start
                scratch = self._scratches[t][:, :m]
                g = self._gather(pack, sl, runs, scratch[21:40])
                s = scratch[8]
                u, v, cx, cz = self._plane(g, sl, scratch, s)
                self._assemble(g, sl, scratch, u, v, cx, cz, s, target, *outputs)

        if k == 1:
            faces(0)
        else:
            pool = _face_pool(k - 1)
            others = [pool.submit(faces, t) for t in range(1, k)]
            try:
                faces(0)
            finally:
                for f in others:
                    f.result()
        if self._reorder is not None:
            perm, dest, stage = self._reorder
            for src, out in zip(stage, (self.means, self.quats, self.scales)):
                _move_records(src, perm, out, dest)
        bad = self._bad_rows(good)
        if bad is not None:
            base, e1, e2, eps = self._exact(bad)
            r_bad, s_bad = frames_from_edges(e1, e2, eps=eps)
            m, q, sc = compose(
                base + (e1 + e2) / 3,
                r_bad,
                s_bad,
                self.d_mu[:, bad].T,
                np.log(self.exp_scale[:, bad].T),
                self.q_res[:, bad].T,
            )
            rows = self.rows[bad]
            self.means[rows], self.scales[rows], self.quats[rows] = m, sc, q
        return Gaussians(self.means, self.quats, self.scales)

    def _assemble(self, g, sl, scratch, u, v, cx, cz, s, target, means, quats, scales):
        l0, l1, l2, ch, sh = scratch[9:14]
        blk = scratch[14:21]  # means (3 rows), then quaternion p (4 rows)
        tmp = scratch[0]  # p1: free once the plane is done
        dx, dy, dz = self.d_mu[:, sl]
        # Residual mean in the root frame: (cx, 0, cz) + s·Ry(φ)·Δμ, Ry(φ) = [[u,0,-v],[0,1,0],[v,0,u]]
        np.multiply(u, dx, out=l0)
        np.multiply(v, dz, out=tmp)
        l0 -= tmp
        l0 *= s
        l0 += cx
        np.multiply(s, dy, out=l1)
        np.multiply(v, dx, out=l2)
        np.multiply(u, dz, out=tmp)
        l2 += tmp
        l2 *= s
        l2 += cz
        mean = blk[0:3]
        v0, x, nrm, z = g[0:3], g[3:6], g[6:9], g[9:12]
        np.multiply(x, l0, out=mean)
        mean += v0
        tmp3 = scratch[1:4]  # q1, p2, q2: free too
        np.multiply(nrm, l1, out=tmp3)
        mean += tmp3
        np.multiply(z, l2, out=tmp3)
        mean += tmp3
        for k in range(3):  # column by column: a transposed block copy is 5x slower
            means[target, k] = mean[k]
        np.multiply(self.exp_scale[:, sl], s, out=tmp3)
        for k in range(3):
            scales[target, k] = tmp3[k]
        # Half angle of φ (cos φ = u, sin φ = -v) without branches or masks (numpy's masked
        # copies cost ~25 multiplies each): (1 + u + |v|, sign(-v)·(1 - u + |v|)) is
        # 2·(cos(φ/2) + |sin(φ/2)|)·(cos(φ/2), sin(φ/2)), a sum of non-negative terms with
        # norm 2·sqrt(1 + |v|) >= 2, so nothing cancels or divides by a small number.
        av = scratch[3]  # q2: free
        np.abs(v, out=av)
        np.add(av, 1, out=tmp)
        np.sqrt(tmp, out=tmp)
        np.divide(0.5, tmp, out=tmp)  # 1 / norm
        np.add(av, 1, out=ch)
        np.subtract(ch, u, out=sh)
        ch += u
        ch *= tmp
        sh *= tmp
        np.negative(v, out=av)
        np.copysign(sh, av, out=sh)
        # p = q_y(φ) ⊗ ΔR with q_y = (ch, 0, sh, 0)
        dw, dqx, dqy, dqz = self.q_res[:, sl]
        p = blk[3:7]
        np.multiply(ch, dw, out=p[0])
        np.multiply(sh, dqy, out=tmp)
        p[0] -= tmp
        np.multiply(ch, dqx, out=p[1])
        np.multiply(sh, dqz, out=tmp)
        p[1] += tmp
        np.multiply(ch, dqy, out=p[2])
        np.multiply(sh, dw, out=tmp)
        p[2] += tmp
        np.multiply(ch, dqz, out=p[3])
        np.multiply(sh, dqx, out=tmp)
        p[3] -= tmp
        # q = q_root ⊗ p
        qr = g[15:19]
        out = scratch[9:13]  # l0, l1, l2, ch: done with
        for k, row in enumerate(_HAMILTON):
            acc = out[k]
            (ia, ib, _), *rest = row  # the first term of every component is positive
            np.multiply(qr[ia], p[ib], out=acc)
            for ia, ib, sign in rest:
                np.multiply(qr[ia], p[ib], out=tmp)
                if sign > 0:
                    acc += tmp
                else:
                    acc -= tmp
        for k in range(4):
            quats[target, k] = out[k]


# Rows of (p, a, b, c, d, e, f) (quat_rows' names) holding quaternion component c (first index)
# for Shepperd pivot k (second index).
_SHEPPERD_PICK = np.array([[0, 1, 2, 3], [1, 0, 4, 5], [2, 4, 0, 6], [3, 5, 6, 0]], np.intp)


def _root_quats(R, out):
    """quat_rows(R) into out [4,F], for the root frames: the same arithmetic, so the same bits
    for rotation matrices (where every candidate is finite), with the pivot found by comparisons
    and each component picked by a one-hot product. numpy's argmax along the short axis,
    take_along_axis, where, choose and take each cost more than the whole arithmetic, a few
    times this function's time on the roots of a paper-scale avatar."""
    tr = R[0][0] + R[1][1] + R[2][2]
    piv0 = 1 + tr
    piv1 = 1 + R[0][0] - R[1][1] - R[2][2]
    piv2 = 1 - R[0][0] + R[1][1] - R[2][2]
    piv3 = 1 - R[0][0] - R[1][1] + R[2][2]
    # np.argmax over the four (the first of equal pivots): strict comparisons, lower pair first
    hi01, hi23 = piv1 > piv0, piv3 > piv2
    best01, best23 = np.maximum(piv0, piv1), np.maximum(piv2, piv3)
    upper = best23 > best01
    onehot = np.empty((4,) + tr.shape, tr.dtype)
    lower = ~upper
    onehot[0] = lower & ~hi01
    onehot[1] = lower & hi01
    onehot[2] = upper & ~hi23
    onehot[3] = upper & hi23
    vals = np.empty((7,) + tr.shape, tr.dtype)
    p = vals[0]
    np.maximum(best01, best23, out=p)
    np.maximum(p, 1e-30, out=p)
    np.sqrt(p, out=p)
    p *= 0.5
    inv = 0.25 / p
    for row, (i, j, sign) in enumerate(((2, 1, -1), (0, 2, -1), (1, 0, -1), (0, 1, 1), (0, 2, 1), (1, 2, 1)), 1):
        (np.add if sign > 0 else np.subtract)(R[i][j], R[j][i], out=vals[row])
        vals[row] *= inv
    # The picked value plus zeros: exact (a -0.0 may come out +0.0).
    np.einsum("kn,ckn->cn", onehot, vals[_SHEPPERD_PICK], out=out)
    out *= np.where(out[0] < 0, -1, 1).astype(out.dtype)
    out /= np.sqrt(np.sum(out * out, axis=0))
    return out


_POOL = None
_POOL_LOCK = threading.Lock()


def _face_pool(workers):
    """The threads GaussianEvaluator hands face chunks to (made on first use, grown on demand;
    only evaluator calls submit to it, so a chunk never waits on another chunk's pool)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[0] < workers:
            if _POOL is not None:
                _POOL[1].shutdown(wait=False)  # its running chunks finish; new ones go to the larger pool
            _POOL = (workers, ThreadPoolExecutor(workers, thread_name_prefix="pa-faces"))
        return _POOL[1]


def _move_records(src, perm, out, dest):
    """out[dest] = src[perm] (perm None: src) for C-contiguous [n,w] arrays, moving each row as one
    w-float record: numpy's row indexing copies a row float by float, several times slower."""
    rec = np.dtype((np.void, src.shape[1] * src.itemsize))
    s, o = src.view(rec).reshape(-1), out.view(rec).reshape(-1)
    if isinstance(dest, slice):
        if perm is None:
            o[dest] = s
        else:
            np.take(s, perm, out=o[dest])
    else:
        o[dest] = s if perm is None else s[perm]


def _as_run(rows):
    """A slice when rows are consecutive increasing integers, else the rows themselves."""
    if len(rows) and rows[-1] - rows[0] == len(rows) - 1 and bool(np.all(np.diff(rows) == 1)):
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows


_HAMILTON = (  # (a index, b index, sign) per output component of a ⊗ b
    ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)),
    ((0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)),
    ((0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)),
    ((0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1)),
)


def evaluate(
    forest: Forest, vertices: np.ndarray, ids=None, weights=None, dtype=np.float32, with_vertices: bool = False
) -> FaceGeometry:
    """Frames of forest faces on one frame [V,3] or a batch of frames [T,V,3] (fresh arrays).

    For repeated evaluation of the same faces, keep a FaceEvaluator instead.
    """
    verts = np.asarray(vertices)
    if verts.ndim not in (2, 3) or verts.shape[-1] != 3:
        raise ValueError(f"evaluate: vertices must be [V,3] or [T,V,3], got {np.shape(vertices)}")
    ev = FaceEvaluator(forest, ids=ids, weights=weights, dtype=dtype)
    if verts.ndim == 2:
        g = ev(verts, with_vertices)
        return FaceGeometry(g.t.copy(), g.r.copy(), g.s.copy(), g.vertices, g.edges)
    parts = [
        FaceGeometry(*(None if x is None else x.copy() for x in vars(ev(f, with_vertices)).values())) for f in verts
    ]
    pick = lambda name: None if getattr(parts[0], name) is None else np.stack([getattr(p, name) for p in parts])  # noqa: E731
    return FaceGeometry(pick("t"), pick("r"), pick("s"), pick("vertices"), pick("edges"))


def compose(t, r, s, d_mu, d_log_scale, d_rot):
    """World Gaussians from face frames and residuals: μ = s·r·Δμ + t, S = s·exp(ΔS), R = r ⊗ ΔR.

    Shapes broadcast over leading axes: t [...,n,3], r [...,n,3,3], s [...,n]; residuals [n,...].
    Returns ``Gaussians``: means [...,n,3], quats [...,n,4] (wxyz, unit), scales [...,n,3].
    """
    means = s[..., None] * np.einsum("...ij,...j->...i", r, d_mu) + t
    scales = s[..., None] * np.exp(d_log_scale)
    quats = quat_multiply(rotmat_to_quat(r), quat_normalize(d_rot))
    return Gaussians(means, quats, scales)
