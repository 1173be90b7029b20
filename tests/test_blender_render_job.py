"""Render Splats' job logic (blender_addon/render_job.py) without a UI.

Under ``--background`` Blender's timers never fire, so the modal operator's polling cannot
run here; the job object it polls is tested directly instead: a persistent worker in another
interpreter, answers arriving on a reader thread, cancel = kill, the image equal to the core
rasteriser's. The module imports bpy only for the extension's user folder, so these tests
pass their own numba cache folder and run without Blender.
"""

import os
import stat
import sys
import time

import numpy as np
import pytest

from progressive_avatars.blender_addon import render_job


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
    assert first.wait(timeout=900) == "done", first.message  # a cold compile on a loaded machine
    first_s = time.perf_counter() - t
    t = time.perf_counter()
    second = render_job.RenderJob(sys.executable, arrays, cache_dir=cache)
    assert second.wait(timeout=60) == "done", second.message
    second_s = time.perf_counter() - t
    assert second.worker is first.worker and second.worker.alive()
    assert second_s * 5 <= first_s, (first_s, second_s)
    image, alpha, _ = render_numpy(
        arrays["means"],
        arrays["quats"],
        arrays["scales"],
        arrays["opacities"],
        arrays["colors"],
        cam,
        arrays["background"],
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
    assert again.wait(timeout=200) == "done", again.message
    np.testing.assert_array_equal(again.rgba, second.rgba)


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
