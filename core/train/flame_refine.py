"""FLAME parameter refinement during training (FLAME-mode datasets): per-timestep corrections
to the tracked expression, joint poses and translation, learnt with the avatar.

Tracking is imperfect; letting the photometric loss move the parameters a little fixes
misaligned jaws and eyes that the Gaussians would otherwise blur over. The corrections
start at zero and use GaussianAvatars' learning rates (expression 1e-3, pose 1e-5,
translation 1e-6), so they stay small. Shape and static offsets are per subject and left as
tracked. Only training timesteps are refined; the refined parameters are written to
RUN/flame_refined.npz.
"""

from __future__ import annotations

import numpy as np
import torch

from ..flame.model import POSE_WIDTHS
from .flame_torch import FlameTorch

_DELTAS = ("expr", "pose", "translation")


def _row(d: dict, key: str, width: int) -> np.ndarray:
    v = d.get(key)
    out = np.zeros(width)
    if v is not None:
        v = np.asarray(v, np.float64).reshape(-1)
        n = min(width, v.size)
        out[:n] = v[:n]
    return out


def _offsets(per: list, key: str, n_vertices: int):
    """Per-vertex offsets [1|T,V,3] of the timesteps (one row when every file holds the same;
    zeros for a file without them), or None when no file has them."""
    rows = [None if p.get(key) is None else np.asarray(p[key], np.float32).reshape(-1, n_vertices, 3)[:1] for p in per]
    given = [r for r in rows if r is not None]
    if not given:
        return None
    if len(given) == len(rows) and all(np.array_equal(r, given[0]) for r in given[1:]):
        return torch.from_numpy(given[0].copy())
    zero = np.zeros((1, n_vertices, 3), np.float32)
    return torch.from_numpy(np.concatenate([zero if r is None else r for r in rows]))


def _rows_of(offsets, rows):
    if offsets is None or offsets.shape[0] == 1:
        return offsets
    return offsets[rows]


class FlameRefiner:
    def __init__(self, dataset, lrs: dict):
        self.flame = FlameTorch(dataset.flame_model)
        self.timesteps = np.asarray(dataset.timesteps, np.int64)
        self.row = {int(t): i for i, t in enumerate(self.timesteps)}
        per = [dataset.flame_params_at(t) for t in self.timesteps.tolist()]
        E, V = self.flame.n_expr, self.flame.n_vertices
        # Everything the dataset's own evaluation reads (Dataset.vertices_at), row by row, so that
        # zero corrections give the tracked meshes exactly: the shape and static offsets as each
        # timestep's file holds them, the per-frame dynamic offsets (VHAP) as a fixed base.
        self.shape = torch.tensor(np.stack([_row(p, "shape", self.flame.n_shape) for p in per]), dtype=torch.float32)
        self.static_offset = _offsets(per, "static_offset", V)
        self.dynamic_offset = _offsets(per, "dynamic_offset", V)
        self.base = {
            "expr": torch.tensor(np.stack([_row(p, "expr", E) for p in per]), dtype=torch.float32),
            "pose": torch.tensor(
                np.stack([np.concatenate([_row(p, k, w) for k, w in POSE_WIDTHS]) for p in per]), dtype=torch.float32
            ),
            "translation": torch.tensor(np.stack([_row(p, "translation", 3) for p in per]), dtype=torch.float32),
        }
        self.delta = {k: torch.zeros_like(v).requires_grad_(True) for k, v in self.base.items()}
        self.lrs = {
            "expr": lrs.get("flame_expr", 1e-3),
            "pose": lrs.get("flame_pose", 1e-5),
            "translation": lrs.get("flame_translation", 1e-6),
        }
        self.opt = torch.optim.Adam([{"params": [self.delta[k]], "lr": self.lrs[k]} for k in _DELTAS], eps=1e-15)

    def has(self, timestep) -> bool:
        return int(timestep) in self.row

    def params(self, rows) -> dict:
        """Refined FLAME parameters (torch) of the given rows, as FlameTorch takes them."""
        p = {k: self.base[k][rows] + self.delta[k][rows] for k in _DELTAS}
        pose = p["pose"]
        out = {
            "shape": self.shape[rows],
            "expr": p["expr"],
            "translation": p["translation"],
            "static_offset": _rows_of(self.static_offset, rows),
            "dynamic_offset": _rows_of(self.dynamic_offset, rows),
        }
        o = 0
        for key, w in POSE_WIDTHS:
            out[key] = pose[:, o : o + w]
            o += w
        return out

    def vertices(self, timestep) -> torch.Tensor:
        """Vertices [V,3] of a training timestep under the current corrections (differentiable)."""
        i = self.row[int(timestep)]
        return self.flame(**self.params(slice(i, i + 1)))[0]

    def step(self):
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)

    def gradients(self) -> dict:
        return {f"gradient of FLAME {k} correction": self.delta[k].grad for k in _DELTAS}

    def corrections(self) -> dict:
        return {f"FLAME {k} correction": self.delta[k] for k in _DELTAS}

    # -- persistence ------------------------------------------------------------------------
    def state(self) -> dict:
        out = {"flame_timesteps": self.timesteps.copy()}
        for i, k in enumerate(_DELTAS):
            out[f"flame_delta_{k}"] = self.delta[k].detach().numpy().copy()
            st = self.opt.state.get(self.delta[k], {})
            if st:
                out[f"flame_adam_m_{k}"] = st["exp_avg"].numpy().copy()
                out[f"flame_adam_v_{k}"] = st["exp_avg_sq"].numpy().copy()
                out[f"flame_adam_step_{k}"] = np.asarray(float(st["step"]))
        return out

    def load_state(self, d, source: str):
        if "flame_timesteps" in d:
            was = np.asarray(d["flame_timesteps"]).reshape(-1)
            if not np.array_equal(was, self.timesteps):
                raise ValueError(
                    f"{source}: the FLAME corrections are for training timesteps {_ids(was)}, the dataset's are "
                    f"{_ids(self.timesteps)}: resume on the dataset the run was started on"
                )
        for k in _DELTAS:
            key = f"flame_delta_{k}"
            if key not in d:
                raise ValueError(
                    f"{source}: the checkpoint has no FLAME corrections; resume with the same --refine-flame setting"
                )
            arr = np.asarray(d[key])
            if arr.shape != tuple(self.delta[k].shape):
                raise ValueError(
                    f"{source}: FLAME {k} corrections have shape {arr.shape}, the dataset needs "
                    f"{tuple(self.delta[k].shape)}"
                )
            with torch.no_grad():
                self.delta[k].copy_(torch.from_numpy(arr))
            if f"flame_adam_m_{k}" in d:
                self.opt.state[self.delta[k]] = {
                    "step": torch.tensor(float(d[f"flame_adam_step_{k}"])),
                    "exp_avg": torch.from_numpy(np.array(d[f"flame_adam_m_{k}"])),
                    "exp_avg_sq": torch.from_numpy(np.array(d[f"flame_adam_v_{k}"])),
                }

    @torch.no_grad()
    def refined_arrays(self) -> dict:
        """Per-timestep refined parameters (numpy), and the corrections alone."""
        p = self.params(slice(None))
        out = {"timesteps": self.timesteps}
        for key in ("expr", "translation") + tuple(k for k, _ in POSE_WIDTHS):
            out[key] = p[key].numpy().astype(np.float32)
        out["shape"] = self.shape.numpy()
        for k in _DELTAS:
            out[f"correction_{k}"] = self.delta[k].detach().numpy().copy()
        return out


def _ids(timesteps: np.ndarray, shown: int = 8) -> str:
    t = [int(x) for x in timesteps[:shown]]
    return str(t)[:-1] + (f", ... ({len(timesteps)})]" if len(timesteps) > shown else "]")
