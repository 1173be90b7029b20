"""Run the benchmarks and write docs/BENCHMARKS.md. Every figure there comes from here.

    python scripts/bench.py [--quick] [--only forest,render,...] [--report runs/report_cpu]
    python scripts/bench.py --only none --report DIR    # only add (or replace) a report's section
    python scripts/bench.py --only none --drop DIR      # only take a superseded report's section out

Without --only every section below is measured again first.

Sections: forest (evaluation speed, float32 precision), render (CPU rasteriser against the
dense reference), train (training iteration, f6907ae against this tree), data (loading), data_gen (synthetic dataset),
data_gen_paper (the paper-scale one, extrapolated from a reduced run), stream (bytes, decode
speed), blender (import, slider, frame change), compile (a first run's kernel compilation), and
the training/evaluation figures read from an evaluation report folder written by
scripts/evaluate.py.
"""

import argparse
import importlib
import json
import os
import sys
import time
import traceback

import _bootstrap

SECTIONS = ["forest", "render", "train", "data", "data_gen", "data_gen_paper", "stream", "blender", "compile"]
ORDER = SECTIONS + ["gpu"]


def report_section(report_dir: str) -> str:
    path = os.path.join(report_dir, "report.json")
    if not os.path.exists(path):
        return ""
    with open(path) as fh:
        json.load(fh)  # a torn report.json fails here, before its report.md is quoted
    md_path = os.path.join(report_dir, "report.md")
    body = open(md_path).read().split("\n", 1)[1] if os.path.exists(md_path) else ""
    paper_md = os.path.join(report_dir, "paper_table.md")  # evaluate.py --paper-table
    if os.path.exists(paper_md):
        body += "\n" + open(paper_md).read().replace("# The paper's tables", "### The paper's tables", 1)
    rel = os.path.relpath(os.path.abspath(report_dir), os.path.join(_bootstrap.ROOT, "docs"))
    if not rel.startswith(".."):  # pictures inside docs/ are linked; elsewhere they are not in the repo
        body = body.replace("](", f"]({rel}/")
    return f"## Training and evaluation (from `{report_dir}/report.json`)\n{body}"


HEADINGS = {  # how each section's heading starts, to read the current page back into sections
    "forest": "## Forest evaluation",
    "render": "## CPU rasteriser",
    "data": "## Dataset loading",
    "data_gen": "## Synthetic dataset generation",
    "stream": "## Stream benchmark",
    "blender": "## Blender extension",
    "data_gen_paper": "## Paper-scale synthetic dataset generation",
    "gpu": "## GPU:",
    "train": "## Training iteration:",
    "compile": "## First-run kernel compilation",
    "quant": "## Robust quantisation",  # scripts/bench_quant.py, included with --section quant=FILE
    # bench_render.py --against COMMIT --run RUN, with --section raster_levels=FILE (before the next: same prefix)
    "raster_levels": "## Rasteriser kernels, every level",
    # bench_render.py --against COMMIT --run RUN --one-image, with --section raster_trained=FILE
    "raster_trained": "## Rasteriser kernels, trained avatar",
    "raster_kernels": "## Rasteriser kernels",  # bench_render.py --against COMMIT, with --section raster_kernels=FILE
    "memory": "## Freed memory kept by training processes",  # bench_memory.py, with --section memory=FILE
}


def read_sections(path: str) -> dict:
    """The sections of an existing BENCHMARKS.md, keyed as this script keys them: a report's own
    ## headings (ablations, figures) stay inside its section. The page is the only record, so
    re-measuring one section on a fresh machine keeps the others."""
    if not os.path.exists(path):
        return {}
    parts, key, marked = {}, None, False
    for line in open(path).read().split("\n"):
        if line.startswith("<!-- section:"):  # a block written by bench_common.replace_section
            key, marked = "marked:" + line[len("<!-- section:") : -len(" -->")], True
            parts[key] = []
        elif marked:  # inside a marked block everything belongs to it, up to its end marker
            marked = not line.startswith("<!-- /section:")
        elif line.startswith("## "):
            found = next((k for k, h in HEADINGS.items() if line.startswith(h)), None)
            if found is None and line[3:].strip() in SECTIONS:  # a section whose benchmark failed
                found = line[3:].strip()
            if found is None and line.startswith("## Training and evaluation (from `"):
                found = "report:" + line.split("`")[1].rsplit("/report.json", 1)[0]
            if found is not None:
                key = found
                parts[key] = []
        if key is not None:
            parts[key].append(line)
    return {k: "\n".join(v).rstrip("\n") for k, v in parts.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", help="comma-separated sections: " + ",".join(SECTIONS) + " (none: only --report)")
    ap.add_argument("--report", action="append", default=[], help="evaluation report folder(s) to include")
    ap.add_argument(
        "--section",
        action="append",
        default=[],
        metavar="NAME=FILE",
        help="a section measured elsewhere (e.g. gpu=DIR/gpu.md from scripts/bench_gpu.py on a CUDA machine)",
    )
    ap.add_argument(
        "--drop",
        action="append",
        default=[],
        metavar="REPORT",
        help="remove a report folder's section (one superseded by another report)",
    )
    ap.add_argument("--out", default=os.path.join(_bootstrap.ROOT, "docs", "BENCHMARKS.md"))
    args = ap.parse_args(_bootstrap.script_args() if argv is None else argv)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    wanted = SECTIONS if not args.only else [s.strip() for s in args.only.split(",") if s.strip() not in ("", "none")]
    # Mistakes are refused before any benchmark runs (the whole set takes hours).
    unknown = [s for s in wanted if s not in SECTIONS]
    if unknown:
        ap.error(f"--only {args.only}: no section {', '.join(unknown)} (sections: {','.join(SECTIONS)}, or none)")
    for rep in args.report:
        if not os.path.isfile(os.path.join(rep, "report.json")):
            ap.error(f"--report {rep}: no report.json there (scripts/evaluate.py --out {rep} writes one)")
    for spec in args.section:
        name, _, path = spec.partition("=")
        if not name or not os.path.isfile(path):
            ap.error(f"--section {spec}: NAME=FILE with an existing FILE")
    parts = read_sections(args.out)  # sections not re-measured now are kept as they are
    for rep in args.drop:
        if "report:" + rep not in parts:
            ap.error(f"--drop {rep}: {args.out} has no section from {rep}/report.json")
    # The training section sets the process's malloc as training processes run (bench_train.run):
    # it runs last so that no other section is measured under that setting.
    for name in sorted(wanted, key=lambda n: n == "train"):
        t0 = time.perf_counter()
        try:
            mod = importlib.import_module(f"bench_{name}")
            parts[name] = mod.run(quick=args.quick).rstrip("\n")
        except Exception:  # a broken section must not hide the others; its failure is reported
            parts[name] = f"## {name}\n\nbenchmark failed:\n\n```\n{traceback.format_exc()}```\n"
        print(f"{name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    for rep in args.report:
        parts["report:" + rep] = report_section(rep)
    for rep in args.drop:
        parts.pop("report:" + rep, None)
    for spec in args.section:
        name, _, path = spec.partition("=")
        with open(path) as fh:
            parts[name] = fh.read().rstrip("\n")
    head = (
        "# Benchmarks\n\nEvery figure on this page is written by `python scripts/bench.py` (sections list their own "
        "machine, command and date). Speed is always reported with the accuracy it kept. The machine is a shared "
        "2-core VM: other work on it shows up as noise, so minima are given beside medians.\n\n"
    )
    order = [s for s in ORDER if s in parts] + [k for k in parts if k not in ORDER]  # reports as first added
    text = head + "\n\n".join(parts[k] for k in order if parts[k]) + "\n"
    with open(args.out + ".tmp", "w") as fh:
        fh.write(text)
    os.replace(args.out + ".tmp", args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
