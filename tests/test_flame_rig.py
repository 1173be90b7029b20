"""The FLAME rig (shape keys + keyed armature) reproduces FLAME exactly, checked outside
Blender by evaluating it the way Blender does (tests/test_blender_extension.py checks that
Blender agrees)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from progressive_avatars.core.flame.model import _model_from_mapping, flame_forward
from progressive_avatars.core.flame.rig import SLIDER_LIMIT, build_flame_rig

from tests.test_flame import N_EXPR, N_SHAPE, make_flame_arrays, random_params  # noqa: E402

MODEL = _model_from_mapping(make_flame_arrays(seed=5), "test model", N_SHAPE)


def test_rig_equals_flame_and_correctives_follow_bones():
    prm = random_params(7, seed=2, scale=0.5)
    rig = build_flame_rig(MODEL, prm)
    want = flame_forward(MODEL, **prm, dtype=np.float64)
    np.testing.assert_allclose(rig.vertices(), want, atol=1e-12)
    np.testing.assert_allclose(rig.vertices(pose_from_bones=False), want, atol=1e-12)
    # The stored corrective values are what the bones' rotations give (Blender drives them).
    L = rig.local_matrices()
    np.testing.assert_allclose((L[:, 1:, :3, :3] - np.eye(3)).reshape(7, -1), rig.pose_values, atol=1e-12)
    # With no expression the non-root bones are pure rotations about their rest heads.
    still = build_flame_rig(MODEL, dict(prm, expr=np.zeros((7, N_EXPR))))
    np.testing.assert_allclose(still.locations[:, 1:], 0.0, atol=1e-12)
    assert rig.expr_key_names()[0] == "expr_000" and len(rig.pose_key_names()) == 36
    assert rig.pose_key_names()[9] == "pose_jaw_00"


def test_nersemble_placement_and_scaled_keys():
    T = 5
    prm = random_params(T, seed=3)
    prm["expr"][1, 2] = -31.0  # beyond the slider range: the key is stored scaled
    R = Rotation.random(T, random_state=4).as_matrix()
    local = {k: v for k, v in prm.items() if k not in ("rotation", "translation")}
    want = (
        1.7 * np.einsum("tab,tvb->tva", R, flame_forward(MODEL, **local, dtype=np.float64))
        + prm["translation"][:, None]
    )
    # NeRSemble files hold the placement twice (Euler rotation and rotation_matrices): FLAME's own
    # rotation stays zero, or the head would be turned by it on top of the placement.
    rig = build_flame_rig(
        MODEL,
        dict(
            local,
            rotation=prm["rotation"],
            rotation_matrices=R,
            translation=prm["translation"],
            scale=np.array([[1.7]]),
        ),
    )
    np.testing.assert_allclose(rig.vertices(), want, atol=1e-12)
    np.testing.assert_allclose(rig.scales[:, 0], 1.7)
    np.testing.assert_array_equal(rig.scales[:, 1:], 1.0)
    assert np.abs(rig.expr_values).max() <= SLIDER_LIMIT
    assert rig.expr_scale[2] == pytest.approx(31.0 / (SLIDER_LIMIT * 0.999))


def test_quaternions_sign_continuous_through_a_full_turn():
    T = 40
    jaw = np.zeros((T, 3))
    jaw[:, 0] = np.linspace(0, 2 * np.pi * 0.99, T)  # passes 180 degrees, where q and -q swap
    prm = dict(random_params(1, seed=6), jaw_pose=jaw, expr=np.zeros((T, N_EXPR)))
    prm = {
        k: (v if k in ("shape", "static_offset", "jaw_pose", "expr") else np.repeat(v, T, axis=0))
        for k, v in prm.items()
    }
    rig = build_flame_rig(MODEL, prm)
    dots = np.sum(rig.quaternions[1:, 2] * rig.quaternions[:-1, 2], axis=-1)
    assert dots.min() > 0.9
    np.testing.assert_allclose(rig.vertices(), flame_forward(MODEL, **prm, dtype=np.float64), atol=1e-12)


def test_what_a_rig_cannot_hold():
    prm = random_params(3, seed=7)
    dyn = np.zeros((3, MODEL.n_vertices, 3))
    assert build_flame_rig(MODEL, dict(prm, dynamic_offset=dyn)).ignored == ()
    dyn[1, 4] = 1e-3
    assert build_flame_rig(MODEL, dict(prm, dynamic_offset=dyn)).ignored == ("dynamic_offset",)
    with pytest.raises(ValueError, match="identity shape changes"):
        build_flame_rig(MODEL, dict(prm, shape=np.random.default_rng(0).normal(size=(3, N_SHAPE))))


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1), pose_scale=st.floats(0.0, 3.0), expr_scale=st.floats(0.0, 40.0), T=st.integers(1, 4)
)
def test_rig_matches_flame_for_any_pose(seed, pose_scale, expr_scale, T):
    rng = np.random.default_rng(seed)
    prm = dict(
        shape=rng.normal(size=N_SHAPE),
        expr=expr_scale * rng.normal(size=(T, N_EXPR)),
        rotation=pose_scale * rng.normal(size=(T, 3)),
        neck_pose=pose_scale * rng.normal(size=(T, 3)),
        jaw_pose=pose_scale * rng.normal(size=(T, 3)),
        eyes_pose=pose_scale * rng.normal(size=(T, 6)),
        translation=rng.normal(size=(T, 3)),
    )
    rig = build_flame_rig(MODEL, prm)
    want = flame_forward(MODEL, **prm, dtype=np.float64)
    assert np.all(np.isfinite(rig.quaternions)) and np.abs(rig.expr_values).max(initial=0) <= SLIDER_LIMIT
    np.testing.assert_allclose(rig.vertices(), want, atol=1e-9 * max(1.0, np.abs(want).max()))


@pytest.mark.parametrize("key, value", [("translation", 1e39), ("jaw_pose", 1e200), ("expr", 1e300)])
def test_rig_refuses_what_blender_cannot_hold(key, value):
    """A translation beyond float32, or a pose or expression so large its keys overflow, is
    refused: Blender would store it as inf/NaN keyframes and the import would 'succeed'."""
    prm = random_params(3, seed=8)
    prm[key] = np.full_like(prm[key], value)
    with np.errstate(all="ignore"), pytest.raises(ValueError, match="not finite numbers a rig can hold"):
        build_flame_rig(MODEL, prm)


def test_pose_keys_named_row_then_column():
    """A jaw turned 90 degrees about z: R - I = [[-1,-1,0],[1,-1,0],[0,0,0]], so the key named
    pose_jaw_01 (row 0, column 1) holds -1 and pose_jaw_10 holds +1."""
    prm = dict(jaw_pose=[[0, 0, np.pi / 2]])
    rig = build_flame_rig(MODEL, prm)
    names = rig.pose_key_names()
    assert names[9:18] == [f"pose_jaw_{a}{b}" for a in range(3) for b in range(3)]
    values = dict(zip(names, rig.pose_values[0]))
    assert [values[f"pose_jaw_{ab}"] for ab in ("00", "01", "02", "10", "11", "12", "20", "21", "22")] == pytest.approx(
        [-1, -1, 0, 1, -1, 0, 0, 0, 0], abs=1e-15
    )
    assert values["pose_neck_01"] == 0.0 and values["pose_eye_1_22"] == 0.0


def test_per_frame_static_offset_refused():
    prm = random_params(3, seed=9)
    prm["static_offset"] = np.repeat(prm["static_offset"], 3, axis=0)
    prm["static_offset"][2, 0, 0] += 1e-3
    with pytest.raises(ValueError, match="per-frame offsets cannot be carried by a rig"):
        build_flame_rig(MODEL, prm)


def test_overflowing_keys_refused_even_where_nothing_else_overflows():
    # An expression direction that moves no joint: only its scaled shape key leaves float32.
    arrays = make_flame_arrays(seed=5)
    arrays["shapedirs"][arrays["J_regressor"].any(axis=0), :, -1] = 0.0
    still_joints = _model_from_mapping(arrays, "test model", N_SHAPE)
    expr = np.zeros((1, N_EXPR))
    expr[0, -1] = 1e42
    with pytest.raises(ValueError, match="expression shapes that are not finite numbers"):
        build_flame_rig(still_joints, dict(expr=expr))
    # A placement scale beyond float32 whose translation keeps the root bone's location at 0.
    s, j0 = 1e39, MODEL.J_regressor[0] @ MODEL.v_template
    with pytest.raises(ValueError, match="bone scales that are not finite numbers"):
        build_flame_rig(MODEL, dict(rotation_matrices=np.eye(3)[None], scale=s, translation=(1 - s) * j0[None]))
