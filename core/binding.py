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

from dataclasses import dataclass

import numpy as np

from .forest import Forest

MIN_SCALE = 1e-10  # metres; keeps degenerate faces' Gaussians valid (positive scale)
MIN_EDGE = 1e-15  # metres; shorter edges count as zero (their direction, and its gradient, is noise)


# -- quaternions --------------------------------------------------------------------------
def quat_normalize(q: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    identity = np.zeros_like(q)
    identity[..., 0] = 1
    return np.where(n > 0, q / np.where(n > 0, n, 1), identity)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(quat_normalize(q), -1, 0)
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=-1).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices [...,3,3] -> unit quaternions wxyz with w >= 0.

    Shepperd's method: of the four algebraic forms, use the one whose pivot component is
    largest, so no division by a near-zero component ever happens.
    """
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    piv = np.stack([1 + tr, 1 + 2 * m[..., 0, 0] - tr, 1 + 2 * m[..., 1, 1] - tr, 1 + 2 * m[..., 2, 2] - tr], -1)
    k = np.argmax(piv, axis=-1)
    p = 0.5 * np.sqrt(np.maximum(np.take_along_axis(piv, k[..., None], -1)[..., 0], 1e-30))
    inv = 0.25 / p
    a = m[..., 2, 1] - m[..., 1, 2]
    b = m[..., 0, 2] - m[..., 2, 0]
    c = m[..., 1, 0] - m[..., 0, 1]
    d = m[..., 0, 1] + m[..., 1, 0]
    e = m[..., 0, 2] + m[..., 2, 0]
    f = m[..., 1, 2] + m[..., 2, 1]
    cand = np.stack([
        np.stack([p, a * inv, b * inv, c * inv], -1),
        np.stack([a * inv, p, d * inv, e * inv], -1),
        np.stack([b * inv, d * inv, p, f * inv], -1),
        np.stack([c * inv, e * inv, f * inv, p], -1),
    ], -2)
    q = np.take_along_axis(cand, k[..., None, None], -2)[..., 0, :]
    q = np.where(q[..., :1] < 0, -q, q)
    return quat_normalize(q)


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


def frames_from_edges(e1: np.ndarray, e2: np.ndarray, normal: np.ndarray | None = None):
    """Face frames r [...,3,3] and scales s [...] from edges e1 = v1 - v0, e2 = v2 - v0.

    `normal` (unnormalised) may be supplied when it is known more precisely than x × e2:
    every descendant of a root face is coplanar with it and has the root's normal, which
    stays well conditioned when the small face is a sliver.
    """
    dtype = e1.dtype
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


def _cross(a, b):
    # Written out: np.cross is several times slower on [n,3] float32 arrays.
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


class FaceEvaluator:
    """Evaluates a fixed set of forest faces frame after frame, reusing its buffers.

    Every descendant lies in its root's plane and shares its normal, so each face is worked
    out in its root's 2D frame: one gather of per-root data, then a few scalar operations per
    face on contiguous rows (component-major buffers; the returned arrays are views of them
    and are overwritten by the next call). Edges come from weight differences times root
    edges, so deep (tiny) faces keep float32 precision. Faces under degenerate roots take the
    general 3D path.
    """

    def __init__(self, forest: Forest, ids=None, weights=None, dtype=np.float32):
        self.forest = forest
        self.dtype = np.dtype(dtype)
        W = forest.weights() if weights is None else np.asarray(weights)
        root = forest.root
        if ids is not None:
            ids = np.asarray(ids, np.int64)
            W, root = W[ids], root[ids]
        self.root = np.ascontiguousarray(root)
        self.W = W.astype(self.dtype)
        Wt = np.ascontiguousarray(self.W.reshape(-1, 9).T)  # [9,n]: row 3k+j = W[:,k,j]
        self.w = {k: (Wt[3 * k + 1], Wt[3 * k + 2]) for k in range(3)}
        n = len(self.root)
        self.n = n
        self._gathered = np.empty((15, n), self.dtype)
        self._tmp = np.empty((8, n), self.dtype)
        self._r = np.empty((3, 3, n), self.dtype)
        self._t = np.empty((3, n), self.dtype)
        self._s = np.empty(n, self.dtype)

    def _roots(self, verts):
        """Per root face, component-major [15,F0]: v0, x axis, unit normal, z axis, |E1|, E2·x, E2·z."""
        tri = self.forest.template_faces
        dtype = self.dtype
        eps = 8 * np.finfo(dtype).eps
        vt = np.ascontiguousarray(verts.T)  # [3,V]: rows are contiguous, so are the gathers below
        v0 = vt[:, tri[:, 0]]
        E1 = vt[:, tri[:, 1]] - v0
        E2 = vt[:, tri[:, 2]] - v0
        normal = np.stack([E1[1] * E2[2] - E1[2] * E2[1], E1[2] * E2[0] - E1[0] * E2[2], E1[0] * E2[1] - E1[1] * E2[0]])
        L = np.sqrt(np.einsum("ij,ij->j", E1, E1))
        nn = np.sqrt(np.einsum("ij,ij->j", normal, normal))
        n2 = np.sqrt(np.einsum("ij,ij->j", E2, E2))
        good = (L > 0) & (nn > eps * L * n2)
        xr = E1 / np.where(good, L, 1)
        nh = normal / np.where(good, nn, 1)
        zr = np.stack([xr[1] * nh[2] - xr[2] * nh[1], xr[2] * nh[0] - xr[0] * nh[2], xr[0] * nh[1] - xr[1] * nh[0]])
        a = np.einsum("ij,ij->j", E2, xr)
        b = np.einsum("ij,ij->j", E2, zr)
        pack = np.concatenate([v0, xr, nh, zr, L[None], a[None], b[None]], 0).astype(dtype, copy=False)
        return pack, good, v0.T, E1.T, E2.T

    def __call__(self, vertices, with_vertices: bool = False) -> "FaceGeometry":
        verts = np.asarray(vertices, dtype=self.dtype)
        if verts.ndim != 2 or verts.shape[1] != 3:
            raise ValueError(f"FaceEvaluator: vertices must be [V,3], got {np.shape(vertices)}")
        if self.forest.template_faces.max() >= len(verts):
            raise ValueError(f"FaceEvaluator: template needs {self.forest.template_faces.max() + 1} vertices, got {len(verts)}")
        pack, good, rv0, E1, E2 = self._roots(verts)
        g = self._gathered
        for row in range(15):  # 1-D takes are far faster than one 2-D take along axis 1
            np.take(pack[row], self.root, out=g[row])
        L, a, b = g[12], g[13], g[14]
        p1, q1, p2, q2, p0, q0, u, v = self._tmp

        def plane(k, p, q):  # 2D coordinates (along xr, along zr) of W[:,k,1]·E1 + W[:,k,2]·E2
            w1, w2 = self.w[k]
            np.multiply(w1, L, out=p)
            np.multiply(w2, a, out=u)
            p += u
            np.multiply(w2, b, out=q)

        plane(1, p1, q1)
        plane(2, p2, q2)
        plane(0, p0, q0)
        length = self._s  # reused: becomes s below
        np.multiply(p1, p1, out=u)
        np.multiply(q1, q1, out=v)
        np.add(u, v, out=length)
        np.sqrt(length, out=length)
        degenerate = length <= 0
        np.divide(p1, np.where(degenerate, 1, length), out=u)  # cos
        np.divide(q1, np.where(degenerate, 1, length), out=v)  # sin
        # tx, tz (centroid in the root plane) into p0, q0
        p1 += p2
        p1 /= 3
        p0 += p1
        q1 += q2
        q1 /= 3
        q0 += q1
        # s = (length + |cos·q2 - sin·p2|) / 2, using p1/q1 as scratch now
        np.multiply(u, q2, out=p1)
        np.multiply(v, p2, out=q1)
        p1 -= q1
        np.abs(p1, out=p1)
        length += p1
        length *= 0.5
        np.maximum(length, MIN_SCALE, out=length)
        r, t = self._r, self._t
        for k in range(3):  # three coordinates, not a loop over faces
            xk, nk, zk = g[3 + k], g[6 + k], g[9 + k]
            np.multiply(u, xk, out=r[k, 0])
            np.multiply(v, zk, out=p2)
            r[k, 0] += p2
            np.copyto(r[k, 1], nk)
            np.multiply(u, zk, out=r[k, 2])
            np.multiply(v, xk, out=p2)
            r[k, 2] -= p2
            np.multiply(p0, xk, out=t[k])
            t[k] += g[k]
            np.multiply(q0, zk, out=p2)
            t[k] += p2
        rv = np.moveaxis(r, 2, 0)  # [n,3,3] view
        tv, sv = t.T, self._s
        bad = ~good[self.root] | degenerate
        fv = fe = None
        if with_vertices or bad.any():
            W, root = self.W, self.root
            gE1, gE2 = E1[root], E2[root]
            e1 = W[:, 1, 1:2] * gE1 + W[:, 1, 2:3] * gE2
            e2 = W[:, 2, 1:2] * gE1 + W[:, 2, 2:3] * gE2
            base = rv0[root] + W[:, 0, 1:2] * gE1 + W[:, 0, 2:3] * gE2
            if bad.any():
                r_bad, s_bad = frames_from_edges(e1[bad], e2[bad])
                rv[bad], sv[bad] = r_bad, s_bad
                tv[bad] = (base + (e1 + e2) / 3)[bad]
            if with_vertices:
                fv = np.stack([base, base + e1, base + e2], axis=1)
                fe = np.stack([e1, e2], axis=1)
        return FaceGeometry(tv, rv, sv, fv, fe)


_HAMILTON = (  # (a index, b index, sign) per output component of a ⊗ b
    ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)),
    ((0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)),
    ((0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)),
    ((0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1)),
)


class GaussianEvaluator:
    """World Gaussians (means, wxyz quats, scales) of a fixed set of faces, frame after frame.

    The same result as `compose` on `FaceEvaluator` output, in float32 on component-major
    buffers: the generic compose (einsum, stacked Shepperd candidates) costs several times a
    frame budget at 170k Gaussians. Outputs are row-major [capacity,3]/[capacity,4] views of
    reused buffers whose first n rows hold this frame (Blender's foreach_set wants whole
    attributes, so a larger capacity lets callers hand them over without copying).
    """

    def __init__(self, forest: Forest, d_mu, d_log_scale, d_rot, ids=None, weights=None, capacity=None):
        self.faces = FaceEvaluator(forest, ids=ids, weights=weights)
        n = self.faces.n
        sel = slice(None) if ids is None else np.asarray(ids, np.int64)
        self.n = n
        self.d_mu = np.ascontiguousarray(np.asarray(d_mu)[sel].T, np.float32)
        self.exp_scale = np.ascontiguousarray(np.exp(np.asarray(d_log_scale, np.float64)[sel]).T, np.float32)
        self.q_res = np.ascontiguousarray(quat_normalize(np.asarray(d_rot, np.float64)[sel]).T, np.float32)
        cap = n if capacity is None else max(int(capacity), n)
        self.means = np.zeros((cap, 3), np.float32)
        self.scales = np.zeros((cap, 3), np.float32)
        self.quats = np.zeros((cap, 4), np.float32)
        self.quats[:, 0] = 1
        self._a = np.empty((4, n), np.float32)  # face-frame quaternion, component-major
        self._tmp = np.empty((2, n), np.float32)

    def __call__(self, vertices):
        """Returns (means, quats, scales) for mesh vertices [V,3]; rows [0, n) are this frame's."""
        if self.n == 0:
            return self.means, self.quats, self.scales
        g = self.faces(vertices)
        n = self.n
        R = [[g.r[:, i, j] for j in range(3)] for i in range(3)]
        t, s = g.t, g.s
        tmp, acc = self._tmp
        for i in range(3):
            np.multiply(R[i][0], self.d_mu[0], out=acc)
            np.multiply(R[i][1], self.d_mu[1], out=tmp)
            acc += tmp
            np.multiply(R[i][2], self.d_mu[2], out=tmp)
            acc += tmp
            acc *= s
            acc += t[:, i]
            self.means[:n, i] = acc
            np.multiply(self.exp_scale[i], s, out=tmp)
            self.scales[:n, i] = tmp
        self._frame_quats(R)
        a, b = self._a, self.q_res
        for k, row in enumerate(_HAMILTON):
            acc.fill(0)
            for ia, ib, sign in row:
                np.multiply(a[ia], b[ib], out=tmp)
                if sign > 0:
                    acc += tmp
                else:
                    acc -= tmp
            self.quats[:n, k] = acc
        return self.means, self.quats, self.scales

    def _frame_quats(self, R):
        """Unit quaternions (w >= 0) of the face frames into self._a.

        Where w >= 1/4 (rotations up to ~150 degrees: nearly every face) the trace formula
        divides by 4w and is as accurate as Shepperd's method; the rest go through
        rotmat_to_quat on that subset only.
        """
        out, (tmp, inv) = self._a, self._tmp
        np.add(R[0][0], R[1][1], out=tmp)
        tmp += R[2][2]
        tmp += 1
        np.maximum(tmp, 0, out=tmp)
        w = out[0]
        np.sqrt(tmp, out=w)
        w *= 0.5
        weak = np.flatnonzero(w < 0.25)
        np.maximum(w, 0.25, out=inv)
        np.divide(0.25, inv, out=inv)
        for comp, (i1, j1), (i2, j2) in ((1, (2, 1), (1, 2)), (2, (0, 2), (2, 0)), (3, (1, 0), (0, 1))):
            np.subtract(R[i1][j1], R[i2][j2], out=out[comp])
            out[comp] *= inv
        if len(weak):
            sub = np.stack([np.stack([R[i][j][weak] for j in range(3)], -1) for i in range(3)], -2)
            out[:, weak] = rotmat_to_quat(sub.astype(np.float64)).T


def evaluate(forest: Forest, vertices: np.ndarray, ids=None, weights=None, dtype=np.float32,
             with_vertices: bool = False) -> FaceGeometry:
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
    parts = [FaceGeometry(*(None if x is None else x.copy() for x in vars(ev(f, with_vertices)).values())) for f in verts]
    pick = lambda name: None if getattr(parts[0], name) is None else np.stack([getattr(p, name) for p in parts])  # noqa: E731
    return FaceGeometry(pick("t"), pick("r"), pick("s"), pick("vertices"), pick("edges"))


def compose(t, r, s, d_mu, d_log_scale, d_rot):
    """World Gaussians from face frames and residuals: μ = s·r·Δμ + t, S = s·exp(ΔS), R = r ⊗ ΔR.

    Shapes broadcast over leading axes: t [...,n,3], r [...,n,3,3], s [...,n]; residuals [n,...].
    Returns means [...,n,3], scales [...,n,3], quats [...,n,4] (wxyz, unit).
    """
    means = s[..., None] * np.einsum("...ij,...j->...i", r, d_mu) + t
    scales = s[..., None] * np.exp(d_log_scale)
    quats = quat_multiply(rotmat_to_quat(r), quat_normalize(d_rot))
    return means, scales, quats
