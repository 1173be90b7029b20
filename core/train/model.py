"""The trainable avatar (torch): forest + one Gaussian per face, growable.

Parameters are plain leaf tensors keyed by name so the optimiser state can be grown
alongside them when faces split.
"""

from __future__ import annotations

import numpy as np
import torch

from . import binding_kernels
from ..geometry import sh
from ..avatar.avatar import PARAM_NAMES, Avatar
from ..avatar.forest import Forest


class TorchAvatar:
    def __init__(self, avatar: Avatar, device="cpu"):
        self.device = torch.device(device)
        self.forest = avatar.forest
        self.params = {
            name: torch.tensor(getattr(avatar, name), device=self.device).requires_grad_(True) for name in PARAM_NAMES
        }
        self.params["split_logits"] = torch.tensor(self.forest.split_logits, device=self.device).requires_grad_(True)
        if avatar.sh_degree:
            self.params["f_rest"] = torch.tensor(avatar.f_rest, device=self.device).requires_grad_(True)
        self.active_sh_degree = avatar.sh_degree  # training raises it band by band
        self._structure_changed()

    @classmethod
    def from_template(
        cls,
        faces,
        color=(0.5, 0.5, 0.5),
        opacity=0.7,
        log_scale=(np.log(0.5), np.log(0.1), np.log(0.5)),
        device="cpu",
        sh_degree: int = 0,
        coarse=None,
        stand_ins: bool = False,
        backdrop: bool = False,
    ) -> "TorchAvatar":
        """`coarse`: None, or (coarse_faces, coarse_counts, root_ref or None), the table and
        counts from core.coarse.build_coarse; `stand_ins`: the coarse faces are stand-ins
        (Forest.drawn) rather than cumulative levels; `backdrop`: retired stand-ins stay behind
        every other Gaussian (Forest.render_set)."""
        if coarse is None:
            forest = Forest(faces)
        else:
            cf, counts, ref = coarse
            forest = Forest(
                faces, coarse_faces=cf, coarse_counts=counts, root_ref=ref, stand_ins=stand_ins, backdrop=backdrop
            )
        av = Avatar.initial(forest, color=color, opacity=opacity)
        av.d_log_scale[:] = np.asarray(log_scale, np.float32)
        av.f_rest = np.zeros((forest.num_faces, sh.num_rest(sh_degree), 3), np.float32)
        return cls(av, device)

    @property
    def sh_degree(self) -> int:
        return sh.degree_of(self.params["f_rest"].shape[1]) if "f_rest" in self.params else 0

    def _structure_changed(self):
        self.binding = binding_kernels.FaceBinding(self.forest)
        # 0 at coarse stand-ins, 1 elsewhere (without_stand_ins); the stand-ins' faces
        finer = self.forest.level >= self.forest.num_coarse_levels
        self._finer = torch.as_tensor(finer, dtype=torch.float32)
        self.stand_in_ids = torch.as_tensor(np.flatnonzero(~finer), device=self.device)
        self._coarse = ~finer
        self.level_ids = [
            torch.as_tensor(self.forest.cumulative(lvl), device=self.device) for lvl in range(self.forest.max_level + 1)
        ]

    def without_stand_ins(self, opacities: torch.Tensor) -> torch.Tensor:
        """``opacities`` [N] with the coarse stand-ins at zero: what the template level and finer
        show, the whole avatar included (Forest.drawn). Zero rather than dropped, so that every
        image keeps all N Gaussians in face order (growth reads per-face gradients)."""
        if not self.forest.stand_ins:
            return opacities
        return opacities * self._finer.to(device=opacities.device, dtype=opacities.dtype)

    def finer_inputs(self, opacities: torch.Tensor):
        """(opacities, behind) for the images of the template level and finer, the whole avatar
        included: the stand-ins at zero opacity (without_stand_ins), or, with a backdrop forest,
        as they are and composited behind every other Gaussian (render's ``behind``)."""
        if self.forest.backdrop:
            return opacities, self._coarse
        return self.without_stand_ins(opacities), None

    @property
    def num_faces(self) -> int:
        return self.forest.num_faces

    def gaussians(self, vertices: torch.Tensor, camera_center=None) -> dict:
        """Activated world-space Gaussians of every face for one frame's vertices [V,3];
        colours seen from ``camera_center`` up to the active SH degree."""
        p = self.params
        # float64 numba kernels (binding_kernels); binding_torch is their test reference
        means, quats, scales = self.binding.gaussians(
            vertices, p["split_logits"], p["d_mu"], p["d_log_scale"], p["d_rot"]
        )
        degree = min(self.active_sh_degree, self.sh_degree) if camera_center is not None else 0
        if degree:
            c = torch.as_tensor(np.asarray(camera_center), dtype=means.dtype, device=means.device).reshape(1, 3)
            d = torch.nn.functional.normalize(means - c, dim=1, eps=1e-12)
            rgb = sh.sh_rgb(p["f_dc"], p["f_rest"], d, torch.stack, degree)
        else:
            rgb = 0.5 + sh.SH_C0 * p["f_dc"]
        return {
            "means": means,
            "quats": quats,
            "scales": scales,
            "opacities": torch.sigmoid(p["opacity_logit"]),
            "colors": rgb.clamp_min(0.0),
        }

    def split(self, face_ids: np.ndarray) -> np.ndarray:
        """Split leaves; children start as copies of their parent's Gaussian, centred on the child face.

        Returns the new faces' indices (flat). The caller grows the optimiser state.
        """
        children = self.forest.split(face_ids)
        if children.size == 0:
            return children.ravel()
        parents = torch.as_tensor(np.repeat(np.unique(np.asarray(face_ids, np.int64)), 3), device=self.device)
        with torch.no_grad():
            for name, value in self.params.items():
                if name == "split_logits":
                    new = torch.zeros((children.size, 3), dtype=value.dtype, device=self.device)
                elif name == "d_mu":
                    new = torch.zeros((children.size, 3), dtype=value.dtype, device=self.device)
                else:
                    new = value[parents].clone()
                self.params[name] = torch.cat([value.detach(), new]).requires_grad_(True)
        self._structure_changed()
        return children.ravel()

    def to_avatar(self, meta=None) -> Avatar:
        arrays = {n: self.params[n].detach().cpu().numpy() for n in PARAM_NAMES}
        f = self.forest
        forest = f._like(f.parent, f.slot, self.params["split_logits"].detach().cpu().numpy(), f.root_ref)
        rest = self.params["f_rest"].detach().cpu().numpy() if "f_rest" in self.params else None
        return Avatar(forest, **arrays, meta=dict(meta or {}), f_rest=rest)
