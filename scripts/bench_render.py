"""Benchmark of the CPU rasteriser: forward/backward time and peak memory on head-like scenes,
and time/error against the dense float64 reference of the tests.

    python scripts/bench_render.py [--quick]
    python scripts/bench_render.py --against COMMIT [--reps N] [--threads 1,2] [--run RUN [--one-image]] [--out FILE]

``run(quick=False)`` returns the Markdown section the script prints. ``--against`` instead
times each kernel of core/render/kernels.py at COMMIT (extracted with `git show` and imported
as its own module) against this tree's, interleaved rep by rep in one process, at each numba
thread count of --threads, and checks both against the dense float64 reference (section
"Rasteriser kernels"; put it into docs/BENCHMARKS.md with `scripts/bench.py --only none
--section raster_kernels=FILE`). With --run RUN the scene is that trained run's avatar, every
level rendered in one pass (section "Rasteriser kernels, every level": --section
raster_levels=FILE); with --one-image too, that avatar as one image (section "Rasteriser kernels,
trained avatar": --section raster_trained=FILE).
"""

from __future__ import annotations

import os

# Before torch loads OpenMP: see core/render/rasterize.py (spinning workers starve each other on a busy box).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401  (makes progressive_avatars importable, strips Blender's "--")

import datetime  # noqa: E402
import inspect  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

from bench_common import machine  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# The float64 record of kernels before 2026-11-24 (rasterize.py's pool holds float32 ones), kept
# between calls as the pool keeps its own.
_OLD_RECORD = np.empty(0)
_POOLS = {}  # kernel module name -> record buffer pool (kernel_pipeline)


def head_scene(n, seed=0):
    """Gaussians on an ellipsoid (semi-axes ~0.1 m) facing +z, scales 1-3 mm, like a real avatar."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = d * np.array([0.085, 0.11, 0.095])
    quats = rng.normal(size=(n, 4))
    scales = rng.uniform(1e-3, 3e-3, size=(n, 3))
    scales[np.arange(n), rng.integers(0, 3, n)] *= 0.2  # surfels are flattish
    opacities = rng.uniform(0.2, 0.98, size=n)
    colors = rng.uniform(0.0, 1.0, size=(n, 3))
    return [x.astype(np.float32) for x in (means, quats, scales, opacities, colors)]


def head_camera(width, height):
    from progressive_avatars.core.geometry.camera import Camera

    f = 3.0 * height  # the 0.22 m tall head fills about two thirds of the image height at 1 m
    return Camera.look_at(
        [0.05, 0.02, 1.0], [0, 0, 0], [0, 1, 0], f * 1.02, f, width * 0.52, height * 0.49, width, height
    )


def _rss_peak_mb():
    """Peak resident set size so far (MB). Reset with _reset_peak where the kernel allows it."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _rss_now_mb():
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _reset_peak() -> bool:
    """Linux resets VmHWM to the current RSS on writing 5 to clear_refs."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _timed(fn, repeats):
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def bench_scene(width, height, n, repeats=3, threads=None):
    import numba
    import torch

    from progressive_avatars.core.render.rasterize import render

    numba.set_num_threads(threads or numba.config.NUMBA_NUM_THREADS)

    cam = head_camera(width, height)
    params = [torch.from_numpy(x) for x in head_scene(n)]

    def forward(grad):
        ps = [p.clone().requires_grad_(grad) for p in params]
        return ps, render(*ps, cam, compute_contrib=False)  # as training and evaluation call it

    def fwd_bwd():
        ps, out = forward(True)
        out.image.sum().backward()

    fwd_bwd()  # warm-up: numba cache load / compile, page faults
    with torch.no_grad():
        fwd_ms = _timed(lambda: forward(False), repeats)
    times = []
    for _ in range(repeats):
        ps, out = forward(True)
        loss = (out.image * 0.5).sum() + out.alpha.sum()
        t0 = time.perf_counter()
        loss.backward()
        times.append(time.perf_counter() - t0)
    bwd_ms = min(times) * 1e3
    total_ms = _timed(fwd_bwd, repeats)
    base = _rss_now_mb()
    exact = _reset_peak()
    fwd_bwd()
    peak = _rss_peak_mb()
    visible = int((out.radii > 0).sum())
    threads = numba.get_num_threads()
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return dict(
        width=width,
        height=height,
        n=n,
        threads=threads,
        visible=visible,
        fwd_ms=fwd_ms,
        bwd_ms=bwd_ms,
        total_ms=total_ms,
        rss_base_mb=base,
        rss_peak_mb=peak,
        peak_exact=exact,
        coverage=float(out.alpha.detach().mean()),
    )


def bench_reference(width=64, height=64, n=500, repeats=3):
    import torch

    from progressive_avatars.core.render.reference import render_reference

    from progressive_avatars.core.render.rasterize import render

    cam = head_camera(width, height)
    params = [torch.from_numpy(x) for x in head_scene(n, seed=1)]
    params[2] = params[2] * 6.0  # fewer, larger Gaussians so a small image is still covered
    p64 = [p.double() for p in params]

    def ours():
        ps = [p.clone().requires_grad_(True) for p in params]
        out = render(*ps, cam)
        out.image.sum().backward()
        return out

    def ref():
        ps = [p.clone().requires_grad_(True) for p in p64]
        img, alpha, _ = render_reference(*ps, cam)
        img.sum().backward()
        return img

    out = ours()
    img = ref()
    err = float((out.image.detach().double() - img.detach()).abs().max())
    t_ours = _timed(ours, repeats)
    t_ref = _timed(ref, repeats)
    return dict(width=width, height=height, n=n, ours_ms=t_ours, ref_ms=t_ref, max_err=err)


def run(quick: bool = False) -> str:
    import numba
    import torch

    sizes = [(256, 256, 40_000)] if quick else [(256, 256, 40_000), (802, 550, 170_000)]
    thread_counts = sorted({1, numba.config.NUMBA_NUM_THREADS})
    rows = [bench_scene(w, h, n, repeats=2 if quick else 5, threads=t) for w, h, n in sizes for t in thread_counts]
    ref = bench_reference(repeats=2 if quick else 3)
    cmd = "python scripts/bench_render.py" + (" --quick" if quick else "")
    mem_note = (
        "peak RSS from /proc/self/status VmHWM, reset through /proc/self/clear_refs before one forward+backward"
        if all(r["peak_exact"] for r in rows)
        else "peak RSS from getrusage ru_maxrss (process high-water mark; may include earlier peaks)"
    )
    lines = [
        "## CPU rasteriser benchmark",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `{cmd}`",
        f"- machine: {machine()}, {platform.platform()}, numba {numba.__version__} with "
        f"{numba.get_num_threads()} threads "
        f"({numba.threading_layer()}), torch {torch.__version__}",
        "- scene: Gaussians on an ellipsoid (semi-axes 85/110/95 mm) at ~1 m, scales 1-3 mm (one axis "
        "x0.2), opacity U(0.2, 0.98), float32 tensors; render(compute_contrib=False), as training and evaluation "
        "call it (from 2026-11-27; before, every render summed alpha*T per Gaussian); times are the best of several "
        f"runs after a warm-up (OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')})",
        f"- memory: {mem_note}; the baseline is the RSS before that call",
        f"- load average when the section was written: {', '.join(f'{x:.1f}' for x in os.getloadavg())} "
        f"(the machine is shared; more than {os.cpu_count()} means other processes competed for the cores)",
        "",
        "| image | Gaussians (not culled) | numba threads | forward ms | backward ms | fwd+bwd ms | RSS before MB "
        "| peak RSS MB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['width']}x{r['height']} | {r['n']:,} ({r['visible']:,}) | {r['threads']} "
            f"| {r['fwd_ms']:.1f} | {r['bwd_ms']:.1f} | {r['total_ms']:.1f} | {r['rss_base_mb']:.0f} "
            f"| {r['rss_peak_mb']:.0f} |"
        )
    lines += [
        "",
        f"Against the dense float64 torch reference (core/render/reference.py), {ref['width']}x"
        f"{ref['height']}, {ref['n']} Gaussians, forward+backward: ours {ref['ours_ms']:.1f} ms, reference "
        f"{ref['ref_ms']:.1f} ms (x{ref['ref_ms'] / ref['ours_ms']:.1f}); max abs image error "
        f"{ref['max_err']:.2e}.",
        "",
    ]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- old against new kernels

STAGES = [
    "project_forward",
    "sort",
    "pack_splats",
    "bin_tiles",
    "raster_forward",
    "raster_backward",
    "project_backward",
]


def old_kernels(commit):
    """core/render/kernels.py at ``commit`` as a module of its own (numba caches it beside the file)."""
    import importlib
    import subprocess
    import sys

    rev = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", commit], check=True, capture_output=True)
    rev = rev.stdout.decode().strip()
    folder = os.path.join(ROOT, "runs", "bench_old_raster")
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, f"kernels_{rev}.py")
    if not os.path.exists(path):
        src = subprocess.run(
            ["git", "-C", ROOT, "show", f"{rev}:core/render/kernels.py"], check=True, capture_output=True
        )
        with open(path, "wb") as fh:
            fh.write(src.stdout)
    if folder not in sys.path:  # imported by name, so that numba's cache can find the module again
        sys.path.insert(0, folder)
    return rev, importlib.import_module(f"kernels_{rev}")


def kernel_pipeline(rk, arrays, cam, grad_image, grad_alpha, near=0.01, eps2d=0.3, glevel=None):
    """The CPU render of core/render/rasterize.py, forward and backward, kernel by kernel with
    module ``rk``'s kernels; returns per-stage (wall ms, process CPU ms), the image, alpha and
    the gradients (means, quats, scales, opacities, colors). With ``glevel`` [N] (levels 0..L-1)
    one pass renders the L nested images of render_levels (grad_image [L, H, W, C], grad_alpha
    [L, H, W]); image and alpha are then [L, H, W, ...]."""
    means, quats, scales, opac, colors, bg = arrays
    W, H = cam.width, cam.height
    times = {}
    clock = [time.perf_counter(), time.process_time()]

    def mark(name):
        t, c = time.perf_counter(), time.process_time()
        times[name] = ((t - clock[0]) * 1e3, (c - clock[1]) * 1e3)
        clock[:] = [t, c]

    Rc, tc = np.ascontiguousarray(cam.R, np.float64), np.ascontiguousarray(cam.t, np.float64)
    fx, fy, cx, cy = float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy)
    lim = rk.fov_limits(W, H, fx, fy, cx, cy)
    clock[:] = [time.perf_counter(), time.process_time()]
    xy, conic, depth, rect, radii, cut = rk.project_forward(
        means, quats, scales, opac, Rc, tc, fx, fy, cx, cy, lim, W, H, near, eps2d
    )
    mark("project_forward")
    # depth_order and splat_rows sort parts at once since 2026-11-27 (rasterize.py passes its
    # thread count); before, one thread sorted
    parts = hasattr(rk, "depth_order") and "parts" in inspect.signature(rk.depth_order.py_func).parameters
    if parts:  # ad3d079 sorted in one part per thread at any size; sort_parts chooses since
        threads = numba.get_num_threads()
        parts = (rk.sort_parts(len(means), threads) if hasattr(rk, "sort_parts") else threads,)
    else:
        parts = ()
    if hasattr(rk, "depth_order"):
        order = rk.depth_order(depth, radii != 0, *parts)
    else:  # kernels before the radix sort: rasterize.py sorted with numpy
        visible = np.flatnonzero(radii != 0)
        order = visible[np.argsort(depth[visible], kind="stable")].astype(np.int64)
    mark("sort")
    if glevel is None:
        glevel, upto = np.zeros(len(means), np.int64), np.zeros(1, np.int64)
        grad_image, grad_alpha = grad_image[None], grad_alpha[None]
    else:
        upto = np.arange(int(glevel.max()) + 1, dtype=np.int64)
    tiles_x = -(-W // rk.TILE)
    packed = hasattr(rk, "pack_splats")  # kernels that read packed splat rows (since c0bb2c0)
    if packed:
        n_ch = colors.shape[1]
        row_of, gaussian = rk.splat_rows(order, rect, tiles_x, -(-H // rk.TILE), *parts)
        splats = rk.pack_splats(
            gaussian, xy, conic, opac, cut, colors, rect, glevel, rk.aligned_splats(len(order), n_ch)
        )
        # what the kernels take in place of the per-Gaussian arrays
        gaussians_fwd = (splats, gaussian, len(means), n_ch)
        gaussians_bwd = gaussians_fwd
    mark("pack_splats")
    if packed:
        tile_start, ids = rk.bin_tiles(splats, row_of, tiles_x, -(-H // rk.TILE))
    else:
        tile_start, ids = rk.bin_tiles(rect, order, tiles_x, -(-H // rk.TILE))
        gaussians_fwd = (xy, conic, opac, cut, colors, rect)
        gaussians_bwd = (xy, conic, opac, colors)
    mark("bin_tiles")
    record_args = inspect.signature(rk.raster_forward.py_func).parameters
    if "rec_keep" in record_args or "rec_gauss" in record_args:
        # Kernels whose backward replays the forward's record: rasterize.py's buffer pool, as in
        # training (steady state: reused buffers, no re-run).
        from progressive_avatars.core.render.rasterize import _RecordBuffers

        # Each module its own pool: old and new records differ in size, and a pool sized by the
        # other's last call would make a forward run twice.
        pool = _POOLS.setdefault(rk.__name__, _RecordBuffers())

        chunks = numba.get_num_threads()
        while True:
            bufs = pool.take(W * H, len(upto), chunks)
            if "rec_gauss" in record_args:  # kernels before 2026-11-24 recorded exp(power) in float64
                if len(_OLD_RECORD) != len(bufs[0]):
                    _OLD_RECORD.resize(len(bufs[0]), refcheck=False)
                run_bufs = (_OLD_RECORD, bufs[1])
            else:  # kernels before the shared record of nested images took no image bits
                run_bufs = bufs if "rec_img" in record_args else bufs[:2]
            levels = (upto,) if packed else (glevel, upto)
            # training's forward takes no contrib (kernels since 2026-11-27 can leave it out)
            no_contrib = {"contrib": False} if "contrib" in record_args else {}
            image, t_final, last, _, (rec_start, rec_n, used) = rk.raster_forward(
                tile_start, ids, *gaussians_fwd, bg, W, H, tiles_x, *levels, chunks, *run_bufs, **no_contrib
            )
            if pool.learn(used, len(bufs[0]), W * H, len(upto)):
                break
        mark("raster_forward")
        slots = ()
        if hasattr(rk, "backward_slots"):  # kernels that take the per-pair scratch from the caller
            from progressive_avatars.core.render.rasterize import _scratch

            if len(inspect.signature(rk.backward_slots.py_func).parameters) == 2:
                slot_start = rk.backward_slots(tile_start, last)  # last per tile since 2026-11-27
            else:
                slot_start = rk.backward_slots(tile_start, last, W, H, tiles_x)
            slots = (slot_start, _scratch.take(rk.scratch_entries(slot_start, colors.shape[1])))
        # Kernels since 2026-11-24 night take upto (Gaussians of the last image only replay apart).
        levels_bwd = {"upto": upto} if "upto" in inspect.signature(rk.raster_backward.py_func).parameters else {}
        grads, _ = rk.raster_backward(
            tile_start, ids, *gaussians_bwd, bg, t_final, last,
            grad_image, grad_alpha, W, H, tiles_x, *run_bufs, rec_start, rec_n, *slots, **levels_bwd,
        )  # fmt: skip
        pool.give(bufs)
    else:
        image, t_final, last, _ = rk.raster_forward(
            tile_start, ids, xy, conic, opac, cut, colors, rect, bg, W, H, tiles_x, glevel, upto
        )
        mark("raster_forward")
        grads, _ = rk.raster_backward(
            tile_start, ids, xy, conic, opac, cut, colors, rect, bg, t_final, last,
            grad_image, grad_alpha, W, H, tiles_x, glevel, upto,
        )  # fmt: skip
    mark("raster_backward")
    proj_args = (
        means, quats, scales, Rc, tc, fx, fy, lim, eps2d, radii,
        np.ascontiguousarray(grads[:, rk.G_U : rk.G_V + 1]), np.ascontiguousarray(grads[:, rk.G_CA : rk.G_CC + 1]),
        np.zeros(len(means)),
    )  # fmt: skip
    if "g_means" in inspect.signature(rk.project_backward.py_func).parameters:
        # kernels since 2026-11-27 write into the caller's arrays, in the dtype training wants
        g_means, g_quats, g_scales = (np.empty((len(means), k), means.dtype) for k in (3, 4, 3))
        rk.project_backward(*proj_args, g_means, g_quats, g_scales)
    else:
        g_means, g_quats, g_scales = rk.project_backward(*proj_args)
    mark("project_backward")
    g_colors = grads[:, rk.G_COLOR : rk.G_COLOR + colors.shape[1]]
    one = len(upto) == 1 and glevel.max() == 0
    out = dict(image=image[0] if one else image, alpha=1.0 - (t_final[0] if one else t_final), pairs=len(ids))
    out["grads"] = [g_means, g_quats, g_scales, grads[:, rk.G_OPAC], g_colors]
    return times, out


def _reference_errors(rk, seed=1, width=96, height=80, n=1500):
    """Max abs image/alpha error and the worst relative gradient error (norm of the difference
    over the norm, per parameter) of module ``rk``'s pipeline against the dense float64 reference
    on a small head-like scene, loss = sum(image * w) + sum(alpha * w')."""
    import torch

    from progressive_avatars.core.render.reference import render_reference

    cam = head_camera(width, height)
    params = [np.ascontiguousarray(x, np.float64) for x in head_scene(n, seed=seed)]
    params[2] = params[2] * 4.0  # a small image still covered by overlapping Gaussians
    bg = np.array([0.2, 0.5, 0.1])
    rng = np.random.default_rng(seed)
    wi, wa = rng.normal(size=(height, width, 3)), rng.normal(size=(height, width))
    _, out = kernel_pipeline(rk, params + [bg], cam, wi, wa)
    ref = [torch.tensor(x, requires_grad=True) for x in params]
    img, alpha, _ = render_reference(*ref, cam, torch.tensor(bg))
    ((img * torch.tensor(wi)).sum() + (alpha * torch.tensor(wa)).sum()).backward()
    img_err = max(
        float(np.abs(out["image"] - img.detach().numpy()).max()),
        float(np.abs(out["alpha"] - alpha.detach().numpy()).max()),
    )
    grad_err = max(
        float(
            np.linalg.norm(np.asarray(a).ravel() - r.grad.numpy().ravel()) / max(np.linalg.norm(r.grad.numpy()), 1e-30)
        )
        for a, r in zip(out["grads"], ref)
    )
    return img_err, grad_err


def trained_scene(run):
    """(arrays, camera, levels) of a trained run: its Gaussians (float64, background last) as
    training binds them for its first training view, at the dataset's full size, and each
    Gaussian's forest level."""
    import torch

    from bench_train import resumed_trainer

    with resumed_trainer(run) as tr:
        sample = tr.train[0]
        with torch.no_grad():
            g = tr.model.gaussians(tr._vertices(sample), sample.camera.center)
        arrays = [np.ascontiguousarray(g[k].numpy(), np.float64) for k in ("means", "quats", "scales", "opacities")]
        arrays += [np.ascontiguousarray(g["colors"].numpy(), np.float64), np.asarray(tr.background, np.float64)]
        return arrays, sample.camera, np.asarray(tr.model.forest.level, np.int64)


def compare_kernels(commit, width=802, height=550, n=170_000, reps=5, threads=None, run=None, one_image=False):
    """Old (``commit``) and new kernels on the same scene, interleaved rep by rep; per stage the
    min / median wall ms and min CPU ms, plus both against each other and the reference. With
    ``run`` (a trained run folder) the scene is that avatar, every level rendered in one pass (as
    training with every level supervised does), instead of the synthetic head; with ``one_image``
    too, the whole avatar as one image (as inference and a finest-level step render it)."""
    import numba

    from progressive_avatars.core.render import kernels as new_rk

    rev, old_rk = old_kernels(commit)
    numba.set_num_threads(threads or numba.config.NUMBA_NUM_THREADS)
    glevel = None
    if run:
        arrays, cam, glevel = trained_scene(run)
        width, height, n = cam.width, cam.height, len(glevel)
        if one_image:
            glevel = None
    else:
        cam = head_camera(width, height)
        arrays = [np.ascontiguousarray(x, np.float64) for x in head_scene(n)] + [np.zeros(3)]
    n_img = 1 if glevel is None else int(glevel.max()) + 1
    rng = np.random.default_rng(0)
    wi = rng.uniform(0.0, 1.0, size=(n_img, height, width, 3))
    wa = rng.uniform(-1.0, 1.0, size=(n_img, height, width))
    if glevel is None:
        wi, wa = wi[0], wa[0]
    runs = {"old": [], "new": []}
    outs = {}
    for rep in range(reps + 1):  # rep 0 is the warm-up (numba cache load, page faults)
        for name, rk in (("old", old_rk), ("new", new_rk)):
            times, outs[name] = kernel_pipeline(rk, arrays, cam, wi, wa, glevel=glevel)
            if rep:
                runs[name].append(times)
    diff_img = float(np.abs(outs["old"]["image"] - outs["new"]["image"]).max())
    diff_grad = max(
        float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(np.asarray(a)), 1e-30))
        for a, b in zip(outs["old"]["grads"], outs["new"]["grads"])
    )
    ref = {name: _reference_errors(rk) for name, rk in (("old", old_rk), ("new", new_rk))}
    threads = numba.get_num_threads()
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return dict(
        rev=rev, width=width, height=height, n=n, reps=reps, threads=threads, runs=runs,
        pairs={k: v["pairs"] for k, v in outs.items()}, diff_img=diff_img, diff_grad=diff_grad, ref=ref,
        run=run, images=n_img, one_image=bool(run and one_image),
    )  # fmt: skip


def kernels_section(results, command) -> str:
    """The Markdown section of compare_kernels' results, one table per thread count."""
    import numba

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    r = results[0]
    scene = "scripts/bench_render.py's head"
    images = "one image"
    kind = ""
    if r.get("run"):
        scene = f"the trained avatar of `{os.path.relpath(r['run'], ROOT)}` bound for its first training view"
        images = f"every level at once ({r['images']} nested images, one pass, as with every level supervised)"
        kind = ", every level"
        if r.get("one_image"):
            images = "the whole avatar as one image (as inference and a finest-level step render it)"
            kind = ", trained avatar"
    lines = [
        f"## Rasteriser kernels{kind}: {r['rev']} (old) against this tree (new), same run",
        "",
        f"- date: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- command: `{command}`",
        f"- machine: {machine()}, {platform.platform()}, numba {numba.__version__} ({numba.threading_layer()})",
        f"- load average when written: {load} (2 cores shared with other jobs: above 2, others competed for "
        "the cores; compare old with new, which ran interleaved rep by rep, rather than absolute times)",
        f"- scene: {scene}, {r['width']}x{r['height']}, {r['n']:,} Gaussians; the kernels "
        f"called directly in float64 as core/render/rasterize.py calls them (no torch); {images}; loss weights "
        f"random; {r['reps']} reps after a warm-up; tile-Gaussian pairs old {r['pairs']['old']:,}, new "
        f"{r['pairs']['new']:,}",
        "- old = core/render/kernels.py at that commit (`git show`), imported as its own module in the same process",
        "- pack_splats: splat_rows and pack_splats, the packed per-Gaussian rows the tile kernels read since c0bb2c0; "
        "kernels before that have no such stage (0 ms) and read the per-Gaussian arrays of project_forward",
        "- raster_forward: without the per-Gaussian alpha*T sums (contrib) where the kernels can leave them out "
        "(since 2026-11-27), as training calls them; older kernels always summed them",
    ]
    for r in results:

        def col(name, stage, wall=True):
            at = 0 if wall else 1
            return [t[stage][at] if stage != "total" else sum(v[at] for v in t.values()) for t in r["runs"][name]]

        def ratio(name):
            return sum(col(name, "total", False)) / sum(col(name, "total"))

        lines += [
            "",
            f"### numba threads: {r['threads']}",
            "",
            f"Cores this process got (process CPU time over wall time, all reps): old {ratio('old'):.2f}, new "
            f"{ratio('new'):.2f} (1 = one core's worth).",
            "",
            "| stage | old wall ms (min / median) | new wall ms (min / median) | speed-up (median) "
            "| old / new CPU ms (min) |",
            "|---|---|---|---|---|",
        ]
        for stage in STAGES + ["total"]:
            o, n = col("old", stage), col("new", stage)
            co, cn = col("old", stage, False), col("new", stage, False)
            lines.append(
                f"| {stage} | {min(o):.1f} / {np.median(o):.1f} | {min(n):.1f} / {np.median(n):.1f} "
                f"| x{np.median(o) / max(np.median(n), 1e-9):.2f} | {min(co):.1f} / {min(cn):.1f} |"
            )
    (oi, og), (ni, ng) = r["ref"]["old"], r["ref"]["new"]
    lines += [
        "",
        f"Old against new on this scene: max abs image difference {max(x['diff_img'] for x in results):.1e}, "
        f"worst relative gradient difference {max(x['diff_grad'] for x in results):.1e}. Against the dense "
        "float64 reference (core/render/reference.py; 96x80, 1,500 Gaussians, scales x4, background "
        f"(0.2, 0.5, 0.1)): max abs image/alpha error old {oi:.1e}, new {ni:.1e}; worst relative gradient "
        f"error (means, quats, scales, opacities, colours) old {og:.1e}, new {ng:.1e} (bounds of issue 18: "
        "1e-5 and 1e-3).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    args = _bootstrap.script_args()
    if "--against" in args:
        commit = args[args.index("--against") + 1]
        reps = int(args[args.index("--reps") + 1]) if "--reps" in args else 5
        cmd = "python scripts/bench_render.py " + " ".join(args)
        threads = args[args.index("--threads") + 1] if "--threads" in args else "1,2"
        run = args[args.index("--run") + 1] if "--run" in args else None
        one_image = "--one-image" in args
        if one_image and run is None:
            _sys.exit("bench_render: --one-image needs --run RUN (the synthetic head is one image already)")
        results = [
            compare_kernels(commit, reps=reps, threads=int(t), run=run, one_image=one_image) for t in threads.split(",")
        ]
        text = kernels_section(results, cmd)
        if "--out" in args:
            with open(args[args.index("--out") + 1], "w") as fh:
                fh.write(text + "\n")
        print(text)
    else:
        print(run(quick="--quick" in args))
