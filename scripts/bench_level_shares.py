"""Where a trained avatar's image comes from, level by level.

    python scripts/bench_level_shares.py --data runs/synthetic_paper --run 'multi-level=runs/paper8/adaptive'
        [--run NAME=DIR ...] [--views 8] [--about TEXT] [--write]

For each run and each forest level (inner faces and leaves apart): how many Gaussians, their
share of the whole avatar's alpha*T summed over evenly spread held-out views (the paper's
importance, core/render/importance.py), the median projected size (largest standard deviation
in pixels, median over those views) and the fraction whose opacity is below 0.1. A prefix that
stops at level l keeps only what levels 0..l carry: where the deep levels carry little, a
finest-level-only avatar loses little at a mid-stream cut whatever its coarse levels learned
(issue 17's "without multi-level supervision" row). --write puts the section into
docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401
from bench_common import header, replace_section  # noqa: E402

TITLE = "Where the image comes from, level by level (issue 17)"


def level_rows(avatar, dataset, views: int) -> list[dict]:
    from progressive_avatars.core.avatar.avatar import sigmoid
    from progressive_avatars.core.render.importance import face_importance, view_subset

    W = face_importance(avatar, dataset, max_views=views, progress=False, per_level=False, weighting="alpha")
    evaluator = avatar.evaluator()
    sigma_px = []
    for i in view_subset(len(dataset), views):
        info = dataset.frame_info(int(i))
        means, _, scales = evaluator(dataset.vertices_at(info.timestep_index))
        cam = info.camera
        depth = (means @ np.asarray(cam.R, np.float64).T + np.asarray(cam.t, np.float64))[:, 2]
        sigma_px.append(scales.max(1) * cam.fx / np.maximum(depth, 1e-9))
    sigma_px = np.median(np.stack(sigma_px), axis=0)
    opacity = sigmoid(avatar.opacity_logit.ravel())
    forest = avatar.forest
    total = W.sum()
    rows = []
    for lv in range(forest.max_level + 1):
        for leaf in (False, True):
            sel = (forest.level == lv) & (forest.is_leaf() == leaf)
            if sel.any():
                rows.append(
                    dict(
                        level=lv,
                        depth=lv - forest.num_coarse_levels,
                        leaf=leaf,
                        n=int(sel.sum()),
                        share=float(W[sel].sum() / total),
                        sigma_px=float(np.median(sigma_px[sel])),
                        faint=float(np.mean(opacity[sel] < 0.1)),
                    )
                )
    return rows


def section(runs: dict, data: str, views: int, about: str, command: str) -> str:
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.io.dataset import Dataset

    dataset = Dataset(data, "val", cache_images=0)
    cam = dataset.frame_info(0).camera
    out = [header(TITLE, command)]
    out.append(
        f"Held-out views of `{data}` ({cam.width}x{cam.height} px), {views} spread views. Share: the level's part of "
        "the whole avatar's alpha*T summed over those views (what a prefix without it loses in coverage terms). "
        "Sigma: the Gaussians' largest standard deviation projected to pixels, median over views then over the "
        "level. Faint: opacity below 0.1. Depth: subdivision depth below the template (negative: coarse levels)."
    )
    if about:
        out.append(about)
    for name, run in runs.items():
        avatar = Avatar.load(os.path.join(run, "avatar.npz"))
        rows = level_rows(avatar, dataset, views)
        out.append(f"### {name} (`{run}`, {avatar.num_gaussians:,} Gaussians)")
        table = [
            "| level | depth | faces | Gaussians | share of alpha*T | cumulative share | sigma px (median) | faint |",
            "|---|---|---|---|---|---|---|---|",
        ]
        cum = 0.0
        for r in rows:
            cum += r["share"]
            table.append(
                f"| {r['level']} | {r['depth']} | {'leaves' if r['leaf'] else 'inner'} | {r['n']:,} | "
                f"{r['share']:.3f} | {cum:.3f} | {r['sigma_px']:.2f} | {r['faint']:.2f} |"
            )
        out.append("\n".join(table))
        deep = [r for r in rows if r["depth"] >= 3]
        if deep:
            n = sum(r["n"] for r in deep)
            out.append(
                f"Depth 3 and deeper: {n:,} Gaussians ({n / avatar.num_gaussians:.0%} of the stream), "
                f"{sum(r['share'] for r in deep):.3f} of alpha*T."
            )
    return "\n\n".join(out) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--run", action="append", required=True, metavar="NAME=DIR")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--about", default="")
    ap.add_argument("--write", action="store_true", help="replace the section in docs/BENCHMARKS.md")
    args = ap.parse_args(_bootstrap.script_args() if argv is None else argv)
    runs = {}
    for spec in args.run:
        name, sep, run = spec.partition("=")
        if not sep or not os.path.isfile(os.path.join(run, "avatar.npz")):
            ap.error(f"--run wants NAME=DIR with DIR/avatar.npz, got {spec!r}")
        runs[name] = run
    if args.views < 1:
        ap.error("--views must be >= 1")
    command = "python scripts/bench_level_shares.py " + " ".join(
        [f"--data {args.data}"]
        + [f"--run '{s}'" for s in args.run]
        + [f"--views {args.views}"]
        + (["--about ..."] if args.about else [])
    )
    text = section(runs, args.data, args.views, args.about, command)
    print(text)
    if args.write:
        replace_section(os.path.join(_bootstrap.ROOT, "docs", "BENCHMARKS.md"), TITLE, text)


if __name__ == "__main__":
    main()
