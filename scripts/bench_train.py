"""Training-iteration speed, old (commit f6907ae, before issue 18) against new, in one run.

    python scripts/bench_train.py [--quick] [--write]

(--write puts the section into docs/BENCHMARKS.md; scripts/bench.py --only train does too,
with the other sections it has cached.)

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
dense float64 reference (core/render/reference.py) on a small scene.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sys as _sys

_sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401

import contextlib  # noqa: E402
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
# The old column of the trained rows, which f6907ae cannot read: the tree before the latest
# speed work (update it when re-measuring after the next).
PREV_COMMIT = "56df5fa"


def _extract_core(commit, folder, name, marker):
    """``commit``'s core/ as package ``name`` under ``folder`` (extracted once, when ``marker``, a
    path inside core/, is missing; numba caches its kernels there), importable from then on."""
    pkg = os.path.join(folder, name)
    if not os.path.exists(os.path.join(pkg, "core", marker)):
        os.makedirs(pkg, exist_ok=True)
        tar = subprocess.run(["git", "-C", ROOT, "archive", commit, "core"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", pkg], input=tar, check=True)
        open(os.path.join(pkg, "__init__.py"), "w").close()
    if folder not in sys.path:
        sys.path.insert(0, folder)


def old_package():
    """The f6907ae core/ as package `pa_old`."""
    _extract_core(OLD_COMMIT, OLD_DIR, "pa_old", "render.py")
    return importlib.import_module("pa_old.core.train"), importlib.import_module("pa_old.core.render")


def prev_trainer(commit=PREV_COMMIT):
    """core/train/trainer.py of ``commit``'s core/, extracted as package `pa_<commit>` (its
    imports are relative, so it runs on its own kernels)."""
    name = f"pa_{commit}"
    _extract_core(commit, os.path.join(ROOT, "runs", f"bench_prev_{commit}"), name, os.path.join("train", "trainer.py"))
    return importlib.import_module(f"{name}.core.train.trainer")


# Where each module lives in this tree's tier folders; the old tree (f6907ae) is flat.
_NEW_PLACES = {
    "camera": "geometry.camera",
    "data": "io.dataset",
    "losses": "train.losses",
    "policies": "train.policies",
}


def _in(train_mod, name):
    """Module `name` of the package train_mod belongs to (old, previous and new each have their own)."""
    if train_mod.__name__.startswith("pa_old."):
        return importlib.import_module(train_mod.__name__.rsplit(".", 1)[0] + "." + name)
    package = train_mod.__name__.split(".core.")[0]  # progressive_avatars, or pa_<commit>
    return importlib.import_module(f"{package}.core.{_NEW_PLACES[name]}")


def _camera_as(cam, train_mod):
    Camera = _in(train_mod, "camera").Camera
    return Camera(cam.R, cam.t, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)


class _Views:
    """A dataset stand-in: the training views scaled to another image size (built with the
    Dataset and Camera of the code under test)."""

    def __init__(self, data, train_mod, height, count=8):
        import torch

        Camera = _in(train_mod, "camera").Camera
        ds = _in(train_mod, "data").Dataset(data, "train", cache_images=count)
        self.samples = []
        for i in np.linspace(0, len(ds) - 1, count).astype(int):
            s = ds[int(i)]
            c = s.camera
            k = height / c.height
            width = int(round(c.width * k))
            cam = Camera(c.R, c.t, c.fx * k, c.fy * k, c.cx * k, c.cy * k, width, height)
            img = torch.nn.functional.interpolate(
                torch.from_numpy(s.image).permute(2, 0, 1)[None], (height, width), mode="bilinear", align_corners=False
            )[0].permute(1, 2, 0)
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
    extra = {} if train_mod.__name__.startswith("pa_old.") else {"coarse_levels": ()}  # the same forest on both
    cfg = train_mod.config_for("cpu", supervision=supervision, seed=0, **extra)
    tr = train_mod.Trainer(data, out, cfg)
    if views is not None:
        tr.train = views
    _grow(tr, plan)
    captured = {}
    step = tr.opt.step

    def capture(params, lr_scale=None):
        if not captured:  # a parameter nothing depends on may have no gradient (old) or zeros (new)
            captured.update(
                {
                    k: (p.grad.detach().double().numpy().ravel() if p.grad is not None else np.zeros(p.numel()))
                    for k, p in params.items()
                }
            )
        return step(params, lr_scale)

    tr.opt.step = capture
    return tr, captured


def bench_steps(data, label, supervision, plan, reps, height=None):
    import torch

    old_train, _ = old_package()
    from progressive_avatars.core.train import trainer as new_train

    with tempfile.TemporaryDirectory() as tmp:
        views = [None if height is None else _Views(data, m, height) for m in (old_train, new_train)]
        old, old_cap = _make(old_train, data, os.path.join(tmp, "old"), supervision, plan, views[0])
        new, new_cap = _make(new_train, data, os.path.join(tmp, "new"), supervision, plan, views[1])
        assert old.model.num_faces == new.model.num_faces
        s_old = old.step()
        s_new = new.step()
        loss_err = abs(s_new["loss"] - s_old["loss"]) / abs(s_old["loss"])
        g_old = np.concatenate([old_cap[k] for k in sorted(old_cap)])
        g_new = np.concatenate([new_cap[k] for k in sorted(old_cap)])
        grad_err = float(np.linalg.norm(g_new - g_old) / np.linalg.norm(g_old))
        t_old, t_new, c_old, c_new = [], [], [], []
        for _ in range(reps):
            for tr, times, cpu in ((old, t_old, c_old), (new, t_new, c_new)):
                t0, c0 = time.perf_counter(), time.process_time()
                tr.step()
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
        row = _row(label, new, supervision, t_new, c_new, t_old, c_old, loss_err, grad_err)
    del torch
    return row


def _row(label, trainer, supervision, t_new, c_new, t_old=None, c_old=None, loss_err=None, grad_err=None):
    """A table row: wall and CPU seconds per step of the new code (and of the old, when it ran)."""
    return dict(
        label=label,
        faces=trainer.model.num_faces,
        levels=len(trainer._levels()),
        supervision=supervision,
        width=trainer.train[0].camera.width,
        height=trainer.train[0].camera.height,
        old=t_old,
        new=t_new,
        cpu_old=c_old,
        cpu_new=c_new,
        loss_err=loss_err,
        grad_err=grad_err,
    )


def trained_run() -> str | None:
    """The newest paper-scale run with a checkpoint (runs/paper*/adaptive), or None."""
    import glob

    found = sorted(glob.glob(os.path.join(ROOT, "runs", "paper*", "adaptive", "checkpoint.npz")), key=os.path.getmtime)
    return os.path.dirname(found[-1]) if found else None


def train_config(run, train_mod):
    """(dataset folder, TrainConfig) a run was trained with (its config.json, read by
    core.io.run.run_config), the config in ``train_mod``'s class."""
    from progressive_avatars.core.io.run import run_config

    cfg = run_config(run)
    if cfg is None:
        raise FileNotFoundError(f"{run}: no config.json")
    fields = {f.name for f in dataclasses.fields(train_mod.TrainConfig)}
    return cfg["data"], train_mod.TrainConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in cfg.items() if k in fields}
    )


def step_with(trainer, train_mod, **overrides):
    """A resumed trainer stepped under other settings: a trainer resumes only with its run's
    own settings (d1531d9), but stepping a trained avatar under another supervision or with
    in-level prefixes is what the benches measure. Only fields the step reads per iteration
    may be overridden (supervision, prefix cuts, schedules)."""
    trainer.cfg = dataclasses.replace(trainer.cfg, **overrides)
    if "supervision" in overrides:
        trainer.supervision = _in(train_mod, "policies").Supervision(trainer.cfg.supervision)
    return trainer


@contextlib.contextmanager
def resumed_trainer(run, train_mod=None, **overrides):
    """The working tree's Trainer (or that of ``train_mod``, a trainer module) resumed from a
    trained run's checkpoint and config, in a scratch folder so that the run itself is never
    written to, then stepped with ``overrides`` of its TrainConfig (step_with)."""
    import shutil

    from progressive_avatars.core.train import trainer as new_train

    new_train = train_mod or new_train
    data, config = train_config(run, new_train)
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("checkpoint.npz", "config.json"):
            shutil.copy(os.path.join(run, name), tmp)
        yield step_with(new_train.Trainer(data, tmp, config, resume=True), new_train, **overrides)


def bench_trained(run, supervision, reps):
    """`Trainer.step()` on a trained paper-scale avatar: the run's checkpoint (its last
    iteration: growth over, every Gaussian trained), its dataset's views preloaded as for the
    other rows. f6907ae cannot read the checkpoint: the old column is PREV_COMMIT's trainer,
    resumed from the same checkpoint and stepped alternately with the working tree's."""
    from progressive_avatars.core.train import trainer as new_train

    prev = prev_trainer()
    with resumed_trainer(run, supervision=supervision) as tr, resumed_trainer(run, prev, supervision=supervision) as tp:
        height = tr.train[0].camera.height
        tr.train, tp.train = _Views(tr.data_dir, new_train, height), _Views(tp.data_dir, prev, height)
        start = tr.iteration
        tp.step()  # warm-up
        tr.step()
        times = {"old": ([], []), "new": ([], [])}
        for _ in range(reps):
            for name, trainer in (("old", tp), ("new", tr)):
                t0, c0 = time.perf_counter(), time.process_time()
                trainer.step()
                times[name][0].append(time.perf_counter() - t0)
                times[name][1].append(time.process_time() - c0)
        label = (
            f"paper scale, trained ({supervision}; `{os.path.relpath(run, ROOT)}`, iteration {start}; "
            f"old = {PREV_COMMIT})"
        )
        return _row(label, tr, supervision, *times["new"], *times["old"])


def _raster_pair(old_render, old_cam, reps):
    """802x550, 170k head-scene Gaussians (float32 tensors), forward + backward: ``old_render``
    (a render function of another tree, with its own Camera ``old_cam``) against this tree's as
    training calls it (no contrib: the trainer reads none, and since 2026-11-27 the forward can
    leave it out; the older trees always computed it), interleaved; times, CPU times, visible
    count, and whether image, alpha and every gradient are bit-identical."""
    import torch

    from bench_render import head_camera, head_scene
    from progressive_avatars.core.render.rasterize import render

    def new_render(*a):
        return render(*a, compute_contrib=False)

    cam = head_camera(802, 550)
    params = [torch.from_numpy(x) for x in head_scene(170_000)]

    def run(fn, c):
        ps = [p.clone().requires_grad_(True) for p in params]
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn(*ps, c)
        ((out.image * 0.5).sum() + out.alpha.sum()).backward()
        return (time.perf_counter() - t0, time.process_time() - c0), [out.image, out.alpha] + [p.grad for p in ps]

    def old(*a):
        return old_render(*a[:-1], old_cam)

    _, a = run(old, None)
    _, b = run(new_render, cam)
    identical = all(torch.equal(x, y) for x, y in zip(a, b))
    image_diff = max(float((x.detach().double() - y.detach().double()).abs().max()) for x, y in zip(a[:2], b[:2]))
    grad_diff = max(
        float((x.double() - y.double()).norm() / y.double().norm().clamp_min(1e-30)) for x, y in zip(a[2:], b[2:])
    )
    t_old, t_new = [], []
    for _ in range(reps):
        t_old.append(run(old, None)[0])
        t_new.append(run(new_render, cam)[0])
    out = new_render(*params, cam)
    return dict(
        old=[t[0] for t in t_old],
        new=[t[0] for t in t_new],
        cpu_old=[t[1] for t in t_old],
        cpu_new=[t[1] for t in t_new],
        visible=int((out.radii > 0).sum()),
        identical=identical,
        image_diff=image_diff,
        grad_diff=grad_diff,
    )


def bench_raster(reps):
    """The raster-only row: f6907ae's render against this tree's."""
    from bench_render import head_camera

    old_train, old_render_mod = old_package()
    return _raster_pair(old_render_mod.render, _camera_as(head_camera(802, 550), old_train), reps)


RASTER_INPUTS_COMMIT = "527199a"  # before the rasteriser read float32 inputs in place (and the keyed depth sort)


def bench_raster_inputs(reps):
    """RASTER_INPUTS_COMMIT's render (float64 copies of the float32 inputs, checks as torch
    operations, a zero screen-space offset added, the depth sort gathering its keys in every
    pass) against this tree's, on the raster-only row's scene."""
    from bench_render import head_camera

    prev_trainer(RASTER_INPUTS_COMMIT)
    package = f"pa_{RASTER_INPUTS_COMMIT}.core"
    old_render = importlib.import_module(f"{package}.render.rasterize").render
    Camera = importlib.import_module(f"{package}.geometry.camera").Camera
    c = head_camera(802, 550)
    return _raster_pair(old_render, Camera(c.R, c.t, c.fx, c.fy, c.cx, c.cy, c.width, c.height), reps)


def bench_ssim(reps, size=(802, 551)):
    """Old (11x11 window, five conv2d) against new (fused kernel) SSIM, forward + backward."""
    import torch

    old_train, _ = old_package()
    old_ssim = _in(old_train, "losses").ssim
    from progressive_avatars.core.train.losses import ssim as new_ssim

    g = torch.Generator().manual_seed(0)
    b = torch.rand(size + (3,), generator=g)
    a = (0.7 * b + 0.3 * torch.rand(size + (3,), generator=g)).requires_grad_(True)

    def run(fn):
        a.grad = None
        t0 = time.perf_counter()
        v = fn(a, b)
        v.backward()
        return time.perf_counter() - t0, float(v.detach()), a.grad.clone()

    _, v_old, g_old = run(old_ssim)
    _, v_new, g_new = run(new_ssim)
    t_old, t_new = [], []
    for _ in range(reps):
        t_old.append(run(old_ssim)[0])
        t_new.append(run(new_ssim)[0])
    return dict(
        old=t_old,
        new=t_new,
        value_err=abs(v_old - v_new),
        grad_err=float((g_new - g_old).norm() / g_old.norm()),
        size=size,
    )


BINDING_COMMIT = "5dda6c5"  # before the binding read float32 and ran its weight recursion in parallel


def bench_binding(run_dir, reps):
    """The face binding forward + backward (core/train/binding_kernels.py) on a trained paper-scale
    avatar's parameters and one of its frames: BINDING_COMMIT's (float64 copies of the float32
    parameters and gradients in, float64 results cast back, a serial weight recursion) against
    this tree's (the kernels read and write the float32 arrays, the weights per root in
    parallel), interleaved; each side's index plan made once, as training makes it once per
    forest. Returns the times and whether every output and gradient is bit-identical."""
    import torch

    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.train import binding_kernels as new_kernels

    prev_trainer(BINDING_COMMIT)
    old_kernels = importlib.import_module(f"pa_{BINDING_COMMIT}.core.train.binding_kernels")
    av = Avatar.load(os.path.join(run_dir, "avatar.npz"))
    data = Dataset(av.meta["data"], "train", cache_images=0)
    verts = torch.from_numpy(np.asarray(data.vertices_at(data.frame_info(0).timestep_index), np.float32))
    n = av.num_gaussians
    arrays = [av.forest.split_logits, av.d_mu, av.d_log_scale, av.d_rot]
    params = {
        i: torch.from_numpy(np.ascontiguousarray(x, np.float32)).requires_grad_(True) for i, x in enumerate(arrays)
    }
    g = torch.Generator().manual_seed(0)
    upstream = [torch.randn((n, k), generator=g) for k in (3, 3, 4)]

    plans = {old_kernels: old_kernels.FaceBinding(av.forest), new_kernels: new_kernels.FaceBinding(av.forest)}

    def step(kernels):
        for t in params.values():
            t.grad = None
        t0 = time.perf_counter()
        out = plans[kernels].gaussians(verts, *params.values())
        sum((x * u).sum() for x, u in zip((out.means, out.scales, out.quats), upstream)).backward()
        dt = time.perf_counter() - t0
        return dt, [x.detach().clone() for x in (out.means, out.scales, out.quats)] + [
            t.grad.clone() for t in params.values()
        ]

    _, a = step(old_kernels)
    _, b = step(new_kernels)
    identical = all(torch.equal(x, y) for x, y in zip(a, b))
    t_old, t_new = [], []
    for _ in range(reps):
        t_old.append(step(old_kernels)[0])
        t_new.append(step(new_kernels)[0])
    return dict(faces=n, old=t_old, new=t_new, identical=identical)


def bench_adam(reps, rows=(21_444, 161_098)):
    """The Adam step with the trainer's finite checks of every gradient and parameter: the
    previous tree's (PREV_COMMIT: torch elementwise operations, a torch sum per check) against
    the compiled pass, interleaved, on the avatar's parameters at a cpu-preset and a
    paper-scale size. Returns per size the times and the largest parameter difference after
    one step from the same state."""
    import torch

    from progressive_avatars.core.avatar.avatar import PARAM_NAMES
    from progressive_avatars.core.train.adam import Adam

    prev = prev_trainer()
    widths = {"d_mu": 3, "d_log_scale": 3, "d_rot": 4, "opacity_logit": 1, "f_dc": 3, "split_logits": 3}
    out = []
    for n in rows:
        g = torch.Generator().manual_seed(0)

        def params():
            return {
                k: torch.randn((n, widths[k]) if widths[k] > 1 else (n,), generator=g).requires_grad_(True)
                for k in PARAM_NAMES
            }

        ours, theirs = params(), params()
        with torch.no_grad():
            for k in PARAM_NAMES:
                theirs[k].copy_(ours[k])
        lrs = {k: 1e-3 for k in PARAM_NAMES}
        opt_new, opt_old = Adam(ours, lrs), prev.Adam(theirs, lrs)
        grads = [{k: 1e-3 * torch.randn(ours[k].shape, generator=g) for k in PARAM_NAMES} for _ in range(4)]

        def new_step(i):
            for k in PARAM_NAMES:
                ours[k].grad = grads[i % 4][k].clone()
            t0 = time.perf_counter()
            assert not opt_new.nonfinite_gradients(ours)
            assert not opt_new.step(ours, {"d_mu": 0.5})
            return time.perf_counter() - t0

        def old_step(i):
            for k in PARAM_NAMES:
                theirs[k].grad = grads[i % 4][k].clone()
            t0 = time.perf_counter()
            for k, t in theirs.items():
                prev._check_finite(i, **{f"gradient of {k}": t.grad})
            opt_old.step(theirs, {"d_mu": 0.5})
            for k, t in theirs.items():
                prev._check_finite(i, **{k: t})
            return time.perf_counter() - t0

        new_step(0), old_step(0)
        diff = max(
            float((ours[k] - theirs[k]).detach().abs().max() / theirs[k].detach().abs().max()) for k in PARAM_NAMES
        )
        t_old, t_new = [], []
        for i in range(1, 4 * reps + 1):
            t_old.append(old_step(i))
            t_new.append(new_step(i))
        out.append(dict(rows=n, old=t_old, new=t_new, diff=diff))
    return out


def raster_reference_errors():
    """Both rasterisers against the dense float64 reference on a small head-like scene:
    max abs image error and the worst relative gradient error over all inputs."""
    import torch

    from bench_render import head_camera, head_scene

    from progressive_avatars.core.render.reference import render_reference

    from progressive_avatars.core.render.rasterize import render as new_render

    old_train, old_render_mod = old_package()
    cam = head_camera(64, 64)
    old_cam = _camera_as(cam, old_train)
    params = [torch.from_numpy(x) for x in head_scene(400, seed=1)]
    params[2] = params[2] * 6.0
    bg = torch.tensor([0.2, 0.4, 0.1])
    g = torch.Generator().manual_seed(0)
    wi, wa = (
        torch.randn(64, 64, 3, generator=g, dtype=torch.float64),
        torch.randn(64, 64, generator=g, dtype=torch.float64),
    )

    def grads(fn, dtype, camera=cam):
        ps = [p.detach().clone().to(dtype).requires_grad_(True) for p in params + [bg]]
        out = fn(*ps[:5], camera, ps[5])
        img, alpha = (out[0], out[1]) if isinstance(out, tuple) else (out.image, out.alpha)
        ((img.double() * wi).sum() + (alpha.double() * wa).sum()).backward()
        return img.detach().double(), [p.grad.double() for p in ps]

    ref_img, ref_g = grads(render_reference, torch.float64)
    rows = {}
    for name, fn, camera in (("old", old_render_mod.render, old_cam), ("new", new_render, cam)):
        img, gr = grads(fn, torch.float32, camera)
        rel = max(float((a - b).norm() / b.norm()) for a, b in zip(gr, ref_g))
        rows[name] = (float((img - ref_img).abs().max()), rel)
    return rows


def binding_inference_errors(depth: int = 6, roots: int = 200) -> dict:
    """The training binding against numpy inference (float64) on the finest faces of a forest
    `depth` levels deep with random (learned-like) split logits on a FLAME-sized template in
    metres, the parameters in float32 as the trainer holds them: max scale error relative to
    each face's scale, max frame-entry error, max centroid error in float32 spacings of the
    centroid's coordinates (world positions are float32: a sliver's centroid cannot be
    finer). For f6907ae's torch binding (float32 weight recursion) and this tree's kernels."""
    import torch

    from progressive_avatars.core.avatar import binding
    from progressive_avatars.core.avatar.forest import Forest
    from progressive_avatars.core.geometry.rotations import quat_to_rotmat
    from progressive_avatars.core.synthetic.shapes import sphere_mesh
    from progressive_avatars.core.train import binding_kernels

    old_train, _ = old_package()
    OldTorchForest = _in(old_train, "binding_torch").TorchForest
    rng = np.random.default_rng(6)
    verts, faces = sphere_mesh(70, 72, radius=0.1)
    forest = Forest(faces)
    current = rng.choice(len(faces), roots, replace=False)
    for _ in range(depth):
        current = forest.split(current).ravel()
    forest.split_logits[:] = rng.normal(0, 1.0, forest.split_logits.shape).astype(np.float32)
    v32 = (verts + rng.normal(0, 1e-3, verts.shape)).astype(np.float32)
    ref = binding.evaluate(forest, v32.astype(np.float64), dtype=np.float64)
    finest = np.flatnonzero(forest.level == depth)
    s_ref, t_ref, r_ref = ref.s[finest], ref.t[finest], ref.r[finest]
    logits = torch.tensor(forest.split_logits)

    def errors(t, r, s):
        return {
            "centroid": float(
                (np.abs(t[finest] - t_ref).max(1) / np.spacing(np.abs(t_ref).max(1).astype(np.float32))).max()
            ),
            "scale": float((np.abs(s[finest] - s_ref) / s_ref).max()),
            "frame": float(np.abs(r[finest] - r_ref).max()),
        }

    n = forest.num_faces
    zero, ident = torch.zeros(n, 3), torch.zeros(n, 4)
    ident[:, 0] = 1
    m, q, sc = binding_kernels.FaceBinding(forest).gaussians(torch.tensor(v32), logits, zero, zero, ident)
    new = errors(m.double().numpy(), quat_to_rotmat(q.double().numpy()), sc.double().numpy()[:, 0])
    old_forest = OldTorchForest(forest)
    t, r, s = old_forest.evaluate(torch.tensor(v32), old_forest.weights(logits))
    old = errors(t.double().numpy(), r.double().numpy(), s.double().numpy())
    return {
        "old": old,
        "new": new,
        "faces": n,
        "template_faces": len(faces),
        "finest": len(finest),
        "depth": depth,
        "roots": roots,
        "median_scale": float(np.median(s_ref)),
    }


def _fmt(times):
    t = sorted(times)
    return f"{t[0] * 1e3:.0f} / {t[len(t) // 2] * 1e3:.0f}"


def run(quick: bool = False, data: str | None = None) -> str:
    import numba
    import torch

    from bench_common import header

    from progressive_avatars.core.train.memory import retain_freed_memory

    retained = retain_freed_memory()  # as scripts/train.py runs a training process (old and new alike)
    data = data or os.path.join(ROOT, "runs", "synthetic")
    if not os.path.exists(os.path.join(data, "transforms_train.json")):
        raise FileNotFoundError(f"{data}: no synthetic dataset; make it with scripts/make_synthetic.py --out {data}")
    load0 = os.getloadavg()
    reps = 3 if quick else 6
    rows = []
    cpu_plans = [
        ("cpu preset, 5k faces", []),
        ("cpu preset, 20k faces", [1.0]),
        ("cpu preset, ~37k faces", [1.0, 0.35]),
    ]
    if quick:
        cpu_plans = cpu_plans[1:2]
    for label, plan in cpu_plans:
        # short steps (tens of ms): five times the reps, so that one slow moment of the VM does not move the median
        rows.append(bench_steps(data, label, "all", plan, 5 * reps))
        print(rows[-1]["label"], _fmt(rows[-1]["old"]), _fmt(rows[-1]["new"]), file=sys.stderr)
    paper_plan = [1.0, 1.0, 0.45, 0.12]  # levels 0-4, ~150k faces
    for sup in ("sampled", "all"):
        rows.append(bench_steps(data, f"paper scale ({sup})", sup, paper_plan, reps, 802))
        print(rows[-1]["label"], _fmt(rows[-1]["old"]), _fmt(rows[-1]["new"]), file=sys.stderr)
    run_dir = trained_run()
    if run_dir is not None:
        for sup in ("sampled", "all"):
            rows.append(bench_trained(run_dir, sup, 3 * reps))  # each step draws its view and level: more reps
            print(rows[-1]["label"], _fmt(rows[-1]["old"]), _fmt(rows[-1]["new"]), file=sys.stderr)
    raster = bench_raster(reps)
    raster_inputs = bench_raster_inputs(2 * reps)
    ref = raster_reference_errors()
    bind_err = binding_inference_errors()
    ss = bench_ssim(reps)
    adam = bench_adam(reps)
    binding = bench_binding(run_dir, 3 * reps) if run_dir is not None else None
    load1 = os.getloadavg()
    cmd = "python scripts/bench.py --only train" + (" --quick" if quick else "")
    lines = [
        header("Training iteration: f6907ae (old) against this tree (new), same run", cmd),
        f"- threads: numba {numba.get_num_threads()} ({numba.threading_layer()}), torch "
        f"{torch.get_num_threads()}; load average {load0[0]:.1f} at the start, {load1[0]:.1f} at the end "
        f"({os.cpu_count()} cores, shared with other jobs: read the ratios, taken from interleaved runs, "
        "rather than the absolute times)",
        "- old = `git archive f6907ae core` imported as its own package in the same process; each rep "
        f"runs one old step then one new step; times are min / median ms over the reps ({5 * reps} reps of the cpu "
        f"preset rows, {reps} of the untrained paper-scale rows, {3 * reps} of the trained ones)",
        "- CPU ms: process CPU time (all threads) per iteration, min over the reps: less sensitive to "
        "waiting for the cores than wall time, though contention still inflates it",
        "- malloc: "
        + (
            "freed memory kept for reuse (core/train/memory.py retain_freed_memory, as scripts/train.py sets it for "
            "a training process), for old and new alike; its effect on its own: section 'Freed memory kept by "
            "training processes'"
            if retained
            else "the C library's defaults (retain_freed_memory had no effect here)"
        ),
        "- state: the initial avatar after a fixed split plan (children copy their parent's Gaussian), not a "
        "trained one: its Gaussians are larger and overlap more than trained ones, so rendering costs more; the "
        "*trained* rows step the working tree from a finished paper-scale run's checkpoint instead (its "
        "coarse levels included, the preset's supervision and every level), on 8 of its own training views "
        f"preloaded; f6907ae cannot read that checkpoint, so their old column is {PREV_COMMIT} (the tree "
        "before the packed splat rows, the inlined projections and bindings, the fused photometric loss and "
        "the last-image walk) resumed from the same checkpoint and stepped alternately with the new",
        "- accuracy: loss and whole-gradient relative difference between old and new on the first step from "
        "an identical state (new binds in float64, old's forest weights were float32)",
        "",
        "| iteration | image | faces | levels rendered | old ms (min / median) | new ms (min / median) "
        "| speed-up (median) | old / new CPU ms | speed-up (CPU) | loss diff | gradient diff |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        speed = np.median(r["old"]) / np.median(r["new"])
        co, cn = min(r["cpu_old"]), min(r["cpu_new"])
        errs = [f"{e:.1e}" if e is not None else "-" for e in (r["loss_err"], r["grad_err"])]
        lines.append(
            f"| {r['label']} | {r['width']}x{r['height']} | {r['faces']:,} | {r['levels']} "
            f"| {_fmt(r['old'])} | {_fmt(r['new'])} | x{speed:.2f} | {co * 1e3:.0f} / {cn * 1e3:.0f} "
            f"| x{co / cn:.2f} | {errs[0]} | {errs[1]} |"
        )
    speed = np.median(raster["old"]) / np.median(raster["new"])
    lines += [
        f"| raster only: 802x550, 170k Gaussians ({raster['visible']:,} visible), forward + backward (new: as "
        "training calls it, no contrib) | 802x550 "
        f"| - | 1 | {_fmt(raster['old'])} | {_fmt(raster['new'])} | x{speed:.2f} "
        f"| {min(raster['cpu_old']) * 1e3:.0f} / {min(raster['cpu_new']) * 1e3:.0f} "
        f"| x{min(raster['cpu_old']) / min(raster['cpu_new']):.2f} | - | - |",
        "",
        f"SSIM loss alone ({ss['size'][0]}x{ss['size'][1]}, forward + backward, min / median ms): old "
        f"{_fmt(ss['old'])}, new {_fmt(ss['new'])} (x{np.median(ss['old']) / np.median(ss['new']):.2f}); value "
        f"difference {ss['value_err']:.1e}, gradient relative difference {ss['grad_err']:.1e}.",
        "",
        "Adam: the step of every parameter with the trainer's finite checks of each gradient and parameter, "
        f"{PREV_COMMIT} (torch elementwise operations, a torch sum per check) against the compiled pass "
        "(core/train/adam.py), min / median ms: "
        + "; ".join(
            f"{a['rows']:,} rows: old {1e3 * min(a['old']):.1f} / {1e3 * np.median(a['old']):.1f}, "
            f"new {1e3 * min(a['new']):.1f} / {1e3 * np.median(a['new']):.1f} "
            f"(x{np.median(a['old']) / np.median(a['new']):.2f})"
            for a in adam
        )
        + f"; parameters after one step from the same state differ by at most {max(a['diff'] for a in adam):.1e} "
        "of their largest value (float32 rounding: torch fuses some multiply-adds).",
        "",
    ]
    if binding is not None:
        lines += [
            f"Face binding, forward + backward ({binding['faces']:,} faces of `{os.path.relpath(run_dir, ROOT)}`, "
            f"one frame), {BINDING_COMMIT} (float64 copies of the float32 parameters and gradients, float64 results "
            "cast back, the weight recursion serial) against this tree (the kernels read and write the float32 arrays; "
            "the weight recursion and its backward run per root in parallel), min / median ms: old "
            f"{_fmt(binding['old'])}, new {_fmt(binding['new'])} (x{np.median(binding['old']) / np.median(binding['new']):.2f}); "
            + ("every output and gradient bit-identical." if binding["identical"] else "**outputs differ**."),
            "",
        ]
    lines += [
        f"Raster only (the row above), {RASTER_INPUTS_COMMIT} (float64 copies of the float32 inputs, the input "
        "checks as torch operations, the depth sort gathering its keys in every pass) against this tree (the "
        "kernels read the float32 arrays in place, widening every load to float64; one compiled pass checks them; "
        "the sort's keys travel with the indices; from 0c6a277 also the box walk of near-axis-aligned splats and the "
        "replay's moment sums; from ad3d079 the sort and the splat-row grouping on one slice per thread, the "
        "projection writing each output once, its backward into the parameters' dtype; docs/BENCHMARKS.md "
        "'Rasteriser kernels'), min / "
        "median ms: old "
        f"{_fmt(raster_inputs['old'])}, new {_fmt(raster_inputs['new'])} "
        f"(x{np.median(raster_inputs['old']) / np.median(raster_inputs['new']):.2f}); "
        + (
            "image, alpha and every gradient bit-identical."
            if raster_inputs["identical"]
            else f"outputs differ: image and alpha by at most {raster_inputs['image_diff']:.1e}, gradients by "
            f"{raster_inputs['grad_diff']:.1e} relative."
        ),
        "",
        "Against the dense float64 reference (64x64, 400 head-scene Gaussians, float32 inputs): old max image "
        f"error {ref['old'][0]:.1e}, worst relative gradient error {ref['old'][1]:.1e}; new {ref['new'][0]:.1e}, "
        f"{ref['new'][1]:.1e}.",
        "",
        f"Training binding against numpy inference (float64), depth {bind_err['depth']} with random split logits "
        f"({bind_err['roots']} of a {bind_err['template_faces']:,}-face sphere's faces split {bind_err['depth']} times, "
        f"{bind_err['faces']:,} faces, metres, median finest face scale {bind_err['median_scale'] * 1e3:.3f} mm; "
        "float32 parameters as the trainer holds them), worst of the "
        f"{bind_err['finest']:,} finest faces, scale relative to the face's scale, frame entries absolute, "
        "centroid in float32 spacings of its coordinates: "
        + "; ".join(
            f"{side} scale {e['scale']:.1e}, frame {e['frame']:.1e}, centroid {e['centroid']:.2f} spacings"
            for side, e in (("old", bind_err["old"]), ("new", bind_err["new"]))
        )
        + " (target: scale and frame 1e-5).",
        "",
    ]
    return "\n".join(lines)


def write_section(text: str, path: str = os.path.join(ROOT, "docs", "BENCHMARKS.md")):
    """Put the section into BENCHMARKS.md in place of an earlier one (or before the training
    reports), leaving the other sections as they are."""
    doc = open(path).read()
    title = text.split("\n", 1)[0]
    start = doc.find(title + "\n")
    if start < 0:
        start = doc.find("## Training and evaluation")
        start = len(doc) if start < 0 else start
        end = start
    else:
        nxt = doc.find("\n## ", start + len(title))
        end = len(doc) if nxt < 0 else nxt + 1
    new = doc[:start] + text.rstrip("\n") + "\n\n" + doc[end:]
    with open(path + ".tmp", "w") as fh:
        fh.write(new)
    os.replace(path + ".tmp", path)


def _arguments(argv):
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions (a quick look, not for the record)")
    ap.add_argument("--write", action="store_true", help="put the section into docs/BENCHMARKS.md")
    return ap.parse_args(argv)


if __name__ == "__main__":
    args = _arguments(_bootstrap.script_args())
    section = run(quick=args.quick)
    print(section)
    if args.write:
        write_section(section)
