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

# 3: root_rank (a stream that interleaves roots with other faces); 4: stand-ins; 5: backdrop stand-ins
FORMAT_VERSION = 5


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
    """Structure of the subdivision forest: topology plus split-point logits.

    Roots are the first R faces. A root is one triangle of the *root table*: the coarse
    triangles (levels 0..K-1, three template vertices each, grouped by level) followed by the
    template faces (level K). ``root_ref[i]`` names root i's row of that table, so roots may
    come in any order (a stream's spread-out order) and a prefix may hold any subset of them.
    Without coarse levels (K = 0) and without ``root_ref`` the roots are the template faces in
    template order, as before. ``depth`` = level - K is the subdivision depth below the
    template (negative for coarse faces); only template faces and their descendants split.

    Coarse faces are *stand-ins* when ``stand_ins`` (docs/FORMAT.md 2.4, docs/ARCHITECTURE.md): they
    render only until the template faces around them have arrived, so the finished avatar is
    the template level and its subdivisions alone (see ``drawn``). ``retire`` [C], per coarse
    table row, is the stream position at which the stand-in makes way (docs/FORMAT.md 2.4; a
    stream's forest; None for a trained one): it renders in a prefix of n records while
    n <= retire. Without stand-ins coarse faces stay in every prefix (cumulative levels).
    With ``backdrop`` (stand-ins only) a retired stand-in stays, composited behind every other
    Gaussian (see ``render_set``), so a prefix only ever gains what it draws.
    """

    def __init__(
        self,
        template_faces,
        parent=None,
        slot=None,
        split_logits=None,
        *,
        coarse_faces=None,
        coarse_counts=(),
        root_ref=None,
        root_rank=None,
        stand_ins=False,
        retire=None,
        backdrop=False,
    ):
        faces = np.ascontiguousarray(template_faces, dtype=np.int32)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"Forest: template faces must be a non-empty [F,3] array, got shape {faces.shape}")
        if faces.min() < 0:
            raise ValueError("Forest: template faces hold negative vertex indices")
        self.template_faces = faces
        self.coarse_counts = tuple(int(c) for c in coarse_counts)
        C = sum(self.coarse_counts)
        coarse = np.zeros((0, 3), np.int32) if coarse_faces is None else np.ascontiguousarray(coarse_faces, np.int32)
        if coarse.ndim != 2 or coarse.shape[1] != 3 or len(coarse) != C or any(c < 1 for c in self.coarse_counts):
            raise ValueError(
                f"Forest: coarse faces {coarse.shape} disagree with the coarse level counts {list(self.coarse_counts)}"
            )
        if C and (coarse.min() < 0 or coarse.max() > faces.max()):
            raise ValueError("Forest: coarse faces must be triangles of template vertices")
        self.coarse_faces = coarse
        if root_ref is None:
            n_roots = C + len(faces)
            if parent is not None:
                n_roots = min(n_roots, len(parent))
            root_ref = np.arange(n_roots, dtype=np.int64)
        self.root_ref = np.asarray(root_ref, np.int64).copy()
        R = len(self.root_ref)
        self.parent = np.full(R, -1, np.int64) if parent is None else np.asarray(parent, np.int64).copy()
        self.slot = np.full(R, -1, np.int8) if slot is None else np.asarray(slot, np.int8).copy()
        N = len(self.parent)
        if split_logits is None:
            split_logits = np.zeros((N, 3), np.float32)
        self.split_logits = np.asarray(split_logits, np.float32).reshape(N, 3).copy()
        self._derive()
        self.root_rank = self._check_root_rank(root_rank)
        self._set_stand_ins(stand_ins, retire, backdrop)

    def _set_stand_ins(self, stand_ins, retire, backdrop=False):
        self.stand_ins = bool(stand_ins) and self.num_coarse > 0
        self.backdrop = bool(backdrop) and self.stand_ins
        self.retire = None
        if self.stand_ins and retire is not None:
            retire = np.asarray(retire, np.int64).reshape(-1)
            if len(retire) != self.num_coarse or (len(retire) and retire.min() < 0):
                raise ValueError(
                    f"Forest: stand-in retire positions {retire.shape} must be {self.num_coarse} values >= 0"
                )
            self.retire = retire.copy()

    def shown_until(self) -> np.ndarray | None:
        """[N] per face, the most stream records with which it still renders: a coarse
        stand-in's retire position (without them, the stream position of the last template
        face), every other face for ever (int32 max). None without stand-ins."""
        if not self.stand_ins:
            return None
        K = self.num_coarse_levels
        until = np.full(self.num_faces, np.iinfo(np.int32).max, np.int64)
        coarse = np.flatnonzero(self.level < K)
        if self.retire is not None:
            until[coarse] = self.retire[self.root_ref[coarse]]
        else:
            tmpl = self.level == K
            until[coarse] = self.stream_rank()[tmpl].max() if tmpl.any() else until[0]
        return until

    def drawn(self, ids=None, records=None) -> np.ndarray:
        """The faces that render when faces ``ids`` (default: every face) have arrived, in the
        order given. Without stand-ins: all of them. With stand-ins a coarse face drops out
        once its region is complete: when ``ids`` are the first ``records`` stream records
        (for ``ids=None`` by default this forest's own faces: a stream prefix or the whole
        avatar), once ``records`` exceeds its ``shown_until``; otherwise (a set of whole levels,
        another order's prefix) once every template face is among ``ids``."""
        whole = ids is None
        ids = np.arange(self.num_faces, dtype=np.int64) if whole else np.asarray(ids, np.int64)
        if not self.stand_ins or len(ids) == 0:
            return ids
        if whole and records is None:
            records = self.num_faces
        if records is not None:
            return ids[self.shown_until()[ids] >= int(records)]
        K = self.num_coarse_levels
        if np.count_nonzero(self.level[ids] == K) < len(self.template_faces):
            return ids
        return ids[self.level[ids] >= K]

    def render_set(self, ids=None, records=None) -> tuple[np.ndarray, np.ndarray | None]:
        """(faces, behind): the faces that render when faces ``ids`` have arrived and, for a
        backdrop forest, which of them composite behind all the others (the retired stand-ins;
        None when none are). Otherwise ``(drawn(ids, records), None)``. ``records`` as in
        ``drawn``; ids that are this forest's first n stream records count as n records."""
        if not self.backdrop:
            return self.drawn(ids, records), None
        whole = ids is None
        ids = np.arange(self.num_faces, dtype=np.int64) if whole else np.asarray(ids, np.int64)
        if records is None and (whole or np.array_equal(ids, self.stream_ids(len(ids)))):
            records = len(ids)
        behind = ~np.isin(ids, self.drawn(ids, records))
        return ids, (behind if behind.any() else None)

    # -- structure ------------------------------------------------------------------------
    @property
    def num_coarse_levels(self) -> int:
        return len(self.coarse_counts)

    @property
    def num_coarse(self) -> int:
        """Rows of the coarse table (coarse triangles of every coarse level)."""
        return len(self.coarse_faces)

    @property
    def root_table(self) -> np.ndarray:
        """[C + F0, 3]: the coarse triangles, then the template faces."""
        if not self.num_coarse:
            return self.template_faces
        return np.concatenate([self.coarse_faces, self.template_faces])

    @property
    def root_faces(self) -> np.ndarray:
        """[R,3] template vertex indices of each root, in face order (what the binding reads)."""
        if not self.num_coarse and np.array_equal(self.root_ref, np.arange(len(self.root_ref))):
            return self.template_faces[: len(self.root_ref)]
        return self.root_table[self.root_ref]

    def _root_levels(self) -> np.ndarray:
        C = self.num_coarse
        ends = np.cumsum(self.coarse_counts)
        return np.where(
            self.root_ref < C, np.searchsorted(ends, self.root_ref, side="right"), self.num_coarse_levels
        ).astype(np.int8)

    def _derive(self):
        R, N = len(self.root_ref), len(self.parent)
        C, F0, K = self.num_coarse, len(self.template_faces), self.num_coarse_levels
        idx = np.arange(N)
        if N < R or len(self.slot) != N:
            raise ValueError("Forest: parent/slot arrays shorter than the roots")
        if R and (self.root_ref.min() < 0 or self.root_ref.max() >= C + F0 or len(np.unique(self.root_ref)) != R):
            raise ValueError("Forest: root references must be distinct rows of the coarse + template table")
        if np.any(self.parent[:R] != -1):
            raise ValueError("Forest: the first faces must be the roots (parent -1)")
        nonroot = idx[R:]
        p = self.parent[R:]
        if np.any(p < 0) or np.any(p >= nonroot):
            raise ValueError("Forest: every non-root face needs a parent that precedes it")
        if np.any((self.slot[R:] < 0) | (self.slot[R:] > 2)):
            raise ValueError("Forest: child slots must be 0, 1 or 2")
        children = np.full((N, 3), -1, np.int64)
        children[p, self.slot[R:].astype(np.int64)] = nonroot
        # A slot used twice would be silently overwritten above; count to catch it.
        if np.count_nonzero(children >= 0) != N - R:
            raise ValueError("Forest: two faces claim the same (parent, slot)")
        self.children = children
        level = np.zeros(N, np.int8)
        level[:R] = self._root_levels()
        root = idx.copy()
        # Parents precede children, so iterating "child = parent + 1" settles in depth+1 passes.
        while True:
            new_level = level.copy()
            new_level[R:] = level[p] + 1
            new_root = root.copy()
            new_root[R:] = root[p]
            if np.array_equal(new_level, level) and np.array_equal(new_root, root):
                break
            level, root = new_level, new_root
        if np.any(level[R:] <= level[p]):  # int8 wrapped past 127
            raise ValueError("Forest: faces deeper than level 127 (the deepest a forest holds)")
        if K and np.any(level[p] < K):
            raise ValueError("Forest: coarse faces cannot have children")
        self.level = level
        self.root = root

    @property
    def num_roots(self) -> int:
        """Parentless faces (coarse and template roots): faces 0..num_roots-1."""
        return len(self.root_ref)

    def _check_root_rank(self, root_rank) -> np.ndarray:
        R, N = self.num_roots, self.num_faces
        if root_rank is None:
            return np.arange(R, dtype=np.int64)
        rank = np.asarray(root_rank, np.int64).copy()
        if rank.shape != (R,) or (R and (rank[0] < 0 or rank[-1] >= N or np.any(np.diff(rank) <= 0))):
            raise ValueError(f"Forest: root_rank must be {R} increasing stream positions in [0, {N})")
        if R < N and not np.array_equal(rank, np.arange(R)):
            p = self.parent[R:]
            own = self._ranks(rank)
            if np.any(own[p] >= own[R:]):
                raise ValueError("Forest: root_rank puts a root after one of its children")
        return rank

    def stream_rank(self) -> np.ndarray:
        """[N] stream position of each face: roots at ``root_rank``, the other faces at the
        remaining positions in face order."""
        return self._ranks(self.root_rank)

    def _ranks(self, rr) -> np.ndarray:
        R, N = self.num_roots, self.num_faces
        rank = np.empty(N, np.int64)
        if len(rr) == 0 or rr[-1] == R - 1:  # roots first
            rank[:] = np.arange(N)
            return rank
        rank[:R] = rr
        free = np.ones(N, bool)
        free[rr] = False
        rank[R:] = np.flatnonzero(free)
        return rank

    def stream_order(self) -> np.ndarray:
        """[N] face at each stream position (the inverse of ``stream_rank``)."""
        out = np.empty(self.num_faces, np.int64)
        out[self.stream_rank()] = np.arange(self.num_faces)
        return out

    def roots_in_prefix(self, n: int) -> int:
        """Roots among the first n stream records."""
        return int(np.searchsorted(self.root_rank, int(n)))

    def stream_ids(self, n: int) -> np.ndarray:
        """Faces of the first n stream records, ascending (0..n-1 when the roots come first)."""
        n = int(min(max(int(n), 0), self.num_faces))
        r = self.roots_in_prefix(n)
        if r == min(n, self.num_roots):
            return np.arange(n, dtype=np.int64)
        return np.concatenate([np.arange(r), self.num_roots + np.arange(n - r)]).astype(np.int64)

    @property
    def depth(self) -> np.ndarray:
        """Subdivision depth below the template per face (level - K; coarse faces negative)."""
        return (self.level - self.num_coarse_levels).astype(np.int8)

    @property
    def max_depth(self) -> int:
        return max(int(self.level.max()) - self.num_coarse_levels, 0) if self.num_faces else 0

    def splittable(self) -> np.ndarray:
        """Leaves that may split: template faces and their descendants (never coarse faces)."""
        leaves = self.leaves()
        return leaves[self.level[leaves] >= self.num_coarse_levels]

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
        if np.any(self.level[ids] >= np.iinfo(np.int8).max):  # (levels are int8: 127 + 1 would wrap)
            raise ValueError(f"Forest.split: faces at level {np.iinfo(np.int8).max} do not split (the deepest level)")
        if np.any(self.level[ids] < self.num_coarse_levels):
            raise ValueError("Forest.split: coarse faces do not split")
        N, k = self.num_faces, len(ids)
        new = N + np.arange(3 * k).reshape(k, 3)
        self.parent = np.concatenate([self.parent, np.repeat(ids, 3)])
        self.slot = np.concatenate([self.slot, np.tile(np.arange(3, dtype=np.int8), k)])
        self.split_logits = np.concatenate([self.split_logits, np.zeros((3 * k, 3), np.float32)])
        self.children = np.concatenate([self.children, np.full((3 * k, 3), -1, np.int64)])
        self.children[ids] = new
        self.level = np.concatenate([self.level, np.repeat(self.level[ids] + 1, 3).astype(np.int8)])
        self.root = np.concatenate([self.root, np.repeat(self.root[ids], 3)])
        self.retire = None  # stream positions of a stream this forest no longer is
        return new

    def subdivide_uniform(self, depth: int) -> "Forest":
        """Split every leaf until `depth` levels exist (uniform subdivision ablation)."""
        while self.max_depth < depth or self.max_level < self.num_coarse_levels:
            leaves = self.splittable()
            self.split(leaves[self.level[leaves] == self.max_level])
        return self

    def depth_per_root(self) -> np.ndarray:
        """Deepest subdivision depth reached under each template face [F0] (template order);
        -1 for template faces whose root is not in this forest (a stream prefix)."""
        F0, C = len(self.template_faces), self.num_coarse
        depth = np.full(F0, -1, np.int8)
        tmpl = self.root_ref[self.root] - C  # template face of each face's root (< 0: coarse)
        keep = tmpl >= 0
        np.maximum.at(depth, tmpl[keep], self.depth[keep])
        return depth

    def depth_histogram(self) -> np.ndarray:
        """Number of template faces whose tree reaches depth d, for d = 0..max_depth."""
        d = self.depth_per_root()
        return np.bincount(d[d >= 0], minlength=self.max_depth + 1)

    def cumulative(self, level: int) -> np.ndarray:
        """Indices of the faces levels 0..level render together (what level `level` shows)."""
        return np.flatnonzero(self.level <= level)

    def cut(self, level: int) -> np.ndarray:
        """The surface tiling at `level`: faces at that level plus shallower leaves."""
        return np.flatnonzero((self.level == level) | ((self.level < level) & self.is_leaf()))

    def reorder(self, order) -> "Forest":
        """A copy with faces permuted by `order` (new face i = old face order[i]), in its own
        stream order (roots first).

        The order must keep the roots first (in any order among themselves) and parents
        before children.
        """
        order = np.asarray(order, np.int64)
        R = self.num_roots
        if len(order) != self.num_faces or not np.array_equal(np.sort(order), np.arange(self.num_faces)):
            raise ValueError("Forest.reorder: order must be a permutation of all faces")
        if not np.array_equal(np.sort(order[:R]), np.arange(R)):
            raise ValueError("Forest.reorder: roots must stay first")
        inverse = np.empty_like(order)
        inverse[order] = np.arange(len(order))
        parent = self.parent[order]
        parent = np.where(parent >= 0, inverse[np.maximum(parent, 0)], -1)
        # (the stream positions change with the order: the retire positions no longer hold)
        return self._like(parent, self.slot[order], self.split_logits[order], self.root_ref[order[:R]], retire=None)

    def _like(self, parent, slot, split_logits, root_ref, root_rank=None, retire="same") -> "Forest":
        return Forest(
            self.template_faces,
            parent,
            slot,
            split_logits,
            coarse_faces=self.coarse_faces,
            coarse_counts=self.coarse_counts,
            root_ref=root_ref,
            root_rank=root_rank,
            stand_ins=self.stand_ins,
            retire=self.retire if isinstance(retire, str) else retire,
            backdrop=self.backdrop,
        )

    def prefix(self, n: int) -> "Forest":
        """The faces of the first n stream records (any n >= 1: parents precede children; a
        prefix may hold some roots only), roots first."""
        n = int(n)
        if not 1 <= n <= self.num_faces:
            raise ValueError(f"Forest.prefix: n must be in [1, {self.num_faces}], got {n}")
        ids = self.stream_ids(n)
        R, r = self.num_roots, self.roots_in_prefix(n)
        parent = self.parent[ids]
        if r < R:  # the other faces move up behind the r roots received
            parent = np.where(parent >= R, parent - (R - r), parent)
        return self._like(parent, self.slot[ids], self.split_logits[ids], self.root_ref[:r], self.root_rank[:r])

    # -- geometry -------------------------------------------------------------------------
    def barycentrics(self, logits=None) -> np.ndarray:
        """Split-point barycentrics [N,3], on the simplex by construction."""
        return softmax(np.asarray(self.split_logits if logits is None else logits, np.float64))

    def weights(self, logits=None) -> np.ndarray:
        """Per-face geometry weights [N,3,3] float64 (rows: w_v0, w_v1 - w_v0, w_v2 - w_v0)."""
        N, F0 = self.num_faces, self.num_roots
        bary = self.barycentrics(logits)
        lo = int(self.level[F0:].min()) if N > F0 else 1
        W = np.empty((N, 3, 3), np.float64)
        W[:F0] = np.array([[1.0, 0.0, 0.0], [-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]])
        for lvl in range(lo, self.max_level + 1):
            ids = np.flatnonzero(self.level[F0:] == lvl) + F0
            p = self.parent[ids]
            W[ids] = child_weights(W[p], bary[p], self.slot[ids])
        return W

    def vertex_weights(self, logits=None) -> np.ndarray:
        """Absolute barycentric weights of each face's three vertices over its root [N,3,3]."""
        W = self.weights(logits)
        return np.stack([W[:, 0], W[:, 0] + W[:, 1], W[:, 0] + W[:, 2]], axis=1)

    # -- persistence ----------------------------------------------------------------------
    def state(self, prefix: str = "forest_") -> dict:
        # version 2 adds the coarse table and root_ref, version 3 root_rank; each file says the
        # lowest version that reads it, so plain forests stay readable by version 1 readers
        interleaved = not np.array_equal(self.root_rank, np.arange(self.num_roots))
        version = (
            5
            if self.backdrop
            else 4
            if self.stand_ins
            else 3
            if interleaved
            else 2
            if self.num_coarse or not np.array_equal(self.root_ref, np.arange(len(self.root_ref)))
            else 1
        )
        out = {
            prefix + "version": np.array(version),
            prefix + "template_faces": self.template_faces,
            prefix + "parent": self.parent,
            prefix + "slot": self.slot,
            prefix + "split_logits": self.split_logits,
            prefix + "coarse_faces": self.coarse_faces,
            prefix + "coarse_counts": np.asarray(self.coarse_counts, np.int64),
            prefix + "root_ref": self.root_ref,
        }
        if interleaved:
            out[prefix + "root_rank"] = self.root_rank
        if self.stand_ins:
            out[prefix + "stand_ins"] = np.array(True)
            if self.retire is not None:
                out[prefix + "retire"] = self.retire
            if self.backdrop:
                out[prefix + "backdrop"] = np.array(True)
        return out

    @classmethod
    def from_verified(
        cls,
        template_faces,
        parent,
        slot,
        split_logits,
        children,
        level,
        root,
        *,
        coarse_faces=None,
        coarse_counts=(),
        root_ref=None,
        root_rank=None,
        stand_ins=False,
        retire=None,
        backdrop=False,
    ) -> "Forest":
        """A Forest from arrays already checked against every rule ``_derive`` enforces (roots
        first, parents precede children in the previous level, slots 0..2 and unique), with
        children/level/root derived by the caller: the stream reader verifies the structure as
        records arrive and must not pay a second full validation pass. Equal to
        ``Forest(template_faces, parent, slot, split_logits, ...)`` (tests/test_stream.py)."""
        if template_faces.min() < 0:
            raise ValueError("Forest: template faces hold negative vertex indices")
        f = cls.__new__(cls)
        f.template_faces = template_faces
        f.coarse_faces = np.zeros((0, 3), np.int32) if coarse_faces is None else coarse_faces
        f.coarse_counts = tuple(int(c) for c in coarse_counts)
        n_roots = int(np.count_nonzero(parent < 0)) if root_ref is None else len(root_ref)
        f.root_ref = np.arange(n_roots, dtype=np.int64) if root_ref is None else root_ref
        f.parent, f.slot, f.split_logits = parent, slot, split_logits
        f.children, f.level, f.root = children, level, root
        f.root_rank = np.arange(n_roots, dtype=np.int64) if root_rank is None else root_rank
        f._set_stand_ins(stand_ins, retire, backdrop)
        return f

    @classmethod
    def from_state(cls, data, prefix: str = "forest_", source: str = "forest") -> "Forest":
        missing = [k for k in ("template_faces", "parent", "slot", "split_logits") if prefix + k not in data]
        if missing:
            raise ValueError(f"{source}: missing forest arrays {missing}")
        version = int(data[prefix + "version"]) if prefix + "version" in data else FORMAT_VERSION
        if version > FORMAT_VERSION:
            raise ValueError(f"{source}: forest format version {version} is newer than this reader ({FORMAT_VERSION})")
        try:
            extra = {}
            if prefix + "root_ref" in data:  # (older files: no coarse levels, roots in template order)
                extra = dict(
                    coarse_faces=data[prefix + "coarse_faces"],
                    coarse_counts=tuple(data[prefix + "coarse_counts"].tolist()),
                    root_ref=data[prefix + "root_ref"],
                )
                if prefix + "root_rank" in data:
                    extra["root_rank"] = data[prefix + "root_rank"]
                if prefix + "stand_ins" in data:
                    extra["stand_ins"] = bool(data[prefix + "stand_ins"])
                    if prefix + "retire" in data:
                        extra["retire"] = data[prefix + "retire"]
                    if prefix + "backdrop" in data:
                        extra["backdrop"] = bool(data[prefix + "backdrop"])
            return cls(
                data[prefix + "template_faces"],
                data[prefix + "parent"],
                data[prefix + "slot"],
                data[prefix + "split_logits"],
                **extra,
            )
        except KeyError as exc:  # root_ref without the coarse arrays that go with it
            raise ValueError(f"{source}: incomplete forest: {exc.args[0] if exc.args else exc}") from None
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
