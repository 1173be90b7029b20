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
def blender_camera(camera, z_up: bool = True, sensor_width: float = 36.0) -> dict:
    """Blender camera settings reproducing a pinhole ``Camera`` (OpenCV intrinsics).

    Blender cameras look down -z with +y up (the OpenGL convention the dataset's c2w uses).
    Focal length and shifts are expressed against the larger image side (sensor_fit AUTO
    semantics); non-square pixels (fx ≠ fy) become a pixel aspect ratio.
    """
    w, h = camera.width, camera.height
    big = float(max(w, h))
    c2w = camera.c2w_opengl()
    if z_up:
        c2w = Y_UP_TO_Z_UP @ c2w
    # Blender scales x by pixel_aspect_x / pixel_aspect_y; keep fx as the reference.
    aspect_y = camera.fx / camera.fy
    f_big = camera.fx if w >= h else camera.fy * aspect_y
    return {
        "matrix_world": c2w,
        "lens": f_big / big * sensor_width,
        "sensor_width": sensor_width,
        "sensor_fit": "AUTO",
        "shift_x": (w / 2.0 - camera.cx) / big,
        "shift_y": (camera.cy - h / 2.0) / big,
        "resolution": (int(w), int(h)),
        "pixel_aspect": (1.0, float(aspect_y)),
    }


def camera_from_blender(matrix_world, lens, sensor_width, shift_x, shift_y, width, height, z_up: bool = True):
    """The core ``Camera`` seeing what a Blender camera (sensor_fit AUTO, square pixels) sees."""
    from ..geometry.camera import Camera

    c2w = np.asarray(matrix_world, np.float64).reshape(4, 4)
    if z_up:
        c2w = np.linalg.inv(Y_UP_TO_Z_UP) @ c2w
    # Remove object scale so R is a rotation.
    c2w = c2w.copy()
    c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0, keepdims=True)
    big = float(max(width, height))
    f = lens / sensor_width * big
    cx = width / 2.0 - shift_x * big
    cy = height / 2.0 + shift_y * big
    return Camera.from_c2w_opengl(c2w, f, f, cx, cy, int(width), int(height))


def transform_gaussians(matrix, means, quats, scales):
    """Gaussians carried by an object transform (rotation, uniform scale, translation):
    Blender object space → world space for export and rendering."""
    M = np.asarray(matrix, np.float64).reshape(4, 4)
    A = M[:3, :3]
    s = float(np.cbrt(abs(np.linalg.det(A)))) or 1.0
    Rm = A / s
    q_obj = binding.rotmat_to_quat(Rm[None])[0]
    means_w = (np.asarray(means, np.float64) @ A.T + M[:3, 3]).astype(np.float32)
    quats_w = binding.quat_multiply(q_obj[None], np.asarray(quats, np.float64)).astype(np.float32)
    return means_w, quats_w, (np.asarray(scales, np.float32) * s).astype(np.float32)
