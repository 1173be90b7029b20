"""Budget sweeps and reports: quality against bytes for a progressive avatar.

An avatar here is in STREAM ORDER (core.stream.read_stream), so the Gaussians of a budget
are a prefix: faces [0, count). Metrics are PSNR/SSIM inside the foreground mask and on the
whole image (core.train.metrics), on the dataset's val (novel view, NVS) and test (novel
expression, NES) splits.
"""

from __future__ import annotations

import time

import numpy as np

from ..train import metrics
from ..avatar.avatar import Avatar, sh_to_rgb, sigmoid
from ..avatar.binding import compose, evaluate


class SplitRenderer:
    """Renders face subsets of one avatar on the views of one dataset split."""

    def __init__(self, avatar: Avatar, dataset, max_views: int | None = 32):
        from ..render.importance import view_subset

        self.avatar, self.dataset = avatar, dataset
        self.views = view_subset(len(dataset), max_views)
        self.weights = avatar.forest.weights()
        self.opac = sigmoid(avatar.opacity_logit)
        self.rgb = sh_to_rgb(avatar.f_dc)
        self.bg = np.asarray(dataset.background, np.float32)

    def first(self, n: int) -> np.ndarray:
        """The faces the avatar's first n stream records render (0..n-1 unless its stream
        interleaved roots with deeper faces, docs/FORMAT.md version 5, or holds coarse
        stand-ins whose regions are complete, Forest.drawn)."""
        f = self.avatar.forest
        if f.backdrop:  # every record renders (retired stand-ins behind the rest: render)
            return f.stream_ids(n)
        return f.drawn(f.stream_ids(n), records=n)

    def render(self, view: int, ids: np.ndarray, with_alpha: bool = False):
        """(image, seconds) of faces `ids` on a view, plus the alpha [H,W] with `with_alpha`:
        those of them that render (Forest.render_set: coarse stand-ins make way, or go behind
        the rest, once every template face is among them, or, for a prefix of the stream, their
        region's). No faces (a budget inside the header): the background, alpha 0."""
        from ..render.rasterize import render_numpy

        info = self.dataset.frame_info(int(view))
        ids, behind = self.avatar.forest.render_set(ids)
        if len(ids) == 0:
            cam = info.camera
            image = np.broadcast_to(self.bg, (cam.height, cam.width, len(self.bg))).astype(np.float32)
            alpha = np.zeros((cam.height, cam.width), np.float32)
            return (image, 0.0, alpha) if with_alpha else (image, 0.0)
        verts = self.dataset.vertices_at(info.timestep_index)
        av = self.avatar
        geo = evaluate(av.forest, verts, ids=ids, weights=self.weights)
        means, quats, scales = compose(geo.t, geo.r, geo.s, av.d_mu[ids], av.d_log_scale[ids], av.d_rot[ids])
        t0 = time.perf_counter()
        image, alpha, _ = render_numpy(
            means, quats, scales, self.opac[ids], self.rgb[ids], info.camera, self.bg, compute_contrib=False,
            behind=behind,
        )  # fmt: skip
        seconds = time.perf_counter() - t0
        return (image, seconds, alpha) if with_alpha else (image, seconds)

    def score(self, ids: np.ndarray, ssim: bool = True) -> dict:
        """Mean over the views: PSNR/SSIM in the mask and on the whole image, and mask
        coverage: the fraction of ground-truth mask pixels (mask >= 0.5) whose rendered alpha
        is >= 0.5 (a hole in a prefix shows here even where the background matches)."""
        psnr_m, ssim_m, psnr_w, ssim_w, ms, cov = [], [], [], [], [], []
        for v in self.views:
            image, seconds, alpha = self.render(v, ids, with_alpha=True)
            s = self.dataset[int(v)]
            psnr_m.append(metrics.psnr(image, s.image, s.mask))
            psnr_w.append(metrics.psnr(image, s.image))
            if ssim:
                ssim_m.append(metrics.ssim(image, s.image, s.mask))
                ssim_w.append(metrics.ssim(image, s.image))
            inside = np.asarray(s.mask) >= 0.5
            n_in = int(np.count_nonzero(inside))
            cov.append(float(np.count_nonzero(alpha[inside] >= 0.5)) / n_in if n_in else float("nan"))
            ms.append(seconds * 1e3)
        nan = float("nan")
        # Views with an empty mask have no in-mask score: left out of the in-mask means.
        return {
            "psnr": metrics.defined_mean(psnr_m),
            "ssim": metrics.defined_mean(ssim_m) if ssim else nan,
            "psnr_full_image": float(np.mean(psnr_w)),
            "ssim_full_image": float(np.mean(ssim_w)) if ssim else nan,
            "coverage": metrics.defined_mean(cov),
            "views": len(self.views),
            "views_with_empty_mask": int(np.count_nonzero(~np.isfinite(psnr_m))),
            "render_ms": float(np.median(ms)),
        }


def random_within_levels(level: np.ndarray, seed: int = 0) -> np.ndarray:
    """A stream order with each level's faces shuffled (the paper's 'W/ Random' ablation).

    Levels still go in order, so parents still precede children.
    """
    rng = np.random.default_rng(seed)
    keys = rng.random(len(level))
    return np.lexsort((keys, level))


def importance_only(importance: np.ndarray) -> np.ndarray:
    """Faces by descending importance ignoring levels (the 'importance-only' ablation)."""
    return np.argsort(-importance, kind="stable")


# --------------------------------------------------------------------------------------
# the paper's tables (scripts/evaluate.py --paper-table)
# --------------------------------------------------------------------------------------

# ProgressiveAvatars (CVPR 2026), NeRSemble at 550x802, RTX 4090 (DESIGN.md): Table 1 rows
# {budget: (NVS PSNR, NVS SSIM, NES PSNR, NES SSIM, Gaussians, MB, FPS)} and Table 3.
PAPER_TABLE1 = {
    "5": (27.89, 0.851, 25.13, 0.804, 10144, 2.60, 291),
    "25": (29.14, 0.892, 25.58, 0.846, 37302, 9.56, 278),
    "50": (30.03, 0.904, 25.71, 0.884, 84132, 21.56, 258),
    "100": (31.47, 0.929, 25.89, 0.908, 169438, 43.42, 260),
}
PAPER_GAUSSIANAVATARS = (31.10, 0.937, 25.80, 0.911, 163829, 41.90, 271)
PAPER_TABLE3 = {"mls_35": 29.87, "finest_only_35": 20.06, "ranked_25": 29.14, "random_25": 28.40}
# issue 17's acceptance thresholds (NVS dB unless said)
PAPER_TARGETS = {
    "detail_db": 3.0,
    "base_bytes_max": 0.06,
    "growth_min": 12.0,
    "gap_max": {"5": 3.0, "25": 1.5, "50": 0.8},
    "ranked_minus_random": 0.5,
    "mls_minus_finest": 5.0,
    "adaptive_minus_uniform": 0.3,
}


def _monotone(values) -> bool:
    v = list(values)
    return all(b >= a - 1e-9 for a, b in zip(v, v[1:]))


def paper_table(report: dict) -> dict:
    """Our numbers in the paper's layout from an evaluation report: Table 1 rows with gaps to
    100 % beside the paper's, Table 3's ablations, and issue 17's acceptance checks (each
    {"ours", "target", "paper", "ok"}; "ok" None where the report lacks what it needs)."""
    budgets = report["budgets"]
    full = budgets.get("100")
    rows = {}
    for key, e in budgets.items():
        if key not in PAPER_TABLE1:  # the paper's rows only (the report has more budgets)
            continue
        p = PAPER_TABLE1.get(key)
        row = {
            "nvs_psnr": e["nvs"]["psnr"],
            "nvs_ssim": e["nvs"]["ssim"],
            "nes_psnr": e["nes"]["psnr"],
            "nes_ssim": e["nes"]["ssim"],
            "gaussians": e["gaussians"],
            "mb": e["bytes"] / 1e6,
            "render_ms": e["render_ms"],
        }
        if full is not None:
            row["nvs_gap"] = full["nvs"]["psnr"] - e["nvs"]["psnr"]
            row["nes_gap"] = full["nes"]["psnr"] - e["nes"]["psnr"]
        if p is not None:
            row["paper"] = {
                "nvs_psnr": p[0],
                "nvs_ssim": p[1],
                "nes_psnr": p[2],
                "nes_ssim": p[3],
                "gaussians": p[4],
                "mb": p[5],
                "fps": p[6],
                "nvs_gap": PAPER_TABLE1["100"][0] - p[0],
                "nes_gap": PAPER_TABLE1["100"][2] - p[2],
            }
        rows[key] = row
    a = report["ablations"]
    t3 = {
        "random_order_25": {
            "ranked": a["random_order_25"]["ranked"]["psnr"],
            "random": a["random_order_25"]["random"]["psnr"],
            "stream": a["random_order_25"].get("stream", {}).get("psnr"),
            "paper": (PAPER_TABLE3["ranked_25"], PAPER_TABLE3["random_25"]),
        },
        "importance_only_50": {
            "levels": a["importance_only_50"]["levels_then_importance"]["psnr"],
            "importance_only": a["importance_only_50"]["importance_only"]["psnr"],
        },
    }
    if "finest_only_35" in a:
        f = a["finest_only_35"]
        t3["finest_only_35"] = {
            "multi_level": f["multi_level"]["psnr"],
            "finest_only": f["finest_only"]["psnr"],
            "paper": (PAPER_TABLE3["mls_35"], PAPER_TABLE3["finest_only_35"]),
            # None: this run is the multi-level side; else the partner trained as the finest-only run
            "partner": None
            if f.get("multi_level_run", report.get("run")) == report.get("run")
            else f["multi_level_run"],
            "finest_run": f.get("run"),
        }
    if "finest_only_35_level_order" in a:
        f = a["finest_only_35_level_order"]
        t3["finest_only_35_level_order"] = {
            "multi_level": f["multi_level"]["psnr"],
            "finest_only": f["finest_only"]["psnr"],
            "paper": (PAPER_TABLE3["mls_35"], PAPER_TABLE3["finest_only_35"]),
        }
    if "finest_only_short" in a:
        t3["finest_only_short"] = {
            b: {"multi_level": f["multi_level"]["psnr"], "finest_only": f["finest_only"]["psnr"]}
            for b, f in a["finest_only_short"].items()
        }
    T = PAPER_TARGETS
    checks = {}

    def check(name, ours, target, paper, ok):
        checks[name] = {"ours": ours, "target": target, "paper": paper, "ok": ok}

    # The paper's base is the whole template level: with coarse levels above it (DESIGN.md 7)
    # that is the prefix ending at level K, K the number of coarse levels.
    K = int(report.get("first_head", {}).get("coarse_levels", 0) or 0)
    lp = a["level_prefixes"]["nvs"]
    base = lp.get(K, lp.get(str(K)))
    # Without the 100 % budget (or the base prefix) a criterion is listed unscored, not left out.
    d = full["nvs"]["psnr"] - base["psnr"] if full is not None and base is not None else None
    check(
        "detail: NVS 100 % minus the base level alone (dB)",
        "not run" if d is None else d,
        f">= {T['detail_db']}",
        3.58,
        None if d is None else d >= T["detail_db"],
    )
    counts = report["level_counts"]
    base_share = report["base_bytes"] / report["stream_bytes"] if report.get("base_bytes") else None
    check(
        "base share of the stream's bytes (header"
        + (" with the embedded template" if report.get("template_embedded") else ", no template embedded")
        + ", included)",
        base_share,
        f"<= {T['base_bytes_max']}",
        2.60 / 43.42,
        None if base_share is None else base_share <= T["base_bytes_max"],
    )
    if report.get("base_bytes") and report.get("header_bytes") is not None:
        h = report["header_bytes"]
        share = (report["base_bytes"] - h) / max(report["stream_bytes"] - h, 1)
        check(
            "base share of the record bytes (header excluded)",
            share,
            f"<= {T['base_bytes_max']}",
            2.60 / 43.42,
            share <= T["base_bytes_max"],
        )
    growth = report["gaussians"] / max(sum(counts[: K + 1]), 1)
    check("growth: all Gaussians / base", growth, f">= {T['growth_min']}", 169438 / 10144, growth >= T["growth_min"])
    for key, limit in T["gap_max"].items():
        g = rows[key]["nvs_gap"] if key in rows and "nvs_gap" in rows[key] else None
        check(
            f"NVS gap to 100 % at {key} % (dB)",
            "not run" if g is None else g,
            f"<= {limit}",
            PAPER_TABLE1["100"][0] - PAPER_TABLE1[key][0] if key in PAPER_TABLE1 else None,
            None if g is None else g <= limit,
        )
    d = t3["random_order_25"]["ranked"] - t3["random_order_25"]["random"]
    check(
        "ranked minus random at 25 % (dB)",
        d,
        f">= {T['ranked_minus_random']}",
        29.14 - 28.40,
        d >= T["ranked_minus_random"],
    )
    if "finest_only_35" in t3:
        d = t3["finest_only_35"]["multi_level"] - t3["finest_only_35"]["finest_only"]
        check(
            "multi-level minus finest-only at 35 % (dB)",
            d,
            f">= {T['mls_minus_finest']}",
            29.87 - 20.06,
            d >= T["mls_minus_finest"],
        )
    else:
        check(
            "multi-level minus finest-only at 35 % (dB)", "not run", f">= {T['mls_minus_finest']}", 29.87 - 20.06, None
        )
    if "finest_only_35_level_order" in t3:  # the same, both streams in the paper's order
        f = t3["finest_only_35_level_order"]
        d = f["multi_level"] - f["finest_only"]
        check(
            "multi-level minus finest-only at 35 %, both in the paper's level-by-level order (dB)",
            d,
            f">= {T['mls_minus_finest']}",
            29.87 - 20.06,
            d >= T["mls_minus_finest"],
        )
    vs = report.get("adaptive_vs_uniform")
    if vs:
        ok = (
            vs["n"] > 1
            and vs["mean"] >= T["adaptive_minus_uniform"]
            and all(x >= T["adaptive_minus_uniform"] for x in vs["diffs"])
        )
        check(
            "adaptive minus uniform at matched Gaussians, NVS (dB), every seed",
            vs["mean"],
            f">= {T['adaptive_minus_uniform']} on > 1 seed",
            None,
            ok,
        )
    else:
        check(
            "adaptive minus uniform at matched Gaussians, NVS (dB), every seed",
            "not run",
            f">= {T['adaptive_minus_uniform']} on > 1 seed",
            None,
            None,
        )
    order = sorted(budgets, key=float)
    mono = all(_monotone([budgets[k][s][m] for k in order]) for s in ("nvs", "nes") for m in ("psnr", "ssim"))
    check("every budget's quality monotone (NVS, NES; PSNR, SSIM)", mono, "True", True, mono)
    return {"table1": rows, "table3": t3, "checks": checks}
