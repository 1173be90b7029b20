"""``Gaussians``: world-space Gaussian geometry in the rasteriser's argument order.

Every evaluator returns one (``GaussianEvaluator``, ``binding.compose``, ``binding_torch.compose``,
``FaceBinding.gaussians``), so ``render(*g, opacities, colors, camera)`` and
``means, quats, scales = g`` read the same way everywhere. The fields are numpy arrays or
torch tensors alike. Blender tier (stdlib only).
"""

from __future__ import annotations

from typing import Any, NamedTuple


class Gaussians(NamedTuple):
    """means [N,3]; quats [N,4] wxyz (unit); scales [N,3] (standard deviations, > 0)."""

    means: Any
    quats: Any
    scales: Any
