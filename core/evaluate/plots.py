"""Pictures and Markdown for evaluation reports (matplotlib, imported lazily, Agg backend)."""

from __future__ import annotations

import json
import re

import numpy as np


def _percent(p: float) -> str:
    """A budget percent for a label: 12.5, 8.33, 25 (two decimals at most, none when whole)."""
    return f"{p:.2f}".rstrip("0").rstrip(".")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path):
    """Save ``fig`` atomically (temporary beside ``path``, then one rename): a failed write
    (disk full, an exception while drawing) leaves an earlier picture at ``path`` intact."""
    import os

    from ..io.atomic import atomic_open

    fmt = os.path.splitext(os.fspath(path))[1][1:].lower() or "png"
    try:
        with atomic_open(path, "wb") as fh:
            fig.savefig(fh, format=fmt, dpi=110, bbox_inches="tight")
    finally:
        _plt().close(fig)
    return path


def psnr_vs_bytes(path, curve, budgets, curve_views=None):
    """The curve and the budgets are scored on different numbers of views (the curve on fewer),
    so their levels differ by the views' own spread: the labels say how many."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    mb = np.array([c["bytes"] for c in curve]) / 1e6
    on = f", {curve_views} views" if curve_views else ""
    ax.plot(mb, [c["psnr"] for c in curve], "-o", ms=3, label=f"NVS (stream prefixes{on})")
    for key, entry in budgets.items():
        ax.plot(entry["bytes"] / 1e6, entry["nvs"]["psnr"], "s", color="C1")
        ax.plot(entry["bytes"] / 1e6, entry["nes"]["psnr"], "^", color="C2")
        ax.annotate(
            f"{key}%",
            (entry["bytes"] / 1e6, entry["nvs"]["psnr"]),
            textcoords="offset points",
            xytext=(4, -10),
            fontsize=7,
        )
    n = {e["nvs"].get("views") for e in budgets.values()}
    on = f", {n.pop()} views" if len(n) == 1 and None not in n else ""
    ax.plot([], [], "s", color="C1", label=f"NVS at budgets{on}")
    ax.plot([], [], "^", color="C2", label="NES at budgets")
    ax.set_xlabel("bytes received (MB)")
    ax.set_ylabel("PSNR in mask (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    if curve and "coverage" in curve[0]:
        ax2 = ax.twinx()
        ax2.plot(mb, [c["coverage"] for c in curve], "-", color="C3", lw=1, alpha=0.8)
        ax2.set_ylabel("mask coverage (alpha >= 0.5)", color="C3", fontsize=8)
        ax2.set_ylim(0, 1.02)
    ax.set_title("Quality against transmitted bytes")
    return _save(fig, path)


def budget_strip(path, renderer, info, budgets, view_index=0):
    """One view rendered at each budget, then the ground truth."""
    plt = _plt()
    view = int(renderer.views[min(view_index, len(renderer.views) - 1)])
    sample = renderer.dataset[view]
    panels, titles = [], []
    for b in budgets:
        n = int(info.count_for_percent(b))
        image, _ = renderer.render(view, renderer.first(n))
        panels.append(image)
        titles.append(f"{b:g}% ({n:,} G)")
    panels.append(sample.image)
    titles.append("ground truth")
    fig, axes = plt.subplots(
        1, len(panels), figsize=(2.0 * len(panels), 2.0 * sample.image.shape[0] / sample.image.shape[1] + 0.4)
    )
    for ax, im, title in zip(np.atleast_1d(axes), panels, titles):
        ax.imshow(np.clip(im, 0, 1), interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    return _save(fig, path)


def order_strip(path, renderer, info, budgets, orders: dict, view_index=0):
    """One view at each budget, one row per stream order ({name: permutation, or None for the
    stream's own}), the ground truth at the end of each row: where two orders differ, look."""
    plt = _plt()
    view = int(renderer.views[min(view_index, len(renderer.views) - 1)])
    sample = renderer.dataset[view]
    cols = len(budgets) + 1
    h = sample.image.shape[0] / sample.image.shape[1]
    fig, axes = plt.subplots(len(orders), cols, figsize=(2.0 * cols, (2.0 * h + 0.4) * len(orders)), squeeze=False)
    for row, (name, order) in enumerate(orders.items()):
        for col, b in enumerate(budgets):
            n = int(info.count_for_percent(b))
            ids = renderer.first(n) if order is None else np.sort(order[:n])
            image, _ = renderer.render(view, ids)
            axes[row, col].imshow(np.clip(image, 0, 1), interpolation="nearest")
            axes[row, col].set_title(f"{b:g}% ({n:,} G)", fontsize=8)
        axes[row, -1].imshow(np.clip(sample.image, 0, 1), interpolation="nearest")
        axes[row, -1].set_title("ground truth", fontsize=8)
        axes[row, 0].text(
            -0.04, 0.5, name, rotation=90, fontsize=9, ha="right", va="center", transform=axes[row, 0].transAxes
        )
    for ax in axes.ravel():
        ax.axis("off")
    return _save(fig, path)


def depth_colors(depth: np.ndarray, max_depth: int | None = None) -> np.ndarray:
    """RGB per depth, the same ramp as the Blender depth display (core.bridge.depth)."""
    from ..bridge.depth import depth_colors as rgba

    return rgba(depth, max_depth)[:, :3]


def depth_picture(path, avatar, dataset, views=(0,)):
    """The base level coloured by each template face's subdivision depth, beside the 100 % render."""
    from ..avatar.binding import compose, evaluate
    from ..render.rasterize import render_numpy

    plt = _plt()
    f = avatar.forest
    depth = f.depth_per_root()
    base = np.flatnonzero(f.level[: f.num_roots] == f.num_coarse_levels)  # the template level's faces
    F0 = len(base)
    base_depth = depth[f.root_ref[base] - f.num_coarse]
    n_views = min(3, len(dataset))
    picks = np.linspace(0, len(dataset) - 1, n_views).astype(int)
    fig, axes = plt.subplots(2, n_views, figsize=(2.2 * n_views, 5.6), squeeze=False)
    for col, v in enumerate(picks):
        info = dataset.frame_info(int(v))
        verts = dataset.vertices_at(info.timestep_index)
        geo = evaluate(avatar.forest, verts, ids=base)
        # Opaque, face-sized discs so the colour reads as a surface.
        means, quats, scales = compose(
            geo.t,
            geo.r,
            geo.s,
            np.zeros((F0, 3)),
            np.log(np.tile([0.55, 0.05, 0.55], (F0, 1))),
            np.tile([1.0, 0, 0, 0], (F0, 1)),
        )
        img, _, _ = render_numpy(
            means,
            quats,
            scales,
            np.full(F0, 0.99, np.float32),
            depth_colors(base_depth),
            info.camera,
            np.ones(3, np.float32),
        )
        shown, behind = avatar.forest.render_set()  # the finished avatar (retired stand-ins gone or behind)
        full = evaluate(avatar.forest, verts, ids=shown)
        m2, q2, s2 = compose(full.t, full.r, full.s, avatar.d_mu[shown], avatar.d_log_scale[shown], avatar.d_rot[shown])
        from ..avatar.avatar import sh_to_rgb, sigmoid

        ref, _, _ = render_numpy(
            m2,
            q2,
            s2,
            sigmoid(avatar.opacity_logit[shown]),
            sh_to_rgb(avatar.f_dc[shown]),
            info.camera,
            np.asarray(dataset.background, np.float32),
            behind=behind,
        )
        axes[0, col].imshow(np.clip(ref, 0, 1))
        axes[1, col].imshow(np.clip(img, 0, 1))
        axes[0, col].axis("off")
        axes[1, col].axis("off")
    axes[0, 0].set_title("avatar (100 %)", fontsize=8)
    axes[1, 0].set_title("subdivision depth per face", fontsize=8)
    hist = np.bincount(depth, minlength=int(depth.max()) + 1)
    cols = depth_colors(np.arange(len(hist)), int(depth.max()))
    handles = [plt.Rectangle((0, 0), 1, 1, color=cols[d]) for d in range(len(hist))]
    fig.legend(
        handles, [f"depth {d}: {hist[d]} faces" for d in range(len(hist))], loc="lower center", ncol=2, fontsize=7
    )
    return _save(fig, path)


def depth_detail_stats(depth: np.ndarray, detail: np.ndarray) -> dict:
    """How subdivision depth follows appearance detail: rank correlation and mean detail per depth."""
    from scipy.stats import spearmanr

    rho = spearmanr(depth, detail).correlation
    q = np.quantile(detail, [0.25, 0.75])
    return {
        "spearman": float(rho),
        "mean_depth_detailed_quartile": float(depth[detail >= q[1]].mean()),
        "mean_depth_smooth_quartile": float(depth[detail <= q[0]].mean()),
        "mean_detail_per_depth": {int(d): float(detail[depth == d].mean()) for d in np.unique(depth)},
    }


def read_log(metrics_log) -> list[dict]:
    """The JSON objects of a .jsonl log (RUN/metrics.jsonl, RUN/resources.jsonl), one a line.
    A torn last line (a trainer killed mid-write leaves one; the trainer drops it on resume) is
    skipped; a line elsewhere that is not a JSON object is a ValueError naming the file and line."""
    with open(metrics_log, "rb") as fh:
        lines = [(i, ln) for i, ln in enumerate(fh.read().split(b"\n"), 1) if ln.strip()]
    rows = []
    for k, (i, line) in enumerate(lines):
        try:
            row = json.loads(line)
        except ValueError as exc:  # UnicodeDecodeError too (a write cut inside a character)
            if k == len(lines) - 1:
                break  # the torn last line of a killed writer
            raise ValueError(f"{metrics_log}: line {i} is not valid JSON ({exc})") from None
        if not isinstance(row, dict):
            raise ValueError(f"{metrics_log}: line {i} is not a JSON object (a {type(row).__name__})")
        rows.append(row)
    return rows


def first_reaching(rows: list[dict], target: float, key: str) -> float | None:
    """`key` ("seconds" or "iteration") of the first evaluation whose NVS PSNR reaches
    `target` (None if never)."""
    for r in rows:
        if r.get("val_psnr", -np.inf) >= target:
            return r[key]
    return None


def training_summary(rows: list[dict], tail: int = 4) -> dict:
    """Iterations and seconds of a run's metrics log, and the spread of its last `tail`
    validation PSNRs: how much the score moves between evaluations near the end, a yardstick
    for differences between runs."""
    vals = [r["val_psnr"] for r in rows if "val_psnr" in r][-tail:]
    last = rows[-1] if rows else {}
    return {
        "iterations": last.get("iteration"),
        "seconds": last.get("seconds"),
        "val_tail_mean": float(np.mean(vals)) if vals else None,
        "val_tail_sd": float(np.std(vals, ddof=1)) if len(vals) > 1 else None,
        "val_tail_n": len(vals),
    }


def seed_group(name: str) -> str:
    """The group a run belongs to: its name without a trailing "_seed<k>" (seed 0 has none)."""
    return re.sub(r"_seed\d+$", "", name)


def _seed_of(name: str) -> int:
    m = re.search(r"_seed(\d+)$", name)
    return int(m.group(1)) if m else 0


def _seed_members(runs) -> dict:
    """{group: [(name, entry), ...]} in the runs' order (see seed_group)."""
    by = {}
    for name in runs:
        by.setdefault(seed_group(name), []).append((name, runs[name]))
    return by


def seed_pairs(runs: dict) -> list[dict]:
    """Paired differences between seed groups (see seed_groups): for two groups, the NVS PSNR
    differences of their runs with the same seed (the seed draws the training views' order, so
    a pair differs by the method more than by luck), over the seeds both have (two or more)."""
    by = {g: {_seed_of(n): e["nvs"]["psnr"] for n, e in m} for g, m in _seed_members(runs).items() if len(m) >= 2}
    out = []
    names = list(by)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            seeds = sorted(set(by[a]) & set(by[b]))
            if len(seeds) < 2:
                continue
            d = np.array([by[a][k] - by[b][k] for k in seeds])
            out.append(
                {
                    "a": a,
                    "b": b,
                    "seeds": seeds,
                    "diffs": d.tolist(),
                    "mean": float(d.mean()),
                    "sd": float(d.std(ddof=1)),
                }
            )
    return out


def seed_groups(runs: dict) -> dict:
    """Mean and spread over seeds: runs ({name: {"gaussians", "nvs": {"psnr"},
    "level_prefixes_nvs"}}) whose names differ only by a "_seed<k>" suffix form a group; groups
    of two or more runs get the mean and sample sd of NVS PSNR and Gaussians, and the mean of
    each level prefix's PSNR (levels every run of the group has)."""
    out = {}
    for group, members in _seed_members(runs).items():
        if len(members) < 2:
            continue
        psnr = np.array([e["nvs"]["psnr"] for _, e in members], np.float64)
        gs = np.array([e["gaussians"] for _, e in members], np.float64)
        levels = set.intersection(*(set(map(str, e["level_prefixes_nvs"])) for _, e in members))
        prefixes = {
            k: float(np.mean([{str(a): b for a, b in e["level_prefixes_nvs"].items()}[k]["psnr"] for _, e in members]))
            for k in sorted(levels, key=int)
        }
        out[group] = {
            "runs": [n for n, _ in members],
            "n": len(members),
            "nvs_psnr_mean": float(psnr.mean()),
            "nvs_psnr_sd": float(psnr.std(ddof=1)),
            "nvs_psnr_min": float(psnr.min()),
            "nvs_psnr_max": float(psnr.max()),
            "gaussians_mean": float(gs.mean()),
            "gaussians_sd": float(gs.std(ddof=1)),
            "level_prefixes_nvs_mean": prefixes,
        }
    return out


def _group_styles(names, also=()) -> dict:
    """{name: (colour, legend label or None)}: runs that differ only by seed share a colour and
    one legend entry ("NAME (k seeds)"); a run alone keeps its own name. ``also``: runs drawn
    elsewhere (this run, in its own style) that still count among their group's seeds."""
    names = list(names)
    size = {g: len(m) for g, m in _seed_members(dict.fromkeys(names + list(also))).items()}
    colour, out = {}, {}
    for n in names:
        g = seed_group(n)
        first = g not in colour
        colour.setdefault(g, f"C{len(colour) % 10}")
        own = ", this run in black" if any(seed_group(x) == g for x in also) else ""
        out[n] = (colour[g], (f"{g} ({size[g]} seeds{own})" if size[g] > 1 else n) if first else None)
    return out


def psnr_vs_time(path, logs: dict, this_name=None):
    """NVS PSNR against training time for one or more runs ({name: metrics.jsonl or its rows}), and a
    second panel against iterations zoomed on the plateau (time depends on the machine's
    load; iterations do not). ``this_name``: the name of the run logged as "this run", so it
    joins its seed group (one colour and one legend entry with its other seeds)."""
    plt = _plt()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11.5, 3.6))
    tops = []
    alias = {k: this_name if k == "this run" and this_name and this_name not in logs else k for k in logs}
    grouped = _group_styles([alias[k] for k in logs])
    style = {k: grouped[alias[k]] for k in logs}
    for name, log in logs.items():
        ev = [r for r in (log if isinstance(log, list) else read_log(log)) if "val_psnr" in r]
        y = [r["val_psnr"] for r in ev]
        colour, label = style[name]
        ax.plot([r["seconds"] / 60 for r in ev], y, "-o", ms=3, color=colour, label=label)
        ax2.plot([r["iteration"] for r in ev], y, "-o", ms=3, color=colour)
        tops.append(max(y, default=np.nan))
    ax.set_xlabel("training time (min)")
    ax.set_ylabel("NVS PSNR in mask (dB)")
    ax2.set_xlabel("iteration")
    top = np.nanmax(tops) if tops and np.isfinite(tops).any() else None
    if top is not None:
        ax2.set_ylim(top - 1.0, top + 0.1)
    ax2.set_title("plateau", fontsize=9)
    for a in (ax, ax2):
        a.grid(alpha=0.3)
    ax2.legend(*ax.get_legend_handles_labels(), fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return _save(fig, path)


def quality_vs_gaussians(path, report: dict):
    """NVS PSNR against Gaussian count: this run's stream prefixes (budgets and level sets)
    and each compared run's level prefixes (levels <= 0, 1, ...), so runs meet at equal
    counts. None without compared runs."""
    a = report["ablations"]
    if not a.get("compare"):
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.2, 3.8))
    b = sorted(report["budgets"].values(), key=lambda e: e["gaussians"])
    ax.plot(
        [e["gaussians"] for e in b],
        [e["nvs"]["psnr"] for e in b],
        "-o",
        color="k",
        lw=2,
        ms=5,
        label="this run: stream budgets (quantised)",
        zorder=5,
    )
    lp = a["level_prefixes"]
    ax.plot(
        [lp["counts"][k] for k in lp["nvs"]],
        [v["psnr"] for v in lp["nvs"].values()],
        "s",
        color="k",
        ms=5,
        mfc="none",
        label="this run: level prefixes",
        zorder=5,
    )
    # This run (seed 0 of its group when the compared runs are its other seeds) is drawn in black.
    style = _group_styles(a["compare"], also=[report["name"]] if report.get("name") else [])
    for name, c in a["compare"].items():
        colour, label = style[name]
        counts = np.cumsum(c["level_counts"])
        pts = sorted((int(counts[int(k)]), v["psnr"]) for k, v in c["level_prefixes_nvs"].items())
        x, y = zip(*pts)
        ax.plot(x, y, "--", marker=".", ms=5, lw=1, color=colour, label=label)
        ax.plot(x[-1], y[-1], "D", ms=5, color=colour)
    ax.set_xscale("log")
    top = max([e["nvs"]["psnr"] for e in b] + [c["nvs"]["psnr"] for c in a["compare"].values()])
    ax.set_ylim(top - 6.0, top + 0.3)  # the level-0 prefixes and the plateau; tiny budgets fall off
    ax.set_xlabel("Gaussians rendered (log)")
    ax.set_ylabel("NVS PSNR in mask (dB)")
    ax.set_title("Quality against Gaussians (diamonds: other runs in full)", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the plot: curves meet lower right
    return _save(fig, path)


def _non_decreasing(values, slack) -> tuple:
    """(holds, worst drop) of a sequence against its running maximum."""
    v = np.asarray(values, np.float64)
    drop = float((np.maximum.accumulate(v) - v).max()) if len(v) else 0.0
    return drop <= slack, drop


def _steps(d: dict, curve: list) -> str:
    """The curve a criterion checked: its point count is in the criterion, or for reports from
    before it was recorded, the report's own curve."""
    n = d.get("curve_points", len(curve))
    percents = [c.get("percent") for c in curve]
    if n == len(curve) and percents == [float(p) for p in range(1, n + 1)]:
        return "the curve in 1 % steps"
    step = (100.0 / n) if n > 1 and percents == [100.0 * (i + 1) / n for i in range(n)] else None
    return f"the curve's {n} point(s)" + (f" ({_percent(step)} % steps)" if step else "")


def done_when(r: dict) -> dict:
    """Issue 16's measurable criteria on one report (each: value, threshold, met)."""
    curve = r.get("curve_nvs", [])
    out = {}
    pts = [(c["percent"], c["coverage"]) for c in curve if c["percent"] >= 2 - 1e-9 and "coverage" in c]
    pts += [
        (float(k), e["nvs"]["coverage"]) for k, e in r["budgets"].items() if float(k) >= 2 and "coverage" in e["nvs"]
    ]
    if pts:
        worst = min(pts, key=lambda x: x[1])
        out["coverage_from_2pct"] = {
            "min": worst[1],
            "at_percent": worst[0],
            "threshold": 0.95,
            "met": worst[1] >= 0.95,
        }
    # The curve and the budget table, each on its own views (their values do not mix): both
    # must be non-decreasing; a curve of one point checks nothing by itself.
    b = r["budgets"]
    table = [b[k]["nvs"] for k in sorted(b, key=float)]
    for key, field, slack in (("psnr_non_decreasing", "psnr", 0.05), ("coverage_non_decreasing", "coverage", 0.0)):
        series = [[c[field] for c in curve if field in c], [e[field] for e in table if field in e]]
        series = [v for v in series if len(v) > 1]
        if series:
            drop = max(_non_decreasing(v, slack)[1] for v in series)
            out[key] = {"worst_drop": drop, "slack": slack, "met": drop <= slack, "curve_points": len(curve)}
    if "5" in b and "100" in b:
        gap = b["100"]["nvs"]["psnr"] - b["5"]["nvs"]["psnr"]
        out["psnr_5_within_3db"] = {"gap_db": gap, "threshold": 3.0, "met": gap <= 3.0}
    cv = r.get("ablations", {}).get("coarse_vs_none")
    if cv:
        cost = cv["budgets"]["100"]["without"]["psnr"] - cv["budgets"]["100"]["with"]["psnr"]
        out["coarse_cost_100"] = {"cost_db": cost, "threshold": 0.1, "met": cost <= 0.1}
    out.update(_done_when_seeds(r))
    return out


def _done_when_seeds(r: dict) -> dict:
    """The criteria that a single seed cannot settle (seed-to-seed spread at 100 % is as large as
    the 0.1 dB bound), over this run's other seeds where the report has them: the 5 % gap and the
    coverage from 2 % on every seed's own stream (--budget-compare NAME_seed<k>), and the coarse
    levels' cost as the mean of the per-seed differences against the runs without them."""
    out = {}
    mine = seed_group(r.get("name") or "")
    bc = r.get("ablations", {}).get("budget_compare", {})
    seeds = {r.get("name"): {"budgets": bc["this"]}} if "this" in bc else {}  # "this": {budget: scores}
    seeds.update({n: e for n, e in bc.items() if n != "this" and seed_group(n) == mine})
    if len(seeds) >= 2 and all({"5", "100"} <= set(e["budgets"]) for e in seeds.values()):
        gaps = {n: e["budgets"]["100"]["psnr"] - e["budgets"]["5"]["psnr"] for n, e in seeds.items()}
        out["psnr_5_within_3db_every_seed"] = {"gap_db": gaps, "threshold": 3.0, "met": max(gaps.values()) <= 3.0}
        cov = {
            n: min(
                (v["coverage"] for k, v in e["budgets"].items() if float(k) >= 2 and "coverage" in v), default=np.nan
            )
            for n, e in seeds.items()
        }
        out["coverage_from_2pct_every_seed"] = {
            "min": cov,
            "threshold": 0.95,
            "met": bool(all(c >= 0.95 for c in cov.values())),  # nan (no coverage scored): not met
        }
    cv = r.get("ablations", {}).get("coarse_vs_none")
    without = [n for n, c in r.get("ablations", {}).get("compare", {}).items() if cv and c.get("run") == cv.get("run")]
    for p in r.get("seed_pairs", []):
        if without and p["a"] == mine and p["b"] == seed_group(without[0]):
            cost = -p["mean"]  # a minus b is with minus without
            out["coarse_cost_100_seed_mean"] = {
                "cost_db": cost,
                "per_seed_db": [-d for d in p["diffs"]],
                "seeds": p["seeds"],
                "threshold": 0.1,
                "met": cost <= 0.1,
            }
    return out


def report_markdown(r: dict) -> str:
    ds = r.get("data_summary") or {}
    about = (
        f" ({ds['width']}x{ds['height']} px images, tracked template {ds['faces']:,} faces)"
        if {"width", "height", "faces"} <= set(ds)
        else ""
    )
    lines = [
        "# Evaluation report",
        "",
        f"- run: `{r['run']}`",
        f"- data: `{r['data']}`{about}",
        f"- machine: {r['machine']}",
        f"- date: {r['date']}",
        f"- command: `{r['command']}`",
        f"- stream: {r['stream_bytes']:,} bytes, {r['gaussians']:,} Gaussians "
        f"({r['bytes_per_gaussian']:.1f} B/Gaussian with header), levels {r['level_counts']}",
    ]
    if r.get("about"):
        lines += ["", r["about"]]
    own = r.get("training", {}).get("this run", {})
    if own.get("seconds") is not None:
        lines.append(
            f"- training (from the run's metrics log): {own['iterations']} iterations, "
            f"{own['seconds']:.0f} s of training steps ({own['seconds'] / 60:.1f} min)"
            + (
                f", {wall:.0f} s wall time with evaluations and checkpoints"
                if (wall := r.get("resources", {}).get("this run", {}).get("wall_seconds"))
                else ""
            )
        )
    cov = all("coverage" in e["nvs"] for e in r["budgets"].values())
    lines += [
        "",
        "| budget | Gaussians | bytes | NVS PSNR / SSIM | NES PSNR / SSIM |"
        + (" NVS / NES coverage |" if cov else "")
        + " render ms |",
        "|---|---|---|---|---|---|" + ("---|" if cov else ""),
    ]
    for key, e in r["budgets"].items():
        c = f" {e['nvs']['coverage']:.3f} / {e['nes']['coverage']:.3f} |" if cov else ""
        lines.append(
            f"| {key} % | {e['gaussians']:,} | {e['bytes']:,} | {e['nvs']['psnr']:.2f} / {e['nvs']['ssim']:.3f} | "
            f"{e['nes']['psnr']:.2f} / {e['nes']['ssim']:.3f} |{c} {e['render_ms']:.1f} |"
        )
    first = next(iter(r["budgets"].values()), {})
    empty = {k: first.get(k, {}).get("views_with_empty_mask", 0) for k in ("nvs", "nes")}
    if any(empty.values()):  # (the same views at every budget)
        lines += [
            "",
            "Views with an empty foreground mask have no in-mask score and are left out of the PSNR, SSIM and "
            "coverage above: "
            + ", ".join(f"{n} of {first[k]['views']} {k.upper()} views" for k, n in empty.items() if n),
        ]
    fh = r.get("first_head")
    if fh:
        lines += [
            "",
            f"First whole head ({'the coarsest level' if fh['coarse_levels'] else 'the template level'}, "
            f"{fh['head_gaussians']:,} Gaussians; header {fh['header_bytes']:,} B included, template "
            f"{'embedded' if fh.get('template_embedded') else 'not embedded: the receiver has it'}) and the whole base "
            f"(every coarse and template face, {fh['base_gaussians']:,} Gaussians):",
            "",
            "| | bytes | % of stream | at 1 Mbit/s | at 10 Mbit/s | at 100 Mbit/s |",
            "|---|---|---|---|---|---|",
        ]
        for what in ("head", "base"):
            lines.append(
                f"| {'first whole head' if what == 'head' else 'whole base'} | {fh[what + '_bytes']:,} | "
                f"{100 * fh[what + '_bytes'] / fh['total_bytes']:.2f} | "
                + " | ".join(f"{1e3 * fh[f'{what}_seconds_{m}mbit']:.1f} ms" for m in (1, 10, 100))
                + " |"
            )
    curve = r.get("curve_nvs", [])
    if curve and "coverage" in curve[0]:
        lines += [
            "",
            f"PSNR-against-bytes curve in {len(curve)} steps ({r.get('curve_views', '?')} NVS views each): "
            "percent: PSNR dB / mask coverage",
            "",
            "<details><summary>all points</summary>",
            "",
            ", ".join(f"{_percent(c['percent'])}: {c['psnr']:.2f} / {c['coverage']:.3f}" for c in curve),
            "",
            "</details>",
        ]
    dw = r.get("done_when")
    if dw:
        lines += ["", "Issue 16 criteria on this run (and, where named, on its other seeds):", ""]
        names = {
            "coverage_from_2pct": lambda d: f"mask coverage ≥ 0.95 from 2 %: min {d['min']:.3f} at {d['at_percent']:g} %",
            "psnr_non_decreasing": lambda d: f"NVS PSNR non-decreasing over the budget table and {_steps(d, curve)} (0.05 dB slack): worst drop {d.get('worst_drop', d.get('worst_drop_db', 0.0)):.3f} dB",
            "coverage_non_decreasing": lambda d: f"coverage non-decreasing over the budget table and {_steps(d, curve)}: worst drop {d['worst_drop']:.4f}",
            "psnr_5_within_3db": lambda d: f"NVS PSNR at 5 % within 3 dB of 100 %: {d['gap_db']:.2f} dB below",
            "coarse_cost_100": lambda d: f"coarse levels cost ≤ 0.1 dB at 100 %: {d['cost_db']:+.3f} dB",
            "psnr_5_within_3db_every_seed": lambda d: "NVS PSNR at 5 % within 3 dB of 100 %, every seed's own stream: "
            + ", ".join(f"{n} {g:.2f}" for n, g in d["gap_db"].items())
            + " dB below",
            "coverage_from_2pct_every_seed": lambda d: "mask coverage ≥ 0.95 from 2 %, every seed (budgets 2-100 %): min "
            + ", ".join(f"{n} {c:.3f}" for n, c in d["min"].items()),
            "coarse_cost_100_seed_mean": lambda d: "coarse levels cost ≤ 0.1 dB at 100 %, mean over seeds "
            + ", ".join(str(k) for k in d["seeds"])
            + f" (float32 avatars): {d['cost_db']:+.3f} dB (per seed "
            + ", ".join(f"{c:+.3f}" for c in d["per_seed_db"])
            + ")",
        }
        for k, d in dw.items():
            lines.append(f"- {'met' if d['met'] else '**not met**'}: {names[k](d)}")
    a = r["ablations"]
    lines += ["", "## Ablations (NVS PSNR in mask)", ""]
    ro = a["random_order_25"]
    if "stream" in ro:
        lines.append(
            f"- 25 %, level by level: importance-ranked {ro['ranked']['psnr']:.2f} dB vs random order within levels "
            f"{ro['random']['psnr']:.2f} dB (the stream's own order: {ro['stream']['psnr']:.2f} dB)"
        )
    else:  # reports before 2026-11-29 ranked with the stream's own order, which mixes levels
        lines.append(
            f"- 25 %: the stream's order {ro['ranked']['psnr']:.2f} dB vs random order within levels "
            f"{ro['random']['psnr']:.2f} dB"
        )
    io = a["importance_only_50"]
    lines.append(
        f"- 50 %: the stream's order (parents first, by importance) {io['levels_then_importance']['psnr']:.2f} dB vs "
        f"importance only (ignoring parents) {io['importance_only']['psnr']:.2f} dB"
    )
    ik = a.get("importance_kind")
    if ik and "this" in next(iter(ik.values())):  # (reports before 2026-11-24 keyed it otherwise: not shown)
        kinds = [k for k in ("this", "alpha", "whole") if k in next(iter(ik.values()))]
        pts = ", ".join(
            f"{b} %: "
            + " / ".join(f"{d[k]['psnr']:.2f}" for k in kinds)
            + " dB (coverage "
            + " / ".join(f"{d[k]['coverage']:.3f}" for k in kinds)
            + ")"
            for b, d in ik.items()
        )
        lines.append(
            "- ranking inside levels by importance measured on the levels up to each face's own, pixels "
            "weighted by the error of the levels below (this stream) / the same, plain alpha*T / alpha*T on "
            f"the whole avatar (the paper's): {pts}"
        )
    il = a.get("interleaved_order")
    if il:
        pts = ", ".join(
            f"{b} %: {d['levels_first']['psnr']:.2f} / {d['interleaved']['psnr']:.2f} dB (coverage "
            f"{d['levels_first']['coverage']:.3f} / {d['interleaved']['coverage']:.3f})"
            for b, d in il.items()
        )
        lines.append(
            "- every root first, level by level (stream version 4's order) / the coarse levels first, then any face "
            "whose parent has arrived by descending importance, template faces included (core/stream/order.py "
            f"interleaved_order: version 5, {'this stream' if r.get('stream_version', 4) >= 5 else 'not this stream'}): {pts}"
        )
    q = a["quantisation_100"]
    lines.append(
        f"- 100 %: quantised {q['quantised']['psnr']:.3f} dB ({q['bytes_quantised']:,} B) vs float32 "
        f"{q['float32']['psnr']:.3f} dB ({q['bytes_float32']:,} B): loss {q['psnr_loss_db']:.3f} dB"
    )
    ro = a.get("root_order")
    if ro:
        cuts = list(ro["cuts"])
        lines += [
            "",
            "Order of the roots inside their levels, at cuts inside a root level (NVS PSNR / coverage; "
            "forest: as trained, the template level in template order; spatial: spread over the head, "
            "core/avatar/coarse.py; importance: descending (measured per level); both: spatial dyadic blocks, each by importance; "
            "auto, the writer's default: importance where it is known, else spatial):",
            "",
            "| order | " + " | ".join(f"{c} ({ro['cuts'][c]:,} G)" for c in cuts) + " |",
            "|---|" + "---|" * len(cuts),
        ]
        for how, vals in ro["orders"].items():
            lines.append(
                f"| {how} | " + " | ".join(f"{vals[c]['psnr']:.2f} / {vals[c]['coverage']:.3f}" for c in cuts) + " |"
            )
    cv = a.get("coarse_vs_none")
    if cv:
        lines += [
            "",
            f"With against without coarse levels (the same model trained without them: `{cv['run']}`; "
            f"streams {cv['bytes_with']:,} / {cv['bytes_without']:,} B; first whole head "
            f"{cv['first_head_with']['head_bytes']:,} / {cv['first_head_without']['head_bytes']:,} B), NVS:",
            "",
            "| budget | with: Gaussians, PSNR / SSIM, coverage | without: Gaussians, PSNR / SSIM, coverage | Δ PSNR |",
            "|---|---|---|---|",
        ]
        for b, e in cv["budgets"].items():
            w, o = e["with"], e["without"]
            lines.append(
                f"| {b} % | {w['gaussians']:,}, {w['psnr']:.2f} / {w['ssim']:.3f}, {w['coverage']:.3f} | "
                f"{o['gaussians']:,}, {o['psnr']:.2f} / {o['ssim']:.3f}, {o['coverage']:.3f} | "
                f"{w['psnr'] - o['psnr']:+.2f} |"
            )
    bc = a.get("budget_compare")
    if bc:
        others = [k for k in bc if k != "this"]
        lines += [
            "",
            "Short budgets against other runs, each written and scored as this stream (its own "
            "importance, its own bytes), NVS PSNR / coverage: "
            + ", ".join(f"{k}: `{bc[k]['run']}` ({bc[k]['bytes']:,} B)" for k in others),
            "",
            "| budget | this run | " + " | ".join(others) + " |",
            "|---|---|" + "---|" * len(others),
        ]
        for b, mine in bc["this"].items():
            cells = [f"{mine['psnr']:.2f} / {mine['coverage']:.3f}"]
            cells += [f"{bc[k]['budgets'][b]['psnr']:.2f} / {bc[k]['budgets'][b]['coverage']:.3f}" for k in others]
            lines.append(f"| {b} % | " + " | ".join(cells) + " |")
    if cv or bc:
        lines.append("")  # a table ends before the list that follows
    lp = a["level_prefixes"]
    lines.append(
        "- level prefixes: "
        + ", ".join(f"level ≤{k}: {lp['counts'][k]:,} G, {v['psnr']:.2f} dB" for k, v in lp["nvs"].items())
    )
    sd = a["single_asset_vs_discrete"]
    lines.append(f"- one stream {sd['stream_bytes']:,} B vs separately stored budgets {sd['discrete_sum_bytes']:,} B")
    if a.get("compare"):
        t = r.get("time_to_psnr", {})
        train = r.get("training", {})
        lines += [
            "",
            "Other runs on the same views (100 %; level prefixes are NVS PSNR of levels ≤ k). *val tail*: "
            "mean ± sd of the last evaluations in the run's training log (8 views each): how much a run's "
            "score moves near the end of training. Training seconds depend on what else ran on the machine. "
            "This run is scored from its quantised stream, the others from their float32 avatars (the "
            "quantisation loss is in the list above).",
            "",
            f"| run | Gaussians | NVS PSNR | Δ vs this run | level prefixes | val tail | iterations / seconds "
            f"to {t.get('target', float('nan')):.2f} dB | training s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        main_psnr = r["budgets"]["100"]["nvs"]["psnr"] if "100" in r["budgets"] else None
        entries = (
            {"this run": {"gaussians": r["gaussians"], "nvs": {"psnr": main_psnr}, "level_prefixes_nvs": lp["nvs"]}}
            if main_psnr is not None
            else {}
        )
        entries.update(a["compare"])
        for name, c in entries.items():
            label = f"`{r['name']}` (this run)" if name == "this run" and r.get("name") else f"`{name}`"
            pref = ", ".join(f"≤{k}: {v['psnr']:.2f}" for k, v in c["level_prefixes_nvs"].items())
            tr = train.get(name, {})
            tail = f"{tr['val_tail_mean']:.2f} ± {tr['val_tail_sd']:.2f}" if tr.get("val_tail_sd") is not None else ""
            its = t.get("iterations", {})
            reach = (
                "" if name not in its else "never" if its[name] is None else f"{its[name]} / {t['seconds'][name]:.0f}"
            )
            secs = f"{tr['seconds']:.0f}" if tr.get("seconds") is not None else ""
            delta = c["nvs"]["psnr"] - main_psnr if main_psnr is not None else float("nan")
            lines.append(
                f"| {label} | {c['gaussians']:,} | {c['nvs']['psnr']:.2f} | {delta:+.2f} | {pref} | {tail} | "
                f"{reach} | {secs} |"
            )
        lines.append("")
    if r.get("seed_groups"):
        lines += [
            "",
            "Runs that differ only by their seed (`NAME_seed<k>`; the run named without a suffix is seed 0): "
            "mean ± sd over seeds (sample sd), the range, and the mean level-prefix PSNRs. "
            "All scored from float32 avatars.",
            "",
            "| runs | seeds | Gaussians | NVS PSNR mean ± sd | min .. max | level prefixes (mean) |",
            "|---|---|---|---|---|---|",
        ]
        for group, g in r["seed_groups"].items():
            pref = ", ".join(f"≤{k}: {v:.2f}" for k, v in g["level_prefixes_nvs_mean"].items())
            lines.append(
                f"| `{group}` | {g['n']} | {g['gaussians_mean']:,.0f} ± {g['gaussians_sd']:,.0f} | "
                f"{g['nvs_psnr_mean']:.3f} ± {g['nvs_psnr_sd']:.3f} | {g['nvs_psnr_min']:.2f} .. "
                f"{g['nvs_psnr_max']:.2f} | {pref} |"
            )
        lines.append("")
    if r.get("seed_pairs"):
        lines += [
            "",
            "Paired by seed (the seed draws the sequence of training views, so with all levels "
            "supervised two runs with the same seed see the same views in the same order): NVS PSNR of "
            "the first minus the second, per seed and mean ± sd.",
            "",
            "| first | second | seeds | difference per seed (dB) | mean ± sd (dB) |",
            "|---|---|---|---|---|",
        ]
        for p in r["seed_pairs"]:
            per = ", ".join(f"{d:+.3f}" for d in p["diffs"])
            lines.append(
                f"| `{p['a']}` | `{p['b']}` | {', '.join(map(str, p['seeds']))} | {per} | "
                f"{p['mean']:+.3f} ± {p['sd']:.3f} |"
            )
        lines.append("")
    if "depth_vs_detail" in r:
        d = r["depth_vs_detail"]
        if np.isfinite(d["spearman"]):
            rho = f"Spearman ρ = {d['spearman']:.3f}"
        else:  # no rank correlation when every face is at one depth (no growth) or detail is flat
            rho = "no rank correlation (every face at one depth, or the same detail everywhere)"
        lines += [
            "",
            f"Depth follows detail: {rho}; mean depth on the most detailed quarter of "
            f"faces {d['mean_depth_detailed_quartile']:.2f} vs smoothest quarter {d['mean_depth_smooth_quartile']:.2f}.",
        ]
    lines += ["", "## Figures", ""] + [f"![{k}]({v})" for k, v in r.get("figures", {}).items()]
    # Blocks open and close with a blank line; one between two blocks is enough.
    return re.sub(r"\n{3,}", "\n\n", "\n".join(lines)) + "\n"


# --------------------------------------------------------------------------------------
# the paper's layout (scripts/evaluate.py --paper-table)
# --------------------------------------------------------------------------------------


def full_resolution_strip(path, renderer, info, budgets, view_index=0):
    """One view at each budget and the ground truth side by side at the dataset's own pixel
    size (no resampling), each under a one-line label."""
    from PIL import Image, ImageDraw, ImageFont

    view = int(renderer.views[min(view_index, len(renderer.views) - 1)])
    sample = renderer.dataset[view]
    panels, labels = [], []
    for b in budgets:
        n = int(info.count_for_percent(b))
        image, _ = renderer.render(view, renderer.first(n))
        panels.append(image)
        labels.append(f"{b:g}%" + (f" ({n:,} Gaussians)" if renderer.dataset[view].image.shape[1] >= 160 else ""))
    panels.append(sample.image)
    labels.append("ground truth")
    h, w = sample.image.shape[:2]
    # Labels sized to the panels (the default 10 px font was ~3 px high once a 2,750 px sheet was
    # shown at page width); Pillow's own scalable font, else its bitmap one.
    size = max(10, w // 16)
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        font, size = ImageFont.load_default(), 10
    bar = size + 8
    sheet = Image.new("RGB", (w * len(panels), h + bar), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for k, (im, label) in enumerate(zip(panels, labels)):
        sheet.paste(Image.fromarray(np.clip(np.round(np.asarray(im) * 255), 0, 255).astype(np.uint8)), (k * w, bar))
        draw.text((k * w + 4, 3), label, fill=(0, 0, 0), font=font)
    from ..io.atomic import atomic_save_image

    return atomic_save_image(sheet, path)


def _group_means(seeds: dict, xs: np.ndarray) -> np.ndarray:
    """A group's mean PSNR over its seeds at counts ``xs`` (interpolated in log Gaussians)."""
    return np.mean(
        [
            np.interp(np.log(xs), np.log([p["gaussians"] for p in pts]), [p["psnr"] for p in pts])
            for pts in seeds.values()
        ],
        axis=0,
    )


def curves_crossover(curves: dict, a: str = "adaptive", b: str = "uniform"):
    """(lo, hi, last): the Gaussian counts both groups' curves cover and the largest count in
    that range where ``b``'s mean is level with or above ``a``'s (None: ``a`` ahead throughout);
    None when the groups share no range."""
    if a not in curves or b not in curves:
        return None
    every = [pts for group in (a, b) for pts in curves[group].values()]
    lo = max(min(p["gaussians"] for p in pts) for pts in every)
    hi = min(max(p["gaussians"] for p in pts) for pts in every)
    if not hi > lo:
        return None
    xs = np.geomspace(lo, hi, 64)
    behind = np.flatnonzero(_group_means(curves[b], xs) >= _group_means(curves[a], xs))
    return int(lo), int(hi), (int(xs[behind[-1]]) if len(behind) else None)


def seed_curves_vs_gaussians(path, curves: dict, views: int | None = None):
    """NVS PSNR against Gaussians rendered (stream prefixes) for groups of runs over seeds
    ({group: {seed: [{"gaussians", "psnr"}, ...]}}): each seed thin, and mean ± sd of the
    seeds at the counts they share. ``views``: how many NVS views each point scores (the
    label says it: a table scored on other views has other values)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.2, 3.8))
    for i, (group, seeds) in enumerate(curves.items()):
        colour = f"C{i}"
        for seed, pts in seeds.items():
            ax.plot([p["gaussians"] for p in pts], [p["psnr"] for p in pts], "-", lw=0.8, alpha=0.5, color=colour)
        if len(seeds) > 1:
            # the seeds' curves at common counts (interpolated in log Gaussians)
            lo = max(min(p["gaussians"] for p in pts) for pts in seeds.values())
            hi = min(max(p["gaussians"] for p in pts) for pts in seeds.values())
            if hi > lo:
                xs = np.geomspace(lo, hi, 8)
                ys = np.array(
                    [
                        np.interp(np.log(xs), np.log([p["gaussians"] for p in pts]), [p["psnr"] for p in pts])
                        for pts in seeds.values()
                    ]
                )
                ax.errorbar(
                    xs,
                    ys.mean(0),
                    yerr=ys.std(0, ddof=1),
                    fmt="-o",
                    ms=3,
                    capsize=2,
                    color=colour,
                    label=f"{group}: mean ± sd over {len(seeds)} seeds",
                )
                continue
        pts = next(iter(seeds.values()))
        ax.plot(
            [p["gaussians"] for p in pts], [p["psnr"] for p in pts], "-o", ms=3, color=colour, label=f"{group} (1 seed)"
        )
    ax.set_xscale("log")
    ax.set_xlabel("Gaussians rendered (stream prefix, log)")
    ax.set_ylabel("NVS PSNR in mask (dB)" + (f", {views} views" if views else ""))
    ax.set_title("Adaptive against uniform subdivision", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return _save(fig, path)


def run_resources(run: str) -> dict:
    """Training iterations and seconds (metrics log), wall seconds summed over invocations and
    peak resident memory (RUN/resources.jsonl from scripts/train.py; None when absent)."""
    import os

    out = {"iterations": None, "train_seconds": None, "wall_seconds": None, "peak_rss_mb": None}
    log = os.path.join(run, "metrics.jsonl")
    if os.path.exists(log):
        rows = read_log(log)
        if rows:
            out["iterations"], out["train_seconds"] = rows[-1].get("iteration"), rows[-1].get("seconds")
    res = os.path.join(run, "resources.jsonl")
    if os.path.exists(res):
        rows = read_log(res)
        if rows:
            out["wall_seconds"] = float(sum(r.get("wall_seconds", 0.0) for r in rows))
            out["peak_rss_mb"] = float(max(r.get("peak_rss_mb", 0.0) for r in rows))
    return out


def _fmt(x, spec, none="–"):
    return none if x is None else format(x, spec)


def paper_table_markdown(r: dict) -> str:
    """The report in the paper's layout (Table 1, Table 3, adaptive vs uniform, resources,
    acceptance checks), our numbers beside the paper's."""
    from .sweep import PAPER_GAUSSIANAVATARS

    pt = r["paper_table"]
    ds = r.get("data_summary") or {}
    size = f"{ds['width']}x{ds['height']} px" if {"width", "height"} <= set(ds) else "?"
    lines = [
        "# The paper's tables on our data",
        "",
        f"- run: `{r['run']}`; data: `{r['data']}` ({size}, template {ds.get('faces', '?'):,} faces)"
        if isinstance(ds.get("faces"), int)
        else f"- run: `{r['run']}`; data: `{r['data']}` ({size})",
        f"- machine: {r['machine']}",
        f"- date: {r['date']}",
        f"- command: `{r['command']}`",
        f"- stream: {r['stream_bytes']:,} bytes, {r['gaussians']:,} Gaussians, levels {r['level_counts']}",
        "- paper: ProgressiveAvatars on NeRSemble at 550x802 px, RTX 4090 (DESIGN.md). Ours: the synthetic head, "
        "scored from the quantised stream; PSNR/SSIM inside the foreground mask; render ms of the CPU renderer "
        "at the dataset's size (the paper gives FPS on a GPU).",
        "",
    ]
    if r.get("about"):
        lines += [r["about"], ""]
    lines += [
        "## Table 1: budgets",
        "",
        "| budget | NVS PSNR / SSIM | paper | NVS gap to 100 % (paper) | NES PSNR / SSIM | paper | "
        "NES gap (paper) | Gaussians (paper) | MB (paper) | render ms (paper FPS) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, row in sorted(pt["table1"].items(), key=lambda kv: float(kv[0])):
        p = row.get("paper", {})
        lines.append(
            f"| {key} % | {row['nvs_psnr']:.2f} / {row['nvs_ssim']:.3f} | "
            f"{_fmt(p.get('nvs_psnr'), '.2f')} / {_fmt(p.get('nvs_ssim'), '.3f')} | "
            f"{_fmt(row.get('nvs_gap'), '.2f')} ({_fmt(p.get('nvs_gap'), '.2f')}) | "
            f"{row['nes_psnr']:.2f} / {row['nes_ssim']:.3f} | "
            f"{_fmt(p.get('nes_psnr'), '.2f')} / {_fmt(p.get('nes_ssim'), '.3f')} | "
            f"{_fmt(row.get('nes_gap'), '.2f')} ({_fmt(p.get('nes_gap'), '.2f')}) | "
            f"{row['gaussians']:,} ({_fmt(p.get('gaussians'), ',')}) | {row['mb']:.2f} ({_fmt(p.get('mb'), '.2f')}) | "
            f"{row['render_ms']:.0f} ({_fmt(p.get('fps'), 'd')}) |"
        )
    g = PAPER_GAUSSIANAVATARS
    lines += [
        "",
        f"Paper's GaussianAvatars: NVS {g[0]:.2f} / {g[1]:.3f}, NES {g[2]:.2f} / {g[3]:.3f}, "
        f"{g[4]:,} Gaussians, {g[5]:.2f} MB.",
        "",
        "## Table 3: ablations (NVS PSNR)",
        "",
    ]
    t3 = pt["table3"]
    partner = t3.get("finest_only_35", {}).get("partner")
    if partner:  # every multi-level / finest-only row below compares these two runs
        lines += [
            f"The multi-level / finest-only rows compare {partner} with {t3['finest_only_35']['finest_run']}, "
            "two runs trained alike but for the supervision (their settings: the Training table), not this run.",
            "",
        ]
    lines += ["| ablation | ours | paper |", "|---|---|---|"]
    if "finest_only_35" in t3:
        f = t3["finest_only_35"]
        lines.append(
            f"| 35 %: multi-level supervision / finest level only | {f['multi_level']:.2f} / "
            f"{f['finest_only']:.2f} | {f['paper'][0]:.2f} / {f['paper'][1]:.2f} |"
        )
    else:
        lines.append("| 35 %: finest level only | not run (no --finest-only) | 29.87 / 20.06 |")
    if "finest_only_35_level_order" in t3:
        f = t3["finest_only_35_level_order"]
        lines.append(
            f"| 35 %, both streams in the paper's order (every level whole before the next, stream version 4): "
            f"multi-level supervision / finest level only | {f['multi_level']:.2f} / {f['finest_only']:.2f} | "
            f"{f['paper'][0]:.2f} / {f['paper'][1]:.2f} |"
        )
    for b, f in t3.get("finest_only_short", {}).items():  # not in the paper's table
        lines.append(
            f"| {b} %: multi-level supervision / finest level only | {f['multi_level']:.2f} / "
            f"{f['finest_only']:.2f} | no number |"
        )
    ro = t3["random_order_25"]
    lines.append(
        f"| 25 %, level by level: importance-ranked / random within levels | {ro['ranked']:.2f} / {ro['random']:.2f} | "
        f"{ro['paper'][0]:.2f} / {ro['paper'][1]:.2f} |"
    )
    if ro.get("stream") is not None:
        lines.append(f"| 25 %: the stream's own order (levels interleaved) | {ro['stream']:.2f} | no number |")
    io = t3["importance_only_50"]
    lines.append(
        f"| 50 %: the stream's order (parents first) / importance only | {io['levels']:.2f} / "
        f"{io['importance_only']:.2f} | holes (no number) |"
    )
    vs = r.get("adaptive_vs_uniform")
    lines += ["", "## Adaptive against uniform subdivision at matched Gaussian counts", ""]
    if vs:
        lines += [
            "Both streams cut to the smaller of the two runs' Gaussian counts (same seed), NVS PSNR.",
            "",
            "| seed | Gaussians | adaptive | uniform | adaptive − uniform | totals (adaptive / uniform) |",
            "|---|---|---|---|---|---|",
        ]
        for p in vs["pairs"]:
            lines.append(
                f"| {p['seed']} | {p['gaussians']:,} | {p['adaptive']:.2f} | {p['uniform']:.2f} | "
                f"{p['diff']:+.2f} | {p['adaptive_total']:,} / {p['uniform_total']:,} |"
            )
        lines.append(f"| mean ± sd | | | | {vs['mean']:+.2f} ± {_fmt(vs['sd'], '.2f')} ({vs['n']} seeds) | |")
    else:
        lines.append("not run (no --uniform)")
    cross = curves_crossover(r.get("quality_curves") or {})
    if cross:
        lo, hi, last = cross
        on = f" on {r['quality_curves_views']} NVS views" if r.get("quality_curves_views") else ""
        lines += [
            "",
            f"Along the streams (the plot{on}, so its values differ from the table's; means over the seeds, "
            f"{lo:,} to {hi:,} Gaussians): "
            + (
                f"uniform is level with or above adaptive up to about {last:,} Gaussians, adaptive ahead above."
                if last
                else "adaptive is ahead at every count."
            ),
        ]
    lines += [
        "",
        "## Training",
        "",
        "| run | iterations | training s (steps) | wall s (all invocations) | peak RSS MB | settings unlike this run's |",
        "|---|---|---|---|---|---|",
    ]
    for name, res in r.get("resources", {}).items():
        lines.append(
            f"| {name} | {_fmt(res['iterations'], 'd')} | {_fmt(res['train_seconds'], '.0f')} | "
            f"{_fmt(res['wall_seconds'], '.0f')} | {_fmt(res['peak_rss_mb'], '.0f')} | "
            f"{_fmt(res.get('recipe'), 's', 'unknown (no config.json)')} |"
        )
    lines += [
        "",
        "## Acceptance (issue 17)",
        "",
        "| criterion | ours | target | paper | met |",
        "|---|---|---|---|---|",
    ]
    for name, c in pt["checks"].items():
        ours = c["ours"]
        ours = f"{ours:.3f}" if isinstance(ours, float) else str(ours)
        paper = c["paper"]
        paper = f"{paper:.3f}" if isinstance(paper, float) else ("–" if paper is None else str(paper))
        met = {True: "yes", False: "**no**", None: "?"}[c["ok"]]
        lines.append(f"| {name} | {ours} | {c['target']} | {paper} | {met} |")
    figs = r.get("figures", {})
    lines += ["", "## Figures", ""] + [
        f"![{k}]({v})" for k, v in figs.items() if k.startswith(("strip_full", "paper_quality", "depth", "psnr_vs"))
    ]
    return "\n".join(lines) + "\n"


def labelled_strip(path, panels, labels, title=None):
    """Pictures side by side (RGB/RGBA arrays in [0,1] or uint8), each with its label above it
    (budget, Gaussians, bytes: a strip readers can read without the caption)."""
    plt = _plt()
    h, w = np.asarray(panels[0]).shape[:2]
    fig, axes = plt.subplots(1, len(panels), figsize=(2.4 * len(panels), 2.4 * h / w + 0.5), squeeze=False)
    for ax, img, label in zip(axes[0], panels, labels):
        img = np.asarray(img)
        ax.imshow(img if img.dtype == np.uint8 else np.clip(img, 0, 1), interpolation="lanczos")
        ax.set_title(label, fontsize=9)
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)
