"""FLAME loading (restricted unpickler) and forward pass, on a small FLAME-format model
built here: same keys and shape semantics as generic_model.pkl, pickled with chumpy-like
``Ch`` arrays and a scipy.sparse J_regressor so the real unpickling path runs."""

import contextlib
import os
import pickle
import sys
import types

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from progressive_avatars.core.flame import model as fl
from progressive_avatars.core.flame.model import FlameModelError, UnsafePickleError, flame_forward, load_flame_model

N_V, N_J, N_SHAPE, N_EXPR = 50, 5, 6, 4
PARENTS = np.array([-1, 0, 1, 1, 1])  # FLAME: global, neck, jaw, eye, eye


def make_flame_arrays(seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(N_V, 3))
    v = 0.1 * d / np.linalg.norm(d, axis=1, keepdims=True)
    faces = np.stack([rng.permutation(N_V)[:3] for _ in range(80)]).astype(np.uint32)
    shapedirs = 0.01 * rng.normal(size=(N_V, 3, N_SHAPE + N_EXPR))
    posedirs = 0.005 * rng.normal(size=(N_V, 3, 9 * (N_J - 1)))
    jr = np.zeros((N_J, N_V))
    for j in range(N_J):
        idx = rng.choice(N_V, 4, replace=False)
        jr[j, idx] = 0.25
    w = rng.random((N_V, N_J)) ** 3
    w /= w.sum(1, keepdims=True)
    kintree = np.stack([np.where(PARENTS < 0, 4294967295, PARENTS), np.arange(N_J)]).astype(np.int64)
    return dict(
        v_template=v,
        f=faces,
        shapedirs=shapedirs,
        posedirs=posedirs,
        J_regressor=jr,
        weights=w,
        kintree_table=kintree,
        bs_style="lbs",
        bs_type="lrotmin",
    )


@contextlib.contextmanager
def fake_chumpy():
    """A stand-in ``chumpy.ch.Ch`` importable only while pickling, with chumpy's state layout."""

    class Ch:
        def __init__(self, x):
            self.x = np.asarray(x, np.float64)

        def __getstate__(self):
            # What chumpy's Ch.__getstate__ leaves after dropping _parents and _cache.
            return {
                "x": self.x,
                "_dirty_vars": {"x"},
                "_itr": None,
                "_depends_on_deps": {},
                "_make_dense": False,
                "_make_sparse": False,
            }

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    pkg, mod = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    mod.Ch = Ch
    pkg.ch = mod
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch")}
    sys.modules.update({"chumpy": pkg, "chumpy.ch": mod})
    try:
        yield Ch
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


def write_flame_pkl(path, protocol=2, sparse="csc", seed=0):
    arrays = make_flame_arrays(seed)
    with fake_chumpy() as Ch:
        d = dict(arrays)
        d["shapedirs"] = Ch(arrays["shapedirs"])
        d["v_template"] = Ch(arrays["v_template"])
        d["J_regressor"] = {"csc": sp.csc_matrix, "csr": sp.csr_matrix, "coo": sp.coo_matrix}[sparse](
            arrays["J_regressor"]
        )
        with open(path, "wb") as f:
            pickle.dump(d, f, protocol=protocol)
    assert "chumpy" not in sys.modules
    return arrays


@pytest.fixture(scope="module")
def model_and_arrays(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("flame") / "generic_model.pkl")
    arrays = write_flame_pkl(path)
    return load_flame_model(path, n_shape=N_SHAPE), arrays


def random_params(T, seed=1, scale=0.3):
    rng = np.random.default_rng(seed)
    return dict(
        shape=rng.normal(size=N_SHAPE),
        expr=rng.normal(size=(T, N_EXPR)),
        rotation=scale * rng.normal(size=(T, 3)),
        neck_pose=scale * rng.normal(size=(T, 3)),
        jaw_pose=scale * rng.normal(size=(T, 3)),
        eyes_pose=scale * rng.normal(size=(T, 6)),
        translation=0.05 * rng.normal(size=(T, 3)),
        static_offset=0.002 * rng.normal(size=(1, N_V, 3)),
    )


# ---------------------------------------------------------------------------- loading


@pytest.mark.parametrize("protocol", [1, 2])
@pytest.mark.parametrize("sparse", ["csc", "csr", "coo"])
def test_pickle_with_chumpy_and_sparse_loads(tmp_path, protocol, sparse):
    path = str(tmp_path / "m.pkl")
    arrays = write_flame_pkl(path, protocol=protocol, sparse=sparse)
    m = load_flame_model(path, n_shape=N_SHAPE)
    np.testing.assert_array_equal(m.v_template, arrays["v_template"])
    np.testing.assert_array_equal(m.shapedirs, arrays["shapedirs"])
    np.testing.assert_array_equal(m.J_regressor, arrays["J_regressor"])
    np.testing.assert_array_equal(m.parents, PARENTS)
    assert m.faces.dtype == np.int32 and m.faces.shape == (80, 3)
    assert (m.n_shape, m.n_expr, m.n_joints, m.n_vertices) == (N_SHAPE, N_EXPR, N_J, N_V)
    assert "chumpy" not in sys.modules  # the loader never needs the real package


def test_npz_conversion_round_trip(tmp_path, model_and_arrays):
    m, _ = model_and_arrays
    p = str(tmp_path / "flame.npz")
    m.save_npz(p)
    m2 = load_flame_model(p)  # n_shape travels in the npz
    assert m2.n_shape == N_SHAPE
    prm = random_params(3)
    np.testing.assert_array_equal(flame_forward(m, **prm), flame_forward(m2, **prm))


def test_default_split_caps_at_component_count(tmp_path):
    path = str(tmp_path / "m.pkl")
    write_flame_pkl(path)
    m = load_flame_model(path)  # 300 requested, 10 available: all shape, no expression
    assert (m.n_shape, m.n_expr) == (N_SHAPE + N_EXPR, 0)


@pytest.mark.parametrize(
    "target,expected",
    [("os.system", "system"), ("builtins.eval", "builtins.eval"), ("subprocess.Popen", "subprocess.Popen")],
)
def test_malicious_pickle_refused_without_side_effect(tmp_path, target, expected):
    marker = tmp_path / "pwned"
    cmd = f"touch {marker}"

    class Evil:
        def __reduce__(self):
            if target == "os.system":
                return (os.system, (cmd,))
            if target == "builtins.eval":
                return (eval, (f"__import__('os').system({cmd!r})",))
            import subprocess

            return (subprocess.Popen, (["touch", str(marker)],))

    arrays = make_flame_arrays()
    arrays["v_template"] = Evil()
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps(arrays, protocol=2))
    with pytest.raises(UnsafePickleError) as ei:
        load_flame_model(str(path))
    msg = str(ei.value)
    assert str(path) in msg and "refused to load global" in msg and expected in msg
    assert not marker.exists()


def test_reconstruct_of_non_array_type_refused(tmp_path):
    # numpy's _reconstruct is allowed, but only to rebuild ndarrays.
    payload = b"\x80\x02cnumpy.core.multiarray\n_reconstruct\nc__builtin__\nset\nK\x00\x85U\x01b\x87R."
    p = tmp_path / "x.pkl"
    p.write_bytes(payload)
    with pytest.raises(FlameModelError, match="non-ndarray"):
        load_flame_model(str(p))


def test_model_errors_name_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pkl"):
        load_flame_model(str(tmp_path / "nope.pkl"))
    p = tmp_path / "partial.pkl"
    a = make_flame_arrays()
    del a["weights"]
    p.write_bytes(pickle.dumps(a, protocol=2))
    with pytest.raises(FlameModelError, match=r"partial\.pkl.*missing keys \['weights'\]"):
        load_flame_model(str(p))
    p2 = tmp_path / "garbage.pkl"
    p2.write_bytes(b"\x80\x02not a pickle at all")
    with pytest.raises(FlameModelError, match="garbage.pkl"):
        load_flame_model(str(p2))
    a = make_flame_arrays()
    a["posedirs"] = a["posedirs"][:, :, :30]
    p3 = tmp_path / "badpose.pkl"
    p3.write_bytes(pickle.dumps(a, protocol=2))
    with pytest.raises(FlameModelError, match=r"badpose\.pkl: posedirs"):
        load_flame_model(str(p3))


# ---------------------------------------------------------------------------- forward


def reference_forward(a, n_shape, prm):
    """Independent, loop-based LBS written from the FLAME/SMPL equations (test only)."""
    T = prm["expr"].shape[0]
    out = np.zeros((T, N_V, 3))
    for t in range(T):
        betas = np.concatenate([prm["shape"], prm["expr"][t]])
        vs = a["v_template"] + prm["static_offset"][0] + np.tensordot(a["shapedirs"], betas, axes=([2], [0]))
        Jt = a["J_regressor"] @ vs
        pose = [
            prm["rotation"][t],
            prm["neck_pose"][t],
            prm["jaw_pose"][t],
            prm["eyes_pose"][t][:3],
            prm["eyes_pose"][t][3:],
        ]
        Rs = [Rotation.from_rotvec(p).as_matrix() for p in pose]
        feat = np.concatenate([(R - np.eye(3)).ravel() for R in Rs[1:]])
        vp = vs + np.tensordot(a["posedirs"], feat, axes=([2], [0]))
        G = []
        for j in range(N_J):
            L = np.eye(4)
            L[:3, :3] = Rs[j]
            L[:3, 3] = Jt[j] - (Jt[PARENTS[j]] if j else 0)
            G.append(L if j == 0 else G[PARENTS[j]] @ L)
        for v in range(N_V):
            M = sum(
                a["weights"][v, j] * G[j] @ np.block([[np.eye(3), -Jt[j][:, None]], [np.zeros((1, 3)), 1]])
                for j in range(N_J)
            )
            out[t, v] = (M @ np.append(vp[v], 1.0))[:3] + prm["translation"][t]
    return out


def test_forward_matches_independent_reference(model_and_arrays):
    m, a = model_and_arrays
    prm = random_params(3)
    got = flame_forward(m, dtype=np.float64, **prm)
    np.testing.assert_allclose(got, reference_forward(a, N_SHAPE, prm), atol=1e-12)


def test_zero_pose_is_template_plus_blendshapes(model_and_arrays):
    m, a = model_and_arrays
    rng = np.random.default_rng(3)
    shape, expr = rng.normal(size=N_SHAPE), rng.normal(size=(2, N_EXPR))
    got = flame_forward(m, shape=shape, expr=expr, dtype=np.float64)
    betas = np.concatenate([np.broadcast_to(shape, (2, N_SHAPE)), expr], 1)
    want = a["v_template"] + np.einsum("vck,tk->tvc", a["shapedirs"], betas)
    np.testing.assert_allclose(got, want, atol=1e-12)
    # Fewer coefficients than the model has are zero-padded.
    np.testing.assert_allclose(
        flame_forward(m, shape=shape[:2], dtype=np.float64)[0],
        a["v_template"] + a["shapedirs"][:, :, :2] @ shape[:2],
        atol=1e-12,
    )


def test_global_rotation_is_rigid_about_root_joint(model_and_arrays):
    m, a = model_and_arrays
    prm = random_params(1)
    base = dict(shape=prm["shape"], expr=prm["expr"], static_offset=prm["static_offset"])
    rest = flame_forward(m, dtype=np.float64, **base)[0]
    r = np.array([0.3, -0.5, 0.2])
    R = Rotation.from_rotvec(r).as_matrix()
    t = np.array([0.01, 0.02, -0.03])
    moved = flame_forward(m, rotation=r, translation=t, dtype=np.float64, **base)[0]
    j0 = a["J_regressor"][0] @ rest
    np.testing.assert_allclose(moved, (rest - j0) @ R.T + j0 + t, atol=1e-12)
    # Rigid: pairwise distances kept.
    d0 = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
    d1 = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    np.testing.assert_allclose(d0, d1, atol=1e-12)


def test_axis_angle_matches_scipy_including_tiny_angles():
    rng = np.random.default_rng(0)
    r = np.concatenate(
        [rng.normal(size=(20, 3)), 1e-9 * rng.normal(size=(5, 3)), np.zeros((1, 3)), np.array([[np.pi, 0, 0]])]
    )
    np.testing.assert_allclose(fl.axis_angle_to_matrix(r), Rotation.from_rotvec(r).as_matrix(), atol=1e-14)


def test_parameter_validation(model_and_arrays):
    m, _ = model_and_arrays
    with pytest.raises(ValueError, match="non-zero coefficients up to number 5 "):
        flame_forward(m, expr=np.eye(1, N_EXPR + 96, 4))  # one non-zero beyond the model's N_EXPR = 4
    flame_forward(m, expr=np.concatenate([np.ones((1, N_EXPR)), np.zeros((1, 96))], 1))  # zero tail is fine
    with pytest.raises(ValueError, match="static_offset"):
        flame_forward(m, static_offset=np.zeros((1, N_V + 1, 3)))
    with pytest.raises(ValueError, match="number of frames"):
        flame_forward(m, rotation=np.zeros((3, 3)), jaw_pose=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="NaN"):
        flame_forward(m, jaw_pose=np.array([[np.nan, 0, 0]]))


def test_chunked_frames_match_single_frames(model_and_arrays):
    m, _ = model_and_arrays
    prm = random_params(fl._CHUNK + 5, seed=7)
    allv = flame_forward(m, **prm)
    for t in (0, fl._CHUNK - 1, fl._CHUNK, fl._CHUNK + 4):
        one = {k: (v[t : t + 1] if k not in ("shape", "static_offset") else v) for k, v in prm.items()}
        np.testing.assert_allclose(flame_forward(m, **one)[0], allv[t], atol=1e-6)


# ---------------------------------------------------------------------------- torch twin


def test_torch_agrees_with_numpy_float32(model_and_arrays):
    torch = pytest.importorskip("torch")
    from progressive_avatars.core.train.flame_torch import FlameTorch

    m, _ = model_and_arrays
    prm = random_params(6, seed=5, scale=0.6)
    want = flame_forward(m, **prm)
    layer = FlameTorch(m)
    got = layer(**{k: torch.as_tensor(v, dtype=torch.float32) for k, v in prm.items()}).numpy()
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-5)
    # Zero pose, default arguments.
    np.testing.assert_allclose(layer().numpy()[0], m.v_template, atol=1e-6)


def test_torch_counts_frames_as_numpy_does(model_and_arrays):
    """One frame's pose in its [2,3] / [J,3] form and a [V,3] dynamic offset are one frame in
    the torch twin too (it returned 2, J or V copies where flame_forward returns one)."""
    torch = pytest.importorskip("torch")
    from progressive_avatars.core.train.flame_torch import FlameTorch

    m, _ = model_and_arrays
    layer = FlameTorch(m, dtype=torch.float64)
    rng = np.random.default_rng(11)
    eyes, jaw, off = rng.normal(size=(2, 3)), rng.normal(size=3), rng.normal(size=(N_V, 3))
    full = np.concatenate([np.zeros(6), jaw, eyes.ravel()]).reshape(N_J, 3)
    for kw in (dict(eyes_pose=eyes, jaw_pose=jaw), dict(pose=full), dict(dynamic_offset=off)):
        want = flame_forward(m, **kw, dtype=np.float64)
        got = layer(**{k: torch.as_tensor(v) for k, v in kw.items()}).numpy()
        assert got.shape == want.shape == (1, N_V, 3), (list(kw), got.shape)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    # Beside two-frame parameters one frame's [6] eyes and [V,3] offset broadcast; [2,3] eyes are
    # two frames of the wrong width there (both refuse); two frames of offsets do not fit three.
    two = dict(expr=rng.normal(size=(2, N_EXPR)), eyes_pose=eyes.ravel(), dynamic_offset=off)
    np.testing.assert_allclose(
        layer(**{k: torch.as_tensor(v) for k, v in two.items()}).numpy(),
        flame_forward(m, **two, dtype=np.float64),
        rtol=0,
        atol=1e-9,
    )
    two["eyes_pose"] = eyes
    with pytest.raises(ValueError, match="eyes_pose: expected 6 values per frame"):
        flame_forward(m, **two)
    with pytest.raises(ValueError, match="eyes_pose: expected 6 values per frame"):
        layer(**{k: torch.as_tensor(v) for k, v in two.items()})
    with pytest.raises(ValueError, match="disagree on the number of frames"):
        layer(
            expr=torch.zeros(3, N_EXPR, dtype=torch.float64), dynamic_offset=torch.zeros(2, N_V, 3, dtype=torch.float64)
        )
    # Offsets in any other layout are refused by both, not re-cut into [T,V,3] by the torch twin.
    for name, bad in (("dynamic_offset", np.zeros((2, N_V * 3))), ("static_offset", np.zeros(N_V * 3))):
        kw = dict(expr=np.zeros((2, N_EXPR)), **{name: bad})
        with pytest.raises(ValueError, match=rf"{name}: expected \[1\|T,{N_V},3\]"):
            flame_forward(m, **kw)
        with pytest.raises(ValueError, match=rf"{name}: expected \[1\|T,{N_V},3\]"):
            layer(**{k: torch.as_tensor(v) for k, v in kw.items()})


def test_torch_gradients_finite_and_correct(model_and_arrays):
    torch = pytest.importorskip("torch")
    from progressive_avatars.core.train.flame_torch import FlameTorch

    m, _ = model_and_arrays
    layer = FlameTorch(m, dtype=torch.float64)
    rng = np.random.default_rng(2)
    jaw = torch.tensor(0.2 * rng.normal(size=(1, 3)), requires_grad=True)
    expr = torch.tensor(rng.normal(size=(1, 2)), requires_grad=True)
    probe = torch.tensor(rng.normal(size=(1, N_V, 3)))  # random projection: one backward pass, full coverage
    assert torch.autograd.gradcheck(
        lambda j, e: (layer(jaw_pose=j, expr=e) * probe).sum(), (jaw, expr), eps=1e-6, atol=1e-6
    )
    # At exactly zero pose (where a naive Rodrigues gives NaN gradients).
    zero = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    layer(rotation=zero, neck_pose=zero).sum().backward()
    assert torch.isfinite(zero.grad).all()


# ---------------------------------------------------------------------------- closed-form checks


def two_joint_arm():
    """A 4-vertex arm small enough to pose by hand: a root joint at vertex a = (0,0,0) and a
    child joint at b = (1,0,0), each regressed from its one vertex; a, b follow the root and
    c = (2,0,0), d = (2,1,0) the child (one-hot weights). The shape component moves b by +x and
    c by +z, the expression component d by +y. Two pose correctives on the child's features
    (R - I) row-major: d.x += 0.5 (R-I)[0,1] and c.z += 0.25 (R-I)[1,0]."""
    V = 4
    shapedirs = np.zeros((V, 3, 2))
    shapedirs[1, 0, 0] = shapedirs[2, 2, 0] = 1.0
    shapedirs[3, 1, 1] = 1.0
    posedirs = np.zeros((V, 3, 9))
    posedirs[3, 0, 1] = 0.5
    posedirs[2, 2, 3] = 0.25
    return fl.FlameModel(
        v_template=np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 1, 0]]),
        faces=np.array([[0, 1, 2], [1, 2, 3]]),
        shapedirs=shapedirs,
        posedirs=posedirs,
        J_regressor=np.eye(2, V),
        weights=np.array([[1.0, 0], [1, 0], [0, 1], [0, 1]]),
        parents=np.array([-1, 0]),
        n_shape=1,
    )


def test_two_joint_arm_posed_by_hand():
    arm = two_joint_arm()
    q = np.pi / 2  # about z: (x, y, z) -> (-y, x, z); R - I = [[-1,-1,0],[1,-1,0],[0,0,0]]
    pose = np.array(
        [
            [0, 0, 0, 0, 0, q],  # child only: c, d swing about b, both correctives on
            [0, 0, q, 0, 0, 0],  # root only: rigid about a; the root is no corrective feature
            [0, 0, q, 0, 0, q],  # both, then translated (after skinning, so not rotated)
            [0, 0, 0, 0, 0, q],  # child, with the shape moving its joint b to (3,0,0)
        ]
    )
    got = flame_forward(
        arm,
        pose=pose,
        shape=[[0], [0], [0], [2]],
        translation=[[0, 0, 0], [0, 0, 0], [0.5, 0, -1], [0, 0, 0]],
        dtype=np.float64,
    )
    want = [
        [[0, 0, 0], [1, 0, 0], [1, 1, 0.25], [0, 0.5, 0]],
        [[0, 0, 0], [0, 1, 0], [0, 2, 0], [-1, 2, 0]],
        [[0.5, 0, -1], [0.5, 1, -1], [-0.5, 1, -0.75], [0, 0, -1]],
        [[0, 0, 0], [3, 0, 0], [3, -1, 2.25], [2, -1.5, 0]],
    ]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    # A static offset is part of the rest shape, so it moves the joints like the shape does.
    offset = np.zeros((1, 4, 3))
    offset[0, 1, 0] = offset[0, 2, 2] = 2.0
    np.testing.assert_allclose(
        flame_forward(arm, pose=pose[3], static_offset=offset, dtype=np.float64)[0], want[3], rtol=0, atol=1e-12
    )
    # Zero pose: template plus blendshapes plus both offsets.
    dyn = np.full((1, 4, 3), 0.125)
    rest = flame_forward(
        arm, pose=np.zeros(6), shape=[0.5], expr=[-3], static_offset=offset, dynamic_offset=dyn, dtype=np.float64
    )
    np.testing.assert_allclose(
        rest[0], [[0.125] * 3, [3.625, 0.125, 0.125], [2.125, 0.125, 2.625], [2.125, -1.875, 0.125]], rtol=0, atol=1e-12
    )
    with pytest.raises(ValueError, match="has 2 joints, not FLAME's 5"):
        flame_forward(arm, jaw_pose=[0, 0, q])


def test_chunks_keep_their_frames_offsets_and_report_progress(monkeypatch):
    monkeypatch.setattr(fl, "_CHUNK", 2)
    arm = two_joint_arm()
    dyn = np.zeros((5, 4, 3))
    dyn[:, 3, 2] = np.arange(5)
    calls = []
    got = flame_forward(
        arm, pose=np.zeros(6), dynamic_offset=dyn, dtype=np.float64, progress=lambda *a: calls.append(a)
    )
    assert calls == [(2, 5), (4, 5), (5, 5)]
    np.testing.assert_allclose(got[:, 3], [[2, 1, t] for t in range(5)], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[:, :3], np.broadcast_to(arm.v_template[:3], (5, 3, 3)), rtol=0, atol=1e-12)


def test_rodrigues_of_known_axis_angles():
    c, s = np.cos(0.09), np.sin(0.09)  # small enough to tempt a series, large enough to need the exact form
    n = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    r = np.array([[np.pi / 2, 0, 0], [0, np.pi / 2, 0], [0, 0, np.pi / 2], [0, 0, 0.09], np.pi * n])
    want = [
        [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
        [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],
        [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
        [[c, -s, 0], [s, c, 0], [0, 0, 1]],
        2 * np.outer(n, n) - np.eye(3),  # a half turn about n
    ]
    np.testing.assert_allclose(fl.axis_angle_to_matrix(r), want, rtol=0, atol=1e-15)


def test_one_frame_in_any_of_its_documented_forms(model_and_arrays):
    m, _ = model_and_arrays
    rng = np.random.default_rng(9)
    eyes, jaw = rng.normal(size=6), rng.normal(size=3)
    want = flame_forward(m, eyes_pose=eyes[None], jaw_pose=jaw[None], dtype=np.float64)
    assert want.shape == (1, N_V, 3)
    # [2,3] eyes and [J,3] poses were read as 2 and J frames of the wrong width.
    np.testing.assert_array_equal(flame_forward(m, eyes_pose=eyes.reshape(2, 3), jaw_pose=jaw, dtype=np.float64), want)
    full = np.concatenate([np.zeros(6), jaw, eyes]).reshape(N_J, 3)
    np.testing.assert_array_equal(flame_forward(m, pose=full, dtype=np.float64), want)
    # A [V,3] dynamic offset is one frame (it gave V copies of it).
    off = rng.normal(size=(N_V, 3))
    got = flame_forward(m, dynamic_offset=off, dtype=np.float64)
    np.testing.assert_allclose(got, (m.v_template + off)[None], rtol=0, atol=1e-12)
    # An empty pose array is no pose.
    np.testing.assert_array_equal(flame_forward(m, jaw_pose=np.array([])), flame_forward(m))


def test_offsets_checked(model_and_arrays):
    m, _ = model_and_arrays
    two = dict(expr=np.zeros((2, N_EXPR)))
    with pytest.raises(ValueError, match=r"static_offset: expected \[1\|T,50,3\], got \(3, 50, 3\)"):
        flame_forward(m, static_offset=np.zeros((3, N_V, 3)), **two)
    bad = np.zeros((1, N_V, 3))
    bad[0, 7, 1] = np.nan
    with pytest.raises(ValueError, match="FLAME offsets contain NaN"):
        flame_forward(m, static_offset=bad)


# ---------------------------------------------------------------------------- model arrays


def _model(**override):
    return fl._model_from_mapping(dict(make_flame_arrays(), **override), "test.pkl", N_SHAPE)


def _nan_at(key):
    a = np.array(make_flame_arrays()[key], np.float64)
    a.flat[a.size // 2] = np.nan
    return a


@pytest.mark.parametrize(
    "override, message",
    [
        (dict(kintree_table=np.array([[-1, 0, 2, 1, 1], [0, 1, 2, 3, 4]])), "parents must precede"),
        (dict(kintree_table=np.array([[-1, 0, -1, 1, 1], [0, 1, 2, 3, 4]])), "parents must precede"),
        (dict(kintree_table=np.zeros((3, N_J), np.int64)), r"kintree_table must be \[2,J\]"),
        (dict(kintree_table=np.array([[-1, 0, 1, 1, 1], [0, 1, 1, 3, 4]])), r"number the joints 0\.\.4 once each"),
        (dict(f=np.array([[0, 1, N_V]])), "faces index outside"),
        (dict(f=np.array([[0, -1, 2]])), "faces index outside"),
        (dict(weights=np.ones((N_V, N_J + 1))), r"weights must be \[50,5\]"),
        (dict(weights=_nan_at("weights")), "weights contains NaN"),
        (dict(posedirs=_nan_at("posedirs")), "posedirs contains NaN"),
        (dict(shapedirs=_nan_at("shapedirs")), "shapedirs contains NaN"),
        (dict(J_regressor=_nan_at("J_regressor")), "J_regressor contains NaN"),
    ],
    ids=[
        "self-parent",
        "negative-parent",
        "kintree-3-rows",
        "kintree-duplicate-id",
        "face-V",
        "face-negative",
        "weights-J",
        "nan-weights",
        "nan-posedirs",
        "nan-shapedirs",
        "nan-regressor",
    ],
)
def test_inconsistent_model_arrays_refused(override, message):
    with pytest.raises(FlameModelError, match=r"test\.pkl: .*" + message):
        _model(**override)


def test_other_array_layouts_read_alike():
    a = make_flame_arrays()
    P = 9 * (N_J - 1)
    m = _model(
        shapedirs=a["shapedirs"].reshape(N_V * 3, -1),  # [V*3,K], vertex-major
        posedirs=a["posedirs"].reshape(N_V * 3, P).T,  # [P,V*3], the transpose some exports keep
        kintree_table=a["kintree_table"][:, [3, 0, 4, 2, 1]],  # columns in any order
    )
    np.testing.assert_array_equal(m.shapedirs, a["shapedirs"])
    np.testing.assert_array_equal(m.posedirs, a["posedirs"])
    np.testing.assert_array_equal(m.parents, PARENTS)
    neg = fl._model_from_mapping(make_flame_arrays(), "test.pkl", -2)
    assert (neg.n_shape, neg.n_expr) == (0, N_SHAPE + N_EXPR)


def test_pickled_fortran_arrays_and_duplicate_sparse_entries(tmp_path):
    a = make_flame_arrays()
    d = dict(a, shapedirs=np.asfortranarray(a["shapedirs"]), weights=np.asfortranarray(a["weights"]))
    # scipy keeps repeated COO entries and sums them when densifying.
    rows, cols = [0, 0, 1, 2, 3, 4, 4], [5, 5, 6, 7, 8, 9, 1]
    d["J_regressor"] = sp.coo_matrix(([0.25, 0.5, 1.0, 1.0, 1.0, 0.5, 0.5], (rows, cols)), shape=(N_J, N_V))
    jr = np.zeros((N_J, N_V))
    jr[0, 5], jr[1, 6], jr[2, 7], jr[3, 8], jr[4, 9], jr[4, 1] = 0.75, 1, 1, 1, 0.5, 0.5
    for protocol in (2, 5):
        p = tmp_path / f"f{protocol}.pkl"
        p.write_bytes(pickle.dumps(d, protocol=protocol))
        m = load_flame_model(str(p), n_shape=N_SHAPE)
        np.testing.assert_array_equal(m.shapedirs, a["shapedirs"])
        np.testing.assert_array_equal(m.weights, a["weights"])
        np.testing.assert_array_equal(m.J_regressor, jr)


@pytest.mark.parametrize("top", [[1, 2], 5, None])
def test_pickle_that_is_not_a_dict_refused(tmp_path, top):
    p = tmp_path / "list.pkl"
    p.write_bytes(pickle.dumps(top, protocol=2))
    with pytest.raises(FlameModelError, match=r"list\.pkl: expected a dict of arrays"):
        load_flame_model(str(p))
