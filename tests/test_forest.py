import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from progressive_avatars.core.avatar.forest import Forest
from tests.helpers import random_forest, sphere_mesh


def tri_area(v):
    return 0.5 * np.linalg.norm(np.cross(v[..., 1, :] - v[..., 0, :], v[..., 2, :] - v[..., 0, :]), axis=-1)


def face_vertices(forest, verts):
    W = forest.vertex_weights()  # [N,3 face verts,3 root weights]
    rv = verts[forest.root_faces[forest.root]]  # [N,3,3]
    return np.einsum("nij,njk->nik", W, rv)


def test_split_structure_and_queries():
    forest = Forest(np.array([[0, 1, 2], [0, 2, 3]]))
    kids = forest.split([1])
    assert kids.tolist() == [[2, 3, 4]]
    assert forest.parent.tolist() == [-1, -1, 1, 1, 1]
    assert forest.slot.tolist() == [-1, -1, 0, 1, 2]
    assert forest.root.tolist() == [0, 1, 1, 1, 1]
    assert forest.level.tolist() == [0, 0, 1, 1, 1]
    forest.split([3])
    assert forest.depth_per_root().tolist() == [0, 2]
    assert forest.depth_histogram().tolist() == [1, 0, 1]
    assert forest.leaves().tolist() == [0, 2, 4, 5, 6, 7]
    assert forest.cumulative(1).tolist() == [0, 1, 2, 3, 4]
    assert forest.cut(1).tolist() == [0, 2, 3, 4]  # root 0 is a leaf at level 0
    assert forest.cut(2).tolist() == [0, 2, 4, 5, 6, 7]
    with pytest.raises(ValueError, match="only leaf faces"):
        forest.split([1])
    with pytest.raises(IndexError):
        forest.split([99])


def test_children_tile_parent_exactly():
    rng = np.random.default_rng(0)
    verts, faces = sphere_mesh(6, 8)
    forest = random_forest(faces, rng, depth=4, frac=0.6, logit_scale=2.0)
    fv = face_vertices(forest, verts)
    area = tri_area(fv)
    inner = np.flatnonzero(~forest.is_leaf())
    child_sum = area[forest.children[inner]].sum(axis=1)
    np.testing.assert_allclose(child_sum, area[inner], rtol=1e-10, atol=1e-18)
    # Children share the parent's vertices and the split point.
    p = fv[inner]
    c = fv[forest.children[inner]]
    np.testing.assert_allclose(c[:, 0, :2], p[:, [0, 1]], atol=1e-15)
    np.testing.assert_allclose(c[:, 1, :2], p[:, [1, 2]], atol=1e-15)
    np.testing.assert_allclose(c[:, 2, :2], p[:, [2, 0]], atol=1e-15)
    b = forest.barycentrics()[inner]
    np.testing.assert_allclose(c[:, 0, 2], np.einsum("ni,nij->nj", b, p), atol=1e-15)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-60, 60), min_size=3, max_size=3), st.integers(1, 5), st.integers(0, 2**31 - 1))
def test_weights_stay_on_simplex_for_any_logits(logit, depth, seed):
    rng = np.random.default_rng(seed)
    forest = Forest(np.array([[0, 1, 2]]))
    for _ in range(depth):
        leaves = forest.leaves()
        forest.split(leaves[rng.random(len(leaves)) < 0.7] if len(leaves) > 1 else leaves)
    forest.split_logits[:] = np.asarray(logit) + rng.normal(0, 20, forest.split_logits.shape)
    b = forest.barycentrics()
    assert np.all(b >= 0) and np.allclose(b.sum(-1), 1)
    W = forest.weights()
    VW = forest.vertex_weights()
    assert np.all(np.isfinite(W))
    np.testing.assert_allclose(VW.sum(-1), 1, atol=1e-12)
    assert VW.min() >= -1e-12
    np.testing.assert_allclose(W[:, 1:].sum(-1), 0, atol=1e-12)


def test_uniform_subdivision_counts():
    forest = Forest(np.array([[0, 1, 2], [0, 2, 3]])).subdivide_uniform(3)
    assert forest.level_counts().tolist() == [2, 6, 18, 54]
    assert forest.num_faces == 80


def test_reorder_and_prefix_preserve_geometry():
    rng = np.random.default_rng(1)
    verts, faces = sphere_mesh(5, 6)
    forest = random_forest(faces, rng, depth=3)
    # Sort by level then reversed index inside a level: parents still precede children.
    idx = np.arange(forest.num_faces)
    order = np.lexsort((np.where(forest.level == 0, idx, -idx), forest.level))
    re = forest.reorder(order)
    np.testing.assert_allclose(face_vertices(re, verts), face_vertices(forest, verts)[order], atol=1e-15)
    pre = re.prefix(forest.num_roots + 5)
    np.testing.assert_allclose(face_vertices(pre, verts), face_vertices(re, verts)[: pre.num_faces], atol=1e-15)
    with pytest.raises(ValueError, match="permutation"):
        forest.reorder(order[:-1])
    with pytest.raises(ValueError, match="roots must stay first"):
        forest.reorder(order[::-1])
    swapped = order.copy()
    last = np.flatnonzero(forest.level[order] == forest.max_level)[0]
    swapped[[forest.num_roots, last]] = swapped[[last, forest.num_roots]]
    with pytest.raises(ValueError, match="parent that precedes"):
        forest.reorder(swapped)


def test_save_load_roundtrip(tmp_path):
    rng = np.random.default_rng(2)
    _, faces = sphere_mesh(5, 6)
    forest = random_forest(faces, rng, depth=3)
    path = tmp_path / "forest.npz"
    forest.save(path)
    back = Forest.load(path)
    for name in ("template_faces", "parent", "slot", "split_logits", "level", "root", "children"):
        np.testing.assert_array_equal(getattr(back, name), getattr(forest, name))
    np.savez(tmp_path / "bad.npz", forest_parent=forest.parent)
    with pytest.raises(ValueError, match="bad.npz: missing forest arrays"):
        Forest.load(tmp_path / "bad.npz")


def test_invalid_structures_are_refused():
    faces = np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match="precedes"):
        Forest(faces, parent=[-1, 5], slot=[-1, 0])
    with pytest.raises(ValueError, match="same \\(parent, slot\\)"):
        Forest(faces, parent=[-1, 0, 0], slot=[-1, 0, 0])
    with pytest.raises(ValueError, match="\\[F,3\\]"):
        Forest(np.zeros((0, 3)))


def _capped_cylinder(n_around=32, n_up=16, n_cap=6):
    """A closed cylinder (radius 1, height 2) with flat caps: sharp rims, like a neck's cut."""
    radii = np.concatenate([np.linspace(0, 1, n_cap + 1)[1:], np.ones(n_up - 1), np.linspace(1, 0, n_cap + 1)[:-1]])
    heights = np.concatenate([np.zeros(n_cap), np.linspace(0, 2, n_up + 1)[1:-1], np.full(n_cap, 2.0)])
    th = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    ring = np.stack(
        [np.outer(radii, np.cos(th)), np.repeat(heights[:, None], n_around, 1), np.outer(radii, np.sin(th))], -1
    )
    v = np.concatenate([[[0.0, 0.0, 0.0]], ring.reshape(-1, 3), [[0.0, 2.0, 0.0]]])
    R, k = len(radii), np.arange(n_around)
    k1 = (k + 1) % n_around
    a = 1 + np.arange(R - 1)[:, None] * n_around
    side = np.concatenate(
        [np.stack([a + k, a + k1, a + n_around + k1], -1), np.stack([a + k, a + n_around + k1, a + n_around + k], -1)]
    )
    top = len(v) - 1
    last = 1 + (R - 1) * n_around
    faces = np.concatenate(
        [
            np.stack([np.zeros_like(k), 1 + k1, 1 + k], -1),
            side.reshape(-1, 3),
            np.stack([np.full_like(k, top), last + k, last + k1], -1),
        ]
    )
    return v, np.ascontiguousarray(faces[:, ::-1])  # outward winding


def test_coarse_levels_keep_the_surface_they_stand_for():
    """A coarse triangle is a chord of the surface; with each Voronoi cell represented by its
    outermost vertex (not its seed) the chords keep sharp rims, so a coarse level keeps most of
    the template's area (seed corners: 0.81 / 0.86 of it at 1/32 / 1/16 here), and no triangle
    faces against the surface."""
    from progressive_avatars.core.avatar import coarse

    v, f = _capped_cylinder()

    def area(t):
        return 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1).sum()

    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (np.einsum("ij,ij->i", fn, v[f].mean(1) - [0, 1, 0]) > 0).all()  # outward winding
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    for frac in (1 / 32, 1 / 16):
        cf, counts = coarse.build_coarse(v, f, (frac,))
        t = cf.astype(np.int64)
        assert 0.5 * frac * len(f) < counts[0] < 1.5 * frac * len(f)
        assert area(t) > 0.88 * area(f), (frac, area(t) / area(f))
        tn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        assert (np.einsum("ij,ij->i", tn, vn[t].sum(1)) > 0).all()


def test_coarse_roots_bind_like_template_faces_and_survive_reorder_prefix_and_save(tmp_path):
    """Coarse faces (three template vertices each) are roots of the root table: they bind
    exactly like a template face over the same vertices, never split, and the forest keeps
    its geometry through a root permutation, a prefix shorter than the roots and save/load."""
    from progressive_avatars.core.avatar import binding
    from progressive_avatars.core.avatar import coarse

    rng = np.random.default_rng(4)
    verts, faces = sphere_mesh(8, 12)
    cf, counts = coarse.build_coarse(verts, faces, (0.125, 0.5))
    assert len(counts) == 2 and set(np.unique(cf)) <= set(np.unique(faces))
    f = Forest(faces, coarse_faces=cf, coarse_counts=counts)
    C, F0 = len(cf), len(faces)
    assert f.num_roots == C + F0 and f.level_counts().tolist() == [*counts, F0]
    assert f.depth[:C].tolist() == [-2] * counts[0] + [-1] * counts[1]
    with pytest.raises(ValueError, match="coarse"):
        f.split([0])
    f.split(f.splittable()[rng.random(F0) < 0.3])
    f.split_logits[:] = rng.normal(0, 1, f.split_logits.shape)
    v = verts + rng.normal(0, 1e-3, verts.shape)
    g = binding.evaluate(f, v)
    plain = binding.evaluate(Forest(np.concatenate([cf, faces])), v)  # the same triangles as plain roots
    np.testing.assert_allclose(g.t[: C + F0], plain.t, atol=1e-12)
    np.testing.assert_allclose(g.r[: C + F0], plain.r, atol=1e-12)
    # roots permuted inside their levels (a stream's spread-out order), then a prefix
    R = f.num_roots
    perm = np.concatenate(
        [
            rng.permutation(counts[0]),
            counts[0] + rng.permutation(counts[1]),
            C + rng.permutation(F0),
            np.arange(R, f.num_faces),
        ]
    )
    f2 = f.reorder(perm)
    g2 = binding.evaluate(f2, v)
    np.testing.assert_allclose(g2.t, g.t[perm], atol=1e-12)
    for n in (1, counts[0] + 3, C + 10, R + 5):
        p = f2.prefix(n)
        np.testing.assert_allclose(binding.evaluate(p, v).t, g2.t[:n], atol=1e-12)
        d = p.depth_per_root()
        assert len(d) == F0 and np.count_nonzero(d >= 0) == min(max(n - C, 0), F0)
    f2.save(tmp_path / "f.npz")
    f3 = Forest.load(tmp_path / "f.npz")
    for k in ("parent", "slot", "split_logits", "coarse_faces", "root_ref", "level", "root"):
        np.testing.assert_array_equal(getattr(f3, k), getattr(f2, k))
    assert f3.coarse_counts == counts
    np.testing.assert_array_equal(f3.depth_per_root(), f.depth_per_root())
