"""Generation time of the paper-scale synthetic dataset, measured on a reduced version.

    python scripts/bench_data_gen_paper.py

`make_synthetic.py --preset paper` writes 640 images of 550x802 (16 cameras x 10 sequences x 4
frames) from a 131k-face surface. This builds that surface and generates 2 timesteps x 2
cameras at the full size in one process, measures CPU seconds (all threads) for the build and
per image, and extrapolates to the preset: build + per-image CPU x 640 / 2 workers. CPU time is
used because the wall time of a shared machine depends on what else runs; the load average at
the start is given.
"""

import datetime
import os
import sys
import tempfile
import time

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap  # noqa: F401

from bench_common import machine
from progressive_avatars.core.synthetic import dataset, surface

PRESET_IMAGES = 16 * 10 * 4
WORKERS = 2


def _cpu():
    t = os.times()
    return t.user + t.system


def run(quick: bool = False) -> str:
    load = os.getloadavg()[0]
    surface._paper_cached.cache_clear()
    c0, w0 = _cpu(), time.perf_counter()
    tv, tf, fv, ff = surface.paper_head()
    build_cpu, build_wall = _cpu() - c0, time.perf_counter() - w0
    cameras, frames = 2, 1
    with tempfile.TemporaryDirectory(prefix="pa_bench_paper_") as tmp:
        c0, w0 = _cpu(), time.perf_counter()
        s = dataset.make_dataset(
            os.path.join(tmp, "ds"),
            resolution=802,
            cameras=cameras,
            sequences=2,
            frames=frames,
            progress=False,
            detail="paper",
        )
        gen_cpu, gen_wall = _cpu() - c0, time.perf_counter() - w0
    per_image = gen_cpu / s["images"]
    estimate = build_cpu + per_image * PRESET_IMAGES / WORKERS
    lines = [
        "## Paper-scale synthetic dataset generation (measured on a reduced version, extrapolated)",
        "",
        f"- machine: {machine()}; load average at the start {load:.1f} (other work shares the cores)",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        "- command: `python scripts/bench_data_gen_paper.py`",
        f"- template {len(tf):,} faces / {len(tv):,} vertices; imaged surface {len(ff):,} faces; "
        f"{s['width']}x{s['height']} px, {s['supersample']}x{s['supersample']} samples/pixel, {s['intersector']}",
        "",
        "| part | CPU s | wall s |",
        "|---|---|---|",
        f"| surface build (once) | {build_cpu:.1f} | {build_wall:.1f} |",
        f"| {s['images']} images ({s['timesteps']} timesteps x {cameras} cameras, with detail.npz and PNGs) "
        f"| {gen_cpu:.1f} | {gen_wall:.1f} |",
        f"| per image | {per_image:.2f} | |",
        "",
        f"Estimate for `make_synthetic.py --preset paper` ({PRESET_IMAGES} images, {WORKERS} worker processes on 2 "
        f"idle cores): {build_cpu:.0f} s + {per_image:.2f} s x {PRESET_IMAGES} / {WORKERS} = **{estimate / 60:.1f} min** "
        "(the build is not parallel; two workers on two cores are assumed not to slow each other).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    print(run())
    sys.exit(0)
