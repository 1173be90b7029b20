"""core/geometry/: rotations (torch paths, w >= 0, tiny angles) and cameras (validation, look_at
handedness, scaled, K, viewmat), against values worked out by hand."""

import math

import numpy as np
import pytest
import torch

from progressive_avatars.core.geometry.camera import Camera
from progressive_avatars.core.geometry.rotations import (
    axis_angle_to_matrix,
    quat_normalize,
    quat_to_rotmat,
    rotmat_to_quat,
)


def test_torch_zero_quaternion_stays_zero_with_finite_gradient():
    q = torch.zeros(2, 4, dtype=torch.float64, requires_grad=True)
    u = quat_normalize(q)
    assert torch.equal(u.detach(), torch.zeros(2, 4, dtype=torch.float64))
    R = quat_to_rotmat(q)
    np.testing.assert_array_equal(R.detach().numpy(), np.broadcast_to(np.eye(3), (2, 3, 3)))
    R.sum().backward()
    assert torch.all(torch.isfinite(q.grad))


def _rz(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])


@pytest.mark.parametrize("kind", ["numpy", "torch"])
def test_rotmat_to_quat_has_w_nonnegative_off_the_w_pivot(kind):
    # 200 degrees about z: the z component is the pivot; q = ±(cos 100°, 0, 0, sin 100°),
    # and with w >= 0 it is (-cos 100°, 0, 0, -sin 100°) = (0.17365, 0, 0, -0.98481).
    R = _rz(200.0)[None]
    q = rotmat_to_quat(R) if kind == "numpy" else rotmat_to_quat(torch.tensor(R)).numpy()
    np.testing.assert_allclose(q[0], [0.17364817766693041, 0, 0, -0.984807753012208], atol=1e-12)


def test_torch_axis_angle_quarter_turn_by_hand():
    R = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=torch.float64))[0].numpy()
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    R = axis_angle_to_matrix(torch.tensor([[0.3, 0.0, 0.0]], dtype=torch.float64))[0].numpy()
    c, s = math.cos(0.3), math.sin(0.3)
    np.testing.assert_allclose(R, [[1, 0, 0], [0, c, -s], [0, s, c]], atol=1e-15)


def test_numpy_axis_angle_series_branch_is_exact_to_rounding():
    # th = 5e-5 (th^2 = 2.5e-9 < 1e-8: the Taylor branch); the off-diagonal entries are
    # sin(th)·k_i ± 2 sin^2(th/2)·k_j k_l, which float64 gets to ~1e-16 relative.
    axis = np.array([2.0, -3.0, 6.0]) / 7.0
    th = 5e-5
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    want = np.eye(3) + math.sin(th) * K + 2 * math.sin(th / 2) ** 2 * (K @ K)
    got = axis_angle_to_matrix(th * axis)
    off = ~np.eye(3, dtype=bool)
    np.testing.assert_allclose(got[off], want[off], rtol=1e-12)


def test_rotmat_to_quat_of_a_slightly_scaled_matrix_is_unit():
    R = 1.001 * _rz(30.0)[None]
    q = rotmat_to_quat(R)
    assert abs(np.linalg.norm(q[0]) - 1.0) < 1e-12
    np.testing.assert_allclose(q[0], [math.cos(math.radians(15)), 0, 0, math.sin(math.radians(15))], atol=1e-3)


GOOD = dict(R=np.eye(3), t=np.zeros(3), fx=50.0, fy=60.0, cx=16.0, cy=12.0, width=32, height=24)


@pytest.mark.parametrize(
    "change,message",
    [
        (dict(fy=0.0), "focal"),
        (dict(fx=-1.0), "focal"),
        (dict(width=0), "image size"),
        (dict(height=0), "image size"),
        (dict(t=np.array([0.0, np.nan, 0.0])), "NaN or inf"),
        (dict(R=np.diag([1.0, np.inf, 1.0])), "NaN or inf"),
    ],
)
def test_camera_refuses_bad_values(change, message):
    with pytest.raises(ValueError, match=message):
        Camera(**{**GOOD, **change})


def test_look_at_is_a_proper_rotation_with_world_up_at_the_top():
    cam = Camera.look_at([0, 0, 1.0], [0, 0, 0], [0, 1, 0], 100.0, 120.0, 30.0, 20.0, 60, 40)
    assert np.linalg.det(cam.R) == pytest.approx(1.0)
    # camera axes: x = world +x, y (down) = world -y, z = world -z; the point is 1 in front.
    uv, z = cam.project(np.array([[0.1, 0.2, 0.0]]))
    np.testing.assert_allclose(uv[0], [100 * 0.1 + 30, -120 * 0.2 + 20], atol=1e-12)
    assert z[0] == pytest.approx(1.0)


def test_scaled_rounds_sizes_and_scales_each_axis_by_its_own_ratio():
    cam = Camera(np.eye(3), np.zeros(3), 100.0, 110.0, 50.0, 30.0, 100, 60)
    s = cam.scaled(0.337)  # 33.7 -> 34 px wide, 20.22 -> 20 px high
    assert (s.width, s.height) == (34, 20)
    np.testing.assert_allclose([s.fx, s.fy, s.cx, s.cy], [34.0, 110 / 3, 17.0, 10.0], rtol=1e-12)
    tiny = cam.scaled(0.001)
    assert (tiny.width, tiny.height) == (1, 1)


def test_K_and_viewmat_by_hand():
    R = np.array([[0, 1.0, 0], [-1.0, 0, 0], [0, 0, 1.0]])
    cam = Camera(R, np.array([1.0, 2.0, 3.0]), 50.0, 60.0, 16.0, 12.0, 32, 24)
    np.testing.assert_array_equal(cam.K(), [[50, 0, 16], [0, 60, 12], [0, 0, 1]])
    want = np.array([[0, 1, 0, 1], [-1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1.0]])
    np.testing.assert_array_equal(cam.viewmat(), want)
