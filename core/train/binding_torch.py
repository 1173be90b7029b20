"""Differentiable forest evaluation and Gaussian composition (torch).

Same formulas and conventions as binding.py (numpy); the two agree to float32 precision.
Gradients flow to the mesh vertices and to the split logits.
"""

from __future__ import annotations

import numpy as np
import torch

from ..avatar.binding import MIN_EDGE
from ..avatar.forest import Forest
from ..geometry.gaussians import Gaussians
from ..geometry.rotations import quat_multiply, quat_normalize, quat_to_rotmat, rotmat_to_quat  # noqa: F401


def _norm(v: torch.Tensor) -> torch.Tensor:
    # Scaled by the largest component (tiny float32 vectors would underflow when squared),
    # and clamped so the derivative at a zero vector stays finite (0), never NaN.
    m = v.detach().abs().amax(-1).clamp_min(torch.finfo(v.dtype).tiny)
    u = v / m[..., None]
    return torch.sqrt((u * u).sum(-1).clamp_min(1e-30)) * m


def _safe_unit(v: torch.Tensor, n: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    # torch.where still backpropagates 0 * d(branch): dividing by a denormal length in the
    # unselected branch would make that 0 * inf = NaN, so masked-out rows divide by 1.
    return v / torch.where(ok, n, torch.ones_like(n))[..., None]


def frames_from_edges(e1: torch.Tensor, e2: torch.Tensor, normal: torch.Tensor | None = None):
    """Face frames r [...,3,3] and scales s [...] from edges (same rules as binding.py)."""
    eps = 8 * torch.finfo(e1.dtype).eps
    n1, n2 = _norm(e1), _norm(e2)
    has1 = n1.detach() > MIN_EDGE
    has2 = n2.detach() > MIN_EDGE
    axis_x = torch.zeros_like(e1)
    axis_x[..., 0] = 1
    x = torch.where(
        has1[..., None], _safe_unit(e1, n1, has1), torch.where(has2[..., None], _safe_unit(e2, n2, has2), axis_x)
    )
    own = torch.linalg.cross(x, e2)
    own_n = _norm(own)
    own_flat = ~has2 | (own_n.detach() <= eps * n2.detach())
    own_hat = _safe_unit(own, own_n, ~own_flat)
    if normal is None:
        y, flat = own_hat, own_flat
    else:
        nn = _norm(normal)
        good = nn.detach() > MIN_EDGE * MIN_EDGE
        n_hat = _safe_unit(normal, nn, good)
        x_in = x - (x * n_hat).sum(-1, keepdim=True) * n_hat
        x = torch.where(good[..., None], x_in / _norm(x_in)[..., None], x)
        y = torch.where(good[..., None], n_hat, own_hat)
        flat = ~good & own_flat
    least = torch.argmin(x.detach().abs(), dim=-1)
    # a comparison, not one_hot: one_hot checks its input's range on the host, a sync that a CUDA graph refuses
    helper = (least[..., None] == torch.arange(3, device=least.device)).to(e1.dtype)
    alt = torch.linalg.cross(x, helper)
    alt = alt / _norm(alt)[..., None]
    y = torch.where(flat[..., None], alt, y)
    z = torch.linalg.cross(x, y)
    r = torch.stack([x, y, z], dim=-1)
    s = 0.5 * (torch.where(has1, n1, torch.zeros_like(n1)) + (z * e2).sum(-1).abs())
    return r, s.clamp_min(1e-10)


class TorchForest:
    """Index tensors of a Forest, for differentiable evaluation of all its faces."""

    def __init__(self, forest: Forest, device="cpu"):
        self.forest = forest
        self.device = torch.device(device)
        as_t = lambda a: torch.as_tensor(np.ascontiguousarray(a), device=self.device)  # noqa: E731
        self.template_faces = as_t(forest.root_faces.astype(np.int64))  # per root (coarse and template)
        self.root = as_t(forest.root)
        self.levels = []
        R = forest.num_roots
        for lvl in range(int(forest.level[R:].min()) if forest.num_faces > R else 1, forest.max_level + 1):
            ids = np.flatnonzero(forest.level[R:] == lvl) + R
            self.levels.append((as_t(ids), as_t(forest.parent[ids]), as_t(forest.slot[ids].astype(np.int64))))

    @property
    def num_faces(self) -> int:
        return self.forest.num_faces

    def weights(self, split_logits: torch.Tensor) -> torch.Tensor:
        """[N,3,3] geometry weights (numpy Forest.weights' layout), differentiable in the logits."""
        N = self.forest.num_faces
        dtype = split_logits.dtype
        bary = torch.softmax(split_logits, dim=-1)
        base = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]], dtype=dtype, device=self.device)
        W = base.expand(N, 3, 3)
        for ids, parent, slot in self.levels:
            pw, b = W[parent], bary[parent]
            w0, d1, d2 = pw[:, 0], pw[:, 1], pw[:, 2]
            b0, b1, b2 = b[:, 0:1], b[:, 1:2], b[:, 2:3]
            s = slot[:, None]
            new_w0 = torch.where(s == 0, w0, torch.where(s == 1, w0 + d1, w0 + d2))
            new_d1 = torch.where(s == 0, d1, torch.where(s == 1, d2 - d1, -d2))
            new_d2 = torch.where(
                s == 0, b1 * d1 + b2 * d2, torch.where(s == 1, b2 * d2 - (b0 + b2) * d1, b1 * d1 - (b0 + b1) * d2)
            )
            W = W.index_copy(0, ids, torch.stack([new_w0, new_d1, new_d2], dim=1))
        return W

    def evaluate(self, vertices: torch.Tensor, weights: torch.Tensor, ids: torch.Tensor | None = None):
        """(t, r, s) for faces `ids` (default all) on vertices [V,3] or [T,V,3]."""
        single = vertices.dim() == 2
        verts = vertices[None] if single else vertices
        tri = self.template_faces
        root = self.root if ids is None else self.root[ids]
        W = weights if ids is None else weights[ids]
        W = W.to(verts.dtype)
        rv0 = verts[:, tri[:, 0]]
        E1 = (verts[:, tri[:, 1]] - rv0)[:, root]
        E2 = (verts[:, tri[:, 2]] - rv0)[:, root]
        normal = torch.linalg.cross(E1, E2)
        rv0 = rv0[:, root]

        def combine(w):
            return w[None, :, 1:2] * E1 + w[None, :, 2:3] * E2

        e1, e2 = combine(W[:, 1]), combine(W[:, 2])
        r, s = frames_from_edges(e1, e2, normal)
        t = rv0 + combine(W[:, 0]) + (e1 + e2) / 3
        if single:
            return t[0], r[0], s[0]
        return t, r, s


def compose(t, r, s, d_mu, d_log_scale, d_rot):
    """μ = s·r·Δμ + t, S = s·exp(ΔS), R = r ⊗ ΔR (wxyz): ``Gaussians`` of tensors; see binding.compose."""
    means = s[..., None] * torch.einsum("...ij,...j->...i", r, d_mu) + t
    scales = s[..., None] * torch.exp(d_log_scale)
    quats = quat_multiply(rotmat_to_quat(r), quat_normalize(d_rot))
    return Gaussians(means, quats, scales)
