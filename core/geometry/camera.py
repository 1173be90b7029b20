"""Pinhole camera model shared by the rasteriser, the dataset loader and the evaluation.

Conventions (one source of truth):
- World-to-camera extrinsics ``R`` (3x3), ``t`` (3,) in OpenCV axes: x right, y down,
  z forward (points in front of the camera have z > 0).
- Intrinsics fx, fy, cx, cy in pixels; the centre of pixel (i, j) (column i, row j) sits at
  continuous image coordinates (i + 0.5, j + 0.5), so cx = w / 2 is a centred principal point.
  This matches gsplat, so both backends see the same image.
- Datasets store camera-to-world matrices in OpenGL axes (y up, z backward); flipping the
  y and z columns turns them into OpenCV camera-to-world.
numpy only: this module runs inside Blender.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Camera:
    R: np.ndarray  # (3, 3) world-to-camera rotation, OpenCV axes
    t: np.ndarray  # (3,) world-to-camera translation
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(self.t, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("Camera: extrinsics contain NaN or inf")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"Camera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Camera: image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def from_c2w_opengl(cls, c2w, fx, fy, cx, cy, width, height) -> "Camera":
        """From a dataset's camera-to-world matrix in OpenGL axes (GaussianAvatars/VHAP)."""
        c2w = np.asarray(c2w, dtype=np.float64).reshape(4, 4) @ _GL_TO_CV
        R_c2w = c2w[:3, :3]
        R = R_c2w.T
        t = -R @ c2w[:3, 3]
        return cls(R, t, float(fx), float(fy), float(cx), float(cy), int(width), int(height))

    @classmethod
    def look_at(cls, eye, target, up, fx, fy, cx, cy, width, height) -> "Camera":
        """A camera at ``eye`` looking at ``target``; ``up`` is the world up direction."""
        eye = np.asarray(eye, np.float64)
        fwd = np.asarray(target, np.float64) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(up, np.float64))
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
        return cls(R, -R @ eye, fx, fy, cx, cy, width, height)

    def c2w_opengl(self) -> np.ndarray:
        c2w = np.eye(4)
        c2w[:3, :3] = self.R.T
        c2w[:3, 3] = self.center
        return c2w @ _GL_TO_CV

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    def viewmat(self) -> np.ndarray:
        """4x4 world-to-camera matrix (OpenCV axes), as gsplat expects."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points) @ self.R.T + self.t

    def project(self, points: np.ndarray):
        """World points [..., 3] -> (uv [..., 2] in continuous pixel coordinates, depth [...])."""
        pc = self.to_camera(points)
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * pc[..., 0] / z + self.cx
            v = self.fy * pc[..., 1] / z + self.cy
        return np.stack([u, v], axis=-1), z

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.5 halves width and height)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=w, height=h)
