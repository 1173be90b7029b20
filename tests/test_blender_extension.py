"""The Blender extension end to end, with the bpy module in subprocesses.

bpy is one per process and keeps global state, so every Blender session here runs in its
own interpreter with BLENDER_USER_RESOURCES/CONFIG/SCRIPTS in a temporary folder (no real
Blender configuration is read or written). The package is validated and built with
Blender's own blender_ext.py, installed into the clean Blender and driven through its
operators; one session prints a JSON report that the tests below assert on.
"""

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
import zipfile

import numpy as np
import pytest

from tests.helpers import random_forest, sphere_mesh

pytestmark = [pytest.mark.blender, pytest.mark.slow]  # one Blender session (build, install, scenario) for the module

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
T_FRAMES = 8
CHECK_FRAMES = (0, 3, 7)


def _bpy_dir():
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("bpy module not installed")
    return list(spec.submodule_search_locations)[0]


def _blender_ext():
    return os.path.join(_bpy_dir(), "5.0", "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")


def _clean_env(tmp):
    env = dict(os.environ)
    for key in ("BLENDER_USER_RESOURCES", "BLENDER_USER_CONFIG", "BLENDER_USER_SCRIPTS", "BLENDER_USER_DATAFILES"):
        env[key] = os.path.join(tmp, key.lower())
        os.makedirs(env[key], exist_ok=True)
    env["PYTHONPATH"] = ""
    return env


def run_scenario(script, args, tag, tmp):
    """Run a Blender scenario file (tests/blender_scenarios) as a plain Python with bpy, in clean
    Blender user folders under ``tmp``; its report is the JSON after ``tag`` on its last such
    line (the test fails with the session's output when there is none)."""
    proc = subprocess.run(
        [sys.executable, script, *args], capture_output=True, text=True, env=_clean_env(tmp), timeout=300
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(tag + " ")]
    if not lines:
        pytest.fail("Blender session produced no report:\n" + proc.stdout[-3000:] + proc.stderr[-3000:])
    report = json.loads(lines[-1][len(tag) + 1 :])
    return report, proc


def scenario_step(report, name):
    """One step's record of a scenario report (run_scenario), failing with its traceback."""
    r = report[name]
    assert "error" not in r, r["error"]
    return r


def make_inputs(folder):
    """A sphere sequence (mesh npz) and a stream written by core (its template = the mesh)."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.stream.writer import write_stream

    rng = np.random.default_rng(7)
    v, f = sphere_mesh(10, 14, radius=0.1)
    t = np.arange(T_FRAMES, dtype=np.float64)[:, None, None]
    wobble = np.sin(3 * v[None, :, 1:2] / 0.1 + t) * 0.01
    verts = (v[None] * (1 + 0.05 * t) + wobble + rng.normal(0, 1e-3, (T_FRAMES,) + v.shape)).astype(np.float32)
    seq = os.path.join(folder, "seq.npz")
    np.savez(seq, vertices=verts, faces=f)
    forest = random_forest(f, rng, depth=3, frac=0.4)
    av = Avatar.initial(forest)
    N = forest.num_faces
    av.d_mu[:] = rng.normal(0, 0.2, (N, 3))
    av.d_log_scale[:] = -1.3 + rng.normal(0, 0.2, (N, 3))
    av.d_rot[:] = rng.normal(size=(N, 4))
    av.f_dc[:] = rng.normal(0, 1.2, (N, 3))
    av.opacity_logit[:] = rng.normal(1.5, 0.5, N)
    stream = os.path.join(folder, "avatar.pavs")
    write_stream(stream, av, importance=rng.random(N), quantize=False)
    trainer = os.path.join(folder, "fake_train.py")
    with open(trainer, "w") as fh:
        fh.write(
            textwrap.dedent(f"""
            import argparse, shutil, os
            p = argparse.ArgumentParser(); p.add_argument('--data'); p.add_argument('--out'); p.add_argument('--preset')
            a = p.parse_args(); os.makedirs(a.out, exist_ok=True)
            for i in range(1, 5):
                print(f'it {{i}}/4 loss 0.1', flush=True)
            shutil.copy({stream!r}, os.path.join(a.out, 'avatar.pavs'))
        """)
        )
    return seq, stream, trainer, verts


def make_rig_inputs(folder):
    """A small FLAME-format model (npz) and a VHAP tracked-parameter file for it."""
    from tests.test_flame import N_SHAPE, make_flame_arrays, random_params

    from progressive_avatars.core.flame.model import _model_from_mapping

    arrays = make_flame_arrays(seed=3)
    model = _model_from_mapping(arrays, "test model", N_SHAPE)
    model_path = os.path.join(folder, "flame_model.npz")
    model.save_npz(model_path)
    f = arrays["f"].copy()  # a model whose face 4 names a vertex twice: no valid Blender mesh
    f[4, 2] = f[4, 0]
    _model_from_mapping(dict(arrays, f=f), "bad model", N_SHAPE).save_npz(os.path.join(folder, "flame_badface.npz"))
    prm = random_params(T_FRAMES, seed=11, scale=0.4)
    prm["expr"][2, 1] = 14.0  # beyond Blender's slider range: stored scaled
    params_path = os.path.join(folder, "tracked_flame_params.npz")
    np.savez(params_path, **prm)
    return model_path, params_path


def _scenario(name):
    with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "blender_scenarios", name)) as fh:
        return fh.read()


SCENARIO = _scenario("extension_session.py").replace("__FRAMES__", repr(CHECK_FRAMES))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = str(tmp_path_factory.mktemp("blender"))
    ext = _blender_ext()
    validate = subprocess.run([sys.executable, ext, "validate", ROOT], capture_output=True, text=True)
    dist = os.path.join(tmp, "dist")
    os.makedirs(dist)
    from progressive_avatars.core.bridge.payload import build_extension

    try:  # the zip with the training tier as its inner archive (scripts/build_extension.py)
        zips = [build_extension(ROOT, dist, ext)]
        build = subprocess.CompletedProcess([], 0, "", "")
    except RuntimeError as exc:
        zips, build = [], subprocess.CompletedProcess([], 1, str(exc), "")
    out = os.path.join(tmp, "out")
    os.makedirs(out)
    seq, stream, trainer, verts = make_inputs(out)
    flame_path, params_path = make_rig_inputs(out)
    result = {
        "validate": validate,
        "build": build,
        "zips": zips,
        "out": out,
        "seq": seq,
        "stream": stream,
        "verts": verts,
        "flame": flame_path,
        "params": params_path,
        "report": None,
    }
    if build.returncode != 0 or len(zips) != 1:
        return result
    script = os.path.join(tmp, "scenario.py")
    with open(script, "w") as fh:
        fh.write(SCENARIO)
    proc = subprocess.run(
        [sys.executable, script, zips[0], seq, stream, trainer, out, flame_path, params_path],
        capture_output=True,
        text=True,
        env=_clean_env(tmp),
        timeout=600,
    )
    result["proc"] = proc
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PA_REPORT ")]
    if lines:
        result["report"] = json.loads(lines[-1][len("PA_REPORT ") :])
        result["arrays"] = dict(np.load(os.path.join(out, "arrays.npz")))
    return result


def _report(session):
    if session["report"] is None:
        proc = session.get("proc")
        pytest.fail(
            "Blender session produced no report:\n"
            + (proc.stdout[-3000:] + proc.stderr[-3000:] if proc else session["build"].stdout + session["build"].stderr)
        )
    return session["report"]


def _no_error(rep, name):
    errs = [e for e in rep["errors"] if e.startswith(name + ":")]
    assert not errs, errs[0]


def _read_header(path):
    from progressive_avatars.core.stream.format import read_header

    return read_header(path)


def _read_stream(path):
    from progressive_avatars.core.stream.reader import read_stream

    return read_stream(path)


def test_manifest_validates_and_builds(session):
    assert session["validate"].returncode == 0, session["validate"].stdout + session["validate"].stderr
    assert session["build"].returncode == 0, session["build"].stdout + session["build"].stderr
    (zp,) = session["zips"]
    names = zipfile.ZipFile(zp).namelist()
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert "blender_addon/__init__.py" in names and "core/bridge/budget.py" in names
    leaked = [
        n
        for n in names
        if n.split("/")[0] in ("tests", "scripts", "docs", ".venv", "runs", ".git")
        or "__pycache__" in n
        or n.endswith(".pyc")
    ]
    assert not leaked, leaked
    # Training and export run from the zip's inner archive (core/train/jobs.py); the synthetic-data
    # generator and the evaluation report/plots are not shipped (tests/test_tiers.py checks the tiers).
    assert {"core/io/run.py", "core/io/mesh_io.py", "training_tier.pyz"} <= set(names)
    assert not {"core/train/jobs.py", "core/synthetic/dataset.py", "core/evaluate/plots.py"} & set(names)


def test_installs_and_enables_in_clean_blender(session):
    rep = _report(session)
    _no_error(rep, "install")
    assert rep["addon_enabled"]
    assert all(rep["operators"].values()), rep["operators"]
    assert len(rep["panels"]) == 4
    assert rep["extension_dir"] and "user_default" in rep["extension_dir"]


def test_import_sequence_positions_exact(session):
    rep = _report(session)
    _no_error(rep, "import")
    verts = session["verts"]
    assert rep["shape_keys"] == T_FRAMES + 1  # Basis + one per frame
    assert rep["frame_range"] == [5, 5 + T_FRAMES - 1]
    for t in CHECK_FRAMES:
        np.testing.assert_allclose(session["arrays"][f"seq_{t}"], verts[t], atol=1e-6, rtol=0)


def test_import_flame_rig(session):
    """As a FLAME rig: the evaluated mesh equals FLAME at every checked frame; edits to an
    expression key and to the jaw bone give what core's rig model says (whose equality with
    FLAME is pinned in test_flame_rig); weights, keys, bones and drivers are what was built."""
    rep = _report(session)
    _no_error(rep, "rig")
    from progressive_avatars.core.flame.model import flame_forward, load_flame_model
    from progressive_avatars.core.flame.rig import build_flame_rig

    model = load_flame_model(session["flame"])
    prm = dict(np.load(session["params"]))
    rig = build_flame_rig(model, prm)
    r = rep["rig"]
    assert "holds meshes, not FLAME parameters" in rep["rig_mesh_sequence"]
    assert "face 4" in rep["rig_bad_faces"] and "uses a vertex twice" in rep["rig_bad_faces"]
    assert r["result"] == ["FINISHED"] and r["modifiers"] == ["ARMATURE"]
    assert r["keys"] == ["Basis"] + rig.expr_key_names() + rig.pose_key_names()
    assert r["bones"] == ["root", "neck", "jaw", "eye_0", "eye_1"] and r["groups"] == r["bones"]
    assert r["drivers"] == 9 * 4 and r["simple"]  # evaluated without Python (no auto-exec needed)
    assert r["frame_range"] == [3, 3 + T_FRAMES - 1]
    for k, m in enumerate(r["rest"]):  # bones rest unrotated at FLAME's joints
        np.testing.assert_allclose(np.array(m)[:3, :3], np.eye(3), atol=1e-6)
        np.testing.assert_allclose(np.array(m)[:3, 3], rig.rest_joints[k], atol=1e-6)
    np.testing.assert_allclose(session["arrays"]["rig_weights"], model.weights, atol=1e-6)
    assert rig.expr_scale[1] > 1  # the 14.0 coefficient went through a scaled key
    want = flame_forward(model, **prm)
    for t in CHECK_FRAMES:
        np.testing.assert_allclose(session["arrays"][f"rig_{t}"], want[t], atol=2e-6, rtol=0)
    rig.expr_values[3, 0] = 2.5
    rig.quaternions[3, 2] = [0.9, 0.3, -0.2, 0.25]
    edited = rig.vertices(frames=[3])[0]
    assert np.abs(edited - want[3]).max() > 1e-3  # the edit is visible
    np.testing.assert_allclose(session["arrays"]["rig_edit_3"], edited, atol=2e-6, rtol=0)


def test_undo_leaves_no_stale_points(session):
    rep = _report(session)
    _no_error(rep, "undo")
    assert rep["undo"]["budget"] == 30.0
    av = _read_stream(rep["undo"]["file"])  # the last URL load: a cut stream
    ref = av.gaussians(session["verts"][rep["undo"]["frame"]])
    np.testing.assert_allclose(session["arrays"]["undo_pos"], ref["means"], atol=1e-5, rtol=0)


def test_budget_shows_stream_count(session):
    rep = _report(session)
    _no_error(rep, "load")
    info = _read_header(session["stream"])
    assert rep["at25"]["count"] == info.count_for_percent(25)
    assert rep["at25_instances"] == info.count_for_percent(25)
    assert rep["at100_instances"] == info.num_records
    assert rep["at25"]["total"] == info.num_records
    assert abs(rep["at25"]["mb"] - info.bytes_for_count(info.count_for_percent(25)) / 1e6) < 1e-9
    # the deepest level among the first records (version 5 interleaves the levels after the lead)
    forest = _read_stream(session["stream"]).forest
    assert rep["at25"]["level"] == int(forest.level[forest.stream_ids(info.count_for_percent(25))].max())
    assert rep["at25"]["level"] > int(forest.level[info.count_for_percent(25) - 1])  # not the last record's


def test_frames_match_core_evaluation(session):
    rep = _report(session)
    _no_error(rep, "load")
    from progressive_avatars.core.avatar.binding import quat_to_rotmat

    av = _read_stream(session["stream"])
    n = _read_header(session["stream"]).count_for_percent(25)
    verts = session["verts"]
    for t in (3, 6):
        ref = av.gaussians(verts[t])
        a = session["arrays"]
        assert rep[f"instances_{t}"] == n
        np.testing.assert_allclose(a[f"pos_{t}"][:n], ref["means"][:n], atol=1e-5, rtol=0)
        np.testing.assert_allclose(a[f"scl_{t}"][:n], ref["scales"][:n], atol=1e-6, rtol=1e-5)
        dots = np.abs(np.sum(a[f"rot_{t}"][:n] * ref["quats"][:n], axis=1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-5)
        # What Geometry Nodes instances: a hull at the mean (a camera card by default), and
        # the splat the material draws: its axes rotation·diag(scale) and its centre.
        xf = a[f"xf_{t}"]
        np.testing.assert_allclose(xf[:, :3, 3], ref["means"][:n], atol=1e-5)
        splat = a[f"splat_{t}"]
        want = quat_to_rotmat(ref["quats"][:n]) * ref["scales"][:n, None, :]
        np.testing.assert_allclose(splat[:, :3, :3], want, atol=1e-5)
        np.testing.assert_allclose(splat[:, :3, 3], ref["means"][:n], atol=1e-5)
    ref = av.gaussians(verts[6])
    np.testing.assert_allclose(session["arrays"]["pos_100_6"], ref["means"], atol=1e-5, rtol=0)


def test_depth_attribute_and_legend(session):
    rep = _report(session)
    _no_error(rep, "load")
    forest = _read_stream(session["stream"]).forest
    np.testing.assert_array_equal(session["arrays"]["depth"], forest.depth_per_root())
    assert rep["depth_color_domain"] == "CORNER"
    assert rep["active_color"] == "pa_depth_color"
    assert [c for _, c in rep["legend"]] == forest.depth_histogram().tolist()


def test_export_ply_current_frame_budget(session):
    rep = _report(session)
    _no_error(rep, "export")
    from progressive_avatars.core.io.ply import read_ply

    g = read_ply(os.path.join(session["out"], "frame.ply"))
    av = _read_stream(session["stream"])
    n = rep["export_count"]
    assert n == _read_header(session["stream"]).count_for_percent(50)
    ref = av.gaussians(session["verts"][2])
    np.testing.assert_allclose(g["means"], ref["means"][:n], atol=1e-5)
    # The model's own colours and opacities (once the preview's linear display colours leaked in).
    np.testing.assert_allclose(g["colors"], ref["colors"][:n], atol=1e-5)
    np.testing.assert_allclose(g["opacities"], ref["opacities"][:n], atol=1e-5)


def test_camera_conversion_projects_like_core(session):
    rep = _report(session)
    _no_error(rep, "camera")
    assert rep["camera_uv_err"] < 1e-3


def test_train_operator_runs_script_and_loads_result(session):
    rep = _report(session)
    _no_error(rep, "train")
    assert rep["train"]["result"] == ["FINISHED"]
    assert rep["train"]["progress"] == 100.0 and not rep["train"]["running"]
    assert rep["train"]["loaded"] == "avatar.pavs"
    _no_error(rep, "errors_reported")
    assert "Cannot load avatar" in rep["missing_file"]


def test_save_reload_keeps_state(session):
    rep = _report(session)
    _no_error(rep, "save_reload")
    r = rep["reload"]
    info = _read_header(session["stream"])
    assert r["is_preview"] and r["source"] == rep["mesh_name"] and r["filepath"] == "avatar.pavs"
    assert r["budget"] == pytest.approx(30.0) and r["count"] == info.count_for_percent(30)
    assert r["instances"] == info.count_for_percent(30)
    assert {"rotation", "scale", "opacity", "color", "level", "rank"} <= set(r["attributes"])
    assert r["instances_60"] == r["count_60"] == info.count_for_percent(60)
    av = _read_stream(session["stream"])
    n = r["count_60"]
    np.testing.assert_allclose(
        session["arrays"]["reload_pos_4"][:n], av.gaussians(session["verts"][4])["means"][:n], atol=1e-5
    )
    # Depth follows the budget: the deepest level among the first count_60 Gaussians per face.
    from progressive_avatars.core.bridge.depth import depth_per_face

    want = depth_per_face(av.forest, av.forest.num_roots, n)
    np.testing.assert_array_equal(session["arrays"]["reload_depth"], want)
    assert (want >= 0).all() and not np.array_equal(want, av.forest.depth_per_root())


def test_cycles_renders_show_coloured_splats(session):
    rep = _report(session)
    _no_error(rep, "render")
    from PIL import Image

    lit = {}
    for b in (5, 100):
        img = np.asarray(Image.open(os.path.join(session["out"], f"render_{b}.png")).convert("RGB"), np.float32) / 255
        border = np.concatenate([img[0], img[-1], img[:, 0], img[:, -1]])
        bg = np.median(border, axis=0)
        assert np.abs(border - bg).max() < 0.1, f"{b}%: the background is not clean"
        lit[b] = np.abs(img - bg).max(axis=2) > 0.1
        assert lit[b].mean() > 0.02, f"{b}%: almost nothing visible"
        chroma = img.max(axis=2) - img.min(axis=2)
        assert chroma[lit[b]].mean() > 0.08, f"{b}%: splats are not coloured"
    # The budget is what Cycles renders: 5 % of the records, and less of the sphere lit than at 100 %
    # (the roots go by importance, spread over the sphere, so 5 % already lights much of it).
    info = _read_header(session["stream"])
    assert rep["render_5_count"] == info.count_for_percent(5) < rep["render_100_count"] == info.num_records
    assert lit[100].mean() > lit[5].mean() + 0.02


def test_render_splats_operator_matches_core_render(session):
    rep = _report(session)
    _no_error(rep, "render_splats")
    from progressive_avatars.core.bridge.splats import srgb_to_linear
    from progressive_avatars.core.bridge.transforms import camera_from_blender, transform_gaussians
    from progressive_avatars.core.render.rasterize import render_numpy

    r = rep["splats"]
    assert r["result"] == ["FINISHED"]
    av = _read_stream(session["stream"])
    n = r["count"]
    assert n == _read_header(session["stream"]).count_for_percent(50)
    g = av.gaussians(session["verts"][r["frame"]], ids=np.arange(n))
    means, quats, scales = transform_gaussians(np.array(r["preview_matrix"]), g["means"], g["quats"], g["scales"])
    w, h = r["size"]
    cam = camera_from_blender(np.array(r["camera_matrix"]), r["lens"], r["sensor"], *r["shift"], w, h, z_up=False)
    image, alpha = render_numpy(means, quats, scales, g["opacities"], g["colors"], cam, np.zeros(3, np.float32))[:2]
    got = session["arrays"]["splats_image"]
    assert alpha.max() > 0.5 and (alpha > 0.01).mean() > 0.05  # the head is in view, not a blank frame
    # Rendered with the model's (sRGB) colours over nothing (Film > Transparent), stored as Blender
    # keeps render results: scene-linear and premultiplied by the coverage.
    straight = image / np.where(alpha > 0, alpha, 1)[..., None]
    np.testing.assert_allclose(got[..., :3], srgb_to_linear(straight) * alpha[..., None], atol=1e-4)
    np.testing.assert_allclose(got[..., 3], alpha, atol=1e-4)
    assert r["alpha_mode"] == "PREMUL"


def test_preview_follows_a_modifier_deformation(session):
    """Whatever Blender evaluates: a modifier added to the mesh moves the preview (the
    depsgraph handler), and removing it moves it back."""
    rep = _report(session)
    _no_error(rep, "mesh_edit")
    av = _read_stream(session["stream"])
    a = session["arrays"]
    assert np.abs(a["edit_verts"] - a["unedit_verts"]).max() > 1e-3  # the twist really deformed the mesh
    np.testing.assert_allclose(a["edit_pos"], av.gaussians(a["edit_verts"])["means"], atol=1e-5)
    np.testing.assert_allclose(a["unedit_pos"], av.gaussians(a["unedit_verts"])["means"], atol=1e-5)


def test_url_streaming_keeps_the_verified_prefix(session):
    """Load from a loopback HTTP server: refused while online access is off; a whole stream
    loads whole; a connection cut midway keeps exactly the verified records."""
    rep = _report(session)
    _no_error(rep, "url")
    assert "Online access is disabled" in rep["url_offline"]
    info = _read_header(session["stream"])
    whole, cut = rep["url"]["avatar.pavs"], rep["url"]["cut.pavs"]
    assert whole["result"] == ["FINISHED"] and whole["total"] == whole["instances"] == info.num_records
    assert whole["file"] == info.total_bytes
    half = info.total_bytes // 2
    n = max(k for k in range(info.num_records + 1) if info.bytes_for_count(k) <= half)
    assert cut["result"] == ["FINISHED"] and cut["total"] == cut["instances"] == n > 0
    assert cut["file"] == info.bytes_for_count(n)


def test_readme_names_the_add_on_controls_as_blender_shows_them():
    """README's Blender paragraph named controls that do not exist under those names (Load avatar,
    Train, Export PLY: the buttons read Load Progressive Avatar, Train Avatar, Export Splats PLY)."""
    import ast
    import re

    labels = set()
    for name in os.listdir(os.path.join(ROOT, "blender_addon")):
        if name.endswith(".py"):
            with open(os.path.join(ROOT, "blender_addon", name)) as fh:
                tree = ast.parse(fh.read())
            labels |= {
                n.value.lower() for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
            }
    with open(os.path.join(ROOT, "README.md")) as fh:
        readme = fh.read()
    start = readme.index("In the 3D view's sidebar")
    paragraph = readme[start : readme.index("How the\nlook works", start)]
    bold = re.findall(r"\*\*([^*]+)\*\*", paragraph)
    menus = re.findall(r"File > Import > \*([^*]+)\*", paragraph)
    assert len(bold) >= 7 and len(menus) == 2, (bold, menus)
    assert [n for n in bold + menus if n.replace("\n", " ").lower() not in labels] == []
