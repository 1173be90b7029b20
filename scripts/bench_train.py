"""Training-iteration speed, old (commit f6907ae, before issue 18) against new, in one run.

    python scripts/bench_train.py [--quick] [--data runs/synthetic]

The old code is the f6907ae tree of core/ extracted with `git archive` into
runs/bench_old_f6907ae (imported as its own package, so both run in this process) and is
timed interleaved with the working tree's: rep by rep, old then new, so the machine's load
hits both alike. Rows:

- cpu preset: `Trainer.step()` (binding, every level rendered, loss, backward, Adam) on the
  synthetic dataset (88x128 px) at 5k / 20k / 40k faces (the preset's cap).
- paper scale: the same step on 550x802 px views (the dataset's cameras and images scaled
  up) at ~150k faces over 5 levels, with the paper-scale supervision ("sampled": the finest
  level and one other) and with every level supervised.
- raster: the CPU rasteriser alone, 802x550 and 170k Gaussians (scripts/bench_render.py's
  head scene), forward + backward.

Accuracy kept: for the step rows, the first step of both runs starts from the same state
(same seed, same forest, same parameters); the table gives the relative difference of the
loss and of the whole parameter gradient between old and new (new computes the binding in
float64; old ran its weight recursion in float32). For the raster row, both against the
dense float64 reference (tests/reference_rasterizer.py) on a small scene.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sys as _sys

_sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401

import dataclasses  # noqa: E402
import importlib  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OLD_COMMIT = "f6907ae"
OLD_DIR = os.path.join(ROOT, "runs", "bench_old_f6907ae")


def old_package():
    """The f6907ae core/ as package `pa_old` (extracted once; numba caches its kernels there)."""
    pkg = os.path.join(OLD_DIR, "pa_old")
    if not os.path.exists(os.path.join(pkg, "core", "render.py")):
        os.makedirs(pkg, exist_ok=True)
        tar = subprocess.run(["git", "-C", ROOT, "archive", OLD_COMMIT, "core"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", pkg], input=tar, check=True)
        open(os.path.join(pkg, "__init__.py"), "w").close()
    if OLD_DIR not in sys.path:
        sys.path.insert(0, OLD_DIR)
    return importlib.import_module("pa_old.core.train"), importlib.import_module("pa_old.core.render")


class _Views:
    """A dataset stand-in: the training views scaled to another image size."""

    def __init__(self, ds, height, count=8):
        import torch

        from progressive_avatars.core.camera import Camera

        self.samples = []
        for i in np.linspace(0, len(ds) - 1, count).astype(int):
            s = ds[int(i)]
            c = s.camera
            k = height / c.height
            width = int(round(c.width * k))
            cam = Camera(c.R, c.t, c.fx * k, c.fy * k, c.cx * k, c.cy * k, width, height)
            img = torch.nn.functional.interpolate(torch.from_numpy(s.image).permute(2, 0, 1)[None], (height, width),
                                                  mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
            self.samples.append(dataclasses.replace(s, camera=cam, image=np.ascontiguousarray(img.numpy())))
        self.background = ds.background

    def __len__(self):
        return len(self.samples)

    def __getitem__(self, i):
        return self.samples[i]


def _grow(trainer, plan):
    """Split leaves by a fixed plan: per round, the fraction of the deepest leaves to split."""
    rng = np.random.default_rng(123)
    for frac in plan:
        forest = trainer.model.forest
        leaves = forest.leaves()
        leaves = leaves[forest.level[leaves] == forest.max_level]
        pick = np.sort(leaves[rng.random(len(leaves)) < frac])
        trainer.model.split(pick)
        trainer.opt.grow(trainer.model.params)
    trainer._reset_accumulators()


def _make(train_mod, data, out, supervision, plan, views=None):
    cfg = train_mod.config_for("cpu", supervision=supervision, seed=0)
    tr = train_mod.Trainer(data, out, cfg)
    if views is not None:
        tr.train = views
    _grow(tr, plan)
    captured = {}
    step = tr.opt.step

    def capture(params, lr_scale=None):
        if not captured:
            captured["grad"] = np.concatenate([p.grad.detach().double().numpy().ravel() for p in params.values()
                                               if p.grad is not None])
        return step(params, lr_scale)

    tr.opt.step = capture
    return tr, captured


def bench_steps(data, label, supervision, plan, reps, views=None):
    import torch

    old_train, _ = old_package()
    from progressive_avatars.core import train as new_train

    with tempfile.TemporaryDirectory() as tmp:
        old, old_cap = _make(old_train, data, os.path.join(tmp, "old"), supervision, plan, views)
        new, new_cap = _make(new_train, data, os.path.join(tmp, "new"), supervision, plan, views)
        assert old.model.num_faces == new.model.num_faces
        s_old = old.step()
        s_new = new.step()
        loss_err = abs(s_new["loss"] - s_old["loss"]) / abs(s_old["loss"])
        grad_err = float(np.linalg.norm(new_cap["grad"] - old_cap["grad"]) / np.linalg.norm(old_cap["grad"]))
        t_old, t_new = [], []
        for _ in range(reps):
            for tr, times in ((old, t_old), (new, t_new)):
                t0 = time.perf_counter()
                tr.step()
                times.append(time.perf_counter() - t0)
        levels = len(new._levels())
    del torch
    return dict(label=label, faces=new.model.num_faces, levels=levels, supervision=supervision,
                width=new.train[0].camera.width, height=new.train[0].camera.height, old=t_old, new=t_new,
                loss_err=loss_err, grad_err=grad_err)


def bench_raster(reps):
    import torch

    from bench_render import head_camera, head_scene
    from progressive_avatars.core.render import render as new_render

    _, old_render_mod = old_package()
    cam = head_camera(802, 550)
    params = [torch.from_numpy(x) for x in head_scene(170_000)]

    def run(fn):
        ps = [p.clone().requires_grad_(True) for p in params]
        t0 = time.perf_counter()
        out = fn(*ps, cam)
        ((out.image * 0.5).sum() + out.alpha.sum()).backward()
        return time.perf_counter() - t0, out

    run(old_render_mod.render)
    run(new_render)
    t_old, t_new = [], []
    for _ in range(reps):
        t_old.append(run(old_render_mod.render)[0])
        dt, out = run(new_render)
        t_new.append(dt)
    return dict(old=t_old, new=t_new, visible=int((out.radii > 0).sum()))


def raster_reference_errors():
    """Both rasterisers against the dense float64 reference on a small head-like scene:
    max abs image error and the worst relative gradient error over all inputs."""
    import torch

    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from bench_render import head_camera, head_scene
    from reference_rasterizer import render_reference

    from progressive_avatars.core.render import render as new_render

    _, old_render_mod = old_package()
    cam = head_camera(64, 64)
    params = [torch.from_numpy(x) for x in head_scene(400, seed=1)]
    params[2] = params[2] * 6.0
    bg = torch.tensor([0.2, 0.4, 0.1])
    g = torch.Generator().manual_seed(0)
    wi, wa = torch.randn(64, 64, 3, generator=g, dtype=torch.float64), torch.randn(64, 64, generator=g,
                                                                                   dtype=torch.float64)

    def grads(fn, dtype):
        ps = [p.detach().clone().to(dtype).requires_grad_(True) for p in params + [bg]]
        out = fn(*ps[:5], cam, ps[5])
        img, alpha = (out[0], out[1]) if isinstance(out, tuple) else (out.image, out.alpha)
        ((img.double() * wi).sum() + (alpha.double() * wa).sum()).backward()
        return img.detach().double(), [p.grad.double() for p in ps]

    ref_img, ref_g = grads(render_reference, torch.float64)
    rows = {}
    for name, fn in (("old", old_render_mod.render), ("new", new_render)):
        img, gr = grads(fn, torch.float32)
        rel = max(float((a - b).norm() / b.norm()) for a, b in zip(gr, ref_g))
        rows[name] = (float((img - ref_img).abs().max()), rel)
    return rows


def _fmt(times):
    t = sorted(times)
    return f"{t[0] * 1e3:.0f} / {t[len(t) // 2] * 1e3:.0f}"


def run(quick: bool = False, data: str | None = None) -> str:
    import numba
    import torch

    from bench_common import header

    data = data or os.path.join(ROOT, "runs", "synthetic")
    if not os.path.exists(os.path.join(data, "transforms_train.json")):
        raise FileNotFoundError(f"{data}: no synthetic dataset; make it with scripts/make_synthetic.py --out {data}")
    load0 = os.getloadavg()
    reps = 3 if quick else 6
    rows = []
    cpu_plans = [("cpu preset, 5k faces", []), ("cpu preset, ~20k faces", [1.0, 0.35]),
                 ("cpu preset, ~40k faces", [1.0, 0.9, 0.35])]
    if quick:
        cpu_plans = cpu_plans[1:2]
    for label, plan in cpu_plans:
        rows.append(bench_steps(data, label, "all", plan, reps))
        print(rows[-1]["label"], _fmt(rows[-1]["old"]), _fmt(rows[-1]["new"]), file=sys.stderr)
    from progressive_avatars.core.data import Dataset

    views = _Views(Dataset(data, "train", cache_images=16), 802)
    paper_plan = [1.0, 1.0, 0.45, 0.12]  # levels 0-4, ~150k faces
    for sup in ("sampled", "all"):
        rows.append(bench_steps(data, f"paper scale ({sup})", sup, paper_plan, max(2, reps // 2), views))
        print(rows[-1]["label"], _fmt(rows[-1]["old"]), _fmt(rows[-1]["new"]), file=sys.stderr)
    raster = bench_raster(reps)
    ref = raster_reference_errors()
    load1 = os.getloadavg()
    cmd = "python scripts/bench.py --only train" + (" --quick" if quick else "")
    lines = [header("Training iteration: f6907ae (old) against this tree (new), same run", cmd),
             f"- threads: numba {numba.get_num_threads()} ({numba.threading_layer()}), torch "
             f"{torch.get_num_threads()}; load average {load0[0]:.1f} at the start, {load1[0]:.1f} at the end "
             f"({os.cpu_count()} cores, shared with other jobs: read the ratios, taken from interleaved runs, "
             "rather than the absolute times)",
             "- old = `git archive f6907ae core` imported as its own package in the same process; each rep "
             "runs one old step then one new step; times are min / median ms over the reps",
             "- accuracy: loss and whole-gradient relative difference between old and new on the first step from "
             "an identical state (new binds in float64, old's forest weights were float32)",
             "",
             "| iteration | image | faces | levels rendered | old ms (min / median) | new ms (min / median) "
             "| speed-up (median) | loss diff | gradient diff |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        speed = np.median(r["old"]) / np.median(r["new"])
        lines.append(f"| {r['label']} | {r['width']}x{r['height']} | {r['faces']:,} | {r['levels']} "
                     f"| {_fmt(r['old'])} | {_fmt(r['new'])} | x{speed:.2f} | {r['loss_err']:.1e} "
                     f"| {r['grad_err']:.1e} |")
    speed = np.median(raster["old"]) / np.median(raster["new"])
    lines += [
        f"| raster only: 802x550, 170k Gaussians ({raster['visible']:,} visible), forward + backward | 802x550 "
        f"| - | 1 | {_fmt(raster['old'])} | {_fmt(raster['new'])} | x{speed:.2f} | - | - |",
        "",
        "Against the dense float64 reference (64x64, 400 head-scene Gaussians, float32 inputs): old max image "
        f"error {ref['old'][0]:.1e}, worst relative gradient error {ref['old'][1]:.1e}; new {ref['new'][0]:.1e}, "
        f"{ref['new'][1]:.1e}.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    args = _bootstrap.script_args()
    print(run(quick="--quick" in args))
