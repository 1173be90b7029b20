"""Training-side face binding as numba kernels: forest weights, face frames and Gaussian
composition, forward and hand-written backward, wrapped in one torch autograd Function.

Same formulas as binding.py (numpy inference) and binding_torch.py (the torch reference the
tests compare against), computed in float64 whatever the parameters' dtype, so training sees
the Gaussians inference will see (the float32 weight recursion of the torch path lost 1e-2 of
a face's scale at depth 5 with learned split points).

Every descendant lies in its root's plane and shares its normal, so each face is worked out
in its root's frame (origin v0, axes X = E1/|E1|, normal N, Z = X x N, and the root
triangle's plane coordinates |E1|, a = E2.X, b = E2.Z): the face's first edge has plane
coordinates (p1, q1), its frame is the root's turned about N by that edge's angle
(x = c X + s Z, y = N, z = c Z - s X with (c, s) = (p1, q1)/|(p1, q1)|), its scale
(|e1| + |z.e2|)/2 and its centroid v0 + cx X + cz Z. One parallel pass over the roots, faces
grouped by root; the backward sums each root's gradient in its own slot (fixed order) and a
serial pass scatters roots onto vertices: deterministic for any thread count.

Gradient of the rotation: r moves only on SO(3) (every input perturbation turns it), so the
quaternion's gradient is taken in the body frame (dq = q x (0, w/2)) and handed to the frame
columns as dL/dx = g_wz y, dL/dy = g_wx z, dL/dz = g_wy x: it differs from differentiating
Shepperd's formula only by a component normal to SO(3), which the chain rule annihilates.

Degenerate faces (a root whose normal vanishes, a face whose first edge vanishes) take the
numpy fallbacks in the forward and pass no gradient to the geometry (vertices, split logits);
their residuals still learn.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from ..avatar.binding import MIN_EDGE, MIN_SCALE
from ..avatar.forest import Forest
from ..geometry.gaussians import Gaussians
from ..render.kernels import _PARALLEL  # only explicit prange loops run in parallel
from ..render.rasterize import float64_array, shared_array

# Runs of roots the binding kernels take in parallel: each run makes its small scratch arrays once
# rather than once per root (most roots of a young avatar are a single face).
ROOT_CHUNKS = 64

# Root rows: v0 (3), X (3), N (3), Z (3), L, a, b, good, eps (the flatness bound, _root_frame)
_R_V0, _R_X, _R_N, _R_Z, _R_L, _R_A, _R_B, _R_GOOD, _R_EPS = 0, 3, 6, 9, 12, 13, 14, 15, 16
_ROOT_ROWS = 17


# ----------------------------------------------------------------------------- weights
@njit(cache=True, inline="always")
def _child_weights(W, bary, i, p, s):
    b0 = bary[p, 0]
    b1 = bary[p, 1]
    b2 = bary[p, 2]
    for c in range(2):
        w0 = W[p, 0, c]
        d1 = W[p, 1, c]
        d2 = W[p, 2, c]
        if s == 0:
            W[i, 0, c] = w0
            W[i, 1, c] = d1
            W[i, 2, c] = b1 * d1 + b2 * d2
        elif s == 1:
            W[i, 0, c] = w0 + d1
            W[i, 1, c] = d2 - d1
            W[i, 2, c] = b2 * d2 - (b0 + b2) * d1
        else:
            W[i, 0, c] = w0 + d2
            W[i, 1, c] = -d2
            W[i, 2, c] = b1 * d1 - (b0 + b1) * d2


@njit(parallel=_PARALLEL, cache=True)
def weights_forward(logits, parent, slot, n_roots, order, root_start):
    """Softmax barycentrics [N,3] and the columns 1, 2 of the geometry weights [N,3,2] in float64
    (rows w_v0, w_v1 - w_v0, w_v2 - w_v0 over the root's vertices; column 0 is never used
    by the geometry). One parallel pass over the roots, each root's faces in ``order`` (grouped
    by root, parents first, as FaceBinding holds them): the same arithmetic per face as one
    serial pass in face order, so the same bits for any thread count."""
    n = logits.shape[0]
    bary = np.empty((n, 3))
    for i in prange(n):
        m = max(logits[i, 0], max(logits[i, 1], logits[i, 2]))
        e0 = math.exp(logits[i, 0] - m)
        e1 = math.exp(logits[i, 1] - m)
        e2 = math.exp(logits[i, 2] - m)
        tot = e0 + e1 + e2
        bary[i, 0] = e0 / tot
        bary[i, 1] = e1 / tot
        bary[i, 2] = e2 / tot
    W = np.zeros((n, 3, 2))
    for root in prange(len(root_start) - 1):
        for k in range(root_start[root], root_start[root + 1]):
            i = order[k]
            if i < n_roots:
                W[i, 1, 0] = 1.0
                W[i, 2, 1] = 1.0
            else:
                _child_weights(W, bary, i, parent[i], slot[i])
    return bary, W


@njit(parallel=_PARALLEL, cache=True)
def weights_backward(gW, W, bary, parent, slot, n_roots, order, root_start):
    """d loss / d logits [N,3] from d loss / d W [N,3,2] (gW is consumed: children add into
    their parents' rows, last face first). Per root in parallel, its faces last first: every
    parent receives its children's terms in the order one serial pass from the last face
    gives them (a parent and its children share a root), so the bits do not depend on the
    thread count."""
    n = W.shape[0]
    gb = np.zeros((n, 3))
    for root in prange(len(root_start) - 1):
        for k in range(root_start[root + 1] - 1, root_start[root] - 1, -1):
            i = order[k]
            if i < n_roots:
                continue
            p = parent[i]
            b0 = bary[p, 0]
            b1 = bary[p, 1]
            b2 = bary[p, 2]
            s = slot[i]
            for c in range(2):
                g0 = gW[i, 0, c]
                g1 = gW[i, 1, c]
                g2 = gW[i, 2, c]
                d1 = W[p, 1, c]
                d2 = W[p, 2, c]
                gW[p, 0, c] += g0
                if s == 0:
                    gW[p, 1, c] += g1 + b1 * g2
                    gW[p, 2, c] += b2 * g2
                    gb[p, 1] += g2 * d1
                    gb[p, 2] += g2 * d2
                elif s == 1:
                    gW[p, 1, c] += g0 - g1 - (b0 + b2) * g2
                    gW[p, 2, c] += g1 + b2 * g2
                    gb[p, 2] += g2 * (d2 - d1)
                    gb[p, 0] -= g2 * d1
                else:
                    gW[p, 2, c] += g0 - g1 - (b0 + b1) * g2
                    gW[p, 1, c] += b1 * g2
                    gb[p, 1] += g2 * (d1 - d2)
                    gb[p, 0] -= g2 * d2
    g_logits = np.empty((n, 3))
    for i in prange(n):
        dot = gb[i, 0] * bary[i, 0] + gb[i, 1] * bary[i, 1] + gb[i, 2] * bary[i, 2]
        for k in range(3):
            g_logits[i, k] = bary[i, k] * (gb[i, k] - dot)
    return g_logits


# ----------------------------------------------------------------------------- roots
# The per-face helpers take arrays, and LLVM leaves such calls in place; numba's own inlining
# takes a third off the bind forward and a fifth off its backward on a 161k-face forest (an
# A/B run, same bits).
@njit(cache=True, inline="always")
def _root_frame(verts, tri, f, out, eps):
    """Fill root row `out` for template face f (see _R_*). `eps` is the inference evaluator's
    flatness bound for the vertices' own precision (8 eps of float32 for float32 meshes): a
    triangle flatter than that has no trustworthy normal there, so here neither, or training
    and inference would place its Gaussians by different frames."""
    i0 = tri[f, 0]
    i1 = tri[f, 1]
    i2 = tri[f, 2]
    e1x = verts[i1, 0] - verts[i0, 0]
    e1y = verts[i1, 1] - verts[i0, 1]
    e1z = verts[i1, 2] - verts[i0, 2]
    e2x = verts[i2, 0] - verts[i0, 0]
    e2y = verts[i2, 1] - verts[i0, 1]
    e2z = verts[i2, 2] - verts[i0, 2]
    for k in range(3):
        out[_R_V0 + k] = verts[i0, k]
    out[_R_EPS] = eps
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    L = math.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    l2 = math.sqrt(e2x * e2x + e2y * e2y + e2z * e2z)
    good = L > MIN_EDGE and nn > MIN_EDGE * MIN_EDGE and nn > eps * L * l2
    out[_R_GOOD] = 1.0 if good else 0.0
    if not good:
        for k in range(3, 15):
            out[k] = 0.0
        return
    X0 = e1x / L
    X1 = e1y / L
    X2 = e1z / L
    N0 = nx / nn
    N1 = ny / nn
    N2 = nz / nn
    Z0 = X1 * N2 - X2 * N1
    Z1 = X2 * N0 - X0 * N2
    Z2 = X0 * N1 - X1 * N0
    out[_R_X] = X0
    out[_R_X + 1] = X1
    out[_R_X + 2] = X2
    out[_R_N] = N0
    out[_R_N + 1] = N1
    out[_R_N + 2] = N2
    out[_R_Z] = Z0
    out[_R_Z + 1] = Z1
    out[_R_Z + 2] = Z2
    out[_R_L] = L
    out[_R_A] = e2x * X0 + e2y * X1 + e2z * X2
    out[_R_B] = e2x * Z0 + e2y * Z1 + e2z * Z2


@njit(parallel=_PARALLEL, cache=True)
def roots_forward(verts, tri, eps):
    F0 = tri.shape[0]
    pack = np.empty((F0, _ROOT_ROWS))
    for f in prange(F0):
        _root_frame(verts, tri, f, pack[f], eps)
    return pack


# ----------------------------------------------------------------------------- one face
@njit(cache=True, inline="always")
def _unit3(x, y, z):
    m = max(abs(x), max(abs(y), abs(z)))
    if m == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    ux = x / m
    uy = y / m
    uz = z / m
    n = math.sqrt(ux * ux + uy * uy + uz * uz)
    return ux / n, uy / n, uz / n, n * m


@njit(cache=True, inline="always")
def _general_frame(verts, tri, f, Wi, r, eps):
    """numpy frames_from_edges(e1, e2) without a normal, for faces under degenerate roots,
    flat below `eps` as there: fills r (3x3, columns x, y, z) and returns (s, t0, t1, t2)."""
    i0 = tri[f, 0]
    i1 = tri[f, 1]
    i2 = tri[f, 2]
    E1 = np.empty(3)
    E2 = np.empty(3)
    e1 = np.empty(3)
    e2 = np.empty(3)
    t = np.empty(3)
    for k in range(3):
        E1[k] = verts[i1, k] - verts[i0, k]
        E2[k] = verts[i2, k] - verts[i0, k]
    for k in range(3):
        e1[k] = Wi[1, 0] * E1[k] + Wi[1, 1] * E2[k]
        e2[k] = Wi[2, 0] * E1[k] + Wi[2, 1] * E2[k]
        t[k] = verts[i0, k] + Wi[0, 0] * E1[k] + Wi[0, 1] * E2[k] + (e1[k] + e2[k]) / 3.0
    u1x, u1y, u1z, n1 = _unit3(e1[0], e1[1], e1[2])
    u2x, u2y, u2z, n2 = _unit3(e2[0], e2[1], e2[2])
    if n1 > MIN_EDGE:
        x0, x1, x2 = u1x, u1y, u1z
    elif n2 > MIN_EDGE:
        x0, x1, x2 = u2x, u2y, u2z
    else:
        x0, x1, x2 = 1.0, 0.0, 0.0
    o0 = x1 * e2[2] - x2 * e2[1]
    o1 = x2 * e2[0] - x0 * e2[2]
    o2 = x0 * e2[1] - x1 * e2[0]
    y0, y1, y2, on = _unit3(o0, o1, o2)
    if n2 <= MIN_EDGE or on <= eps * n2:
        ax, ay, az = abs(x0), abs(x1), abs(x2)
        h0, h1, h2 = 0.0, 0.0, 0.0
        if ax <= ay and ax <= az:
            h0 = 1.0
        elif ay <= az:
            h1 = 1.0
        else:
            h2 = 1.0
        y0, y1, y2, _ = _unit3(x1 * h2 - x2 * h1, x2 * h0 - x0 * h2, x0 * h1 - x1 * h0)
    z0 = x1 * y2 - x2 * y1
    z1 = x2 * y0 - x0 * y2
    z2 = x0 * y1 - x1 * y0
    r[0, 0], r[1, 0], r[2, 0] = x0, x1, x2
    r[0, 1], r[1, 1], r[2, 1] = y0, y1, y2
    r[0, 2], r[1, 2], r[2, 2] = z0, z1, z2
    s = 0.5 * (n1 + abs(z0 * e2[0] + z1 * e2[1] + z2 * e2[2]))
    return max(s, MIN_SCALE), t[0], t[1], t[2]


@njit(cache=True, inline="always")
def _plane_face(g, Wi):
    """Face in its (good) root's plane: c, s of its first edge, its length l, p2, q2 of its
    second edge, centroid plane coordinates cx, cz, the scale and whether the first edge is
    proper (False: fallback direction, no geometry gradient)."""
    L = g[_R_L]
    a = g[_R_A]
    b = g[_R_B]
    p1 = Wi[1, 0] * L + Wi[1, 1] * a
    q1 = Wi[1, 1] * b
    p2 = Wi[2, 0] * L + Wi[2, 1] * a
    q2 = Wi[2, 1] * b
    k1 = Wi[0, 0] + (Wi[1, 0] + Wi[2, 0]) / 3.0
    k2 = Wi[0, 1] + (Wi[1, 1] + Wi[2, 1]) / 3.0
    cx = k1 * L + k2 * a
    cz = k2 * b
    ell = math.sqrt(p1 * p1 + q1 * q1)
    proper = ell > MIN_EDGE
    if proper:
        c = p1 / ell
        s = q1 / ell
        scale = 0.5 * (ell + abs(c * q2 - s * p2))
    else:
        l2 = math.sqrt(p2 * p2 + q2 * q2)
        if l2 > MIN_EDGE:
            c = p2 / l2
            s = q2 / l2
        else:
            c = 1.0
            s = 0.0
        scale = 0.5 * abs(c * q2 - s * p2)
    return c, s, ell, p1, q1, p2, q2, cx, cz, max(scale, MIN_SCALE), proper


@njit(cache=True, inline="always")
def _rotmat_to_quat(r, q):
    """Shepperd's method as binding.rotmat_to_quat (w >= 0, unit)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    piv0 = 1.0 + tr
    piv1 = 1.0 + 2.0 * r[0, 0] - tr
    piv2 = 1.0 + 2.0 * r[1, 1] - tr
    piv3 = 1.0 + 2.0 * r[2, 2] - tr
    k = 0
    best = piv0
    if piv1 > best:
        k, best = 1, piv1
    if piv2 > best:
        k, best = 2, piv2
    if piv3 > best:
        k, best = 3, piv3
    p = 0.5 * math.sqrt(max(best, 1e-30))
    inv = 0.25 / p
    a = (r[2, 1] - r[1, 2]) * inv
    b = (r[0, 2] - r[2, 0]) * inv
    c = (r[1, 0] - r[0, 1]) * inv
    d = (r[0, 1] + r[1, 0]) * inv
    e = (r[0, 2] + r[2, 0]) * inv
    f = (r[1, 2] + r[2, 1]) * inv
    if k == 0:
        q[0], q[1], q[2], q[3] = p, a, b, c
    elif k == 1:
        q[0], q[1], q[2], q[3] = a, p, d, e
    elif k == 2:
        q[0], q[1], q[2], q[3] = b, d, p, f
    else:
        q[0], q[1], q[2], q[3] = c, e, f, p
    sgn = -1.0 if q[0] < 0 else 1.0
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    for i in range(4):
        q[i] *= sgn / n


@njit(cache=True, inline="always")
def _qmul(a, b, out):
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]


@njit(cache=True, inline="always")
def _normalise_residual(qd):
    """qd (4,) to a unit quaternion in place, as the numpy evaluator does: the plain norm for
    any usual residual (the bits of before), a rescaled one below 1e-12 (1e-30 components
    square to 0), the identity for a zero residual (the face's own frame). Returns |qd|."""
    nd = math.sqrt(qd[0] ** 2 + qd[1] ** 2 + qd[2] ** 2 + qd[3] ** 2)
    if nd < 1e-12:
        m = max(abs(qd[0]), abs(qd[1]), abs(qd[2]), abs(qd[3]))
        if m == 0.0:
            qd[0] = 1.0
            return 0.0
        for i in range(4):
            qd[i] = qd[i] / m
        n = math.sqrt(qd[0] ** 2 + qd[1] ** 2 + qd[2] ** 2 + qd[3] ** 2)
        for i in range(4):
            qd[i] = qd[i] / n
        return n * m
    for i in range(4):
        qd[i] = qd[i] / nd
    return nd


@njit(cache=True, inline="always")
def _face_frame(verts, tri, pack, root, f, Wf, r):
    """Frame r, scale and centroid of face f; also the plane quantities the backward needs."""
    g = pack[root]
    if g[_R_GOOD] == 0.0:
        sc, t0, t1, t2 = _general_frame(verts, tri, root, Wf, r, g[_R_EPS])
        return sc, t0, t1, t2, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False
    c, s, ell, p1, q1, p2, q2, cx, cz, sc, proper = _plane_face(g, Wf)
    for k in range(3):
        X = g[_R_X + k]
        Z = g[_R_Z + k]
        r[k, 0] = c * X + s * Z
        r[k, 1] = g[_R_N + k]
        r[k, 2] = c * Z - s * X
    t0 = g[_R_V0] + cx * g[_R_X] + cz * g[_R_Z]
    t1 = g[_R_V0 + 1] + cx * g[_R_X + 1] + cz * g[_R_Z + 1]
    t2 = g[_R_V0 + 2] + cx * g[_R_X + 2] + cz * g[_R_Z + 2]
    return sc, t0, t1, t2, c, s, ell, p1, q1, p2, q2, cx, cz, proper


@njit(parallel=_PARALLEL, cache=True)
def bind_forward(verts, tri, pack, order, root_start, W, d_mu, d_log_scale, d_rot, means, scales, quats):
    """World Gaussians of every face into means [N,3], scales [N,3], quats [N,4] (wxyz), computed
    in float64 and rounded once on the store when the outputs are float32. The residuals may be
    float32 or float64: every load is widened first, so both give the same bits."""
    F0 = tri.shape[0]
    n_chunks = min(F0, ROOT_CHUNKS)
    for chunk in prange(n_chunks):  # scratch made once per run of roots, not once per root
        r = np.empty((3, 3))
        qr = np.empty(4)
        qd = np.empty(4)
        qf = np.empty(4)
        for root in range(F0 * chunk // n_chunks, F0 * (chunk + 1) // n_chunks):
            for k in range(root_start[root], root_start[root + 1]):
                f = order[k]
                sc, t0, t1, t2, _, _, _, _, _, _, _, _, _, _ = _face_frame(verts, tri, pack, root, f, W[f], r)
                m0 = np.float64(d_mu[f, 0])
                m1 = np.float64(d_mu[f, 1])
                m2 = np.float64(d_mu[f, 2])
                means[f, 0] = sc * (r[0, 0] * m0 + r[0, 1] * m1 + r[0, 2] * m2) + t0
                means[f, 1] = sc * (r[1, 0] * m0 + r[1, 1] * m1 + r[1, 2] * m2) + t1
                means[f, 2] = sc * (r[2, 0] * m0 + r[2, 1] * m1 + r[2, 2] * m2) + t2
                for i in range(3):
                    scales[f, i] = sc * math.exp(np.float64(d_log_scale[f, i]))
                _rotmat_to_quat(r, qr)
                for i in range(4):
                    qd[i] = np.float64(d_rot[f, i])
                _normalise_residual(qd)
                _qmul(qr, qd, qf)
                for i in range(4):
                    quats[f, i] = qf[i]


@njit(parallel=_PARALLEL, cache=True)
def bind_backward(
    verts, tri, pack, order, root_start, W, d_mu, d_log_scale, d_rot, g_means, g_scales, g_quats, g_dmu, g_dls, g_drot
):
    """Gradients: per root of (v0, v1, v2) [F0,3,3] and per face of the geometry weights [N,3,2]
    (returned, float64), of d_mu, d_log_scale and d_rot (into g_dmu, g_dls, g_drot, rounded once
    on the store when float32). Inputs float32 or float64 alike: every load is widened first."""
    n = W.shape[0]
    F0 = tri.shape[0]
    g_root = np.zeros((F0, 3, 3))
    gW = np.zeros((n, 3, 2))
    n_chunks = min(F0, ROOT_CHUNKS)
    for chunk in prange(n_chunks):  # scratch made once per run of roots, not once per root
        r = np.empty((3, 3))
        qr = np.empty(4)
        qd = np.empty(4)
        h = np.empty(4)
        tmp = np.empty(4)
        gq = np.empty(4)
        G = np.empty((3, 3))  # dL/d columns x, y, z
        dm = np.empty(3)
        gmv = np.empty(3)
        acc = np.empty(15)  # dL/d root rows v0, X, N, Z, L, a, b
        E1 = np.empty(3)
        E2 = np.empty(3)
        gX = np.empty(3)
        gN = np.empty(3)
        gE1 = np.empty(3)
        gE2 = np.empty(3)
        gZt = np.empty(3)
        for root in range(F0 * chunk // n_chunks, F0 * (chunk + 1) // n_chunks):
            G[:] = 0.0
            acc[:] = 0.0
            g = pack[root]
            good = g[_R_GOOD] != 0.0
            for k in range(root_start[root], root_start[root + 1]):
                f = order[k]
                sc, t0, t1, t2, c, s, ell, p1, q1, p2, q2, cx, cz, proper = _face_frame(
                    verts, tri, pack, root, f, W[f], r
                )
                for i in range(3):
                    dm[i] = np.float64(d_mu[f, i])
                    gmv[i] = np.float64(g_means[f, i])
                gm0 = gmv[0]
                gm1 = gmv[1]
                gm2 = gmv[2]
                # scales = sc exp(dls)
                gsc = 0.0
                for i in range(3):
                    e = math.exp(np.float64(d_log_scale[f, i]))
                    gs_i = np.float64(g_scales[f, i])
                    gsc += gs_i * e
                    g_dls[f, i] = gs_i * sc * e
                # means = sc r dmu + t
                rd0 = r[0, 0] * dm[0] + r[0, 1] * dm[1] + r[0, 2] * dm[2]
                rd1 = r[1, 0] * dm[0] + r[1, 1] * dm[1] + r[1, 2] * dm[2]
                rd2 = r[2, 0] * dm[0] + r[2, 1] * dm[1] + r[2, 2] * dm[2]
                gsc += gm0 * rd0 + gm1 * rd1 + gm2 * rd2
                for j in range(3):
                    g_dmu[f, j] = sc * (r[0, j] * gm0 + r[1, j] * gm1 + r[2, j] * gm2)
                    for i in range(3):
                        G[i, j] = sc * dm[j] * gmv[i]
                # quats = q(r) x qd
                _rotmat_to_quat(r, qr)
                for i in range(4):
                    qd[i] = np.float64(d_rot[f, i])
                # |d_rot| bounded below for the gradient only (it is 1/|d_rot|; 0 for a zero residual)
                nd = _normalise_residual(qd)
                nd = max(nd, 1e-12) if nd > 0 else math.inf
                for i in range(4):
                    gq[i] = np.float64(g_quats[f, i])
                # dL/dqd = conj(qr) x gq; d_rot: project off qd, divide by |d_rot|
                tmp[0] = qr[0]
                tmp[1] = -qr[1]
                tmp[2] = -qr[2]
                tmp[3] = -qr[3]
                _qmul(tmp, gq, h)
                dot = h[0] * qd[0] + h[1] * qd[1] + h[2] * qd[2] + h[3] * qd[3]
                for i in range(4):
                    g_drot[f, i] = (h[i] - dot * qd[i]) / nd
                if not good or not proper:
                    continue
                # body-frame rotation gradient: g_w = vec(h x conj(qd)) / 2
                tmp[0] = qd[0]
                tmp[1] = -qd[1]
                tmp[2] = -qd[2]
                tmp[3] = -qd[3]
                _qmul(h, tmp, gq)
                gwx = 0.5 * gq[1]
                gwy = 0.5 * gq[2]
                gwz = 0.5 * gq[3]
                for i in range(3):
                    G[i, 0] += gwz * r[i, 1]
                    G[i, 1] += gwx * r[i, 2]
                    G[i, 2] += gwy * r[i, 0]
                # x = c X + s Z, y = N, z = c Z - s X; t = v0 + cx X + cz Z
                gc = 0.0
                gs = 0.0
                gcx = 0.0
                gcz = 0.0
                for i in range(3):
                    X = g[_R_X + i]
                    Z = g[_R_Z + i]
                    gc += G[i, 0] * X + G[i, 2] * Z
                    gs += G[i, 0] * Z - G[i, 2] * X
                    acc[_R_X + i] += c * G[i, 0] - s * G[i, 2]
                    acc[_R_Z + i] += s * G[i, 0] + c * G[i, 2]
                    acc[_R_N + i] += G[i, 1]
                    gt = gmv[i]
                    acc[_R_V0 + i] += gt
                    acc[_R_X + i] += cx * gt
                    acc[_R_Z + i] += cz * gt
                    gcx += gt * X
                    gcz += gt * Z
                # scale = (ell + |c q2 - s p2|) / 2 (unless clamped)
                gell = 0.0
                gp2 = 0.0
                gq2 = 0.0
                d = c * q2 - s * p2
                if 0.5 * (ell + abs(d)) > MIN_SCALE:
                    gell = 0.5 * gsc
                    gd = 0.5 * gsc * (1.0 if d > 0 else (-1.0 if d < 0 else 0.0))
                    gc += gd * q2
                    gs -= gd * p2
                    gq2 = gd * c
                    gp2 = -gd * s
                # (c, s) = (p1, q1) / ell
                ge = gell - (gc * c + gs * s) / ell
                gp1 = gc / ell + ge * c
                gq1 = gs / ell + ge * s
                L = g[_R_L]
                a = g[_R_A]
                b = g[_R_B]
                Wf = W[f]
                k1 = Wf[0, 0] + (Wf[1, 0] + Wf[2, 0]) / 3.0
                k2 = Wf[0, 1] + (Wf[1, 1] + Wf[2, 1]) / 3.0
                acc[_R_L] += gp1 * Wf[1, 0] + gp2 * Wf[2, 0] + gcx * k1
                acc[_R_A] += gp1 * Wf[1, 1] + gp2 * Wf[2, 1] + gcx * k2
                acc[_R_B] += gq1 * Wf[1, 1] + gq2 * Wf[2, 1] + gcz * k2
                gk1 = gcx * L
                gk2 = gcx * a + gcz * b
                gW[f, 0, 0] = gk1
                gW[f, 0, 1] = gk2
                gW[f, 1, 0] = gp1 * L + gk1 / 3.0
                gW[f, 1, 1] = gp1 * a + gq1 * b + gk2 / 3.0
                gW[f, 2, 0] = gp2 * L + gk1 / 3.0
                gW[f, 2, 1] = gp2 * a + gq2 * b + gk2 / 3.0
            if not good:
                continue
            # root rows -> v0, E1, E2 -> vertices
            i0 = tri[root, 0]
            i1 = tri[root, 1]
            i2 = tri[root, 2]
            for i in range(3):
                E1[i] = verts[i1, i] - verts[i0, i]
                E2[i] = verts[i2, i] - verts[i0, i]
            X = g[_R_X : _R_X + 3]
            Nv = g[_R_N : _R_N + 3]
            Z = g[_R_Z : _R_Z + 3]
            for i in range(3):
                gX[i] = acc[_R_X + i]
                gN[i] = acc[_R_N + i]
            gZ = acc[_R_Z : _R_Z + 3]
            gE1[:] = 0.0
            gE2[:] = 0.0
            ga = acc[_R_A]
            gb = acc[_R_B]
            for i in range(3):  # a = E2.X, b = E2.Z
                gE2[i] += ga * X[i] + gb * Z[i]
                gX[i] += ga * E2[i]
            for i in range(3):
                gZt[i] = gZ[i] + gb * E2[i]
            # Z = X x N
            gX[0] += Nv[1] * gZt[2] - Nv[2] * gZt[1]
            gX[1] += Nv[2] * gZt[0] - Nv[0] * gZt[2]
            gX[2] += Nv[0] * gZt[1] - Nv[1] * gZt[0]
            gN[0] += gZt[1] * X[2] - gZt[2] * X[1]
            gN[1] += gZt[2] * X[0] - gZt[0] * X[2]
            gN[2] += gZt[0] * X[1] - gZt[1] * X[0]
            # N = n / |n|, n = E1 x E2
            n0 = E1[1] * E2[2] - E1[2] * E2[1]
            n1 = E1[2] * E2[0] - E1[0] * E2[2]
            n2 = E1[0] * E2[1] - E1[1] * E2[0]
            nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            dn = gN[0] * Nv[0] + gN[1] * Nv[1] + gN[2] * Nv[2]
            gn0 = (gN[0] - dn * Nv[0]) / nn
            gn1 = (gN[1] - dn * Nv[1]) / nn
            gn2 = (gN[2] - dn * Nv[2]) / nn
            gE1[0] += E2[1] * gn2 - E2[2] * gn1
            gE1[1] += E2[2] * gn0 - E2[0] * gn2
            gE1[2] += E2[0] * gn1 - E2[1] * gn0
            gE2[0] += gn1 * E1[2] - gn2 * E1[1]
            gE2[1] += gn2 * E1[0] - gn0 * E1[2]
            gE2[2] += gn0 * E1[1] - gn1 * E1[0]
            # X = E1 / L, L = |E1|
            L = g[_R_L]
            dx = gX[0] * X[0] + gX[1] * X[1] + gX[2] * X[2]
            for i in range(3):
                gE1[i] += (gX[i] - dx * X[i]) / L + acc[_R_L] * X[i]
                g_root[root, 0, i] = acc[_R_V0 + i] - gE1[i] - gE2[i]
                g_root[root, 1, i] = gE1[i]
                g_root[root, 2, i] = gE2[i]
    return g_root, gW


@njit(cache=True)
def scatter_roots(g_root, tri, n_verts):
    out = np.zeros((n_verts, 3))
    for f in range(tri.shape[0]):
        for j in range(3):
            v = tri[f, j]
            for i in range(3):
                out[v, i] += g_root[f, j, i]
    return out


# ----------------------------------------------------------------------------- torch
class FaceBinding:
    """Index arrays of a Forest for the kernels: faces grouped by root, parents first."""

    def __init__(self, forest: Forest):
        self.forest = forest
        self.tri = np.ascontiguousarray(forest.root_faces, np.int64)
        self.parent = np.ascontiguousarray(forest.parent, np.int64)
        self.slot = np.ascontiguousarray(forest.slot, np.int64)
        root = np.asarray(forest.root, np.int64)
        self.order = np.ascontiguousarray(np.argsort(root, kind="stable"), np.int64)
        self.root_start = np.zeros(forest.num_roots + 1, np.int64)
        np.cumsum(np.bincount(root, minlength=forest.num_roots), out=self.root_start[1:])

    def weights(self, split_logits) -> np.ndarray:
        """Forest.weights' layout [N,3,3] in float64 (column 0 filled in), for comparisons."""
        logits = np.ascontiguousarray(np.asarray(split_logits, np.float64))
        _, W = weights_forward(logits, self.parent, self.slot, self.forest.num_roots, self.order, self.root_start)
        full = np.empty((len(W), 3, 3))
        full[:, :, 1:] = W
        full[:, 0, 0] = 1 - W[:, 0, 0] - W[:, 0, 1]
        full[:, 1:, 0] = -W[:, 1:, 0] - W[:, 1:, 1]
        return full

    def gaussians(self, vertices, split_logits, d_mu, d_log_scale, d_rot):
        """``Gaussians`` (means, quats, scales) as torch tensors in d_mu's dtype, differentiable in
        every input."""
        means, scales, quats = _Bind.apply(vertices, split_logits, d_mu, d_log_scale, d_rot, self)
        return Gaussians(means, quats, scales)


def _array(x: torch.Tensor) -> np.ndarray:
    a = shared_array(x)
    return a if a is not None else float64_array(x)


def _output(like: torch.Tensor, n: int, width: int) -> torch.Tensor:
    """An output [n, width] the kernels write: in ``like``'s dtype on the CPU (one rounding on
    the store, as a float64 result cast afterwards), else float64, cast by ``_moved``."""
    return torch.empty((n, width), dtype=like.dtype if shared_array(like) is not None else torch.float64)


def _moved(x: torch.Tensor, like_kind) -> torch.Tensor:
    dtype, device = like_kind
    return x.to(device=device, dtype=dtype)


class _Bind(torch.autograd.Function):
    @staticmethod
    def forward(ctx, vertices, split_logits, d_mu, d_log_scale, d_rot, plan):
        n = plan.forest.num_faces
        if split_logits.shape != (n, 3) or d_mu.shape != (n, 3) or d_log_scale.shape != (n, 3) or d_rot.shape != (n, 4):
            raise ValueError(
                f"FaceBinding: parameters must have {n} rows (split_logits, d_mu, d_log_scale [N,3], "
                f"d_rot [N,4]), got {tuple(split_logits.shape)}, {tuple(d_mu.shape)}, "
                f"{tuple(d_log_scale.shape)}, {tuple(d_rot.shape)}"
            )
        if vertices.dim() != 2 or vertices.shape[1] != 3 or vertices.shape[0] <= int(plan.tri.max()):
            raise ValueError(
                f"FaceBinding: vertices must be [V,3] with V > {int(plan.tri.max())}, got {tuple(vertices.shape)}"
            )
        verts = float64_array(vertices)
        bary, W = weights_forward(
            float64_array(split_logits), plan.parent, plan.slot, plan.forest.num_roots, plan.order, plan.root_start
        )
        # The flatness bound of the numpy evaluator for these vertices' precision (binding.py).
        eps = 8 * float(
            torch.finfo(vertices.dtype).eps if vertices.dtype.is_floating_point else np.finfo(np.float64).eps
        )
        pack = roots_forward(verts, plan.tri, eps)
        means, scales, quats = (_output(d_mu, n, w) for w in (3, 3, 4))
        arrays = tuple(_array(x) for x in (d_mu, d_log_scale, d_rot))
        bind_forward(
            verts, plan.tri, pack, plan.order, plan.root_start, W, *arrays, means.numpy(), scales.numpy(), quats.numpy()
        )
        # The residuals are read again in the backward: saved, so that torch refuses a backward
        # after they were changed in place (the kernels read their memory, not a copy).
        ctx.save_for_backward(d_mu, d_log_scale, d_rot)
        ctx.saved = (plan, verts, bary, W, pack)
        ctx.kinds = [(x.dtype, x.device) for x in (vertices, split_logits, d_mu, d_log_scale, d_rot)]
        kind = (d_mu.dtype, d_mu.device)
        return tuple(_moved(x, kind) for x in (means, scales, quats))

    @staticmethod
    def backward(ctx, g_means, g_scales, g_quats):
        plan, verts, bary, W, pack = ctx.saved
        arrays = tuple(_array(x) for x in ctx.saved_tensors)
        n = W.shape[0]
        zeros = lambda k: np.zeros((n, k))  # noqa: E731
        gm = _array(g_means) if g_means is not None else zeros(3)
        gs = _array(g_scales) if g_scales is not None else zeros(3)
        gq = _array(g_quats) if g_quats is not None else zeros(4)
        g_dmu, g_dls, g_drot = (_output(x, n, w) for x, w in zip(ctx.saved_tensors, (3, 3, 4)))
        g_root, gW = bind_backward(
            verts, plan.tri, pack, plan.order, plan.root_start, W, *arrays, gm, gs, gq,
            g_dmu.numpy(), g_dls.numpy(), g_drot.numpy(),
        )  # fmt: skip
        g_verts = g_logits = None
        if ctx.needs_input_grad[0]:
            g_verts = torch.from_numpy(scatter_roots(g_root, plan.tri, verts.shape[0]))
        if ctx.needs_input_grad[1]:
            g_logits = torch.from_numpy(
                weights_backward(
                    gW, W, bary, plan.parent, plan.slot, plan.forest.num_roots, plan.order, plan.root_start
                )
            )

        def out(x, i):
            if x is None or not ctx.needs_input_grad[i]:
                return None
            return _moved(x, ctx.kinds[i])

        return (out(g_verts, 0), out(g_logits, 1), out(g_dmu, 2), out(g_dls, 3), out(g_drot, 4), None)
