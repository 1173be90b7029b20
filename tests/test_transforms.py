"""core/bridge/transforms.py (numpy only): Gaussians carried by any object matrix, and Blender
camera intrinsics for every sensor fit and pixel aspect."""

import math

import numpy as np
import pytest

from progressive_avatars.core.bridge.transforms import (
    blender_camera,
    blender_intrinsics,
    camera_from_blender,
    transform_gaussians,
)
from progressive_avatars.core.geometry.camera import Camera
from progressive_avatars.core.geometry.rotations import quat_to_rotmat


def _gaussians(rng, n=200):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    scales = np.exp(rng.normal(np.log(0.01), 0.6, (n, 3)))
    scales[::7, 2] *= 0.05  # flat, like trained splats
    scales[::11, 1] = 0.0  # a degenerate splat
    return rng.normal(0, 0.1, (n, 3)), q, scales


def _cov(q, s):
    R = quat_to_rotmat(np.asarray(q, np.float64))
    return R @ (np.asarray(s, np.float64)[:, :, None] ** 2 * np.swapaxes(R, 1, 2))


def _rot(rng):
    q = rng.normal(size=4)
    return quat_to_rotmat(q / np.linalg.norm(q))


def _matrices():
    rng = np.random.default_rng(7)
    R = _rot(rng)
    shear = np.eye(3)
    shear[0, 1], shear[2, 0] = 0.7, -0.4
    cases = {
        "identity": np.eye(3),
        "rotation x2": 2.0 * R,
        "mirror x": np.diag([-1.0, 1, 1]),
        "mirror -1,-1,-1": -np.eye(3),
        "non-uniform 2,1,0.5": np.diag([2.0, 1, 0.5]),
        "rotated non-uniform": R @ np.diag([1.5, 0.3, 2.0]) @ _rot(rng),
        "parented mirror": R @ np.diag([-1.5, 1.5, 1.5]),
        "shear": R @ shear,
        "flattened z": np.diag([1.0, 1, 0]),
        "rank 1": np.outer([1.0, 2, -1], [0.5, 0.1, 0.3]),
        "zero": np.zeros((3, 3)),
    }
    for k in range(4):
        cases[f"random {k}"] = rng.normal(size=(3, 3))
    out = {}
    for name, A in cases.items():
        M = np.eye(4)
        M[:3, :3] = A
        M[:3, 3] = [0.3, -1.0, 2.0]
        out[name] = M
    return out


@pytest.mark.parametrize("name", list(_matrices()))
def test_transform_gaussians_world_covariance_is_a_sigma_at(name):
    """The world covariance is exactly A·Σ·Aᵀ for any matrix, as a proper rotation (wxyz,
    w >= 0) and three non-negative scales; mirrored, non-uniform, sheared and singular
    matrices included (a collapsed axis has scale 0: nothing visible)."""
    M = _matrices()[name]
    A = M[:3, :3]
    means, q, s = _gaussians(np.random.default_rng(1))
    mw, qw, sw = transform_gaussians(M, means.astype(np.float32), q.astype(np.float32), s.astype(np.float32))
    assert mw.dtype == qw.dtype == sw.dtype == np.float32
    assert mw.shape == means.shape and qw.shape == q.shape and sw.shape == s.shape
    np.testing.assert_allclose(mw, means @ A.T + M[:3, 3], atol=1e-6)
    assert np.all(np.isfinite(qw)) and np.all(np.isfinite(sw)) and np.all(sw >= 0)
    np.testing.assert_allclose(np.linalg.norm(qw, axis=1), 1.0, atol=1e-6)
    assert np.all(qw[:, 0] >= 0)
    expected = A @ _cov(q, s) @ A.T
    scale = np.abs(expected).max(axis=(1, 2), keepdims=True) + 1e-30
    err = np.abs(_cov(qw, sw) - expected) / scale
    assert err.max() < 2e-5, (name, err.max())
    rank = np.linalg.matrix_rank(A)
    if rank < 3:  # the collapsed axes have zero scale, the others keep theirs
        assert np.all((sw == 0).sum(1) >= 3 - rank)
    if rank == 0:
        assert np.all(sw == 0)


def test_transform_gaussians_keeps_each_splats_axes():
    """A similarity (also mirrored) scales each axis alike; a non-uniform scale along the
    splat's own axes scales each of them by its own factor, in the same order."""
    means, q, s = _gaussians(np.random.default_rng(2), 50)
    for sign in (1.0, -1.0):
        _, qw, sw = transform_gaussians(np.diag([2 * sign] * 3 + [1.0]), means, q, s)
        np.testing.assert_allclose(sw, 2 * s, rtol=1e-6)
    ident = np.tile([1.0, 0, 0, 0], (len(s), 1))
    _, qw, sw = transform_gaussians(np.diag([2.0, 1.0, 0.5, 1.0]), means, ident, s)
    np.testing.assert_allclose(sw, s * [2.0, 1.0, 0.5], rtol=1e-6, atol=1e-12)
    _, qw, sw = transform_gaussians(np.diag([0.0, 0.0, 0.0, 1.0]), means, q, s)
    assert np.all(sw == 0)  # an object scaled to 0 shows nothing


# -- cameras -------------------------------------------------------------------------------
def test_blender_intrinsics_follow_the_sensor_fit_and_pixel_aspect():
    f = 50.0
    # AUTO: the sensor width spans the larger side.
    assert blender_intrinsics(f, 36, 96, 48) == pytest.approx((f / 36 * 96, f / 36 * 96, 48, 24))
    assert blender_intrinsics(f, 36, 48, 96) == pytest.approx((f / 36 * 96, f / 36 * 96, 24, 48))
    # VERTICAL: the sensor height spans the height; HORIZONTAL: the sensor width the width.
    assert blender_intrinsics(f, 36, 96, 48, sensor_height=24, sensor_fit="VERTICAL")[:2] == pytest.approx((100, 100))
    fh = f / 36 * 48
    assert blender_intrinsics(f, 36, 48, 96, sensor_fit="HORIZONTAL")[:2] == pytest.approx((fh, fh))
    # Pixel aspect 2:1 (pixels twice as wide as tall): fy = 2 fx; AUTO compares 2·64 with 64.
    fx, fy, cx, cy = blender_intrinsics(f, 36, 64, 64, pixel_aspect=(2, 1))
    assert (fx, fy) == pytest.approx((f / 36 * 64, 2 * f / 36 * 64))
    # 1:2 and a wide image: 100·1 < 60·2, so AUTO fits the height (in pixel widths: 2·60).
    fx, fy, _, _ = blender_intrinsics(f, 36, 100, 60, pixel_aspect=(1, 2))
    assert (fx, fy) == pytest.approx((f / 36 * 120, f / 36 * 60))
    # Shifts are fractions of the fitted side; +y shift moves the image up (the centre down).
    fx, fy, cx, cy = blender_intrinsics(f, 36, 96, 48, 0.1, -0.2)
    assert (cx, cy) == pytest.approx((48 - 9.6, 24 - 19.2))
    fx, fy, cx, cy = blender_intrinsics(f, 36, 96, 48, 0.1, -0.2, sensor_fit="VERTICAL")
    assert (cx, cy) == pytest.approx((48 - 4.8, 24 - 9.6))
    with pytest.raises(ValueError, match="px"):
        blender_intrinsics(f, 36, 0, 48)
    with pytest.raises(ValueError, match="sensor fit"):
        blender_intrinsics(f, 36, 48, 48, sensor_fit="DIAGONAL")


@pytest.mark.parametrize(
    "fx,fy,cx,cy,w,h",
    [
        (600.0, 600.0, 190.0, 130.0, 320, 240),
        (500.0, 600.0, 150.0, 130.0, 320, 240),
        (600.0, 500.0, 170.0, 110.0, 320, 240),
        (600.0, 450.0, 130.0, 170.0, 240, 320),
        (450.0, 600.0, 130.0, 170.0, 240, 320),
        (300.0, 900.0, 100.0, 100.0, 320, 120),  # the height fits once the pixel aspect applies
        # fx/fy = 3: w = 320 >= h = 240 but w < 3·h, so AUTO fits the height (in pixel widths)
        (900.0, 300.0, 150.0, 110.0, 320, 240),
    ],
)
def test_blender_camera_round_trip_any_pixel_aspect(fx, fy, cx, cy, w, h):
    cam = Camera.look_at([0.2, 0.1, 0.7], [0, 0, 0], [0, 1, 0], fx, fy, cx, cy, w, h)
    s = blender_camera(cam)
    assert min(s["pixel_aspect"]) == 1.0  # Blender's pixel aspect is at least 1
    back = camera_from_blender(
        s["matrix_world"],
        s["lens"],
        s["sensor_width"],
        s["shift_x"],
        s["shift_y"],
        *s["resolution"],
        sensor_fit=s["sensor_fit"],
        pixel_aspect=s["pixel_aspect"],
    )
    np.testing.assert_allclose([back.fx, back.fy, back.cx, back.cy], [fx, fy, cx, cy], rtol=1e-9)
    pts = np.random.default_rng(0).normal(0, 0.1, (10, 3))
    np.testing.assert_allclose(back.project(pts)[0], cam.project(pts)[0], atol=1e-6)


def test_zero_sensor_and_zero_lens_are_refused():
    with pytest.raises(ValueError, match="sensor"):
        blender_intrinsics(50.0, 0.0, 64, 48)
    with pytest.raises(ValueError, match="lens"):
        blender_intrinsics(0.0, 36.0, 64, 48)


def test_camera_from_a_scaled_blender_object_drops_the_scale():
    # matrix_world = [Rz(90°) · diag(2, 3, 4) | (1, 2, 3)], not Z-up converted.
    M = np.eye(4)
    M[:3, :3] = np.array([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 1.0]]) @ np.diag([2.0, 3.0, 4.0])
    M[:3, 3] = [1.0, 2.0, 3.0]
    cam = camera_from_blender(M, 50.0, 36.0, 0.0, 0.0, 64, 48, z_up=False)
    # OpenGL c2w columns (0,1,0), (-1,0,0), (0,0,1) -> OpenCV (0,1,0), (1,0,0), (0,0,-1).
    R = np.array([[0, 1.0, 0], [1.0, 0, 0], [0, 0, -1.0]])
    np.testing.assert_allclose(cam.R, R, atol=1e-15)
    np.testing.assert_allclose(cam.t, [-2.0, -1.0, 3.0], atol=1e-15)
    assert cam.fx == pytest.approx(50.0 / 36.0 * 64)


def test_lens_of_tall_pixels_on_a_landscape_image():
    # fx/fy = 3: w = 320 >= h = 240 but w < 3·h, so AUTO fits the height (in pixel widths).
    cam = Camera.look_at([0.2, 0.1, 0.7], [0, 0, 0], [0, 1, 0], 900.0, 300.0, 150.0, 110.0, 320, 240)
    assert blender_camera(cam)["lens"] == pytest.approx(900.0 / (3 * 240) * 36.0)


def test_camera_from_a_turned_and_stretched_blender_object():
    # matrix_world = [Rz(30°) · diag(2, 3, 4) | (1, 2, 3)]: column norms 2, 3, 4, row norms not.
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    M = np.eye(4)
    M[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ np.diag([2.0, 3.0, 4.0])
    M[:3, 3] = [1.0, 2.0, 3.0]
    cam = camera_from_blender(M, 50.0, 36.0, 0.0, 0.0, 64, 48, z_up=False)
    R = np.array([[c, s, 0], [s, -c, 0], [0, 0, -1.0]])
    np.testing.assert_allclose(cam.R, R, atol=1e-15)
    np.testing.assert_allclose(cam.t, [-(c + 2 * s), -(s - 2 * c), 3.0], atol=1e-14)
