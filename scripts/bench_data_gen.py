"""Benchmark of synthetic dataset generation (core/synthetic/dataset.py).

    python scripts/bench_data_gen.py [--quick]

`run(quick=False)` generates the default dataset (10 sequences x 8 frames x 16 cameras at
88x128, 2x2 samples per pixel) into a temporary directory and returns a Markdown section;
quick=True generates a small one (2 sequences x 2 frames x 4 cameras at 64 px).
"""

import argparse
import datetime
import os
import sys
import tempfile
import time

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap

from bench_common import machine
from progressive_avatars.core.synthetic import dataset, surface


def run(quick: bool = False) -> str:
    config = (
        dict(resolution=64, cameras=4, sequences=2, frames=2)
        if quick
        else dict(resolution=128, cameras=16, sequences=10, frames=8)
    )
    command = "python scripts/make_synthetic.py --out DIR " + " ".join(f"--{k} {v}" for k, v in config.items())
    with tempfile.TemporaryDirectory(prefix="pa_bench_synth_") as tmp:
        t0 = time.perf_counter()
        surface.head_template()  # build (or reuse) the template outside the timed generation
        t_template = time.perf_counter() - t0
        s = dataset.make_dataset(os.path.join(tmp, "ds"), progress=False, **config)
    lines = [
        "## Synthetic dataset generation" + (" (quick)" if quick else ""),
        "",
        f"- machine: {machine()}",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `{command}`",
        "",
        "| images | size | samples/pixel | mesh faces | template build | generation | rays | rays/s | intersector |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {s['images']} | {s['width']}x{s['height']} | {s['supersample']}x{s['supersample']} | {s['faces']} "
        f"| {t_template:.2f} s | {s['seconds']:.1f} s | {s['rays'] / 1e6:.1f} M | {s['rays_per_second'] / 1e6:.2f} M "
        f"| {s['intersector']} |",
        "",
    ]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description="benchmark synthetic dataset generation")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(_bootstrap.script_args(argv))
    print(run(quick=args.quick))
    return 0


if __name__ == "__main__":
    sys.exit(main())
