"""Render Splats' job logic (blender_addon/render_job.py) without a UI.

Under ``--background`` Blender's timers never fire, so the modal operator's polling cannot
run here; the job object it polls is tested directly instead: a persistent worker in another
interpreter, answers arriving on a reader thread, cancel = kill, the image equal to the core
rasteriser's. The module imports bpy only for the extension's user folder, so these tests
pass their own numba cache folder and run without Blender; the last one runs the Render Splats
operator in a Blender session (the bpy module) with the job replaced by a recorder, to check
what the operator hands the renderer (camera, Gaussians) and what it puts behind the splats.
"""

import json
import os
import stat
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from progressive_avatars.blender_addon import render_job
from tests.helpers import BPY_CHILD_PRELUDE, run_bpy_child


def _job_arrays(n=4000, size=(72, 96), seed=3):
    """A head-sized blob of trained-proportion splats (mm-scale, flat, mostly opaque) 0.6 m
    in front of the camera."""
    from progressive_avatars.core.geometry.camera import Camera

    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    means = (0.1 * d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    scales = np.exp(rng.normal(np.log(0.006), 0.5, (n, 3))).astype(np.float32)
    scales[:, 2] *= 0.1
    q = rng.normal(size=(n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, h = size
    cam = Camera(np.eye(3), np.array([0.0, 0.0, 0.6]), 110.0, 110.0, w / 2, h / 2, w, h)
    return cam, dict(
        R=cam.R,
        t=cam.t,
        intr=np.array([cam.fx, cam.fy, cam.cx, cam.cy]),
        size=np.array([w, h]),
        background=np.array([0.1, 0.2, 0.3], np.float32),
        means=means,
        quats=q,
        scales=scales,
        opacities=(1 / (1 + np.exp(-rng.normal(2, 1.5, n)))).astype(np.float32),
        colors=rng.random((n, 3)).astype(np.float32),
    )


@pytest.fixture
def no_workers():
    yield
    render_job.stop_all()


def test_a_python_without_the_renderer_fails_with_its_path(tmp_path, no_workers):
    fake = tmp_path / "python_without_site"
    fake.write_text(f'#!/bin/sh\nexec "{sys.executable}" -I -S "$@"\n')  # no site-packages: no numpy
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    _, arrays = _job_arrays(n=10)
    job = render_job.RenderJob(str(fake), arrays, cache_dir=str(tmp_path / "cache"))
    assert job.wait(timeout=60) == "failed"
    assert str(fake) in job.message and "numpy" in job.message
    assert not os.path.exists(job.tmp)  # its inputs are cleaned up
    with pytest.raises(OSError):
        render_job.RenderJob(str(tmp_path / "no_such_python"), arrays, cache_dir=str(tmp_path / "cache"))


def _fake_python(tmp_path, script, name="fake_python"):
    fake = tmp_path / name
    fake.write_text("#!/bin/sh\n" + script)
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    return str(fake)


def test_a_job_that_cannot_start_leaves_no_folder(tmp_path, own_tmp, no_workers):
    """The job's inputs (job.npz, 1.2 MB for a head) were saved before the worker started: a
    Python that is not executable (PermissionError), is missing, or inputs that cannot be saved
    left /tmp/pa_render_* behind."""
    _, arrays = _job_arrays(n=10)
    not_executable = tmp_path / "not_executable"
    not_executable.write_text("ply\n")
    for python in (str(not_executable), str(tmp_path / "no_such_python")):
        with pytest.raises(OSError):
            render_job.RenderJob(python, arrays, cache_dir=str(tmp_path / "cache"))
        assert not os.listdir(own_tmp), python

    class Unsaveable:
        def __array__(self, *args, **kwargs):
            raise RuntimeError("cannot be saved")

    with pytest.raises(RuntimeError):
        render_job.RenderJob(sys.executable, dict(arrays, means=Unsaveable()), cache_dir=str(tmp_path / "cache"))
    assert not os.listdir(own_tmp)
    assert not render_job._workers  # nothing was started for it


# A worker that says it is ready and then: exits before the job is sent (the job's write hits
# a broken pipe), or answers with a message the job cannot read.
_DIES_WHEN_READY = "echo '{\"ready\": true}'\n"
_GARBLED_ANSWER = 'echo \'{"ready": true}\'\nread line\necho \'{"id": 1, "progress": "half"}\'\nexec sleep 60\n'


@pytest.mark.parametrize("script", [_DIES_WHEN_READY, _GARBLED_ANSWER], ids=["broken_pipe", "garbled"])
def test_a_job_whose_worker_breaks_fails_and_leaves_no_folder(tmp_path, own_tmp, no_workers, script):
    """poll() raised (BrokenPipeError, ValueError) instead of failing the job: the modal
    operator's timer died with a traceback and the job's folder stayed."""
    _, arrays = _job_arrays(n=10)
    job = render_job.RenderJob(_fake_python(tmp_path, script), arrays, cache_dir=str(tmp_path / "cache"))
    assert os.path.isdir(job.tmp)
    if script is _DIES_WHEN_READY:
        job.worker.proc.wait(timeout=30)
        end = time.perf_counter() + 30
        while job.worker.messages.qsize() < 2 and time.perf_counter() < end:  # "ready", then the end
            time.sleep(0.01)
    assert job.wait(timeout=30) == "failed", job.message
    assert "render process ended" in job.message or "half" in job.message, job.message
    assert not os.path.exists(job.tmp) and not os.listdir(own_tmp)


def test_cancel_and_stop_all_remove_the_folders_of_unfinished_jobs(tmp_path, own_tmp, no_workers):
    """Cancel removes the job's folder; disabling the add-on or quitting (stop_all) killed the
    workers but left the folders of jobs still waiting for them."""
    _, arrays = _job_arrays(n=10)
    python = _fake_python(tmp_path, "exec sleep 60\n")  # never becomes ready
    first = render_job.RenderJob(python, arrays, cache_dir=str(tmp_path / "cache"))
    first.cancel()
    assert first.state == "cancelled" and not os.path.exists(first.tmp)
    a = render_job.RenderJob(python, arrays, cache_dir=str(tmp_path / "cache"))
    b = render_job.RenderJob(python, arrays, cache_dir=str(tmp_path / "cache"))
    assert a.worker is b.worker and a.poll() == b.poll() == "starting" and len(os.listdir(own_tmp)) == 2
    render_job.stop_all()
    assert a.state == b.state == "cancelled" and not a.worker.alive()
    assert not os.listdir(own_tmp)
    # A process (Blender, a script) that ends with a job still waiting removes its folder too.
    code = (
        "import sys, tempfile\n"
        "from progressive_avatars.blender_addon import render_job\n"
        "from progressive_avatars.tests.test_blender_render_job import _job_arrays\n"
        "tempfile.tempdir = sys.argv[2]\n"
        "job = render_job.RenderJob(sys.argv[1], _job_arrays(n=10)[1], cache_dir=sys.argv[3])\n"
        "print('STATE', job.state, job.worker.alive())\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, python, str(own_tmp), str(tmp_path / "cache")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "STATE starting True" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert not os.listdir(own_tmp)


_STORE_IMAGE = """
import json, sys
import numpy as np
import bpy
from progressive_avatars.blender_addon.render_job import store_image
rgba = np.array(json.loads(sys.argv[1]), np.float32)
def pixels(img):
    px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
    img.pixels.foreach_get(px)
    return px.reshape(img.size[1], img.size[0], 4)[::-1].tolist()  # rows top-down
img = store_image(rgba)
res = dict(alpha_mode=img.alpha_mode, transparent=pixels(img))
# Blender's own way out: Save As Render / save_render read the float pixels as premultiplied.
sc = bpy.context.scene
sc.view_settings.view_transform = "Standard"
sc.render.image_settings.file_format, sc.render.image_settings.color_mode = "PNG", "RGBA"
img.save_render(sys.argv[2], scene=sc)
res["png"] = pixels(bpy.data.images.load(sys.argv[2]))  # a byte image: sRGB-encoded, straight, / 255
try:
    res["over_grey"] = pixels(store_image(rgba, background=[0.5, 0.5, 0.5]))
except Exception as exc:
    res["over_grey"] = repr(exc)
print("RESULT", json.dumps(res))
"""


@pytest.mark.blender
def test_store_image_holds_premultiplied_linear_colour_and_a_linear_background(tmp_path):
    """The render's RGB is premultiplied (blended over black) and sRGB-encoded. store_image
    decoded the premultiplied values and flagged them STRAIGHT: at the edge of a red splat
    (A 0.389) the image held 0.125 = srgb_to_linear(0.389) instead of 0.389, and edges went
    dark in the compositor and in a saved PNG. The background is scene-linear, used as is."""
    import importlib.util

    from progressive_avatars.core.bridge.splats import srgb_to_linear

    if importlib.util.find_spec("bpy") is None:
        pytest.skip("bpy module not installed")
    srgb = np.array([[1.0, 0.0, 0.0], [0.7, 0.5, 0.2], [0.3, 0.6, 0.9], [0.0, 0.0, 0.0]], np.float32)
    alpha = np.array([0.389, 0.6, 1.0, 0.0], np.float32)
    rgba = np.concatenate([srgb * alpha[:, None], alpha[:, None]], -1).reshape(2, 2, 4)  # premultiplied
    code = textwrap.dedent(_STORE_IMAGE)
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "bl"), BLENDER_USER_CONFIG=str(tmp_path / "bl"))
    proc = subprocess.run(
        [sys.executable, "-c", code, json.dumps(rgba.tolist()), str(tmp_path / "out.png")],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert line, proc.stdout[-2000:] + proc.stderr[-2000:]
    res = json.loads(line[0][len("RESULT ") :])
    linear = srgb_to_linear(srgb)
    want = np.concatenate([linear * alpha[:, None], alpha[:, None]], -1).reshape(2, 2, 4)
    got = np.array(res["transparent"])
    np.testing.assert_allclose(got[0, 0], [0.389, 0, 0, 0.389], atol=1e-5)  # the red splat's edge
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert res["alpha_mode"] == "PREMUL"
    # Saved the way Blender saves renders, the splats keep their own colours at every coverage.
    png = np.array(res["png"]).reshape(4, 4)
    covered = alpha > 0
    np.testing.assert_allclose(png[covered, :3], srgb[covered], atol=1.5 / 255)
    np.testing.assert_allclose(png[:, 3], alpha, atol=1.5 / 255)
    # Over a scene-linear grey 0.5: 0.5 where nothing covers it (decoding it again gave 0.214).
    assert not isinstance(res["over_grey"], str), res["over_grey"]
    over = np.array(res["over_grey"])
    np.testing.assert_allclose(over[1, 1], [0.5, 0.5, 0.5, 1.0], atol=1e-6)
    a = alpha.reshape(2, 2, 1)
    np.testing.assert_allclose(over[..., :3], want[..., :3] + (1 - a) * 0.5, atol=1e-5)
    np.testing.assert_allclose(over[..., 3], 1.0)


def _wait_seeing(job, timeout):
    """RenderJob.wait, recording every message the job showed on the way (``job.seen``)."""
    job.seen, end = [], time.perf_counter() + timeout
    while job.poll() not in ("done", "failed", "cancelled") and time.perf_counter() < end:
        if job.message not in job.seen:
            job.seen.append(job.message)
        time.sleep(0.02)
    return job.state


@pytest.mark.slow
def test_worker_renders_once_warm_returns_at_once_and_cancels(tmp_path, no_workers):
    from progressive_avatars.core.render.rasterize import render_numpy

    cache = str(tmp_path / "numba_cache")  # empty: the first render compiles, as after a fresh install
    cam, arrays = _job_arrays()
    t = time.perf_counter()
    first = render_job.RenderJob(sys.executable, arrays, cache_dir=cache)
    returned = time.perf_counter() - t
    assert returned < 1.0  # the operator gets control back while the worker starts
    assert first.state == "starting" and first.poll() in ("starting", "rendering")
    # A cold compile on a loaded machine takes minutes: the job says why it waits.
    assert _wait_seeing(first, 900) == "done", first.message
    assert "starting the renderer: compiling its kernels (once for this version)" in first.seen, first.seen
    first_s = time.perf_counter() - t
    t = time.perf_counter()
    second = render_job.RenderJob(sys.executable, arrays, cache_dir=cache)
    assert second.wait(timeout=60) == "done", second.message
    second_s = time.perf_counter() - t
    assert second.worker is first.worker and second.worker.alive()
    assert second_s * 5 <= first_s, (first_s, second_s)
    # Over black whatever the job's background: RGB premultiplied, store_image adds the background.
    image, alpha, _ = render_numpy(
        arrays["means"],
        arrays["quats"],
        arrays["scales"],
        arrays["opacities"],
        arrays["colors"],
        cam,
        np.zeros(3, np.float32),
    )
    assert (alpha > 0.5).mean() > 0.1
    np.testing.assert_allclose(second.rgba[..., :3], image, atol=1e-6)
    np.testing.assert_allclose(second.rgba[..., 3], alpha, atol=1e-6)
    np.testing.assert_array_equal(first.rgba, second.rgba)
    # Two renders in flight on one worker (two clicks): each gets its own image.
    other_cam, other = _job_arrays(n=500, size=(40, 30), seed=9)
    a = render_job.RenderJob(sys.executable, other, cache_dir=cache)
    b = render_job.RenderJob(sys.executable, arrays, cache_dir=cache)
    assert a.worker is b.worker
    assert b.wait(timeout=60) == "done" and a.wait(timeout=60) == "done", (a.message, b.message)
    assert a.rgba.shape == (30, 40, 4)
    np.testing.assert_array_equal(b.rgba, second.rgba)
    # Cancel: the worker dies at once, the job says so, the next render starts a new worker.
    job = render_job.RenderJob(sys.executable, arrays, cache_dir=cache)
    worker = job.worker
    job.cancel()
    assert job.state == "cancelled" and job.poll() == "cancelled" and job.rgba is None
    assert not worker.alive()
    again = render_job.RenderJob(sys.executable, arrays, cache_dir=cache)
    assert again.worker is not worker
    assert _wait_seeing(again, 200) == "done", again.message
    assert not [m for m in again.seen if "compiling" in m], again.seen  # a new worker, the kernels cached
    np.testing.assert_array_equal(again.rgba, second.rgba)


def test_job_draws_retired_backdrop_stand_ins_behind_and_a_ply_leaves_them_out(tmp_path):
    """A job carrying a ``behind`` mask (current_gaussians of a backdrop avatar) renders those
    Gaussians behind every other, as the stream's own renderer does; without_behind (the PLY
    export) leaves them out and says how many."""
    from progressive_avatars.core.bridge.render_job import render_job as run_job
    from progressive_avatars.core.bridge.splats import without_behind
    from progressive_avatars.core.render.rasterize import render_numpy

    cam, arrays = _job_arrays(n=1500, seed=5)
    behind = np.zeros(1500, bool)
    behind[::7] = True
    keys = ("means", "quats", "scales", "opacities", "colors")
    np.savez(tmp_path / "job.npz", behind=behind, **arrays)
    run_job(str(tmp_path / "job.npz"), str(tmp_path / "out.npy"))
    got = np.load(tmp_path / "out.npy")
    image, alpha, _ = render_numpy(*(arrays[k] for k in keys), cam, np.zeros(3, np.float32), behind=behind)
    plain = render_numpy(*(arrays[k] for k in keys), cam, np.zeros(3, np.float32))[0]
    np.testing.assert_allclose(got[..., :3], image, atol=1e-6)
    np.testing.assert_allclose(got[..., 3], alpha, atol=1e-6)
    assert np.abs(plain - image).max() > 0.05  # the mask mattered
    g = {k: arrays[k] for k in keys}
    kept, left = without_behind(dict(g, behind=behind))
    assert left == behind.sum() and "behind" not in kept
    for k in keys:
        np.testing.assert_array_equal(kept[k], g[k][~behind])
    assert without_behind(g) == (g, 0)


def test_job_renders_from_its_own_camera_and_clamps_negative_colours(tmp_path):
    """The job's camera is the one the add-on saved (rotation, fx != fy, off-centre principal
    point, width x height) and its colours are clamped at 0 as 3DGS clamps SH colours: the image
    is render_numpy's of that camera built here and of max(colours, 0)."""
    from progressive_avatars.core.bridge.render_job import render_job as run_job
    from progressive_avatars.core.geometry.camera import Camera
    from progressive_avatars.core.render.rasterize import render_numpy

    _, arrays = _job_arrays(n=1500, size=(64, 48), seed=6)
    cam = Camera.look_at([0.35, 0.2, 0.45], [0, 0, 0], [0, 1, 0], 90.0, 120.0, 30.0, 22.0, 64, 48)
    arrays.update(R=cam.R, t=cam.t, intr=np.array([90.0, 120.0, 30.0, 22.0]), size=np.array([64, 48]))
    arrays["colors"] = arrays["colors"] * 1.6 - 0.5  # a third of the channels below 0
    np.savez(tmp_path / "job.npz", **arrays)
    run_job(str(tmp_path / "job.npz"), str(tmp_path / "out.npy"))
    got = np.load(tmp_path / "out.npy")
    keys = ("means", "quats", "scales", "opacities")
    bg = np.zeros(3, np.float32)
    image, alpha, _ = render_numpy(*(arrays[k] for k in keys), np.maximum(arrays["colors"], 0), cam, bg)
    assert got.shape == (48, 64, 4) and (alpha > 0.5).mean() > 0.1
    np.testing.assert_allclose(got[..., :3], image, atol=1e-6)
    np.testing.assert_allclose(got[..., 3], alpha, atol=1e-6)
    unclamped = render_numpy(*(arrays[k] for k in keys), arrays["colors"], cam, bg)[0]
    assert np.abs(unclamped - image).max() > 0.05  # the clamp mattered


_CALL_KERNEL = """import importlib, importlib.util, sys
import numpy as np
root, name = sys.argv[1], sys.argv[2]
spec = importlib.util.spec_from_file_location(name, root + "/__init__.py", submodule_search_locations=[root])
m = importlib.util.module_from_spec(spec); sys.modules[name] = m; spec.loader.exec_module(m)
k = importlib.import_module(name + ".core.render.kernels")
d = np.random.default_rng(0).random(1000)
print(k.depth_order(d, d > 0.1)[:5].tolist())
"""


def test_private_package_processes_keep_numba_cache_out_of_the_sources(tmp_path, monkeypatch):
    """The render worker and the Train runner import the extension as "pa_ext". numba keys its
    cache by source file, and an entry compiled as pa_ext names that module: written into a
    checkout's __pycache__, it made every later ``python scripts/...`` there fail with "No module
    named 'pa_ext'" (as the Train operator's runner did). Their environment keeps the cache apart."""
    import shutil
    import subprocess

    from progressive_avatars.blender_addon import training_tier

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    checkout = tmp_path / "checkout"  # a copy of the sources, so the real one is never touched
    shutil.copytree(os.path.join(root, "core"), checkout / "core", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(os.path.join(root, "__init__.py"), checkout / "__init__.py")
    call = tmp_path / "call.py"
    call.write_text(_CALL_KERNEL)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))  # numba_cache_dir()'s fallback lives there
    monkeypatch.setitem(sys.modules, "bpy", None)  # not inside Blender: the fallback, and no bpy loaded here
    env = training_tier.runner_env()
    assert not env.get("NUMBA_CACHE_DIR", "").startswith((root, str(checkout)))
    first = subprocess.run(
        [sys.executable, str(call), str(checkout), "pa_ext"], env=env, capture_output=True, text=True
    )
    assert first.returncode == 0, first.stderr[-2000:]
    assert not list(checkout.rglob("*.nbi")) and list((tmp_path / "home").rglob("*.nbi"))
    plain = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}  # a command-line run
    second = subprocess.run(
        [sys.executable, str(call), str(checkout), "progressive_avatars"], env=plain, capture_output=True, text=True
    )
    assert second.returncode == 0 and second.stdout == first.stdout, second.stderr[-2000:]


# -- the operator's side: what Render Splats hands the renderer ---------------------------
_OPERATOR_CHILD = (
    BPY_CHILD_PRELUDE
    + r'''
from bpy_extras.object_utils import world_to_camera_view
from mathutils import Vector

load_extension("pa_rj")
ply_import = sys.modules["pa_rj.blender_addon.ply_import"]
render_job = sys.modules["pa_rj.blender_addon.render_job"]
sys.modules["pa_rj.blender_addon.prefs"].python_problem = lambda *a, **k: ""  # no Python runs here
SENT = []


class FakeJob:
    """Records the arrays Render Splats sends the renderer and draws nothing (transparent)."""

    def __init__(self, python, arrays):
        SENT.append({k: np.array(v) for k, v in arrays.items()})
        w, h = (int(x) for x in arrays["size"])
        self.rgba = np.zeros((h, w, 4), np.float32)
        self.state, self.message, self.seconds, self.progress = "done", "", 0.0, 1.0

    def wait(self, *a, **k):
        return self.state

    def poll(self):
        return self.state

    def cancel(self):
        pass


render_job.RenderJob = FakeJob
R = {"cases": {}, "errors": {}}
arrays = {}


def run():
    n = len(SENT)
    try:
        res = list(bpy.ops.render.progressive_avatars_splats(wait=True))
    except RuntimeError as exc:
        return str(exc), None
    return res, (SENT[-1] if len(SENT) > n else None)


def image():
    img = bpy.data.images["PA Splats"]
    px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
    img.pixels.foreach_get(px)
    return px.reshape(img.size[1], img.size[0], 4)


try:
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    sc = bpy.context.scene
    with np.load(os.path.join(out, "splats.npz")) as d:
        g = {k: d[k] for k in d.files}
    obj = ply_import.create_splat_object(bpy.context, "splats", g)
    obj.location = (0.05, 0.1, -0.02)
    obj.rotation_euler = (0.3, -0.2, 0.5)
    bpy.context.view_layer.objects.active = obj
    camd = bpy.data.cameras.new("cam")
    cam = bpy.data.objects.new("cam", camd)
    sc.collection.objects.link(cam)
    sc.camera = cam
    cam.location = (0.0, -1.2, 0.05)
    cam.rotation_euler = (np.pi / 2, 0.0, 0.1)
    sc.world = bpy.data.worlds.new("w")
    sc.world.color = (0.0, 0.0, 0.0)
    cases = {
        "auto 64x64": dict(res=(64, 64)),
        "auto 96x48": dict(res=(96, 48)),
        "auto 48x96": dict(res=(48, 96)),
        "vertical 96x48": dict(res=(96, 48), fit="VERTICAL"),
        "vertical 48x96 sensor 30": dict(res=(48, 96), fit="VERTICAL", sensor_height=30.0),
        "horizontal 48x96": dict(res=(48, 96), fit="HORIZONTAL"),
        "shift 96x48": dict(res=(96, 48), shift=(0.1, -0.2)),
        "shift vertical 48x96": dict(res=(48, 96), shift=(-0.05, 0.15), fit="VERTICAL"),
        "pixel aspect 2:1": dict(res=(64, 64), aspect=(2.0, 1.0)),
        "pixel aspect 1:2 100x60": dict(res=(100, 60), aspect=(1.0, 2.0), shift=(0.1, 0.1)),
        "pixel aspect 1:3 vertical": dict(res=(80, 60), aspect=(1.0, 3.0), fit="VERTICAL", shift=(0.05, -0.1)),
        "lens unit FOV": dict(res=(64, 48), fov=0.9),
        "percentage 50": dict(res=(128, 96), pct=50),
        "percentage 33": dict(res=(100, 70), pct=33, fit="VERTICAL"),
    }
    local = np.asarray(g["means"], np.float64)
    for tag, c in cases.items():
        r = sc.render
        r.resolution_x, r.resolution_y = c["res"]
        r.resolution_percentage = c.get("pct", 100)
        r.pixel_aspect_x, r.pixel_aspect_y = c.get("aspect", (1.0, 1.0))
        camd.type, camd.sensor_fit = "PERSP", c.get("fit", "AUTO")
        camd.lens_unit = "FOV" if "fov" in c else "MILLIMETERS"
        camd.lens, camd.sensor_width, camd.sensor_height = 50.0, 36.0, c.get("sensor_height", 24.0)
        if "fov" in c:
            camd.angle = c["fov"]
        camd.shift_x, camd.shift_y = c.get("shift", (0.0, 0.0))
        bpy.context.view_layer.update()
        res, sent = run()
        w = r.resolution_x * r.resolution_percentage // 100
        h = r.resolution_y * r.resolution_percentage // 100
        world = local @ np.array(obj.matrix_world)[:3, :3].T + np.array(obj.matrix_world)[:3, 3]
        # A render at a percentage is framed as one of its size in pixels (rounded down) at 100 %
        # (world_to_camera_view frames the unscaled resolution, whose aspect can differ slightly).
        r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
        exp = []
        for p in world:
            v = world_to_camera_view(sc, cam, Vector(p.tolist()))
            exp.append([v.x * w, (1.0 - v.y) * h])  # Blender's y runs up, image rows down
        R["cases"][tag] = {"result": res, "size": [w, h], "expected": exp}
        if sent is not None:
            for k in ("R", "t", "intr", "size", "means"):
                arrays[f"{tag}|{k}"] = sent[k]

    # Cameras the renderer cannot draw: refused with a reason, nothing sent.
    r = sc.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = 64, 64, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    for kind in ("ORTHO", "PANO"):
        camd.type = kind
        R["errors"][kind] = run()[0]
    camd.type = "PERSP"
    r.resolution_percentage = 1
    R["errors"]["0 px"] = run()[0]
    r.resolution_percentage = 100
    empty = bpy.data.objects.new("an empty", None)
    sc.collection.objects.link(empty)
    sc.camera = empty
    R["errors"]["empty"] = run()[0]
    sc.camera = cam
    R["sent_count"] = len(SENT)

    # The world behind the splats: its Background node (scene-linear), not the viewport colour.
    bg = next(n for n in sc.world.node_tree.nodes if n.type == "BACKGROUND")
    bg.inputs["Color"].default_value = (0.5, 0.25, 0.1, 1.0)
    bg.inputs["Strength"].default_value = 1.5
    sc.world.color = (0.9, 0.9, 0.9)
    res, sent = run()
    R["background"] = {"result": res, "sent": sent["background"].tolist(), "corner": image()[0, 0].tolist()}
    sc.render.film_transparent = True
    res, sent = run()
    R["transparent"] = {"result": res, "corner": image()[0, 0].tolist()}
    sc.render.film_transparent = False

    # Object scale 0: nothing to draw; scale 0 on one axis: flat splats, positive scales.
    obj.scale = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    res, sent = run()
    R["scale 0"] = {"result": res, "count": int(len(sent["means"]))}
    obj.scale = (1.0, 1.0, 0.0)
    bpy.context.view_layer.update()
    res, sent = run()
    R["flattened"] = {"result": res, "count": int(len(sent["means"])), "min": float(sent["scales"].min())}
    # A mirrored, non-uniformly scaled object: the world covariances are A Σ Aᵀ.
    obj.scale = (-1.0, 2.0, 0.5)
    bpy.context.view_layer.update()
    res, sent = run()
    R["mirror"] = {"result": res, "matrix": [list(x) for x in obj.matrix_world]}
    for k in ("quats", "scales"):
        arrays[f"mirror|{k}"] = sent[k]
except Exception:
    R["error"] = traceback.format_exc()
np.savez(os.path.join(out, "sent.npz"), **arrays)
print("PA_RJ " + json.dumps(R))
'''
)


@pytest.mark.blender
def test_render_splats_frames_like_blender_and_draws_the_world(tmp_path):
    """Render Splats hands the renderer the camera Blender renders with, for every sensor fit,
    lens unit, shift, pixel aspect and resolution percentage: the Gaussians' centres land on
    the pixels bpy_extras.object_utils.world_to_camera_view gives. Orthographic and panoramic
    cameras, an Empty as scene camera and a render of 0 px are refused with their reason.
    The world behind the splats is the World's Background colour (scene-linear, what users
    edit); a zero-scaled object draws nothing and a mirrored one keeps its covariances."""

    from progressive_avatars.core.geometry.camera import Camera
    from progressive_avatars.core.geometry.rotations import quat_to_rotmat
    from tests.test_blender_extension import _bpy_dir, _clean_env

    _bpy_dir()
    rng = np.random.default_rng(5)
    n = 12
    q = rng.normal(size=(n, 4))
    g = {
        "means": rng.uniform(-0.2, 0.2, (n, 3)).astype(np.float32),
        "quats": (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        "scales": np.exp(rng.normal(np.log(0.01), 0.5, (n, 3))).astype(np.float32),
        "opacities": rng.uniform(0.5, 0.9, n).astype(np.float32),
        "colors": rng.uniform(0.1, 0.9, (n, 3)).astype(np.float32),
    }
    np.savez(tmp_path / "splats.npz", **g)
    rep, _ = run_bpy_child(_OPERATOR_CHILD, tmp_path, "PA_RJ", _clean_env(str(tmp_path)))
    with np.load(tmp_path / "sent.npz") as d:
        sent = {k: d[k] for k in d.files}
    for tag, case in rep["cases"].items():
        assert case["result"] == ["FINISHED"], (tag, case["result"])
        w, h = case["size"]
        assert sent[f"{tag}|size"].tolist() == [w, h], tag
        cam = Camera(sent[f"{tag}|R"], sent[f"{tag}|t"], *sent[f"{tag}|intr"], w, h)
        uv, depth = cam.project(sent[f"{tag}|means"].astype(np.float64))
        assert np.all(depth > 0), tag
        np.testing.assert_allclose(uv, np.array(case["expected"]), atol=2e-3, err_msg=tag)
    errors = rep["errors"]
    assert "orthographic" in errors["ORTHO"] and "perspective cameras only" in errors["ORTHO"]
    assert "panoramic" in errors["PANO"]
    assert "0×0 px" in errors["0 px"] and "percentage" in errors["0 px"]
    assert "'an empty'" in errors["empty"] and "not a camera" in errors["empty"]
    assert rep["sent_count"] == len(rep["cases"])  # none of those reached the renderer
    # The splats are rendered over black; the image holds the world colour behind them.
    assert rep["background"]["result"] == ["FINISHED"] and rep["background"]["sent"] == [0.0, 0.0, 0.0]
    np.testing.assert_allclose(rep["background"]["corner"], [0.75, 0.375, 0.15, 1.0], atol=1e-5)
    np.testing.assert_allclose(rep["transparent"]["corner"], [0.0, 0.0, 0.0, 0.0], atol=1e-6)
    assert rep["scale 0"] == {"result": ["FINISHED"], "count": 0}
    assert rep["flattened"]["count"] == n and rep["flattened"]["min"] > 0
    M = np.array(rep["mirror"]["matrix"])
    A = M[:3, :3]

    def cov(quats, scales):
        Rm = quat_to_rotmat(np.asarray(quats, np.float64))
        return Rm @ (np.asarray(scales, np.float64)[:, :, None] ** 2 * np.swapaxes(Rm, 1, 2))

    expected = A @ cov(g["quats"], g["scales"]) @ A.T
    got = cov(sent["mirror|quats"], sent["mirror|scales"])
    np.testing.assert_allclose(got, expected, atol=1e-6 * np.abs(expected).max())


def test_the_cold_compiling_worker_test_is_marked_slow():
    """It waits up to 900 s for a worker compiling its kernels from an empty cache: when a helper
    was put between it and its @pytest.mark.slow, the mark went to the helper and the quick loop
    (-m "not slow") ran it."""
    marks = [m.name for m in getattr(test_worker_renders_once_warm_returns_at_once_and_cancels, "pytestmark", [])]
    assert "slow" in marks, marks
    assert not hasattr(_wait_seeing, "pytestmark")
