"""Supervision modes at the paper's scale: multi-level, base levels only, finest level only
(issue 17's Table 3 row and what it suggests; experiments).

    python scripts/bench_supervision.py --data runs/synthetic_paper \
        --run multi-level=runs/paper5/adaptive --run base=runs/paper6/base_mls \
        --run finest-only=runs/paper5/finest --run "finest-only, 2x iterations=runs/paper5/finest_12k" \
        [--views 16] [--write]

The paper's ablation (multi-level supervision 29.87 dB against finest level only 20.06 at 35 %)
comes from 60k iterations; ours from 6k, where the finest-only run's prefixes stay almost as good
as the multi-level run's past the base levels, and its finished avatar is better. This scores
each run's own stream, ordered as evaluate.py orders it (version 5: by importance, levels
interleaved), on the NVS split at several budgets, and at 35 % in the paper's order (version 4:
every level whole before the next), so that runs of different supervision and length line up;
every run is also compared with the first at each budget. Each run's importance is measured (or
read from its cache) as evaluate.py does; its avatar.pavs is rewritten. --write puts the section
into docs/BENCHMARKS.md.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401
from bench_common import header, named_runs, replace_section, runs_parser  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BUDGETS = (5, 10, 25, 35, 50, 100)
SECTION = "Supervision modes at the paper's scale (issue 17 experiments)"


def _training_seconds(run: str):
    """The training time the run's metrics log ends with (seconds of steps, resumes summed), or
    None where the log has none."""
    from progressive_avatars.core.evaluate.plots import read_log

    path = os.path.join(run, "metrics.jsonl")
    secs = [float(r["seconds"]) for r in read_log(path) if "seconds" in r] if os.path.isfile(path) else []
    return secs[-1] if secs else None


def _last_growth(run: str, bound: int) -> int:
    """The iteration from which the run's metrics log shows its final Gaussian count (growth
    happens on the schedule's steps up to ``bound``, grow_stop of the iterations; a run resumed
    with more iterations has a later bound than its growth had): ``bound`` where the log has none."""
    from progressive_avatars.core.evaluate.plots import read_log

    path = os.path.join(run, "metrics.jsonl")
    rows = [r for r in read_log(path) if "level_counts" in r] if os.path.isfile(path) else []
    if not rows:
        return bound
    final = rows[-1]["level_counts"]
    return min(bound, next(int(r["iteration"]) for r in rows if r["level_counts"] == final))


def _stream(avatar, W, tmp: str, version: int, split):
    """The quantised stream of ``version`` written into ``tmp`` as evaluate.py writes it for its
    tables (``split``'s rest pose places the stand-ins; the template not embedded, so budgets
    count the records' bytes; before 2026-11-28 this embedded it, ~1 % of the stream): the
    writer's info and the stream read back."""
    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.stream.writer import write_stream

    path = os.path.join(tmp, f"v{version}.pavs")
    info = write_stream(
        path,
        avatar,
        W,
        quantize=True,
        drop_sh=True,
        version=version,
        vertices=split.canonical_vertices,
        embed_template=False,
    )
    return info, read_stream(path, template_faces=split.faces)


def score(run: str, data: str, views: int) -> dict:
    """NVS PSNR (in the mask) at BUDGETS % of the run's version 5 stream and at 35 % of its
    version 4 stream, NES PSNR (the held-out sequence) at BUDGETS % of the version 5 stream, with
    its iteration count, training time and Gaussians."""
    from progressive_avatars.core.evaluate.sweep import SplitRenderer
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.dataset import Dataset

    nvs, nes = Dataset(data, "val"), Dataset(data, "test")
    avatar = runs.load_run_avatar(run)
    W = runs.run_importance(run, avatar, data, progress=False)
    with open(os.path.join(run, "config.json")) as fh:
        cfg = json.load(fh)
    row = {"iterations": int(cfg["iterations"]), "supervision": cfg["supervision"], "gaussians": avatar.num_gaussians}
    row["seconds"] = _training_seconds(run)
    row["mode"] = cfg["supervision"]
    if cfg.get("finest_tail"):
        row["supervision"] += f", finest tail {cfg['finest_tail']:g}"
    if cfg.get("prefix_cuts"):
        row["supervision"] += f", prefix cuts {cfg['prefix_cuts']}"
    if cfg.get("split_min_px"):
        row["supervision"] += f", size floor {cfg['split_min_px']:g} px"
    levels = cfg.get("coarse_levels") or []
    row["coarse"] = [levels, bool(cfg.get("coarse_stand_ins")), bool(cfg.get("coarse_backdrop"))] if levels else []
    if not levels:
        row["supervision"] += ", no coarse levels"
    row["reset"] = int(cfg.get("opacity_reset_every") or 0)
    row["grown_until"] = _last_growth(run, int(float(cfg["grow_stop"]) * row["iterations"]))
    if row["reset"]:
        row["supervision"] += f", opacity reset every {row['reset']:,}"
    with tempfile.TemporaryDirectory() as tmp:
        for version in (5, 4):
            info, stream = _stream(avatar, W, tmp, version, nvs)
            r = SplitRenderer(stream, nvs, views)
            for b in BUDGETS if version == 5 else (35,):
                s = r.score(r.first(int(info.count_for_percent(b))), ssim=False)
                row[f"v{version}_{b}"] = s["psnr"]
            if version == 5:
                r = SplitRenderer(stream, nes, views)
                for b in BUDGETS:
                    row[f"nes_{b}"] = r.score(r.first(int(info.count_for_percent(b))), ssim=False)["psnr"]
    return row


def score_at_counts(run: str, data: str, views: int, counts) -> dict:
    """NVS PSNR (in the mask) of the run's version 5 stream cut to each of ``counts`` Gaussians."""
    from progressive_avatars.core.evaluate.sweep import SplitRenderer
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.dataset import Dataset

    avatar = runs.load_run_avatar(run)
    W = runs.run_importance(run, avatar, data, progress=False)
    with tempfile.TemporaryDirectory() as tmp:
        nvs = Dataset(data, "val")
        r = SplitRenderer(_stream(avatar, W, tmp, 5, nvs)[1], nvs, views)
        return {int(n): r.score(r.first(int(n)), ssim=False)["psnr"] for n in counts}


def _recipe(row: dict) -> tuple:
    """What two runs must share to be paired as multi-level against finest-only."""
    return row.get("reset", 0), row["iterations"], row.get("grown_until"), json.dumps(row.get("coarse"))


def strip(runs_: dict, data: str, views: int, view: int, path: str):
    """One row per run, one NVS view at 10 % and 35 % of its version 5 stream, 35 % of its version 4
    stream and 100 %, cut to the face below the eyes (where the stubble shows the reset's streaks)."""
    import numpy as np
    from PIL import Image

    from progressive_avatars.core.evaluate.sweep import SplitRenderer
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.dataset import Dataset

    nvs, rows = Dataset(data, "val"), []
    for run in runs_.values():
        avatar = runs.load_run_avatar(run)
        W = runs.run_importance(run, avatar, data, progress=False)
        tiles = []
        with tempfile.TemporaryDirectory() as tmp:
            for version, budget in ((5, 10), (5, 35), (4, 35), (5, 100)):
                info, stream = _stream(avatar, W, tmp, version, nvs)
                r = SplitRenderer(stream, nvs, views)
                image, _, alpha = r.render(r.views[view], r.first(int(info.count_for_percent(budget))), True)
                ys, xs = np.nonzero(alpha > 0.5)
                top = int(ys.min() + 0.45 * (ys.max() - ys.min()))  # below the eyes, to the neck
                tiles.append(image[top : top + 300, xs.min() : xs.max() + 1])
        h = min(t.shape[0] for t in tiles)
        rows.append(np.concatenate([t[:h] for t in tiles], 1))
    w = min(r.shape[1] for r in rows)
    img = np.concatenate([r[:, :w] for r in rows], 0)
    k = -(-200 // min(r.shape[0] for r in rows))  # small images' rows at least 200 px, pixels kept square
    img = img.repeat(k, 0).repeat(k, 1)
    Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(path, optimize=True)


def section(rows: dict, command: str, views: int, about: str = "", title: str = SECTION) -> str:
    names = list(rows)
    lines = [
        header(title, command),
        *([about, ""] if about else []),
        f"NVS PSNR in the mask ({views} views) at a budget of each run's own stream (version 5, the order "
        "evaluate.py writes), and at 35 % in the paper's order (version 4: every level whole before the next); "
        "bytes counted as in evaluate.py's tables (template not embedded). "
        "Paper (60k iterations, its order): multi-level 29.87, finest level only 20.06 at 35 %.",
        "",
        "| run | supervision | iterations | last growth | training s | Gaussians | "
        + " | ".join(f"{b} %" for b in BUDGETS)
        + " | 35 %, version 4 |",
        "|---|---|---|---|---|---|" + "---|" * (len(BUDGETS) + 1),
    ]
    for name in names:
        r = rows[name]
        secs = "–" if r.get("seconds") is None else f"{r['seconds']:,.0f}"
        lines.append(
            f"| {name} | {r['supervision']} | {r['iterations']:,} | {r['grown_until']:,} | {secs} | {r['gaussians']:,} | "
            + " | ".join(f"{r[f'v5_{b}']:.2f}" for b in BUDGETS)
            + f" | {r['v4_35']:.2f} |"
        )
    lines += [
        "",
        f"NES PSNR in the mask ({views} views of the held-out sequence) at the same budgets of the version 5 streams:",
        "",
        "| run | " + " | ".join(f"{b} %" for b in BUDGETS) + " |",
        "|---|" + "---|" * len(BUDGETS),
    ]
    for name in names:
        lines.append(f"| {name} | " + " | ".join(f"{rows[name][f'nes_{b}']:.2f}" for b in BUDGETS) + " |")
    ref = rows[names[0]]
    if len(names) > 1:
        lines += ["", f"Each run minus {names[0]} (dB), at the budgets above and at 35 % version 4:", ""]
        for name in names[1:]:
            r = rows[name]
            lines.append(
                f"- {name}: "
                + ", ".join(f"{b} % {r[f'v5_{b}'] - ref[f'v5_{b}']:+.2f}" for b in BUDGETS)
                + f"; 35 % version 4 {r['v4_35'] - ref['v4_35']:+.2f}; NES "
                + ", ".join(f"{b} % {r[f'nes_{b}'] - ref[f'nes_{b}']:+.2f}" for b in BUDGETS)
            )
    matched = {n: r for n, r in rows.items() if "first_at_own_count" in r}
    if matched:
        lines += [
            "",
            f"Runs smaller than {names[0]}, against its stream cut to their Gaussian count (NVS, 100 % of theirs):",
            "",
        ]
        for name, r in matched.items():
            own, first = r["v5_100"], r["first_at_own_count"]
            lines.append(
                f"- {name}: {r['gaussians']:,} Gaussians, {own:.2f} dB against {names[0]} at as many {first:.2f} dB "
                f"({own - first:+.2f})"
            )
    multi = [n for n in names if rows[n]["mode"] != "finest"]
    if multi and any(rows[n]["mode"] == "finest" for n in names):
        lines += [
            "",
            "Multi-level minus each finest-only run at 35 % (issue 17's criterion: >= 5 dB), against the first "
            "multi-level run of the same recipe (opacity reset, iterations, last growth, coarse levels):",
            "",
        ]
        for name in names:
            r = rows[name]
            if r["mode"] == "finest":
                pair = next((n for n in multi if _recipe(rows[n]) == _recipe(r)), None)
                if pair is None:
                    lines.append(f"- {name}: no multi-level run of its recipe")
                    continue
                m = rows[pair]
                lines.append(
                    f"- {name} (against {pair}): {m['v5_35'] - r['v5_35']:+.2f} dB (version 5), "
                    f"{m['v4_35'] - r['v4_35']:+.2f} dB (version 4)"
                )
    # The same finest-only recipe trained for different lengths: what the extra iterations did. The
    # "supervision" text names the recipe's options (reset, tail, ...), so it groups like with like.
    groups: dict = {}
    for n in names:
        if rows[n]["mode"] == "finest":
            groups.setdefault((rows[n]["supervision"], rows[n].get("grown_until")), []).append(n)
    for group in groups.values():
        if len({rows[n]["iterations"] for n in group}) < 2:
            continue
        group.sort(key=lambda n: rows[n]["iterations"])
        short, long = rows[group[0]], rows[group[-1]]
        lines += [
            "",
            f"Finest-only ({short['supervision']}) at {long['iterations']:,} minus at {short['iterations']:,} "
            "iterations: "
            + ", ".join(f"{b} % {long[f'v5_{b}'] - short[f'v5_{b}']:+.2f}" for b in BUDGETS)
            + f"; 35 % version 4 {long['v4_35'] - short['v4_35']:+.2f} dB.",
        ]
    return "\n".join(lines) + "\n"


def main():
    ap = runs_parser(__doc__)
    ap.add_argument(
        "--strip", metavar="PNG", help="also a picture: per run, one NVS view at 10/35 %% (v5), 35 %% (v4), 100 %%"
    )
    ap.add_argument("--strip-view", type=int, default=3, help="which of the --views NVS views (default 3)")
    ap.add_argument("--title", default=SECTION, help="the section's heading (another section than the default's)")
    a = ap.parse_args(_bootstrap.script_args())
    rows, paths = {}, named_runs(a.run, "bench_supervision", "config.json")
    for name, run in paths.items():
        rows[name] = score(run, a.data, a.views)
        print(name, json.dumps(rows[name]), flush=True)
    first_run = a.run[0].partition("=")[2]
    first = rows[next(iter(rows))]
    smaller = {n: r["gaussians"] for n, r in rows.items() if r["gaussians"] < first["gaussians"]}
    if smaller:
        at = score_at_counts(first_run, a.data, a.views, sorted(set(smaller.values())))
        for name, count in smaller.items():
            rows[name]["first_at_own_count"] = at[count]
    command = "python scripts/bench_supervision.py --data " + a.data + "".join(f" --run '{s}'" for s in a.run)
    command += f" --title '{a.title}'" if a.title != SECTION else ""
    command += " --about ..." if a.about else ""
    command += f" --strip {a.strip}" + (f" --strip-view {a.strip_view}" if a.strip_view != 3 else "") if a.strip else ""
    text = section(rows, command, a.views, a.about, a.title)
    if a.strip:
        strip(paths, a.data, a.views, a.strip_view, a.strip)
        rel = os.path.relpath(os.path.abspath(a.strip), os.path.join(ROOT, "docs"))
        text += (
            f"\n![NVS view {a.strip_view}, one row per run]({rel})\n\nOne row per run, in the table's order; columns: "
            "10 % and 35 % of its version 5 stream, 35 % of its version 4 stream (every level whole first), 100 %; "
            "the face below the eyes to the neck.\n"
        )
    print(text)
    if a.write:
        replace_section(os.path.join(ROOT, "docs", "BENCHMARKS.md"), a.title, text)


if __name__ == "__main__":
    main()
