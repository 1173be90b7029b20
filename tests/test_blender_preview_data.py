"""core/bridge/ (budget, splats, depth, transforms): the numpy side of the Blender preview (no bpy needed)."""

import os

import numpy as np

from progressive_avatars.core.avatar import binding
import pytest

from progressive_avatars.core.bridge.budget import Budget
from progressive_avatars.core.bridge.depth import (
    NOT_ARRIVED,
    NOT_ARRIVED_COLOR,
    depth_colors,
    depth_legend,
    depth_per_face,
    per_corner,
)
from progressive_avatars.core.bridge.splats import preview_order, splat_evaluator
from progressive_avatars.core.bridge.transforms import blender_camera, camera_from_blender, transform_gaussians
from progressive_avatars.core.avatar.avatar import Avatar
from progressive_avatars.core.avatar.binding import quat_to_rotmat
from progressive_avatars.core.geometry.camera import Camera
from tests.helpers import random_forest, sphere_mesh


def _avatar(rng):
    v, f = sphere_mesh(10, 14)
    forest = random_forest(f, rng, depth=3, frac=0.5)
    av = Avatar.initial(forest)
    N = forest.num_faces
    av.d_mu[:] = rng.normal(0, 0.4, (N, 3))
    av.d_log_scale[:] = rng.normal(-1, 0.3, (N, 3))
    av.d_rot[:] = rng.normal(size=(N, 4))
    return av, v


@pytest.mark.parametrize("q", [[1, 0, 0, 0], [0, 1, 0, 0], [0.1, 0.3, 0.9, 0.2], [0.05, -0.7, 0.1, 0.7]])
def test_splat_evaluator_matches_core_compose(q):
    rng = np.random.default_rng(1)
    av, v = _avatar(rng)
    verts = (v @ quat_to_rotmat(np.array(q, float)).T).astype(np.float32)  # large rotations: small-w path
    # Reference: the generic float64 path (evaluate + compose), not the evaluator under test.
    geo = binding.evaluate(av.forest, verts.astype(np.float64), dtype=np.float64)
    m, qq, s = binding.compose(geo.t, geo.r, geo.s, av.d_mu, av.d_log_scale, av.d_rot)
    ref = {"means": m, "scales": s, "quats": qq}
    layouts = (None, preview_order(av))  # stream order; grouped by root (Blender's)
    for count, order in [(c, o) for c in (None, av.num_gaussians // 3) for o in layouts]:
        ev = splat_evaluator(av, count, av.forest.weights(), order)
        means, quats, scales = ev(verts)
        n = ev.n
        assert means.shape == (av.num_gaussians, 3)
        rows = np.arange(n) if order is None else np.argsort(order)[:n]  # the rows of ranks 0..n-1
        np.testing.assert_allclose(means[rows], ref["means"][:n], atol=1e-6)
        np.testing.assert_allclose(scales[rows], ref["scales"][:n], rtol=1e-5, atol=1e-8)
        np.testing.assert_allclose(np.abs(np.sum(quats[rows] * ref["quats"][:n], 1)), 1, atol=2e-6)
        np.testing.assert_allclose(np.linalg.norm(quats[rows], axis=1), 1, atol=1e-6)


def test_budget_fallback_and_levels():
    rng = np.random.default_rng(2)
    av, _ = _avatar(rng)
    b = Budget(av.num_gaussians, av.forest.level.copy(), 1000)
    assert b.count_for_percent(0) == 0 and b.count_for_percent(100) == av.num_gaussians
    assert b.count_for_percent(150) == av.num_gaussians
    n = b.count_for_percent(50)
    assert b.level_reached(n) == av.forest.level[n - 1]
    assert b.bytes_for_count(av.num_gaussians) == 1000


def test_depth_colours_and_legend():
    depth = np.array([0, 1, 2, 2, 3, 0])
    cols = depth_colors(depth, 3)
    assert cols.shape == (6, 4) and cols.dtype == np.float32
    assert np.all((cols >= 0) & (cols <= 1))
    assert not np.allclose(cols[0], cols[4])
    legend = depth_legend(depth)
    assert [(d, n) for d, n, _ in legend] == [(0, 2), (1, 1), (2, 2), (3, 1)]
    corners = per_corner(cols, np.array([3, 3, 4, 3, 3, 3]))
    assert len(corners) == 19 and np.allclose(corners[6:10], cols[2])


def test_blender_camera_round_trip():
    cam = Camera.look_at([0.2, 0.1, 0.7], [0, 0, 0], [0, 1, 0], 600.0, 600.0, 190.0, 130.0, 320, 240)
    s = blender_camera(cam)
    back = camera_from_blender(
        s["matrix_world"], s["lens"], s["sensor_width"], s["shift_x"], s["shift_y"], *s["resolution"]
    )
    pts = np.random.default_rng(0).normal(0, 0.1, (10, 3))
    np.testing.assert_allclose(back.project(pts)[0], cam.project(pts)[0], atol=1e-6)


def test_transform_gaussians_rigid():
    rng = np.random.default_rng(3)
    av, v = _avatar(rng)
    g = av.gaussians(v.astype(np.float32))
    M = np.eye(4)
    M[:3, :3] = quat_to_rotmat(np.array([0.3, 0.1, 0.8, 0.2])) * 2.0
    M[:3, 3] = [1, 2, 3]
    means, quats, scales = transform_gaussians(M, g["means"], g["quats"], g["scales"])
    moved = av.gaussians((v @ M[:3, :3].T + M[:3, 3]).astype(np.float32))
    np.testing.assert_allclose(means, moved["means"], atol=1e-5)
    np.testing.assert_allclose(scales, moved["scales"], rtol=1e-4)
    Rw = quat_to_rotmat(quats)
    np.testing.assert_allclose(Rw, quat_to_rotmat(moved["quats"]), atol=1e-4)


def test_depth_per_face_of_a_prefix_marks_faces_not_arrived():
    """A stream cut inside the template level: faces past the received roots are NOT_ARRIVED,
    with their own colour and legend row; the legend still lists every level."""
    rng = np.random.default_rng(4)
    av, _ = _avatar(rng)
    forest = av.forest
    F0 = forest.num_roots
    full = depth_per_face(forest, F0)
    np.testing.assert_array_equal(full, forest.depth_per_root())
    cut = depth_per_face(forest, F0, F0 // 3)
    assert (cut[: F0 // 3] == 0).all() and (cut[F0 // 3 :] == NOT_ARRIVED).all()
    cols = depth_colors(cut, forest.max_level)
    np.testing.assert_array_equal(cols[F0 // 3 :], np.broadcast_to(NOT_ARRIVED_COLOR, (F0 - F0 // 3, 4)))
    assert not np.allclose(cols[0], NOT_ARRIVED_COLOR)
    legend = depth_legend(cut, forest.max_level)
    assert [(d, n) for d, n, _ in legend] == [(-1, F0 - F0 // 3), (0, F0 // 3)] + [
        (d, 0) for d in range(1, forest.max_level + 1)
    ]
    with pytest.raises(ValueError, match="template faces"):
        depth_per_face(forest, F0 - 1)


def test_preview_of_an_interleaved_stream_selects_by_stream_rank():
    """A version 5 stream sends template faces after deeper ones: the preview's budget (points'
    rank, the evaluator's rows, level reached, depth colours) follows the stream positions,
    and agrees with the avatar a reader decodes from the same prefix."""
    from progressive_avatars.core.bridge.splats import static_attributes
    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.stream.writer import encode_stream

    rng = np.random.default_rng(5)
    v, f = sphere_mesh(10, 14)
    forest = random_forest(f, rng, depth=3, frac=0.5, coarse_from=v)
    av = Avatar.initial(forest)
    av.d_mu[:] = rng.normal(0, 0.3, (forest.num_faces, 3))
    data = encode_stream(av, rng.random(forest.num_faces), quantize=False)
    full = read_stream(data)
    fo = full.forest
    assert fo.root_rank[-1] > fo.num_roots  # interleaved: some deeper face precedes a template face
    order = preview_order(full)
    static = static_attributes(full, order)
    np.testing.assert_array_equal(static["rank"], fo.stream_rank()[order])
    budget = Budget.for_avatar(full, len(data))
    F0 = len(fo.template_faces)
    verts = v.astype(np.float32)
    for n in (3, fo.roots_in_prefix(fo.num_roots) // 2, int(fo.root_rank[-1]), int(fo.root_rank[-1]) + 1, fo.num_faces):
        part = read_stream(data, max_gaussians=n)
        ids = fo.stream_ids(n)
        ev = splat_evaluator(full, n, fo.weights(), order)
        means = ev(verts)[0]
        rows = np.flatnonzero(static["rank"] < n)
        assert len(rows) == n
        np.testing.assert_allclose(means[rows], full.gaussians(verts, ids=order[rows])["means"], atol=1e-6)
        np.testing.assert_allclose(np.sort(means[rows], 0), np.sort(part.gaussians(verts)["means"], 0), atol=1e-6)
        assert budget.level_reached(n) == part.forest.max_level == fo.level[ids].max()
        np.testing.assert_array_equal(depth_per_face(fo, F0, n), part.forest.depth_per_root())


def test_budget_rounding_level_reached_and_depth_scale():
    """What the slider shows beside the preview, by hand: percent of a count rounds (it
    floored), bytes round, "level reached" is the level of the last record shown (it read
    the next record's), and a .npz avatar's depth scale counts from the template, not from
    its coarse levels."""
    from progressive_avatars.core.bridge.budget import fraction_count
    from tests.test_stream import make_avatar

    assert fraction_count(3, 50.0) == 2 and fraction_count(1000, 33.35) == 334
    b = Budget(4, np.array([0, 0, 1, 2], np.int8), 100)
    assert [b.level_reached(n) for n in range(5)] == [-1, 0, 0, 1, 2]
    assert Budget(3, np.zeros(3, np.int8), 1000).bytes_for_count(2) == 667
    _, av, _ = make_avatar(3, coarse=True)
    assert av.forest.num_coarse_levels > 0
    f = av.forest
    assert Budget.for_avatar(av, 1000).max_depth(f) == int(f.level.max()) - f.num_coarse_levels


RAMP = np.array(
    [[0.050, 0.030, 0.280], [0.150, 0.300, 0.620], [0.100, 0.600, 0.600], [0.450, 0.800, 0.300], [0.990, 0.900, 0.150]]
)


def test_depth_colours_hit_the_ramp_stops_and_clamp_beyond_the_top():
    cols = depth_colors(np.array([0, 2, 4, 1, 9]), 4)
    np.testing.assert_allclose(cols[:, :3], [RAMP[0], RAMP[2], RAMP[4], RAMP[1], RAMP[4]], atol=1e-6)
    np.testing.assert_array_equal(cols[:, 3], 1.0)
    # halfway between stops 1 and 2 (depth 3 of top 8: x = 1.5)
    np.testing.assert_allclose(depth_colors(np.array([3]), 8)[0, :3], (RAMP[1] + RAMP[2]) / 2, atol=1e-6)


def test_depth_colours_with_max_depth_zero_are_the_first_stop():
    cols = depth_colors(np.array([0, 0]), 0)
    np.testing.assert_allclose(cols[:, :3], [RAMP[0], RAMP[0]], atol=1e-6)


def test_legend_of_nothing_arrived_still_lists_depth_zero():
    legend = depth_legend(np.array([NOT_ARRIVED, NOT_ARRIVED, NOT_ARRIVED]))
    assert [(d, n) for d, n, _ in legend] == [(NOT_ARRIVED, 3), (0, 0)]
    np.testing.assert_allclose(legend[0][2], NOT_ARRIVED_COLOR[:3])
    np.testing.assert_allclose(legend[1][2], RAMP[0], atol=1e-6)


def _stream_file(tmp_path):
    """A version 5 stream with coarse levels, in blocks of 8 records, written to a file; its
    header's sizes (FORMAT.md 6)."""
    from progressive_avatars.core.stream.format import read_header
    from progressive_avatars.core.stream.writer import write_stream
    from tests.test_stream import make_avatar

    verts, av, imp = make_avatar(3, coarse=True)
    path = tmp_path / "a.pavs"
    write_stream(str(path), av, imp, records_per_block=8, vertices=verts)
    h = read_header(str(path))
    return av, path, h


def test_budget_of_a_stream_follows_its_bytes_and_header(tmp_path):
    """Budget.for_avatar from a stream file (load_avatar): a percent is the records wholly in
    floor(p/100 x total) bytes, n records take H + n R + 4 floor((n-1)/B) bytes (FORMAT.md 6,
    by hand), the level reached after n records is the deepest among them in stream order (a
    version 5 stream sends deeper faces before the last template faces), and a cut file keeps
    the header's depth scale and never counts records it does not hold."""
    from fractions import Fraction

    from progressive_avatars.core.bridge.budget import load_avatar
    from progressive_avatars.core.stream.reader import read_stream

    av, path, h = _stream_file(tmp_path)
    H, R, B, N, K = h.header_size, h.record_size, h.records_per_block, h.num_records, h.num_coarse_levels
    S = B * R + 4
    total = H + N * R + 4 * -(-N // B)
    assert os.path.getsize(path) == total and N == av.num_gaussians and K > 0
    full, budget = load_avatar(str(path))

    def by_hand(p):
        k = int(Fraction(p) * total // 100)
        return 0 if k < H else min(N, (k - H) // S * B + min((k - H) % S // R, B))

    for p in (0.5, 1.0, 10.0, 25.0, 50.0, 99.0, 100.0):
        assert budget.count_for_percent(p) == by_hand(p), p
    assert budget.count_for_percent(10.0) != round(N * 0.1)  # not the fraction of Gaussians
    assert budget.count_for_percent(150.0) == N and budget.count_for_percent(-5.0) == 0
    for n in (1, B, B + 1, N):
        assert budget.bytes_for_count(n) == H + n * R + 4 * ((n - 1) // B), n
    lead = int(np.sum(av.forest.level < K))
    data = path.read_bytes()
    for n in range(lead - 1, lead + 12):  # past the lead: template faces and their children mix
        assert budget.level_reached(n) == read_stream(data, max_gaussians=n).forest.max_level, n
    assert budget.level_reached(lead + 11) > K  # some deeper face arrived before the template level was whole
    assert budget.max_level() == av.forest.max_level and budget.max_depth() == av.forest.max_level - K

    # The coarse levels only: the avatar holds levels 0..K-1, the header knows the whole depth.
    cut = tmp_path / "cut.pavs"
    cut.write_bytes(data[: H + lead * R + 4 * ((lead - 1) // B)])
    part, b = load_avatar(str(cut))
    assert part.num_gaussians == b.total == lead and part.forest.max_level == K - 1
    assert b.count_for_percent(100.0) == b.count_for_percent(150.0) == lead  # not the header's N
    assert b.count_for_percent(0.0) == b.count_for_percent(-5.0) == 0
    assert b.max_level() == av.forest.max_level and b.max_depth() == av.forest.max_level - K


def test_budget_slider_reads_the_typed_percent():
    """A FloatProperty keeps 0.35 as 0.3499999940...: 0.35 % of 1000 Gaussians is 3.5, which
    rounds to 4, as a viewer given "0.35" shows; the 32-bit value would show 3. Percents
    outside [0, 100] are clamped."""
    from progressive_avatars.core.bridge.budget import fraction_count, typed_percent

    assert typed_percent(np.float32(16.1)) == 16.1 and typed_percent(np.float32(0.35)) == 0.35
    b = Budget(1000, np.zeros(1000, np.int8), 5000)
    assert b.count_for_slider(np.float32(0.35)) == 4 and b.count_for_percent(float(np.float32(0.35))) == 3
    assert fraction_count(10, -50.0) == 0 and fraction_count(10, 250.0) == 10


def test_load_avatar_and_check_mesh_refuse_what_does_not_fit(tmp_path):
    """load_avatar's refusals name the file and say what is wrong (a missing or empty file, a
    foreign file, a stream cut inside its header or before its first record); check_mesh takes
    the avatar's own template (its largest index + 1 vertices exactly) and refuses a mesh with
    fewer vertices, other faces (.npz), or another template (a stream's hash)."""
    from progressive_avatars.core.bridge.budget import check_mesh, load_avatar
    from progressive_avatars.core.stream.format import TemplateMismatch

    av, path, h = _stream_file(tmp_path)
    data = path.read_bytes()
    with pytest.raises(FileNotFoundError, match="nope.pavs: file not found"):
        load_avatar(str(tmp_path / "nope.pavs"))
    (tmp_path / "empty.pavs").write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty.pavs: the file is empty \(0 bytes\)"):
        load_avatar(str(tmp_path / "empty.pavs"))
    (tmp_path / "foreign.pavs").write_bytes(b"GIF89a" + bytes(100))
    with pytest.raises(ValueError, match="foreign.pavs: not a ProgressiveAvatars stream or avatar .npz"):
        load_avatar(str(tmp_path / "foreign.pavs"))
    (tmp_path / "head.pavs").write_bytes(data[: h.header_size // 2])
    with pytest.raises(ValueError, match="no Gaussian arrived"):
        load_avatar(str(tmp_path / "head.pavs"))
    (tmp_path / "first.pavs").write_bytes(data[: h.header_size + h.record_size - 1])
    with pytest.raises(
        ValueError,
        match=f"first.pavs: the stream holds no complete Gaussian record.*byte {h.header_size + h.record_size}",
    ):
        load_avatar(str(tmp_path / "first.pavs"))

    faces = av.forest.template_faces
    full, budget = load_avatar(str(path))
    check_mesh(full, budget, faces)  # its own template: largest index + 1 vertices
    fewer = faces.copy()
    fewer[fewer == faces.max()] = 0
    with pytest.raises(ValueError, match="vertices in use; the avatar's template needs"):
        check_mesh(full, budget, fewer)
    with pytest.raises(TemplateMismatch):
        check_mesh(full, budget, faces[::-1].copy())
    npz = tmp_path / "a.npz"
    av.save(str(npz))
    plain, pb = load_avatar(str(npz))
    assert pb.info is None and pb.total == av.num_gaussians
    check_mesh(plain, pb, faces)
    with pytest.raises(ValueError, match="are not the avatar's template"):
        check_mesh(plain, pb, faces[::-1].copy())


def test_srgb_to_linear_by_hand():
    """The sRGB decoding curve (IEC 61966-2-1): linear c / 12.92 up to 0.04045, then
    ((c + 0.055) / 1.055) ** 2.4, out-of-range values clamped to [0, 1] first."""
    from progressive_avatars.core.bridge.splats import srgb_to_linear

    c = np.array([-0.3, 0.0, 0.02, 0.04045, 0.5, 1.0, 1.5])
    want = [0.0, 0.0, 0.02 / 12.92, 0.04045 / 12.92, 0.21404114, 1.0, 1.0]  # (0.555 / 1.055) ** 2.4
    np.testing.assert_allclose(srgb_to_linear(c), want, rtol=1e-6, atol=1e-9)


def _stand_in_avatar(seed=6):
    """A trained-like avatar whose coarse faces are stand-ins (retire positions from a stream),
    with activations and colours spread as training leaves them."""
    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.stream.writer import encode_stream

    rng = np.random.default_rng(seed)
    v, f = sphere_mesh(10, 14, radius=0.1)
    forest = random_forest(f, rng, depth=3, frac=0.4, coarse_from=v, stand_ins=True)
    av = Avatar.initial(forest)
    N = forest.num_faces
    av.opacity_logit[:] = rng.normal(1.5, 1.5, N)
    av.f_dc[:] = rng.normal(0, 1.2, (N, 3))  # some channels below 0 after the DC term: clamped
    av.d_mu[:] = rng.normal(0, 0.2, (N, 3))
    full = read_stream(encode_stream(av, rng.random(N), quantize=False, vertices=v))
    assert full.forest.stand_ins and full.forest.retire is not None
    return full, v


def test_static_attributes_by_hand_and_retire_as_the_modifier_reads_it():
    """static_attributes at the preview's root-grouped points: opacity = sigmoid(logit),
    colour = sRGB-decoded 0.5 + C0 * DC (clamped at 0), alpha 1, the level and stream rank of
    each point's face, and retire = shown_until + 1 for stand-ins, 0 (never) for every other
    point. The modifier shows a point while rank < Count and not (retire > 0 and Count >=
    retire): at every count that is the forest's drawn set of that stream prefix."""
    from progressive_avatars.core.bridge.splats import static_attributes

    full, _ = _stand_in_avatar()
    fo = full.forest
    order = preview_order(full)
    st = static_attributes(full, order)
    np.testing.assert_allclose(st["opacity"], 1 / (1 + np.exp(-full.opacity_logit[order])), rtol=1e-6)
    dc = np.clip(0.5 + 0.28209479177387814 * full.f_dc[order], 0, 1)
    lin = np.where(dc <= 0.04045, dc / 12.92, ((dc + 0.055) / 1.055) ** 2.4)
    rgba = st["color"].reshape(-1, 4)
    assert len(rgba) == full.num_gaussians and (dc == 0).any() and (dc > 0.5).any()
    np.testing.assert_allclose(rgba[:, :3], lin, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(rgba[:, 3], 1.0)
    np.testing.assert_array_equal(st["level"], fo.level[order])
    np.testing.assert_array_equal(st["rank"], fo.stream_rank()[order])
    K = fo.num_coarse_levels
    coarse = fo.level[order] < K
    assert coarse.any() and (st["retire"][coarse] > 0).all() and (st["retire"][~coarse] == 0).all()
    for n in sorted(
        {
            1,
            int(st["retire"][coarse].min()) - 1,
            int(st["retire"][coarse].min()),
            int(np.median(st["retire"][coarse])),
            int(st["retire"].max()),
            full.num_gaussians,
        }
    ):
        shown = (st["rank"] < n) & ~((st["retire"] > 0) & (n >= st["retire"]))
        np.testing.assert_array_equal(
            np.sort(order[shown]), np.sort(fo.drawn(fo.stream_ids(n), records=n)), err_msg=str(n)
        )


def test_preview_order_groups_points_by_root_and_the_evaluator_cuts_exactly_count():
    """preview_order lays the points out by root face (stable: face order within a root), so
    at full budget the evaluator writes them without a scatter; a budget of n evaluates exactly
    the faces of the first n stream records, and every other point keeps what its row held."""
    full, v = _stand_in_avatar(7)
    fo = full.forest
    order = preview_order(full)
    assert np.array_equal(np.sort(order), np.arange(full.num_gaussians))
    assert (np.diff(fo.root[order]) >= 0).all()
    same_root = np.diff(fo.root[order]) == 0
    assert (np.diff(order)[same_root] > 0).all()
    assert splat_evaluator(full, None, fo.weights(), order)._reorder is None  # the point order: no scatter
    rank = fo.stream_rank()[order]
    for n in (1, fo.num_roots // 2, full.num_gaussians - 1):
        ev = splat_evaluator(full, n, fo.weights(), order)
        assert ev.n == n
        means, quats, scales = ev(v.astype(np.float32))
        np.testing.assert_allclose(
            means[rank < n], full.gaussians(v.astype(np.float32), ids=order[rank < n])["means"], atol=1e-6
        )
        np.testing.assert_array_equal(means[rank >= n], 0.0)  # not evaluated: as made
        np.testing.assert_array_equal(quats[rank >= n], np.tile([1.0, 0, 0, 0], ((rank >= n).sum(), 1)))


def test_depth_scale_legend_and_corners_at_their_edges():
    """Without max_depth the ramp spans the deepest depth given (one level: its two ends);
    per_corner repeats each face's own row; a legend's scale below 0 still lists depth 0; a
    negative record count shows nothing arrived."""
    np.testing.assert_allclose(depth_colors(np.array([0, 1]))[:, :3], [RAMP[0], RAMP[4]], atol=1e-6)
    np.testing.assert_allclose(depth_colors(np.array([2, 0, 1]))[:, :3], [RAMP[4], RAMP[0], RAMP[2]], atol=1e-6)
    rows = np.arange(4)[:, None] * np.ones((1, 4))
    np.testing.assert_array_equal(per_corner(rows, [3, 4, 3, 5])[:, 0], [0] * 3 + [1] * 4 + [2] * 3 + [3] * 5)
    legend = depth_legend(np.full(3, NOT_ARRIVED), -1)
    assert [(d, n) for d, n, _ in legend] == [(NOT_ARRIVED, 3), (0, 0)]
    np.testing.assert_allclose(legend[1][2], RAMP[0], atol=1e-6)
    rng = np.random.default_rng(8)
    av, _ = _avatar(rng)
    F0 = av.forest.num_roots
    np.testing.assert_array_equal(depth_per_face(av.forest, F0, -1), np.full(F0, NOT_ARRIVED))


def test_preview_threads_at_full_scale_give_the_bits_of_one_thread():
    """The preview's default evaluator (PREVIEW_THREADS) on at least THREADED_MIN faces: the
    calling thread and a pool thread take two chunks of ~n/4 faces each, every thread with its
    own scratch rows, and the outputs are bit for bit one thread's, frame after frame; one face
    fewer stays on the calling thread. Chunks this long are where threads sharing scratch rows
    would overwrite each other's passes (the threaded test with 40-face chunks cannot show it)."""
    from progressive_avatars.core.avatar.binding import GaussianEvaluator

    rng = np.random.default_rng(9)
    v, f = sphere_mesh(24, 40, radius=0.1)
    forest = random_forest(f, rng, depth=3, frac=1.0)
    N = forest.num_faces
    assert N > GaussianEvaluator.THREADED_MIN
    av = Avatar.initial(forest)
    av.d_mu[:] = rng.normal(0, 0.3, (N, 3))
    av.d_log_scale[:] = rng.normal(-4, 0.3, (N, 3))
    av.d_rot[:] = rng.normal(size=(N, 4))
    w, order = forest.weights(), preview_order(av)
    frames = [(v * s).astype(np.float32) for s in (1.0, 1.1)]
    ref = av.gaussians(frames[1], ids=order)["means"]
    for count, threads, chunks in (
        (GaussianEvaluator.THREADED_MIN - 1, 1, 2),
        (GaussianEvaluator.THREADED_MIN, 2, 4),
        (None, 2, 4),
    ):
        one = splat_evaluator(av, count, w, order, threads=1)
        two = splat_evaluator(av, count, w, order, threads=2)
        assert (two.threads, len(two._chunks)) == (threads, chunks), count
        for verts in frames * 3:  # a race need not show on every frame
            want = [x.copy() for x in one(verts)]
            for got, x in zip(two(verts), want):
                np.testing.assert_array_equal(got, x)
    np.testing.assert_allclose(two(frames[1]).means, ref, atol=1e-6)
