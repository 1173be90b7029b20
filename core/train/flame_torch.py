"""FLAME forward pass in torch: differentiable twin of ``flame.flame_forward``.

Used where FLAME parameters are refined during training. The maths (Rodrigues with Taylor
coefficients near zero, pose correctives from non-root joints, LBS relative to the rest
pose, translation after skinning) mirrors the numpy version line for line, so the two agree
to float32 precision. Gradients are finite at zero pose.
"""

from __future__ import annotations

import numpy as np
import torch

from ..geometry.rotations import axis_angle_to_matrix

from ..flame.model import FlameModel, load_flame_model

__all__ = ["axis_angle_to_matrix_torch", "FlameTorch"]


def axis_angle_to_matrix_torch(r: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [...,3,3] from axis-angle [...,3]; finite gradients at r = 0."""
    return axis_angle_to_matrix(r)


class FlameTorch(torch.nn.Module):
    """FLAME as a torch module (buffers only, no trainable weights of its own)."""

    def __init__(self, model, dtype=torch.float32, device=None):
        super().__init__()
        model = load_flame_model(model) if not isinstance(model, FlameModel) else model
        self.n_shape, self.n_expr = model.n_shape, model.n_expr
        self.n_vertices, self.n_joints = model.n_vertices, model.n_joints
        V = self.n_vertices

        def buf(name, a, dt=dtype):
            self.register_buffer(name, torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=device))

        buf("v_template", model.v_template)
        buf("shape_basis", model.shapedirs.reshape(V * 3, -1).T)  # [K, V*3]
        buf("pose_basis", model.posedirs.reshape(V * 3, -1).T)  # [P, V*3]
        buf("J_regressor", model.J_regressor)
        buf("weights", model.weights)
        buf("faces", model.faces, torch.int64)
        self.parents = [int(p) for p in model.parents]

    def _rows(self, x, T, width, name):
        if x is None:
            return self.v_template.new_zeros((T, width))
        x = torch.as_tensor(x, dtype=self.v_template.dtype, device=self.v_template.device)
        if not x.numel():
            x = x.new_zeros((1, width))
        # Rows are frames, as flame_forward reads them (model._pose): one frame may be [6], [2,3]
        # or [J,3], but beside T = 2 frames a [2,3] eyes_pose is two frames of the wrong width.
        if x.dim() <= 1 or (x.numel() == width and x.shape[0] != T):
            x = x.reshape(1, -1)
        else:
            x = x.reshape(x.shape[0], -1)
        if x.shape[1] != width:
            raise ValueError(f"{name}: expected {width} values per frame, got shape {tuple(x.shape)}")
        if x.shape[0] not in (1, T):
            raise ValueError(f"{name}: expected 1 or {T} rows of {width}, got {tuple(x.shape)}")
        return x.expand(T, width)

    def _coeffs(self, x, n_model, T, name):
        if x is None:
            return self.v_template.new_zeros((T, n_model))
        x = torch.as_tensor(x, dtype=self.v_template.dtype, device=self.v_template.device)
        x = x.reshape(1, -1) if x.dim() <= 1 else x.reshape(x.shape[0], -1)
        if x.shape[0] not in (1, T):
            raise ValueError(f"{name}: expected 1 or {T} rows, got {x.shape[0]}")
        n = x.shape[1]
        if n > n_model:
            if bool((x[:, n_model:] != 0).any()):
                last = int(torch.nonzero((x != 0).any(dim=0)).max()) + 1
                raise ValueError(
                    f"{name} has non-zero coefficients up to number {last} (of {n}) but the model has only {n_model}"
                )
            x = x[:, :n_model]
        elif n < n_model:
            x = torch.cat([x, x.new_zeros((x.shape[0], n_model - n))], dim=1)
        return x.expand(T, n_model)

    def forward(
        self,
        shape=None,
        expr=None,
        rotation=None,
        neck_pose=None,
        jaw_pose=None,
        eyes_pose=None,
        translation=None,
        static_offset=None,
        dynamic_offset=None,
        pose=None,
    ) -> torch.Tensor:
        """Vertices [T,V,3]; same parameters and broadcasting as ``flame.flame_forward``."""
        V, J = self.n_vertices, self.n_joints
        # Frames counted as flame_forward counts them: one frame's worth of pose values ([2,3]
        # eyes, [J,3] pose) and a [V,3] dynamic offset are one frame, not 2, J or V.
        T = 1
        for name, x, one_frame in (
            ("shape", shape, None),
            ("expr", expr, None),
            ("rotation", rotation, 3),
            ("neck_pose", neck_pose, 3),
            ("jaw_pose", jaw_pose, 3),
            ("eyes_pose", eyes_pose, 6),
            ("translation", translation, 3),
            ("pose", pose, 3 * J),
            ("dynamic_offset", dynamic_offset, 3 * V),
        ):
            if x is None:
                continue
            x = torch.as_tensor(x)
            if x.dim() < 2 or x.shape[0] == 1 or x.numel() == one_frame:
                continue
            n = x.shape[0]
            if T not in (1, n):
                raise ValueError(f"FLAME parameters disagree on the number of frames ({name}: {n} vs {T})")
            T = n
        betas = torch.cat(
            [self._coeffs(shape, self.n_shape, T, "shape"), self._coeffs(expr, self.n_expr, T, "expression")], dim=1
        )
        if pose is not None:
            full = self._rows(pose, T, 3 * J, "pose").reshape(T, J, 3)
        else:
            if J != 5:
                raise ValueError(f"the model has {J} joints, not FLAME's 5: pass pose=[T,{3 * J}]")
            full = torch.cat(
                [
                    self._rows(rotation, T, 3, "rotation"),
                    self._rows(neck_pose, T, 3, "neck_pose"),
                    self._rows(jaw_pose, T, 3, "jaw_pose"),
                    self._rows(eyes_pose, T, 6, "eyes_pose"),
                ],
                dim=1,
            ).reshape(T, 5, 3)
        transl = self._rows(translation, T, 3, "translation")

        v_shaped = self.v_template + (betas @ self.shape_basis).reshape(T, V, 3)
        for name, off in (("static_offset", static_offset), ("dynamic_offset", dynamic_offset)):
            if off is not None:
                off = torch.as_tensor(off, dtype=v_shaped.dtype, device=v_shaped.device)
                # Read as flame_forward reads offsets (leading axes folded into frames, nothing
                # re-cut): a flat [T,V*3] layout is refused there, so here too.
                off = off.reshape((-1,) + tuple(off.shape[-2:])) if off.dim() >= 2 else off
                if off.dim() != 3 or off.shape[1:] != (V, 3) or off.shape[0] not in (1, T):
                    raise ValueError(f"{name}: expected [1|T,{V},3], got {tuple(off.shape)}")
                v_shaped = v_shaped + off
        joints = self.J_regressor @ v_shaped  # [T,J,3]
        R = axis_angle_to_matrix_torch(full)  # [T,J,3,3]
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        feat = (R[:, 1:] - eye).reshape(T, -1)
        v_posed = v_shaped + (feat @ self.pose_basis).reshape(T, V, 3)
        rel = torch.cat([joints[:, :1], joints[:, 1:] - joints[:, self.parents[1:]]], dim=1)
        # Chain as (rotation, translation) pairs: avoids in-place writes that autograd dislikes.
        Gr, Gt = [R[:, 0]], [rel[:, 0]]
        for j in range(1, J):
            p = self.parents[j]
            Gr.append(Gr[p] @ R[:, j])
            Gt.append((Gr[p] @ rel[:, j, :, None])[..., 0] + Gt[p])
        Gr = torch.stack(Gr, dim=1)  # [T,J,3,3]
        Gt = torch.stack(Gt, dim=1)  # [T,J,3]
        At = Gt - (Gr @ joints[..., None])[..., 0]
        A = torch.cat([Gr, At[..., None]], dim=-1)  # [T,J,3,4]
        Tv = (self.weights @ A.reshape(T, J, 12)).reshape(T, V, 3, 4)
        verts = (Tv[..., :3] @ v_posed[..., None])[..., 0] + Tv[..., 3]
        return verts + transl[:, None, :]
