"""The evaluation report of a trained run, as a library function (scripts/evaluate.py is its
command line; tests call ``build_report`` directly). Reporting tier (numba render, matplotlib).

The run is scored at several transmission budgets: PSNR/SSIM and mask coverage per budget,
the PSNR-against-bytes curve in 1 % steps, the first whole head, ablations (root order inside
levels, coarse levels, random order, importance only, quantisation, compared runs), pictures,
and with ``paper_table`` the paper's layout. Writes REPORT_DIR/report.json, report.md and PNGs.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from ..io import run as runs
from ..io.safe_io import file_digest
from ..stream.order import ROOT_ORDERS, root_keys, stream_order
from ..stream.reader import read_stream
from ..stream.writer import build_stream, write_stream
from ..train.policies import RESUMABLE
from . import plots
from .sweep import SplitRenderer, importance_only, random_within_levels


@dataclass
class ReportOptions:
    """What ``build_report`` evaluates; the names are scripts/evaluate.py's options."""

    run: str
    out: str
    data: str | None = None
    flame_model: str | None = None
    budgets: tuple = (1, 2, 5, 10, 25, 50, 100)
    strips: tuple = (1, 2, 5, 25, 100)
    views: int = 24
    curve_points: int = 100
    curve_views: int = 8
    root_order: str = "auto"
    embed_template: bool = False
    no_coarse_run: str | None = None
    compare: tuple = ()
    budget_compare: tuple = ()  # NAME=RUN: scored at the short budgets of its own stream
    name: str = ""
    about: str = ""
    paper_table: bool = False
    finest_only: str | None = None
    multi_level: str | None = None  # the finest-only run's multi-level partner (default: this run)
    uniform: tuple = ()
    adaptive: tuple = ()
    progress: bool = True
    command: str = ""


def _shown(path: str) -> str:
    """A run or data folder as the report shows it: relative to the working directory when it
    lies inside it (reports are committed; a local absolute path says nothing to a reader)."""
    full = os.path.abspath(path)
    rel = os.path.relpath(full)
    return full if rel.startswith("..") else rel


def _levels_prefixes(avatar):
    """Cumulative level sets: level l shows the faces of level <= l (how many are drawn: coarse
    stand-ins make way once the template level is whole, unless they stay behind:
    Forest.render_set)."""
    f = avatar.forest
    return {int(lvl): len(f.render_set(np.flatnonzero(f.level <= lvl))[0]) for lvl in range(int(f.level.max()) + 1)}


def _score_levels(renderer):
    """Scores of each cumulative level set of the renderer's avatar (a stream prefix when the
    stream goes level by level; a set of faces spread over a version 5 stream)."""
    level = renderer.avatar.forest.level
    return {int(lvl): renderer.score(np.flatnonzero(level <= lvl)) for lvl in range(int(level.max()) + 1)}


RATES_MBIT = (1, 10, 100)


def first_head(info) -> dict:
    """Bytes (header included) and seconds at 1/10/100 Mbit/s to the first whole head (the
    coarsest level; the template level without coarse levels) and to the whole base."""
    out = {
        "coarse_levels": info.num_coarse_levels,
        "header_bytes": info.header_size,
        "template_embedded": info.template_embedded,
        "head_gaussians": info.head_records,
        "head_bytes": info.head_bytes,
        "base_gaussians": info.num_roots,
        "base_bytes": info.base_bytes,
        "total_bytes": info.total_bytes,
    }
    for r in RATES_MBIT:
        out[f"head_seconds_{r}mbit"] = info.head_bytes * 8 / (r * 1e6)
        out[f"base_seconds_{r}mbit"] = info.base_bytes * 8 / (r * 1e6)
    return out


def root_order_ablation(avatar, W, rest, info, renderer) -> dict:
    """NVS quality of prefixes that end inside a root level (a coarse level, the template
    level), for each order of the roots inside their levels."""
    ends = info.level_ends()
    K = info.num_coarse_levels
    starts = np.concatenate([[0], ends[:-1]])
    cuts = {}
    for lv in range(K + 1):  # a quarter and a half into each root level
        a, size = int(starts[lv]), int(info.level_counts[lv])
        for frac in (0.25, 0.5):
            cuts[f"level {lv} + {frac:.0%}"] = a + max(1, int(frac * size))
    out = {"cuts": cuts, "orders": {}}
    for how in ROOT_ORDERS:
        order = stream_order(avatar.forest, W, root_keys(avatar.forest, how, W, rest))
        out["orders"][how] = {k: renderer.score(np.sort(order[:n]), ssim=False) for k, n in cuts.items()}
    return out


def _own_stream_scores(run0, data, rest, info, nvs_split, views, scratch, progress, root_order, budgets):
    """Another run written as this run's stream is (same writer settings, its own importance),
    scored on the NVS views at ``budgets`` percent of its own bytes: (its StreamInfo,
    {budget: {gaussians, psnr, ssim, coverage}})."""
    from ..io import run as runs
    from .sweep import SplitRenderer

    av0 = runs.load_run_avatar(run0)
    W0 = runs.run_importance(run0, av0, data, progress=progress)
    p0 = os.path.join(scratch, "other.pavs")
    info0 = write_stream(
        p0,
        av0,
        W0,
        quantize=True,
        metadata={"run": os.path.abspath(run0)},
        drop_sh=True,
        vertices=rest,
        root_order=root_order,
        embed_template=info.template_embedded,
    )
    r0 = SplitRenderer(read_stream(p0, template_faces=nvs_split.faces), nvs_split, views)
    scores = {}
    for b in budgets:
        n0 = int(info0.count_for_percent(b))
        scores[f"{b:g}"] = {"gaussians": n0, **r0.score(r0.first(n0))}
    return info0, scores


def coarse_ablation(run0, data, rest, nvs_renderer, info, nvs_split, views, scratch, progress, root_order) -> dict:
    """This run against `run0` (trained without coarse levels) at 2, 5 and 100 % of each one's
    own stream (same writer settings)."""
    info0, scores = _own_stream_scores(
        run0, data, rest, info, nvs_split, views, scratch, progress, root_order, (2, 5, 100)
    )
    out = {
        "run": _shown(run0),
        "bytes_with": info.total_bytes,
        "bytes_without": info0.total_bytes,
        "first_head_with": first_head(info),
        "first_head_without": first_head(info0),
        "budgets": {},
    }
    for b in (2, 5, 100):
        n1 = int(info.count_for_percent(b))
        out["budgets"][str(b)] = {
            "with": {"gaussians": n1, **nvs_renderer.score(nvs_renderer.first(n1))},
            "without": scores[str(b)],
        }
    return out


def importance_kind_ablation(avatar, others, rest, budgets, info, nvs_split, nvs_renderer, args, scratch) -> dict:
    """The stream (inside each level by importance per level, pixels weighted by the error of the
    levels below) against the same writer ranking by each importance in ``others`` ({name: [N]},
    e.g. plain alpha*T per level, and on the whole avatar: the paper's), NVS at 1, 2, 3, 5, 10 and
    25 %: the budgets whose prefixes end inside a level, where the ranking decides."""
    from .sweep import SplitRenderer

    renderers = {}
    for name, W in others.items():
        path = os.path.join(scratch, f"{name}_importance.pavs")
        write_stream(
            path,
            avatar,
            W,
            quantize=True,
            drop_sh=True,
            vertices=rest,
            root_order=args.root_order,
            embed_template=args.embed_template,
        )
        renderers[name] = SplitRenderer(read_stream(path, template_faces=nvs_split.faces), nvs_split, args.views)
    out = {}
    for b in (1, 2, 3, 5, 10, 25):
        n = int(info.count_for_percent(b))  # the same records, so the same count in every stream
        ours = budgets.get(f"{b:g}", {}).get("nvs") or nvs_renderer.score(nvs_renderer.first(n))
        out[str(b)] = {"gaussians": n, "this": ours, **{k: r.score(r.first(n)) for k, r in renderers.items()}}
    return out


def _data_summary(data) -> dict | None:
    """Image size and template of a dataset written by make_synthetic.py (None for others)."""
    path = os.path.join(data, "summary.json")
    if not os.path.exists(path):
        return None
    with open(path) as fh:
        s = json.load(fh)
    return {k: s[k] for k in ("width", "height", "faces", "vertices", "cameras", "timesteps") if k in s}


def _run_stream(run, data, progress, nvs_split):
    """(stream-ordered quantised avatar, StreamInfo) of a trained run: importance (cached in the
    run), then RUN/avatar.pavs (coarse stand-ins retire on ``nvs_split``'s rest pose)."""
    from ..io import run as runs

    avatar = runs.load_run_avatar(run)
    W = runs.run_importance(run, avatar, data, progress=progress)
    raw, info = _write_stream_of_run(
        os.path.join(run, "avatar.pavs"),
        avatar,
        W,
        quantize=True,
        metadata={"run": os.path.abspath(run)},
        drop_sh=True,
        vertices=nvs_split.canonical_vertices,
    )
    return read_stream(raw), info


def _write_stream_of_run(path: str, avatar, W, **kwargs):
    """(stream bytes, StreamInfo), the bytes also written to ``path`` (a run's avatar.pavs): what
    the report scores and measures is these bytes, not the file read back, which an export or
    another evaluation of the same run may have replaced in between."""
    from ..io.atomic import atomic_open

    raw, info = build_stream(avatar, W, **kwargs)
    with atomic_open(path) as fh:
        fh.write(raw)
    return raw, info


# What says how a run was trained, not only how long, logged or batched (the iterations have
# their own column): its settings but those a resume may change and the data's place.
_NOT_RECIPE = frozenset(RESUMABLE) | {"data", "world_size", "effective_batch"}


def run_recipe(run: str, reference: str) -> str | None:
    """How ``run`` was trained differently from ``reference``: the settings in their config.json
    that differ, as ``name value`` ("the same" when none do, "this run's" for ``reference`` itself;
    None when either file is unreadable)."""

    def settings(folder):
        try:
            with open(os.path.join(folder, "config.json"), encoding="utf-8") as fh:
                cfg = json.load(fh)
        except (OSError, ValueError):
            return None
        return cfg if isinstance(cfg, dict) else None

    ours, ref = settings(run), settings(reference)
    if ours is None or ref is None:
        return None
    if os.path.samefile(run, reference):
        return "this run's"
    diff = [
        f"{k} {json.dumps(ours.get(k))}"
        for k in sorted((set(ours) | set(ref)) - _NOT_RECIPE)
        if ours.get(k) != ref.get(k)
    ]
    return "; ".join(diff) if diff else "the same"


def _seeded(specs, first=None):
    """{seed: (name, run)} from NAME=RUN / NAME_seed<k>=RUN specs (plus `first` as seed 0)."""
    from . import plots

    out = {} if first is None else {0: first}
    for spec in specs:
        name, _, run = spec.partition("=")
        out[plots._seed_of(name)] = (name, run)
    return out


def _level_order_score(run, data, nvs_split, views, percent, path, progress) -> dict:
    """A run written in the paper's stream order (stream version 4: every level whole before the
    next, by importance inside each) and scored on the NVS views at ``percent`` of its bytes."""
    from ..io import run as runs
    from .sweep import SplitRenderer

    avatar = runs.load_run_avatar(run)
    W = runs.run_importance(run, avatar, data, progress=progress)
    info = write_stream(path, avatar, W, quantize=True, drop_sh=True, version=4, vertices=nvs_split.canonical_vertices)
    r = SplitRenderer(read_stream(path), nvs_split, views)
    n = int(info.count_for_percent(percent))
    return {**r.score(r.first(n)), "gaussians": n}


def _paper_extras(args, report, streamed, info, rend, splits, data, progress, scratch):
    """What --paper-table adds to the report: base bytes, the finest-only ablation at 35 %,
    adaptive against uniform at matched Gaussian counts per seed (and the curves of quality
    against Gaussians of both), training time and peak memory, full-resolution strips."""
    from . import plots
    from .sweep import SplitRenderer

    figs = {}
    nvs = rend["nvs"]
    report["base_bytes"] = int(info.base_bytes)  # through the template level (coarse levels included)
    report["header_bytes"] = int(info.header_size)
    if args.finest_only:
        other, oinfo = _run_stream(args.finest_only, data, progress, splits["nvs"])
        other_nvs = SplitRenderer(other, splits["nvs"], args.views)
        # The multi-level side: this run, or a partner trained with the finest-only run's recipe
        # (its iterations, its opacity reset), so that the two differ in the supervision alone.
        partner = args.multi_level or args.run
        if partner == args.run:
            mls_nvs, minfo = nvs, info
        else:
            mls, minfo = _run_stream(partner, data, progress, splits["nvs"])
            mls_nvs = SplitRenderer(mls, splits["nvs"], args.views)

        def both(percent):
            """The multi-level and the finest-only run at ``percent`` of their own streams."""
            n_ours, n_other = int(minfo.count_for_percent(percent)), int(oinfo.count_for_percent(percent))
            return {
                "multi_level": {**mls_nvs.score(mls_nvs.first(n_ours)), "gaussians": n_ours},
                "finest_only": {**other_nvs.score(other_nvs.first(n_other)), "gaussians": n_other},
            }

        report["ablations"]["finest_only_35"] = {
            "run": _shown(args.finest_only),
            "multi_level_run": _shown(partner),
            **both(35),
        }
        # The paper's ablation is at 35 %; shorter budgets show where the prefixes' supervision
        # matters once the stream is ordered by importance (not a criterion).
        report["ablations"]["finest_only_short"] = {f"{b:g}": both(b) for b in (5, 10, 25)}
        # The paper's streams send every level whole before the next, so its 35 % prefix lacks
        # the finest levels altogether; ours interleaves the levels by importance (version 5).
        # Both runs in the paper's order too, so that the row compares with the paper's.
        report["ablations"]["finest_only_35_level_order"] = {
            "multi_level": _level_order_score(
                partner, data, splits["nvs"], args.views, 35, os.path.join(scratch, "mls_v4.pavs"), progress
            ),
            "finest_only": _level_order_score(
                args.finest_only, data, splits["nvs"], args.views, 35, os.path.join(scratch, "finest_v4.pavs"), progress
            ),
        }
    # Adaptive (this run = seed 0, and --adaptive runs) against uniform (--uniform), per seed: both
    # streams cut to the smaller of the two Gaussian counts, so the counts match exactly.
    adaptive = _seeded(args.adaptive, first=("this run", args.run))
    uniform = _seeded(args.uniform)
    curve_views = max(4, args.views // 2)
    curves, pairs = {}, []
    streams = {}
    for group, members in (("adaptive", adaptive), ("uniform", uniform)):
        for seed, (name, run) in sorted(members.items()):
            av, inf = (streamed, info) if run == args.run else _run_stream(run, data, progress, splits["nvs"])
            streams[(group, seed)] = (av, inf)
            r = SplitRenderer(av, splits["nvs"], curve_views)
            counts = np.unique(np.geomspace(int(av.forest.level_counts()[0]), av.num_gaussians, 6).astype(int))
            curves.setdefault(group, {})[seed] = [
                {"gaussians": int(n), "psnr": r.score(r.first(n))["psnr"]} for n in counts
            ]
    for seed in sorted(set(adaptive) & set(uniform)):
        (a_av, _), (u_av, _) = streams[("adaptive", seed)], streams[("uniform", seed)]
        n = min(a_av.num_gaussians, u_av.num_gaussians)
        a_r, u_r = SplitRenderer(a_av, splits["nvs"], args.views), SplitRenderer(u_av, splits["nvs"], args.views)
        a, u = a_r.score(a_r.first(n)), u_r.score(u_r.first(n))
        pairs.append(
            {
                "seed": seed,
                "gaussians": n,
                "adaptive": a["psnr"],
                "uniform": u["psnr"],
                "adaptive_total": a_av.num_gaussians,
                "uniform_total": u_av.num_gaussians,
                "diff": a["psnr"] - u["psnr"],
            }
        )
    report["quality_curves"] = curves
    report["quality_curves_views"] = curve_views
    if pairs:
        d = np.array([p["diff"] for p in pairs])
        report["adaptive_vs_uniform"] = {
            "pairs": pairs,
            "diffs": d.tolist(),
            "n": len(d),
            "mean": float(d.mean()),
            "sd": float(d.std(ddof=1)) if len(d) > 1 else None,
        }
    if curves:
        figs["paper_quality_vs_gaussians"] = plots.seed_curves_vs_gaussians(
            os.path.join(args.out, "paper_quality_vs_gaussians.png"), curves, curve_views
        )
    # Training wall time and peak memory of every run (metrics log; scripts/train.py's resources.jsonl).
    runs_used = {"this run": args.run, **({"finest only": args.finest_only} if args.finest_only else {})}
    if args.finest_only and args.multi_level and args.multi_level != args.run:
        runs_used["multi-level, finest-only's recipe"] = args.multi_level
    runs_used.update({f"adaptive seed {k}": r for k, (_, r) in adaptive.items() if r != args.run})
    runs_used.update({f"uniform seed {k}": r for k, (_, r) in uniform.items()})
    report["resources"] = {name: plots.run_resources(run) for name, run in runs_used.items()}
    for name, run in runs_used.items():  # how each run was trained, beside its time and memory
        report["resources"][name]["recipe"] = run_recipe(run, args.run)
    budgets = [float(k) for k in report["budgets"] if k in ("5", "25", "50", "100")] or [
        float(k) for k in report["budgets"]
    ]  # the paper's columns when the report has them
    for k, r in rend.items():
        figs[f"strip_full_{k}"] = plots.full_resolution_strip(
            os.path.join(args.out, f"strip_full_{k}.png"), r, info, budgets
        )
    return figs


def _validate_splits(splits: dict, progress: bool) -> None:
    """Every image, mask, mesh and camera of the splits the report scores, checked before any
    rendering (core/io/validate.py): a corrupt file is one DataError naming it, not a failure
    minutes into the evaluation."""
    from ..io.sequences import DataError
    from ..io.validate import validate_dataset

    for ds in splits.values():
        try:
            validate_dataset(ds, progress=progress)
        except DataError as exc:  # its advice is worded for training
            raise DataError(str(exc).replace("fix them before training", "fix them before evaluating", 1)) from None


def _read_logs(args: ReportOptions) -> dict:
    """{name: rows} of the training logs the report uses (this run's and the compared runs'
    metrics.jsonl, when present), read before the rendering so that a damaged log fails at
    once (a torn last line is skipped, plots.read_log). With ``paper_table`` the logs that
    plots.run_resources reads later (metrics.jsonl and resources.jsonl of every run in the
    table) are checked now as well."""
    logs = {"this run": args.run}
    logs.update({spec.partition("=")[0]: spec.partition("=")[2] for spec in args.compare})
    rows = {}
    for name, run in logs.items():
        path = os.path.join(run, "metrics.jsonl")
        if os.path.exists(path):
            rows[name] = plots.read_log(path)
    if args.paper_table:
        others = [args.run, args.finest_only, args.multi_level] + [
            spec.partition("=")[2] for spec in (*args.adaptive, *args.uniform)
        ]
        for run in filter(None, others):
            for log in ("metrics.jsonl", "resources.jsonl"):
                if os.path.exists(os.path.join(run, log)):
                    plots.read_log(os.path.join(run, log))
    return rows


def _write_json(path: str, obj) -> None:
    """``obj`` as JSON at ``path``, atomically: a failed write (disk full) keeps the previous file."""
    from ..io.atomic import atomic_open

    with _naming(path), atomic_open(path, "w") as fh:
        json.dump(obj, fh, indent=1)


def _write_text(path: str, text: str) -> None:
    """``text`` (UTF-8) at ``path``, atomically."""
    from ..io.atomic import atomic_open

    with _naming(path), atomic_open(path, "wb") as fh:
        fh.write(text.encode("utf-8"))


@contextmanager
def _naming(path: str):
    """An OSError that names no file (a disk-full write) is given ``path``, so the message says
    which file could not be written."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror or str(exc), path) from exc
        raise


def _check_other_runs(args: ReportOptions) -> None:
    """Every other run the options name is a folder with a readable avatar.npz, and every
    NAME=RUN option has both: checked before any rendering (each is used only after minutes of
    scoring this run, and a spec without NAME= would load ./avatar.npz)."""
    named = {
        "--compare": args.compare,
        "--budget-compare": args.budget_compare,
        "--uniform": args.uniform,
        "--adaptive": args.adaptive,
    }
    given = [(option, spec) for option, specs in named.items() for spec in specs]
    for option, spec in given:
        name, eq, run = spec.partition("=")
        if not (eq and name and run):
            raise ValueError(f"{option} {spec}: expected NAME=RUN (a name for the report, then the run folder)")
    runs_named = [(option, spec.partition("=")[2]) for option, spec in given]
    runs_named += [
        (option, run)
        for option, run in (
            ("--no-coarse-run", args.no_coarse_run),
            ("--finest-only", args.finest_only),
            ("--multi-level", args.multi_level),
        )
        if run is not None
    ]
    for option, run in runs_named:
        path = os.path.join(run, "avatar.npz")
        if not os.path.isdir(run):
            raise ValueError(f"{option} {run}: not a run folder")
        try:
            with open(path, "rb"):
                pass
        except OSError as exc:
            why = "no trained avatar in this run folder" if not os.path.exists(path) else exc.strerror or exc
            raise ValueError(f"{option} {run}: {path}: {why}") from None
    # Every run is scored on this run's meshes (run_dataset): another run's own refined FLAME
    # parameters would be ignored, so the comparison would not be like for like.
    mine = os.path.join(args.run, "flame_refined.npz")
    mine = file_digest(mine) if os.path.exists(mine) else None
    for option, run in runs_named:
        theirs = os.path.join(run, "flame_refined.npz")
        if (file_digest(theirs) if os.path.exists(theirs) else None) != mine:
            raise ValueError(
                f"{option} {run}: trained with other FLAME refinement (flame_refined.npz) than {args.run}; "
                "every run is scored on the meshes of the run evaluated, so compare runs refined alike "
                "(or none refined)"
            )


def build_report(args: ReportOptions) -> dict:
    """Evaluate ``args.run`` and write the report into ``args.out``; returns the report dict.
    Bad input (budgets, a missing run or dataset, another run an option names) raises
    ValueError / FileNotFoundError, before ``args.out`` is made when it is about the options
    or the runs."""

    t_start = time.perf_counter()
    budgets = [float(b) for b in args.budgets]
    if not budgets or any(not 0 < b <= 100 for b in budgets):
        raise ValueError(f"budgets must be percentages in (0, 100], got {budgets}")
    if any(not 0 <= float(b) <= 100 for b in args.strips):
        raise ValueError(f"strip budgets must be percentages in [0, 100], got {list(args.strips)}")
    if min(args.views, args.curve_points, args.curve_views) < 1:
        raise ValueError(
            f"views, curve points and curve views must be >= 1, got {args.views}, {args.curve_points} and "
            f"{args.curve_views}"
        )
    if args.multi_level and not (args.paper_table and args.finest_only):
        raise ValueError(
            f"--multi-level {args.multi_level}: it names the finest-only ablation's multi-level run; "
            "give it with --paper-table and --finest-only"
        )
    _check_other_runs(args)
    avatar = runs.load_run_avatar(args.run)
    data = runs.run_data_dir(args.run, args.data)
    fm = runs.run_flame_model(args.run, args.flame_model)
    splits = {"nvs": runs.run_dataset(args.run, data, "val", fm), "nes": runs.run_dataset(args.run, data, "test", fm)}
    for ds in splits.values():
        ds.check_same_mesh(avatar.forest.template_faces, f"the template of {args.run}'s avatar")

    # Only for a run that loads: a mistyped --run leaves no folder. Two evaluations writing one
    # folder at once would leave a report beside the other's pictures and curves.
    def busy(holder):
        return f"{args.out} is being written by another evaluation ({holder}): wait for it, or choose another --out"

    with runs.folder_lock(args.out, ".evaluate.lock", busy, remove=True):
        return _evaluate_into(args, t_start, budgets, avatar, data, fm, splits)


def _evaluate_into(args: ReportOptions, t_start, budgets, avatar, data, fm, splits) -> dict:
    """build_report's work once its inputs are loaded and checked, with ``args.out`` held."""
    strips = [float(b) for b in args.strips]
    progress = args.progress
    # Everything read later is checked now, before minutes of rendering: every image, mask, mesh
    # and camera of the splits scored, and the training logs (a bad line is refused here).
    _validate_splits(splits, progress)
    log_rows = _read_logs(args)
    W = runs.run_importance(args.run, avatar, data, progress=progress, flame_model=args.flame_model)
    stream_path = os.path.join(args.run, "avatar.pavs")
    if avatar.sh_degree:
        print(
            f"note: the avatar has SH degree {avatar.sh_degree}; the stream (and so this report) carries its "
            "DC colour only",
            file=sys.stderr,
        )
    rest = splits["nvs"].canonical_vertices  # spread-out root order (core/avatar/coarse.py)
    stream_bytes, info = _write_stream_of_run(
        stream_path,
        avatar,
        W,
        quantize=True,
        metadata={"run": os.path.abspath(args.run)},
        drop_sh=True,
        vertices=rest,
        root_order=args.root_order,
        embed_template=args.embed_template,
    )
    scratch = tempfile.mkdtemp(prefix="pa_eval_")
    try:  # the scratch folder goes on every exit path (an error, Ctrl-C), not only on success
        lossless_path = os.path.join(scratch, "lossless.pavs")  # only to measure what quantisation costs
        write_stream(lossless_path, avatar, W, quantize=False, drop_sh=True, vertices=rest, root_order=args.root_order)
        streamed = read_stream(stream_bytes, template_faces=splits["nvs"].faces)
        exact = read_stream(lossless_path)
        order = info.order
        total_bytes = len(stream_bytes)

        rend = {k: SplitRenderer(streamed, ds, args.views) for k, ds in splits.items()}
        report = {
            "run": _shown(args.run),
            "data": _shown(data),
            "data_summary": _data_summary(data),
            "about": args.about,
            "name": args.name,
            "stream_bytes": total_bytes,
            "bytes_per_gaussian": total_bytes / streamed.num_gaussians,
            "gaussians": streamed.num_gaussians,
            "level_counts": streamed.forest.level_counts().tolist(),
            "stream_version": info.version,
            "budgets": {},
            "ablations": {},
        }
        for b in budgets:
            n = int(info.count_for_percent(b))
            ids = rend["nvs"].first(n)
            entry = {"gaussians": n, "bytes": int(info.bytes_for_count(n))}
            for k, r in rend.items():
                entry[k] = r.score(ids)
            entry["render_ms"] = entry["nvs"]["render_ms"]
            report["budgets"][f"{b:g}"] = entry
            if progress:
                print(
                    f"budget {b:g}%: {n} Gaussians, NVS {entry['nvs']['psnr']:.2f} dB "
                    f"(coverage {entry['nvs']['coverage']:.3f}), NES {entry['nes']['psnr']:.2f} dB"
                )

        # PSNR and coverage against bytes, many budgets (NVS, fewer views to keep it quick).
        curve_r = SplitRenderer(streamed, splits["nvs"], args.curve_views)
        curve = []
        for b in np.linspace(100 / args.curve_points, 100, args.curve_points):
            n = int(info.count_for_percent(b))
            sc = curve_r.score(curve_r.first(n), ssim=False)
            curve.append(
                {
                    "percent": float(b),
                    "bytes": int(info.bytes_for_count(n)),
                    "gaussians": n,
                    "psnr": sc["psnr"],
                    "coverage": sc["coverage"],
                }
            )
        report["curve_nvs"] = curve
        report["curve_views"] = len(curve_r.views)
        report["first_head"] = first_head(info)
        report["root_order"] = args.root_order
        report["template_embedded"] = info.template_embedded

        # Ablations on our data.
        abl = report["ablations"]
        nvs = rend["nvs"]
        abl["root_order"] = root_order_ablation(avatar, W, rest, info, SplitRenderer(avatar, splits["nvs"], args.views))
        if args.no_coarse_run:
            abl["coarse_vs_none"] = coarse_ablation(
                args.no_coarse_run,
                data,
                rest,
                rend["nvs"],
                info,
                splits["nvs"],
                args.views,
                scratch,
                progress,
                args.root_order,
            )
        n25, n50 = int(info.count_for_percent(25)), int(info.count_for_percent(50))
        # The paper's importance-only ablation ranks by importance measured on the whole avatar (per
        # level, the stream's own ranking, coarse faces would simply come first).
        W_whole = runs.run_importance(
            args.run, avatar, data, progress=progress, per_level=False, flame_model=args.flame_model
        )
        imp = importance_only(W_whole[order])[:n50]
        W_alpha = runs.run_importance(
            args.run, avatar, data, progress=progress, weighting="alpha", flame_model=args.flame_model
        )
        abl["importance_kind"] = importance_kind_ablation(
            avatar,
            {"alpha": W_alpha, "whole": W_whole},
            rest,
            report["budgets"],
            info,
            splits["nvs"],
            nvs,
            args,
            scratch,
        )
        # This stream (version 5: any face as soon as its parent has arrived) against the order
        # that sends every root first, level by level (version 4's), over the same faces.
        W_dec = W[order]
        levels_first = stream_order(streamed.forest, W_dec, streamed.forest.root_rank)
        # The paper's random-order ablation, like for like: both level by level (every root first),
        # inside each level by importance or at random. The stream's own prefix (version 5 mixes
        # levels) is the third number: it differs from random in two things at once.
        rand = random_within_levels(streamed.forest.level, seed=0)[:n25]
        abl["random_order_25"] = {
            "ranked": nvs.score(np.sort(levels_first[:n25])),
            "random": nvs.score(np.sort(rand)),
            "stream": report["budgets"].get("25", {}).get("nvs") or nvs.score(nvs.first(n25)),
            "gaussians": n25,
        }
        abl["interleaved_order"] = {}
        for b in (1, 2, 3, 5, 10, 25, 50):
            n = int(info.count_for_percent(b))
            abl["interleaved_order"][f"{b:g}"] = {
                "gaussians": n,
                "levels_first": nvs.score(np.sort(levels_first[:n])),
                "interleaved": report["budgets"].get(f"{b:g}", {}).get("nvs") or nvs.score(nvs.first(n)),
            }
        abl["importance_only_50"] = {
            "levels_then_importance": nvs.score(nvs.first(n50)),
            "importance_only": nvs.score(np.sort(imp)),
            "gaussians": n50,
        }
        exact_nvs = SplitRenderer(exact, splits["nvs"], args.views)
        abl["quantisation_100"] = {
            "quantised": nvs.score(np.arange(streamed.num_gaussians)),
            "float32": exact_nvs.score(np.arange(exact.num_gaussians)),
            "bytes_quantised": total_bytes,
            "bytes_float32": os.path.getsize(lossless_path),
        }
        abl["quantisation_100"]["psnr_loss_db"] = (
            abl["quantisation_100"]["float32"]["psnr"] - abl["quantisation_100"]["quantised"]["psnr"]
        )
        abl["level_prefixes"] = {
            "counts": _levels_prefixes(streamed),
            "nvs": _score_levels(nvs),
        }
        sizes = {f"{b:g}": int(info.bytes_for_count(int(info.count_for_percent(b)))) for b in budgets}
        abl["single_asset_vs_discrete"] = {
            "stream_bytes": total_bytes,
            "discrete_sum_bytes": int(sum(sizes.values())),
            "discrete_budgets": sizes,
        }
        short = (1, 2, 5, 10, 25, 100)
        for spec in args.budget_compare:
            name, _, other = spec.partition("=")
            info0, scores = _own_stream_scores(
                other, data, rest, info, splits["nvs"], args.views, scratch, progress, args.root_order, short
            )
            mine = {}
            for b in short:
                n1 = int(info.count_for_percent(b))
                mine[f"{b:g}"] = report["budgets"].get(f"{b:g}", {}).get("nvs") or nvs.score(nvs.first(n1))
            abl.setdefault("budget_compare", {"this": mine})[name] = {
                "run": _shown(other),
                "bytes": info0.total_bytes,
                "budgets": scores,
            }
        for spec in args.compare:
            name, _, other = spec.partition("=")
            other_av = runs.load_run_avatar(other)
            other_rend = SplitRenderer(other_av, splits["nvs"], args.views)
            entry = {
                "run": _shown(other),
                "gaussians": other_av.num_gaussians,
                "level_counts": other_av.forest.level_counts().tolist(),
                "nvs": other_rend.score(np.arange(other_av.num_gaussians)),
            }
            level = other_av.forest.level
            entry["level_prefixes_nvs"] = {
                int(lvl): other_rend.score(np.flatnonzero(level <= lvl)) for lvl in range(int(level.max()) + 1)
            }
            abl.setdefault("compare", {})[name] = entry
        grouped = dict(abl.get("compare", {}))
        if args.name:  # this run joins its seeds' group, scored like them from its float32 avatar
            grouped = {
                args.name: {
                    "gaussians": avatar.num_gaussians,
                    "nvs": abl["quantisation_100"]["float32"],
                    "level_prefixes_nvs": _score_levels(exact_nvs),
                },
                **grouped,
            }
        report["seed_groups"] = plots.seed_groups(grouped)
        report["seed_pairs"] = plots.seed_pairs(grouped)

        # Detail against depth.
        detail_path = os.path.join(data, "detail.npz")
        depth = avatar.forest.depth_per_root()
        if os.path.exists(detail_path):
            detail = np.load(detail_path)["face_detail"]
            if len(detail) == len(depth):
                report["depth_vs_detail"] = plots.depth_detail_stats(depth, detail)

        # Pictures.
        figs = {}
        figs["psnr_vs_bytes"] = plots.psnr_vs_bytes(
            os.path.join(args.out, "psnr_vs_bytes.png"), curve, report["budgets"], report.get("curve_views")
        )
        for k, r in rend.items():
            figs[f"strip_{k}"] = plots.budget_strip(os.path.join(args.out, f"strip_{k}.png"), r, info, strips)
        figs["strip_interleaved"] = plots.order_strip(
            os.path.join(args.out, "strip_interleaved.png"),
            rend["nvs"],
            info,
            (2, 5, 10),
            {"every root first (v4)": levels_first, "this stream (v5)": None},
        )
        figs["depth"] = plots.depth_picture(os.path.join(args.out, "depth.png"), streamed, splits["nes"])
        rows = {k: rs for k, rs in log_rows.items() if rs}  # read (and checked) before the rendering
        if rows:
            figs["psnr_vs_time"] = plots.psnr_vs_time(os.path.join(args.out, "psnr_vs_time.png"), rows, args.name)
            finals = [max((r.get("val_psnr", -np.inf) for r in rs), default=-np.inf) for rs in rows.values()]
            target = min(finals) - 0.5  # a level every run reaches, so the times compare
            if np.isfinite(target):
                report["time_to_psnr"] = {
                    "target": float(target),
                    "seconds": {k: plots.first_reaching(rs, target, "seconds") for k, rs in rows.items()},
                    "iterations": {k: plots.first_reaching(rs, target, "iteration") for k, rs in rows.items()},
                }
            report["training"] = {k: plots.training_summary(rs) for k, rs in rows.items()}
        figs["quality_vs_gaussians"] = plots.quality_vs_gaussians(
            os.path.join(args.out, "quality_vs_gaussians.png"), report
        )
        if args.paper_table:
            figs.update(_paper_extras(args, report, streamed, info, rend, splits, data, progress, scratch))
        report["figures"] = {k: os.path.basename(v) for k, v in figs.items() if v}
        report["machine"] = f"{platform.node()} ({os.cpu_count()} CPUs, {platform.processor() or platform.machine()})"
        report["date"] = time.strftime("%Y-%m-%d %H:%M:%S")
        report["command"] = args.command
        report["done_when"] = plots.done_when(report)
        report["seconds"] = time.perf_counter() - t_start
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    _write_json(os.path.join(args.out, "report.json"), report)
    _write_text(os.path.join(args.out, "report.md"), plots.report_markdown(report))
    if args.paper_table:
        from .sweep import paper_table

        report["paper_table"] = paper_table(report)
        _write_json(os.path.join(args.out, "report.json"), report)
        _write_text(os.path.join(args.out, "paper_table.md"), plots.paper_table_markdown(report))
    return report
