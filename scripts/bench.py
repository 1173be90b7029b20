"""Run the benchmarks and write docs/BENCHMARKS.md. Every figure there comes from here.

    python scripts/bench.py [--quick] [--only forest,render,...] [--report runs/report_cpu]

Sections: forest (evaluation speed, float32 precision), render (CPU rasteriser against the
dense reference), train (training iteration, f6907ae against this tree), data (loading), data_gen (synthetic dataset), stream (bytes, decode
speed), blender (import, slider, frame change), and the training/evaluation figures read
from an evaluation report folder written by scripts/evaluate.py.
"""

import argparse
import importlib
import json
import os
import sys
import time
import traceback

import _bootstrap

SECTIONS = ["forest", "render", "train", "data", "data_gen", "stream", "blender"]


def report_section(report_dir: str) -> str:
    path = os.path.join(report_dir, "report.json")
    if not os.path.exists(path):
        return ""
    with open(path) as fh:
        r = json.load(fh)
    md_path = os.path.join(report_dir, "report.md")
    body = open(md_path).read().split("\n", 1)[1] if os.path.exists(md_path) else ""
    rel = os.path.relpath(os.path.abspath(report_dir), os.path.join(_bootstrap.ROOT, "docs"))
    if not rel.startswith(".."):  # pictures inside docs/ are linked; elsewhere they are not in the repo
        body = body.replace("](", f"]({rel}/")
    return f"## Training and evaluation (from `{report_dir}/report.json`)\n{body}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", help="comma-separated sections: " + ",".join(SECTIONS) + " (none: only --report)")
    ap.add_argument("--report", action="append", default=[], help="evaluation report folder(s) to include")
    ap.add_argument("--out", default=os.path.join(_bootstrap.ROOT, "docs", "BENCHMARKS.md"))
    args = ap.parse_args(_bootstrap.script_args() if argv is None else argv)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    wanted = SECTIONS if not args.only else [s.strip() for s in args.only.split(",") if s.strip() not in ("", "none")]
    parts = {}
    # Keep sections from an earlier run when only some are re-measured.
    cache = args.out + ".sections.json"
    if os.path.exists(cache):
        with open(cache) as fh:
            parts = json.load(fh)
    for name in wanted:
        t0 = time.perf_counter()
        try:
            mod = importlib.import_module(f"bench_{name}")
            parts[name] = mod.run(quick=args.quick)
        except Exception:  # a broken section must not hide the others; its failure is reported
            parts[name] = f"## {name}\n\nbenchmark failed:\n\n```\n{traceback.format_exc()}```\n"
        print(f"{name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    for rep in args.report:
        parts["report:" + rep] = report_section(rep)
    with open(cache + ".tmp", "w") as fh:
        json.dump(parts, fh)
    os.replace(cache + ".tmp", cache)
    head = ("# Benchmarks\n\nEvery figure on this page is written by `python scripts/bench.py` (sections list their own "
            "machine, command and date). Speed is always reported with the accuracy it kept. The machine is a shared "
            "2-core VM: other work on it shows up as noise, so minima are given beside medians.\n\n")
    order = [s for s in SECTIONS if s in parts] + [k for k in parts if k not in SECTIONS]  # reports as first added
    text = head + "\n\n".join(parts[k] for k in order if parts[k]) + "\n"
    with open(args.out + ".tmp", "w") as fh:
        fh.write(text)
    os.replace(args.out + ".tmp", args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
