"""The Blender extension as artists use it: cut streams, topology guard, depth colours,
messages, imports without anything but Blender.

Each scenario runs the installed extension zip in a clean bpy subprocess (like
tests/test_blender_extension.py) with torch, numba, trimesh, PIL, scipy and plyfile blocked
from import in that process, so a stray import fails here. The avatar is a *trained* one (the
tiny preset, conftest's tiny_run): its level sizes, its template, its header share.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.test_blender_extension import ROOT, _blender_ext, _clean_env

pytestmark = pytest.mark.blender

BLOCKED = ("torch", "numba", "trimesh", "PIL", "scipy", "plyfile")


def _scenario(name):
    with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "blender_scenarios", name)) as fh:
        return fh.read()


PRELUDE = _scenario("guard_prelude.py")

CUT_SCENARIO = _scenario("guard_cut_streams.py")


def build_zip(tmp):
    ext = _blender_ext()
    dist = os.path.join(tmp, "dist")
    os.makedirs(dist, exist_ok=True)
    from progressive_avatars.core.bridge.payload import build_extension

    return build_extension(ROOT, dist, ext)  # the training tier as the zip's inner archive


def run_scenario(tmp, body, args, timeout=600):
    script = os.path.join(tmp, "scenario.py")
    with open(script, "w") as fh:
        fh.write(PRELUDE.replace("__BLOCKED__", repr(BLOCKED)) + body)
    proc = subprocess.run(
        [sys.executable, script, json.dumps(args)], capture_output=True, text=True, env=_clean_env(tmp), timeout=timeout
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PA_REPORT ")]
    if not lines:
        pytest.fail("Blender session produced no report:\n" + proc.stdout[-3000:] + proc.stderr[-3000:])
    rep = json.loads(lines[-1][len("PA_REPORT ") :])
    rep["stdout"] = proc.stdout
    arrays = dict(np.load(os.path.join(args["out"], "arrays.npz")))
    return rep, arrays


def _no_error(rep, name):
    errs = [e for e in rep["errors"] if e.startswith(name + ":")]
    assert not errs, errs[0]


@pytest.fixture(scope="module")
def cut_session(tiny_run, tiny_dataset, tmp_path_factory):
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.stream.format import read_header
    from progressive_avatars.core.stream.writer import write_stream

    tmp = str(tmp_path_factory.mktemp("guard"))
    out = os.path.join(tmp, "out")
    os.makedirs(out)
    av = Avatar.load(os.path.join(tiny_run, "avatar.npz"))
    train = Dataset(tiny_dataset, "train")
    seq = train.sequence()
    seq_path = os.path.join(out, "head_seq.npz")
    np.savez(seq_path, vertices=seq.vertices, faces=seq.faces)
    imp = np.random.default_rng(0).random(av.num_gaussians)
    full = os.path.join(out, "full.pavs")
    # Its coarse levels as trained by default, backdrop stand-ins: Blender's preview hides each
    # once its region has arrived, Render Splats draws it behind. Their regions need the rest pose.
    assert av.forest.backdrop
    rest = train.canonical_vertices
    write_stream(full, av, imp, vertices=rest)
    bare = os.path.join(out, "bare.pavs")  # no embedded template: the mesh in Blender is it
    write_stream(bare, av, imp, embed_template=False, vertices=rest)
    hb, hf = read_header(bare), read_header(full)
    raw_bare, raw_full = open(bare, "rb").read(), open(full, "rb").read()
    cuts = {}

    def cut(name, raw, nbytes):
        p = os.path.join(out, f"{name}.pavs")
        with open(p, "wb") as fh:
            fh.write(raw[:nbytes])
        cuts[name] = p

    for pct in (1, 3, 10, 50):
        cut(f"bare_{pct}", raw_bare, hb.total_bytes * pct // 100)
        cut(f"full_{pct}", raw_full, hf.total_bytes * pct // 100)
    starts = np.concatenate([[0], np.cumsum(hb.level_counts)])
    # inside every level's stretch of records, mid-record (version 5 mixes the levels after the
    # coarse ones, so each such cut holds part of several levels: the template's included)
    for lv in range(len(hb.level_counts)):
        mid = int(starts[lv] + hb.level_counts[lv] // 2)
        cut(f"level{lv}", raw_bare, hb.bytes_for_count(mid) + hb.record_size // 2)
    K = hb.num_coarse_levels  # a third past the coarse levels: most template faces not arrived
    cut("template_mid", raw_bare, hb.bytes_for_count(int(starts[K] + hb.level_counts[K] // 3)))
    cut("empty", raw_bare, 0)
    cut("header_only", raw_bare, hb.header_size)
    url_cuts = {f"bare_{p}": ("bare.pavs", hb.total_bytes * p // 100) for p in (1, 3, 10, 50)}
    url_cuts.update({f"full_{p}": ("full.pavs", hf.total_bytes * p // 100) for p in (3, 50)})
    args = {
        "zip": build_zip(tmp),
        "seq": seq_path,
        "out": out,
        "cuts": cuts,
        "full": bare,
        "url_streams": [bare, full],
        "url_cuts": url_cuts,
        "url_same_tail": hf.total_bytes // 2,
        "backdrop": bare,
        "python": sys.executable,
    }
    rep, arrays = run_scenario(tmp, CUT_SCENARIO, args)
    return {
        "rep": rep,
        "arrays": arrays,
        "cuts": cuts,
        "seq": seq,
        "bare": bare,
        "full": full,
        "url_cuts": url_cuts,
        "url_same_tail": args["url_same_tail"],
        "header": hb,
        "backdrop": bare,
    }


def _expected(path, faces):
    from progressive_avatars.core.stream.reader import read_stream

    return read_stream(path, template_faces=faces)


@pytest.mark.slow
def test_nothing_blocked_was_imported(cut_session):
    assert cut_session["rep"]["blocked_loaded"] == []
    assert cut_session["rep"]["import"] == ["FINISHED"]


@pytest.mark.slow
def test_cut_streams_load_and_preview_what_arrived(cut_session):
    """Cut at 1/3/10/50 % (no embedded template: the header is small) and inside every
    level: each loads, shows exactly the verified records, on the mesh's frame."""
    from progressive_avatars.core.bridge.depth import depth_per_face

    rep, arrays, seq = cut_session["rep"], cut_session["arrays"], cut_session["seq"]
    _no_error(rep, "cuts")
    h = cut_session["header"]
    assert len(h.level_counts) >= 3  # a trained avatar that grew at least two levels
    names = [n for n in cut_session["cuts"] if n.startswith("bare_") or n.startswith("level")]
    loaded = 0
    for name in names:
        r = rep["cuts"][name]
        av = _expected(cut_session["cuts"][name], seq.faces)
        if av is None:  # inside the header (1 % of a small stream): refused by name, scene unchanged
            assert "no Gaussian arrived" in r["result"] and cut_session["cuts"][name] in r["result"], (name, r)
            assert r["unchanged"] and not r["preview_left"], (name, r)
            continue
        loaded += 1
        assert r["result"] == ["FINISHED"], (name, r)
        n = av.num_gaussians
        # every point has its place; Geometry Nodes draws those the forest draws (a coarse
        # stand-in makes way once its region has arrived)
        assert r["total"] == n and r["instances"] == len(av.forest.drawn()) > 0, (name, r)
        assert not r["status"], r["status"]
        ref = av.gaussians(seq.vertices[1].astype(np.float32), ids=np.arange(n))
        # positions in rank order: the avatar's faces in stream order (roots come first in the
        # decoded avatar; version 5 sends some after deeper faces)
        np.testing.assert_allclose(arrays[f"pos_{name}"], ref["means"][av.forest.stream_order()], atol=1e-5, rtol=0)
        depth = arrays[f"depth_{name}"]
        expected = depth_per_face(av.forest, h.num_template_faces)  # core's answer
        np.testing.assert_array_equal(depth, expected)
        legend = dict((d, c) for d, c in r["legend"])
        assert legend.get(-1, 0) == int((expected < 0).sum())
        # Every depth of the whole stream has its row (and colour), however short the cut.
        assert [d for d, _ in r["legend"] if d >= 0] == list(range(len(h.level_counts) - h.num_coarse_levels))
        # The slider: a percent of the whole stream, as far as it arrived.
        for p, (count, inst, status) in r["slider"].items():
            want = min(h.count_for_percent(float(p)), n)
            shown = len(av.forest.drawn(av.forest.stream_ids(want), records=want))
            assert count == want and inst == shown, (name, p, count, inst, want, shown, status)
    K = h.num_coarse_levels  # the case of issue 16: a cut inside the template level loads
    assert loaded >= len(h.level_counts) and sum(h.level_counts[:K]) < rep["cuts"][f"level{K}"]["total"] < sum(
        h.level_counts[: K + 1]
    )


@pytest.mark.slow
def test_backdrop_stream_renders_retired_stand_ins_behind_and_exports_without_them(cut_session):
    """A backdrop-stand-in stream (the default training's) in Blender: the preview shows what
    the forest draws, Render Splats the core rasteriser's image with the retired stand-ins
    behind the rest (as the stream's own renderer), and the PLY export the drawn ones only."""
    import plyfile

    from progressive_avatars.core.bridge.splats import srgb_to_linear
    from progressive_avatars.core.bridge.transforms import camera_from_blender, transform_gaussians
    from progressive_avatars.core.render.rasterize import render_numpy

    rep, seq = cut_session["rep"], cut_session["seq"]
    _no_error(rep, "backdrop")
    r = rep["backdrop"]
    assert r["load"] == r["render"] == r["ply"] == ["FINISHED"], r
    av = _expected(cut_session["backdrop"], seq.faces)
    f = av.forest
    n = r["count"]
    assert f.backdrop and n == av.num_gaussians
    faces, behind = f.render_set(f.stream_ids(n), records=n)
    assert behind is not None and behind.sum() == f.num_coarse  # the whole stream: every stand-in retired
    assert r["instances"] == len(faces) - behind.sum()  # the preview: the drawn ones
    g = av.gaussians(seq.vertices[r["frame"]].astype(np.float32), ids=faces)
    means, quats, scales = transform_gaussians(np.array(r["preview_matrix"]), g["means"], g["quats"], g["scales"])
    w, h = r["size"]
    cam = camera_from_blender(np.array(r["camera_matrix"]), r["lens"], r["sensor"], *r["shift"], w, h, z_up=False)
    args = (means, quats, scales, g["opacities"], g["colors"], cam, np.zeros(3, np.float32))
    image, alpha = render_numpy(*args, behind=behind)[:2]
    got = cut_session["arrays"]["backdrop_image"]
    assert (alpha > 0.5).mean() > 0.1  # the head fills the frame
    straight = image / np.where(alpha > 0, alpha, 1)[..., None]
    np.testing.assert_allclose(got[..., :3], srgb_to_linear(straight) * alpha[..., None], atol=1e-4)
    np.testing.assert_allclose(got[..., 3], alpha, atol=1e-4)
    ply = plyfile.PlyData.read(r["ply_path"])
    assert ply["vertex"].count == len(faces) - behind.sum()


@pytest.mark.slow
def test_cut_inside_header_fails_cleanly(cut_session):
    """With the template embedded a trained head's header is ~13 % of the stream: a cut at
    1/3/10 % holds no Gaussian. The load refuses, naming the file, and changes nothing."""
    rep = cut_session["rep"]
    _no_error(rep, "cuts")
    for name in ("full_1", "full_3", "empty", "header_only"):
        r = rep["cuts"][name]
        assert isinstance(r["result"], str) and os.path.basename(cut_session["cuts"][name]) in r["result"], r
        assert r["unchanged"] and not r["preview_left"], r
    assert "empty" in rep["cuts"]["empty"]["result"]
    assert "no complete Gaussian" in rep["cuts"]["header_only"]["result"]
    assert rep["cuts"]["full_50"]["result"] == ["FINISHED"]
    assert rep["cuts"]["full_50"]["total"] == _expected(cut_session["cuts"]["full_50"], None).num_gaussians


@pytest.mark.slow
def test_cut_url_transfers(cut_session):
    from progressive_avatars.core.stream.format import read_header

    rep, arrays, seq = cut_session["rep"], cut_session["arrays"], cut_session["seq"]
    _no_error(rep, "url")
    for key, (name, nbytes) in cut_session["url_cuts"].items():
        r = rep["url"][key]
        h = read_header(cut_session[name.split(".")[0]])
        n = h.count_for_bytes(nbytes)
        if n == 0:  # only the header arrived
            assert "no complete Gaussian" in r["result"] and r["unchanged"], r
            continue
        assert r["file"] == h.bytes_for_count(n)
        faces = None if h.template_embedded else seq.faces
        path = cut_session["bare"] if not h.template_embedded else cut_session["full"]
        from progressive_avatars.core.stream.reader import read_stream

        part = read_stream(path, max_gaussians=n, template_faces=faces)
        shown = len(part.forest.drawn())
        assert r["result"] == ["FINISHED"] and r["total"] == n and r["instances"] == shown, (key, r, n, shown)
        ref = part.gaussians(seq.vertices[1].astype(np.float32), ids=np.arange(n))
        np.testing.assert_allclose(arrays[f"urlpos_{key}"], ref["means"][part.forest.stream_order()], atol=1e-5, rtol=0)
    assert rep["url"]["bare_3"]["result"] == ["FINISHED"]  # (1 % of this small stream is inside its header)


@pytest.mark.slow
def test_url_downloads_do_not_share_a_file(cut_session):
    """Two URLs whose paths end alike: each preview keeps its own verified download."""
    from progressive_avatars.core.stream.format import read_header

    rep = cut_session["rep"]
    _no_error(rep, "url")
    (n1, r1, p1, t1, s1), (n2, r2, p2, t2, s2) = rep["url_same_tail"]
    assert r1 == r2 == ["FINISHED"] and p1 != p2
    for name, total, size in ((n1, t1, s1), (n2, t2, s2)):
        h = read_header(cut_session[name.split(".")[0]])
        n = h.count_for_bytes(cut_session["url_same_tail"])
        assert total == n > 0 and size == h.bytes_for_count(n), (name, total, n, size)


@pytest.mark.slow
def test_artist_slips(cut_session):
    """The mesh deleted under a preview, the preview deleted under its depth colours, a reload
    over a level filter, no file chosen, a saved project: each ends in a sane scene and the
    decoded avatars of deleted previews are let go."""
    rep = cut_session["rep"]
    _no_error(rep, "slips")
    r = rep["slips"]
    assert "choose a stream" in r["no_file"]
    res, unchanged = r["repeated_vertex"]
    assert "repeated_vertex.npz: face 5" in res and "uses a vertex twice" in res and unchanged, res
    res, unchanged = r["duplicate_face"]
    assert "duplicate_face.npz: face 9" in res and "repeats face 3" in res and unchanged, res
    shown, after, count, status = r["mesh_gone"]
    assert 0 < shown == after < count and status == "No mesh bound"  # never points left unplaced
    assert r["groups_after_reload"] == []
    assert r["orphan_poll"] and r["orphan_hide"] == ["FINISHED"] and r["orphan_after"] == [False, []]
    assert r["cache"][0] >= 1 and r["cache"][1]  # one decoded avatar per live preview, no more
    assert r["saved_load"] == ["FINISHED"] and r["stored"].startswith("//")
    saving = rep["stdout"].split("PA_SAVE_BEGIN")[1].split("PA_SAVE_END")[0]
    assert "blend relative" not in saving, saving


@pytest.mark.slow
def test_failed_load_leaves_scene_as_it_was(cut_session):
    rep = cut_session["rep"]
    _no_error(rep, "rollback")
    r = rep["rollback"]
    assert "injected failure" in r["result"]
    assert r["unchanged"], r["diff"]
    assert r["old_kept"]


@pytest.mark.slow
def test_depth_colours_toggle_and_levels(cut_session):
    from progressive_avatars.core.bridge.depth import NOT_ARRIVED_COLOR, depth_colors, depth_per_face

    rep, arrays, seq = cut_session["rep"], cut_session["arrays"], cut_session["seq"]
    _no_error(rep, "depth_toggle")
    assert rep["toggle_on"] == ["FINISHED"] and rep["on"]["views"] > 0
    assert rep["on"]["active"] == "pa_depth_color" and rep["on"]["shading"] == ["VERTEX"]
    depth = arrays["depth_toggle"]
    av = _expected(cut_session["cuts"]["template_mid"], seq.faces)
    n = av.num_gaussians
    h = cut_session["header"]
    top = len(h.level_counts) - 1 - h.num_coarse_levels  # the whole avatar's deepest depth: the colour scale

    def colours(d):  # what core says each face shows: its depth's colour, or "not arrived"
        return np.where((d < 0)[:, None], NOT_ARRIVED_COLOR, depth_colors(np.maximum(d, 0), top))

    expected = depth_per_face(av.forest, len(depth))
    np.testing.assert_array_equal(depth, expected)
    arrived = int((expected >= 0).sum())
    assert 0 < arrived < len(depth)  # a third of the template level: some faces arrived, most not
    corner = arrays["depth_colors_corner"].reshape(-1, 3, 4)  # triangles: 3 corners a face
    np.testing.assert_allclose(corner, np.broadcast_to(colours(expected)[:, None], corner.shape), atol=1e-6)
    legend = rep["on"]["legend"]
    assert legend[0][:2] == [-1, len(depth) - arrived]
    np.testing.assert_allclose(legend[0][2], NOT_ARRIVED_COLOR[:3], atol=1e-6)
    m = rep["on_low_count"]  # colours follow the budget
    low = arrays["depth_colors_low"].reshape(-1, 3, 4)
    assert 0 < m < n
    d_low = depth_per_face(av.forest, len(depth), m)
    assert 0 < int((d_low >= 0).sum()) < arrived  # fewer faces than at the whole cut, but some
    low_expected = colours(d_low)
    np.testing.assert_allclose(low, np.broadcast_to(low_expected[:, None], low.shape), atol=1e-6)
    # Off: the user's active colour and every view's colour mode come back, our colours go.
    assert rep["toggle_off"] == ["FINISHED"]
    assert rep["off"] == {"active": "user_paint", "shading": ["OBJECT"], "colour_attrs": ["user_paint"]}
    lv = rep["levels"]
    for k in range(3):
        assert lv[str(k)][0] == h.level_counts[k] and lv[str(k)][1][0] == "PA Level"
    whole = _expected(cut_session["bare"], seq.faces)
    assert lv["-1"][0] == len(whole.forest.drawn()) < h.num_records and "PA Level" not in lv["-1"][1]
    assert "mesh was deleted" in rep["deleted_mesh"]


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["REMESH", "SUBSURF", "DECIMATE"])
def test_topology_changing_modifier_is_refused(cut_session, kind):
    """Remesh / Subdivision Surface / Decimate on the bound mesh: the status names the mesh,
    the counts and the modifier; no Gaussian stays standing on wrong vertices; the load
    reports it; 'Shape keys only' follows the mesh exactly; removing the modifier recovers."""
    rep, arrays, seq = cut_session["rep"], cut_session["arrays"], cut_session["seq"]
    _no_error(rep, "topology")
    t = rep["topology"]
    n = cut_session["header"].num_records
    from progressive_avatars.core.stream.reader import read_stream

    whole = read_stream(cut_session["bare"], template_faces=seq.faces)
    shown = len(whole.forest.drawn())  # the whole stream: no stand-in
    assert shown < n and t["clean"] == ["", shown]
    r = t[kind]
    mod = f"my_{kind.lower()}"
    assert mod in r["status"] and "head_seq" in r["status"] and "Shape keys only" in r["status"], r
    if kind != "SUBSURF":
        assert "2562" in r["status"] and "5120" in r["status"]
    assert r["instances"] == 0
    assert r["shape_keys"] == ["", shown]
    ref = whole.gaussians(seq.vertices[1].astype(np.float32), ids=np.arange(n))
    np.testing.assert_allclose(arrays[f"topo_pos_{kind}"], ref["means"][whole.forest.stream_order()], atol=1e-5, rtol=0)
    assert r["load"] == ["FINISHED"] and mod in r["load_status"]
    report = rep["stdout"].split(f"PA_LOAD_WITH {kind}")[1].split("PA_LOAD_WITH")[0]  # the operator's reports
    assert "Warning" in report and mod in report, report
    assert r["removed"] == ["", shown]
    assert t["render_only_subsurf"] == ["", shown]


# -- training from the installed zip, messages and state --------------------------------------
TRAIN_SCENARIO = _scenario("guard_train_from_zip.py")

BLOCK_CHECKOUT = """import importlib.abc, sys
class _NoCheckout(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("progressive_avatars", "scripts", "_bootstrap"):
            raise ImportError(f"{name}: the checkout is not available to the extension's trainer")
sys.meta_path.insert(0, _NoCheckout())
"""


@pytest.fixture(scope="module")
def train_session(tiny_dataset, tmp_path_factory):
    import trimesh

    from tests.test_train import _flame_mode_dataset

    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.stream.writer import write_stream
    from tests.helpers import random_forest, sphere_mesh

    tmp = str(tmp_path_factory.mktemp("train"))
    out = os.path.join(tmp, "out")
    os.makedirs(out)
    # A Python that cannot import the checkout: what the extension runs must come from the zip.
    block = os.path.join(tmp, "block")
    os.makedirs(block)
    with open(os.path.join(block, "sitecustomize.py"), "w") as fh:
        fh.write(BLOCK_CHECKOUT)
    python = os.path.join(tmp, "python_no_checkout")
    with open(python, "w") as fh:
        fh.write(f'#!/bin/sh\nPYTHONPATH={block} exec {sys.executable} "$@"\n')
    os.chmod(python, 0o755)
    rng = np.random.default_rng(3)

    def seed_stream(faces, name):  # something loaded before training (replaced by the result)
        av = Avatar.initial(random_forest(faces, rng, depth=1, frac=0.2))
        p = os.path.join(out, name)
        write_stream(p, av, quantize=False)
        return p

    seq = Dataset(tiny_dataset, "train").sequence()
    seq_path = os.path.join(out, "head_seq.npz")
    np.savez(seq_path, vertices=seq.vertices, faces=seq.faces)
    flame_root, model, model_path, _ts, _one = _flame_mode_dataset(tiny_dataset, tmp_path_factory.mktemp("flame"))
    train = {
        "mesh": (tiny_dataset, seq_path, {}),
        "flame": (str(flame_root), str(flame_root / "flame_param"), {"flame_model": model_path}),
    }
    seeds = {"mesh": seed_stream(seq.faces, "seed_mesh.pavs"), "flame": seed_stream(model.faces, "seed_flame.pavs")}
    # Messages and imports
    foreign = os.path.join(out, "foreign.pavs")
    with open(foreign, "wb") as fh:
        fh.write(b"GIF89a" + bytes(100))
    foreign_npz = os.path.join(out, "foreign.npz")
    np.savez(foreign_npz, a=np.zeros(3))
    empty = os.path.join(out, "empty.pavs")
    open(empty, "wb").close()
    npz_folder = os.path.join(out, "npz_frames")
    os.makedirs(npz_folder)
    v, f = sphere_mesh(8, 10)
    for i in range(3):
        np.savez(os.path.join(npz_folder, f"f{i}.npz"), vertices=v * (1 + i), faces=f)
    folders = {}
    for ext in ("obj", "ply"):
        d = os.path.join(out, f"{ext}_frames")
        os.makedirs(d)
        for i in range(4):
            trimesh.Trimesh(v * (1 + 0.1 * i), f, process=False).export(os.path.join(d, f"frame_{i}.{ext}"))
        folders[f"{ext}_folder"] = os.path.join(d, f"frame_0.{ext}")
    stream = os.path.join(out, "avatar.pavs")
    write_stream(stream, Avatar.initial(random_forest(seq.faces, rng, depth=2, frac=0.3)))
    args = {
        "zip": build_zip(tmp),
        "out": out,
        "python": python,
        "flame_model": model_path,
        "train": train,
        "seed_stream": seeds,
        "seq": seq_path,
        "foreign_pavs": foreign,
        "foreign_npz": foreign_npz,
        "empty_pavs": empty,
        "flame_params": os.path.join(str(flame_root), "flame_param", "00000.npz"),
        "npz_folder": npz_folder,
        "stream": stream,
        **folders,
    }
    rep, arrays = run_scenario(tmp, TRAIN_SCENARIO, args, timeout=1500)
    return {"rep": rep, "arrays": arrays, "args": args, "verts": v, "faces": f}


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["mesh", "flame"])
def test_train_from_installed_zip_loads_onto_starting_mesh(train_session, kind):
    """No checkout reachable (the configured Python blocks it), the FLAME model from the
    preferences: training and export run from the extension's folder and the stream lands on
    the mesh that started training (a preview of it was active, not the mesh)."""
    from progressive_avatars.core.stream.format import read_header

    rep = train_session["rep"]
    _no_error(rep, "train")
    assert rep["blocked_loaded"] == []
    r = rep["train"][kind]
    assert r["result"] == ["FINISHED"], r
    run = os.path.join(train_session["args"]["out"], "run_" + kind)
    assert r["loaded"] == os.path.join(run, "avatar.pavs")
    h = read_header(r["loaded"])
    from progressive_avatars.core.stream.reader import read_stream

    f = read_stream(r["loaded"]).forest
    shown = len(f.drawn())  # the preview draws what the forest draws
    assert r["total"] == h.num_records and shown == r["instances"] > 0 and not r["status"]
    # trained as by default (backdrop stand-ins): in the whole stream every stand-in has retired
    assert f.backdrop and shown == h.num_records - f.num_coarse
    assert len(r["previews"]) == 1  # replaced the seed preview on the starting mesh
    cfg = json.load(open(os.path.join(run, "config.json")))
    if kind == "flame":
        assert cfg["flame_model"] == train_session["args"]["flame_model"]
    assert os.path.isfile(os.path.join(run, "avatar.npz"))
    if kind == "mesh":  # trained again into the same Run folder: refused, then Overwrite Run
        again = rep["train_again"]
        assert "Training failed (exit 2)" in again["refused"] and "choose another Run folder" in again["message"]
        assert again["overwritten"] == ["FINISHED"], again


@pytest.mark.slow
def test_messages_name_the_file_or_setting(train_session):
    rep, args = train_session["rep"], train_session["args"]
    _no_error(rep, "messages")
    m = rep["messages"]
    assert "Python not found" in m["bad_python"] and os.path.join(args["out"], "no", "python3") in m["bad_python"]
    assert "Preferences" in m["bad_python"]
    msg, running = m["python_not_executable"]
    assert "not executable" in msg and "not_executable_python" in msg and not running, m["python_not_executable"]
    msg, running = m["second_training"]
    assert "already running" in msg and running, m["second_training"]  # the first one's state untouched
    assert (
        "Python not found" in m["bad_python_render"]
        and os.path.join(args["out"], "no", "python3") in m["bad_python_render"]
    )
    assert "foreign.pavs" in m["foreign_pavs"] and "not a ProgressiveAvatars stream" in m["foreign_pavs"]
    assert "foreign.npz" in m["foreign_npz"] and "not an avatar file" in m["foreign_npz"]
    assert "empty.pavs" in m["empty_pavs"] and "empty" in m["empty_pavs"]
    assert "00000.npz" in m["flame_no_model"] and "FLAME model" in m["flame_no_model"]
    assert "preferences" in m["flame_no_model"] and "flame_model=" not in m["flame_no_model"]
    assert m["mesh_npz_folder"] == ["FINISHED"] and m["mesh_npz_folder_frames"] == 3
    assert m["range_kept"] == [["FINISHED"], 7, 9, 24]
    assert m["range_set"][0] == ["FINISHED"] and m["range_set"][1:] == [
        7,
        7 + m["range_set"][4] - 1,
        30,
        m["range_set"][4],
    ]
    v, f = train_session["verts"], train_session["faces"]
    for key in ("obj_folder", "ply_folder"):
        res, frames, nv, nf = m[key]
        assert res == ["FINISHED"] and frames == 4 and (nv, nf) == (len(v), len(f))
        np.testing.assert_allclose(train_session["arrays"][key], v * 1.2, atol=1e-6)  # frame 2, object space
    assert m["load_unsaved"] == ["FINISHED"] and m["path_unsaved"] == args["stream"]
    assert m["path_saved"] == "//../" + os.path.basename(args["stream"])
    moved = os.path.join(args["out"], "moved", os.path.basename(args["stream"]))
    assert os.path.normpath(m["moved"][0]) == moved and m["moved"][1] > 0 and not m["moved"][2]
    assert m["load_rel"] == ["FINISHED"] and m["stored_path"].startswith("//")
    assert "Budget" in m["export_zero"] and "0 Gaussians" in m["export_zero"]
    assert m["tab"] == "Progressive Avatars"
    from progressive_avatars.core.io.ply import read_ply

    assert m["export_half"][0] == ["FINISHED"] and m["export_half"][1] > 0
    assert len(read_ply(os.path.join(args["out"], "h.ply"))["means"]) == m["export_half"][1]
    with open(os.path.join(ROOT, "README.md")) as fh:
        assert "*Progressive Avatars*" in fh.read()
