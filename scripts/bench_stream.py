"""Benchmark of the progressive stream: size per Gaussian, decode throughput, base-level cost.

    python scripts/bench_stream.py [--quick]

``run(quick=False)`` returns the Markdown section the script prints. The avatar is synthetic
(a ~10k-face sphere template grown to ~170k faces over three levels, random parameters):
sizes and speeds depend on the counts, not on the values.
"""

from __future__ import annotations

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap  # noqa: F401  (makes progressive_avatars importable, strips Blender's "--")

import datetime
import os
import platform
import sys
import tempfile
import time

import numpy as np


def build_avatar(quick: bool):
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.avatar.forest import Forest
    from progressive_avatars.core.synthetic.shapes import sphere_mesh

    from progressive_avatars.core.avatar.coarse import build_coarse

    rng = np.random.default_rng(0)
    verts, faces = sphere_mesh(80, 64) if not quick else sphere_mesh(30, 32)  # 10,112 / 1,856 faces
    coarse, counts = build_coarse(verts, faces)  # the default coarse levels, as trained avatars have
    forest = Forest(faces, coarse_faces=coarse, coarse_counts=counts)
    for frac in (1.0, 0.6, 0.45):  # 10k -> ~170k faces, like the paper's 10,144 -> 169,438
        leaves = forest.leaves()
        leaves = leaves[forest.level[leaves] == forest.max_level]
        forest.split(leaves[rng.random(len(leaves)) < frac])
    forest.split_logits[:] = rng.normal(0, 0.5, forest.split_logits.shape)
    N = forest.num_faces
    av = Avatar(
        forest,
        rng.normal(0, 0.3, (N, 3)),
        rng.normal(-1, 0.5, (N, 3)),
        rng.normal(size=(N, 4)),
        rng.normal(0, 2, N),
        rng.normal(0, 1, (N, 3)),
    )
    return verts, av, rng.random(N)


def _times(fns: dict, reps: int) -> dict:
    """{key: (best, median) wall seconds} of reps calls of each function, after one warm-up
    call each. The repetitions go round-robin over all functions, so that a slow spell of a
    shared machine lands on every measurement alike instead of on whichever ran then."""
    for fn in fns.values():
        fn()
    ts = {k: [] for k in fns}
    for _ in range(reps):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            ts[k].append(time.perf_counter() - t)
    return {k: (min(v), float(np.median(v))) for k, v in ts.items()}


def _readers(S, data: bytes, faces) -> dict:
    """The four measured ways of reading `data` (a function per stream: no shared loop variables)."""

    def verify():
        S.StreamReader(faces).feed(data)

    def verify_decode():
        r = S.StreamReader(faces)
        r.feed(data)
        r.arrays()

    def chunked():
        r = S.StreamReader(faces)
        for i in range(0, len(data), 65536):
            r.feed(data[i : i + 65536])
        r.avatar()

    def full():
        S.read_stream(data, template_faces=faces)

    return {"v": verify, "vd": verify_decode, "c": chunked, "f": full}


def _without_coarse(av):
    """The same avatar without its coarse levels (build_avatar's coarse roots are faces 0..C-1,
    the template's follow in template order; coarse faces have no children)."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.avatar.forest import Forest

    f, C = av.forest, av.forest.num_coarse
    ff = Forest(f.template_faces, np.where(f.parent[C:] >= 0, f.parent[C:] - C, -1), f.slot[C:], f.split_logits[C:])
    return Avatar(ff, *(getattr(av, n)[C:] for n in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc")))


def old_against_new(av, imp, reps) -> str:
    """f6907ae's read_stream against this tree's on the same version-2 stream (the avatar
    without its coarse levels: version 2 has none), and this tree's on versions 3, 4 and 5,
    round-robin in one process: the machine's speed, not the format's, moves the absolute
    figures between runs on different days."""
    import importlib

    from bench_train import OLD_COMMIT, old_package

    from progressive_avatars.core.stream import reader as S
    from progressive_avatars.core.stream import writer as W

    old_package()
    old = importlib.import_module("pa_old.core.stream")
    faces = av.forest.template_faces
    plain = _without_coarse(av)
    v2 = W.encode_stream(plain, imp[-plain.num_gaussians :], embed_template=False, version=2)
    v3 = W.encode_stream(av, imp, embed_template=False, version=3)
    v4 = W.encode_stream(av, imp, embed_template=False, version=4)
    v5 = W.encode_stream(av, imp, embed_template=False)
    fns = {
        f"{OLD_COMMIT} reader, version 2": lambda: old.read_stream(v2, template_faces=faces),
        "this reader, version 2": lambda: S.read_stream(v2, template_faces=faces),
        "this reader, version 3": lambda: S.read_stream(v3, template_faces=faces),
        "this reader, version 4": lambda: S.read_stream(v4, template_faces=faces),
        "this reader, version 5": lambda: S.read_stream(v5, template_faces=faces),
    }
    times = _times(fns, reps)
    sizes = {k: len({"2": v2, "3": v3, "4": v4, "5": v5}[k[-1]]) for k in fns}
    return (
        "Same run, read_stream of the quantised stream without template (MB/s, best / median): "
        + ", ".join(f"{k} {sizes[k] / 1e6 / t[0]:.0f} / {sizes[k] / 1e6 / t[1]:.0f}" for k, t in times.items())
        + "."
    )


def run(quick: bool = False) -> str:
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from progressive_avatars.core.stream import reader as S
    from progressive_avatars.core.stream import writer as W

    verts, av, imp = build_avatar(quick)
    reps = 3 if quick else 25
    lines = []
    rows = []
    per_feed = {}
    piecewise_gbit = float("nan")
    with tempfile.TemporaryDirectory() as d:
        results = {}
        for quant in (True, False):
            for embed in (True, False):
                p = os.path.join(d, f"s{quant}{embed}.pavs")
                t = time.perf_counter()
                info = W.write_stream(p, av, imp, quantize=quant, embed_template=embed)
                wt = time.perf_counter() - t
                with open(p, "rb") as fh:
                    data = fh.read()
                results[(quant, embed)] = (info, data, wt)
        fns = {}
        for (quant, embed), (info, data, wt) in results.items():
            faces = av.forest.template_faces if not embed else None
            for name, fn in _readers(S, data, faces).items():
                fns[(quant, embed, name)] = fn
        times = _times(fns, reps)
        for (quant, embed), (info, data, wt) in results.items():
            mb = len(data) / 1e6
            t_v, t_vd, t_c, t_f = (times[(quant, embed, name)] for name in ("v", "vd", "c", "f"))
            base = info.base_bytes
            rate = " / ".join  # best / median
            rows.append(
                f"| {'quantised' if quant else 'lossless'} | {'yes' if embed else 'no'} | {info.num_records:,} | "
                f"{len(data):,} | {len(data) / info.num_records:.2f} | {info.record_size} | {mb / t_v[0]:.0f} | "
                f"{rate(f'{mb / t:.0f}' for t in t_vd)} | {rate(f'{mb / t:.0f}' for t in t_c)} | "
                f"{rate(f'{mb / t:.0f}' for t in t_f)} | {base:,} ({info.num_template_faces:,}) | "
                f"{base * 8 / 10e6:.3f} | {wt:.2f} |"
            )
            feeds = -(-len(data) // 65536)
            per_feed[(quant, embed)] = (t_c[0] - t_f[0]) / feeds  # both end in an Avatar
            if quant and embed:
                piecewise_gbit = 8 * mb / t_c[0] / 1e3
    try:
        import numpy

        npv = numpy.__version__
    except Exception:  # pragma: no cover
        npv = "?"
    cmd = "python scripts/bench_stream.py" + (" --quick" if quick else "")
    lines += [
        "## Stream benchmark (core/stream/, docs/FORMAT.md)",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `{cmd}`",
        f"- machine: {platform.platform()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs "
        f"(shared; load average {os.getloadavg()[0]:.1f}), numpy {npv}, Python {platform.python_version()}",
        f"- avatar: {av.num_gaussians:,} Gaussians, levels {av.forest.level_counts().tolist()} (synthetic; best of {reps})",
        "",
        "Throughput is stream MB (10^6 bytes) per second of wall time, best / median of the repetitions:",
        "*verify* = StreamReader.feed of the whole stream (checksums + structure checks), *+decode* = plus",
        "decoding every parameter to float32 arrays, *read_stream* = bytes to an Avatar (forest included),",
        "*64 KiB* = StreamReader fed 64 KiB pieces (what the HTTP client feeds), then .avatar(). Product target:",
        "decoding (+decode, read_stream) >= 500 MB/s for quantised streams. Feeding in pieces adds a fixed cost",
        "per feed (about 40 numpy calls for the checks of a small batch); per 64 KiB feed, best case: "
        + ", ".join(
            f"{'quantised' if q else 'lossless'}{' + template' if e else ''} {t * 1e6:.0f} µs"
            for (q, e), t in per_feed.items()
        )
        + f" (against read_stream). The piecewise path keeps up with links up to {piecewise_gbit:.1f} Gbit/s. On a shared",
        "machine the spread between runs is large: compare numbers taken in the same conditions.",
        "",
        "| records | template embedded | Gaussians | bytes | bytes/Gaussian | record | verify MB/s | +decode MB/s | "
        "64 KiB pieces -> Avatar MB/s | read_stream MB/s | base level bytes (faces) | base s @ 10 Mbit/s | write s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        old_against_new(av, imp, reps),
        "",
    ]
    return "\n".join(lines)


def _arguments(argv):
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions (a quick look, not for the record)")
    return ap.parse_args(argv)


if __name__ == "__main__":
    print(run(quick=_arguments(_bootstrap.script_args()).quick))
