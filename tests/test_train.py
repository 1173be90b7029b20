import json
import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch

from progressive_avatars.core.avatar.avatar import Avatar
from progressive_avatars.core.train import losses, metrics
from progressive_avatars.core.train.trainer import Adam, Trainer, config_for

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_tiny_preset_trains_end_to_end(tiny_run):
    avatar = Avatar.load(os.path.join(tiny_run, "avatar.npz"))
    counts = avatar.forest.level_counts()
    assert len(counts) >= 2 and counts[1] > 0, "adaptive growth split some faces"
    rows = [json.loads(line) for line in open(os.path.join(tiny_run, "metrics.jsonl"))]
    assert rows[-1]["iteration"] == config_for("tiny").iterations
    assert "val_psnr" in rows[-1]
    # Training improves on the first logged loss and beats an empty (background-only) image.
    assert rows[-1]["train_psnr"] > rows[0]["train_psnr"]
    for name in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc"):
        assert np.all(np.isfinite(getattr(avatar, name)))


# With a reset every 5 iterations (growth until 19) the stop at 15 falls on a reset: the
# checkpoint must hold the reset state and the resumed run must not cut the opacities again.
@pytest.mark.parametrize("prefix_cuts,opacity_reset_every", [(0, 0), (1, 0), (0, 5)])
def test_kill_and_resume_matches_uninterrupted_run(tiny_dataset, tmp_path, prefix_cuts, opacity_reset_every):
    cfg = config_for(
        "tiny",
        iterations=24,
        grow_every=8,
        grow_start=8,
        checkpoint_every=10,
        eval_every=1000,
        prefix_cuts=prefix_cuts,
        opacity_reset_every=opacity_reset_every,
        rank_every=6,
        rank_views=2,
    )
    full = Trainer(tiny_dataset, str(tmp_path / "full"), cfg)
    full.run(progress=False)
    # Stopped after 15 iterations (a real kill is tested below); a fresh Trainer resumes.
    part = Trainer(tiny_dataset, str(tmp_path / "part"), cfg)
    part.run(progress=False, stop_after=15)
    ck = np.load(tmp_path / "part" / "checkpoint.npz")
    assert json.loads(str(ck["state_json"]))["iteration"] == 15
    resumed = Trainer(tiny_dataset, str(tmp_path / "part"), cfg, resume=True)
    assert resumed.iteration == 15
    resumed.run(progress=False)
    a = Avatar.load(tmp_path / "full" / "avatar.npz")
    b = Avatar.load(tmp_path / "part" / "avatar.npz")
    np.testing.assert_array_equal(a.forest.parent, b.forest.parent)
    for name in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-5, err_msg=name)
    rows = [json.loads(line)["iteration"] for line in open(tmp_path / "part" / "metrics.jsonl")]
    assert rows == sorted(set(rows)), "no duplicated log lines after resume"
    resets = [
        [r["iteration"] for r in map(json.loads, open(tmp_path / run / "metrics.jsonl")) if "opacity_reset" in r]
        for run in ("full", "part")
    ]
    assert resets == [[5, 10, 15]] * 2 if opacity_reset_every else resets == [[], []]


@pytest.mark.slow  # a training run or a subprocess
def test_killed_process_resumes(tiny_dataset, tmp_path):
    """A real kill: the training process is terminated mid-run, then --resume finishes it."""
    run = tmp_path / "killed"
    cmd = [
        sys.executable,
        os.path.join(ROOT, "scripts", "train.py"),
        "--data",
        tiny_dataset,
        "--out",
        str(run),
        "--preset",
        "tiny",
        "--iterations",
        "40",
        "--no-progress",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    ck, res = run / "checkpoint.npz", run / "resources.jsonl"
    import time

    deadline = time.time() + 120
    while not res.exists() and time.time() < deadline and proc.poll() is None:  # written after a checkpoint
        time.sleep(0.2)
    proc.kill()
    proc.wait()
    assert ck.exists(), "a checkpoint was written before the kill"
    out = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1])["iterations"] == 40
    # The killed invocation's time and memory still count: its row was kept from its checkpoint.
    rows = [json.loads(ln) for ln in res.read_text().splitlines()]
    assert len(rows) == 2 and rows[0]["iterations"] in (20, 40) and rows[1]["iterations"] == 40
    assert rows[0]["invocation"] != rows[1]["invocation"] and all(r["wall_seconds"] > 0 for r in rows)
    # The same command without --resume (forgotten) is refused and touches nothing of the run;
    # --overwrite starts over: a new avatar, the old invocations' rows gone.
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and not p.name.startswith(".")}
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "already holds a run" in out.stderr and "--resume" in out.stderr, out.stderr
    after = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and not p.name.startswith(".")}
    assert after == before
    out = subprocess.run(cmd[:-2] + ["4", "--no-progress", "--overwrite"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1])["iterations"] == 4
    rows = [json.loads(ln) for ln in res.read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["iterations"] == 4


def test_resume_keeps_the_runs_settings_and_overwrite_clears_the_old_run(tiny_dataset, tmp_path, capsys):
    """--resume continues the run that is there, as it was set up: other run-defining settings
    are refused at once (they mixed two trainings, or crashed mid-run), a finished run without
    its checkpoint is not silently started over, and --overwrite clears the replaced run's
    checkpoint before anything else can be resumed from it."""
    from progressive_avatars.core.train.trainer import RunExistsError

    run = tmp_path / "run"
    cfg = config_for("tiny", iterations=4, checkpoint_every=2, eval_every=10**6)
    Trainer(tiny_dataset, str(run), cfg).run(progress=False)
    with pytest.raises(ValueError, match=r"settings other than the run's: coarse_levels .*; seed 0 -> 7"):
        Trainer(tiny_dataset, str(run), config_for("tiny", iterations=4, seed=7, coarse_levels=()), resume=True)
    with pytest.raises(ValueError, match=r"prefix_cuts 0 -> 2"):
        Trainer(tiny_dataset, str(run), config_for("tiny", iterations=4, prefix_cuts=2), resume=True)
    # What may change: the length, logging, checkpoints, memory and batch.
    more = config_for("tiny", iterations=6, checkpoint_every=3, eval_every=5, image_cache_mb=64.0)
    capsys.readouterr()
    again = Trainer(tiny_dataset, str(run), more, resume=True)
    assert again.iteration == 4
    # A longer run's schedules (fractions of its length) differ from here on: said, not refused.
    err = capsys.readouterr().err
    assert "resumed at iteration 4 with 6 iterations instead of 4" in err and "position learning rate" in err
    again.run(progress=False)
    assert again.iteration == 6
    # A checkpoint from before the settings travelled in it: config.json's are checked.
    ck = dict(np.load(run / "checkpoint.npz"))
    state = json.loads(str(ck["state_json"]))
    del state["settings"]
    ck["state_json"] = np.array(json.dumps(state))
    np.savez(run / "checkpoint.npz", **ck)
    with pytest.raises(ValueError, match=r"seed 0 -> 3"):
        Trainer(tiny_dataset, str(run), config_for("tiny", iterations=6, seed=3), resume=True)
    capsys.readouterr()
    Trainer(tiny_dataset, str(run), config_for("tiny", iterations=6), resume=True)
    assert "instead of" not in capsys.readouterr().err  # the same length: no note
    # A finished run whose checkpoint is gone is refused, not trained again from scratch.
    os.remove(run / "checkpoint.npz")
    avatar = (run / "avatar.npz").read_bytes()
    with pytest.raises(RunExistsError, match="no checkpoint.npz to resume from"):
        Trainer(tiny_dataset, str(run), cfg, resume=True)
    assert (run / "avatar.npz").read_bytes() == avatar
    # --overwrite: once the new data passed its checks, the old run's files are gone, so a kill
    # before the new run's first checkpoint leaves nothing a --resume could continue wrongly.
    (run / "avatar.pavs").write_bytes(b"old stream")
    (run / "importance.npz").write_bytes(b"old cache")
    fresh = Trainer(tiny_dataset, str(run), config_for("tiny", iterations=4, seed=1), overwrite=True)
    assert sorted(os.listdir(run)) == ["config.json"]
    assert fresh.iteration == 0


def test_threads_must_be_positive(tiny_dataset, tmp_path):
    for n in ("0", "-1"):
        cmd = [sys.executable, os.path.join(ROOT, "scripts", "train.py"), "--data", tiny_dataset]
        out = subprocess.run(
            cmd + ["--out", str(tmp_path / "r"), "--preset", "tiny", "--threads", n], capture_output=True, text=True
        )
        assert out.returncode == 2 and f"--threads must be at least 1, got {n}" in out.stderr, out.stderr
        assert not (tmp_path / "r").exists()


def test_adam_grows_with_new_rows():
    p = {"a": torch.zeros(2, 3, requires_grad=True)}
    opt = Adam(p, {"a": 0.1})
    p["a"].grad = torch.ones(2, 3)
    opt.step(p)
    p["a"] = torch.cat([p["a"].detach(), torch.zeros(1, 3)]).requires_grad_(True)
    opt.grow(p)
    p["a"].grad = torch.ones(3, 3)
    opt.step(p)
    # A new row takes a first Adam step of exactly lr (bias-corrected), like a fresh parameter.
    np.testing.assert_allclose(p["a"].detach()[2].numpy(), -0.1, rtol=1e-4)
    np.testing.assert_allclose(p["a"].detach()[0].numpy(), -0.2, rtol=1e-3)


def test_adam_compiled_step_matches_torch():
    """The compiled pass takes torch's float32 steps (to rounding: torch fuses some multiply-adds),
    across growth, 1-D and 2-D parameters and a per-parameter lr scale."""
    rng = np.random.default_rng(0)

    def params(n):
        torch.manual_seed(n)
        return {"a": torch.randn(n, 3).requires_grad_(True), "b": torch.randn(n).requires_grad_(True)}

    ours, ref = params(3000), params(3000)
    lrs = {"a": 1e-2, "b": 5e-3}
    opt, opt_ref = Adam(ours, lrs), Adam(ref, lrs)
    assert opt._compiled(ours)  # else both would take the torch path
    for it in range(12):
        if it == 6:  # a split appends rows with their own bias correction
            for p, o in ((ours, opt), (ref, opt_ref)):
                for k in p:
                    p[k] = torch.cat([p[k].detach(), torch.ones((500,) + tuple(p[k].shape[1:]))]).requires_grad_(True)
                o.grow(p)
        for k in ours:
            g = torch.tensor(rng.normal(size=tuple(ours[k].shape)) * 10.0 ** rng.uniform(-6, 1), dtype=torch.float32)
            ours[k].grad, ref[k].grad = g.clone(), g.clone()
        assert opt.step(ours, {"a": 0.7}) == []
        opt_ref.steps += 1
        opt_ref._torch_step(ref, {"a": 0.7})
        assert all(ours[k].grad is None for k in ours)
    for k in ours:
        np.testing.assert_allclose(ours[k].detach().numpy(), ref[k].detach().numpy(), rtol=1e-6, atol=1e-7)
        for ours_m, ref_m in ((opt.m[k], opt_ref.m[k]), (opt.v[k], opt_ref.v[k])):
            ref_m = ref_m.numpy()
            np.testing.assert_allclose(ours_m.numpy(), ref_m, rtol=1e-6, atol=1e-6 * np.abs(ref_m).max())
    assert ours["a"].shape == (3500, 3) and not torch.equal(ours["a"][:3000], params(3000)["a"])


def test_adam_reports_nonfinite_gradients_and_parameters():
    p = {"a": torch.zeros(4000, 3, requires_grad=True), "b": torch.zeros(4000, requires_grad=True)}
    opt = Adam(p, {"a": 0.1, "b": 0.1})
    p["a"].grad, p["b"].grad = torch.ones(4000, 3), torch.ones(4000)
    p["b"].grad[3999] = float("nan")
    assert opt.nonfinite_gradients(p) == ["b"]
    p["b"].grad[3999] = 1.0
    opt.m["a"][2500, 1] = float("inf")  # an overflowed moment
    assert opt.step(p) == ["a"]
    assert torch.isinf(p["a"][2500, 1]) and torch.isfinite(p["b"]).all()
    # The torch path (GPU tensors) reports alike.
    q = {"a": torch.zeros(50, 3, requires_grad=True), "b": torch.zeros(50, requires_grad=True)}
    ref = Adam(q, {"a": 0.1, "b": 0.1})
    q["a"].grad, q["b"].grad = torch.ones(50, 3), torch.ones(50)
    ref.m["b"][7] = float("inf")
    ref.steps += 1
    assert ref._torch_step(q, None) == ["b"] and torch.isfinite(q["a"]).all()


@pytest.mark.slow  # a training run or a subprocess
def test_extreme_expressions_stay_finite(tiny_dataset, tmp_path):
    """10x the tiny preset's iterations on exaggerated meshes (crumpled, repeated vertices) never goes NaN."""
    from progressive_avatars.core.io.dataset import Dataset

    iterations = 10 * config_for("tiny").iterations
    tr = Trainer(
        tiny_dataset,
        str(tmp_path / "x"),
        config_for(
            "tiny", iterations=iterations, eval_every=10**6, grow_every=50, grow_start=50, checkpoint_every=10**6
        ),
    )
    rng = np.random.default_rng(0)
    base_getitem = Dataset.__getitem__

    def extreme(self, i):
        s = base_getitem(self, i)
        v = s.vertices.copy()
        pick = rng.random(len(v)) < 0.05
        v[pick] += rng.normal(0, 0.05, (pick.sum(), 3)).astype(np.float32)  # crumpled, degenerate faces
        v[rng.integers(len(v))] = v[0]  # a repeated vertex
        s.vertices = v
        return s

    tr.train.__class__ = type("Extreme", (Dataset,), {"__getitem__": extreme})
    tr.run(progress=False)
    for name, t in tr.model.params.items():
        assert torch.isfinite(t).all(), name


def test_bad_preset_and_data_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown preset"):
        config_for("huge")
    out = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "scripts", "train.py"),
            "--data",
            str(tmp_path / "nope"),
            "--out",
            str(tmp_path / "r"),
            "--preset",
            "tiny",
        ],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2 and "error:" in out.stderr and "nope" in out.stderr
    assert not (tmp_path / "r").exists()  # the run folder it made is gone again, not left holding a lock file
    (tmp_path / "kept").mkdir()  # a folder the user made stays
    cmd = [sys.executable, os.path.join(ROOT, "scripts", "train.py"), "--data", str(tmp_path / "nope")]
    out = subprocess.run(cmd + ["--out", str(tmp_path / "kept"), "--preset", "tiny"], capture_output=True, text=True)
    assert out.returncode == 2 and (tmp_path / "kept").is_dir(), out.stderr


def test_regularisers_have_the_papers_values():
    """GaussianAvatars' regularisers (DESIGN.md): position relu(|dmu| - 1), scale
    relu(exp(dS_log) - 0.6), in face-local units, averaged over the Gaussians."""
    from progressive_avatars.core.train import losses

    d_mu = torch.tensor([[1.5, 0.0, 0.0], [0.0, 0.6, 0.8], [0.0, 0.0, 0.5]], dtype=torch.float64)
    assert float(losses.position_reg(d_mu)) == pytest.approx(0.5 / 3)  # 0.5, 0 (|dmu| = 1), 0
    d_log_scale = torch.log(torch.tensor([[0.8, 0.5, 0.6]], dtype=torch.float64))
    assert float(losses.scale_reg(d_log_scale)) == pytest.approx(0.2 / 3)  # 0.2, 0, 0 (at the bound)


def test_level_weights_scale_each_level_loss(tiny_dataset, tmp_path):
    from progressive_avatars.core.train import losses
    from progressive_avatars.core.train.trainer import level_weight

    def first_step(name, weights):
        cfg = config_for("tiny", level_weights=weights, eval_every=10**6, checkpoint_every=10**6, coarse_levels=())
        tr = Trainer(tiny_dataset, str(tmp_path / name), cfg)
        p = tr.model.params
        with torch.no_grad():
            reg = (
                cfg.position_reg * losses.position_reg(p["d_mu"]) + cfg.scale_reg * losses.scale_reg(p["d_log_scale"])
            ).item()
        assert tr.model.forest.max_level == 0  # the first step supervises level 0 only
        return tr.step()["loss"], reg, tr.grad_sum.copy()

    base, reg, grads = first_step("w1", None)
    tripled, reg3, grads3 = first_step("w3", (3.0,))
    zero, reg0, _ = first_step("w0", (0.0, 1.0))
    # The growth statistic is divided by the level's weight: the threshold keeps its meaning.
    assert grads.max() > 0 and np.allclose(grads3, grads, rtol=1e-4, atol=1e-9)
    assert reg == reg3 == reg0
    photo = base - reg
    assert photo > 0.01
    assert tripled - reg == pytest.approx(3 * photo, rel=1e-5)
    assert zero == pytest.approx(reg, abs=1e-7)  # level 0 weighted 0: only the regularisers remain
    cfg = config_for("tiny", level_weights=(0.25, 0.5, 1.0))
    assert [level_weight(cfg, lv) for lv in range(5)] == [0.25, 0.5, 1.0, 1.0, 1.0]
    assert level_weight(config_for("tiny"), 3) == 1.0
    for bad in ((-1.0,), (0.0, 0.0), (float("nan"),)):
        with pytest.raises(ValueError, match="level weights"):
            config_for("tiny", level_weights=bad)
    config_for("tiny", max_depth=13, coarse_levels=(0.1, 0.2))  # 16 images a step: the most one pass holds
    with pytest.raises(ValueError, match="at most 16"):
        config_for("tiny", max_depth=12, coarse_levels=(0.1, 0.2), prefix_cuts=2)
    out = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "scripts", "train.py"),
            "--data",
            tiny_dataset,
            "--out",
            str(tmp_path / "r"),
            "--preset",
            "tiny",
            "--level-weights",
            "1,-2",
        ],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2 and "level weights" in out.stderr


@pytest.mark.slow  # a training run or a subprocess
def test_train_script_runs_as_blender_would(tiny_dataset, tmp_path):
    """`blender --background --python scripts/train.py -- ARGS`: bpy loaded, Blender's argv, args after --."""
    pytest.importorskip("bpy")
    run = tmp_path / "bl"
    code = (
        "import bpy, runpy, sys\n"
        f"sys.argv = ['blender', '--background', '--python', {os.path.join(ROOT, 'scripts', 'train.py')!r}, '--',"
        f" '--data', {tiny_dataset!r}, '--out', {str(run)!r}, '--preset', 'tiny', '--iterations', '12', '--no-progress']\n"
        f"runpy.run_path({os.path.join(ROOT, 'scripts', 'train.py')!r}, run_name='__main__')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=str(tmp_path),
        env=dict(os.environ, PYTHONPATH=""),
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert Avatar.load(run / "avatar.npz").num_gaussians > 0


def _flame_mode_dataset(tiny_dataset, tmp_path, dynamic_offset=False):
    """A FLAME-mode copy of the tiny dataset (its images, a small FLAME-format model's geometry);
    ``dynamic_offset``: every frame's file also holds VHAP's per-frame vertex offsets."""
    import shutil

    from tests.test_flame import N_SHAPE, make_flame_arrays, random_params

    from progressive_avatars.core.flame.model import _model_from_mapping

    root = tmp_path / "flame_ds"
    shutil.copytree(tiny_dataset, root)
    model = _model_from_mapping(make_flame_arrays(seed=2), "test model", N_SHAPE)
    model.v_template *= 1.2  # head-sized (the synthetic head spans ~0.25 m)
    model_path = str(tmp_path / "flame_model.npz")
    model.save_npz(model_path)
    (root / "flame_param").mkdir()
    prm = random_params(64, seed=3, scale=0.05)
    one = lambda t: {k: (v if k in ("shape", "static_offset") else v[t : t + 1]) for k, v in prm.items()}  # noqa: E731
    np.savez(root / "canonical_flame_param.npz", **one(0))
    timesteps = set()
    for split in ("train", "val", "test"):
        js = root / f"transforms_{split}.json"
        meta = json.loads(js.read_text())
        for fr in meta["frames"]:
            fr.pop("mesh_path", None)
            ts = int(fr["timestep_index"])
            fr["flame_param_path"] = f"flame_param/{ts:05d}.npz"
            timesteps.add(ts)
        js.write_text(json.dumps(meta))
    rng = np.random.default_rng(7)
    for ts in timesteps:
        p = one(ts % 64)
        if dynamic_offset:
            p["dynamic_offset"] = 0.01 * rng.normal(size=(1, model.n_vertices, 3))
        np.savez(root / "flame_param" / f"{ts:05d}.npz", **p)
    return root, model, model_path, sorted(timesteps), one


@pytest.mark.slow  # a training run or a subprocess
def test_flame_mode_dataset_trains_and_exports(tiny_dataset, tmp_path):
    """A GaussianAvatars FLAME-mode dataset (flame_param_path per frame): train.py takes
    --flame-model, the run remembers it, export.py finds it there."""
    root, model, model_path, timesteps, _ = _flame_mode_dataset(tiny_dataset, tmp_path)
    run = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH="")
    base = [
        sys.executable,
        os.path.join(ROOT, "scripts", "train.py"),
        "--data",
        str(root),
        "--out",
        str(run),
        "--preset",
        "tiny",
        "--iterations",
        "8",
        "--no-progress",
    ]
    out = subprocess.run(base, capture_output=True, text=True, timeout=600, env=env)
    assert out.returncode == 2 and "--flame-model" in out.stderr  # FLAME mode without a model: a clear error
    out = subprocess.run(base + ["--flame-model", model_path], capture_output=True, text=True, timeout=600, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    av = Avatar.load(run / "avatar.npz")
    assert len(av.forest.template_faces) == len(model.faces) and np.all(np.isfinite(av.d_mu))
    assert av.forest.num_roots == len(model.faces) + len(av.forest.coarse_faces)
    assert json.loads((run / "config.json").read_text())["flame_model"] == model_path
    out = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "scripts", "export.py"),
            "--run",
            str(run),
            "--ply",
            str(tmp_path / "f.ply"),
            "--frame",
            str(min(timesteps)),
            "--max-views",
            "4",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    # trained as by default (backdrop stand-ins): the finished avatar's PLY leaves them out
    assert json.loads(out.stdout.splitlines()[-1])["ply_gaussians"] == len(av.forest.drawn()) < av.num_gaussians


def test_flame_refinement_learns_resumes_and_is_saved(tiny_dataset, tmp_path):
    root, model, model_path, timesteps, one = _flame_mode_dataset(tiny_dataset, tmp_path)
    cfg = config_for(
        "tiny",
        iterations=16,
        grow_every=8,
        grow_start=8,
        checkpoint_every=8,
        eval_every=1000,
        flame_model=model_path,
        refine_flame=True,
    )
    full = Trainer(str(root), str(tmp_path / "full"), cfg)
    full.run(progress=False)
    part = Trainer(str(root), str(tmp_path / "part"), cfg)
    part.run(progress=False, stop_after=8)
    resumed = Trainer(str(root), str(tmp_path / "part"), cfg, resume=True)
    resumed.run(progress=False)
    a = np.load(tmp_path / "full" / "flame_refined.npz")
    b = np.load(tmp_path / "part" / "flame_refined.npz")
    for k in ("correction_expr", "correction_pose", "correction_translation"):
        assert np.all(np.isfinite(a[k])) and np.abs(a[k]).max() > 0, k  # it learnt something
        np.testing.assert_allclose(a[k], b[k], atol=1e-7, err_msg=k)  # and resumed to the same result
    assert np.abs(a["correction_expr"]).max() < 16 * 1e-3 * 1.01  # Adam moves at most lr per step
    train_ts = set(full.train.timesteps.tolist())
    np.testing.assert_array_equal(a["timesteps"], sorted(train_ts))
    t0 = int(a["timesteps"][0])
    np.testing.assert_allclose(a["expr"][0], one(t0 % 64)["expr"][0] + a["correction_expr"][0], atol=1e-6)
    with pytest.raises(ValueError, match="FLAME-mode dataset"):
        Trainer(tiny_dataset, str(tmp_path / "mesh"), config_for("tiny", refine_flame=True))
    # What comes after training poses the run's data as it was trained: the novel views
    # (training timesteps) on the refined meshes, the novel expressions as tracked.
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.io.run import run_dataset
    from progressive_avatars.core.io.sequences import DataError

    for split in ("val", "test"):
        posed = run_dataset(str(tmp_path / "full"), str(root), split, model_path)
        tracked = Dataset(str(root), split, flame_model=model_path)
        for t in posed.timesteps.tolist():
            if full.refiner.has(t):
                refined = full.refiner.vertices(t).detach().numpy()
                assert np.abs(refined - tracked.vertices_at(t)).max() > 1e-5  # corrections moved it
                np.testing.assert_allclose(posed.vertices_at(t), refined, atol=2e-6)
            else:
                np.testing.assert_array_equal(posed.vertices_at(t), tracked.vertices_at(t))
    assert set(full.val.timesteps.tolist()) <= train_ts and not set(posed.timesteps.tolist()) & train_ts
    # Another dataset's frames are not posed with this run's refinement (same ids, other frames)
    import shutil

    other = tmp_path / "other_data"
    shutil.copytree(root, other)
    posed = run_dataset(str(tmp_path / "full"), str(other), "val", model_path)
    t = int(posed.timesteps[0])
    np.testing.assert_array_equal(
        posed.vertices_at(t), Dataset(str(other), "val", flame_model=model_path).vertices_at(t)
    )
    # A damaged refinement file is named
    (tmp_path / "full" / "flame_refined.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(DataError, match=r"flame_refined\.npz: cannot read refined FLAME parameters"):
        run_dataset(str(tmp_path / "full"), str(root), "val", model_path)


def test_flame_run_keeps_its_avatar_corrections_and_timesteps_together(tiny_dataset, tmp_path, monkeypatch):
    """A run stopped between writing avatar.npz and flame_refined.npz (or a resumed one, between
    the new avatar and the old corrections) exported silently with frames posed unlike training
    posed them; a checkpoint did not say which timesteps its corrections belong to; the ranks'
    state digest left the corrections out."""
    from progressive_avatars.core.io.run import run_dataset

    root, model, model_path, timesteps, one = _flame_mode_dataset(tiny_dataset, tmp_path)
    cfg = config_for(
        "tiny",
        iterations=8,
        grow_every=4,
        grow_start=4,
        checkpoint_every=4,
        eval_every=1000,
        flame_model=model_path,
        refine_flame=True,
    )
    run = tmp_path / "run"
    tr = Trainer(str(root), str(run), cfg)
    tr.run(progress=False)
    with np.load(run / "flame_refined.npz") as z:
        assert int(z["iteration"]) == 8
    with np.load(run / "checkpoint.npz") as z:
        ckpt = dict(z)
    np.testing.assert_array_equal(ckpt["flame_timesteps"], tr.refiner.timesteps)
    run_dataset(str(run), str(root), "val", model_path)  # the pair is whole
    # Importance is measured on the refined meshes, so its cache is keyed on the corrections:
    # others (here the head moved 2 cm), measured again.
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.render import importance

    calls, real = [], importance.face_importance
    monkeypatch.setattr(importance, "face_importance", lambda *a, **k: calls.append(1) or real(*a, **k))
    av = runs.load_run_avatar(str(run))
    w = runs.run_importance(str(run), av, str(root), max_views=1, progress=False)
    refined = dict(np.load(run / "flame_refined.npz"))
    np.savez(run / "flame_refined.npz", **(refined | {"translation": refined["translation"] + 0.02}))
    moved = runs.run_importance(str(run), av, str(root), max_views=1, progress=False)
    assert len(calls) == 2 and not np.array_equal(moved, w)
    # The corrections of another iteration, or none, beside the avatar: refused, with the way out.
    np.savez(run / "flame_refined.npz", **(refined | {"iteration": np.asarray(4)}))
    with pytest.raises(ValueError, match=r"corrections of iteration 4, .*avatar\.npz is of iteration 8 .*--resume"):
        run_dataset(str(run), str(root), "val", model_path)
    os.remove(run / "flame_refined.npz")
    with pytest.raises(ValueError, match=r"trained with --refine-flame but .*flame_refined\.npz is missing"):
        run_dataset(str(run), str(root), "test", model_path)
    link = tmp_path / "data_link"  # the run's own data through another path: checked alike
    os.symlink(root, link)
    with pytest.raises(ValueError, match=r"flame_refined\.npz is missing"):
        run_dataset(str(run), str(link), "val", model_path)
    # A file written before corrections recorded their iteration is taken as the avatar's.
    np.savez(run / "flame_refined.npz", **{k: v for k, v in refined.items() if k != "iteration"})
    run_dataset(str(run), str(root), "val", model_path)
    # An avatar trained without --refine-flame needs no corrections beside it.
    os.remove(run / "flame_refined.npz")
    plain = Avatar.load(str(run / "avatar.npz"))
    plain.meta["config"]["refine_flame"] = False
    plain.save(str(run / "avatar.npz"))
    run_dataset(str(run), str(root), "val", model_path)
    import shutil

    other = tmp_path / "other_data"  # another dataset is posed as tracked: the pair is not needed there
    shutil.copytree(root, other)
    run_dataset(str(run), str(other), "val", model_path)
    # The checkpoint's corrections belong to its timesteps.
    with pytest.raises(ValueError, match=r"corrections are for training timesteps \[.*\], the dataset's are"):
        tr.refiner.load_state(ckpt | {"flame_timesteps": ckpt["flame_timesteps"][::-1] + 1}, "ckpt")
    # The ranks compare the corrections too.
    before = tr._state_digest()
    with torch.no_grad():
        tr.refiner.delta["expr"] += 0.5
    assert tr._state_digest() != before


def test_resume_note_compares_with_the_length_the_checkpoint_followed(tiny_dataset, tmp_path, capsys):
    """The length note compared with config.json's, which a resume stopped before its first
    checkpoint had rewritten: resuming the checkpoint with its own length said "instead of 100",
    resuming with the aborted length said nothing. A changed batch said nothing."""
    run = tmp_path / "run"
    cfg = config_for("tiny", iterations=8, checkpoint_every=4, eval_every=10**6)
    Trainer(tiny_dataset, str(run), cfg).run(progress=False, stop_after=4)
    Trainer(tiny_dataset, str(run), replace(cfg, iterations=20), resume=True)  # killed before a checkpoint
    assert json.loads((run / "config.json").read_text())["iterations"] == 20
    capsys.readouterr()
    Trainer(tiny_dataset, str(run), cfg, resume=True)
    assert "instead of" not in capsys.readouterr().err
    Trainer(tiny_dataset, str(run), replace(cfg, iterations=20), resume=True)
    assert "resumed at iteration 4 with 20 iterations instead of 8" in capsys.readouterr().err
    # Another batch (processes x views per step) is allowed, and said.
    Trainer(tiny_dataset, str(run), replace(cfg, views_per_step=2), resume=True)
    assert "resumed with 2 views per step (1 process(es) x 2) instead of the 1" in capsys.readouterr().err


def test_flame_refiner_starts_at_the_tracked_meshes(tiny_dataset, tmp_path):
    """Zero corrections give the dataset's own meshes, per-frame dynamic offsets (VHAP) included:
    --refine-flame must not move the training geometry before it has learnt anything."""
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.train.flame_refine import FlameRefiner

    root, model, model_path, timesteps, _ = _flame_mode_dataset(tiny_dataset, tmp_path, dynamic_offset=True)
    ds = Dataset(str(root), "train", flame_model=model_path)
    refiner = FlameRefiner(ds, {})
    for t in ds.timesteps.tolist():
        np.testing.assert_allclose(refiner.vertices(t).detach().numpy(), ds.vertices_at(t), atol=2e-6)


def test_flame_corrections_step_at_their_own_learning_rates(tiny_dataset, tmp_path):
    """Adam's first step moves every value by its learning rate (the gradient's sign times lr):
    expression, pose and translation by the rates given for each."""
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.train.flame_refine import FlameRefiner

    root, _, model_path, _, _ = _flame_mode_dataset(tiny_dataset, tmp_path)
    refiner = FlameRefiner(
        Dataset(str(root), "train", flame_model=model_path),
        {"flame_expr": 1e-3, "flame_pose": 2e-5, "flame_translation": 3e-6},
    )
    for k in ("expr", "pose", "translation"):
        refiner.delta[k].grad = torch.ones_like(refiner.delta[k])
    refiner.step()
    for k, lr in (("expr", 1e-3), ("pose", 2e-5), ("translation", 3e-6)):
        np.testing.assert_allclose(refiner.delta[k].detach().numpy(), -lr, rtol=1e-5, err_msg=k)


def test_paper_cpu_preset_schedule_and_bounded_cache():
    """paper-cpu: depth 4 reached while growth still runs, a growth budget that ends at 16.7-18x
    the paper-scale head's base (8192 template + 758 coarse faces) within max_faces, a bounded
    image cache; the cache bound reaches the training Dataset."""
    from types import SimpleNamespace

    from progressive_avatars.core.train.policies import Growth

    cfg = config_for("paper-cpu")
    growth = Growth.from_config(cfg)
    base = 8192 + 758
    last = max(it for it in range(cfg.iterations + 1) if growth.due(it))
    assert 16.7 <= growth.face_budget(base, last) / base <= 18  # base <= 6 % of the records, as the paper's
    assert growth.face_budget(base, last) <= cfg.max_faces and cfg.max_depth == 4
    caps = [
        Trainer.depth_cap(SimpleNamespace(cfg=cfg), it)
        for it in range(cfg.grow_start, cfg.iterations + 1, cfg.grow_every)
    ]
    last_growth = int(cfg.grow_stop * cfg.iterations)
    assert caps[0] == 1 and max(caps) == 4 and caps == sorted(caps)
    assert Trainer.depth_cap(SimpleNamespace(cfg=cfg), last_growth - cfg.grow_every) == 4  # splits at depth 4 happen
    assert 0 < cfg.image_cache_mb <= 2048
    assert config_for("paper-cpu", image_cache_mb=64).image_cache_mb == 64


def test_trainer_image_cache_budget(tiny_dataset, tmp_path):
    cfg = config_for("tiny", iterations=3, image_cache_mb=0.05)
    t = Trainer(tiny_dataset, str(tmp_path / "run"), cfg)
    assert t.train.cache_bytes == int(0.05 * 2**20)
    t.run(progress=False)
    assert 0 < t.train.cached_bytes <= t.train.cache_bytes


def _ssim_dense_reference(a, b):
    """The 11x11 two-dimensional window SSIM that core.train.losses used before the fused kernel."""
    import torch.nn.functional as F

    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    C = x.shape[1]
    t = torch.arange(11, dtype=x.dtype) - 5
    g = torch.exp(-(t**2) / (2 * 1.5**2))
    g = g / g.sum()
    w = (g[:, None] * g[None, :]).expand(C, 1, 11, 11).contiguous()
    mx, my = F.conv2d(x, w, groups=C), F.conv2d(y, w, groups=C)
    sxx = F.conv2d(x * x, w, groups=C) - mx**2
    syy = F.conv2d(y * y, w, groups=C) - my**2
    sxy = F.conv2d(x * y, w, groups=C) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))).mean()


@pytest.mark.parametrize("size", [(11, 11), (37, 23), (128, 88)])
def test_fused_ssim_matches_dense_window_and_metrics(size):
    """The fused CPU SSIM (and its separable torch fallback) against the dense 11x11 window in
    value and gradient, and against core.train.metrics (numpy, float64)."""
    from progressive_avatars.core.train import losses
    from progressive_avatars.core.train import metrics

    rng = np.random.default_rng(size[0])
    b = torch.tensor(rng.uniform(0, 1, size + (3,)), dtype=torch.float32)
    a0 = 0.6 * b + 0.4 * torch.tensor(rng.uniform(0, 1, size + (3,)), dtype=torch.float32)
    values, grads = [], []
    for fn in (losses.ssim, losses.ssim_torch, _ssim_dense_reference):
        a = a0.clone().requires_grad_(True)
        v = fn(a, b)
        v.backward()
        values.append(float(v.detach()))
        grads.append(a.grad)
    assert abs(values[0] - metrics.ssim(a0.numpy(), b.numpy())) < 1e-6
    for v, g in zip(values[:2], grads[:2]):
        assert abs(v - values[2]) < 1e-6
        assert float((g - grads[2]).norm() / grads[2].norm()) < 1e-5


@pytest.mark.parametrize("size", [(11, 11), (12, 25), (128, 88)])
def test_fused_photometric_matches_torch_composition(size):
    """The fused CPU photometric loss ((1 - λ) L1 + λ (1 - SSIM) in one pass over [H, W, C]
    rows, the target's window sums shared through a TargetWindow) against the torch
    composition it replaces, in value and gradient, for two images against one target; pixels
    equal to the target get L1's zero subgradient as in torch. A window made for another
    target is refused."""
    from progressive_avatars.core.train import losses

    rng = np.random.default_rng(size[1])
    b = torch.tensor(rng.uniform(0, 1, size + (3,)), dtype=torch.float32)
    window = losses.TargetWindow(b)
    for _ in range(2):
        a0 = 0.6 * b + 0.4 * torch.tensor(rng.uniform(0, 1, size + (3,)), dtype=torch.float32)
        a0[:4, :3] = b[:4, :3]
        a = a0.clone().requires_grad_(True)
        fused = losses.photometric(a, b, 0.2, window)
        fused.backward()
        r = a0.clone().requires_grad_(True)
        ref = 0.8 * (r - b).abs().mean() + 0.2 * (1 - losses.ssim_torch(r, b))
        ref.backward()
        assert abs(float(fused.detach()) - float(ref.detach())) < 1e-6
        assert float((a.grad - r.grad).norm() / r.grad.norm()) < 1e-5
        tol = 1e-4 * float(r.grad.abs().max())  # where a equals b too (sign 0), pixel by pixel
        assert float((a.grad - r.grad).abs().max()) < tol
    with pytest.raises(ValueError, match="another target"):
        losses.photometric(a0, b.clone(), 0.2, window)


def test_fused_ssim_gradient_finite_where_a_window_is_anticorrelated():
    """A window whose x and y are anticorrelated so that 2 cov + C2 rounds to 0 in float32: cut
    from the paper-scale head's training at iteration 59, where the fused SSIM's gradient was
    0/0 = NaN and stopped the run. The gradient must be finite and match the float64 dense
    window's."""
    from progressive_avatars.core.train import losses

    z = np.load(os.path.join(os.path.dirname(__file__), "data", "ssim_anticorrelated_window.npz"))
    b = torch.from_numpy(z["y"].transpose(1, 2, 0).copy())
    a0 = torch.from_numpy(z["x"].transpose(1, 2, 0).copy())
    ours = a0.clone().requires_grad_(True)
    losses.ssim(ours, b).backward()
    ref = a0.double().clone().requires_grad_(True)
    _ssim_dense_reference(ref, b.double()).backward()
    assert torch.isfinite(ours.grad).all()
    assert float((ours.grad.double() - ref.grad).norm() / ref.grad.norm()) < 1e-3


def test_steps_are_deterministic_for_seed_and_any_numba_thread_count(tiny_dataset, tmp_path):
    """Same seed: bit-identical parameters after a few steps, whatever the number of numba
    threads (binding, rasteriser and SSIM kernels sum in fixed orders)."""
    import numba

    cfg = config_for(
        "tiny", iterations=8, grow_every=3, grow_start=3, eval_every=1000, checkpoint_every=1000, grad_threshold=0.0
    )  # every seen leaf splits: the determinism covers growth
    results = []
    for k, threads in enumerate([numba.config.NUMBA_NUM_THREADS, 1, numba.config.NUMBA_NUM_THREADS]):
        numba.set_num_threads(threads)
        try:
            tr = Trainer(tiny_dataset, str(tmp_path / f"r{k}"), cfg)
            for _ in range(5):
                tr.step()
                tr.iteration += 1
                if tr.iteration % cfg.grow_every == 0:
                    tr._grow(tr.iteration)
        finally:
            numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        results.append({n: p.detach().clone() for n, p in tr.model.params.items()})
    assert results[0]["d_mu"].shape[0] > tr.model.forest.num_roots  # the forest grew on the way
    for other in results[1:]:
        for name, p in results[0].items():
            assert torch.equal(p, other[name]), name


def test_coarse_levels_on_by_default_and_switchable(tiny_dataset, tmp_path):
    """Coarse levels above the template (DESIGN.md 7): built from the canonical mesh on a
    subset of its vertices, supervised by the multi-level loss, never split; off with ()."""
    cfg = config_for("tiny", eval_every=10**6, checkpoint_every=10**6)
    tr = Trainer(tiny_dataset, str(tmp_path / "on"), cfg)
    f = tr.model.forest
    F0 = len(tr.train.faces)
    assert f.num_coarse_levels == 2 and f.level_counts().tolist() == [*f.coarse_counts, F0]
    from progressive_avatars.core.avatar.coarse import DEFAULT_FRACTIONS

    assert cfg.coarse_levels == DEFAULT_FRACTIONS == (1 / 32, 1 / 16)
    for count, frac in zip(f.coarse_counts, DEFAULT_FRACTIONS):  # about the asked fraction of the template
        assert 0.5 * frac * F0 < count < 1.5 * frac * F0, (count, frac * F0)
    assert set(np.unique(f.coarse_faces)) <= set(np.unique(tr.train.faces))
    assert len(tr.model.level_ids) == 3 and len(tr.model.level_ids[0]) == f.coarse_counts[0]
    loss = tr.step()["loss"]
    assert np.isfinite(loss) and tr.model.params["d_mu"].shape[0] == f.num_faces
    tr.grad_sum[:] = 1.0  # every leaf over the threshold: only template faces may split
    tr.grad_count[:] = 1.0
    tr._grow(cfg.grow_start)
    f = tr.model.forest
    assert f.level_counts()[3] > 0 and np.all(f.level[f.num_roots :] >= 3) and f.max_depth == 1
    off = Trainer(tiny_dataset, str(tmp_path / "off"), config_for("tiny", coarse_levels=()))
    assert off.model.forest.num_coarse_levels == 0 and off.model.forest.level_counts().tolist() == [F0]


def test_coarse_stand_ins_train_apart_and_leave_the_finished_avatar(tiny_dataset, tmp_path, monkeypatch):
    """Coarse stand-ins (coarse_stand_ins=True): the coarse levels' images render the coarse
    Gaussians alone; every image of the template level and finer, and the validation render of
    the finished avatar, leave them out (opacity 0), so they learn from their own levels only.
    Cumulative coarse levels stay in every image. In-level prefix cuts need cumulative or
    backdrop ones: refused by name."""
    from progressive_avatars.core.train import trainer as trainer_mod

    cfg = dict(eval_every=10**6, checkpoint_every=10**6)
    SI = dict(coarse_stand_ins=True, coarse_backdrop=False)  # stand-ins that leave
    CUM = dict(coarse_stand_ins=False, coarse_backdrop=False)
    tr = Trainer(tiny_dataset, str(tmp_path / "si"), config_for("tiny", **SI, **cfg))
    f = tr.model.forest
    K, coarse = f.num_coarse_levels, np.flatnonzero(f.level < f.num_coarse_levels)
    assert f.stand_ins and K == 2 and len(coarse) == f.num_coarse
    calls = []
    real = trainer_mod.render_levels

    def spy(means, quats, scales, opacities, colors, *args, level, upto, **kw):
        calls.append((len(means), opacities.detach().numpy().copy(), list(upto)))
        return real(means, quats, scales, opacities, colors, *args, level=level, upto=upto, **kw)

    monkeypatch.setattr(trainer_mod, "render_levels", spy)
    tr.step()
    (n0, _, up0), (n1, op1, up1) = calls
    assert n0 == len(coarse) and up0 == [0, 1] and n1 == f.num_faces and up1 == [2]
    assert np.all(op1[coarse] == 0) and np.all(op1[f.level >= K] > 0)
    monkeypatch.setattr(trainer_mod, "render_levels", real)

    # Weighted 0, the coarse levels teach their Gaussians nothing (their colours stay), while
    # cumulative coarse Gaussians still learn through the template level's image.
    def coarse_colour_moved(name, **kw):
        t = Trainer(tiny_dataset, str(tmp_path / name), config_for("tiny", coarse_weight=0.0, **cfg, **kw))
        before = t.model.params["f_dc"].detach().numpy()[coarse].copy()
        t.step()
        return not np.array_equal(t.model.params["f_dc"].detach().numpy()[coarse], before)

    assert not coarse_colour_moved("si0", **SI) and coarse_colour_moved("cum0", **CUM)

    # The validation score of the finished avatar does not see the stand-ins at all.
    def val_with_loud_coarse(t):
        a = t.evaluate(2)["val_psnr"]
        with torch.no_grad():
            t.model.params["opacity_logit"][coarse] = 8.0
            t.model.params["f_dc"][coarse] = 5.0
        return a, t.evaluate(2)["val_psnr"]

    si = config_for("tiny", **SI, **cfg)
    a, b = val_with_loud_coarse(Trainer(tiny_dataset, str(tmp_path / "v1"), si))
    assert a == b
    a, b = val_with_loud_coarse(Trainer(tiny_dataset, str(tmp_path / "v2"), config_for("tiny", **CUM, **cfg)))
    assert b < a - 0.1
    # A run keeps its kind when resumed without the option.
    old = config_for("tiny", iterations=4, checkpoint_every=2, eval_every=10**6, **SI)
    Trainer(tiny_dataset, str(tmp_path / "old"), old).run(progress=False)
    again = Trainer(
        tiny_dataset, str(tmp_path / "old"), config_for("tiny", iterations=6, eval_every=10**6), resume=True
    )
    assert again.model.forest.stand_ins and again.cfg.coarse_stand_ins and not again.cfg.coarse_backdrop
    assert json.load(open(tmp_path / "old" / "config.json"))["coarse_stand_ins"] is True
    with pytest.raises(ValueError, match="stand-ins that leave"):
        config_for("tiny", prefix_cuts=1, **SI)
    config_for("tiny", prefix_cuts=1)
    config_for("tiny", prefix_cuts=1, **SI, coarse_levels=())


def test_coarse_backdrop_trains_with_the_stand_ins_behind(tiny_dataset, tmp_path, monkeypatch):
    """Backdrop stand-ins (coarse_backdrop=True): the coarse levels' images render the coarse
    Gaussians alone, as stand-ins do; every image of the template level and finer but the whole
    avatar's keeps them at their own opacity, composited behind the rest (render's ``behind`` is
    exactly the coarse faces); the whole avatar's image leaves them out (whole_without_backdrop;
    with it off, that image too has them behind). The validation render of the finished avatar
    draws them behind, as a stream does, so a loud stand-in changes it only where the rest leaves
    light through. The avatar, the checkpoint and a resume keep the kind."""
    from progressive_avatars.core.train import trainer as trainer_mod

    from progressive_avatars.core.render.rasterize import render

    cfg = dict(eval_every=10**6, checkpoint_every=10**6, backdrop_cuts=0)  # (the cuts: the next test)
    calls = []
    real = trainer_mod.render_levels

    def spy(*args, level, upto, behind=None, last_from=None, **kw):
        outs = real(*args, level=level, upto=upto, behind=behind, last_from=last_from, **kw)
        g = [a.detach().clone() for a in args[:5]]
        calls.append(
            (g, args[5], np.asarray(level).copy(), list(upto), behind, last_from, [o.image.detach() for o in outs])
        )
        return outs

    for whole_alone in (True, False):
        tr = Trainer(
            tiny_dataset,
            str(tmp_path / f"bd{whole_alone}"),
            config_for("tiny", coarse_backdrop=True, whole_without_backdrop=whole_alone, **cfg),
        )
        tr.grad_sum[:] = 1.0  # split every template face: a level below the template, the whole avatar's
        tr.grad_count[:] = 1.0
        tr._grow(tr.cfg.grow_start)
        f = tr.model.forest
        K, coarse = f.num_coarse_levels, np.flatnonzero(f.level < f.num_coarse_levels)
        assert f.stand_ins and f.backdrop and K == 2 and f.max_level == 3
        calls.clear()
        monkeypatch.setattr(trainer_mod, "render_levels", spy)
        tr.step()
        monkeypatch.setattr(trainer_mod, "render_levels", real)
        # one pass shares projection and sort: every level, the stand-ins behind the rest
        ((g, camera, level, upto, behind, last_from, images),) = calls
        assert upto == [0, 1, 2, 3] and np.array_equal(level, f.level) and bool((g[3][coarse] > 0).all())
        np.testing.assert_array_equal(np.flatnonzero(behind), coarse)
        assert last_from == (K if whole_alone else None)
        for lv, image in zip(upto, images):
            # what each image must show: a coarse level its stand-ins alone; the template level and
            # finer with every stand-in behind them; the whole avatar, with whole_without_backdrop,
            # without the stand-ins
            shown = f.level <= lv
            if lv == f.max_level and whole_alone:
                shown &= f.level >= K
            ids = torch.as_tensor(np.flatnonzero(shown))
            back = None if lv < K else np.isin(ids.numpy(), coarse)
            want = render(*(x[ids] for x in g), camera, tr.background, behind=back).image
            assert (want - image).abs().max() < 1e-5, (whole_alone, lv)
    assert tr.model.to_avatar().forest.backdrop
    with torch.no_grad():  # the rest made clear: the validation render shows the stand-ins
        tr.model.params["opacity_logit"][f.level >= K] = -30.0
        a = tr.evaluate(2)["val_psnr"]
        tr.model.params["f_dc"][coarse] += 1.0
    assert tr.evaluate(2)["val_psnr"] != a  # (stand-ins that leave would not be seen at all)
    old = config_for("tiny", iterations=4, checkpoint_every=2, eval_every=10**6, coarse_backdrop=True)
    Trainer(tiny_dataset, str(tmp_path / "old"), old).run(progress=False)
    assert Avatar.load(str(tmp_path / "old" / "avatar.npz")).forest.backdrop
    again = Trainer(
        tiny_dataset, str(tmp_path / "old"), config_for("tiny", iterations=6, eval_every=10**6), resume=True
    )
    assert again.model.forest.backdrop and again.cfg.coarse_backdrop and again.cfg.coarse_stand_ins


def test_backdrop_prefix_cuts_render_what_the_stream_shows(tiny_dataset, tmp_path, monkeypatch):
    """In-level prefix cuts with backdrop stand-ins (backdrop_cuts: inside the template level): each cut is
    its own render of every stand-in and the template level's first faces in stream order, the
    stand-ins of complete regions behind the rest: the very faces and mask a reader of the
    stream (version 4, the same importance and rest pose) renders at that many records."""
    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.stream.writer import write_stream
    from progressive_avatars.core.train import trainer as trainer_mod

    cfg = dict(eval_every=10**6, checkpoint_every=10**6, rank_views=3)
    tr = Trainer(
        tiny_dataset,
        str(tmp_path / "bdc"),
        config_for("tiny", coarse_backdrop=True, backdrop_cuts=3, **cfg),
    )
    f = tr.model.forest
    K, N, C = f.num_coarse_levels, f.num_faces, int(np.count_nonzero(f.level < f.num_coarse_levels))
    calls = []
    real = trainer_mod.render_levels

    def spy(means, *args, level, upto, behind=None, **kw):
        calls.append((len(means), list(upto), None if behind is None else np.asarray(behind).copy()))
        return real(means, *args, level=level, upto=upto, behind=behind, **kw)

    monkeypatch.setattr(trainer_mod, "render_levels", spy)
    assert np.isfinite(tr.step()["loss"])
    cuts = [(up[0], b) for n, up, b in calls if n == N and len(up) == 1 and C <= up[0] < C + len(f.template_faces) - 1]
    assert len(cuts) >= 2  # three draws inside the template level (two may coincide)
    assert calls[-1][1][-1] == N - 1  # the finest image still renders last
    key = tr.stream_key
    info = write_stream(
        tmp_path / "s.pavs",
        tr.model.to_avatar(),
        tr.rank_importance,
        quantize=False,
        version=4,
        vertices=tr.train.canonical_vertices,
    )
    np.testing.assert_array_equal(key[info.order], np.arange(N))
    fo = read_stream(str(tmp_path / "s.pavs")).forest
    for u, behind in cuts:  # the renders used the mask
        b = tr._cut_behind(u)
        assert (behind is None) == (b is None) and (b is None or np.array_equal(behind, b))
    some_behind = False
    for u in range(C, C + len(f.template_faces)):  # every prefix ending in the template level
        ids, back = fo.render_set(fo.stream_ids(u + 1))
        shown = np.sort(info.order[ids])
        np.testing.assert_array_equal(shown, np.flatnonzero(key <= u))  # every stand-in + the first faces
        want = np.zeros(N, bool)
        if back is not None:
            want[info.order[ids[back]]] = True
        got = tr._cut_behind(u)
        np.testing.assert_array_equal(np.zeros(N, bool) if got is None else got, want, err_msg=str(u))
        assert np.all(f.level[want] < K)
        some_behind |= bool(want.any())
    assert some_behind and want[f.level < K].all()  # the last: every stand-in behind
    with pytest.raises(ValueError, match="backdrop cuts"):
        config_for("tiny", backdrop_cuts=-1)


def test_cuts_leave_the_view_sequence_of_their_seed_alone(tiny_dataset, tmp_path):
    """In-level prefix cuts draw from their own generator: a run with cuts sees the same training
    views, in the same order, as the run of the same seed without them (so the studies' runs
    paired by seed are paired)."""
    seen = {}
    for name, cuts in (("with", dict(backdrop_cuts=2, prefix_cuts=1)), ("without", dict(backdrop_cuts=0))):
        tr = Trainer(
            tiny_dataset,
            str(tmp_path / name),
            config_for("tiny", eval_every=10**6, checkpoint_every=10**6, rank_views=2, **cuts),
        )
        views, draw = [], tr._views
        tr._views = lambda draw=draw, views=views: views.append(draw()) or views[-1]
        for _ in range(6):
            tr.step()
            tr.iteration += 1
        seen[name] = views
        if name == "with":
            assert tr._cuts()  # cuts were drawn
    assert seen["with"] == seen["without"] and len({v[0] for v in seen["with"]}) > 1


def test_coarse_weight_scales_the_coarse_levels_loss(tiny_dataset, tmp_path):
    cfg = dict(eval_every=10**6, checkpoint_every=10**6)
    full = Trainer(tiny_dataset, str(tmp_path / "w1"), config_for("tiny", **cfg))
    off = Trainer(tiny_dataset, str(tmp_path / "w0"), config_for("tiny", coarse_weight=0.0, **cfg))
    # Same view (same seed), same parameters: only the coarse levels' terms are gone (the coarse
    # Gaussians still learn through every later level, which renders them too).
    assert off.step()["loss"] < full.step()["loss"]
    with pytest.raises(ValueError, match="coarse weight"):
        config_for("tiny", coarse_weight=-1.0)


def test_base_supervision_takes_the_finest_and_one_base_level(tiny_dataset, tmp_path):
    """supervision="base": every step the finest level and one of the coarse and template levels
    (the forest's own count of coarse levels), never a subdivision level below the finest."""
    cfg = config_for("tiny", supervision="base", max_faces=10**6, eval_every=10**6, checkpoint_every=10**6)
    tr = Trainer(tiny_dataset, str(tmp_path / "base"), cfg)
    tr.grad_sum[:] = 1.0
    tr.grad_count[:] = 1.0
    tr._grow(cfg.grow_start)
    tr.grad_sum[:] = 1.0
    tr.grad_count[:] = 1.0
    tr._grow(cfg.grow_start + 2 * cfg.grow_every)  # depth 2 opens at the third growth step
    forest = tr.model.forest
    K, top = forest.num_coarse_levels, forest.max_level
    assert K >= 1 and top >= K + 2  # coarse levels, the template and two subdivision levels
    seen = {tuple(tr._levels()) for _ in range(200)}
    assert seen == {(lv, top) for lv in range(K + 1)}
    assert np.isfinite(tr.step()["loss"])


def test_finest_tail_trains_the_finest_alone_and_keeps_the_base(tiny_dataset, tmp_path, monkeypatch):
    """finest_tail: past 1 - tail of the iterations a step supervises the finest level only and
    leaves the roots' Gaussians (coarse and template faces) exactly as they were; before it, the
    preset's supervision and every face moves. A tail that would overlap growth is refused."""
    with pytest.raises(ValueError, match="finest tail"):
        config_for("tiny", finest_tail=0.5)  # the tiny preset grows until 80 %
    from progressive_avatars.core.train import trainer as trainer_mod

    cfg = config_for(  # cumulative coarse levels: every image of a step in one render (images[-1] counts them)
        "tiny",
        finest_tail=0.2,
        prefix_cuts=2,
        rank_views=2,
        eval_every=10**6,
        checkpoint_every=10**6,
        coarse_stand_ins=False,
        coarse_backdrop=False,
    )
    tr = Trainer(tiny_dataset, str(tmp_path / "tail"), cfg)
    images = []
    real = trainer_mod.render_levels

    def spy(*args, upto, **kw):
        images.append(len(upto))
        return real(*args, upto=upto, **kw)

    monkeypatch.setattr(trainer_mod, "render_levels", spy)
    tr.grad_sum[:] = 1.0
    tr.grad_count[:] = 1.0
    tr._grow(cfg.grow_start)
    R, top = tr.model.forest.num_roots, tr.model.forest.max_level
    assert tr.model.num_faces > R and top >= 1
    p = tr.model.params
    for it, in_tail in ((47, False), (48, True)):  # the tail starts at 60 * 0.8
        tr.iteration = it
        assert (tr._levels() == [top]) == in_tail
        before = {k: v.detach().clone() for k, v in p.items()}
        assert np.isfinite(tr.step()["loss"])
        assert (images[-1] == 1) == in_tail  # no coarser level and no in-level prefix in the tail
        for name in ("d_mu", "d_log_scale", "f_dc", "opacity_logit"):
            roots_same = torch.equal(p[name].detach()[:R], before[name][:R])
            assert roots_same == in_tail, (it, name)
            assert not torch.equal(p[name].detach()[R:], before[name][R:]), (it, name)
        assert not torch.equal(p["split_logits"].detach()[:R], before["split_logits"][:R])


def test_prefix_cuts_supervise_the_streams_prefixes_inside_levels(tiny_dataset, tmp_path, monkeypatch):
    """With prefix_cuts the step also supervises prefixes that end inside a level, in exactly
    the order the stream writer sends the faces (importance measured per level)."""
    from progressive_avatars.core.stream.writer import write_stream
    from progressive_avatars.core.train import trainer as trainer_mod

    cfg = config_for(  # cumulative coarse levels (backdrop ones: test_backdrop_prefix_cuts_...)
        "tiny",
        prefix_cuts=3,
        rank_views=3,
        eval_every=10**6,
        checkpoint_every=10**6,
        coarse_stand_ins=False,
        coarse_backdrop=False,
    )
    tr = Trainer(tiny_dataset, str(tmp_path / "cuts"), cfg)
    tr.grad_sum[:] = 1.0  # split every template face: four levels, the finest not yet ranked
    tr.grad_count[:] = 1.0
    tr._grow(cfg.grow_start)
    counts = tr.model.forest.level_counts()
    assert len(counts) == 4
    calls = []
    real = trainer_mod.render_levels

    def spy(*args, level, upto, **kw):
        calls.append((np.array(level), list(upto)))
        return real(*args, level=level, upto=upto, **kw)

    monkeypatch.setattr(trainer_mod, "render_levels", spy)
    assert np.isfinite(tr.step()["loss"])
    key, upto = calls[-1]
    N = tr.model.num_faces
    assert len(tr.rank_importance) == N  # measured again after the growth
    np.testing.assert_array_equal(np.sort(key), np.arange(N))
    # The level-by-level writer (version 4), given the same importance, sends face info.order[i]
    # i-th: the training's order. (Version 5 interleaves the levels when writing; training on
    # interleaved prefixes measured worse, so training keeps the level order.)
    info = write_stream(tmp_path / "s.pavs", tr.model.to_avatar(), tr.rank_importance, quantize=False, version=4)
    np.testing.assert_array_equal(key[info.order], np.arange(N))
    ends = np.cumsum(counts)
    assert set(ends - 1) <= set(upto) and upto[-1] == N - 1  # every level (supervision "all"), finest last
    inside = [u for u in upto if u + 1 not in ends]
    assert inside, "at least one prefix ends inside a level"
    level = tr.model.forest.level
    for u in inside:
        lv = int(np.searchsorted(ends, u + 1))
        shown = key <= u
        assert np.all(shown[level < lv]) and not np.any(shown[level > lv])
        assert 0 < shown[level == lv].sum() < counts[lv]
        # The level's faces shown are its most important ones.
        imp = tr.rank_importance[level == lv]
        assert imp[shown[level == lv]].min() >= imp[~shown[level == lv]].max()
    with pytest.raises(ValueError, match="prefix cuts"):
        config_for("tiny", prefix_cuts=-1)
    with pytest.raises(ValueError, match="prefix cut weight"):
        config_for("tiny", prefix_cut_weight=float("nan"))

    # The first step sees the same view with or without cuts: weighted 0 the cut images add
    # nothing to the loss; weighted 1 they add their photometric terms.
    def first_loss(name, **kw):
        cum = dict(coarse_stand_ins=False, coarse_backdrop=False)  # (backdrop cuts are in-level prefixes too)
        t = Trainer(tiny_dataset, str(tmp_path / name), config_for("tiny", eval_every=10**6, **cum, **kw))
        return t.step()["loss"]

    base = first_loss("none")
    assert first_loss("w0", prefix_cuts=2, prefix_cut_weight=0.0) == pytest.approx(base, rel=1e-6)
    assert first_loss("w1", prefix_cuts=2) > base + 1e-3


def test_growth_and_supervision_policies_are_validated(tmp_path):
    """An unknown supervision mode or an impossible growth setting is an error when the config is
    made (it used to train "all" silently), and the policies do what the trainer asks of them."""
    from progressive_avatars.core.train.policies import Growth, Supervision

    with pytest.raises(ValueError, match="supervision must be one of"):
        config_for("tiny", supervision="everything")
    with pytest.raises(ValueError, match="grad_threshold"):
        config_for("tiny", grad_threshold=float("nan"))
    rng = np.random.default_rng(0)
    assert Supervision("all").levels(3, rng) == [0, 1, 2, 3] and Supervision("finest").levels(3, rng) == [3]
    assert all(lv[-1] == 3 and len(lv) <= 2 for lv in (Supervision("sampled").levels(3, rng) for _ in range(20)))
    # base: the finest and one level of the base (coarse levels 0, 1 and the template level 2
    # here), every one of them in turn, never a subdivision level below the finest
    base = {tuple(Supervision("base").levels(6, rng, 2)) for _ in range(200)}
    assert base == {(0, 6), (1, 6), (2, 6)}
    assert {tuple(Supervision("base").levels(2, rng, 2)) for _ in range(50)} == {(0, 2), (1, 2)}
    assert {tuple(Supervision("base").levels(3, rng, 0)) for _ in range(20)} == {(0, 3)}
    assert Supervision("base").levels(0, rng, 0) == [0]
    g = Growth.from_config(config_for("cpu"))
    assert not g.due(149) and g.due(150) and not g.due(2850)  # growth stops at 70 % of 4000
    assert g.depth_cap(150) == 1 and g.depth_cap(2800) == 3
    # A budget capped by max_faces below grow_to x the base ends there at the last growth step,
    # not before (depth 3 opens late), from any base, with or without coarse levels.
    capped = Growth.from_config(config_for("cpu", grow_to=20.0, max_faces=25600))
    last = max(it for it in range(g.iterations + 1) if g.due(it))
    for base in (5120, 5120 + 156 + 316, 1280, 1280 + 36 + 76):
        assert capped.face_budget(base, last) == 25600 > capped.face_budget(base, last - g.grow_every)


def test_growth_by_budget_follows_its_schedule():
    """grow_to splits the largest mean gradients above the threshold, as many as the geometric
    schedule allows at each step, reaching grow_to x the base at the last growth step; without
    it the threshold alone decides (the first paper-scale run grew 4.3x where ~17x was asked)."""
    from progressive_avatars.core.avatar.forest import Forest
    from progressive_avatars.core.train.policies import Growth

    rng = np.random.default_rng(3)
    forest = Forest(rng.integers(0, 50, size=(100, 3)))
    kw = dict(iterations=1000, max_depth=3, grow_every=100, grow_start=100, grow_stop=0.5, grad_threshold=1e-3)
    budget = Growth(**kw, max_faces=10_000, grow_to=4.0)
    # five growth steps (100..500): 100 * 4 ** (i / 5) faces after step i; max_faces caps it
    assert [budget.face_budget(100, it) for it in (100, 300, 500)] == [131, 229, 400]
    # a cap below grow_to x the base is the schedule's end, reached at the last step, not early
    capped = Growth(**kw, max_faces=300, grow_to=4.0)
    assert [capped.face_budget(100, it) for it in (100, 300, 500)] == [124, 193, 300]
    assert Growth(**kw, max_faces=90, grow_to=4.0).face_budget(100, 500) == 90  # cap under the base
    grad = rng.random(100) * 2e-3  # about half above the threshold
    count = np.ones(100)
    pick = budget.pick(forest, grad, count, 100)
    assert len(pick) == (131 - 100) // 3
    # the largest gradients, all above the threshold
    assert grad[pick].min() >= np.sort(grad)[-len(pick)] and grad[pick].min() > 1e-3
    # the threshold stays a floor: the budget never splits a face below it
    late = budget.pick(forest, grad, count, 500)
    assert len(late) == np.count_nonzero(grad > 1e-3) < (400 - 100) // 3
    assert len(Growth(**kw, max_faces=10_000).pick(forest, grad, count, 100)) == len(late)
    for bad in (0.5, float("nan"), -1.0):
        with pytest.raises(ValueError, match="grow_to"):
            Growth(**kw, max_faces=100, grow_to=bad)


def test_growth_leaves_out_faces_below_the_size_floor():
    """split_min_px: only leaves whose projected size reaches the floor may split (the rest of
    the budget goes to the next largest gradients); uniform growth ignores it; a floor without
    sizes, or a negative or NaN one, is an error."""
    from progressive_avatars.core.avatar.forest import Forest
    from progressive_avatars.core.train.policies import Growth

    rng = np.random.default_rng(5)
    forest = Forest(rng.integers(0, 50, size=(100, 3)))
    kw = dict(iterations=1000, max_depth=3, grow_every=100, grow_start=100, grow_stop=0.5, grad_threshold=1e-3)
    grad, count = rng.random(100) * 2e-3, np.ones(100)
    size = np.where(np.arange(100) % 2 == 0, 3.0, 1.0)  # even faces 3 px, odd 1 px
    free = Growth(**kw, max_faces=10_000, grow_to=4.0).pick(forest, grad, count, 100, size)
    held = Growth(**kw, max_faces=10_000, grow_to=4.0, min_px=2.0).pick(forest, grad, count, 100, size)
    assert len(held) == len(free) == (131 - 100) // 3  # the budget is filled either way
    assert np.all(held % 2 == 0) and np.any(free % 2 == 1)
    even = np.flatnonzero((np.arange(100) % 2 == 0) & (grad > 1e-3))
    assert set(held) == set(even[np.argsort(-grad[even], kind="stable")][: len(held)])  # largest gradients
    uniform = Growth(**kw, max_faces=10_000, uniform=True, min_px=2.0).pick(forest, grad, count, 100, size)
    assert len(uniform) == 100
    with pytest.raises(ValueError, match="projected sizes"):
        Growth(**kw, max_faces=10_000, min_px=2.0).pick(forest, grad, count, 100)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="split_min_px"):
            config_for("tiny", split_min_px=bad)


def test_uniform_runs_split_every_face_or_refuse_the_face_cap(tiny_dataset, tmp_path):
    """--uniform is every template face split to --max-depth: a face cap too small for that is
    refused before training (it cut the last split by face index, leaving template faces
    0..k deeper than the rest, with no word); a cap that fits gives every face its children."""
    from progressive_avatars.core.io.dataset import Dataset

    from dataclasses import replace

    f0 = len(Dataset(tiny_dataset, "train").faces)
    base = config_for("tiny", uniform=True, max_depth=1, iterations=20, max_faces=10**6)
    fresh = Trainer(tiny_dataset, str(tmp_path / "probe"), base, check_data=False)
    need = fresh.model.forest.num_faces + 3 * f0  # the roots (coarse ones included) and 3 children each
    with pytest.raises(ValueError, match=f"needs {need:,} faces.*--max-faces {need} or more"):
        Trainer(tiny_dataset, str(tmp_path / "short"), replace(base, max_faces=need - 1))
    assert not os.path.exists(tmp_path / "short" / "checkpoint.npz")
    run = str(tmp_path / "fits")
    Trainer(tiny_dataset, run, replace(base, max_faces=need), check_data=False).run(progress=False)
    forest = Avatar.load(os.path.join(run, "avatar.npz")).forest
    assert forest.num_faces == need
    tmpl = forest.num_coarse + np.arange(f0)  # every template face has its three children
    assert np.array_equal(
        np.bincount(forest.parent[forest.parent >= 0], minlength=forest.num_faces)[tmpl], np.full(f0, 3)
    )


def test_trainer_measures_projected_sizes_and_growth_respects_the_floor(tiny_dataset, tmp_path):
    """The trainer's size record is each face's largest projected sigma (pixels) over the steps'
    views, from the Gaussians it rendered; a floor above every face stops growth, none lets it
    grow; the record survives a checkpoint."""
    import torch

    from progressive_avatars.core.train.trainer import Trainer

    cfg = config_for("tiny", split_min_px=1e-6, iterations=4, grow_start=100, grow_every=100)
    tr = Trainer(tiny_dataset, str(tmp_path / "sizes"), cfg)
    expected = np.zeros(tr.model.num_faces)
    for view in (0, 3):
        sample = tr.train[view]
        with torch.no_grad():
            g = tr.model.gaussians(tr._vertices(sample), sample.camera.center)
        means, scales = g["means"].double().numpy(), g["scales"].double().numpy()
        cam = sample.camera
        z = (means @ np.asarray(cam.R).T + cam.t)[:, 2]
        expected = np.maximum(expected, scales.max(1) * cam.fx / z)
        tr._views = lambda view=view: [view]
        tr.step()
        tr.iteration += 1
    assert np.all(expected > 0)
    np.testing.assert_allclose(tr.size_px, expected, rtol=1e-5)
    tr._save_checkpoint()
    again = Trainer(tiny_dataset, str(tmp_path / "sizes"), cfg, resume=True)
    np.testing.assert_array_equal(again.size_px, tr.size_px)

    grown = {}
    for floor in (0.0, 1e6):
        run = Trainer(tiny_dataset, str(tmp_path / f"floor{floor:g}"), config_for("tiny", split_min_px=floor))
        run.run(progress=False)
        grown[floor] = run.model.num_faces - run.model.forest.num_roots
    assert grown[0.0] > 0 and grown[1e6] == 0


def test_opacity_reset_cuts_every_opacity_while_the_forest_grows(tiny_dataset, tmp_path):
    """--opacity-reset-every N (3DGS and GaussianAvatars' reset): after iterations N, 2N, ... up
    to the last growth step every Gaussian's opacity is at most 0.01 and its Adam moments are
    clear while the other parameters' are not; training brings the opacities back; the log
    marks each reset; bad settings fail at configuration."""
    import torch

    from progressive_avatars.core.train.trainer import Trainer

    cfg = config_for("tiny", opacity_reset_every=25)  # 60 iterations, growth until 48: resets at 25 only
    tr = Trainer(tiny_dataset, str(tmp_path / "reset"), cfg)
    tr.run(progress=False, stop_after=24)
    before = torch.sigmoid(tr.model.params["opacity_logit"]).detach().numpy().copy()
    assert before.max() > 0.5
    tr.run(progress=False, stop_after=1)
    op = torch.sigmoid(tr.model.params["opacity_logit"]).detach().numpy()
    assert len(op) == len(before) and op.max() <= 0.01 * (1 + 1e-5)
    high = before > 0.05  # the last step moved these by far less than their distance to the cap
    assert high.mean() > 0.5
    np.testing.assert_allclose(op[high], 0.01, rtol=1e-5)
    assert not tr.opt.m["opacity_logit"].any() and not tr.opt.v["opacity_logit"].any()
    assert tr.opt.m["f_dc"].abs().sum() > 0 and tr.opt.v["d_log_scale"].abs().sum() > 0
    tr.run(progress=False)
    op = torch.sigmoid(tr.model.params["opacity_logit"]).detach().numpy()
    assert np.median(op) > 0.03  # 35 steps after the cut the image has brought most of them back
    log = [json.loads(ln) for ln in open(tmp_path / "reset" / "metrics.jsonl")]
    assert [r["iteration"] for r in log if "opacity_reset" in r] == [25]  # not at 50: growth ended at 48

    for bad in (dict(opacity_reset_every=-1), dict(opacity_reset_to=0.0), dict(opacity_reset_to=1.0)):
        with pytest.raises(ValueError, match="opacity reset"):
            config_for("tiny", **bad)

    # From the command line, with growth stopped earlier (--grow-stop): 30 iterations, growth until
    # 15, so one reset (at 10) and 15 iterations that train the grown forest without one.
    cmd = [sys.executable, os.path.join(ROOT, "scripts", "train.py"), "--data", tiny_dataset, "--preset", "tiny"]
    cmd += ["--iterations", "30", "--opacity-reset-every", "10", "--no-progress"]
    out = subprocess.run(cmd + ["--out", str(tmp_path / "cli"), "--grow-stop", "0.5"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads((tmp_path / "cli" / "config.json").read_text())["grow_stop"] == 0.5
    log = [json.loads(ln) for ln in open(tmp_path / "cli" / "metrics.jsonl")]
    assert [r["iteration"] for r in log if "opacity_reset" in r] == [10]
    out = subprocess.run(cmd + ["--out", str(tmp_path / "bad"), "--grow-stop", "1.5"], capture_output=True, text=True)
    assert out.returncode == 2 and "grow_stop in [0, 1]" in out.stderr and not (tmp_path / "bad").exists()


def test_blender_train_job_refuses_a_finished_run(tiny_dataset, tiny_run, tmp_path, capsys):
    """Blender's Train (core/train/jobs.py) into a Run folder that holds a trained run: refused
    with the UI's words, the run untouched."""
    import shutil

    from progressive_avatars.core.train import jobs

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    rc = jobs.main(["train", "--data", tiny_dataset, "--out", str(run), "--preset", "tiny", "--no-export"])
    assert rc == 2 and "choose another Run folder" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and p.name != ".train.lock"} == {
        k: v for k, v in before.items() if k != ".train.lock"
    }
    # The panel's Overwrite Run (--overwrite) starts over.
    args = ["train", "--data", tiny_dataset, "--out", str(run), "--preset", "tiny", "--iterations", "2"]
    assert jobs.main(args + ["--no-export", "--overwrite"]) == 0
    assert (run / "avatar.npz").read_bytes() != before["avatar.npz"]
    assert [json.loads(ln)["iteration"] for ln in open(run / "metrics.jsonl")][-1] == 2


def test_blender_train_job_stops_with_one_line_and_resumes_an_unwritten_stream(
    tiny_dataset, tiny_run, tmp_path, capsys, monkeypatch
):
    """Blender's Train (core/train/jobs.py) on a full disk: a raw traceback (exit 1) under the
    progress bar, which the add-on then showed as the reason; a trained avatar whose stream was
    not written was offered Overwrite Run (discarding it) where Resume writes the stream."""
    import errno
    import shutil

    from progressive_avatars.core.stream import writer
    from progressive_avatars.core.train import jobs

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", "somewhere/checkpoint.npz")

    args = ["train", "--data", tiny_dataset, "--preset", "tiny"]
    with monkeypatch.context() as m:
        m.setattr(Trainer, "run", full)
        assert jobs.main(args + ["--out", str(tmp_path / "fresh")]) == 3
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last == (
        "error: disk full: No space left on device (somewhere/checkpoint.npz); training stopped, "
        "no checkpoint was written yet"
    )
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    if (run / "avatar.pavs").exists():  # (other tests write the shared run's stream)
        os.remove(run / "avatar.pavs")  # trained, stream not written
    assert jobs.main(args + ["--out", str(run)]) == 2
    assert "tick Resume to write it" in capsys.readouterr().err
    with monkeypatch.context() as m:
        m.setattr(writer, "write_stream", lambda path, *a, **k: full())
        assert jobs.main(args + ["--out", str(run), "--resume"]) == 3
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("error: disk full") and last.endswith("tick Resume to write its stream")
    assert jobs.main(args + ["--out", str(run), "--resume"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == f"result: {run / 'avatar.pavs'}"


def test_blender_train_job_stream_retires_stand_ins_by_region(tiny_dataset, tmp_path):
    """The stream Blender's Train writes (core/train/jobs.py) places each stand-in's retirement on
    the dataset's rest pose, as export.py and evaluate.py do: it used to be written without the
    rest pose, every stand-in in front until the last template face (the writer now refuses that)."""
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.stream.writer import build_stream
    from progressive_avatars.core.train import jobs

    run = tmp_path / "run"
    assert jobs.main(["train", "--data", tiny_dataset, "--out", str(run), "--preset", "tiny", "--iterations", "4"]) == 0
    got = read_stream(str(run / "avatar.pavs")).forest
    assert got.stand_ins and got.retire is not None
    av = Avatar.load(run / "avatar.npz")
    W = runs.run_importance(str(run), av, tiny_dataset, progress=False)  # the job's, cached in the run
    _, info = build_stream(av, W, drop_sh=True, vertices=Dataset(tiny_dataset, None).canonical_vertices)
    np.testing.assert_array_equal(got.retire, info.coarse_retire)
    K = got.num_coarse_levels
    last = int(np.flatnonzero(got.level[got.stream_order()] == K).max())
    assert np.count_nonzero(got.retire < last) > len(got.retire) // 2  # most retire before the last template face


def test_config_refuses_negative_counts_and_caches():
    """Negative iterations used to train 0 iterations silently; a negative seed failed deep in
    numpy without naming the option; a negative or NaN image cache was taken as is."""
    with pytest.raises(ValueError, match="iterations and seed must be >= 0, got -5"):
        config_for("tiny", iterations=-5)
    with pytest.raises(ValueError, match="iterations and seed must be >= 0, got 60 and -1"):
        config_for("tiny", seed=-1)
    for mb in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="image cache must be"):
            config_for("tiny", image_cache_mb=mb)
    assert config_for("tiny", iterations=0, image_cache_mb=0).iterations == 0  # untrained avatar, no cache: allowed
    # refused up front: rank_every 0 divides by zero at the first cut, views_per_step 0 averages no views
    for bad, match in (
        (dict(rank_every=0), "rank_every and rank_views >= 1"),
        (dict(rank_views=0), "rank_every and rank_views >= 1"),
        (dict(prefix_cuts=-1), "prefix cuts must be >= 0"),
        (dict(backdrop_cuts=-1), "backdrop cuts must be >= 0"),
        (dict(views_per_step=0), "views per step must be >= 1"),
        (dict(log_every=0), "intervals must be >= 1"),  # a ZeroDivisionError at the first iteration
        (dict(eval_every=0), "intervals must be >= 1"),
        (dict(checkpoint_every=0), "intervals must be >= 1"),
        (dict(eval_views=-1), "evaluation views >= 0"),  # a linspace error at the first evaluation
    ):
        with pytest.raises(ValueError, match=match):
            config_for("tiny", **bad)
    # backdrop stand-ins are stand-ins; without coarse levels there is neither
    assert config_for("tiny", coarse_stand_ins=False).coarse_stand_ins
    cfg = config_for("tiny", coarse_levels=())
    assert not cfg.coarse_stand_ins and not cfg.coarse_backdrop


def test_blender_training_job_resumes_a_cancelled_run(tiny_dataset, tmp_path, capsys):
    """The Train operator's job (core/train/jobs.py): a cancelled run (checkpoint, no avatar) is
    named as unfinished and offered Resume, which continues it; Resume with Overwrite is one too many."""
    from progressive_avatars.core.train import jobs

    run = tmp_path / "run"
    cfg = config_for("tiny", iterations=8, checkpoint_every=4, eval_every=10**6)
    Trainer(tiny_dataset, str(run), cfg).run(progress=False, stop_after=4)
    os.remove(run / "avatar.npz")  # as Cancel leaves it: killed after its checkpoint, before any avatar
    args = ["train", "--data", tiny_dataset, "--out", str(run), "--preset", "tiny", "--no-export"]
    assert jobs.main(args + ["--iterations", "8"]) == 2
    assert "unfinished training" in capsys.readouterr().err
    assert jobs.main(args + ["--iterations", "8", "--resume"]) == 0
    assert Avatar.load(run / "avatar.npz").num_gaussians > 0
    assert jobs.main(args + ["--iterations", "8"]) == 2
    assert "already holds a trained run" in capsys.readouterr().err


_FREED_MEMORY_PROBE = """
import resource, sys
import numpy as np
if sys.argv[1] == "retain":
    from progressive_avatars.core.train.memory import retain_freed_memory
    assert retain_freed_memory()
counts = []
for _ in range(6):  # a step's pattern: several large arrays made, filled and freed together
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    arrays = [np.ones(5 << 19) for _ in range(3)]  # 20 MB each
    del arrays
    counts.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sum(counts[1:]))
"""


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or __import__("platform").libc_ver()[0] != "glibc",
    reason="retain_freed_memory tunes glibc's malloc only",
)
def test_training_processes_reuse_freed_memory_instead_of_faulting_it_in_again():
    # What scripts/train.py and the add-on's job set: after the first round the same arrays come
    # from memory the process kept, not from fresh pages (glibc's defaults trim the heap here and
    # fault ~1,000 pages in again every round).
    def faults(mode):
        out = subprocess.run(
            [sys.executable, "-c", _FREED_MEMORY_PROBE, mode], capture_output=True, text=True, timeout=120
        )
        assert out.returncode == 0, out.stderr
        return int(out.stdout.strip())

    default, retained = faults("default"), faults("retain")
    if default < 100:  # e.g. transparent huge pages everywhere: few faults to save, nothing to test
        pytest.skip(f"glibc's defaults faulted only {default} pages here")
    assert retained < default / 10


def test_growth_and_sampling_rules_by_hand():
    """Growth's and sampled supervision's rules on hand-made cases: "sampled" is always the
    finest and one coarser level; no leaf at the depth cap splits; with a zero threshold only
    faces that had a gradient split; uniform growth ignores grow_to; the budget ends exactly on
    its target; no growth step that fits gives last_step -1."""
    from progressive_avatars.core.avatar.forest import Forest
    from progressive_avatars.core.train.policies import Growth, Supervision
    from tests.helpers import sphere_mesh

    def growth(**kw):
        a = dict(iterations=1000, max_depth=2, grow_every=100, grow_start=100, grow_stop=0.8, grad_threshold=0.1)
        return Growth(**{**a, "max_faces": 10**6, **kw})

    rng = np.random.default_rng(0)
    for _ in range(200):
        lv = Supervision("sampled").levels(3, rng)
        assert len(lv) == 2 and lv[-1] == 3 and lv[0] < 3
    _, faces = sphere_mesh(3, 4)
    f = Forest(faces)
    N = f.num_faces
    some = np.zeros(N)
    some[:3] = 1.0
    assert growth(grad_threshold=0.0).pick(f, some, np.ones(N), it=800).tolist() == [0, 1, 2]
    f.split(np.arange(N))
    g = growth(max_depth=1)
    assert g.depth_cap(800) == 1 and len(g.pick(f, np.full(f.num_faces, 10.0), np.ones(f.num_faces), it=800)) == 0
    assert growth(uniform=True, grow_to=4.0, max_faces=5000).face_budget(100, 100) == 5000
    g = growth(grow_to=20.0, max_faces=63)
    assert g.face_budget(13, g.last_step) == 63
    assert growth(iterations=50, grow_every=100, grow_start=0).last_step == -1


def test_growth_settings_are_checked_and_gradients_averaged():
    """Impossible growth settings are errors when the policy is made (grow_every 0 would divide
    by zero at the first step; grow_stop is a fraction of the run; a negative threshold splits
    every face); grow_to 1 is a factor (no growth past the base). A face's gradient is its mean
    over the steps that saw it (a face seen often is not split for its sum), and a face whose
    projected size is exactly split_min_px reaches it."""
    from progressive_avatars.core.avatar.forest import Forest
    from progressive_avatars.core.train.policies import Growth
    from tests.helpers import sphere_mesh

    kw = dict(iterations=1000, max_depth=2, grow_every=100, grow_start=100, grow_stop=0.8, grad_threshold=0.4)
    for bad, match in (
        (dict(grow_every=0), "grow_every >= 1"),
        (dict(max_depth=-1), "max_depth >= 0"),
        (dict(max_faces=-1), "max_faces >= 0"),
        (dict(grow_stop=1.5), "grow_stop in"),
        (dict(grow_stop=-0.1), "grow_stop in"),
        (dict(grad_threshold=-0.1), "grad_threshold"),
    ):
        with pytest.raises(ValueError, match=match):
            Growth(**{**kw, "max_faces": 1000, **bad})
    assert Growth(**kw, max_faces=1000, grow_to=1.0).face_budget(100, 500) == 100
    _, faces = sphere_mesh(3, 4)
    f = Forest(faces)
    N = f.num_faces
    grad_sum, grad_count = np.zeros(N), np.ones(N)
    grad_sum[:4], grad_count[:4] = [3.0, 0.5, 0.45, 0.9], [10, 1, 1, 3]  # means 0.3, 0.5, 0.45, 0.3
    g = Growth(**kw, max_faces=10**6)
    assert g.pick(f, grad_sum, grad_count, it=200).tolist() == [1, 2]
    size = np.full(N, 1.0)
    size[1] = 2.0
    held = Growth(**kw, max_faces=10**6, min_px=2.0).pick(f, grad_sum, grad_count, it=200, size_px=size)
    assert held.tolist() == [1]


def test_run_refused_before_training_when_its_disk_cannot_hold_it(
    tiny_dataset, tiny_run, tmp_path, capsys, monkeypatch
):
    """A nearly full disk showed only at the first checkpoint, after up to checkpoint_every
    iterations (hours at the paper's scale): refused before training now, naming what it needs;
    a resume counts the outputs it replaces as free; the estimate holds a trained run's files."""
    import collections
    import runpy
    import shutil

    from progressive_avatars.core.train import trainer as T

    saved = list(sys.path)
    train_main = runpy.run_path(os.path.join(ROOT, "scripts", "train.py"), run_name="train_script")["main"]
    sys.path[:] = saved

    # The estimate covers what a trained run holds at its peak (the last checkpoint's temporary
    # beside the previous one), without being wildly above it.
    names = ("checkpoint.npz", "avatar.npz", "importance.npz", "importance_alpha.npz", "importance_whole.npz")
    held = {n: os.path.getsize(os.path.join(tiny_run, n)) for n in names if os.path.exists(os.path.join(tiny_run, n))}
    ckpt = np.load(os.path.join(tiny_run, "checkpoint.npz"))
    faces = len(ckpt["forest_parent"])
    width = sum(int(np.prod(ckpt[k].shape[1:])) for k in ckpt.files if k.startswith("param_"))
    peak = 2 * held["checkpoint.npz"] + held["avatar.npz"] + 3 * 8 * faces + 25 * faces
    assert peak <= T.run_bytes(faces, width) <= peak + 9 * 2**20
    assert T._faces_bound(config_for("paper-cpu"), 10_000, 9_700, 10_000) == 170_000  # the face cap
    assert T._faces_bound(config_for("tiny"), 100, 100, 100) == 100 + 100 * 12  # full depth 2
    assert T._faces_bound(config_for("tiny", max_depth=0), 100, 100, 100) == 100

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9, 2**20))
    out = tmp_path / "run"
    rc = train_main(["--data", tiny_dataset, "--out", str(out), "--preset", "tiny", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and f"error: {out}: the disk has 1 MB free for this run, which needs about" in err
    assert "free some space or train into another --out folder" in err
    assert not out.exists()  # nothing written: the run folder it made is gone again
    # --overwrite refused for room leaves the run it would replace as it was.
    kept = tmp_path / "kept"
    shutil.copytree(tiny_run, kept)
    before = {p.name: p.read_bytes() for p in kept.iterdir() if p.is_file()}
    args = ["--data", tiny_dataset, "--out", str(kept), "--preset", "tiny", "--no-progress", "--overwrite"]
    assert train_main(args) == 2 and "needs about" in capsys.readouterr().err
    after = {p.name: p.read_bytes() for p in kept.iterdir() if p.is_file()}
    assert {k: v for k, v in after.items() if k != ".train.lock"} == {
        k: v for k, v in before.items() if k != ".train.lock"
    }
    # A resume replaces its checkpoint and avatar: their space is the run's.
    run = tmp_path / "resumed"
    shutil.copytree(tiny_run, run)
    need = T.run_bytes(T._faces_bound(config_for("tiny"), *_roots_template_faces(run)), width)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9, need - sum(held.values()) + 1))
    args = ["--data", tiny_dataset, "--out", str(run), "--preset", "tiny", "--no-progress", "--resume"]
    assert train_main(args) == 0, capsys.readouterr().err


def _roots_template_faces(run):
    ckpt = np.load(os.path.join(run, "checkpoint.npz"))
    template = len(ckpt["forest_template_faces"])
    roots = template + len(ckpt["forest_coarse_faces"])
    return roots, template, len(ckpt["forest_parent"])


def test_ctrl_c_inside_a_compiled_kernel_stops_with_one_line(tiny_dataset, tmp_path, capsys, monkeypatch):
    """Ctrl-C while numba ran a kernel reached train.py (and Blender's Train job) as a SystemError
    with the KeyboardInterrupt as its context: a traceback instead of the "stopped (Ctrl-C)" line."""
    import runpy

    from progressive_avatars.core.train import jobs
    from progressive_avatars.core.train.trainer import raised_from

    def wrapped(*a, **k):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("CPUDispatcher(<function raster_forward>) returned a result with an exception set")

    try:
        wrapped()
    except SystemError as exc:
        assert raised_from(exc, KeyboardInterrupt) and not raised_from(exc, FloatingPointError)
    saved = list(sys.path)
    train_main = runpy.run_path(os.path.join(ROOT, "scripts", "train.py"), run_name="train_script")["main"]
    sys.path[:] = saved
    monkeypatch.setattr(Trainer, "run", wrapped)
    args = ["--data", tiny_dataset, "--preset", "tiny"]
    assert train_main(args + ["--out", str(tmp_path / "a"), "--no-progress"]) == 130
    err = capsys.readouterr().err
    assert "stopped (Ctrl-C) at iteration 0; no checkpoint was written yet" in err and "Traceback" not in err
    assert jobs.main(["train", *args, "--out", str(tmp_path / "b")]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "error: stopped; training stopped, no checkpoint was written yet"
    )
    # Other errors still surface as they are.
    monkeypatch.setattr(Trainer, "run", lambda *a, **k: (_ for _ in ()).throw(SystemError("a real bug")))
    with pytest.raises(SystemError, match="a real bug"):
        jobs.main(["train", *args, "--out", str(tmp_path / "c")])


def test_blender_train_job_exports_under_the_run_lock(tiny_dataset, tiny_run, tmp_path, monkeypatch):
    """The Train job let go of RUN/.train.lock before its export: an Overwrite Run started then
    emptied the folder under it and was left with this avatar's stream."""
    import shutil

    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.train import jobs
    from progressive_avatars.core.train.distributed import run_lock

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    for name in ("avatar.pavs", ".train.lock"):
        if (run / name).exists():
            os.remove(run / name)
    seen = []
    real = runs.run_importance

    def importance(*a, **k):
        try:
            with run_lock(str(run)):
                seen.append("free")
        except RuntimeError as exc:
            seen.append(str(exc))
        return real(*a, **k)

    monkeypatch.setattr(runs, "run_importance", importance)
    assert jobs.main(["train", "--data", tiny_dataset, "--out", str(run), "--preset", "tiny", "--resume"]) == 0
    assert len(seen) == 1 and "is being trained by another process" in seen[0]
    assert (run / "avatar.pavs").exists()


def test_infinite_gradients_are_reported_like_nan_ones():
    """nonfinite_gradients flags +inf and -inf as well as NaN, on the compiled path (CPU,
    contiguous, one dtype) and on the torch path (here: mixed dtypes)."""
    p = {"a": torch.zeros(4000, 3, requires_grad=True), "b": torch.zeros(4000, requires_grad=True)}
    opt = Adam(p, {"a": 0.1, "b": 0.1})
    assert opt._compiled(p)
    for bad in (float("inf"), float("-inf")):
        p["a"].grad, p["b"].grad = torch.ones(4000, 3), torch.ones(4000)
        p["a"].grad[1234, 2] = bad
        assert opt.nonfinite_gradients(p) == ["a"]
    q = {"a": torch.zeros(5, 3, dtype=torch.float64, requires_grad=True), "b": torch.zeros(5, requires_grad=True)}
    ref = Adam(q, {"a": 0.1, "b": 0.1})
    assert not ref._compiled(q)
    q["a"].grad, q["b"].grad = torch.ones(5, 3, dtype=torch.float64), torch.ones(5)
    q["b"].grad[4] = float("inf")
    assert ref.nonfinite_gradients(q) == ["b"]


def test_torch_step_reports_an_overflowed_second_moment_with_finite_parameters():
    """A float32 gradient of 1e30 squares to inf: v = (1 - 0.999)·inf = inf, and the step
    m̂ / (sqrt(v̂) + eps) = finite / inf = 0 leaves the parameter finite (and frozen). The step
    must still name the parameter (its moment is no longer finite), on the torch path as on
    the compiled one; a proper first step (steps = 1) so nothing else goes NaN."""
    for compiled in (True, False):
        p = torch.zeros(4, 3, requires_grad=True)
        opt = Adam({"x": p}, {"x": 0.1})
        p.grad = torch.full((4, 3), 0.5)
        p.grad[2, 1] = 1e30
        if compiled:
            bad = opt.step({"x": p})
        else:
            opt.steps += 1
            bad = opt._torch_step({"x": p}, None)
        assert bad == ["x"]
        assert torch.isfinite(p).all() and float(p.detach()[2, 1]) == 0.0
        assert torch.isinf(opt.v["x"][2, 1])
        # the other values took the first Adam step: exactly -lr · sign(g) (bias-corrected)
        np.testing.assert_allclose(p.detach().numpy()[0], -0.1, rtol=1e-5)


def test_photometric_torch_path_weights_l1_and_ssim():
    """The composition taken off the fused kernels (here: float64 images) is
    (1 - λ)·L1 + λ·(1 - SSIM) (DESIGN.md), L1 the mean absolute difference, SSIM the 11x11
    window of core.train.metrics (numpy, float64)."""
    rng = np.random.default_rng(3)
    b = rng.uniform(0, 1, (16, 14, 3))
    a = 0.5 * b + 0.5 * rng.uniform(0, 1, b.shape)
    l1 = np.abs(a - b).mean()
    s = metrics.ssim(a, b)
    for lam in (0.2, 0.5):
        got = float(losses.photometric(torch.tensor(a), torch.tensor(b), lam))
        assert got == pytest.approx((1 - lam) * l1 + lam * (1 - s), rel=1e-9, abs=1e-12)
    # float32 (fused) and float64 (torch) agree
    fused = float(losses.photometric(torch.tensor(a, dtype=torch.float32), torch.tensor(b, dtype=torch.float32)))
    assert fused == pytest.approx(0.8 * l1 + 0.2 * (1 - s), abs=2e-6)


def test_photometric_passes_a_gradient_to_a_target_that_requires_one():
    """A target that requires a gradient does not take the fused kernels (they give the target
    none): with λ = 0 the loss is mean |a - b|, so d/db = -sign(a - b) / n (by hand)."""
    rng = np.random.default_rng(4)
    a = torch.tensor(rng.uniform(0, 1, (12, 13, 3)), dtype=torch.float32)
    b = torch.tensor(rng.uniform(0, 1, (12, 13, 3)), dtype=torch.float32, requires_grad=True)
    losses.photometric(a, b, 0.0).backward()
    assert b.grad is not None
    expected = -np.sign(a.numpy() - b.detach().numpy()) / a.numel()
    np.testing.assert_allclose(b.grad.numpy(), expected, rtol=1e-6)


def test_photometric_refuses_images_of_different_sizes():
    """An image and a target of different sizes do not meet in the fused kernels (which index
    the target by the image's rows unchecked): torch's size check refuses them."""
    a = torch.rand(12, 12, 3)
    with pytest.raises(RuntimeError):
        losses.photometric(a, torch.rand(13, 12, 3))
    with pytest.raises(RuntimeError):
        losses.photometric(a, torch.rand(12, 14, 3))


def test_a_first_iteration_that_compiles_says_so_in_the_progress_line(tiny_dataset, tmp_path, monkeypatch, capsys):
    """On a machine's first run of a version the first iteration compiles the kernels for
    minutes while the bar (the line the Blender add-on shows) sat at 0 % without a word."""
    from progressive_avatars.core.train import trainer as trainer_module

    probe = "from progressive_avatars.core.train.trainer import kernels_uncached as k; print(k())"
    empty = tmp_path / "numba_cache"
    empty.mkdir()
    cold = subprocess.run(
        [sys.executable, "-c", probe], env={**os.environ, "NUMBA_CACHE_DIR": str(empty)}, capture_output=True, text=True
    )
    assert cold.stdout.split() == ["True"], cold.stderr
    assert not [n for _, _, names in os.walk(empty) for n in names]  # asking compiles nothing
    asked = trainer_module.kernels_uncached
    cfg = config_for("tiny", iterations=2, eval_every=1000)
    for uncached in (True, False):
        monkeypatch.setattr(trainer_module, "kernels_uncached", lambda: uncached)
        Trainer(tiny_dataset, str(tmp_path / f"run{uncached}"), cfg).run(progress=True)
        err = capsys.readouterr().err
        assert ("compiling the kernels" in err) is uncached, err
        assert err.rstrip().splitlines()[-1].lstrip("\r").startswith("train: 100%"), err  # said only while compiling
    # This process has trained (compiled, or loaded from numba's cache, every kernel asked about):
    # cached now, whatever the cache held when the test began (an empty one after a kernel edit,
    # a fresh NUMBA_CACHE_DIR).
    assert asked() is False
