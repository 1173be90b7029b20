"""Training steps with glibc's default malloc settings against core/train/memory.py's
retain_freed_memory (what scripts/train.py and the add-on's training job set): page faults,
system CPU and wall time per step of a trained paper-scale avatar.

    python scripts/bench_memory.py [--run RUN] [--steps 12] [--rounds 2] [--out FILE]

The malloc settings are process-wide and cannot be undone, so each measurement is its own
process (this script with --probe), the two settings alternating round by round. Put the
section into docs/BENCHMARKS.md with `scripts/bench.py --only none --section memory=FILE`.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sys as _sys

_sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SETTINGS = ("glibc defaults", "retain_freed_memory")


def probe(run: str, supervision: str, steps: int, retain: bool) -> dict:
    """In this process: optionally retain freed memory, resume ``run`` and time ``steps`` steps
    (after two warm-up steps) under ``supervision``."""
    if retain:
        from progressive_avatars.core.train.memory import retain_freed_memory

        if not retain_freed_memory():
            raise SystemExit("bench_memory: retain_freed_memory had no effect here (not glibc)")
    import bench_train
    from progressive_avatars.core.train import trainer as train_mod

    def usage():
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_minflt, r.ru_utime, r.ru_stime

    rows = {"wall": [], "faults": [], "user": [], "sys": []}
    with bench_train.resumed_trainer(run, supervision=supervision) as tr:
        tr.train = bench_train._Views(tr.data_dir, train_mod, tr.train[0].camera.height)
        tr.step()
        tr.step()
        for _ in range(steps):
            a, t = usage(), time.perf_counter()
            tr.step()
            b = usage()
            rows["wall"].append((time.perf_counter() - t) * 1e3)
            rows["faults"].append(b[0] - a[0])
            rows["user"].append((b[1] - a[1]) * 1e3)
            rows["sys"].append((b[2] - a[2]) * 1e3)
    rows["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return rows


def measure(run: str, supervision: str, steps: int, rounds: int) -> dict:
    """Both settings, alternating, each round in fresh processes; the rows of all rounds pooled."""
    pooled = {name: {"wall": [], "faults": [], "user": [], "sys": [], "peak_rss_mb": []} for name in SETTINGS}
    for _ in range(rounds):
        for name in SETTINGS:
            cmd = [sys.executable, os.path.abspath(__file__), "--probe", "--run", run]
            cmd += ["--supervision", supervision, "--steps", str(steps)]
            cmd += ["--retain"] if name == SETTINGS[1] else []
            out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
            if out.returncode != 0:
                raise RuntimeError(f"bench_memory probe failed ({name}):\n{out.stderr[-2000:]}")
            rows = json.loads(out.stdout.strip().splitlines()[-1])
            for key in ("wall", "faults", "user", "sys"):
                pooled[name][key] += rows[key]
            pooled[name]["peak_rss_mb"].append(rows["peak_rss_mb"])
    return pooled


def section(results: dict, run: str, steps: int, rounds: int, command: str) -> str:
    from bench_common import machine

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lines = [
        "## Freed memory kept by training processes",
        "",
        f"- date: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- command: `{command}`",
        f"- machine: {machine()}",
        f"- load average when written: {load} (2 cores)",
        f"- steps: `Trainer.step()` of the trained avatar `{os.path.relpath(run, ROOT)}` (its checkpoint, views "
        f"preloaded), {steps} steps after two warm-up steps per process, {rounds} processes per setting, "
        "the settings alternating; per step: minor page faults, system and user CPU (both threads), wall",
        "- glibc defaults: blocks from 128 kB (a threshold glibc raises as large blocks are freed) are mapped "
        "fresh from the kernel and returned on free; retain_freed_memory (core/train/memory.py, set by "
        "scripts/train.py and core/train/jobs.py): blocks up to 32 MB from the heap, up to 512 MB of freed "
        "memory kept for reuse",
        "",
        "| supervision | malloc | page faults / step (mean) | system CPU ms / step | user CPU ms / step | "
        "wall ms (min / median) | peak RSS MB |",
        "|---|---|---|---|---|---|---|",
    ]
    for sup, pooled in results.items():
        for name in SETTINGS:
            r = pooled[name]
            lines.append(
                f"| {sup} | {name} | {np.mean(r['faults']):,.0f} | {np.mean(r['sys']):.0f} | {np.mean(r['user']):.0f} "
                f"| {np.min(r['wall']):.0f} / {np.median(r['wall']):.0f} | {max(r['peak_rss_mb']):,.0f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", help="trained paper-scale run (default: the newest runs/paper*/adaptive)")
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--supervision", default=None, help="one supervision (default: sampled and all)")
    ap.add_argument("--out")
    ap.add_argument("--probe", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--retain", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(_bootstrap.script_args() if argv is None else argv)
    if args.steps < 1 or args.rounds < 1:
        ap.error("--steps and --rounds must be at least 1")
    import bench_train

    run = args.run or bench_train.trained_run()
    if run is None or not os.path.isfile(os.path.join(run, "checkpoint.npz")):
        ap.error(
            f"no trained run with a checkpoint ({run or 'runs/paper*/adaptive'}): train one with --preset paper-cpu"
        )
    if args.probe:
        print(json.dumps(probe(run, args.supervision or "sampled", args.steps, args.retain)))
        return 0
    sups = [args.supervision] if args.supervision else ["sampled", "all"]
    results = {sup: measure(run, sup, args.steps, args.rounds) for sup in sups}
    text = section(
        results,
        run,
        args.steps,
        args.rounds,
        "python scripts/bench_memory.py " + " ".join(argv or _bootstrap.script_args()),
    )
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
