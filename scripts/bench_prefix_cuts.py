"""Training step with and without in-level prefixes (--prefix-cuts), on a trained avatar.

    python scripts/bench_prefix_cuts.py [--run runs/p16_pcw5] [--data runs/synthetic] [--reps 20] [--write]

Two trainers resume the same checkpoint (copied to temporary folders; the run is not touched):
the cpu preset as it is (no in-level prefixes) and the same with --prefix-cuts 2 --prefix-cut-weight
0.5 (the setting of runs/p16_pcw5). Their
steps alternate, so the machine's load hits both alike; the iteration counter is held off the
ranking iterations, whose cost (the per-level importance on rank_views training views, every
rank_every iterations and after each growth step) is timed on its own. The run is made with
`python scripts/train.py --data runs/synthetic --out runs/p16_pcw5 --preset cpu --prefix-cuts 2
--prefix-cut-weight 0.5`. --write puts
the section into docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401
from bench_common import header, load_average, replace_section  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run(run_dir: str, data: str, reps: int) -> str:
    from bench_train import step_with, train_config

    from progressive_avatars.core.train import trainer as train_mod
    from progressive_avatars.core.train.trainer import Trainer, config_for

    ckpt = os.path.join(run_dir, "checkpoint.npz")
    if not os.path.isfile(ckpt):
        raise FileNotFoundError(f"{ckpt}: no checkpoint (train the run first, see this script's docstring)")
    preset = config_for("cpu")
    trainers, scratch = {}, []
    for name, cuts in (("without (the preset)", 0), ("with (--prefix-cuts 2 --prefix-cut-weight 0.5)", 2)):
        d = tempfile.mkdtemp(prefix="bench_cuts_")
        scratch.append(d)
        shutil.copy(ckpt, d)
        tr = Trainer(data, d, train_config(run_dir, train_mod)[1], resume=True, check_data=False)
        step_with(tr, train_mod, prefix_cuts=cuts, prefix_cut_weight=0.5, eval_every=10**9, checkpoint_every=10**9)
        tr.step()  # warm-up (the cut trainer also ranks here)
        trainers[name] = tr
    start = next(iter(trainers.values())).iteration
    off_rank = start + 1 if (start + 1) % preset.rank_every else start + 2
    times = {k: [] for k in trainers}
    load0 = load_average()
    for _ in range(reps):
        for k, tr in trainers.items():
            tr.iteration = off_rank
            w, c = time.perf_counter(), time.process_time()
            tr.step()
            times[k].append(((time.perf_counter() - w) * 1e3, (time.process_time() - c) * 1e3))
    cut = trainers[list(trainers)[1]]
    rank_ms = []
    for _ in range(3):
        w = time.perf_counter()
        cut._rank(measure=True)
        rank_ms.append((time.perf_counter() - w) * 1e3)
    for d in scratch:
        shutil.rmtree(d, ignore_errors=True)
    f = cut.model.forest
    lines = [
        header(
            "Training step with in-level prefixes (issue 16)",
            f"python scripts/bench_prefix_cuts.py --run {os.path.relpath(run_dir, ROOT)} "
            f"--data {os.path.relpath(data, ROOT)} --reps {reps}",
        ),
        f"- avatar: the checkpoint of `{os.path.relpath(run_dir, ROOT)}` ({f.num_faces:,} faces, levels "
        f"{f.level_counts().tolist()}), cpu preset (every level supervised)",
        f"- load average (1 / 5 / 15 min) at the start: {load0}; at the end: {load_average()} (2 cores: above 2, "
        "other work competed; compare the two rows, which ran interleaved)",
        "",
        "| step | wall ms (min / median) | CPU ms (median) |",
        "|---|---|---|",
    ]
    med = {}
    for k, v in times.items():
        a = np.array(v)
        med[k] = float(np.median(a[:, 0]))
        lines.append(f"| {k} | {a[:, 0].min():.1f} / {med[k]:.1f} | {np.median(a[:, 1]):.1f} |")
    a, b = med.values()
    lines += [
        "",
        f"In-level prefixes cost x{b / a:.2f} per step; measuring their order (importance per level on "
        f"{preset.rank_views} training views) takes {min(rank_ms):.0f} ms, once every {preset.rank_every} "
        f"iterations and after each growth step ({min(rank_ms) / preset.rank_every:.1f} ms per iteration). "
        "What they buy is in the issue 16 sections (budgets against the runs trained without them).",
    ]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default=os.path.join(ROOT, "runs", "p16_pcw5"))
    ap.add_argument("--data", default=os.path.join(ROOT, "runs", "synthetic"))
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    text = run(os.path.abspath(args.run), os.path.abspath(args.data), args.reps)
    print(text)
    if args.write:
        replace_section(os.path.join(ROOT, "docs", "BENCHMARKS.md"), "prefix_cuts", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
