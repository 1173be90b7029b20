"""How much of the template's surface the coarse levels keep: this tree's decimation against
core/avatar/coarse.py at an older commit, on the templates of the given datasets.

    python scripts/bench_coarse.py --against COMMIT [--data runs/synthetic runs/synth_coarse]
                                   [--benchmarks docs/BENCHMARKS.md]

Per coarse level (the default fractions): triangles; their area over the template's; the
fraction of the template's pixels the level's triangles cover in the dataset's val views
(the mesh silhouette a coarse prefix starts from, before training moves its Gaussians);
triangles whose normal faces against the surface (against the sum of their corners' vertex
normals); the worst and 10th-percentile triangle quality (4√3·area / Σ edge², 1 = equilateral).
Without --benchmarks the section is printed.
"""

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: F401  (puts the package on sys.path)
from bench_common import header, replace_section

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SECTION = "Coarse levels: the surface they keep (issue 16)"


def old_coarse(commit):
    """(short rev, core/avatar/coarse.py at `commit` as a module of its own)."""
    rev = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", commit], check=True, capture_output=True)
    rev = rev.stdout.decode().strip()
    src = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:core/avatar/coarse.py"], check=True, capture_output=True)
    path = os.path.join(tempfile.mkdtemp(prefix="pa_coarse_"), f"coarse_{rev}.py")
    with open(path, "wb") as fh:
        fh.write(src.stdout)
    spec = importlib.util.spec_from_file_location(f"coarse_{rev}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return rev, mod


def _pixels(v, tris, cam, bary):
    """Boolean image of the pixels hit by points sampled densely on the triangles."""
    p = np.einsum("kj,tjc->tkc", bary, v[tris]).reshape(-1, 3)
    uv, z = cam.project(p)
    u, w = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    ok = (z > 0) & (u >= 0) & (u < cam.width) & (w >= 0) & (w < cam.height)
    img = np.zeros((cam.height, cam.width), bool)
    img[w[ok], u[ok]] = True
    return img


def level_stats(v, faces, cf, counts, cams) -> list[dict]:
    n = 24  # samples per triangle edge: a coarse triangle spans many pixels
    a, b = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
    m = a + b <= n
    bary = np.stack([a[m], b[m], n - a[m] - b[m]], 1) / n
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    area0 = 0.5 * np.linalg.norm(fn, axis=1).sum()
    full = [_pixels(v, faces, c, bary) for c in cams]
    out, start = [], 0
    for count in counts:
        t = np.asarray(cf[start : start + count], np.int64)
        start += count
        tn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        area = 0.5 * np.linalg.norm(tn, axis=1)
        edges = (np.linalg.norm(v[t] - v[np.roll(t, 1, axis=1)], axis=2) ** 2).sum(1)
        quality = 4 * np.sqrt(3) * area / np.maximum(edges, 1e-30)
        cover = [float((_pixels(v, t, c, bary) & f).sum() / max(f.sum(), 1)) for c, f in zip(cams, full)]
        out.append(
            {
                "faces": int(count),
                "area": float(area.sum() / area0),
                "pixels": float(np.mean(cover)),
                "against": int(np.count_nonzero(np.einsum("ij,ij->i", tn, vn[t].sum(1)) <= 0)),
                "q_min": float(quality.min()),
                "q_p10": float(np.percentile(quality, 10)),
            }
        )
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", required=True, help="commit whose core/avatar/coarse.py is the old decimation")
    ap.add_argument("--data", nargs="+", default=["runs/synthetic", "runs/synth_coarse"])
    ap.add_argument("--views", type=int, default=8, help="val views per dataset")
    ap.add_argument("--benchmarks", help="write the section into this Markdown file (docs/BENCHMARKS.md)")
    args = ap.parse_args(argv)

    from progressive_avatars.core.avatar import coarse
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.render.importance import view_subset

    rev, old = old_coarse(args.against)
    cmd = "python scripts/bench_coarse.py " + " ".join(sys.argv[1:] if argv is None else argv)
    lines = [
        header(SECTION, cmd),
        f"Coarse levels (fractions {', '.join(f'1/{round(1 / f)}' for f in coarse.DEFAULT_FRACTIONS)} of the "
        f"template) built by core/avatar/coarse.py at {rev} (old: each Voronoi cell stands at its seed) and in "
        "this tree (new: at its vertex furthest out along the cell's mean normal). *area*: the level's "
        "triangle area over the template's; *pixels*: the fraction of the template mesh's pixels the level's "
        "triangles cover, mean over val views (the silhouette a coarse prefix starts from, before training "
        "moves its Gaussians); *against*: triangles facing against the surface; *quality*: worst / 10th "
        "percentile of 4√3·area/Σedge².\n",
        "| template | level | old: faces, area, pixels, against, quality | new: faces, area, pixels, against, quality |",
        "|---|---|---|---|---|",
    ]
    for data in args.data:
        ds = Dataset(data, "val")
        v = np.asarray(ds.canonical_vertices, np.float64)
        faces = np.asarray(ds.faces, np.int64)
        cams = [ds.frame_info(int(i)).camera for i in view_subset(len(ds), args.views)]
        rows = {}
        for name, mod in (("old", old), ("new", coarse)):
            cf, counts = mod.build_coarse(v, faces, coarse.DEFAULT_FRACTIONS)
            rows[name] = level_stats(v, faces, cf, counts, cams)
        for lv, (o, n) in enumerate(zip(rows["old"], rows["new"])):

            def cell(s):
                return f"{s['faces']}, {s['area']:.3f}, {s['pixels']:.3f}, {s['against']}, {s['q_min']:.2f} / {s['q_p10']:.2f}"

            lines.append(
                f"| {os.path.basename(os.path.normpath(data))} ({len(faces):,} faces) | {lv} | {cell(o)} | {cell(n)} |"
            )
    text = "\n".join(lines) + "\n"
    if args.benchmarks:
        replace_section(args.benchmarks, SECTION, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
