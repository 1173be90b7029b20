"""Forest evaluation speed and float32 precision (issue: foundation).

    python scripts/bench_forest.py
"""

import _bootstrap  # noqa: F401
import numpy as np
from bench_common import best_of, header


def sphere(n_lat, n_lon, radius=0.1):
    import os
    import sys

    sys.path.insert(0, os.path.dirname(_bootstrap.ROOT))
    sys.path.insert(0, _bootstrap.ROOT)
    from tests.helpers import sphere_mesh

    return sphere_mesh(n_lat, n_lon, radius)


def grown_forest(faces, target, rng):
    from progressive_avatars.core.forest import Forest

    f = Forest(faces)
    while f.num_faces < target:
        leaves = f.leaves()
        need = max(1, (target - f.num_faces) // 3)
        f.split(rng.choice(leaves, min(need, max(1, len(leaves) // 2)), replace=False))
    f.split_logits[:] = rng.normal(0, 0.5, f.split_logits.shape)
    return f


def precision_depth6(rng):
    from progressive_avatars.core import binding
    from progressive_avatars.core.forest import Forest

    verts, faces = sphere(70, 72)
    forest = Forest(faces)
    current = rng.choice(len(faces), 40, replace=False)
    for _ in range(6):
        current = forest.split(current).ravel()
    forest.split_logits[:] = rng.normal(0, 1.0, forest.split_logits.shape)
    finest = np.flatnonzero(forest.level == 6)
    v32 = (verts + rng.normal(0, 1e-3, verts.shape)).astype(np.float32)
    W = forest.weights()
    g32 = binding.evaluate(forest, v32, ids=finest, weights=W, dtype=np.float32, with_vertices=True)
    g64 = binding.evaluate(forest, v32.astype(np.float64), ids=finest, weights=W, dtype=np.float64, with_vertices=True)
    s = g64.s
    return (np.abs(g32.edges - g64.edges).max(axis=(1, 2)) / s).max(), np.abs(g32.r - g64.r).max(), (np.abs(g32.s - g64.s) / s).max(), len(faces), np.median(s)


def run(quick=False) -> str:
    from progressive_avatars.core import binding

    rng = np.random.default_rng(0)
    verts, faces = sphere(70, 72)  # ~5k vertices, ~10k faces: FLAME-sized
    v = verts.astype(np.float32)
    out = [header("Forest evaluation (numpy, one frame)", "python scripts/bench.py --only forest"),
           f"Template: UV sphere, {len(verts)} vertices, {len(faces)} faces, radius 0.1 m. Time = `FaceEvaluator(forest)(vertices)`"
           " (centroids, frames, scales of every face), min and median of 30 runs.\n",
           "| faces | max level | min ms | median ms |", "|---|---|---|---|"]
    for target in ([20000, 170000] if quick else [20000, 50000, 100000, 170000, 300000]):
        f = grown_forest(faces, target, rng)
        ev = binding.FaceEvaluator(f)
        lo, med = best_of(lambda: ev(v), repeat=30, warmup=3)
        out.append(f"| {f.num_faces:,} | {f.max_level} | {lo * 1e3:.2f} | {med * 1e3:.2f} |")
    out += ["", "Depth (uniform subdivision of 600 root faces):", "", "| depth | faces | min ms |", "|---|---|---|"]
    from progressive_avatars.core.forest import Forest

    roots = rng.choice(len(faces), 600, replace=False)
    f = Forest(faces)
    current = roots
    for d in range(1, 6 if not quick else 4):
        current = f.split(current).ravel()
        ev = binding.FaceEvaluator(f)
        lo, _ = best_of(lambda: ev(v), repeat=20, warmup=2)
        out.append(f"| {d} | {f.num_faces:,} | {lo * 1e3:.2f} |")
    e, r, s, nroot, med = precision_depth6(rng)
    out += ["", f"Precision, float32 vs float64 at depth 6 ({nroot} root faces, metres; median finest face scale "
            f"{med * 1e3:.3f} mm), max relative to each face's own scale: edges {e:.1e}, frames {r:.1e}, scales {s:.1e} "
            "(target 1e-5).", ""]
    return "\n".join(out)


if __name__ == "__main__":
    print(run())
