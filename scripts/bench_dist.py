"""Data-parallel training speed: 1 process against 2 torchrun processes, same effective batch.

    python scripts/bench_dist.py [--data runs/synthetic] [--iterations 500] [--reps 2] [--write]

Both configurations train the cpu preset for the same number of iterations with 2 views per
iteration: one process rendering both views (all cores), and `torchrun --nproc-per-node 2`
with one view per process (cores // 2 threads each). The runs alternate (1, 2, 1, 2, ...) so
the machine's load hits both alike. Time per iteration is the trainer's own clock (rank 0:
step, all-reduce, growth; evaluation and checkpoints excluded) over the whole run; wall
seconds include start-up (imports, process group), evaluation and checkpoints. Quality is the
validation PSNR after the last iteration (the trainer's evaluation, eval_views of the preset).
The dataset is made with scripts/make_synthetic.py when absent. --write puts the section into
docs/BENCHMARKS.md (between its markers; the rest of the page is kept).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401
from bench_common import header, load_average, replace_section  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TRAIN = os.path.join(ROOT, "scripts", "train.py")
DEFAULT_DATA = os.path.join(ROOT, "runs", "synthetic")


def _run(cmd: list, out: str) -> dict:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    rows = [json.loads(line) for line in open(os.path.join(out, "metrics.jsonl"))]
    last = rows[-1]
    evals = [r for r in rows if "val_psnr" in r]
    return {
        "s_per_it": last["seconds"] / last["iteration"],
        "wall": wall,
        "val_psnr": evals[-1]["val_psnr"],
        "train_psnr": next(r["train_psnr"] for r in reversed(rows) if "train_psnr" in r),
        "faces": next(r["faces"] for r in reversed(rows) if "faces" in r),
        "world_size": last["world_size"],
    }


def run(data: str, iterations: int, reps: int, work: str) -> str:
    if not os.path.isfile(os.path.join(data, "transforms_train.json")):
        subprocess.run([sys.executable, os.path.join(ROOT, "scripts", "make_synthetic.py"), "--out", data], check=True)
    # --overwrite: a second bench run reuses the run folders of the first (timed from scratch)
    common = ["--data", data, "--preset", "cpu", "--overwrite", "--iterations", str(iterations), "--no-progress"]
    configs = {
        "1 process x 2 views": lambda out: [sys.executable, TRAIN, "--out", out, "--views-per-step", "2", *common],
        "2 processes x 1 view (torchrun, gloo)": lambda out: [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc-per-node",
            "2",
            TRAIN,
            "--out",
            out,
            *common,
        ],
    }
    # Warm-up: numba's compiled kernels cached on disk before anything is timed.
    warm = os.path.join(work, "warmup")
    _run([sys.executable, TRAIN, "--out", warm, *common[:-3], "--iterations", "2", "--no-progress"], warm)
    load0 = load_average()
    results = {name: [] for name in configs}
    for rep in range(reps):  # alternated, so load changes hit both
        for k, (name, make) in enumerate(configs.items()):
            out = os.path.join(work, f"c{k}_r{rep}")
            results[name].append(_run(make(out), out))
    load1 = load_average()
    lines = [
        header(
            "Data-parallel training: 1 process against 2 (torchrun)",
            f"python scripts/bench_dist.py --iterations {iterations} --reps {reps}"
            + ("" if data == DEFAULT_DATA else f" --data {os.path.relpath(data, ROOT)}"),
        ),
        f"- load average (1/5/15 min) {load0} at the start, {load1} at the end, on {os.cpu_count()} cores",
        f"- cpu preset on `{os.path.relpath(data, ROOT)}`, {iterations} iterations, effective batch 2 views "
        "in both rows (growth, seeds and views identical: 2 ranks x 1 view draw the views of 1 process x 2)",
        "- s/it: the trainer's clock on rank 0 (render, backward, all-reduce, Adam, growth; not evaluation "
        "or checkpoints) over the run; min / median over the reps. wall: the whole command (imports, "
        "process group, evaluation, checkpoints), median",
        "- quality: validation PSNR after the last iteration (median over reps; the runs are deterministic)",
        "",
        "| configuration | s/it (min / median) | wall s | val PSNR dB | train PSNR dB | faces |",
        "|---|---|---|---|---|---|",
    ]

    def med(xs):
        xs = sorted(xs)
        return xs[len(xs) // 2]

    for name, rs in results.items():
        s = [r["s_per_it"] for r in rs]
        lines.append(
            f"| {name} | {min(s) * 1000:.0f} / {med(s) * 1000:.0f} ms | {med([r['wall'] for r in rs]):.0f} | "
            f"{med([r['val_psnr'] for r in rs]):.2f} | {med([r['train_psnr'] for r in rs]):.2f} | "
            f"{rs[0]['faces']:,} |"
        )
    a, b = (med([r["s_per_it"] for r in rs]) for rs in results.values())
    pa, pb = (med([r["val_psnr"] for r in rs]) for rs in results.values())
    lines += [
        "",
        f"Speed-up of 2 processes (median s/it): x{a / b:.2f}; validation PSNR difference {pb - pa:+.4f} dB.",
        "",
        "GPU: none was lent to this session; the same command on a CUDA machine measures it there.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=DEFAULT_DATA)
    ap.add_argument("--iterations", type=int, default=500)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--work", default=os.path.join(ROOT, "runs", "bench_dist"))
    ap.add_argument("--write", action="store_true", help="put the section into docs/BENCHMARKS.md")
    ap.add_argument("--note", default="", help="a line added under the header (e.g. about the machine's load)")
    args = ap.parse_args(argv)
    text = run(os.path.abspath(args.data), args.iterations, args.reps, args.work)
    if args.note:
        text += f"\nNote: {args.note}\n"
    print(text)
    if args.write:
        replace_section(os.path.join(ROOT, "docs", "BENCHMARKS.md"), "dist", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
