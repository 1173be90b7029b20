"""Training step of the default coarse mode (backdrop stand-ins), an older tree against this one.

    python scripts/bench_backdrop_step.py [--run runs/backdrop16/default/backdrop_cuts]
        [--cumulative runs/backdrop16/default/cumulative] [--old 8724d3f] [--reps 30] [--write]

Both trees resume the same checkpoint (copied to temporary folders; the run is not touched)
and step interleaved, rep by rep, so the machine's load hits both alike; the iteration counter
is held off the ranking iterations (their cost is in the section "Training step with in-level
prefixes"). The old tree is ``--old``'s core/, extracted with `git archive` under runs/ and
imported as its own package. A third row steps the cumulative-levels run of the same study
(scripts/run_backdrop_study.sh) with this tree, for the price of the mode itself.

--whole OLD_DIR NEW_DIR adds the training seconds of whole runs (every finished run found in both,
from their metrics logs): the study's default-mode runs trained by the old tree and again by this
one (their quality: the issue 16 sections).

Accuracy kept: the first step of old and new starts from the same state (same checkpoint,
same generator: the same view, levels and cut); the section gives the relative difference of
the loss and of the whole parameter gradient. --write puts the section into docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401
from bench_common import header, load_average, replace_section  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _capture(trainer) -> dict:
    """The parameter gradients of the trainer's next optimiser step (filled when it runs)."""
    got, step = {}, trainer.opt.step

    def capture(params, lr_scale=None):
        if not got:
            got.update(
                {k: p.grad.detach().double().numpy().ravel().copy() for k, p in params.items() if p.grad is not None}
            )
        return step(params, lr_scale)

    trainer.opt.step = capture
    return got


def whole_runs(old_dir: str, new_dir: str, old_commit: str) -> list[str]:
    """Table rows: training seconds of the runs under both folders (same relative paths)."""
    from progressive_avatars.core.evaluate.plots import run_resources

    found = []
    for root, _dirs, files in os.walk(new_dir):
        if "avatar.npz" in files:  # finished
            rel = os.path.relpath(root, new_dir)
            if os.path.isfile(os.path.join(old_dir, rel, "avatar.npz")):
                found.append(rel)
    if not found:
        raise SystemExit(f"--whole: no finished run (avatar.npz) under both {old_dir} and {new_dir}")
    lines = [
        "",
        f"Whole runs (4,000 iterations each, cpu preset): `{os.path.relpath(old_dir, ROOT)}` trained by {old_commit}, "
        f"`{os.path.relpath(new_dir, ROOT)}` by this tree (the same commands); training seconds from the runs' metrics logs (what else "
        "ran on the machine differs between them):",
        "",
        "| run | old s | new s | old / new |",
        "|---|---|---|---|",
    ]
    for rel in sorted(found):
        o, n = (run_resources(os.path.join(d, rel))["train_seconds"] for d in (old_dir, new_dir))
        lines.append(f"| {rel} | {o:.0f} | {n:.0f} | x{o / n:.2f} |")
    return lines


def run(run_dir: str, cumulative: str | None, old_commit: str, reps: int) -> str:
    import contextlib

    from bench_train import prev_trainer, resumed_trainer

    old_mod = prev_trainer(old_commit)
    hold = dict(eval_every=10**9, checkpoint_every=10**9)
    with contextlib.ExitStack() as stack:
        rows = {
            f"old ({old_commit})": stack.enter_context(resumed_trainer(run_dir, old_mod, **hold)),
            "new (this tree)": stack.enter_context(resumed_trainer(run_dir, **hold)),
        }
        caps = {k: _capture(tr) for k, tr in rows.items()}
        new = rows["new (this tree)"]
        own = new.cut_rng  # trees before 5fd8e50 drew the cut from the views' generator: so does this step
        new.cut_rng = new.rng
        first = {k: tr.step() for k, tr in rows.items()}  # the same state: view, levels, cut
        new.cut_rng = own
        (lo, go), (ln, gn) = ((first[k]["loss"], caps[k]) for k in rows)
        names = sorted(set(go) & set(gn))
        g_old, g_new = (np.concatenate([g[n] for n in names]) for g in (go, gn))
        loss_err = abs(ln - lo) / abs(lo)
        grad_err = float(np.linalg.norm(g_new - g_old) / np.linalg.norm(g_old))
        if cumulative:
            rows["new, cumulative levels (no stand-ins)"] = stack.enter_context(resumed_trainer(cumulative, **hold))
        for tr in rows.values():
            tr.step()  # warm-up
        times = {k: [] for k in rows}
        load0 = load_average()
        for _ in range(reps):
            for k, tr in rows.items():
                it = tr.iteration
                tr.iteration = it + 1 if (it + 1) % tr.cfg.rank_every else it + 2
                w, c = time.perf_counter(), time.process_time()
                tr.step()
                times[k].append(((time.perf_counter() - w) * 1e3, (time.process_time() - c) * 1e3))
        f = new.model.forest
        faces = {k: tr.model.num_faces for k, tr in rows.items()}
    rel = lambda p: os.path.relpath(p, ROOT)  # noqa: E731
    cmd = f"python scripts/bench_backdrop_step.py --run {rel(run_dir)} --old {old_commit} --reps {reps}"
    if cumulative:
        cmd += f" --cumulative {rel(cumulative)}"
    lines = [
        header("Training step, backdrop stand-ins (the default coarse mode): old against new", cmd),
        f"- avatar: the checkpoint of `{rel(run_dir)}` ({f.num_faces:,} faces, levels {f.level_counts().tolist()}), "
        f"its own settings (cpu preset, backdrop stand-ins, {new.cfg.backdrop_cuts} cut per step)",
        f"- load average (1 / 5 / 15 min) at the start: {load0}; at the end: {load_average()} (2 cores; the rows "
        "ran interleaved)",
        f"- accuracy kept, first step from the same state: loss relative difference {loss_err:.1e}, parameter "
        f"gradient {grad_err:.1e}",
        "",
        "| step | faces | wall ms (min / median) | CPU ms (median) |",
        "|---|---|---|---|",
    ]
    med = {}
    for k, v in times.items():
        a = np.array(v)
        med[k] = float(np.median(a[:, 0]))
        lines.append(f"| {k} | {faces[k]:,} | {a[:, 0].min():.1f} / {med[k]:.1f} | {np.median(a[:, 1]):.1f} |")
    o, n = med[f"old ({old_commit})"], med["new (this tree)"]
    lines += [
        "",
        f"New against old: x{o / n:.2f} per step. The old step drew four passes (the coarse levels' stand-ins, the "
        "cut, the template level and finer, the whole avatar without stand-ins) and sized the forward's record "
        "from the pass before, so a large pass after a small one ran twice; the new one draws the coarse levels, "
        "the template level and finer and the whole avatar in one pass (render_levels' last_from leaves the "
        "stand-ins out of the last image) beside the cut's own, and shrinks the record's size only slowly.",
    ]
    if cumulative:
        lines[-1] += (
            f" The cumulative run ({faces['new, cumulative levels (no stand-ins)']:,} faces: its streams are "
            "shorter) steps once, one pass."
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default=os.path.join(ROOT, "runs", "backdrop16", "default", "backdrop_cuts"))
    ap.add_argument("--cumulative", default=os.path.join(ROOT, "runs", "backdrop16", "default", "cumulative"))
    ap.add_argument("--old", default="8724d3f")
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--whole", nargs=2, metavar=("OLD_DIR", "NEW_DIR"))
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    for d in (args.run, args.cumulative):
        if d and not os.path.isfile(os.path.join(d, "checkpoint.npz")):
            raise SystemExit(f"{d}: no checkpoint.npz (train it: scripts/run_backdrop_study.sh)")
    text = run(os.path.abspath(args.run), args.cumulative and os.path.abspath(args.cumulative), args.old, args.reps)
    if args.whole:
        old_dir, new_dir = (os.path.abspath(d) for d in args.whole)
        text = text.replace(" --reps ", f" --whole {' '.join(args.whole)} --reps ", 1)
        text += "\n" + "\n".join(whole_runs(old_dir, new_dir, args.old))
    print(text)
    if args.write:
        replace_section(os.path.join(ROOT, "docs", "BENCHMARKS.md"), "backdrop_step", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
