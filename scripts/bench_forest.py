"""Forest evaluation speed and float32 precision (issue: foundation).

python scripts/bench_forest.py
"""

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap  # noqa: F401
import numpy as np
from bench_common import best_of, header


def sphere(n_lat, n_lon, radius=0.1):
    import os
    import sys

    sys.path.insert(0, os.path.dirname(_bootstrap.ROOT))
    sys.path.insert(0, _bootstrap.ROOT)
    from progressive_avatars.core.synthetic.shapes import sphere_mesh

    return sphere_mesh(n_lat, n_lon, radius)


def grown_forest(faces, target, rng):
    from progressive_avatars.core.avatar.forest import Forest

    f = Forest(faces)
    while f.num_faces < target:
        leaves = f.leaves()
        need = max(1, (target - f.num_faces) // 3)
        f.split(rng.choice(leaves, min(need, max(1, len(leaves) // 2)), replace=False))
    f.split_logits[:] = rng.normal(0, 0.5, f.split_logits.shape)
    return f


def run(quick=False) -> str:
    from progressive_avatars.core.avatar import binding

    rng = np.random.default_rng(0)
    verts, faces = sphere(70, 72)  # ~5k vertices, ~10k faces: FLAME-sized
    v = verts.astype(np.float32)
    out = [
        header("Forest evaluation (numpy, one frame)", "python scripts/bench.py --only forest"),
        f"Template: UV sphere, {len(verts)} vertices, {len(faces)} faces, radius 0.1 m. Time = `FaceEvaluator(forest, ids)(vertices)`"
        " (centroids, frames, scales of every face), min and median of 60 runs. Rows in root-grouped order"
        " (`ids = binding.root_grouped(forest)`, what the Blender preview uses) and in the forest's own order.\n",
        "| faces | max level | root-grouped min / median ms | forest order min / median ms |",
        "|---|---|---|---|",
    ]
    for target in [20000, 170000] if quick else [20000, 50000, 100000, 170000, 300000]:
        f = grown_forest(faces, target, rng)
        cells = []
        for ids in (binding.root_grouped(f), None):
            ev = binding.FaceEvaluator(f, ids=ids)
            lo, med = best_of(lambda: ev(v), repeat=60, warmup=3)
            cells.append(f"{lo * 1e3:.2f} / {med * 1e3:.2f}")
        out.append(f"| {f.num_faces:,} | {f.max_level} | {cells[0]} | {cells[1]} |")
    out += ["", "Depth (uniform subdivision of 600 root faces):", "", "| depth | faces | min ms |", "|---|---|---|"]
    from progressive_avatars.core.avatar.forest import Forest

    roots = rng.choice(len(faces), 600, replace=False)
    f = Forest(faces)
    current = roots
    for d in range(1, 6 if not quick else 4):
        current = f.split(current).ravel()
        ev = binding.FaceEvaluator(f, ids=binding.root_grouped(f))
        lo, _ = best_of(lambda: ev(v), repeat=20, warmup=2)
        out.append(f"| {d} | {f.num_faces:,} | {lo * 1e3:.2f} |")
    from progressive_avatars.core.synthetic.shapes import depth6_precision

    p = depth6_precision(rng)
    out += [
        "",
        f"Precision, float32 vs float64 at depth 6 ({p['roots']} root faces, metres; median finest face scale "
        f"{p['median_scale'] * 1e3:.3f} mm), max relative to each face's own scale: edges {p['edges']:.1e}, "
        f"frames {p['frames']:.1e}, scales {p['scales']:.1e} (target 1e-5).",
        "",
    ]
    return "\n".join(out)


if __name__ == "__main__":
    print(run())
