"""Whole cpu-preset training runs: f6907ae (before issue 18) against this tree, side by side.

    python scripts/bench_train_run.py [--data runs/synthetic] [--iterations N] [--seeds 0,1,2] [--work DIR] [--write]

scripts/bench_train.py times single iterations from a fixed state; this trains the cpu preset
from scratch to the end with each code, so growth, evaluation and the validation PSNR it
reaches come in too (issue 18: "the cpu preset reaches the same validation PSNR (± 0.1 dB) as
before"). The runs start together, one thread each (torch and numba). The speed-up is taken
from process CPU time per iteration: the runs do not end together (the faster ones leave the
slower more of the machine), and CPU time, unlike wall time, does not count waiting for a core.

Runs: `f6907ae` (the old core/ from git, its own Trainer and cpu preset), `this tree`
(scripts/train.py --preset cpu, coarse levels on as shipped) and `this tree, no coarse
levels` (--no-coarse: the same level structure as f6907ae's). Reported per run: process CPU
time per iteration (the whole command: imports, evaluation and checkpoints included), the
trainer's own clock per iteration (render, backward, Adam, growth; wall time, so it counts
waiting for a core), wall time of the whole command, peak memory, Gaussians, and the
validation PSNR (the trainer's evaluation: the same 8 validation views in both codes) after
the last iteration and the mean of the last three evaluations. Training is chaotic (one seed
against another moves the validation PSNR by about 0.1 dB), so --seeds runs the three side by
side once per seed and the section gives each seed's rows and the mean ± sd of the differences.
--write puts the section into docs/BENCHMARKS.md between its markers.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401
from bench_common import header, load_average, replace_section  # noqa: E402
from bench_train import OLD_COMMIT, OLD_DIR, old_package  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TRAIN = os.path.join(ROOT, "scripts", "train.py")
SECTION = "train-run"
_OLD_MAIN = (
    "import sys; sys.path.insert(0, sys.argv[1]); import torch; torch.set_num_threads(1); "
    "from pa_old.core.train import Trainer, config_for; "
    "cfg = config_for('cpu', iterations=int(sys.argv[4]) or None, seed=int(sys.argv[5])); "
    "Trainer(sys.argv[2], sys.argv[3], cfg).run(progress=False)"
)


def _commands(data: str, work: str, iterations: int, seed: int) -> dict:
    """name -> (command, run folder)."""
    new = [sys.executable, TRAIN, "--data", data, "--preset", "cpu", "--threads", "1", "--no-progress"]
    new += ["--seed", str(seed)]
    if iterations:
        new += ["--iterations", str(iterations)]
    outs = {k: os.path.join(work, k) for k in ("old", "new", "new_nocoarse")}
    return {
        OLD_COMMIT: (
            [sys.executable, "-c", _OLD_MAIN, OLD_DIR, data, outs["old"], str(iterations), str(seed)],
            outs["old"],
        ),
        "this tree": (new + ["--out", outs["new"]], outs["new"]),
        "this tree, no coarse levels": (new + ["--out", outs["new_nocoarse"], "--no-coarse"], outs["new_nocoarse"]),
    }


def _summary(out: str) -> dict:
    rows = [json.loads(line) for line in open(os.path.join(out, "metrics.jsonl"))]
    last = max((r for r in rows if "seconds" in r), key=lambda r: r["iteration"])
    evals = [r for r in rows if "val_psnr" in r]
    tail = [r["val_psnr"] for r in evals[-3:]]
    return {
        "iterations": last["iteration"],
        "s_per_it": last["seconds"] / last["iteration"],
        "val_psnr": evals[-1]["val_psnr"],
        "val_tail": sum(tail) / len(tail),
        "faces": next(r["faces"] for r in reversed(rows) if "faces" in r),
    }


def _run_seed(data: str, iterations: int, work: str, seed: int) -> dict:
    """Trains the three runs of one seed side by side; name -> summary."""
    for sub in ("old", "new", "new_nocoarse"):  # fresh runs: a trainer would resume or refuse
        shutil.rmtree(os.path.join(work, sub), ignore_errors=True)
    os.makedirs(work, exist_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1", MKL_NUM_THREADS="1")
    runs = _commands(data, work, iterations, seed)
    procs = {}
    results = {}
    try:
        for name, (cmd, out) in runs.items():
            log = open(os.path.join(work, os.path.basename(out) + ".log"), "w")
            procs[name] = (
                subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT),
                time.time(),
                log,
            )
        while procs:
            pid, status, usage = os.wait4(-1, 0)
            name = next((k for k, v in procs.items() if v[0].pid == pid), None)
            if name is None:
                continue
            proc, t0, log = procs.pop(name)
            proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
            log.close()
            if proc.returncode != 0:
                raise RuntimeError(f"{name} (seed {seed}) failed ({proc.returncode}): see {log.name}")
            results[name] = dict(
                _summary(runs[name][1]),
                wall=time.time() - t0,
                cpu=usage.ru_utime + usage.ru_stime,
                rss_mb=usage.ru_maxrss / 1024,
            )
    finally:  # a failed or interrupted benchmark leaves no training behind
        for proc, _, log in procs.values():
            proc.kill()
            proc.wait()
            log.close()
    return {name: results[name] for name in runs}


def _mean_sd(values) -> str:
    v = np.asarray(values, float)
    sd = f" ± {v.std(ddof=1):.2f}" if len(v) > 1 else ""
    return f"{v.mean():+.2f}{sd}"


def run(data: str, iterations: int, work: str, seeds=(0,)) -> str:
    if not os.path.isfile(os.path.join(data, "transforms_train.json")):
        raise SystemExit(f"{data}: no dataset there (make one with scripts/make_synthetic.py --out {data})")
    old_package()  # the f6907ae tree, extracted once
    load0 = load_average()
    by_seed = {}
    for seed in seeds:
        by_seed[seed] = _run_seed(data, iterations, work, seed)
        print(f"seed {seed} done", file=sys.stderr)
    load1 = load_average()
    cmd = "python scripts/bench_train_run.py" + (f" --iterations {iterations}" if iterations else "")
    if list(seeds) != [0]:
        cmd += " --seeds " + ",".join(map(str, seeds))
    if os.path.abspath(data) != os.path.join(ROOT, "runs", "synthetic"):
        cmd += f" --data {os.path.relpath(data, ROOT)}"
    lines = [
        header("Whole cpu-preset runs: f6907ae against this tree (issue 18)", cmd),
        f"- load average (1/5/15 min) {load0} at the start, {load1} at the end, on {os.cpu_count()} cores; "
        "the three runs of a seed start together, one thread each; the seeds run one after another",
        f"- data: `{os.path.relpath(data, ROOT)}`; seeds {', '.join(map(str, seeds))}; f6907ae = "
        f"`git archive {OLD_COMMIT} core` run by its own Trainer with its own cpu preset and the same seed",
        "- CPU ms/it: process CPU time of the whole command (imports, evaluation, checkpoints included) per "
        "iteration; the speed-up is the ratio of these (the runs end at different times, so their wall "
        "times saw different loads). Trainer ms/it: the trainer's wall clock (render, backward, Adam, "
        "growth; not evaluation or checkpoints)",
        "- val PSNR: the trainer's evaluation (the same 8 validation views in both codes) after the last "
        "iteration, and the mean of the last three evaluations; Δ: against f6907ae of the same seed",
        "",
        "| seed | run | iterations | Gaussians | CPU ms/it | speed-up (CPU) | trainer ms/it | wall s | peak MB | "
        "val PSNR | Δ vs f6907ae | val PSNR, last 3 | Δ last 3 vs f6907ae |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    stats = {}
    for seed, results in by_seed.items():
        base = results[OLD_COMMIT]
        base_it = base["cpu"] / base["iterations"]
        for name, r in results.items():
            cpu_it = r["cpu"] / r["iterations"]
            d_last, d_tail = r["val_psnr"] - base["val_psnr"], r["val_tail"] - base["val_tail"]
            s = stats.setdefault(name, {"speed": [], "last": [], "tail": []})
            s["speed"].append(base_it / cpu_it)
            s["last"].append(d_last)
            s["tail"].append(d_tail)
            lines.append(
                f"| {seed} | {name} | {r['iterations']} | {r['faces']:,} | {cpu_it * 1e3:.1f} | "
                f"x{base_it / cpu_it:.2f} | {r['s_per_it'] * 1e3:.1f} | {r['wall']:.0f} | "
                f"{r['rss_mb']:.0f} | {r['val_psnr']:.2f} | {d_last:+.2f} | {r['val_tail']:.2f} | {d_tail:+.2f} |"
            )
    lines += [
        "",
        f"Over the {len(by_seed)} seed(s) (mean ± sd across seeds):",
        "",
        "| run | speed-up (CPU) | Δ val PSNR vs f6907ae (dB) | Δ last 3 vs f6907ae (dB) |",
        "|---|---|---|---|",
    ]
    for name, s in stats.items():
        if name == OLD_COMMIT:
            continue
        lines.append(f"| {name} | x{np.mean(s['speed']):.2f} | {_mean_sd(s['last'])} | {_mean_sd(s['tail'])} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.join(ROOT, "runs", "synthetic"))
    ap.add_argument("--iterations", type=int, default=0, help="default: the cpu preset's")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds, each a side-by-side triple (default 0)")
    ap.add_argument("--work", default=os.path.join(ROOT, "runs", "bench_train_run"))
    ap.add_argument("--write", action="store_true", help="put the section into docs/BENCHMARKS.md")
    a = ap.parse_args()
    try:
        seeds = [int(x) for x in a.seeds.split(",")]
    except ValueError:
        ap.error(f"--seeds: comma-separated integers, got {a.seeds!r}")
    if min(seeds) < 0 or len(set(seeds)) != len(seeds):
        ap.error(f"--seeds: distinct non-negative integers, got {a.seeds!r}")
    text = run(a.data, a.iterations, a.work, seeds)
    print(text)
    if a.write:
        replace_section(os.path.join(ROOT, "docs", "BENCHMARKS.md"), SECTION, text)


if __name__ == "__main__":
    main()
