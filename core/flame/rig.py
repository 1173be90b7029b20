"""A FLAME sequence as an editable rig: shape keys plus a keyed armature (numpy only).

What Blender needs to rebuild FLAME exactly, frame by frame, while leaving artists
ordinary controls:

- a basis mesh (template + identity shape + static offset),
- one relative shape key per expression component, keyed with the tracked coefficients,
- one shape key per pose-corrective component (9 per non-root joint), whose value is an
  entry of (R_k - I) for the joint's *local* rotation R_k. Because every bone rests with an
  identity orientation, a bone's local rotation is R_k itself, so Blender can drive these
  keys from the bones (artists rotating the jaw get FLAME's correctives),
- one bone per joint with FLAME's skinning weights, its pose keyed per frame.

FLAME's joints move with the expression (they are regressed from the expression-shaped
mesh), and a bone in Blender rotates about its rest head. Both are absorbed exactly by the
per-frame pose: with rest bones B_k = T(j_k^rest) and FLAME's skinning transforms
A_k = G_k T(-j_k(t)) (G the chained joint transforms), a bone's local pose is

    L_k = [R_k | (I - R_k) (j_k(t) - j_k^rest)]            (non-root)
    L_0 = B_0^-1 M A_0 B_0                                   (root)

where M is the per-frame placement (translation; NeRSemble's scale * rotation too). With an
expression of zero the non-root poses are pure rotations, which is what an artist expects to
see. :meth:`FlameRig.vertices` evaluates the rig the way Blender does (relative shape keys,
then linear blend skinning with pose * rest^-1), so the construction is checked here,
outside Blender, against :func:`flame.flame_forward`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rotations import quat_to_rotmat, rotmat_to_quat
from .model import FlameModel, axis_angle_to_matrix, prepare_params

__all__ = ["FlameRig", "build_flame_rig", "SLIDER_LIMIT", "FLAME_BONE_NAMES", "quat_from_matrix"]

# Blender caps shape-key slider ranges at +-10; keys whose tracked values go beyond are
# stored scaled (delta * s, value / s).
SLIDER_LIMIT = 10.0
FLAME_BONE_NAMES = ("root", "neck", "jaw", "eye_0", "eye_1")  # eyes_pose[:3] drives eye_0


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) [...,4] from rotation matrices [...,3,3] (Shepperd)."""
    return rotmat_to_quat(np.asarray(R, np.float64))


def _homogeneous(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = np.zeros(R.shape[:-2] + (4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def _translation(t: np.ndarray) -> np.ndarray:
    return _homogeneous(np.broadcast_to(np.eye(3), t.shape[:-1] + (3, 3)), t)


@dataclass
class FlameRig:
    """Arrays float64. V vertices, E expression keys, P = 9(J-1) pose keys, T frames, J joints.

    basis [V,3]; expr_deltas [E,V,3] and expr_values [T,E] (already divided by
    ``expr_scale`` [E], the factor folded into each delta); pose_deltas [P,V,3] and
    pose_values [T,P] (entries of R_k - I, row-major per non-root joint);
    rest_joints [J,3]; parents [J]; weights [V,J];
    locations [T,J,3], quaternions [T,J,4] (w,x,y,z, sign-continuous over time),
    scales [T,J] (uniform; 1 except a scaled root) — each bone's local pose per frame.
    """

    faces: np.ndarray
    basis: np.ndarray
    expr_deltas: np.ndarray
    expr_values: np.ndarray
    expr_scale: np.ndarray
    pose_deltas: np.ndarray
    pose_values: np.ndarray
    rest_joints: np.ndarray
    parents: np.ndarray
    weights: np.ndarray
    locations: np.ndarray
    quaternions: np.ndarray
    scales: np.ndarray
    bone_names: tuple
    ignored: tuple = ()

    @property
    def n_frames(self) -> int:
        return self.expr_values.shape[0]

    @property
    def n_joints(self) -> int:
        return self.rest_joints.shape[0]

    def pose_key_names(self) -> list[str]:
        """Names of the pose-corrective keys: ``pose_<bone>_<row><col>``."""
        return [
            f"pose_{self.bone_names[k]}_{a}{b}" for k in range(1, self.n_joints) for a in range(3) for b in range(3)
        ]

    def expr_key_names(self) -> list[str]:
        return [f"expr_{e:03d}" for e in range(self.expr_deltas.shape[0])]

    def local_matrices(self, frames=None) -> np.ndarray:
        """Bones' local poses [T,J,4,4] = T(location) R(quaternion) S(scale), as Blender builds them."""
        sel = slice(None) if frames is None else np.asarray(frames)
        q = self.quaternions[sel]
        R = quat_to_rotmat(q)
        R = R * self.scales[sel][..., None, None]
        return _homogeneous(R, self.locations[sel])

    def vertices(self, frames=None, pose_from_bones: bool = True) -> np.ndarray:
        """Vertices [T,V,3] the way Blender evaluates the rig: relative shape keys (expression
        keyed, pose correctives from the bones' rotations when ``pose_from_bones``, else the
        stored values), then the armature (sum_k w_k P_k B_k^-1)."""
        sel = np.arange(self.n_frames) if frames is None else np.asarray(frames)
        L = self.local_matrices(sel)  # [T,J,4,4]
        T, J = L.shape[:2]
        if pose_from_bones:
            feat = (L[:, 1:, :3, :3] / self.scales[sel][:, 1:, None, None] - np.eye(3)).reshape(T, -1)
        else:
            feat = self.pose_values[sel]
        V = self.basis.shape[0]
        shaped = (
            self.basis[None]
            + (self.expr_values[sel] @ self.expr_deltas.reshape(-1, V * 3)).reshape(T, V, 3)
            + (feat @ self.pose_deltas.reshape(-1, V * 3)).reshape(T, V, 3)
        )
        B = _translation(self.rest_joints)  # [J,4,4]
        P = np.empty_like(L)
        for k in range(J):  # a handful of joints, each batched over frames
            p = self.parents[k]
            P[:, k] = B[k] @ L[:, k] if p < 0 else P[:, p] @ np.linalg.inv(B[p]) @ B[k] @ L[:, k]
        D = P @ np.linalg.inv(B)[None]  # deformation per bone
        Tv = (self.weights @ D[:, :, :3, :].reshape(T, J, 12)).reshape(T, V, 3, 4)
        return np.einsum("tvab,tvb->tva", Tv[..., :3], shaped) + Tv[..., 3]


def build_flame_rig(model: FlameModel, params: dict, bone_names=None) -> FlameRig:
    """The rig reproducing ``flame_forward(model, **params)`` (plus NeRSemble's placement when
    ``params`` holds ``rotation_matrices``/``scale``, as :func:`data.read_nersemble_tracking`
    leaves them). Per-frame ``dynamic_offset`` cannot be carried by a rig: it is left out and
    named in ``ignored`` when non-zero."""
    params = dict(params)
    placement_R = params.pop("rotation_matrices", None)
    scale = float(np.asarray(params.pop("scale", 1.0)).reshape(-1)[0])
    ignored = []
    dyn = params.pop("dynamic_offset", None)
    if dyn is not None and np.any(np.asarray(dyn) != 0):
        ignored.append("dynamic_offset")
    if placement_R is not None:  # NeRSemble: FLAME without its own rotation, placed by s R x + t
        translation = np.asarray(params.pop("translation", np.zeros(3)), np.float64)
        params.pop("rotation", None)
    else:
        translation = None
    T, betas, full, transl, offsets = prepare_params(model, **params)
    if translation is not None:
        transl = np.broadcast_to(translation.reshape(-1, 3), (T, 3)).astype(np.float64)
    V, J, S = model.n_vertices, model.n_joints, model.n_shape
    if offsets is not None and offsets.shape[0] != 1:
        raise ValueError("per-frame offsets cannot be carried by a rig")
    basis = model.v_template + (betas[:1, :S] @ model._shape_basis[:S]).reshape(V, 3)
    if offsets is not None:
        basis = basis + offsets[0]
    expr = betas[:, S:]
    expr_deltas = np.moveaxis(model.shapedirs[:, :, S:], 2, 0)  # [E,V,3]
    expr_scale = (
        np.maximum(1.0, np.abs(expr).max(axis=0, initial=0.0) / (SLIDER_LIMIT * 0.999)) if T else np.ones(expr.shape[1])
    )
    if np.any(betas[:, :S] != betas[:1, :S]):
        raise ValueError("identity shape changes over the sequence; a rig has one basis shape")

    rest_joints = model.J_regressor @ basis  # [J,3]
    # Joints regressed from the expression-shaped mesh; regressing each expression direction
    # once keeps this [T,E] @ [E,J*3] rather than a [T,V,3] mesh per frame.
    joint_dirs = np.einsum("jv,evc->ejc", model.J_regressor, expr_deltas).reshape(-1, J * 3)
    joints = rest_joints[None] + (expr @ joint_dirs).reshape(T, J, 3)
    R = axis_angle_to_matrix(full)  # [T,J,3,3]
    parents = model.parents
    rel = joints.copy()
    rel[:, 1:] -= joints[:, parents[1:]]
    local = _homogeneous(R, rel)
    G = np.empty_like(local)
    G[:, 0] = local[:, 0]
    for j in range(1, J):
        G[:, j] = G[:, parents[j]] @ local[:, j]
    A = G @ _translation(-joints)  # FLAME's skinning transforms [T,J,4,4]
    M = _translation(transl)
    if placement_R is not None:
        Rp = np.broadcast_to(np.asarray(placement_R, np.float64).reshape(-1, 3, 3), (T, 3, 3))
        M = M @ _homogeneous(scale * Rp, np.zeros((T, 3)))
    D = M[:, None] @ A  # the deformation each bone must apply
    B = _translation(rest_joints)
    Binv = _translation(-rest_joints)
    L = np.empty_like(D)
    L[:, 0] = Binv[0] @ D[:, 0] @ B[0]
    for k in range(1, J):
        p = parents[k]
        # L_k = B_k^-1 B_p P_p^-1 P_k with P = D B, i.e. B_k^-1 D_p^-1 D_k B_k.
        L[:, k] = Binv[k] @ np.linalg.inv(D[:, p]) @ D[:, k] @ B[k]
    lin = L[:, :, :3, :3]
    scales = np.ones((T, J))
    scales[:, 0] = np.cbrt(np.linalg.det(lin[:, 0]))  # NeRSemble's scale; joints below are rigid
    quats = quat_from_matrix(lin / scales[..., None, None])
    # Neighbouring frames on the same hemisphere, so interpolated keys turn the short way.
    flip = np.cumprod(np.where(np.sum(quats[1:] * quats[:-1], axis=-1) < 0, -1.0, 1.0), axis=0)
    quats[1:] *= flip[..., None]
    # The rig's keys are stored as float32 in Blender: anything that is not a finite float32
    # there (a pose of 1e200, a translation of 1e39) would import "successfully" as NaN/inf.
    f32 = float(np.finfo(np.float32).max) / 2
    for what, values in (
        ("bone locations", L[:, :, :3, 3]),
        ("bone rotations", quats),
        ("bone scales", scales),
        ("expression keys", expr / expr_scale),
        ("expression shapes", expr_deltas * expr_scale[:, None, None]),
    ):
        if not (np.all(np.isfinite(values)) and np.abs(values).max(initial=0.0) <= f32):
            raise ValueError(f"the parameters give {what} that are not finite numbers a rig can hold")
    names = (
        tuple(bone_names)
        if bone_names is not None
        else (FLAME_BONE_NAMES if J == len(FLAME_BONE_NAMES) else tuple(f"joint_{k}" for k in range(J)))
    )
    return FlameRig(
        faces=model.faces,
        basis=basis,
        expr_deltas=expr_deltas * expr_scale[:, None, None],
        expr_values=expr / expr_scale,
        expr_scale=expr_scale,
        pose_deltas=np.moveaxis(model.posedirs, 2, 0),
        pose_values=(R[:, 1:] - np.eye(3)).reshape(T, -1),
        rest_joints=rest_joints,
        parents=parents.copy(),
        weights=model.weights,
        locations=L[:, :, :3, 3],
        quaternions=quats,
        scales=scales,
        bone_names=names,
        ignored=tuple(ignored),
    )
