"""The per-face subdivision depth display: depth per template face (faces not arrived
included), the colour ramp and its legend, per-corner repetition. Blender tier (numpy).
"""

from __future__ import annotations

import numpy as np


# A perceptual ramp (dark blue → teal → yellow), sampled at depth / max(max_depth, 1).
_RAMP = np.array(
    [
        [0.050, 0.030, 0.280],
        [0.150, 0.300, 0.620],
        [0.100, 0.600, 0.600],
        [0.450, 0.800, 0.300],
        [0.990, 0.900, 0.150],
    ],
    np.float32,
)


NOT_ARRIVED = -1  # depth of a face none of whose Gaussians has arrived
# Neutral light grey: off the ramp (no ramp colour is grey) and unlike the dark depth 0.
NOT_ARRIVED_COLOR = np.array([0.55, 0.55, 0.55, 1.0], np.float32)


def depth_colors(depth: np.ndarray, max_depth: int | None = None) -> np.ndarray:
    """Linear RGBA colours [F,4] float32 for integer depths (0 = darkest); NOT_ARRIVED
    (negative) depths get NOT_ARRIVED_COLOR."""
    depth = np.asarray(depth, np.float32)
    top = float(max(depth.max() if depth.size else 0, 1) if max_depth is None else max(max_depth, 1))
    x = np.clip(depth / top, 0, 1) * (len(_RAMP) - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), len(_RAMP) - 2)
    w = (x - i0)[:, None]
    rgb = _RAMP[i0] * (1 - w) + _RAMP[i0 + 1] * w
    out = np.concatenate([rgb, np.ones((len(rgb), 1), np.float32)], axis=1).astype(np.float32)
    out[depth < 0] = NOT_ARRIVED_COLOR
    return out


def per_corner(values: np.ndarray, loop_totals: np.ndarray) -> np.ndarray:
    """Repeat per-face rows for each of the face's corners (Blender's corner domain)."""
    return np.repeat(np.asarray(values), np.asarray(loop_totals, np.int64), axis=0)


def depth_legend(depth_per_face: np.ndarray, max_depth: int | None = None) -> list[tuple[int, int, tuple]]:
    """(depth, number of template faces, RGB) for every depth 0..max, led by
    (NOT_ARRIVED, count, its colour) when some faces have no Gaussian yet."""
    depth = np.asarray(depth_per_face, np.int64)
    top = int(max(depth.max(), 0)) if depth.size else 0
    top = top if max_depth is None else max(int(max_depth), 0)
    hist = np.bincount(depth[depth >= 0], minlength=top + 1)
    cols = depth_colors(np.arange(top + 1), top)
    out = [(d, int(hist[d]), tuple(float(c) for c in cols[d, :3])) for d in range(top + 1)]
    missing = int(np.count_nonzero(depth < 0))
    if missing:
        out.insert(0, (NOT_ARRIVED, missing, tuple(float(c) for c in NOT_ARRIVED_COLOR[:3])))
    return out


def depth_per_face(forest, num_template_faces: int, count: int | None = None) -> np.ndarray:
    """Deepest level among the Gaussians of the first ``count`` stream records (all if None) under each of the
    mesh's ``num_template_faces`` faces, int32; NOT_ARRIVED where none of them lies under
    the face (a stream cut inside the template level, or a budget below it)."""
    n = forest.num_faces if count is None else int(min(max(count, 0), forest.num_faces))
    ids = forest.stream_ids(n) if hasattr(forest, "stream_ids") else np.arange(n)
    depth = np.full(int(num_template_faces), NOT_ARRIVED, np.int32)
    # A face's root is a row of the root table: coarse triangles first (they sit above the
    # template and cover no single template face), then template faces in any order.
    coarse = int(getattr(forest, "num_coarse", 0))
    ref = getattr(forest, "root_ref", None)
    root = forest.root[ids] if ref is None else np.asarray(ref)[forest.root[ids]] - coarse
    keep = root >= 0
    if keep.any() and int(root[keep].max()) >= len(depth):
        raise ValueError(f"the avatar has {len(forest.template_faces)} template faces, the mesh {len(depth)}")
    below = forest.level[ids].astype(np.int32) - int(getattr(forest, "num_coarse_levels", 0))
    np.maximum.at(depth, root[keep], below[keep])
    return depth
