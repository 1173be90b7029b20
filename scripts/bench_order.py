"""Stream order by units: the version 5 writer's order (core/stream/order.py: interleaved_order,
faces in units of most importance per record) against the order it replaced (each face ranked by
the lesser of its importance and its parent's key) and the paper's level order (version 4), on
trained runs: NVS PSNR in the mask at many budgets of each, and how much of the least
important tenth of the inner faces' importance is left (nearly transparent parents).

    python scripts/bench_order.py --data runs/synthetic_paper --run NAME=RUN [--run ...] [--write]
"""

from __future__ import annotations

import json
import os
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401
from bench_common import header, named_runs, replace_section, runs_parser  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BUDGETS = (5, 10, 15, 20, 25, 35, 50, 65, 80, 100)
SECTION = "Stream order by units (version 5)"
ORDERS = ("units", "capped", "levels")
LABELS = {
    "units": "units (version 5, this tree)",
    "capped": "capped (version 5 before 2026-11-28)",
    "levels": "levels (version 4)",
}


def capped_order(forest, importance, root_key=None) -> np.ndarray:
    """The version 5 writer's order before 2026-11-28: the lead as stream_order, then every other
    face by descending ``min(importance, the parent's key)`` (ties: level, face)."""
    from progressive_avatars.core.stream import order as orders

    key = np.asarray(importance, np.float64)
    lead = max(forest.num_coarse_levels, 1)
    level = forest.level.astype(np.int64)
    head = orders.stream_order(forest, key, root_key)[: int(np.count_nonzero(level < lead))]
    eff = key.copy()
    for lv in range(lead + 1, int(level.max(initial=lead)) + 1):
        ids = np.flatnonzero(level == lv)
        eff[ids] = np.minimum(key[ids], eff[forest.parent[ids]])
    rest = np.flatnonzero(level >= lead)
    rest = rest[np.lexsort((rest, level[rest], -eff[rest]))]
    return np.concatenate([head, rest]).astype(np.int64)


def score(run: str, data: str, views: int) -> dict:
    from progressive_avatars.core.avatar.avatar import sigmoid
    from progressive_avatars.core.evaluate.sweep import SplitRenderer
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.stream import writer
    from progressive_avatars.core.stream.reader import read_stream

    nvs = Dataset(data, "val")
    avatar = runs.load_run_avatar(run)
    W = runs.run_importance(run, avatar, data, progress=False)
    forest = avatar.forest
    inner = ~forest.is_leaf() & (forest.level >= max(forest.num_coarse_levels, 1))
    opacity = sigmoid(avatar.opacity_logit).reshape(-1)
    row = {
        "gaussians": avatar.num_gaussians,
        "inner": int(inner.sum()),
        "faint_inner": float(np.mean(opacity[inner] < 0.01)) if inner.any() else 0.0,
    }
    units = writer.interleaved_order
    with tempfile.TemporaryDirectory() as tmp:
        for name in ORDERS:
            path = os.path.join(tmp, name + ".pavs")
            try:
                if name == "capped":
                    writer.interleaved_order = capped_order  # the writer, with the former order
                info = writer.write_stream(
                    path,
                    avatar,
                    W,
                    quantize=True,
                    drop_sh=True,
                    version=4 if name == "levels" else 5,
                    vertices=nvs.canonical_vertices,
                    embed_template=False,  # budgets as evaluate.py's tables count them (the receiver has the template)
                )
            finally:
                writer.interleaved_order = units
            r = SplitRenderer(read_stream(path, template_faces=nvs.faces), nvs, views)
            row[name] = {b: r.score(r.first(int(info.count_for_percent(b))), ssim=False)["psnr"] for b in BUDGETS}
    return row


def section(rows: dict, command: str, views: int, about: str) -> str:
    lines = [header(SECTION, command), ""]
    if about:
        lines += [about, ""]
    lines += [
        f"NVS PSNR in the mask ({views} views) at a budget of each run's stream in three orders (bytes counted as in "
        "evaluate.py's tables: the template not embedded, the receiver has it). Faint inner: the "
        "share of inner faces (parents, of the template level and below) whose Gaussian has opacity below 0.01.",
        "",
        "| run | Gaussians | faint inner | order | " + " | ".join(f"{b} %" for b in BUDGETS) + " |",
        "|---|---|---|---|" + "---|" * len(BUDGETS),
    ]
    for name, r in rows.items():
        for k in ORDERS:
            lines.append(
                f"| {name} | {r['gaussians']:,} | {r['faint_inner']:.2f} | {LABELS[k]} | "
                + " | ".join(f"{r[k][b]:.2f}" for b in BUDGETS)
                + " |"
            )
    lines += ["", "Units minus capped, and units minus levels (dB), per budget:", ""]
    for name, r in rows.items():
        for k in ("capped", "levels"):
            diff = ", ".join(f"{b} % {r['units'][b] - r[k][b]:+.2f}" for b in BUDGETS)
            lines.append(f"- {name}, units minus {k}: {diff}")
    for name, r in rows.items():
        drops = [
            (a, b, r["units"][b] - r["units"][a]) for a, b in zip(BUDGETS, BUDGETS[1:]) if r["units"][b] < r["units"][a]
        ]
        text = ", ".join(f"{a} -> {b} % {d:+.2f}" for a, b, d in drops) if drops else "none"
        lines.append(f"- {name}: steps down in the units order: {text}")
    lines += ["", "Gaps to 100 % in the units order (issue 17's bounds: 3 dB at 5 %, 1.5 at 25 %, 0.8 at 50 %):", ""]
    for name, r in rows.items():
        u = r["units"]
        lines.append(f"- {name}: " + ", ".join(f"{b} % {u[100] - u[b]:.2f} dB" for b in (5, 25, 50)))
    return "\n".join(lines) + "\n"


def main():
    a = runs_parser(__doc__).parse_args(_bootstrap.script_args())
    rows = {}
    for name, run in named_runs(a.run, "bench_order", "avatar.npz").items():
        rows[name] = score(run, a.data, a.views)
        print(name, json.dumps(rows[name]), flush=True)
    command = "python scripts/bench_order.py --data " + a.data + "".join(f" --run '{s}'" for s in a.run)
    command += f" --views {a.views}" if a.views != 16 else ""
    command += " --about ..." if a.about else ""
    text = section(rows, command, a.views, a.about)
    print(text)
    if a.write:
        replace_section(os.path.join(ROOT, "docs", "BENCHMARKS.md"), SECTION, text)


if __name__ == "__main__":
    main()
