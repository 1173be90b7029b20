"""Evaluate a trained run at several transmission budgets and write a report (the command line of
core/evaluate/report.build_report).

    python scripts/evaluate.py --run RUN [--data DIR] --out REPORT_DIR [--budgets 1,2,5,10,25,50,100]
                               [--no-coarse-run RUN0] [--compare uniform_d2=RUN2 ...]

Writes REPORT_DIR/report.json, report.md and PNGs: PSNR and mask coverage against bytes (in
1 % steps), image strips (one view at each budget next to the ground truth), subdivision
depth on the head, and PSNR against training time. Budgets are percentages of the stream's
bytes, header included; a budget's Gaussians are the stream's whole records within that many
bytes. Mask coverage: the fraction of ground-truth mask pixels whose rendered alpha is >= 0.5.
Also: bytes and time to the first whole head at 1/10/100 Mbit/s, the order of the roots inside
their levels (forest / spatial / importance / both) at cuts inside the coarse and template
levels, and with --no-coarse-run the same model trained without coarse levels at 2/5/100 %.

The report scores the stream it writes as RUN/avatar.pavs, replacing the run's stream. That stream
leaves out the template (the receiver has it, as it has the tracked mesh that drives the avatar;
docs/FORMAT.md 2), so its budgets count what such a receiver is sent; export.py embeds the
template by default (a file readable without the mesh), so the two write the same bytes only
with --embed-template here. The report caches the importance ranking in RUN (importance*.npz,
keyed on the avatar and the data); runs named by --finest-only, --multi-level, --adaptive and
--uniform get theirs likewise. Evaluate a copy of a run you want left untouched.
"""

import argparse
import json
import os
import shlex
import sys

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--data")
    ap.add_argument("--flame-model", help="FLAME model for FLAME-mode datasets (default: the run's)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--budgets", default="1,2,5,10,25,50,100")
    ap.add_argument("--strips", default="1,2,5,25,100", help="budgets shown in the image strips")
    ap.add_argument("--views", type=int, default=24, help="views per split (spread evenly)")
    ap.add_argument("--curve-points", type=int, default=100, help="curve budgets (100: 1 %% steps)")
    ap.add_argument("--curve-views", type=int, default=8, help="NVS views per curve point")
    ap.add_argument(
        "--root-order",
        default="auto",
        choices=["forest", "spatial", "importance", "both", "auto"],
        help="order of the roots inside their levels in the written stream",
    )
    ap.add_argument(
        "--embed-template",
        action="store_true",
        help="embed the template in the evaluated stream, as export.py does by default (the same bytes as its "
        "stream; the budgets then count the template's bytes too). Default: left out, the receiver has it, "
        "as it has the tracked mesh that drives the avatar (FORMAT.md 2)",
    )
    ap.add_argument("--no-coarse-run", help="the same model trained without coarse levels (scored at 2/5/100 %%)")
    ap.add_argument("--compare", action="append", default=[], help="NAME=RUN: another run scored at 100 %%")
    ap.add_argument(
        "--budget-compare",
        action="append",
        default=[],
        metavar="NAME=RUN",
        help="another run written as this one's stream and scored at 1, 2, 5, 10, 25 and 100 %% of its own bytes",
    )
    ap.add_argument(
        "--name",
        default="",
        help="this run's name for grouping with compared runs of other seeds "
        "(NAME_seed1=RUN ...): the report then gives mean ± sd over the seeds",
    )
    ap.add_argument("--about", default="", help="a sentence on what this report compares (printed under its header)")
    ap.add_argument(
        "--paper-table",
        action="store_true",
        help="also write the paper's layout (paper_table.md): Table 1 with gaps to 100 %% beside the "
        "paper's, Table 3, adaptive vs uniform at matched Gaussian counts, full-resolution strips, "
        "training time and peak memory, and issue 17's acceptance checks",
    )
    ap.add_argument(
        "--finest-only",
        metavar="RUN",
        help="paper table: a finest-level-only run, scored at 35 %% of its stream against this run's 35 %%",
    )
    ap.add_argument(
        "--multi-level",
        metavar="RUN",
        help="paper table: the finest-only run's multi-level partner, trained with the same settings but "
        "the supervision (default: this run); the multi-level / finest-only rows then compare the two",
    )
    ap.add_argument(
        "--uniform",
        action="append",
        default=[],
        metavar="NAME=RUN",
        help="paper table: uniform-subdivision runs, NAME_seed<k> for seed k (no suffix: seed 0)",
    )
    ap.add_argument(
        "--adaptive",
        action="append",
        default=[],
        metavar="NAME=RUN",
        help="paper table: this method with other seeds, NAME_seed<k> (this run is seed 0)",
    )
    ap.add_argument(
        "--benchmarks",
        help="also write the report into this Markdown file (docs/BENCHMARKS.md), as "
        "the section named by --section (replaced in place when present)",
    )
    ap.add_argument("--section", default="", help="section name and title for --benchmarks")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(_bootstrap.script_args() if argv is None else argv)
    if args.benchmarks:  # written after the whole evaluation: a path that cannot be is refused now
        folder = os.path.dirname(os.path.abspath(args.benchmarks))
        if os.path.isdir(args.benchmarks):
            ap.error(f"--benchmarks {args.benchmarks}: a folder, not a Markdown file")
        if not os.path.isdir(folder):
            ap.error(f"--benchmarks {args.benchmarks}: no folder {folder} to write it in")

    from progressive_avatars.core.evaluate import plots
    from progressive_avatars.core.evaluate.report import ReportOptions, build_report
    from progressive_avatars.core.io.run import FolderBusyError

    def percents(option, text):
        try:
            return tuple(float(b) for b in text.split(",") if b.strip())
        except ValueError:
            ap.error(f"{option} takes comma-separated percentages, got {text!r}")

    try:
        opts = ReportOptions(
            run=args.run,
            out=args.out,
            data=args.data,
            flame_model=args.flame_model,
            budgets=percents("--budgets", args.budgets),
            strips=percents("--strips", args.strips),
            views=args.views,
            curve_points=args.curve_points,
            curve_views=args.curve_views,
            root_order=args.root_order,
            embed_template=args.embed_template,
            no_coarse_run=args.no_coarse_run,
            compare=tuple(args.compare),
            budget_compare=tuple(args.budget_compare),
            name=args.name,
            about=args.about,
            paper_table=args.paper_table,
            finest_only=args.finest_only,
            multi_level=args.multi_level,
            uniform=tuple(args.uniform),
            adaptive=tuple(args.adaptive),
            progress=not args.no_progress,
            command=shlex.join(["python", "scripts/evaluate.py"] + (sys.argv[1:] if argv is None else argv)),
        )
        report = build_report(opts)
    except (ValueError, FileNotFoundError, FolderBusyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # disk full, permission denied, ...: the report files written before are kept
        return _os_error(exc, args.out)
    if args.benchmarks:
        import bench_common

        body = plots.report_markdown(report).split("\n", 1)[1].replace("\n## ", "\n### ")
        rel = os.path.relpath(os.path.abspath(args.out), os.path.dirname(os.path.abspath(args.benchmarks)))
        body = body.replace("](", f"]({rel}/")
        title = args.section or os.path.basename(os.path.abspath(args.out))
        try:
            bench_common.replace_section(args.benchmarks, title, f"## {title}\n{body}")
        except OSError as exc:
            return _os_error(exc, args.benchmarks)
    print(
        json.dumps(
            {
                "report": os.path.join(args.out, "report.json"),
                "budgets": {k: [v["nvs"]["psnr"], v["nes"]["psnr"]] for k, v in report["budgets"].items()},
            }
        )
    )
    return 0


def _os_error(exc: OSError, where: str) -> int:
    """A clean message naming the file (or else ``where``) for an OSError; exit status 2."""
    path = exc.filename if exc.filename is not None else where
    print(f"error: {path}: {exc.strerror or exc}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
