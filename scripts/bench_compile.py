"""What a machine's first training of a version waits for: numba compiling the kernels.

    python scripts/bench_compile.py [--quick]

`run()` trains the tiny preset for a few iterations on a small temporary dataset three times,
each in a fresh process: with an empty numba cache (what a new machine, a new version or a
new Blender extension install runs), then with the cache that run filled, then again. The
difference is the compilation the first run's first iteration does (its progress line says
so: trainer.kernels_uncached).
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time

import os as _os
import sys as _sys

_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap

from bench_common import header, load_average


def _train(data: str, out: str, cache: str, iterations: int) -> tuple[float, str]:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    cmd = [sys.executable, os.path.join(_bootstrap.ROOT, "scripts", "train.py"), "--data", data, "--out", out]
    cmd += ["--preset", "tiny", "--iterations", str(iterations), "--overwrite"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"train.py failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return seconds, proc.stderr


def run(quick: bool = False) -> str:
    from progressive_avatars.core.synthetic import dataset

    iterations = 6
    load0 = load_average()
    with tempfile.TemporaryDirectory(prefix="pa_bench_compile_") as tmp:
        data = os.path.join(tmp, "data")
        dataset.make_dataset(data, progress=False, resolution=64, cameras=4, sequences=2, frames=2)
        cache = os.path.join(tmp, "numba_cache")
        os.makedirs(cache)
        rows = []
        for name in ("empty cache (first run)", "cache filled by the first run", "again"):
            seconds, err = _train(data, os.path.join(tmp, "run"), cache, iterations)
            rows.append((name, seconds, "compiling the kernels" in err))
            if quick:
                break
    command = f"python scripts/train.py --data DIR --out RUN --preset tiny --iterations {iterations} (NUMBA_CACHE_DIR)"
    lines = [
        header("First-run kernel compilation", "python scripts/bench_compile.py" + (" --quick" if quick else "")),
        f"Each row: `{command}` in a fresh process on a 64-px, 4-camera synthetic dataset; the first with an "
        "empty numba cache, as on a new machine, after an upgrade or in a newly installed Blender extension "
        "(its processes keep their own cache). Wall seconds include starting Python, importing torch and "
        'loading the dataset. The progress line says "compiling the kernels" only when they are not cached.',
        "",
        f"Load average (1 / 5 / 15 min) at the start: {load0}; at the end: {load_average()} (2 cores: other work "
        "on the machine slows every row).",
        "",
        "| numba cache | wall s | progress line says it compiles |",
        "|---|---|---|",
    ]
    lines += [f"| {name} | {s:.1f} | {'yes' if said else 'no'} |" for name, s, said in rows]
    if len(rows) > 1:
        warm = min(s for _, s, _ in rows[1:])
        lines += [
            "",
            f"Compilation on the first run: about {rows[0][1] - warm:.0f} s (first row minus the fastest other).",
        ]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the empty-cache run only")
    args = ap.parse_args(_bootstrap.script_args(argv))
    print(run(quick=args.quick))
    return 0


if __name__ == "__main__":
    sys.exit(main())
