"""Blender's spaces against core's: the Z-up axes, Blender camera settings for a core ``Camera``
and back, Gaussians carried by an object transform. Blender tier (numpy).
"""

from __future__ import annotations

import numpy as np

from ..avatar import binding


# Blender is Z-up; FLAME/dataset space is Y-up (head looks to +z). Rotating +90° about x
# maps dataset y to Blender z, so the head stands up and looks to Blender -y (the front view).
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


# -- cameras -------------------------------------------------------------------------------
SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")


def blender_intrinsics(
    lens,
    sensor_width,
    width,
    height,
    shift_x=0.0,
    shift_y=0.0,
    *,
    sensor_height=24.0,
    sensor_fit="AUTO",
    pixel_aspect=(1.0, 1.0),
):
    """Pinhole intrinsics (fx, fy, cx, cy) in pixels, OpenCV convention (y down, the origin at
    the top-left corner), of a perspective Blender camera rendering ``width`` × ``height`` px.

    Blender's rules (BKE_camera_params_compute_viewplane): the sensor size is the sensor
    height for sensor_fit VERTICAL, else the sensor width; the fitted side is the width for
    HORIZONTAL, the height for VERTICAL and, for AUTO, the larger of width·pixel_aspect_x and
    height·pixel_aspect_y. The lens spans the sensor size over the fitted side; the pixel
    aspect (pixel_aspect_x : pixel_aspect_y, a pixel's width to its height) scales the vertical
    axis; shifts are fractions of the fitted side. The lens unit (millimetres or field of
    view) only changes how ``lens`` is shown.
    """
    if sensor_fit not in SENSOR_FITS:
        raise ValueError(f"unknown sensor fit {sensor_fit!r}; expected one of {', '.join(SENSOR_FITS)}")
    w, h = float(width), float(height)
    ax, ay = (float(a) for a in pixel_aspect)
    if w <= 0 or h <= 0:
        raise ValueError(f"the image is {width}×{height} px: it needs at least one pixel each way")
    if not (lens > 0 and ax > 0 and ay > 0):
        raise ValueError(f"lens {lens} mm and pixel aspect {ax}:{ay} must be positive")
    sensor = float(sensor_height if sensor_fit == "VERTICAL" else sensor_width)
    if not sensor > 0:
        raise ValueError(f"the sensor size is {sensor} mm: it must be positive")
    ycor = ay / ax  # a pixel's height over its width
    horizontal = sensor_fit == "HORIZONTAL" or (sensor_fit == "AUTO" and ax * w >= ay * h)
    viewfac = w if horizontal else ycor * h  # the fitted side, in pixel widths
    fx = lens / sensor * viewfac
    fy = fx / ycor
    cx = w / 2.0 - shift_x * viewfac
    cy = h / 2.0 + shift_y * viewfac / ycor
    return fx, fy, cx, cy


def blender_camera(camera, z_up: bool = True, sensor_width: float = 36.0) -> dict:
    """Blender camera settings reproducing a pinhole ``Camera`` (OpenCV intrinsics).

    Blender cameras look down -z with +y up (the OpenGL convention the dataset's c2w uses).
    Focal length and shifts are expressed against the fitted side (sensor_fit AUTO: the larger
    side once the pixel aspect is applied); non-square pixels (fx ≠ fy) become a pixel aspect
    ratio, the smaller of its two numbers 1 (Blender's minimum). ``blender_intrinsics`` of the
    result gives the camera's intrinsics back.
    """
    w, h = camera.width, camera.height
    c2w = camera.c2w_opengl()
    if z_up:
        c2w = Y_UP_TO_Z_UP @ c2w
    ycor = camera.fx / camera.fy  # a pixel's height over its width (pixel_aspect_y / _x)
    aspect = (1.0, ycor) if ycor >= 1 else (1.0 / ycor, 1.0)
    viewfac = float(w) if w >= ycor * h else ycor * h  # AUTO: ax·w >= ay·h ⇔ w >= ycor·h
    return {
        "matrix_world": c2w,
        "lens": camera.fx / viewfac * sensor_width,
        "sensor_width": sensor_width,
        "sensor_fit": "AUTO",
        "shift_x": (w / 2.0 - camera.cx) / viewfac,
        "shift_y": (camera.cy - h / 2.0) * ycor / viewfac,
        "resolution": (int(w), int(h)),
        "pixel_aspect": (float(aspect[0]), float(aspect[1])),
    }


def camera_from_blender(
    matrix_world,
    lens,
    sensor_width,
    shift_x,
    shift_y,
    width,
    height,
    z_up: bool = True,
    *,
    sensor_height=24.0,
    sensor_fit="AUTO",
    pixel_aspect=(1.0, 1.0),
):
    """The core ``Camera`` seeing what a perspective Blender camera sees (any sensor fit and
    pixel aspect: ``blender_intrinsics``)."""
    from ..geometry.camera import Camera

    c2w = np.asarray(matrix_world, np.float64).reshape(4, 4)
    if z_up:
        c2w = np.linalg.inv(Y_UP_TO_Z_UP) @ c2w
    # Remove object scale so R is a rotation.
    c2w = c2w.copy()
    c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0, keepdims=True)
    fx, fy, cx, cy = blender_intrinsics(
        lens,
        sensor_width,
        width,
        height,
        shift_x,
        shift_y,
        sensor_height=sensor_height,
        sensor_fit=sensor_fit,
        pixel_aspect=pixel_aspect,
    )
    return Camera.from_c2w_opengl(c2w, fx, fy, cx, cy, int(width), int(height))


# -- Gaussians -----------------------------------------------------------------------------
# The six orders in which SVD axes can be matched to a Gaussian's own three axes.
_PERMS = np.array([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]])
_SIMILARITY_RTOL = 1e-5  # A·Aᵀ = s²·I up to float32 matrix_world round-off
_COLLAPSED = 1e-12  # a splat axis this much shorter than its longest one was collapsed by A


def transform_gaussians(matrix, means, quats, scales):
    """Gaussians carried by an object transform: Blender object space → world space for export
    and rendering. Any affine ``matrix`` (mirrors, non-uniform scale, shear, scale 0): the
    world means are A·μ + t and the world covariances exactly A·Σ·Aᵀ (A the linear part),
    re-factored into a proper rotation (wxyz quaternion, w >= 0) and three scales; a singular
    A gives zero scales on the axes it collapses.

    A similarity (rotation, uniform scale, optionally mirrored: A = ±s·R) keeps each splat's
    axes and only turns and scales them (a mirror is the rotation −A/s and the same
    covariance). Otherwise each A·R·S is decomposed by a batched SVD (U·Σ·Vᵀ, covariance
    U·Σ²·Uᵀ), its axes matched to the splat's own (order and sign) so the scales keep their
    meaning, and one axis flipped where U is a reflection (that leaves U·Σ²·Uᵀ unchanged).
    """
    M = np.asarray(matrix, np.float64).reshape(4, 4)
    A = M[:3, :3]
    means = np.asarray(means, np.float64).reshape(-1, 3)
    quats = np.asarray(quats, np.float64).reshape(-1, 4)
    scales = np.asarray(scales, np.float64).reshape(-1, 3)
    means_w = (means @ A.T + M[:3, 3]).astype(np.float32)
    det = float(np.linalg.det(A))
    s = float(np.cbrt(abs(det)))
    if s > 0 and np.abs(A @ A.T - s * s * np.eye(3)).max() <= _SIMILARITY_RTOL * s * s:
        q_obj = binding.rotmat_to_quat((A / np.copysign(s, det))[None])[0]
        quats_w = binding.quat_multiply(q_obj[None], quats)
        quats_w = np.where(quats_w[:, :1] < 0, -quats_w, quats_w)
        return means_w, quats_w.astype(np.float32), (scales * s).astype(np.float32)
    axes = (A @ binding.quat_to_rotmat(quats)) * scales[:, None, :]  # column j: axis j, scaled
    U, sv, _ = np.linalg.svd(axes)
    sv[sv <= _COLLAPSED * sv.max(axis=1, keepdims=True)] = 0.0  # SVD round-off on a collapsed axis
    dots = np.einsum("nik,nij->nkj", U, axes)  # [n, SVD axis k, own axis j]
    score = np.abs(dots[:, _PERMS, np.arange(3)]).sum(-1)  # [n, 6]
    perm = _PERMS[np.argmax(score, axis=1)]  # [n, 3]: the SVD axis for each own axis
    U = np.take_along_axis(U, perm[:, None, :], axis=2)
    sv = np.take_along_axis(sv, perm, axis=1)
    sign = np.take_along_axis(dots, perm[:, None, :], axis=1)[:, 0]
    U = U * np.where(sign < 0, -1.0, 1.0)[:, None, :]
    # A reflection (det −1: a mirroring A) becomes a rotation by flipping its least visible axis.
    flip = np.linalg.det(U) < 0
    col = np.argmin(sv, axis=1)
    U[flip, :, col[flip]] *= -1
    return means_w, binding.rotmat_to_quat(U).astype(np.float32), sv.astype(np.float32)
