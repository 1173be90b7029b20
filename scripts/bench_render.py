"""Benchmark of the CPU rasteriser: forward/backward time and peak memory on head-like scenes,
and time/error against the dense float64 reference of the tests.

    python scripts/bench_render.py [--quick]

``run(quick=False)`` returns the Markdown section the script prints.
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
import platform  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


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
        return ps, render(*ps, cam)

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
        f"- machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} logical CPUs, numba {numba.__version__} with {numba.get_num_threads()} threads "
        f"({numba.threading_layer()}), torch {torch.__version__}, Python {platform.python_version()}",
        "- scene: Gaussians on an ellipsoid (semi-axes 85/110/95 mm) at ~1 m, scales 1-3 mm (one axis "
        "x0.2), opacity U(0.2, 0.98), float32 tensors; times are the best of several runs after a warm-up "
        f"(OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')})",
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


if __name__ == "__main__":
    print(run(quick="--quick" in _bootstrap.script_args()))
