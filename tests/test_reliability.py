"""Careless-user and numerical faults around training, datasets, export and the evaluators:
each one is refused or handled with a clear message before work is wasted."""

import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch

from progressive_avatars.core.io import atomic
from progressive_avatars.core.avatar.avatar import LOG_SCALE_MAX, Avatar
from progressive_avatars.core.avatar.binding import quat_normalize
from progressive_avatars.core.train.binding_torch import quat_normalize as quat_normalize_torch
from progressive_avatars.core.io.dataset import Dataset
from progressive_avatars.core.io.sequences import DataError
from progressive_avatars.core.train.trainer import Trainer, config_for
from progressive_avatars.core.io.validate import dataset_problems
from tests.helpers import random_forest, sphere_mesh

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def data_copy(tiny_dataset, tmp_path):
    dst = tmp_path / "data"
    shutil.copytree(tiny_dataset, dst)
    return dst


def _edit_json(path, fn):
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


# -- datasets ---------------------------------------------------------------------------
def test_clean_dataset_validates(tiny_dataset):
    for split in ("train", "val"):
        assert dataset_problems(Dataset(tiny_dataset, split), progress=False) == []


def test_every_broken_file_reported_before_training(data_copy, tmp_path):
    from PIL import Image

    tj = data_copy / "transforms_train.json"
    frames = json.loads(tj.read_text())["frames"]
    img = [data_copy / f["file_path"] for f in frames]
    # 1. an image of the wrong size, 2. a truncated PNG, 3. a mask of the wrong size
    Image.open(img[0]).resize((13, 20)).save(img[0])
    img[1].write_bytes(img[1].read_bytes()[:200])
    m2 = data_copy / frames[2]["fg_mask_path"]
    Image.open(m2).resize((10, 10)).save(m2)
    # 4. a mesh with the wrong vertex count, 5. NaN vertices, 6. a missing mesh
    meshes = sorted({f["mesh_path"] for f in frames})
    v = np.load(data_copy / meshes[0])["vertices"]
    np.savez(data_copy / meshes[0], vertices=v[:-5])
    v2 = np.load(data_copy / meshes[1])["vertices"].copy()
    v2[7, 1] = np.nan
    np.savez(data_copy / meshes[1], vertices=v2)
    os.remove(data_copy / meshes[2])

    # 7. an all-zero camera matrix, 8. a NaN principal point, 9. a fractional timestep
    def cams(d):
        d["frames"][3]["transform_matrix"] = [[0.0] * 4 for _ in range(4)]
        d["frames"][4]["cx"] = float("nan")
        d["frames"][5]["timestep_index"] = d["frames"][5]["timestep_index"] + 0.5

    _edit_json(tj, cams)
    ds = Dataset(data_copy, "train")  # indexing still works: files are only checked lazily
    problems = dataset_problems(ds, progress=False)
    text = "\n".join(problems)
    for needle in (
        f"{img[0]}: image: size 13x20",
        f"{img[1]}: image: cannot be decoded",
        f"{m2}: mask: size 10x10",
        f"{data_copy / meshes[0]}",
        "NaN",
        f"{data_copy / meshes[2]}: file not found",
        "frames[3]: transform_matrix",
        "frames[4]: principal point cx is nan",
        "frames[5].timestep_index is",
    ):
        assert needle in text, (needle, text)
    assert len(problems) == 9, text
    # The trainer refuses before its first iteration, naming every file in one message.
    with pytest.raises(DataError) as ei:
        Trainer(str(data_copy), str(tmp_path / "run"), config_for("tiny"))
    assert "9 problem(s)" in str(ei.value) and str(img[1]) in str(ei.value)
    assert not (tmp_path / "run" / "checkpoint.npz").exists()


def test_cameras_that_see_none_of_the_mesh_and_a_template_without_area_are_refused(data_copy, tmp_path):
    """Cameras written in OpenCV axes (y, z flipped), or looking away, see nothing of the head:
    training ran to the end (exit 0) with the untrained avatar; a canonical mesh collapsed to
    a point trained likewise, its coarse levels silently dropped."""
    tj = data_copy / "transforms_train.json"
    frames = json.loads(tj.read_text())["frames"]

    def opencv(d, which):
        for i in which:
            m = np.array(d["frames"][i]["transform_matrix"], float)
            m[:3, 1:3] *= -1  # the OpenCV camera axes: y down, looking down +z
            d["frames"][i]["transform_matrix"] = m.tolist()

    _edit_json(tj, lambda d: opencv(d, [0]))
    problems = dataset_problems(Dataset(data_copy, "train"), progress=False)
    assert len(problems) == 1 and "1 frame(s) whose camera sees none of its timestep's mesh" in problems[0]
    assert "frames[0] (00000_00.png); a camera looking away" in problems[0]
    _edit_json(tj, lambda d: opencv(d, range(1, len(frames))))
    with pytest.raises(
        DataError, match=f"(?s)1 problem.*{len(frames)} frame\\(s\\) whose camera sees none.* and 8 more"
    ):
        Trainer(str(data_copy), str(tmp_path / "run"), config_for("tiny"))
    assert not (tmp_path / "run" / "checkpoint.npz").exists()
    _edit_json(tj, lambda d: opencv(d, range(len(frames))))  # back as they were
    assert dataset_problems(Dataset(data_copy, "train"), progress=False) == []
    canon = np.load(data_copy / "canonical_mesh.npz")
    np.savez(data_copy / "canonical_mesh.npz", vertices=np.zeros_like(canon["vertices"]), faces=canon["faces"])
    problems = dataset_problems(Dataset(data_copy, "train"), progress=False)
    assert problems[0].endswith("the canonical mesh has no area (its vertices coincide or lie on one line)")


def test_16bit_png_reads_as_its_values_not_white(data_copy):
    from PIL import Image

    frames = json.loads((data_copy / "transforms_train.json").read_text())["frames"]
    ds8 = Dataset(data_copy, "train", cache_images=0)
    img8, mask8 = ds8.images(0)
    grey = np.asarray(Image.open(data_copy / frames[0]["file_path"]).convert("L"), np.float64)
    Image.fromarray(np.round(grey * 257).astype(np.uint16)).save(data_copy / frames[0]["file_path"])  # 16-bit
    m = np.asarray(Image.open(data_copy / frames[0]["fg_mask_path"]).convert("L"), np.float64)
    Image.fromarray(np.round(m * 257).astype(np.uint16)).save(data_copy / frames[0]["fg_mask_path"])
    assert Image.open(data_copy / frames[0]["file_path"]).mode.startswith("I")
    ds16 = Dataset(data_copy, "train", cache_images=0)
    assert dataset_problems(ds16, progress=False) == []
    img16, mask16 = ds16.images(0)
    np.testing.assert_allclose(img16[..., 0], grey / 255.0, atol=1 / 255)  # was 1.0 everywhere
    np.testing.assert_allclose(mask16, mask8, atol=1 / 255)
    assert img16.mean() < 0.99


def test_broken_val_split_is_an_error_not_dropped(data_copy, tmp_path):
    (data_copy / "transforms_val.json").write_text("{ not json")
    with pytest.raises(DataError, match=r"transforms_val\.json: invalid JSON"):
        Trainer(str(data_copy), str(tmp_path / "r"), config_for("tiny"))
    os.remove(data_copy / "transforms_val.json")  # no val split at all is fine
    assert Trainer(str(data_copy), str(tmp_path / "r2"), config_for("tiny")).val is None


# -- training ---------------------------------------------------------------------------
def test_resume_with_other_data_refused(tiny_dataset, tmp_path, capsys):
    """--resume continues on the training split the run started on, by content: a split edited
    under the same folder (other frames, cameras, timesteps) was resumed silently, and a
    byte-identical copy of the dataset elsewhere was refused."""
    from progressive_avatars.core.synthetic.dataset import make_dataset

    cfg = config_for("tiny", iterations=3, checkpoint_every=2, eval_every=1000, log_every=1)
    run = tmp_path / "run"
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    Trainer(str(data), str(run), cfg).run(progress=False)
    other = tmp_path / "other"
    make_dataset(str(other), resolution=24, cameras=3, sequences=3, frames=1, seed=5, progress=False)
    with pytest.raises(
        ValueError,
        match=rf"transforms_train\.json is not the training split this run was started on \(trained on {data}\)",
    ):
        Trainer(str(other), str(run), cfg, resume=True)
    # The same folder, its split edited (a camera dropped): refused before any work.
    saved = (data / "transforms_train.json").read_bytes()
    _edit_json(
        data / "transforms_train.json", lambda d: d.update(frames=[f for f in d["frames"] if f["camera_index"] != 1])
    )
    with pytest.raises(ValueError, match=r"is not the training split this run was started on: its frames, cameras"):
        Trainer(str(data), str(run), cfg, resume=True)
    # Re-saved by another tool (indentation, key order): the same split, it resumes.
    (data / "transforms_train.json").write_bytes(saved)
    _edit_json(data / "transforms_train.json", lambda d: None)
    assert (data / "transforms_train.json").read_bytes() != saved
    Trainer(str(data), str(run), cfg, resume=True)
    (data / "transforms_train.json").write_bytes(saved)
    # A copy of the dataset elsewhere resumes, with a note.
    copy = tmp_path / "copy"
    shutil.copytree(data, copy)
    capsys.readouterr()
    Trainer(str(copy), str(run), cfg, resume=True)
    assert f"resuming on {copy}, a copy of {data} (the same training split)" in capsys.readouterr().err
    # Same split, contents replaced by another mesh: the checkpoint's template is checked too.
    cfgj = run / "config.json"
    other = copy
    os.remove(other / "canonical_mesh.npz")
    verts, faces = sphere_mesh(4, 5)
    np.savez(other / "canonical_mesh.npz", vertices=verts, faces=faces)
    with pytest.raises(ValueError, match=r"checkpoint's template mesh \(\d+ faces\) is not"):
        Trainer(str(other), str(run), cfg, resume=True, check_data=False)
    # config.json is written atomically: no temporary left, valid JSON.
    assert json.loads(cfgj.read_text())["data"] == str(other)
    assert [n for n in os.listdir(run) if n.endswith(".tmp")] == []


def test_torn_metrics_line_and_stale_temps_do_not_block_resume(tiny_dataset, tmp_path):
    cfg = config_for("tiny", iterations=6, checkpoint_every=4, eval_every=1000, log_every=1)
    run = tmp_path / "run"
    tr = Trainer(tiny_dataset, str(run), cfg)
    tr.run(progress=False, stop_after=4)
    with open(run / "metrics.jsonl", "a") as fh:
        fh.write('{"iteration": 5, "seconds": 1.2, "lo')  # killed mid-write
    # A checkpoint write killed mid-way left its pid-named temporary (pid of a dead process).
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = run / f"checkpoint.npz.{dead.pid}-3.tmp"
    older = run / f"checkpoint.npz.{dead.pid}.tmp"  # the name before per-write numbers
    stale.write_bytes(b"partial")
    older.write_bytes(b"partial")
    resumed = Trainer(tiny_dataset, str(run), cfg, resume=True)
    assert resumed.iteration == 4
    resumed.run(progress=False)
    rows = [json.loads(line)["iteration"] for line in open(run / "metrics.jsonl")]
    assert rows == list(range(1, 7))
    assert not stale.exists() and not older.exists()
    live = run / f"checkpoint.npz.{os.getpid()}-0.tmp"  # a live writer's temporary is never touched
    live.write_bytes(b"x")
    atomic.clean_stale_temps(run / "checkpoint.npz")
    assert live.exists()


def test_a_refused_resume_changes_nothing_and_an_asked_coarse_mode_must_match(tiny_dataset, tmp_path, capsys):
    """A resume refused for its settings left the run folder as it was, except that the log
    lines past the checkpoint were already dropped; a --coarse-mode other than the run's was
    silently replaced by the run's (only a mode not asked for takes the run's); --resume into
    a folder without a checkpoint says that it starts a new run."""
    from dataclasses import replace

    cfg = config_for("tiny", iterations=6, checkpoint_every=4, eval_every=1000, log_every=1)
    run = tmp_path / "run"
    Trainer(tiny_dataset, str(run), cfg, check_data=False).run(progress=False, stop_after=4)
    with open(run / "metrics.jsonl", "a") as fh:  # logged after the checkpoint, then killed
        fh.write(json.dumps({"iteration": 5, "seconds": 1.0, "loss": 0.5}) + "\n")
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and p.name != ".train.lock"}
    cumulative = replace(cfg, coarse_stand_ins=False, coarse_backdrop=False)
    for other, kw, why in (
        (replace(cfg, seed=5), {}, "seed 0 -> 5"),
        (cumulative, dict(coarse_mode_given=True), "coarse_backdrop True -> False"),
    ):
        with pytest.raises(ValueError, match=why):
            Trainer(tiny_dataset, str(run), other, resume=True, check_data=False, **kw)
        after = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and p.name != ".train.lock"}
        assert after == before
    resumed = Trainer(tiny_dataset, str(run), cumulative, resume=True, check_data=False)  # mode not asked for
    assert (resumed.cfg.coarse_stand_ins, resumed.cfg.coarse_backdrop) == (True, True)
    assert [json.loads(ln)["iteration"] for ln in open(run / "metrics.jsonl")] == [1, 2, 3, 4]
    capsys.readouterr()
    Trainer(tiny_dataset, str(tmp_path / "typo"), cfg, resume=True, check_data=False)
    assert "typo holds no checkpoint.npz: --resume starts a new run" in capsys.readouterr().err


def test_an_overflowing_optimiser_moment_stops_training_and_absurd_loss_weights_are_refused(tiny_dataset, tmp_path):
    """A gradient above ~1e20 (a loss weight of 1e38 was accepted) overflowed Adam's second
    moment to inf: every later step of those values was 0 and training went on frozen to exit 0
    (only the parameters were checked); a weight of 1e-45 underflowed the loss to 0 alike."""
    from progressive_avatars.core.train.adam import Adam

    for compiled in (True, False):
        p = torch.zeros(4, 3, requires_grad=True)
        opt = Adam({"x": p}, {"x": 0.1})
        p.grad = torch.full((4, 3), 0.5)
        p.grad[2, 1] = 1e30  # squared: inf in float32
        bad = opt.step({"x": p}) if compiled else opt._torch_step({"x": p}, None)
        assert bad == ["x"] and not torch.isfinite(opt.v["x"]).all()
    tr = Trainer(tiny_dataset, str(tmp_path / "r"), config_for("tiny", eval_every=1000), check_data=False)
    tr.opt.v["f_dc"][5, 0] = float("inf")
    with pytest.raises(FloatingPointError, match="second moment of f_dc overflowed.*training stopped"):
        tr.step()
    for option, value in (("level_weights", (1e38,)), ("level_weights", (1e-45, 1.0)), ("coarse_weight", 1e7)):
        with pytest.raises(ValueError, match=r"must be 0 or in \[1e-06, 1e\+06\]"):
            config_for("tiny", **{option: value})
    with pytest.raises(ValueError, match="prefix cut weight"):
        config_for("tiny", prefix_cut_weight=float("inf"))
    config_for("tiny", level_weights=(0.0, 1e-6, 1e6), coarse_weight=0.0)


def test_a_failed_npz_write_keeps_the_old_file_names_it_and_closes_the_archive(tmp_path, monkeypatch):
    """np.savez left its archive open when a write failed (a full disk): its finaliser later
    failed on the closed file ("Exception ignored ... seek of closed file"), and the OSError
    named no file (the write went through a handle)."""
    import errno
    import gc

    path = tmp_path / "a.npz"
    atomic.atomic_savez(path, x=np.arange(3))
    before = path.read_bytes()
    real, calls = np.lib.format.write_array, []

    def full(fh, array, **kw):
        calls.append(1)
        if len(calls) == 2:
            fh.write(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fh, array, **kw)

    monkeypatch.setattr(np.lib.format, "write_array", full)
    stray = []
    monkeypatch.setattr(sys, "unraisablehook", stray.append)
    with pytest.raises(OSError) as err:
        atomic.atomic_savez(path, x=np.arange(4), y=np.arange(5))
    assert err.value.filename == str(path)
    del err
    gc.collect()
    assert stray == [] and path.read_bytes() == before and os.listdir(tmp_path) == ["a.npz"]
    # As np.savez writes it (not savez_compressed): members stored, read back as written.
    import zipfile

    with zipfile.ZipFile(path) as z:
        assert [(i.filename, i.compress_type) for i in z.infolist()] == [("x.npy", zipfile.ZIP_STORED)]
    with np.load(path) as z:
        assert z["x"].tolist() == [0, 1, 2]
    with pytest.raises(ValueError, match="allow_pickle"):  # object arrays refused, as the readers refuse them
        atomic.atomic_savez(tmp_path / "b.npz", x=np.array([{}, 1], dtype=object))


def test_scale_overflow_stops_training_with_the_trainers_message(tiny_dataset, tmp_path):
    tr = Trainer(tiny_dataset, str(tmp_path / "r"), config_for("tiny", eval_every=1000), check_data=False)
    with torch.no_grad():
        tr.model.params["d_log_scale"][3, 0] = 95.0  # exp overflows float32
    with pytest.raises(FloatingPointError, match="Gaussian scales became NaN/inf; training stopped"):
        tr.step()


@pytest.mark.slow  # a training run or a subprocess
def test_train_script_reports_disk_full(tiny_dataset, tmp_path):
    code = (
        "import errno, runpy, sys;"
        "import progressive_avatars.core.io.atomic as A;"
        "real = A.atomic_savez\n"
        "def full(path, **a):\n"
        "    raise OSError(errno.ENOSPC, 'No space left on device', str(path))\n"
        "A.atomic_savez = full\n"
        "import progressive_avatars.core.train as T; T.atomic_savez = full\n"
        "sys.argv = [%r, '--data', %r, '--out', %r, '--preset', 'tiny', '--iterations', '2', '--no-progress']\n"
        "runpy.run_path(sys.argv[0], run_name='__main__')"
    ) % (os.path.join(ROOT, "scripts", "train.py"), tiny_dataset, str(tmp_path / "r"))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 3, out.stderr
    # The first checkpoint is the one that failed: nothing is kept (it used to say "the last checkpoint ... is kept").
    assert "error: disk full: No space left on device" in out.stderr
    assert "training stopped, no checkpoint was written yet" in out.stderr.strip().splitlines()[-1]
    assert "Traceback" not in out.stderr


# -- export -----------------------------------------------------------------------------
@pytest.mark.parametrize("budget", ["150", "-1", "nan"])  # 0 writes an empty PLY (tests/test_pipeline.py)
def test_export_budget_refused_clearly(tiny_run, tmp_path, budget):
    out = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "scripts", "export.py"),
            "--run",
            tiny_run,
            "--ply",
            str(tmp_path / "x.ply"),
            "--budget",
            budget,
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 2 and "--budget" in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_importance_cache_keyed_on_max_views(tiny_run, tiny_dataset, tmp_path, monkeypatch):
    from progressive_avatars.core.render import importance
    from progressive_avatars.core.io import dataset as runs_dataset
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.dataset import Dataset as RealDataset

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    for n in [f"importance{k}.{e}" for k in ("", "_alpha", "_whole") for e in ("npz", "npy", "json")]:
        if (run / n).exists():
            os.remove(run / n)
    av = runs.load_run_avatar(str(run))
    shutil.copy2(run / "avatar.npz", tmp_path / "run_first_avatar.npz")
    calls = []
    real = importance.face_importance
    monkeypatch.setattr(importance, "face_importance", lambda *a, **k: calls.append(k["max_views"]) or real(*a, **k))
    w2 = runs.run_importance(str(run), av, tiny_dataset, max_views=2, progress=False)
    w2b = runs.run_importance(str(run), av, tiny_dataset, max_views=2, progress=False)
    w_all = runs.run_importance(str(run), av, tiny_dataset, max_views=None, progress=False)
    w2_whole = runs.run_importance(str(run), av, tiny_dataset, max_views=2, progress=False, per_level=False)
    w2_alpha = runs.run_importance(str(run), av, tiny_dataset, max_views=2, progress=False, weighting="alpha")
    w_all_again = runs.run_importance(str(run), av, tiny_dataset, max_views=None, progress=False)
    assert calls == [2, None, 2, 2]  # cached for the same views and kind, recomputed for others
    assert (run / "importance_alpha.npz").exists() and not np.array_equal(w2, w2_alpha)
    np.testing.assert_array_equal(w2, w2b)
    assert not np.array_equal(w2, w_all)
    assert not np.array_equal(w2, w2_whole) and (run / "importance_whole.npz").exists()
    np.testing.assert_array_equal(w_all_again, w_all)  # the whole-avatar kind has its own cache file

    # Another avatar of the same size copied in with an older file time (cp -p, a restore): the
    # cache is keyed on the avatar's contents, not on file times, so it is measured again.
    calls.clear()
    other = tmp_path / "other.npz"
    av2 = runs.load_run_avatar(str(run))
    av2.opacity_logit[:] = av2.opacity_logit[::-1]
    av2.save(str(other))
    old = os.path.getmtime(run / "importance.npz") - 100
    os.utime(other, (old, old))
    shutil.copy2(other, run / "avatar.npz")
    av2 = runs.load_run_avatar(str(run))  # (as every caller: the avatar of the file's bytes)
    w_other = runs.run_importance(str(run), av2, tiny_dataset, max_views=None, progress=False)
    assert calls == [None] and not np.array_equal(w_other, w_all)
    # A training replacing avatar.npz while an evaluation measures the avatar it loaded before: the
    # cache is filed under the loaded avatar's hash, not the new file's (whose next reader would
    # get the old avatar's ranking).
    calls.clear()
    shutil.copy2(tmp_path / "run_first_avatar.npz", run / "avatar.npz")
    w_race = runs.run_importance(str(run), av2, tiny_dataset, max_views=2, progress=False)
    av1 = runs.load_run_avatar(str(run))
    w_first = runs.run_importance(str(run), av1, tiny_dataset, max_views=2, progress=False)
    assert calls == [2, 2] and not np.array_equal(w_race, w_first)
    np.testing.assert_array_equal(w_first, w2)
    # The training split edited in place (frames dropped): measured again as well.
    # A copy of the dataset elsewhere (the same training split file, its images possibly not):
    # keyed on the data folder too, so measured on the copy (the cache holds av1's 2-view one).
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    runs.run_importance(str(run), av1, str(data), max_views=2, progress=False)
    assert calls == [2, 2, 2]
    runs.run_importance(str(run), av2, str(data), max_views=None, progress=False)
    calls.clear()
    meta = json.loads((data / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"][: len(meta["frames"]) // 2]
    (data / "transforms_train.json").write_text(json.dumps(meta))
    runs.run_importance(str(run), av2, str(data), max_views=None, progress=False)
    assert calls == [None]
    # A FLAME model given on the command line is the one the importance pass reads with (and keys)
    seen = []
    monkeypatch.setattr(runs_dataset, "Dataset", lambda *a, **k: seen.append(k["flame_model"]) or RealDataset(*a, **k))
    runs.run_importance(str(run), av2, str(data), max_views=None, progress=False, flame_model="given.pkl")
    assert seen == ["given.pkl"] and calls == [None, None]
    with np.load(run / "importance.npz") as z:
        assert json.loads(str(z["key"]))["flame_model"] == os.path.abspath("given.pkl")


# -- numerical --------------------------------------------------------------------------
def test_log_scale_that_overflows_is_refused():
    verts, faces = sphere_mesh(3, 4)
    av = Avatar.initial(random_forest(faces, np.random.default_rng(0), depth=1))
    bad = av.d_log_scale.copy()
    bad[2, 1] = 88.8
    with pytest.raises(ValueError, match=r"d_log_scale of face 2 is 88.8.*infinite"):
        Avatar(av.forest, av.d_mu, bad, av.d_rot, av.opacity_logit, av.f_dc)
    bad[2, 1] = LOG_SCALE_MAX - 1
    g = Avatar(av.forest, av.d_mu, bad, av.d_rot, av.opacity_logit, av.f_dc).gaussians(verts)
    assert np.all(np.isfinite(g["scales"]))


@pytest.mark.parametrize("norm", [1e-200, 1e-30, 1.0, 1e30, 1e154, 1e300])
def test_quaternions_of_extreme_norm_normalise_to_their_rotation(norm):
    q = np.array([[0.5, -0.5, 0.5, 0.5], [0.0, 0.6, 0.0, 0.8]])
    np.testing.assert_allclose(quat_normalize(q * norm), q, atol=1e-12)
    if 1e-30 <= norm <= 1e30:
        t = quat_normalize_torch(torch.tensor(q * norm, dtype=torch.float32))
        np.testing.assert_allclose(t.numpy(), q, atol=1e-6)
    assert np.array_equal(quat_normalize(np.zeros((1, 4))), [[1.0, 0, 0, 0]])  # only exact zero: identity


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_zero_quaternion_stays_zero_with_a_finite_gradient(dtype):
    """The torch path's documented promise: an exactly zero quaternion stays zero (the identity
    rotation downstream) and its gradient is finite (it was inf: 1/tiny times 1/1e-12)."""
    q = torch.zeros(2, 4, dtype=dtype, requires_grad=True)
    u = quat_normalize_torch(q)
    (u * torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=dtype)).sum().backward()
    assert torch.equal(u.detach(), torch.zeros(2, 4, dtype=dtype))
    # At zero u = q / 1e-12 (the norm's floor): the gradient is the weights over 1e-12.
    np.testing.assert_allclose(q.grad.numpy(), np.tile([1e12, 2e12, 3e12, 4e12], (2, 1)), rtol=1e-6)


@pytest.mark.parametrize("unit", [1e12, 1e-12])
def test_numpy_evaluator_matches_torch_at_absurd_unit_scales(unit):
    """The numpy evaluator pre-scales root edges and normals before squaring, like the torch
    path: the same avatar on a mesh in absurd units gives the same rotations, and means and
    scales that scale with the unit (before: quats off by up to 1.99 at 1e12 and 1e-12)."""
    from progressive_avatars.core.train.binding_torch import TorchForest, compose

    rng = np.random.default_rng(0)
    verts, faces = sphere_mesh(8, 10)
    forest = random_forest(faces, rng, depth=2, frac=0.5)
    N = forest.num_faces
    av = Avatar(
        forest,
        rng.normal(0, 0.3, (N, 3)),
        rng.normal(-1, 0.5, (N, 3)),
        rng.normal(size=(N, 4)),
        rng.normal(size=N),
        rng.normal(size=(N, 3)),
    )
    m1, q1, s1 = [x.copy() for x in av.evaluator()(verts)]
    mk, qk, sk = [x.copy() for x in av.evaluator()(verts * unit)]
    np.testing.assert_allclose(qk, q1, atol=2e-5)
    if unit < 1:
        return  # below MIN_SCALE (1e-10 m) face scales are clamped by design; rotations still agree
    np.testing.assert_allclose(mk / unit, m1, atol=1e-5 * np.abs(m1).max())
    np.testing.assert_allclose(sk / unit, s1, rtol=1e-4)
    tf = TorchForest(forest)
    v = torch.tensor(verts * unit, dtype=torch.float32)
    t, r, s = tf.evaluate(v, tf.weights(torch.tensor(forest.split_logits)))
    mt, qt, st = compose(t, r, s, *(torch.tensor(getattr(av, n)) for n in ("d_mu", "d_log_scale", "d_rot")))
    np.testing.assert_allclose(np.abs(np.sum(qt.numpy() * qk, axis=1)), 1.0, atol=1e-4)  # same rotation (±q)


# -- evaluation report ------------------------------------------------------------------
def _report_opts(run, out, **kw):
    from progressive_avatars.core.evaluate.report import ReportOptions

    small = dict(views=2, curve_points=2, curve_views=1, budgets=(50, 100), strips=(50, 100), progress=False)
    return ReportOptions(run=str(run), out=str(out), **{**small, **kw})


@pytest.fixture
def run_copy(tiny_run, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(tiny_run, dst)
    return dst


def test_read_log_skips_torn_last_line_and_names_a_bad_line(tmp_path):
    from progressive_avatars.core.evaluate.plots import read_log

    log = tmp_path / "metrics.jsonl"
    good = '{"iteration": 1, "seconds": 0.5}\n\n{"iteration": 2, "seconds": 1.0}\n'
    log.write_text(good + '{"iteration": 3, "seconds": 1.2, "lo')  # a writer killed mid-line
    assert [r["iteration"] for r in read_log(log)] == [1, 2]
    log.write_bytes(good.encode() + '{"note": "caf\u00e9'.encode()[:-1])  # cut inside a character
    assert len(read_log(log)) == 2
    log.write_text('{"iteration": 1}\n{"iteration": 2, "sec\n{"iteration": 3}\n')
    with pytest.raises(ValueError, match=r"metrics\.jsonl: line 2 is not valid JSON"):
        read_log(log)
    log.write_text('{"iteration": 1}\n[1, 2]\n')
    with pytest.raises(ValueError, match=r"metrics\.jsonl: line 2 is not a JSON object"):
        read_log(log)


@pytest.mark.slow  # evaluations of the tiny run
def test_evaluate_torn_metrics_line_bad_log_fails_fast_and_scratch_always_removed(
    run_copy, tmp_path, own_tmp, monkeypatch
):
    from progressive_avatars.core.evaluate import plots
    from progressive_avatars.core.evaluate.report import build_report

    log = run_copy / "metrics.jsonl"
    lines = log.read_text().splitlines(keepends=True)
    with open(log, "a") as fh:
        fh.write('{"iteration": 61, "seconds": 1.2, "lo')  # the trainer was killed mid-write
    rep = build_report(_report_opts(run_copy, tmp_path / "ok"))
    assert rep["training"]["this run"]["iterations"] == json.loads(lines[-1])["iteration"]
    assert json.loads((tmp_path / "ok" / "report.json").read_text())["training"] == rep["training"]
    assert os.listdir(own_tmp) == []
    # A bad line before the end is an error naming the file and line, before any rendering.
    log.write_text(lines[0] + "{oops\n" + "".join(lines[1:]))
    with pytest.raises(ValueError, match=r"metrics\.jsonl: line 2 is not valid JSON"):
        build_report(_report_opts(run_copy, tmp_path / "bad_log"))
    assert os.listdir(tmp_path / "bad_log") == [] and os.listdir(own_tmp) == []
    # A failure in the middle of the evaluation still removes the scratch folder.
    log.write_text("".join(lines))

    def broken(*a, **k):
        raise RuntimeError("drawing failed")

    monkeypatch.setattr(plots, "depth_picture", broken)
    with pytest.raises(RuntimeError, match="drawing failed"):
        build_report(_report_opts(run_copy, tmp_path / "crash"))
    assert os.listdir(own_tmp) == []


def test_run_config_errors_name_the_file_and_damaged_importance_cache_is_recomputed(
    run_copy, tiny_dataset, monkeypatch
):
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.render import importance

    cfg = run_copy / "config.json"
    text = cfg.read_text()
    cfg.write_text(text[:30])  # a truncated write
    with pytest.raises(ValueError, match=r"run/config\.json: not valid JSON"):
        runs.run_data_dir(str(run_copy))
    cfg.write_text('{"seed": 0}')
    with pytest.raises(ValueError, match=r'run/config\.json: no "data" entry naming the dataset; pass --data'):
        runs.run_data_dir(str(run_copy))
    cfg.write_text("[1]")
    with pytest.raises(ValueError, match=r"run/config\.json: not a JSON object"):
        runs.run_flame_model(str(run_copy))
    assert runs.run_data_dir(str(run_copy), tiny_dataset) == tiny_dataset  # --data needs no config
    cfg.write_text(text)
    assert runs.run_data_dir(str(run_copy)) == json.loads(text)["data"]

    av = runs.load_run_avatar(str(run_copy))
    calls = []
    real = importance.face_importance
    monkeypatch.setattr(importance, "face_importance", lambda *a, **k: calls.append(1) or real(*a, **k))
    w = runs.run_importance(str(run_copy), av, tiny_dataset, max_views=2, progress=False)
    calls.clear()
    cache = run_copy / "importance.npz"
    good = cache.read_bytes()
    for damaged in (good[:200], b"x\n", b"", b"PK\x03\x04garbage"):
        cache.write_bytes(damaged)  # only its contents are wrong
        np.testing.assert_array_equal(
            runs.run_importance(str(run_copy), av, tiny_dataset, max_views=2, progress=False), w
        )
        with np.load(cache) as z:
            np.testing.assert_array_equal(z["W"], w)  # the cache was rewritten
    with np.load(cache) as z:
        key = z["key"]
    np.savez(cache, W=np.zeros(3), key=key)  # the right key beside an array of another avatar
    np.testing.assert_array_equal(runs.run_importance(str(run_copy), av, tiny_dataset, max_views=2, progress=False), w)
    np.savez(cache, W=np.ones(len(w), np.int64), key=key)  # one per face, but not importances
    np.testing.assert_array_equal(runs.run_importance(str(run_copy), av, tiny_dataset, max_views=2, progress=False), w)
    assert len(calls) == 6


@pytest.mark.slow  # evaluations of the tiny run
def test_evaluate_disk_full_keeps_the_previous_report(run_copy, tmp_path, own_tmp, monkeypatch, capsys):
    import errno
    import runpy

    from progressive_avatars.core.evaluate import plots, report

    monkeypatch.setattr(sys, "path", list(sys.path))  # the script puts its folder on sys.path
    main = runpy.run_path(os.path.join(ROOT, "scripts", "evaluate.py"), run_name="evaluate_script")["main"]
    out = tmp_path / "report"
    args = ["--run", str(run_copy), "--out", str(out), "--views", "2", "--curve-points", "2"]
    args += ["--curve-views", "1", "--budgets", "50,100", "--strips", "50,100", "--no-progress"]
    assert main(args) == 0
    before = {n: (out / n).read_bytes() for n in ("report.json", "report.md", "strip_nvs.png")}
    capsys.readouterr()

    def half_then_disk_full(obj, fh, **kw):
        s = json.dumps(obj, **kw)
        fh.write(s[: len(s) // 2])
        fh.flush()
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(report.json, "dump", half_then_disk_full)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"error: {out / 'report.json'}: No space left on device" in err and "Traceback" not in err
    assert (out / "report.json").read_bytes() == before["report.json"]  # the previous report, whole
    json.loads(before["report.json"])
    assert [n for n in os.listdir(out) if n.endswith(".tmp")] == [] and os.listdir(own_tmp) == []
    monkeypatch.undo()

    # A picture whose write fails keeps the earlier picture (written beside it, then renamed).
    import matplotlib.figure

    def half_png(self, fh, **kw):
        fh.write(b"\x89PNG\r\n")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", half_png)
    fig = plots._plt().figure()
    with pytest.raises(OSError):
        plots._save(fig, str(out / "strip_nvs.png"))
    assert (out / "strip_nvs.png").read_bytes() == before["strip_nvs.png"]
    assert [n for n in os.listdir(out) if n.endswith(".tmp")] == []


@pytest.mark.slow  # an evaluation of the tiny run
def test_evaluate_refuses_a_corrupt_test_image_before_rendering(run_copy, data_copy, tmp_path, own_tmp):
    from progressive_avatars.core.evaluate.report import build_report

    frames = json.loads((data_copy / "transforms_test.json").read_text())["frames"]
    img = data_copy / frames[-1]["file_path"]
    img.write_bytes(img.read_bytes()[:100])
    with pytest.raises(
        DataError, match=rf"(?s)'test' split has 1 problem.*{frames[-1]['file_path']}: image: cannot be"
    ):
        build_report(_report_opts(run_copy, tmp_path / "out", data=str(data_copy)))
    assert os.listdir(tmp_path / "out") == [] and os.listdir(own_tmp) == []


def test_atomic_writes_by_hand(tmp_path, monkeypatch):
    """atomic_open's promises: Ctrl-C inside it leaves the old file and no temporary; the
    temporary is named by the writer's pid and the write's number (two threads writing one path
    at once each have their own) and synced before the rename; another user's
    temporary (its pid cannot be signalled) is kept; an extension PIL cannot write is refused
    before anything is made."""
    from PIL import Image

    p = tmp_path / "a.bin"
    p.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt):
        with atomic.atomic_open(p) as fh:
            fh.write(b"new")
            raise KeyboardInterrupt
    assert os.listdir(tmp_path) == ["a.bin"] and p.read_bytes() == b"old"
    seen, synced = [], []
    real_replace, real_fsync = os.replace, os.fsync
    monkeypatch.setattr(os, "replace", lambda a, b: (seen.append(a), real_replace(a, b)))
    # What fsync finds in the file: the bytes written, flushed out of Python's buffer first
    # (else the sync made durable an empty file and the rename put it in place unsynced).
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(os.fstat(fd).st_size), real_fsync(fd)))
    with atomic.atomic_open(p) as fh:
        fh.write(b"x")
    assert len(seen) == 1 and re.fullmatch(re.escape(f"{p}.{os.getpid()}-") + r"\d+\.tmp", seen[0]), seen
    assert synced == [1] and p.read_bytes() == b"x"
    monkeypatch.undo()
    # Two threads writing one path at once: each its own temporary, and the file is one of theirs.
    inside, errors = threading.Barrier(2), []

    def write(data):
        try:
            with atomic.atomic_open(p) as fh:
                fh.write(data[:4])
                inside.wait(timeout=10)  # both temporaries open now
                fh.write(data[4:])
        except Exception as exc:
            errors.append(exc)

    threads = [threading.Thread(target=write, args=(bytes([k]) * 100_000,)) for k in (1, 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and p.read_bytes() in (bytes([1]) * 100_000, bytes([2]) * 100_000)
    assert os.listdir(tmp_path) == ["a.bin"]
    other = tmp_path / "a.bin.999999.tmp"
    other.write_bytes(b"x")

    def not_mine(pid, sig):
        raise PermissionError

    monkeypatch.setattr(os, "kill", not_mine)
    assert atomic.clean_stale_temps(p) == [] and other.exists()
    monkeypatch.undo()
    assert atomic.image_format("x.psd") is None  # PIL reads PSD, cannot write it
    with pytest.raises(ValueError, match="PIL can write"):
        atomic.atomic_save_image(Image.new("RGB", (2, 2)), tmp_path / "x.psd")
    assert not (tmp_path / "x.psd").exists()
    # An upper-case extension names its format as Image.save(path) reads it.
    assert atomic.image_format("shot.PNG") == "PNG" and atomic.image_format("shot.Jpg") == "JPEG"
    atomic.atomic_save_image(Image.new("RGB", (2, 2), (10, 200, 30)), tmp_path / "shot.BMP")
    with Image.open(tmp_path / "shot.BMP") as im:
        assert im.format == "BMP" and im.getpixel((1, 1)) == (10, 200, 30)


def test_os_error_text_says_what_failed_and_where():
    """One line per failed write: a full disk and an exceeded quota in words, any other error by
    its type; the file the error names, else the place the caller gives."""
    import errno

    text = atomic.os_error_text
    assert text(OSError(errno.ENOSPC, "No space left on device", "out/a.npz")) == (
        "disk full: No space left on device (out/a.npz)"
    )
    assert text(OSError(errno.EDQUOT, "Disk quota exceeded"), "the run folder") == (
        "disk quota exceeded: Disk quota exceeded (the run folder)"
    )
    assert text(OSError(errno.EACCES, "Permission denied", "r/x")) == "PermissionError: Permission denied (r/x)"
    assert text(OSError("odd")) == "OSError: odd (writing the output)"  # no errno, no strerror: the message


def test_stale_temporary_cleanup_takes_only_the_names_atomic_open_gives(tmp_path):
    """clean_stale_temps removes path.<pid>.tmp and path.<pid>-<n>.tmp of a dead pid, nothing
    else: since per-write numbers it split at the first "-" and took any path.<digits>-<text>.tmp
    (a user's "report.json.2024-01-01.tmp", a temporary of a path named "report.json.7-x") for a
    dead writer's."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    p = tmp_path / "report.json"
    ours = [f"report.json.{dead.pid}.tmp", f"report.json.{dead.pid}-12.tmp"]
    others = [
        f"report.json.{dead.pid}-backup.tmp",
        f"report.json.{dead.pid}-2024-01-01.tmp",
        f"report.json.{dead.pid}-.tmp",
        f"report.json.{dead.pid}-x.{dead.pid}-0.tmp",  # a temporary of "report.json.<pid>-x"
        f"report.json_{dead.pid}.tmp",  # another path's ("report.json_<pid>"), not "report.json."
        f"report.json.{dead.pid}.bak",  # not a temporary: ".tmp" ends every one
    ]
    for name in ours + others:
        (tmp_path / name).write_bytes(b"x")
    assert sorted(atomic.clean_stale_temps(p)) == sorted(str(tmp_path / n) for n in ours)
    assert sorted(os.listdir(tmp_path)) == sorted(others)


def test_export_and_evaluation_say_when_the_run_is_being_trained(tiny_run, tmp_path, capsys):
    """During a run's first training, export/evaluate said "train with scripts/train.py first";
    during a --resume they used the older avatar.npz without a word."""
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.train.distributed import run_lock

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    code = (
        "import sys, time\n"
        "from progressive_avatars.core.train.distributed import run_lock\n"
        "with run_lock(sys.argv[1]), run_lock(sys.argv[2]):\n"
        "    print('locked', flush=True)\n"
        "    time.sleep(60)\n"
    )
    p = subprocess.Popen([sys.executable, "-c", code, str(run), str(fresh)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "locked"
        runs.load_run_avatar(str(run))
        assert f"note: {run} is being trained (pid {p.pid} on " in capsys.readouterr().err
        with pytest.raises(
            FileNotFoundError, match=rf"no trained avatar yet: this run is being trained \(pid {p.pid} "
        ):
            runs.load_run_avatar(str(fresh))
    finally:
        p.kill()
        p.wait()
    runs.load_run_avatar(str(run))  # no training: no note; this process's own lock is not another's
    with run_lock(str(run)):
        runs.load_run_avatar(str(run))
    assert "being trained" not in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match="train with scripts/train.py first"):
        runs.load_run_avatar(str(fresh))


def test_training_holder_is_the_lock_held_exclusively_by_another(tmp_path):
    """Who trains a run: the text of RUN/.train.lock while another open file holds it exclusively
    ("another process" when the holder has not written its name yet); another reader asking at
    the same moment (a shared lock) is no training, nor is a finished training's text."""
    import fcntl

    from progressive_avatars.core.io.run import training_holder

    run = tmp_path / "run"
    run.mkdir()
    assert training_holder(str(run)) is None  # never trained here
    lock = run / ".train.lock"
    lock.write_text("pid 1 on elsewhere\n")  # a finished training's
    assert training_holder(str(run)) is None
    with open(lock) as reader:  # an export asking at the same moment
        fcntl.flock(reader.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        assert training_holder(str(run)) is None
    with open(lock) as trainer:
        fcntl.flock(trainer.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert training_holder(str(run)) == "pid 1 on elsewhere"
    lock.write_text("")
    with open(lock) as trainer:  # locked, its name not written yet
        fcntl.flock(trainer.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert training_holder(str(run)) == "another process"


def test_load_run_avatar_reads_again_a_file_replaced_while_it_was_read(run_copy, tmp_path, monkeypatch):
    """A training saving avatar.npz while an export reads it: the avatar is read again, and its
    source_digest is the sha256 of the bytes it was read from (what the importance cache keys
    on); a file replaced during each of three reads is refused, naming it."""
    import hashlib

    from progressive_avatars.core.io import run as runs

    path = run_copy / "avatar.npz"
    newer = Avatar.load(str(path))
    newer.opacity_logit[:] += 1.0
    newer.save(str(tmp_path / "newer.npz"))
    older, newer_file = tmp_path / "older.npz", tmp_path / "newer.npz"
    shutil.copy2(path, older)
    real_load, reads = Avatar.load, []

    def load_while_replaced(p, saves):
        av = real_load(p)
        reads.append(p)
        if len(reads) <= len(saves):  # a training's save lands during this read
            shutil.copy2(saves[len(reads) - 1], path)
        return av

    monkeypatch.setattr(Avatar, "load", lambda p: load_while_replaced(p, [newer_file]))
    av = runs.load_run_avatar(str(run_copy))
    assert len(reads) == 2 and np.array_equal(av.opacity_logit, newer.opacity_logit)
    assert av.source_digest == "sha256:" + hashlib.sha256(newer_file.read_bytes()).hexdigest()
    reads.clear()
    monkeypatch.setattr(Avatar, "load", lambda p: load_while_replaced(p, [older, newer_file, older]))
    with pytest.raises(ValueError, match=r"avatar\.npz changed each time it was read: a training is writing it"):
        runs.load_run_avatar(str(run_copy))
    assert len(reads) == 3


def test_run_config_entries_of_the_wrong_kind_are_refused_naming_the_file(tmp_path):
    """config.json's "data" and "flame_model": an empty or non-text dataset folder and a
    non-text model path are refused naming the file; an empty model path is none; an
    unreadable config.json (a folder) is a ValueError naming it, not a raw OSError."""
    from progressive_avatars.core.io import run as runs

    run = tmp_path / "run"
    run.mkdir()
    cfg = run / "config.json"
    for data, shown in (("", "''"), (5, "5"), (None, "None")):
        cfg.write_text(json.dumps({"data": data}))
        with pytest.raises(ValueError, match=rf'config\.json: "data" is {shown}, not a dataset folder; pass --data'):
            runs.run_data_dir(str(run))
    cfg.write_text(json.dumps({"flame_model": 3}))
    with pytest.raises(ValueError, match=r'config\.json: "flame_model" is 3, not a file path'):
        runs.run_flame_model(str(run))
    assert runs.run_flame_model(str(run), "given.pkl") == "given.pkl"  # given: the config is not read
    cfg.write_text(json.dumps({"flame_model": ""}))
    assert runs.run_flame_model(str(run)) is None
    cfg.write_text(json.dumps({"flame_model": "flame2023.pkl"}))
    assert runs.run_flame_model(str(run)) == "flame2023.pkl"
    os.remove(cfg)
    assert runs.run_flame_model(str(run)) is None and runs.run_config(str(run)) is None
    cfg.mkdir()
    with pytest.raises(ValueError, match=r"config\.json: cannot be read \(Is a directory\)"):
        runs.run_config(str(run))


def test_folder_lock_refuses_a_second_holder_and_a_removed_lock_is_not_held_twice(tmp_path, monkeypatch):
    """folder_lock (a training's run folder, an evaluation's report folder): a second holder is
    refused naming the first; with ``remove`` the file goes at release, and a holder that waited on
    the removed file must take the new one, or two holders would hold two files at once."""
    from progressive_avatars.core.io.run import FolderBusyError, folder_lock

    def busy(holder):
        return f"held by {holder}"

    folder = str(tmp_path / "out")
    with folder_lock(folder, ".lock", busy, remove=True):
        assert open(os.path.join(folder, ".lock")).read().startswith(f"pid {os.getpid()} ")
        with pytest.raises(FolderBusyError, match=rf"held by pid {os.getpid()} on "):
            with folder_lock(folder, ".lock", busy, remove=True):
                pass
    assert os.listdir(folder) == []
    # A waiter (retrying for its second) gets the lock when the holder lets go and removes the file.
    first_in, first_out, order, errors = threading.Event(), threading.Event(), [], []

    def hold(name, wait=None):
        try:
            with folder_lock(folder, ".lock", busy, remove=True):
                order.append(name)
                first_in.set()
                if wait:
                    first_out.wait(timeout=10)
                else:  # the waiter holds it now: nobody else may
                    with pytest.raises(FolderBusyError):
                        with folder_lock(folder, ".lock", busy, remove=True):
                            order.append("third")
        except Exception as exc:
            errors.append(exc)

    a = threading.Thread(target=hold, args=("first", True))
    a.start()
    assert first_in.wait(timeout=10)
    b = threading.Thread(target=hold, args=("second",))
    b.start()
    time.sleep(0.3)  # b retries on the first holder's file
    first_out.set()
    a.join()
    b.join()
    assert errors == [] and order == ["first", "second"] and os.listdir(folder) == []
    # The holder removing the file between a waiter's open and its lock: the waiter locked a file
    # no longer there, and a third process would then lock a new one beside it.
    import fcntl

    real_flock, removed = fcntl.flock, []

    def removed_first(fd, op):
        if not removed:
            removed.append(fd)
            os.remove(os.path.join(folder, ".lock"))
        return real_flock(fd, op)

    open(os.path.join(folder, ".lock"), "w").close()
    monkeypatch.setattr(fcntl, "flock", removed_first)
    with folder_lock(folder, ".lock", busy, remove=True):
        monkeypatch.setattr(fcntl, "flock", real_flock)
        assert removed and os.listdir(folder) == [".lock"]
        with pytest.raises(FolderBusyError):
            with folder_lock(folder, ".lock", busy, remove=True):
                pass
    with folder_lock(folder, ".lock", busy):  # without remove (a run's .train.lock) the file stays
        pass
    assert os.listdir(folder) == [".lock"]


@pytest.mark.slow  # an evaluation of the tiny run
def test_a_second_evaluation_into_one_folder_is_refused(run_copy, tmp_path, monkeypatch, capsys):
    """Two evaluations writing one --out at once mixed their report files; the second is refused
    (exit 2, naming the first) and the folder keeps the first's files."""
    import runpy

    from progressive_avatars.core.io.run import folder_lock

    monkeypatch.setattr(sys, "path", list(sys.path))  # the script puts its folder on sys.path
    main = runpy.run_path(os.path.join(ROOT, "scripts", "evaluate.py"), run_name="evaluate_script")["main"]

    out = tmp_path / "report"
    out.mkdir()
    (out / "report.json").write_text("{}")
    with folder_lock(str(out), ".evaluate.lock", str, remove=True):  # the first evaluation, at work
        rc = main(["--run", str(run_copy), "--out", str(out), "--views", "2", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and f"{out} is being written by another evaluation (pid {os.getpid()} on " in err, err
    assert sorted(os.listdir(out)) == ["report.json"] and (out / "report.json").read_text() == "{}"
