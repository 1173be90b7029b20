import numpy as np
import pytest
import torch
from hypothesis import example, given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from progressive_avatars.core.avatar import binding
from progressive_avatars.core.avatar.forest import Forest
from progressive_avatars.core.geometry.rotations import quat_rows
from progressive_avatars.core.train import binding_torch
from tests.helpers import depth6_precision, random_forest, sphere_mesh


def world_frame(v0, v1, v2):
    """The DESIGN.md formula written out directly on world-space vertices (reference)."""
    x = (v1 - v0) / np.linalg.norm(v1 - v0)
    y = np.cross(x, v2 - v0)
    y /= np.linalg.norm(y)
    z = -np.cross(y, x) / np.linalg.norm(np.cross(y, x))
    s = (np.linalg.norm(v1 - v0) + abs(z @ (v2 - v0))) / 2
    return np.stack([x, y, z], 1), s, (v0 + v1 + v2) / 3


def test_evaluate_matches_world_formula_and_face_vertices():
    rng = np.random.default_rng(0)
    verts, faces = sphere_mesh(6, 8)
    verts = verts + rng.normal(0, 0.01, verts.shape)
    forest = random_forest(faces, rng, depth=3, logit_scale=1.5)
    geo = binding.evaluate(forest, verts, dtype=np.float64, with_vertices=True)
    fv = np.einsum("nij,njk->nik", forest.vertex_weights(), verts[faces[forest.root]])
    np.testing.assert_allclose(geo.vertices, fv, atol=1e-14)
    for i in rng.choice(forest.num_faces, 30, replace=False):
        r, s, t = world_frame(*fv[i])
        np.testing.assert_allclose(geo.r[i], r, atol=1e-9)
        np.testing.assert_allclose(geo.s[i], s, rtol=1e-9)
        np.testing.assert_allclose(geo.t[i], t, atol=1e-14)
    # Proper rotations: orthonormal, det +1.
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", geo.r, geo.r), np.broadcast_to(np.eye(3), geo.r.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(geo.r), 1, atol=1e-12)


def test_batch_of_frames_and_subset():
    rng = np.random.default_rng(1)
    verts, faces = sphere_mesh(5, 6)
    forest = random_forest(faces, rng, depth=2)
    frames = verts[None] * np.array([1.0, 1.1, 0.9])[:, None, None]
    geo = binding.evaluate(forest, frames, dtype=np.float64)
    assert geo.t.shape == (3, forest.num_faces, 3) and geo.r.shape == (3, forest.num_faces, 3, 3)
    ids = np.array([5, 0, forest.num_faces - 1])
    sub = binding.evaluate(forest, frames[1], ids=ids, dtype=np.float64)
    np.testing.assert_allclose(sub.t, geo.t[1, ids], atol=1e-15)
    np.testing.assert_allclose(sub.s, geo.s[1, ids] * 1, rtol=1e-12)
    with pytest.raises(ValueError, match="needs .* vertices"):
        binding.evaluate(forest, verts[:3])


def test_evaluator_row_orders_and_chunks_agree_exactly():
    """Root-grouped ids (np.repeat gather), any other order (np.take) and any chunk size give
    the same numbers, including faces under collapsed roots (the 3D fallback path)."""
    rng = np.random.default_rng(11)
    verts, faces = sphere_mesh(6, 9)
    verts = verts + rng.normal(0, 0.01, verts.shape)
    verts[faces[3, 1]] = verts[faces[3, 0]]  # collapsed roots: a repeated vertex
    forest = random_forest(faces, rng, depth=3, logit_scale=1.5)
    whole = binding.FaceEvaluator(forest, chunk=10**6)(verts)
    grouped = binding.root_grouped(forest)
    assert np.all(np.diff(forest.root[grouped]) >= 0) and np.array_equal(np.sort(grouped), np.arange(forest.num_faces))
    shuffled = rng.permutation(forest.num_faces)[: forest.num_faces // 2]
    for ids in (grouped, shuffled, binding.root_grouped(forest, shuffled)):
        for chunk in (7, 64, 10**6):
            g = binding.FaceEvaluator(forest, ids=ids, chunk=chunk)(verts, with_vertices=True)
            assert np.array_equal(g.t, whole.t[ids]) and np.array_equal(g.r, whole.r[ids])
            assert np.array_equal(g.s, whole.s[ids])
            assert np.all(np.isfinite(g.r)) and np.all(g.s > 0)


def test_gaussian_evaluator_matches_compose_in_any_row_layout():
    """The fused evaluator (root frame ⊗ in-plane half angle) against evaluate + compose in
    float64, for forest order, shuffled subsets written to spread-out rows, and collapsed
    roots and faces (the general-path fallback)."""
    rng = np.random.default_rng(12)
    verts, faces = sphere_mesh(7, 9)
    verts = verts + rng.normal(0, 0.01, verts.shape)
    verts[faces[5, 2]] = verts[faces[5, 0]]  # collapsed roots
    forest = random_forest(faces, rng, depth=3, logit_scale=2.0)
    N = forest.num_faces
    d_mu, d_ls, d_rot = rng.normal(0, 0.5, (N, 3)), rng.normal(-1, 0.3, (N, 3)), rng.normal(size=(N, 4))
    geo = binding.evaluate(forest, verts, dtype=np.float64)
    ref_m, ref_q, ref_s = binding.compose(geo.t, geo.r, geo.s, d_mu, d_ls, d_rot)
    ids = rng.permutation(N)[: N // 2]
    rows = rng.choice(3 * N, len(ids), replace=False)
    cases = [
        (None, None, None, np.arange(N)),
        (ids, None, None, ids),
        (ids, rows, 3 * N, ids),
        (binding.root_grouped(forest), None, None, binding.root_grouped(forest)),
    ]
    for case_ids, case_rows, cap, faces_of_rows in cases:
        ev = binding.GaussianEvaluator(forest, d_mu, d_ls, d_rot, ids=case_ids, rows=case_rows, capacity=cap, chunk=50)
        means, quats, scales = ev(verts.astype(np.float32))
        at = np.arange(len(faces_of_rows)) if case_rows is None else case_rows
        assert means.shape[0] == (cap or len(faces_of_rows))
        np.testing.assert_allclose(means[at], ref_m[faces_of_rows], atol=2e-6)
        np.testing.assert_allclose(scales[at], ref_s[faces_of_rows], rtol=2e-5, atol=1e-9)
        np.testing.assert_allclose(np.abs(np.sum(quats[at] * ref_q[faces_of_rows], 1)), 1, atol=2e-6)
        np.testing.assert_allclose(np.linalg.norm(quats[at], axis=1), 1, atol=1e-6)
    with pytest.raises(ValueError, match="one output row per face"):
        binding.GaussianEvaluator(forest, d_mu, d_ls, d_rot, ids=ids, rows=rows[:3])
    with pytest.raises(ValueError, match="distinct"):
        binding.GaussianEvaluator(forest, d_mu, d_ls, d_rot, ids=ids[:2], rows=[4, 4])


def test_threaded_gaussian_evaluator_gives_the_same_bits():
    """Face chunks split between threads (each with its own scratch) give the bits of one
    thread, in the grouped layout (slices), spread-out rows (staging and reorder) and with a
    collapsed root (the general path after the chunks); below THREADED_MIN faces the default
    chunking keeps to the calling thread."""
    rng = np.random.default_rng(21)
    verts, faces = sphere_mesh(7, 9)
    verts = verts + rng.normal(0, 0.01, verts.shape)
    verts[faces[5, 2]] = verts[faces[5, 0]]
    forest = random_forest(faces, rng, depth=3, logit_scale=2.0)
    N = forest.num_faces
    d_mu, d_ls, d_rot = rng.normal(0, 0.5, (N, 3)), rng.normal(-1, 0.3, (N, 3)), rng.normal(size=(N, 4))
    ids = rng.permutation(N)[: N // 2]
    rows = rng.choice(3 * N, len(ids), replace=False)
    v32 = verts.astype(np.float32)
    for case_ids, case_rows, cap in [(binding.root_grouped(forest), None, None), (ids, rows, 3 * N)]:
        one = binding.GaussianEvaluator(forest, d_mu, d_ls, d_rot, ids=case_ids, rows=case_rows, capacity=cap, chunk=40)
        want = [x.copy() for x in one(v32)]
        for threads in (2, 3):
            ev = binding.GaussianEvaluator(
                forest, d_mu, d_ls, d_rot, ids=case_ids, rows=case_rows, capacity=cap, chunk=40, threads=threads
            )
            assert ev.threads == threads
            for _ in range(2):  # buffers reused
                for got, w in zip(ev(v32), want):
                    np.testing.assert_array_equal(got, w)
    assert binding.GaussianEvaluator(forest, d_mu, d_ls, d_rot, threads=2).threads == 1  # N < THREADED_MIN


def test_quaternion_conventions_against_scipy():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy is xyzw
    np.testing.assert_allclose(binding.quat_to_rotmat(q), R, atol=1e-12)
    back = binding.rotmat_to_quat(R)
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1, atol=1e-10)
    # Hamilton product composes rotations: R(a ⊗ b) = R(a) R(b)
    a, b = q[:100], q[100:]
    np.testing.assert_allclose(binding.quat_to_rotmat(binding.quat_multiply(a, b)), R[:100] @ R[100:], atol=1e-12)
    qt = torch.tensor(q)
    np.testing.assert_allclose(binding_torch.quat_to_rotmat(qt).numpy(), R, atol=1e-12)
    np.testing.assert_allclose(
        np.abs((binding_torch.rotmat_to_quat(torch.tensor(R)).numpy() * q).sum(1)), 1, atol=1e-10
    )
    # Near-180-degree rotations (w ~ 0) are where naive conversions lose the signs.
    flip = np.concatenate([np.zeros((50, 1)), rng.normal(size=(50, 3))], 1)
    flip /= np.linalg.norm(flip, axis=1, keepdims=True)
    Rf = binding.quat_to_rotmat(flip)
    for conv in (binding.rotmat_to_quat, lambda m: binding_torch.rotmat_to_quat(torch.tensor(m)).numpy()):
        np.testing.assert_allclose(binding.quat_to_rotmat(conv(Rf)), Rf, atol=1e-10)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_root_quaternions_are_quat_rows_bit_for_bit(dtype):
    """The evaluator's root quaternions (pivot by comparisons, one-hot pick) are quat_rows' own
    bits on rotation matrices: every Shepperd pivot, ties between pivots (90 and 180 degree
    turns), w near 0, and the identity."""
    rng = np.random.default_rng(4)
    q = rng.normal(size=(2000, 4))
    q[:300, 0] = 0  # half turns: pivots 1-3 tie with or beat 1 + trace
    q[300:400, 1:] = 0  # the identity
    q[400:500] = np.sign(rng.normal(size=(100, 4))) * (rng.random((100, 4)) < 0.5)  # 90-degree turns
    q[400:500, 0] += 1e-3
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    m = binding.quat_to_rotmat(q).astype(dtype)
    R = [[np.ascontiguousarray(m[:, i, j]) for j in range(3)] for i in range(3)]
    want = quat_rows(R)
    got = binding._root_quats(R, np.empty((4, len(q)), dtype))
    np.testing.assert_array_equal(got, want)
    assert got.dtype == dtype


def test_compose_matches_independent_covariance_construction():
    rng = np.random.default_rng(3)
    verts, faces = sphere_mesh(5, 6)
    forest = random_forest(faces, rng, depth=2)
    N = forest.num_faces
    d_mu, d_ls, d_rot = rng.normal(0, 0.5, (N, 3)), rng.normal(0, 0.5, (N, 3)), rng.normal(size=(N, 4))
    geo = binding.evaluate(forest, verts, dtype=np.float64)
    means, quats, scales = binding.compose(geo.t, geo.r, geo.s, d_mu, d_ls, d_rot)
    for i in rng.choice(N, 20, replace=False):
        # Independent: the Gaussian's local frame is r · R(ΔR), its covariance R S² Rᵀ.
        R_local = Rotation.from_quat(d_rot[i, [1, 2, 3, 0]]).as_matrix()
        Rw = geo.r[i] @ R_local
        S = geo.s[i] * np.exp(d_ls[i])
        cov_ref = Rw @ np.diag(S**2) @ Rw.T
        Rq = binding.quat_to_rotmat(quats[i])
        np.testing.assert_allclose(Rq @ np.diag(scales[i] ** 2) @ Rq.T, cov_ref, atol=1e-16)
        np.testing.assert_allclose(means[i], geo.t[i] + geo.s[i] * geo.r[i] @ d_mu[i], atol=1e-15)


def test_numpy_and_torch_agree_float32():
    rng = np.random.default_rng(4)
    verts, faces = sphere_mesh(8, 10)
    forest = random_forest(faces, rng, depth=4, logit_scale=1.0)
    v = verts.astype(np.float32)
    geo = binding.evaluate(forest, v, dtype=np.float32)
    tf = binding_torch.TorchForest(forest)
    W = tf.weights(torch.tensor(forest.split_logits))
    np.testing.assert_allclose(W.numpy(), forest.weights(), atol=1e-6)
    t, r, s = tf.evaluate(torch.tensor(v), W)
    np.testing.assert_allclose(t.numpy(), geo.t, atol=1e-6)
    np.testing.assert_allclose(r.numpy(), geo.r, atol=2e-5)
    np.testing.assert_allclose(s.numpy(), geo.s, rtol=2e-5)
    N = forest.num_faces
    res = (
        rng.normal(0, 0.3, (N, 3)).astype(np.float32),
        rng.normal(0, 0.3, (N, 3)).astype(np.float32),
        rng.normal(size=(N, 4)).astype(np.float32),
    )
    m_np, q_np, s_np = binding.compose(geo.t, geo.r, geo.s, *res)
    m_t, q_t, s_t = binding_torch.compose(t, r, s, *map(torch.tensor, res))
    np.testing.assert_allclose(m_t.numpy(), m_np, atol=1e-6)
    np.testing.assert_allclose(s_t.numpy(), s_np, rtol=1e-5)
    np.testing.assert_allclose(np.abs((q_t.numpy() * q_np).sum(-1)), 1, atol=1e-5)


def test_torch_gradients_match_finite_differences():
    rng = np.random.default_rng(5)
    verts, faces = sphere_mesh(3, 4)
    forest = random_forest(faces, rng, depth=2, frac=0.5)
    tf = binding_torch.TorchForest(forest)
    v = torch.tensor(verts + rng.normal(0, 0.01, verts.shape), requires_grad=True)
    logits = torch.tensor(rng.normal(0, 1, forest.split_logits.shape), requires_grad=True)
    N = forest.num_faces
    d_mu = torch.tensor(rng.normal(0, 0.5, (N, 3)))
    d_ls = torch.tensor(rng.normal(0, 0.3, (N, 3)))
    d_rot = torch.tensor(rng.normal(size=(N, 4)))
    proj = torch.tensor(rng.normal(size=(N, 3 + 3 + 4)))

    def f(v, logits):
        t, r, s = tf.evaluate(v, tf.weights(logits))
        m, q, sc = binding_torch.compose(t, r, s, d_mu, d_ls, d_rot)
        return (torch.cat([m, sc, q * 1e-2], -1) * proj).sum()

    assert torch.autograd.gradcheck(f, (v, logits), eps=1e-7, atol=1e-6, rtol=1e-4)


FLOATS = st.floats(-1, 1, allow_nan=False, width=64)


TINY_EDGE = np.zeros((6, 3))
TINY_EDGE[0, 0] = 1.24094292e-22  # float32 squares underflow: once gave |x| = 0.999


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, (6, 3), elements=FLOATS), st.integers(0, 4))
@example(TINY_EDGE, 0)
@example(TINY_EDGE, 4)
@example(np.pad([[5e-324]], ((0, 5), (0, 2))), 0)  # the smallest double: once gave an infinite gradient
def test_degenerate_triangles_give_finite_deterministic_frames(pts, kind):
    v0, v1, v2 = pts[:3], pts[3:], pts[::-1][:3].copy()
    if kind == 0:
        v1 = v0.copy()  # repeated vertex
    elif kind == 1:
        v2 = v0 + 0.5 * (v1 - v0)  # collinear
    elif kind == 2:
        v1 = v0.copy()
        v2 = v0.copy()  # a point
    elif kind == 3:
        v2 = v0 + (v1 - v0) * 1e-200  # tiny, nearly collinear
    for dtype in (np.float64, np.float32):
        t, r, s = binding.face_frames(v0.astype(dtype), v1.astype(dtype), v2.astype(dtype))
        assert np.all(np.isfinite(r)) and np.all(np.isfinite(s)) and np.all(s > 0)
        # Always a rotation: the fallbacks build an orthonormal frame too.
        np.testing.assert_allclose(np.einsum("nji,njk->nik", r, r), np.broadcast_to(np.eye(3), r.shape), atol=1e-5)
        t2, r2, s2 = binding.face_frames(v0.astype(dtype), v1.astype(dtype), v2.astype(dtype))
        assert np.array_equal(r, r2) and np.array_equal(s, s2)
    tv = [torch.tensor(a, requires_grad=True) for a in (v0, v1, v2)]
    r_t, s_t = binding_torch.frames_from_edges(tv[1] - tv[0], tv[2] - tv[0])
    (r_t.sum() + s_t.sum()).backward()
    assert all(torch.isfinite(a.grad).all() for a in tv)
    assert torch.isfinite(r_t).all()


def test_float32_precision_at_depth_6_on_a_head_sized_mesh():
    """float32 vs float64 on the finest faces, relative to each face's own scale."""
    err = depth6_precision(np.random.default_rng(6))
    assert err["median_scale"] < 1e-3  # typical finest faces are a fraction of a millimetre
    print(f"depth-6 float32 relative error: {err}")
    assert max(err["edges"], err["frames"], err["scales"]) < 1e-5


# -- training kernels (binding_kernels) against the torch reference and numpy inference ---------
def _kernel_inputs(forest, verts, rng, dtype=torch.float64):
    N = forest.num_faces
    mk = lambda a: torch.tensor(a, dtype=dtype, requires_grad=True)  # noqa: E731
    return (
        mk(verts),
        mk(forest.split_logits),
        mk(rng.normal(0, 0.5, (N, 3))),
        mk(rng.normal(-1, 0.3, (N, 3))),
        mk(rng.normal(size=(N, 4))),
    )


def test_binding_kernels_match_torch_reference_values_and_gradients():
    """Forward and backward of the numba kernels against autograd through binding_torch
    (float64, random split logits): the same function to rounding."""
    from progressive_avatars.core.train import binding_kernels

    rng = np.random.default_rng(11)
    verts, faces = sphere_mesh(8, 10)
    forest = random_forest(faces, rng, depth=4, frac=0.6, logit_scale=1.5)
    v, logits, d_mu, d_ls, d_rot = inputs = _kernel_inputs(forest, verts + rng.normal(0, 2e-3, verts.shape), rng)
    tf = binding_torch.TorchForest(forest)
    plan = binding_kernels.FaceBinding(forest)
    np.testing.assert_allclose(plan.weights(forest.split_logits), forest.weights(), atol=1e-15)
    ref = binding_torch.compose(*tf.evaluate(v, tf.weights(logits)), d_mu, d_ls, d_rot)
    new = plan.gaussians(*inputs)
    sign = torch.sign((ref.quats * new.quats).sum(-1, keepdim=True)).detach()  # quaternions are defined up to sign
    for a, b in zip(ref, new._replace(quats=new.quats * sign)):
        np.testing.assert_allclose(b.detach().numpy(), a.detach().numpy(), atol=1e-14)
    cot = [torch.tensor(rng.normal(size=x.shape)) for x in ref]

    def grads(out, flip):
        for p in inputs:
            p.grad = None
        ((out.means * cot[0]).sum() + (out.quats * flip * cot[1]).sum() + (out.scales * cot[2]).sum()).backward()
        return [p.grad.clone() for p in inputs]

    for name, a, b in zip(
        ("vertices", "split_logits", "d_mu", "d_log_scale", "d_rot"),
        grads(ref, 1.0),
        grads(plan.gaussians(*inputs), sign),
    ):
        err = float((a - b).abs().max() / a.abs().max())
        assert err < 1e-10, (name, err)


def test_binding_kernels_gradcheck():
    from progressive_avatars.core.train import binding_kernels

    rng = np.random.default_rng(12)
    verts, faces = sphere_mesh(3, 4)
    forest = random_forest(faces, rng, depth=2, frac=0.5)
    plan = binding_kernels.FaceBinding(forest)
    inputs = _kernel_inputs(forest, verts + rng.normal(0, 0.01, verts.shape), rng)
    proj = torch.tensor(rng.normal(size=(forest.num_faces, 10)))

    def f(*xs):
        m, q, sc = plan.gaussians(*xs)
        return (torch.cat([m, sc, q * 1e-2], -1) * proj).sum()

    assert torch.autograd.gradcheck(f, inputs, eps=1e-7, atol=1e-6, rtol=1e-4)


def test_training_binding_matches_inference_at_depth_6_with_learned_splits():
    """Float32 training parameters as the trainer holds them, random (learned-like) split
    logits: scales and frames agree with numpy inference (float64) to 1e-5 of each face's
    scale; centroids to float32 rounding of world coordinates. The old float32 torch weight
    recursion missed the scale bound by ~40x here."""
    from progressive_avatars.core.train import binding_kernels

    rng = np.random.default_rng(6)
    verts, faces = sphere_mesh(70, 72, radius=0.1)
    forest = Forest(faces)
    current = rng.choice(len(faces), 40, replace=False)
    for _ in range(6):
        current = forest.split(current).ravel()
    forest.split_logits[:] = rng.normal(0, 1.0, forest.split_logits.shape).astype(np.float32)
    N = forest.num_faces
    finest = np.flatnonzero(forest.level == 6)
    v32 = (verts + rng.normal(0, 1e-3, verts.shape)).astype(np.float32)
    g64 = binding.evaluate(forest, v32.astype(np.float64), dtype=np.float64)
    zero = torch.zeros(N, 3)
    ident = torch.zeros(N, 4)
    ident[:, 0] = 1
    m, q, s = binding_kernels.FaceBinding(forest).gaussians(
        torch.tensor(v32), torch.tensor(forest.split_logits), zero, zero, ident
    )
    scale = g64.s[finest]
    assert np.median(scale) < 1e-3
    s_err = float((np.abs(s.numpy()[finest] - scale[:, None]).max(1) / scale).max())
    q_err = float(np.abs(q.numpy()[finest] - binding.rotmat_to_quat(g64.r[finest])).max())
    t_err = np.abs(m.numpy()[finest] - g64.t[finest]).max(1)
    print(f"depth 6, training kernels vs numpy float64: scale {s_err:.2e}, quaternion {q_err:.2e}")
    assert s_err < 1e-5 and q_err < 1e-5
    assert np.all(t_err <= 2 * np.spacing(np.abs(g64.t[finest]).max(1).astype(np.float32)))


def test_binding_kernels_degenerate_roots_stay_finite():
    """Collapsed and collinear template faces and vanishing first edges: finite Gaussians
    and finite gradients (no geometry gradient through the fallbacks)."""
    from progressive_avatars.core.train import binding_kernels

    rng = np.random.default_rng(13)
    verts, faces = sphere_mesh(4, 6)
    forest = random_forest(faces, rng, depth=3, frac=0.7)
    forest.split_logits[forest.num_roots :][:5] = [60.0, -60.0, -60.0]  # split point on a vertex
    v = verts.copy()
    a, b, c = faces[0]
    v[b] = v[a]  # a point-like edge
    a, b, c = faces[3]
    v[c] = 0.5 * (v[a] + v[b])  # collinear
    inputs = _kernel_inputs(forest, v, rng)
    out = binding_kernels.FaceBinding(forest).gaussians(*inputs)
    assert all(torch.isfinite(x).all() for x in out)
    assert torch.all(out.scales > 0)
    sum(x.sum() for x in out).backward()
    assert all(torch.isfinite(p.grad).all() for p in inputs)


@pytest.mark.parametrize("gap", [30.0, 60.0])
def test_binding_kernels_tiny_faces_pass_no_geometry_gradient(gap):
    """Split points e^-gap from v1 at two levels: face 5 = (v1, p, p') has edges ~e^-gap. At
    gap 30 (1e-13 m) its first edge is proper but its scale sits at the MIN_SCALE clamp, so its
    scale's gradient reaches no vertex or split logit; at gap 60 (1e-26 m <= MIN_EDGE) its edge
    has no direction and none of its outputs does (only its residuals learn). The finiteness
    test above missed a 1/|e1| ~ 1e26 gradient through such a face."""
    from progressive_avatars.core.train import binding_kernels

    f = Forest(np.array([[0, 1, 2]]))
    f.split([0])
    f.split([1])
    assert f.parent[5] == 1 and f.slot[5] == 1 and f.parent[1] == 0 and f.slot[1] == 0
    f.split_logits[:] = 0.0
    f.split_logits[0] = f.split_logits[1] = [0.0, gap, 0.0]
    rng = np.random.default_rng(18)
    inputs = _kernel_inputs(f, VERTS + rng.normal(0, 0.1, (3, 3)), rng)
    out = binding_kernels.FaceBinding(f).gaussians(*inputs)
    np.testing.assert_allclose(
        out.scales[5].detach().numpy(), binding.MIN_SCALE * np.exp(inputs[3][5].detach().numpy())
    )
    cot = torch.zeros(f.num_faces, 10, dtype=torch.float64)
    cot[5] = torch.tensor(rng.normal(size=10))
    if gap == 30.0:
        cot[5, :7] = 0.0  # the scales alone: the means and rotation turn with the proper edge
    (torch.cat([out.means, out.quats, out.scales], 1) * cot).sum().backward()
    assert torch.all(inputs[0].grad == 0) and torch.all(inputs[1].grad == 0)
    np.testing.assert_allclose(inputs[3].grad[5].numpy(), cot[5, 7:].numpy() * out.scales[5].detach().numpy())
    if gap == 60.0:
        assert torch.all(inputs[2].grad[5] != 0) and torch.all(inputs[4].grad[5] != 0)


@pytest.mark.parametrize("height", [1e-2, 1e-8, 0.0])
def test_training_and_inference_agree_on_a_collapsing_float32_root(height):
    """A template triangle flattening to a line in some frame (float32 vertices, as datasets
    store them; the 'collinear' one still has sin ~1e-8 after float32 rounding): training and
    inference fall back to the same frame below the float32 flatness bound. Training used to
    trust a float64 normal of rounding noise there: 1.1 face scales and 100-130 degrees apart."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.train.binding_kernels import FaceBinding

    forest = Forest(np.array([[0, 1, 2]], np.int32))
    forest.split(forest.split([0]).ravel())
    rng = np.random.default_rng(0)
    N = forest.num_faces
    forest.split_logits[:] = rng.normal(0, 1, (N, 3))
    av = Avatar.initial(forest)
    av.d_mu[:] = rng.normal(0, 0.3, (N, 3))
    av.d_log_scale[:] = -1.0
    av.d_rot[:] = rng.normal(0, 1, (N, 4))
    v0, v1 = np.array([0.013, -0.021, 0.037]), np.array([0.031, 0.004, 0.052])
    V = np.stack([v0, v1, v0 + 2 * (v1 - v0) + height * np.array([0.3, -0.1, -0.2])]).astype(np.float32)
    inf = binding.GaussianEvaluator(forest, av.d_mu, av.d_log_scale, av.d_rot)(V)
    t = torch.tensor
    tr = FaceBinding(forest).gaussians(t(V), t(forest.split_logits), t(av.d_mu), t(av.d_log_scale), t(av.d_rot))
    s = binding.evaluate(forest, V.astype(np.float64), dtype=np.float64).s
    assert np.abs(inf.means[:N] - tr.means.numpy()).max(1).max() / s.min() < 1e-4
    qa, qb = inf.quats[:N].astype(np.float64), tr.quats.numpy().astype(np.float64)
    assert np.abs(np.abs((qa * qb).sum(1)) - 1).max() < 1e-5  # the same rotations (up to sign)


@pytest.mark.parametrize("kind", ["v1 == v2", "v0 == v1", "collinear"])
def test_training_and_inference_agree_deep_under_a_degenerate_root(kind):
    """Five levels under a zero-area root: the deep faces' edges come from near-cancelling
    weights, so in float32 their rounding alone passed the flatness test and inference framed
    16 of 364 faces from noise (up to 5 % of the triangle away, rotations ~100 degrees off)
    where training's float64 kernel took the fallback frame."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.train.binding_kernels import FaceBinding

    forest = Forest(np.array([[0, 1, 2]], np.int32))
    for _ in range(5):
        forest.split(np.flatnonzero(forest.level == forest.level.max()))
    rng = np.random.default_rng(1)
    N = forest.num_faces
    av = Avatar.initial(forest)
    av.d_mu[:] = rng.normal(0, 0.3, av.d_mu.shape)
    av.d_rot[:] = rng.normal(0, 1, av.d_rot.shape)
    forest.split_logits[:] = rng.normal(0, 0.5, forest.split_logits.shape)
    P = np.array([-0.0300916, 0.08229133, 0.00285548], np.float32)
    Q = np.array([0.1187, -0.0113, 0.0542], np.float32)
    V = np.stack({"v1 == v2": [P, Q, Q], "v0 == v1": [P, P, Q], "collinear": [P, Q, 2 * Q - P]}[kind]).astype(
        np.float32
    )
    t = torch.tensor
    tr = FaceBinding(forest).gaussians(t(V), t(forest.split_logits), t(av.d_mu), t(av.d_log_scale), t(av.d_rot))
    inf = binding.GaussianEvaluator(forest, av.d_mu, av.d_log_scale, av.d_rot)(V)
    size = float(np.linalg.norm(Q - P))
    assert np.abs(inf.means[:N] - tr.means.numpy()).max() < 1e-6 * size
    qa, qb = inf.quats[:N].astype(np.float64), tr.quats.numpy().astype(np.float64)
    assert np.abs(np.abs((qa * qb).sum(1)) - 1).max() < 1e-5
    np.testing.assert_allclose(inf.scales[:N], tr.scales.numpy(), rtol=1e-5)
    # The face frames (FaceEvaluator: the exports' and the reference path) are training's too.
    f = binding.FaceEvaluator(forest)(V)
    g = binding.compose(f.t, f.r, f.s, av.d_mu, av.d_log_scale, av.d_rot)
    assert np.abs(g.means[:N] - tr.means.numpy()).max() < 1e-6 * size


@pytest.mark.parametrize("gap", [20.0, 30.0, 60.0])
@pytest.mark.parametrize("root_edge", [0.02, 1e-18])
def test_training_and_inference_agree_on_faces_with_a_vanishing_first_edge(gap, root_edge):
    """Split logits ``gap`` apart put a split point within ~e^-gap of a vertex, so a child's
    first edge is tiny (1e-19 m) or exactly 0 in float32; a root with two vertices 1e-18 m
    apart has one too. Training treats edges <= MIN_EDGE as having no direction; inference
    used to only below 0, building the frame on rounding noise: the viewer showed a
    millimetre splat where training had learned a sub-pixel one."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.train.binding_kernels import FaceBinding

    V = np.array([[0, 0, 0], [root_edge, 0, 0], [0.005, 0.018, 0.003]], np.float32)
    forest = Forest(np.array([[0, 1, 2]], np.int32))
    forest.split(forest.split([0]).ravel())
    N = forest.num_faces
    rng = np.random.default_rng(0)
    forest.split_logits[:] = rng.normal(0, 0.5, (N, 3))
    forest.split_logits[0] = [-gap / 2, gap / 2, -gap / 2]
    av = Avatar.initial(forest)
    av.d_mu[:] = rng.normal(0, 0.3, (N, 3))
    av.d_rot[:] = rng.normal(0, 1, (N, 4))
    inf = binding.GaussianEvaluator(forest, av.d_mu, av.d_log_scale, av.d_rot)(V)
    t = torch.tensor
    tr = FaceBinding(forest).gaussians(t(V), t(forest.split_logits), t(av.d_mu), t(av.d_log_scale), t(av.d_rot))
    s_inf, s_tr = inf.scales[:N].astype(np.float64), tr.scales.numpy().astype(np.float64)
    big = np.maximum(s_inf, s_tr).max(1)
    # sub-micrometre splats are invisible whatever their exact size (MIN_SCALE's float32 exp)
    assert np.all((np.abs(s_inf - s_tr).max(1) <= 1e-4 * big) | (big < 1e-9)), (s_inf.max(1), s_tr.max(1))
    ref = big.max()
    assert np.abs(inf.means[:N] - tr.means.numpy()).max() < 1e-4 * ref
    qa, qb = inf.quats[:N].astype(np.float64), tr.quats.numpy().astype(np.float64)
    assert np.abs(np.abs((qa * qb).sum(1)) - 1).max() < 1e-4


def test_training_and_inference_agree_on_a_sub_femtometre_root():
    """A root with a proper first edge (3e-15 m > MIN_EDGE), not flat for its size, but a normal
    |e1 x e2| = 9e-31 <= MIN_EDGE² (the second edge is 3e-16 m): both sides call it degenerate
    and take the general frame. Without the MIN_EDGE² bound training framed it by its normal
    while inference did not: rotations 0.1 apart in |q·q'|."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.train.binding_kernels import FaceBinding

    forest = Forest(np.array([[0, 1, 2]], np.int32))
    forest.split(forest.split([0]).ravel())
    N = forest.num_faces
    rng = np.random.default_rng(0)
    forest.split_logits[:] = rng.normal(0, 0.5, (N, 3))
    av = Avatar.initial(forest)
    av.d_mu[:] = rng.normal(0, 0.3, (N, 3))
    av.d_rot[:] = rng.normal(0, 1, (N, 4))
    V = np.array([[0, 0, 0], [3e-15, 0, 0], [0, 1.8e-16, 2.4e-16]], np.float32)
    inf = binding.GaussianEvaluator(forest, av.d_mu, av.d_log_scale, av.d_rot)(V)
    t = torch.tensor
    tr = FaceBinding(forest).gaussians(t(V), t(forest.split_logits), t(av.d_mu), t(av.d_log_scale), t(av.d_rot))
    np.testing.assert_array_equal(tr.scales.numpy(), np.float32(binding.MIN_SCALE))  # every face is clamped
    assert np.abs(inf.means[:N] - tr.means.numpy()).max() < 1e-6 * binding.MIN_SCALE
    qa, qb = inf.quats[:N].astype(np.float64), tr.quats.numpy().astype(np.float64)
    assert np.abs(np.abs((qa * qb).sum(1)) - 1).max() < 1e-5


def test_zero_and_tiny_rotation_residuals_match_inference():
    """d_rot of 0 (the face's own frame) or of norm ~1e-30 (its direction): the training kernel
    gives inference's unit quaternions and finite gradients, none for the zero residual (it used
    to give a zero or ~1e-18 quaternion, which the rasteriser refuses)."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.train.binding_kernels import FaceBinding

    V = np.array([[0, 0, 0], [0.02, 0, 0], [0.005, 0.018, 0.003]], np.float32)
    forest = Forest(np.array([[0, 1, 2]], np.int32))
    av = Avatar.initial(forest)
    for d in ([0.0, 0, 0, 0], [1e-30, 1e-30, 0, 0], [0.3, -0.2, 0.1, 0.9]):
        av.d_rot[0] = d
        want = binding.GaussianEvaluator(forest, av.d_mu, av.d_log_scale, av.d_rot)(V).quats[0]
        d_rot = torch.tensor(av.d_rot, requires_grad=True)
        t = torch.tensor
        g = FaceBinding(forest).gaussians(t(V), t(forest.split_logits), t(av.d_mu), t(av.d_log_scale), d_rot)
        np.testing.assert_allclose(g.quats[0].detach().numpy(), want, atol=1e-6)
        (g.quats * torch.tensor([0.1, 0.2, 0.3, 0.4])).sum().backward()
        assert torch.isfinite(d_rot.grad).all()
        if not any(d):  # no direction to differentiate: no gradient (a 1/1e-12 one would swamp the rest)
            assert torch.all(d_rot.grad == 0)


def test_binding_kernels_deterministic_across_thread_counts():
    import numba

    from progressive_avatars.core.train import binding_kernels

    rng = np.random.default_rng(14)
    verts, faces = sphere_mesh(10, 12)
    forest = random_forest(faces, rng, depth=3, frac=0.6)
    plan = binding_kernels.FaceBinding(forest)
    inputs = _kernel_inputs(forest, verts, rng, torch.float32)
    results = []
    for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}) * 2:
        numba.set_num_threads(threads)
        for p in inputs:
            p.grad = None
        out = plan.gaussians(*inputs)
        (out.means.sum() + out.scales.square().sum() + out.quats[:, 1].sum()).backward()
        results.append([x.detach().clone() for x in out] + [p.grad.clone() for p in inputs])
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    for other in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))


def test_binding_kernels_read_float32_as_their_float64_copies():
    """The kernels read and write the trainer's float32 arrays directly (no float64 copies in
    or out) and widen every load, so the Gaussians and gradients are bit for bit those of the
    same values given in float64, rounded once to float32 (what the copies gave). Sizes with
    a wide spread (|d_rot| from 1e-3 to 1e3, log-scales to +-8) would show a sum or an exp
    taken in float32."""
    from progressive_avatars.core.train import binding_kernels

    rng = np.random.default_rng(15)
    verts, faces = sphere_mesh(12, 14)
    forest = random_forest(faces, rng, depth=3, frac=0.6, logit_scale=1.5)
    plan = binding_kernels.FaceBinding(forest)
    N = forest.num_faces
    values = [
        verts + rng.normal(0, 1e-3, verts.shape),
        forest.split_logits,
        rng.normal(0, 0.5, (N, 3)),
        rng.uniform(-8, 8, (N, 3)),
        rng.normal(size=(N, 4)) * 10.0 ** rng.uniform(-3, 3, (N, 1)),
    ]
    values = [np.asarray(v, np.float32) for v in values]  # exactly representable in both
    cot = [rng.normal(size=(N, k)).astype(np.float32) for k in (3, 3, 4)]

    def run(dtype):
        inputs = [torch.tensor(v, dtype=dtype, requires_grad=True) for v in values]
        out = plan.gaussians(*inputs)
        outs = (out.means, out.scales, out.quats)
        sum((x * torch.tensor(c, dtype=dtype)).sum() for x, c in zip(outs, cot)).backward()
        return [x.detach() for x in outs] + [p.grad for p in inputs]

    f32, f64 = run(torch.float32), run(torch.float64)
    for name, a, b in zip(
        ("means", "scales", "quats", "g_verts", "g_logits", "g_d_mu", "g_d_log_scale", "g_d_rot"), f32, f64
    ):
        assert a.dtype == torch.float32, name
        assert torch.equal(a, b.to(torch.float32)), (name, float((a.double() - b).abs().max()))


def test_binding_kernels_refuse_a_backward_after_an_in_place_change():
    """The backward reads the residuals' own memory (no copy): changing one in place between
    forward and backward is refused by torch, not silently differentiated at the new values."""
    from progressive_avatars.core.train import binding_kernels

    rng = np.random.default_rng(16)
    verts, faces = sphere_mesh(4, 6)
    forest = random_forest(faces, rng, depth=2, frac=0.5)
    inputs = _kernel_inputs(forest, verts, rng, torch.float32)
    out = binding_kernels.FaceBinding(forest).gaussians(*inputs)
    with torch.no_grad():
        inputs[2].add_(1.0)  # d_mu, as an optimiser step would
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        out.means.sum().backward()


def test_binding_kernels_give_each_gradient_its_parameters_dtype():
    """Mixed parameter dtypes: each gradient comes back in its own parameter's dtype, at that
    dtype's precision (a float64 parameter's gradient is not rounded through float32)."""
    from progressive_avatars.core.train import binding_kernels

    rng = np.random.default_rng(17)
    verts, faces = sphere_mesh(4, 6)
    forest = random_forest(faces, rng, depth=2, frac=0.5)
    plan = binding_kernels.FaceBinding(forest)
    v, logits, d_mu, d_ls, d_rot = _kernel_inputs(forest, verts, rng, torch.float32)
    d_ls64 = d_ls.detach().double().requires_grad_(True)
    out = plan.gaussians(v, logits, d_mu, d_ls64, d_rot)
    out.scales.sum().backward()
    ref = d_ls64.detach().clone().requires_grad_(True)  # the same values, every input float64
    ref_out = plan.gaussians(*(x.detach().double() for x in (v, logits, d_mu)), ref, d_rot.detach().double())
    ref_out.scales.sum().backward()
    assert d_mu.grad.dtype == torch.float32 and d_ls64.grad.dtype == torch.float64
    assert torch.equal(d_ls64.grad, ref.grad)


def _point_face_forest():
    """Root (0, 1, 2); both splits put the point exactly on the parent's v0 (softmax of
    (1000, 0, 0) is exactly (1, 0, 0) in float64): face 3 = (v0, v1, v0), and its slot-2 child
    (face 8) = (k, i, p) = (v0, v0, v0), a face shrunk to one point under a proper root."""
    f = Forest(np.array([[0, 1, 2]]))
    f.split([0])
    f.split([1])  # face 1 = slot 0 child: (v0, v1, p = v0)
    f.split_logits[0] = f.split_logits[1] = [1000.0, 0.0, 0.0]
    return f


VERTS = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def test_a_face_shrunk_to_a_point_keeps_the_minimum_scale():
    """MIN_SCALE keeps such a Gaussian valid: its face scale is exactly MIN_SCALE (1e-10), never
    0, in the face frames, the fused Gaussian evaluator and the training reference alike."""
    f = _point_face_forest()
    point = 6  # split([1]) appended faces 4, 5, 6: slots 0, 1, 2 of face 1
    assert f.parent[point] == 1 and f.slot[point] == 2
    np.testing.assert_allclose(f.vertex_weights()[point], [[1, 0, 0]] * 3, atol=0)
    geo = binding.evaluate(f, VERTS)
    assert geo.s[point] == np.float32(binding.MIN_SCALE)
    n = f.num_faces
    ev = binding.GaussianEvaluator(f, np.zeros((n, 3)), np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)))
    g = ev(VERTS.astype(np.float32))
    np.testing.assert_array_equal(g.scales[point], np.float32(binding.MIN_SCALE))
    tf = binding_torch.TorchForest(f)
    _, _, s = tf.evaluate(torch.tensor(VERTS), tf.weights(torch.tensor(f.split_logits, dtype=torch.float64)))
    assert float(s[point]) == pytest.approx(1e-10)


@pytest.mark.parametrize("L", [1e20, 1e30])
def test_float32_frames_of_huge_edges(L):
    """e1 = (L, 0, 0), e2 = (0, L, 0) in float32, where L² overflows float32:
    by hand x = (1, 0, 0), y = x × e2 / |x × e2| = (0, 0, 1), z = x × y = (0, -1, 0),
    s = (|e1| + |z · e2|) / 2 = L (a vector normalised without scaling first would come out 0:
    its length inf)."""
    e1 = np.array([[L, 0, 0]], np.float32)
    e2 = np.array([[0, L, 0]], np.float32)
    r, s = binding.frames_from_edges(e1, e2)
    np.testing.assert_allclose(r[0], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-6)
    np.testing.assert_allclose(s[0], L, rtol=1e-6)
    t, r2, s2 = binding.face_frames(np.zeros(3, np.float32), e1[0], e2[0])
    np.testing.assert_allclose(r2, r[0], atol=1e-6)
    np.testing.assert_allclose(t, [L / 3, L / 3, 0], rtol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_frames_of_degenerate_edges_have_finite_gradients(dtype):
    """A zero first edge (x falls back to the second edge) and a flat face (e2 along e1: the
    fallback normal) give finite frames and finite gradients: the masked-out branches must
    not divide by a zero length (0 * inf = NaN through torch.where)."""
    e1 = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=dtype, requires_grad=True)
    e2 = torch.tensor([[0.0, 2.0, 0.0], [3.0, 0.0, 0.0]], dtype=dtype, requires_grad=True)
    r, s = binding_torch.frames_from_edges(e1, e2)
    assert torch.isfinite(r).all() and torch.isfinite(s).all()
    # by hand: face 0 takes x = e2 / |e2| = (0, 1, 0); s = (0 + |z · e2|) / 2 with z ⟂ x: 0 -> 1e-10
    np.testing.assert_allclose(r[0, :, 0].detach().numpy(), [0, 1, 0], atol=1e-6)
    (r.sum() + s.sum()).backward()
    assert torch.isfinite(e1.grad).all() and torch.isfinite(e2.grad).all()


def test_torch_frames_project_x_into_the_given_normals_plane():
    """With the root's normal given, x is e1's part in the plane (the out-of-plane part
    rounding leaves is removed), so r stays orthonormal: e1 = (1, 0, 0.01), normal (0, 0, 2)
    -> x = (1, 0, 0), y = (0, 0, 1), z = x × y = (0, -1, 0)."""
    e1 = torch.tensor([[1.0, 0.0, 0.01]], dtype=torch.float64)
    e2 = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    r, s = binding_torch.frames_from_edges(e1, e2, torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64))
    np.testing.assert_allclose(r[0].numpy(), [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(r[0].T.numpy() @ r[0].numpy(), np.eye(3), atol=1e-12)
