import signal
import warnings

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


def test_coarse_levels_of_tiny_templates_do_not_repeat():
    """On a template too small for two distinct coarse levels both fractions round to the
    same triangles (80 faces: 4 and 4) and a one-face template's only coarse level is itself:
    such levels are left out, so no Gaussian is a copy of another."""
    from progressive_avatars.core.avatar import coarse

    verts, faces = sphere_mesh(4, 6)
    cf, counts = coarse.build_coarse(verts, faces)
    assert 1 <= len(counts) < 2 and len(cf) < len(faces)
    assert len(np.unique(np.sort(cf, axis=1), axis=0)) == len(cf)
    cf, counts = coarse.build_coarse(verts[:3], np.array([[0, 1, 2]]))
    assert counts == () and len(cf) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a mesh collapsed to one point: no NaN on the way
        cf, counts = coarse.build_coarse(np.zeros_like(verts), faces)
    assert counts == () and len(cf) == 0
    big_v, big_f = sphere_mesh(20, 32)
    assert len(coarse.build_coarse(big_v, big_f)[1]) == 2  # a head-sized template keeps both


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


def test_root_rank_interleaved_stream_positions(tmp_path):
    """A forest read from a stream that sends template roots after deeper faces keeps every
    root first and records where each root arrived: stream_rank/stream_order/stream_ids/prefix
    follow it, an avatar file keeps it, and a root placed after its own child is refused."""
    f = Forest(np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]]))
    f.split([0])  # faces 3, 4, 5 under root 0
    f.split([4])  # faces 6, 7, 8 under face 4
    # stream: root 0, face 3, face 4, root 1, face 5, root 2, faces 6, 7, 8
    g = Forest(f.template_faces, f.parent, f.slot, f.split_logits, root_rank=[0, 3, 5])
    np.testing.assert_array_equal(g.stream_rank(), [0, 3, 5, 1, 2, 4, 6, 7, 8])
    np.testing.assert_array_equal(g.stream_order(), [0, 3, 4, 1, 5, 2, 6, 7, 8])
    assert [g.roots_in_prefix(n) for n in range(10)] == [0, 1, 1, 1, 2, 2, 3, 3, 3, 3]
    np.testing.assert_array_equal(g.stream_ids(4), [0, 1, 3, 4])
    p = g.prefix(4)  # roots 0, 1 and faces 3, 4 (root 0's children)
    np.testing.assert_array_equal(p.parent, [-1, -1, 0, 0])
    np.testing.assert_array_equal(p.root_rank, [0, 3])
    np.testing.assert_array_equal(p.stream_rank(), [0, 3, 1, 2])
    np.testing.assert_array_equal(g.prefix(9).parent, g.parent)
    path = tmp_path / "f.npz"
    g.save(path)
    back = Forest.load(path)
    np.testing.assert_array_equal(back.root_rank, [0, 3, 5])
    assert int(np.load(path)["forest_version"]) == 3
    f.save(tmp_path / "plain.npz")  # roots first: the file stays readable by older readers
    assert int(np.load(tmp_path / "plain.npz")["forest_version"]) == 1
    with pytest.raises(ValueError, match="root after one of its children"):
        Forest(f.template_faces, f.parent, f.slot, f.split_logits, root_rank=[2, 3, 5])  # faces 3, 4 before root 0
    with pytest.raises(ValueError, match="increasing"):
        Forest(f.template_faces, f.parent, f.slot, f.split_logits, root_rank=[0, 5, 3])


def test_stand_ins_make_way_for_the_template_and_persist(tmp_path):
    """Coarse stand-ins (Forest.drawn): in every set without the whole template level, gone
    from the finished avatar and from any set holding every template face; with retire
    positions, a stream prefix of n records keeps a stand-in exactly while n <= its retire
    position; prefix() and save/load keep the rule, reorder() and split() drop the positions
    (they no longer name this forest's stream), and a forest without stand-ins is unchanged."""
    rng = np.random.default_rng(3)
    v, f = sphere_mesh(8, 10)
    fo = random_forest(f, rng, depth=2, frac=0.5, coarse_from=v, stand_ins=True)
    cum = random_forest(f, np.random.default_rng(3), depth=2, frac=0.5, coarse_from=v)
    K, C, N = fo.num_coarse_levels, fo.num_coarse, fo.num_faces
    assert fo.stand_ins and not cum.stand_ins and C > 0
    coarse = np.flatnonzero(fo.level < K)
    np.testing.assert_array_equal(cum.drawn(), np.arange(N))
    np.testing.assert_array_equal(fo.drawn(), np.flatnonzero(fo.level >= K))  # the finished avatar
    np.testing.assert_array_equal(fo.drawn(fo.cumulative(K - 1)), fo.cumulative(K - 1))  # coarse levels only
    np.testing.assert_array_equal(fo.drawn(fo.cumulative(K)), np.flatnonzero(fo.level == K))
    some = np.concatenate([coarse, np.flatnonzero(fo.level == K)[:-1]])  # one template face short
    np.testing.assert_array_equal(fo.drawn(some), some)
    # Without retire positions a prefix keeps its stand-ins until the last template face.
    last_t = int(fo.stream_rank()[fo.level == K].max())
    assert len(fo.drawn(fo.stream_ids(last_t), records=last_t)) == last_t
    assert not np.any(fo.level[fo.drawn(fo.stream_ids(last_t + 1), records=last_t + 1)] < K)
    # With them: exactly while records <= retire.
    retire = rng.integers(C, N, C)
    fr = fo._like(fo.parent, fo.slot, fo.split_logits, fo.root_ref, retire=retire)  # the same, with them
    for n in (1, C, C + 1, int(np.median(retire)), N - 1, N):
        ids = fr.stream_ids(n)
        assert np.array_equal(ids, np.arange(n))  # roots first: prefix faces keep their numbers
        got = fr.drawn(ids, records=n)
        shown = [i for i in ids if fr.level[i] >= K or retire[fr.root_ref[i]] >= n]
        np.testing.assert_array_equal(got, shown)
        kept = fr.prefix(n)
        assert kept.stand_ins and np.array_equal(kept.retire, retire)
        np.testing.assert_array_equal(kept.drawn(), got)
    assert not np.any(fr.level[fr.drawn()] < K)  # every retire position < N
    p = str(tmp_path / "f.npz")
    fr.save(p)
    back = Forest.load(p)
    assert back.stand_ins and np.array_equal(back.retire, retire)
    np.testing.assert_array_equal(back.drawn(), fr.drawn())
    cum.save(p)
    assert not Forest.load(p).stand_ins  # a cumulative forest stays one (older files carry no key)
    assert fr.reorder(np.arange(N)).retire is None and fr.reorder(np.arange(N)).stand_ins
    with pytest.raises(ValueError, match="retire"):
        Forest(f, coarse_faces=fo.coarse_faces, coarse_counts=fo.coarse_counts, stand_ins=True, retire=retire[:-1])
    leaf = fr.splittable()[:1]
    fr.split(leaf)
    assert fr.retire is None and fr.stand_ins


def test_backdrop_stand_ins_stay_behind_and_persist(tmp_path):
    """Backdrop stand-ins (Forest.render_set): every face of a set renders, and exactly the
    stand-ins drawn() would drop composite behind the rest: in a stream prefix of n records
    those whose region is complete, in the finished avatar all of them; the flag needs
    stand-ins, survives prefix() and save/load (forest version 5), and a forest without it
    renders drawn() with nothing behind."""
    rng = np.random.default_rng(3)
    v, f = sphere_mesh(8, 10)
    si = random_forest(f, rng, depth=2, frac=0.5, coarse_from=v, stand_ins=True)
    bd = si._like(si.parent, si.slot, si.split_logits, si.root_ref)
    bd._set_stand_ins(True, None, backdrop=True)
    K, N = bd.num_coarse_levels, bd.num_faces
    assert bd.backdrop and not si.backdrop
    ids, behind = bd.render_set()
    np.testing.assert_array_equal(ids, np.arange(N))
    np.testing.assert_array_equal(behind, bd.level < K)  # the finished avatar: every stand-in behind
    seen_some = False
    for n in range(1, N + 1):
        pre = bd.stream_ids(n)
        got, beh = bd.render_set(pre)
        np.testing.assert_array_equal(got, pre)
        gone = ~np.isin(pre, si.drawn(pre, records=n))
        np.testing.assert_array_equal(np.zeros(n, bool) if beh is None else beh, gone)
        seen_some |= beh is None and np.any(bd.level[pre] < K)
        d, none = si.render_set(pre)
        assert none is None and np.array_equal(d, si.drawn(pre, records=n))
    assert seen_some  # short prefixes keep their stand-ins in front
    bd.save(tmp_path / "bd.npz")
    back = Forest.load(tmp_path / "bd.npz")
    assert back.backdrop and back.stand_ins and int(np.load(tmp_path / "bd.npz")["forest_version"]) == 5
    assert bd.prefix(N // 2).backdrop
    assert not Forest(f, backdrop=True).backdrop  # no stand-ins, no backdrop


def test_coarse_levels_spread_sort_and_refuse_whole_fractions():
    """The coarse levels' promises by hand: the spread order puts its first points in every
    octant (plain Morton order fills one patch first), each level's rows come in that order,
    the fractions may be given in any order (coarsest first either way), and a fraction of 1
    is an error (it was skipped silently)."""
    from progressive_avatars.core.avatar import coarse

    g = np.stack(np.meshgrid(*[np.arange(8.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    first = g[coarse.spread_order(g)[:8]]
    assert len({tuple(p) for p in (first >= 4).astype(int)}) == 8
    v, f = sphere_mesh(12, 16)
    cf, counts = coarse.build_coarse(v, f, (1 / 16, 1 / 32))
    assert counts == coarse.build_coarse(v, f, (1 / 32, 1 / 16))[1] and counts[0] < counts[1]
    starts = np.r_[0, np.cumsum(counts)]
    for a, b in zip(starts[:-1], starts[1:]):
        np.testing.assert_array_equal(coarse.spread_order(coarse.centroids(v, cf[a:b])), np.arange(b - a))
    with pytest.raises(ValueError, match="fractions"):
        coarse.build_coarse(v, f, (1.0,))


def test_coarse_triangles_of_a_double_sided_surface_appear_once():
    """A surface whose faces come twice (a folded or double-sided sheet: the same vertices,
    opposite winding) gives each coarse triangle once, not a front and a back copy."""
    from progressive_avatars.core.avatar import coarse

    v, f = sphere_mesh(12, 16)
    one = coarse.decimate(v, f, 40)
    both = coarse.decimate(v, np.vstack([f, f[:, ::-1]]), 40)
    keys = np.sort(both, axis=1)
    assert len(np.unique(keys, axis=0)) == len(both) and len(both) == len(one)


def _three_roots():
    return np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]])


def test_a_face_that_is_its_own_parent_is_refused():
    """parent[i] == i is not 'a parent that precedes it': refused at once (it must not reach
    the level loop, where level[i] = level[i] + 1 never settles)."""

    def _hang(*_):
        raise TimeoutError("Forest() did not return: a self-parent reached the level loop")

    old = signal.signal(signal.SIGALRM, _hang)
    signal.alarm(5)
    try:
        with pytest.raises(ValueError, match="parent that precedes it"):
            Forest(_three_roots(), parent=[-1, -1, -1, 3], slot=[-1, -1, -1, 0])
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_prefix_renumbers_a_parent_that_is_the_first_non_root_face():
    """Roots 1 and 2 arrive last; the prefix without them holds root 0, its children 3, 4, 5
    and face 3's children 6, 7, 8. Renumbered roots-first, face 3 becomes face 1, so 6, 7, 8
    (new 4, 5, 6) must name parent 1 (by hand: old parent 3 - (R - r) = 3 - 2)."""
    f = Forest(_three_roots())
    f.split([0])  # 3, 4, 5
    f.split([3])  # 6, 7, 8 (children of the first non-root face, index R)
    f.split_logits[:] = np.random.default_rng(1).normal(size=f.split_logits.shape)
    g = Forest(f.template_faces, f.parent, f.slot, f.split_logits, root_rank=[0, 7, 8])
    p = g.prefix(7)
    np.testing.assert_array_equal(p.parent, [-1, 0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(p.slot, [-1, 0, 1, 2, 0, 1, 2])
    np.testing.assert_array_equal(p.level, [0, 1, 1, 1, 2, 2, 2])
    # Geometry: face 6 (slot 0 of face 3 = slot 0 of root 0) has vertices v0, v1 of face 3:
    # root v0, root v1, and the split point's absolute weights softmax(logits[0]).
    b0 = np.exp(f.split_logits[0].astype(np.float64))
    b0 /= b0.sum()
    W = p.vertex_weights()
    np.testing.assert_allclose(W[4, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(W[4, 1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(W[1, 2], b0, atol=1e-12)


def test_root_rank_with_a_repeated_position_is_refused():
    """Two roots at one stream position: not 'increasing' (a repeated rank once slipped into
    the stream-order bookkeeping and failed later with a numpy broadcast error)."""
    f = Forest(_three_roots())
    f.split([0])
    with pytest.raises(ValueError, match="increasing"):
        Forest(f.template_faces, f.parent, f.slot, f.split_logits, root_rank=[0, 3, 3])
    with pytest.raises(ValueError, match="increasing"):
        Forest(_three_roots(), root_rank=[0, 1, 1])
