"""The implicit subdivision forest (numpy only: runs inside Blender).

Every template face is the root of a ternary tree. Splitting face (i, j, k) at the point
p = b0·vi + b1·vj + b2·vk creates children slot 0 = (i, j, p), slot 1 = (j, k, p),
slot 2 = (k, i, p). Every vertex of every descendant is a fixed barycentric combination of
its root face's vertices, so the whole forest evaluates on any frame with one gather and a
small product.

Faces are stored flat in an order where a parent always precedes its children (creation
order, or stream order); roots are faces 0..F0-1 in template order. The split point's
barycentrics are softmax(split_logits): they can never leave the simplex.
"""

from __future__ import annotations

import numpy as np

from ..io.atomic import atomic_savez

FORMAT_VERSION = 1


def softmax(logits: np.ndarray) -> np.ndarray:
    z = logits - logits.max(axis=-1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=-1, keepdims=True)


def child_weights(parent_weights: np.ndarray, bary: np.ndarray, slot: np.ndarray) -> np.ndarray:
    """Geometry weights of children from their parents' weights and split barycentrics.

    Weights are [n,3,3]: row 0 = vertex 0 over the root's vertices, rows 1 and 2 = the edge
    differences (v1 - v0), (v2 - v0). The differences are propagated directly (never formed
    by subtracting absolute weights) so deep faces keep their relative precision.
    """
    w0, d1, d2 = parent_weights[:, 0], parent_weights[:, 1], parent_weights[:, 2]
    b0, b1, b2 = bary[:, 0:1], bary[:, 1:2], bary[:, 2:3]
    to_p = b1 * d1 + b2 * d2  # p - v_i
    s = slot[:, None]
    new_w0 = np.where(s == 0, w0, np.where(s == 1, w0 + d1, w0 + d2))
    new_d1 = np.where(s == 0, d1, np.where(s == 1, d2 - d1, -d2))
    new_d2 = np.where(s == 0, to_p, np.where(s == 1, b2 * d2 - (b0 + b2) * d1, b1 * d1 - (b0 + b1) * d2))
    return np.stack([new_w0, new_d1, new_d2], axis=1)


class Forest:
    """Structure of the subdivision forest: topology plus split-point logits."""

    def __init__(self, template_faces, parent=None, slot=None, split_logits=None):
        faces = np.ascontiguousarray(template_faces, dtype=np.int32)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"Forest: template faces must be a non-empty [F,3] array, got shape {faces.shape}")
        if faces.min() < 0:
            raise ValueError("Forest: template faces hold negative vertex indices")
        F0 = len(faces)
        self.template_faces = faces
        self.parent = np.full(F0, -1, np.int64) if parent is None else np.asarray(parent, np.int64).copy()
        self.slot = np.full(F0, -1, np.int8) if slot is None else np.asarray(slot, np.int8).copy()
        N = len(self.parent)
        if split_logits is None:
            split_logits = np.zeros((N, 3), np.float32)
        self.split_logits = np.asarray(split_logits, np.float32).reshape(N, 3).copy()
        self._derive()

    # -- structure ------------------------------------------------------------------------
    def _derive(self):
        F0, N = len(self.template_faces), len(self.parent)
        idx = np.arange(N)
        if N < F0 or len(self.slot) != N:
            raise ValueError("Forest: parent/slot arrays shorter than the template")
        if np.any(self.parent[:F0] != -1):
            raise ValueError("Forest: the first F0 faces must be the roots (parent -1)")
        nonroot = idx[F0:]
        p = self.parent[F0:]
        if np.any(p < 0) or np.any(p >= nonroot):
            raise ValueError("Forest: every non-root face needs a parent that precedes it")
        if np.any((self.slot[F0:] < 0) | (self.slot[F0:] > 2)):
            raise ValueError("Forest: child slots must be 0, 1 or 2")
        children = np.full((N, 3), -1, np.int64)
        children[p, self.slot[F0:].astype(np.int64)] = nonroot
        # A slot used twice would be silently overwritten above; count to catch it.
        if np.count_nonzero(children >= 0) != N - F0:
            raise ValueError("Forest: two faces claim the same (parent, slot)")
        self.children = children
        level = np.zeros(N, np.int8)
        root = idx.copy()
        # Parents precede children, so iterating "child = parent + 1" settles in depth+1 passes.
        while True:
            new_level = level.copy()
            new_level[F0:] = level[p] + 1
            new_root = root.copy()
            new_root[F0:] = root[p]
            if np.array_equal(new_level, level) and np.array_equal(new_root, root):
                break
            level, root = new_level, new_root
        self.level = level
        self.root = root

    @property
    def num_roots(self) -> int:
        return len(self.template_faces)

    @property
    def num_faces(self) -> int:
        return len(self.parent)

    def __len__(self) -> int:
        return self.num_faces

    @property
    def max_level(self) -> int:
        return int(self.level.max()) if self.num_faces else 0

    def level_counts(self) -> np.ndarray:
        return np.bincount(self.level, minlength=self.max_level + 1)

    def is_leaf(self) -> np.ndarray:
        return self.children[:, 0] < 0

    def leaves(self) -> np.ndarray:
        return np.flatnonzero(self.is_leaf())

    def split(self, face_ids) -> np.ndarray:
        """Split leaf faces; returns the new children's indices [k,3] (slots 0,1,2)."""
        ids = np.unique(np.asarray(face_ids, np.int64).ravel())
        if len(ids) == 0:
            return np.zeros((0, 3), np.int64)
        if ids.min() < 0 or ids.max() >= self.num_faces:
            raise IndexError("Forest.split: face index out of range")
        if not np.all(self.is_leaf()[ids]):
            raise ValueError("Forest.split: only leaf faces can be split")
        N, k = self.num_faces, len(ids)
        new = N + np.arange(3 * k).reshape(k, 3)
        self.parent = np.concatenate([self.parent, np.repeat(ids, 3)])
        self.slot = np.concatenate([self.slot, np.tile(np.arange(3, dtype=np.int8), k)])
        self.split_logits = np.concatenate([self.split_logits, np.zeros((3 * k, 3), np.float32)])
        self.children = np.concatenate([self.children, np.full((3 * k, 3), -1, np.int64)])
        self.children[ids] = new
        self.level = np.concatenate([self.level, np.repeat(self.level[ids] + 1, 3).astype(np.int8)])
        self.root = np.concatenate([self.root, np.repeat(self.root[ids], 3)])
        return new

    def subdivide_uniform(self, depth: int) -> "Forest":
        """Split every leaf until `depth` levels exist (uniform subdivision ablation)."""
        while self.max_level < depth:
            leaves = self.leaves()
            self.split(leaves[self.level[leaves] == self.max_level])
        return self

    def depth_per_root(self) -> np.ndarray:
        """Deepest level reached under each template face [F0]."""
        depth = np.zeros(self.num_roots, np.int8)
        np.maximum.at(depth, self.root, self.level)
        return depth

    def depth_histogram(self) -> np.ndarray:
        """Number of template faces whose tree reaches depth d, for d = 0..max_level."""
        return np.bincount(self.depth_per_root(), minlength=self.max_level + 1)

    def cumulative(self, level: int) -> np.ndarray:
        """Indices of the faces levels 0..level render together (what level `level` shows)."""
        return np.flatnonzero(self.level <= level)

    def cut(self, level: int) -> np.ndarray:
        """The surface tiling at `level`: faces at that level plus shallower leaves."""
        return np.flatnonzero((self.level == level) | ((self.level < level) & self.is_leaf()))

    def reorder(self, order) -> "Forest":
        """A copy with faces permuted by `order` (new face i = old face order[i]).

        The order must keep roots first in template order and parents before children.
        """
        order = np.asarray(order, np.int64)
        if len(order) != self.num_faces or not np.array_equal(np.sort(order), np.arange(self.num_faces)):
            raise ValueError("Forest.reorder: order must be a permutation of all faces")
        if not np.array_equal(order[: self.num_roots], np.arange(self.num_roots)):
            raise ValueError("Forest.reorder: roots must stay first, in template order")
        inverse = np.empty_like(order)
        inverse[order] = np.arange(len(order))
        parent = self.parent[order]
        parent = np.where(parent >= 0, inverse[np.maximum(parent, 0)], -1)
        return Forest(self.template_faces, parent, self.slot[order], self.split_logits[order])

    def prefix(self, n: int) -> "Forest":
        """The first n faces (valid whenever n >= F0, since parents precede children)."""
        if n < self.num_roots:
            raise ValueError(f"Forest.prefix: a prefix needs all {self.num_roots} roots, got {n}")
        return Forest(self.template_faces, self.parent[:n], self.slot[:n], self.split_logits[:n])

    # -- geometry -------------------------------------------------------------------------
    def barycentrics(self, logits=None) -> np.ndarray:
        """Split-point barycentrics [N,3], on the simplex by construction."""
        return softmax(np.asarray(self.split_logits if logits is None else logits, np.float64))

    def weights(self, logits=None) -> np.ndarray:
        """Per-face geometry weights [N,3,3] float64 (rows: w_v0, w_v1 - w_v0, w_v2 - w_v0)."""
        N, F0 = self.num_faces, self.num_roots
        bary = self.barycentrics(logits)
        W = np.empty((N, 3, 3), np.float64)
        W[:F0] = np.array([[1.0, 0.0, 0.0], [-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]])
        for lvl in range(1, self.max_level + 1):
            ids = np.flatnonzero(self.level == lvl)
            p = self.parent[ids]
            W[ids] = child_weights(W[p], bary[p], self.slot[ids])
        return W

    def vertex_weights(self, logits=None) -> np.ndarray:
        """Absolute barycentric weights of each face's three vertices over its root [N,3,3]."""
        W = self.weights(logits)
        return np.stack([W[:, 0], W[:, 0] + W[:, 1], W[:, 0] + W[:, 2]], axis=1)

    # -- persistence ----------------------------------------------------------------------
    def state(self, prefix: str = "forest_") -> dict:
        return {
            prefix + "version": np.array(FORMAT_VERSION),
            prefix + "template_faces": self.template_faces,
            prefix + "parent": self.parent,
            prefix + "slot": self.slot,
            prefix + "split_logits": self.split_logits,
        }

    @classmethod
    def from_state(cls, data, prefix: str = "forest_", source: str = "forest") -> "Forest":
        missing = [k for k in ("template_faces", "parent", "slot", "split_logits") if prefix + k not in data]
        if missing:
            raise ValueError(f"{source}: missing forest arrays {missing}")
        version = int(data[prefix + "version"]) if prefix + "version" in data else FORMAT_VERSION
        if version > FORMAT_VERSION:
            raise ValueError(f"{source}: forest format version {version} is newer than this reader ({FORMAT_VERSION})")
        try:
            return cls(data[prefix + "template_faces"], data[prefix + "parent"], data[prefix + "slot"],
                       data[prefix + "split_logits"])
        except ValueError as exc:
            raise ValueError(f"{source}: {exc}") from None

    def save(self, path) -> None:
        atomic_savez(path, **self.state())

    @classmethod
    def load(cls, path) -> "Forest":
        from ..io.safe_io import check_npz

        check_npz(path)  # bounded before numpy allocates
        with np.load(path, allow_pickle=False) as data:
            return cls.from_state(data, source=str(path))
