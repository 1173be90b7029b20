"""The scripts end to end on the tiny run: export (stream + PLY) and the evaluation report."""

import json
import os
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from progressive_avatars.core.evaluate.sweep import SplitRenderer, importance_only, paper_table, random_within_levels
from tests.helpers import random_forest, sphere_mesh

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")


def run_script(name, *args):
    out = subprocess.run(
        [sys.executable, os.path.join(ROOT, "scripts", name), *args],
        capture_output=True,
        text=True,
        timeout=600,
        env=ENV,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_export(run, *args):
    """scripts/export.py on ``run`` with ``args``, whatever its exit status."""
    cmd = [sys.executable, os.path.join(ROOT, "scripts", "export.py"), "--run", run, *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=ENV)


@pytest.mark.slow  # a training run or a subprocess
def test_export_and_evaluate(tiny_run, tiny_dataset, tmp_path):
    from plyfile import PlyData

    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.avatar.avatar import Avatar

    res = run_script(
        "export.py",
        "--run",
        tiny_run,
        "--stream",
        str(tmp_path / "a.pavs"),
        "--ply",
        str(tmp_path / "f.ply"),
        "--budget",
        "100",
        "--frame",
        "0",
        "--max-views",
        "8",
    )
    trained = Avatar.load(os.path.join(tiny_run, "avatar.npz"))
    # trained as by default (backdrop stand-ins): the PLY leaves the retired ones out, all of them at 100 %
    assert trained.forest.backdrop
    drawn = trained.num_gaussians - trained.forest.num_coarse
    assert res["gaussians"] == trained.num_gaussians and res["ply_gaussians"] == drawn
    assert res["bytes"] == os.path.getsize(tmp_path / "a.pavs")
    ply = PlyData.read(str(tmp_path / "f.ply"))
    assert ply["vertex"].count == drawn
    decoded = read_stream(str(tmp_path / "a.pavs"))
    # Stream order (version 5): the coarse levels, level by level, then any face after its parent
    # (deeper faces before some template faces); the same multiset of levels as trained.
    f5 = decoded.forest
    in_stream = f5.level[f5.stream_order()]
    n_coarse = int(np.sum(trained.forest.level < 2))
    assert np.all(np.diff(in_stream[:n_coarse]) >= 0) and np.all(in_stream[n_coarse:] >= 2)
    assert np.any(np.diff(in_stream[n_coarse:]) < 0) and f5.root_rank[-1] >= f5.num_roots
    rank = f5.stream_rank()
    kids = np.flatnonzero(f5.parent >= 0)
    assert np.all(rank[f5.parent[kids]] < rank[kids])
    assert np.array_equal(np.bincount(f5.level), trained.forest.level_counts())
    # Any budget exports: 0 % holds no whole Gaussian, so the PLY is empty but valid, with a note.
    out = run_export(
        tiny_run, "--stream", tmp_path / "b.pavs", "--ply", tmp_path / "e.ply", "--budget", 0, "--max-views", 8
    )
    assert out.returncode == 0 and "holds no whole Gaussian" in out.stderr, out.stderr[-2000:]
    assert json.loads(out.stdout.strip().splitlines()[-1])["ply_gaussians"] == 0
    assert PlyData.read(str(tmp_path / "e.ply"))["vertex"].count == 0
    # A frame the dataset lacks is refused before anything is written (it used to be checked
    # only after the stream had been written).
    out = run_export(tiny_run, "--stream", tmp_path / "c.pavs", "--ply", tmp_path / "c.ply", "--frame", 99999)
    assert out.returncode == 2 and "no timestep 99999" in out.stderr, out.stderr[-2000:]
    assert not (tmp_path / "c.pavs").exists() and not (tmp_path / "c.ply").exists()
    # An output folder that cannot exist (a file stands there): a message, no traceback; a
    # missing one is made.
    (tmp_path / "afile").write_text("x")
    bad, made = tmp_path / "afile" / "x.pavs", tmp_path / "new" / "dir" / "x.pavs"
    out = run_export(tiny_run, "--stream", bad)
    assert out.returncode == 2 and f"cannot write {bad}" in out.stderr and "Traceback" not in out.stderr, out.stderr
    out = run_export(tiny_run, "--stream", made)
    assert out.returncode == 0 and made.exists(), out.stderr[-2000:]

    report_dir = tmp_path / "report"
    run_script(
        "evaluate.py",
        "--run",
        tiny_run,
        "--out",
        str(report_dir),
        "--budgets",
        "25,100",
        "--views",
        "2",
        "--curve-points",
        "3",
        "--no-progress",
        "--compare",
        f"again={tiny_run}",
        "--compare",
        f"tiny_seed1={tiny_run}",
        "--budget-compare",
        f"itself={tiny_run}",
        "--name",
        "tiny",
        "--about",
        "The tiny run against itself.",
    )
    rep = json.load(open(report_dir / "report.json"))
    assert set(rep["budgets"]) == {"25", "100"}
    full = rep["budgets"]["100"]
    assert full["gaussians"] == trained.num_gaussians
    for key in ("nvs", "nes"):
        assert np.isfinite(full[key]["psnr"]) and 0 < full[key]["ssim"] <= 1
    assert rep["budgets"]["25"]["bytes"] < full["bytes"] <= rep["stream_bytes"]
    assert abs(rep["ablations"]["quantisation_100"]["psnr_loss_db"]) < 0.5
    # issue 16: mask coverage per budget and curve point, the first whole head, the root orders
    assert 0 <= rep["budgets"]["25"]["nvs"]["coverage"] <= full["nvs"]["coverage"] <= 1
    assert all(0 <= c["coverage"] <= 1 for c in rep["curve_nvs"]) and len(rep["curve_nvs"]) == 3
    fh = rep["first_head"]
    assert fh["coarse_levels"] == 2 and fh["head_gaussians"] == trained.forest.level_counts()[0]
    assert fh["header_bytes"] < fh["head_bytes"] < fh["base_bytes"] < rep["stream_bytes"]
    assert set(rep["ablations"]["root_order"]["orders"]) == {"forest", "spatial", "importance", "both", "auto"}
    assert "psnr_non_decreasing" in rep["done_when"]
    # The stream's interleaved order against every root first (version 4's), at the same counts:
    # inside the coarse levels they are the same prefix (both send them first, in the same order).
    il = rep["ablations"]["interleaved_order"]
    assert set(il) == {"1", "2", "3", "5", "10", "25", "50"} and rep["stream_version"] == 5
    inside = [d for d in il.values() if d["gaussians"] <= n_coarse]
    assert inside and all(
        d["interleaved"]["psnr"] == pytest.approx(d["levels_first"]["psnr"], abs=1e-9) for d in inside
    )
    assert il["25"]["interleaved"]["psnr"] == rep["budgets"]["25"]["nvs"]["psnr"]
    # On the trained forest (its base is most of this small stream): a permutation, coarse levels
    # first, every parent before its children.
    from progressive_avatars.core.stream.order import interleaved_order

    f = trained.forest
    inter = interleaved_order(f, np.random.default_rng(0).random(f.num_faces))
    pos = np.empty(f.num_faces, np.int64)
    pos[inter] = np.arange(f.num_faces)
    kids = np.flatnonzero(f.parent >= 0)
    assert np.array_equal(np.sort(inter), np.arange(f.num_faces)) and np.all(pos[f.parent[kids]] < pos[kids])
    assert np.all(f.level[inter[:n_coarse]] < 2) and len(kids) > 0
    assert all(np.isfinite(d["interleaved"]["psnr"]) and 0 <= d["interleaved"]["coverage"] <= 1 for d in il.values())
    for png in (
        "psnr_vs_bytes.png",
        "strip_nvs.png",
        "strip_nes.png",
        "strip_interleaved.png",
        "depth.png",
        "psnr_vs_time.png",
        "quality_vs_gaussians.png",
    ):
        assert (report_dir / png).stat().st_size > 1000, png
    md = (report_dir / "report.md").read_text()
    assert "| 100 % |" in md and "First whole head" in md and "interleaved_order: version 5, this stream" in md
    # The tiny dataset's own summary (make_synthetic) is named in the report.
    ds = rep["data_summary"]
    assert "\nThe tiny run against itself.\n" in md
    assert ds["faces"] == len(trained.forest.template_faces) and f"template {ds['faces']:,} faces" in md
    # A compared run (here the same run, unquantised and in training order) scores within the
    # quantisation loss, and the training summary comes from the run's metrics log.
    again = rep["ablations"]["compare"]["again"]
    assert again["gaussians"] == trained.num_gaussians
    assert abs(again["nvs"]["psnr"] - full["nvs"]["psnr"]) < 0.5
    # The same run written again as the stream is scores the same at every short budget.
    bc = rep["ablations"]["budget_compare"]
    assert set(bc["this"]) == set(bc["itself"]["budgets"]) == {"1", "2", "5", "10", "25", "100"}
    for b, mine in bc["this"].items():
        assert bc["itself"]["budgets"][b]["psnr"] == pytest.approx(mine["psnr"], abs=1e-9), b
    assert bc["itself"]["bytes"] == rep["stream_bytes"] and "| 5 % |" in md and "| this run | itself |" in md
    own = rep["training"]["this run"]
    assert own["iterations"] == 60 and own["seconds"] > 0
    assert rep["training"]["again"] == own
    assert "| `again` |" in md and "| `tiny` (this run) |" in md and "s of training steps" in md
    # --name puts this run (scored from its float32 avatar) in a group with "tiny_seed1" (the
    # same run again): two identical scores, so the mean is that score and the spread 0.
    g = rep["seed_groups"]["tiny"]
    assert g["runs"] == ["tiny", "tiny_seed1"] and set(rep["seed_groups"]) == {"tiny"}
    assert g["nvs_psnr_mean"] == pytest.approx(rep["ablations"]["quantisation_100"]["float32"]["psnr"], abs=1e-9)
    assert g["nvs_psnr_sd"] == pytest.approx(0.0, abs=1e-9) and g["gaussians_mean"] == trained.num_gaussians
    assert f"| `tiny` | 2 | {trained.num_gaussians:,} ± 0 | {g['nvs_psnr_mean']:.3f} ± 0.000 |" in md


def _run_copy(tiny_run, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    return run


@pytest.mark.slow  # subprocesses
def test_export_writes_only_what_it_is_given_and_a_failed_one_changes_nothing(tiny_run, tiny_dataset, tmp_path):
    """--ply alone writes the PLY and nothing else: the run's own stream (here a lossless one)
    is kept, also when the PLY cannot be written (it used to be replaced by a quantised one
    first); the PLY is the prefix of the stream the same command with --stream writes; every
    output path is checked before any work."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.stream.format import read_header
    from progressive_avatars.core.stream.writer import write_stream

    run = _run_copy(tiny_run, tmp_path)
    own = run / "avatar.pavs"
    rest = Dataset(tiny_dataset, None).canonical_vertices
    write_stream(own, Avatar.load(run / "avatar.npz"), quantize=False, vertices=rest)
    before = own.read_bytes()
    assert read_header(before).lossless
    adir = tmp_path / "adir"
    adir.mkdir()
    common = ["--budget", 50, "--max-views", 4]
    out = run_export(str(run), "--ply", adir, *common)  # a folder: the PLY cannot be written there
    assert out.returncode == 2 and f"cannot write {adir}" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert own.read_bytes() == before and os.listdir(adir) == []
    # ... nor when the stream is asked for too: neither file is written
    out = run_export(str(run), "--stream", tmp_path / "s0.pavs", "--ply", adir, *common)
    assert out.returncode == 2 and not (tmp_path / "s0.pavs").exists(), out.stderr
    out = run_export(str(run), "--stream", tmp_path / "same", "--ply", tmp_path / "." / "same", *common)
    assert out.returncode == 2 and "name the same file" in out.stderr and not (tmp_path / "same").exists()
    # A PLY alone: written, the run's stream untouched, no stream named in the result.
    out = run_export(str(run), "--ply", tmp_path / "alone.ply", *common)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert own.read_bytes() == before and res["stream"] is None and res["ply_gaussians"] > 0
    # ... the same PLY as with --stream, whose stream holds the bytes the budget counted.
    both = run_script(
        "export.py",
        "--run",
        str(run),
        "--stream",
        str(tmp_path / "s.pavs"),
        "--ply",
        str(tmp_path / "b.ply"),
        *map(str, common),
    )
    assert (tmp_path / "alone.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    assert both["bytes"] == res["bytes"] == os.path.getsize(tmp_path / "s.pavs") and both["stream"] == str(
        tmp_path / "s.pavs"
    )
    assert own.read_bytes() == before


def test_export_ply_write_failing_late_leaves_the_stream_unwritten(tiny_run, tmp_path, monkeypatch, capsys):
    """A PLY write that fails after the checks (a full disk): the stream asked for in the same
    export is not written either (it is renamed into place only after the PLY)."""
    import errno
    import importlib.util

    from progressive_avatars.core.io import ply

    monkeypatch.setattr(sys, "path", list(sys.path))  # the script puts its folder on sys.path
    monkeypatch.setenv("OMP_WAIT_POLICY", os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))  # and sets this
    spec = importlib.util.spec_from_file_location("export_script", os.path.join(ROOT, "scripts", "export.py"))
    export = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(export)

    def full(*a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(ply, "write_ply", full)
    run = _run_copy(tiny_run, tmp_path)
    old = (run / "avatar.pavs").read_bytes() if (run / "avatar.pavs").exists() else None
    out = tmp_path / "out"
    rc = export.main(
        ["--run", str(run), "--stream", str(out / "s.pavs"), "--ply", str(out / "f.ply"), "--max-views", "2"]
    )
    err = capsys.readouterr().err
    assert rc == 2 and f"cannot write {out / 'f.ply'}" in err and "No space left" in err, err
    assert not (out / "s.pavs").exists() and not (out / "f.ply").exists() and os.listdir(out) == []
    assert ((run / "avatar.pavs").read_bytes() if (run / "avatar.pavs").exists() else None) == old


@pytest.mark.slow  # subprocesses
def test_export_ply_of_an_sh_avatar_needs_no_drop_sh(tiny_run, tmp_path):
    """A PLY of an avatar with SH bands keeps every band and needs no --drop-sh (it used to be
    refused by the stream write every export made, with a message telling the user to export a
    PLY); --stream without --drop-sh is refused before any work, the message naming --drop-sh."""
    from plyfile import PlyData

    from progressive_avatars.core.avatar.avatar import Avatar

    run = _run_copy(tiny_run, tmp_path)
    av = Avatar.load(run / "avatar.npz")
    av.f_rest = np.random.default_rng(0).normal(0, 0.1, (av.num_gaussians, 3, 3)).astype(np.float32)
    av.save(run / "avatar.npz")
    res = run_script(
        "export.py", "--run", str(run), "--ply", str(tmp_path / "sh.ply"), "--budget", "30", "--max-views", "2"
    )
    names = PlyData.read(str(tmp_path / "sh.ply"))["vertex"].data.dtype.names
    assert res["ply_gaussians"] > 0 and [n for n in names if n.startswith("f_rest_")] == [
        f"f_rest_{j}" for j in range(9)
    ]
    out = run_export(str(run), "--stream", tmp_path / "s.pavs", "--ply", tmp_path / "both.ply", "--max-views", "2")
    assert out.returncode == 2 and "Pass --drop-sh" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert "export a PLY to keep" not in out.stderr
    assert not (tmp_path / "s.pavs").exists() and not (tmp_path / "both.ply").exists()


def test_seed_groups():
    from progressive_avatars.core.evaluate.plots import seed_group, seed_groups, seed_pairs

    def run(psnr, gaussians, prefixes):
        return {
            "gaussians": gaussians,
            "nvs": {"psnr": psnr},
            "level_prefixes_nvs": {k: {"psnr": v} for k, v in enumerate(prefixes)},
        }

    assert (
        seed_group("a_w0.3_seed12") == "a_w0.3"
        and seed_group("seed1") == "seed1"
        and seed_group("a_seedx") == "a_seedx"
    )
    g = seed_groups(
        {
            "a": run(24.0, 100, [20.0, 23.0, 24.0]),
            "a_seed1": run(25.0, 110, [21.0, 24.0]),
            "a_seed2": run(26.0, 120, [22.0, 25.0, 26.0]),
            "b": run(30.0, 5, [30.0]),
        }
    )
    assert set(g) == {"a"}  # a group needs two runs
    a = g["a"]
    assert a["n"] == 3 and a["runs"] == ["a", "a_seed1", "a_seed2"]
    assert a["nvs_psnr_mean"] == pytest.approx(25.0) and a["nvs_psnr_sd"] == pytest.approx(1.0)
    assert (a["nvs_psnr_min"], a["nvs_psnr_max"]) == (24.0, 26.0)
    assert a["gaussians_mean"] == pytest.approx(110) and a["gaussians_sd"] == pytest.approx(10)
    assert a["level_prefixes_nvs_mean"] == pytest.approx({"0": 21.0, "1": 24.0})  # levels all three have

    # Paired differences: only over the seeds both groups have, and only with two or more.
    runs = {
        "a": run(24.0, 1, [24.0]),
        "a_seed1": run(25.0, 1, [25.0]),
        "a_seed2": run(26.0, 1, [26.0]),
        "b": run(23.5, 1, [23.5]),
        "b_seed2": run(25.0, 1, [25.0]),
        "c": run(20.0, 1, [20.0]),
        "c_seed5": run(20.0, 1, [20.0]),
    }
    pairs = seed_pairs(runs)
    assert [(p["a"], p["b"], p["seeds"]) for p in pairs] == [("a", "b", [0, 2])]
    assert pairs[0]["diffs"] == pytest.approx([0.5, 1.0]) and pairs[0]["mean"] == pytest.approx(0.75)
    assert pairs[0]["sd"] == pytest.approx(np.std([0.5, 1.0], ddof=1))

    # Legend entries: one per seed group, counting this run (drawn in black) among its seeds.
    from progressive_avatars.core.evaluate.plots import _group_styles

    st = _group_styles(["a_seed1", "a_seed2", "b", "b_seed1", "c"], also=["a"])
    assert st["a_seed1"][1] == "a (3 seeds, this run in black)" and st["a_seed2"] == (st["a_seed1"][0], None)
    assert st["b"][1] == "b (2 seeds)" and st["c"][1] == "c" and st["b"][0] != st["a_seed1"][0]


def test_done_when_over_seeds():
    """The 5 % gap and the coverage from 2 % on every seed's own stream, and the coarse levels'
    cost as the mean of the per-seed differences (one seed at the line does not settle it)."""
    from progressive_avatars.core.evaluate.plots import done_when, seed_pairs

    def short(p5, p100, cov2):
        return {
            "2": {"psnr": 18.0, "coverage": cov2},
            "5": {"psnr": p5, "coverage": 0.98},
            "100": {"psnr": p100, "coverage": 0.99},
        }

    def run(psnr, path="x"):
        return {"run": path, "nvs": {"psnr": psnr}, "gaussians": 1, "level_prefixes_nvs": {}}

    compare = {
        "d_seed1": run(24.9),
        "d_seed2": run(25.0),
        "none": run(24.92, "runs/none"),
        "none_seed1": run(24.95),
        "none_seed2": run(25.1),
    }
    r = {
        "name": "d",
        "budgets": {},
        "ablations": {
            "coarse_vs_none": {
                "run": "runs/none",
                "budgets": {"100": {"with": {"psnr": 24.9}, "without": {"psnr": 24.92}}},
            },
            "budget_compare": {
                "this": short(22.5, 24.9, 0.97),
                "d_seed1": {"budgets": short(21.8, 24.9, 0.96)},
                "other": {"budgets": short(10.0, 24.9, 0.10)},  # not a seed of this run: not counted
            },
            "compare": compare,
        },
    }
    r["seed_pairs"] = seed_pairs({"d": run(24.8), **compare})
    dw = done_when(r)
    gap = dw["psnr_5_within_3db_every_seed"]
    assert gap["gap_db"] == pytest.approx({"d": 2.4, "d_seed1": 3.1}) and not gap["met"]
    cov = dw["coverage_from_2pct_every_seed"]
    assert cov["min"] == pytest.approx({"d": 0.97, "d_seed1": 0.96}) and cov["met"]
    assert dw["coarse_cost_100"]["met"]  # seed 0 alone: 0.02 dB
    cost = dw["coarse_cost_100_seed_mean"]  # per seed 0.12, 0.05, 0.10: mean 0.09
    assert cost["per_seed_db"] == pytest.approx([0.12, 0.05, 0.10]) and cost["cost_db"] == pytest.approx(0.09)
    assert cost["met"] and cost["seeds"] == [0, 1, 2]
    compare["none_seed2"] = run(25.2)  # seed 2 now costs 0.2: mean 0.123
    r["seed_pairs"] = seed_pairs({"d": run(24.8), **compare})
    assert not done_when(r)["coarse_cost_100_seed_mean"]["met"]


def test_scripts_report_bad_input(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "scripts", "evaluate.py"),
            "--run",
            str(tmp_path),
            "--out",
            str(tmp_path / "r"),
        ],
        capture_output=True,
        text=True,
        env=ENV,
    )
    assert out.returncode == 2 and "no trained avatar" in out.stderr
    # Counts and percentages are checked before any work, with the option named (these raised
    # IndexError / ZeroDivisionError deep in the report, or a bare float() message).
    for args, says in (
        (["--views", "0"], "views, curve points and curve views must be >= 1"),
        (["--curve-points", "0"], "views, curve points and curve views must be >= 1"),
        (["--strips", "101"], "strip budgets must be percentages in [0, 100]"),
        (["--strips", "abc"], "--strips takes comma-separated percentages"),
        (["--multi-level", str(tmp_path)], "give it with --paper-table and --finest-only"),
    ):
        out = subprocess.run(
            [sys.executable, os.path.join(ROOT, "scripts", "evaluate.py"), "--run", str(tmp_path)]
            + ["--out", str(tmp_path / "r"), *args],
            capture_output=True,
            text=True,
            env=ENV,
        )
        assert out.returncode == 2 and says in out.stderr and "Traceback" not in out.stderr, (args, out.stderr)
    out = subprocess.run(
        [sys.executable, os.path.join(ROOT, "scripts", "export.py"), "--run", str(tmp_path)],
        capture_output=True,
        text=True,
        env=ENV,
    )
    assert out.returncode != 0 and "nothing to do" in out.stderr


def test_report_is_a_library_function(tiny_run, tmp_path):
    """The evaluation report is built by core/evaluate/report.build_report (scripts/evaluate.py
    is only its command line): bad budgets are refused before any work, and a call writes the
    same report files the script does."""
    from progressive_avatars.core.evaluate.report import ReportOptions, build_report

    import shutil

    with pytest.raises(ValueError, match="budgets"):
        build_report(ReportOptions(run=tiny_run, out=str(tmp_path / "bad"), budgets=(0, 100)))
    for kw, says in (
        (dict(views=0), "views, curve points and curve views must be >= 1"),
        (dict(curve_views=0), "views, curve points and curve views must be >= 1"),
        (dict(strips=(-1,)), "strip budgets"),
        (dict(paper_table=True, multi_level=tiny_run), "--multi-level"),  # without --finest-only
    ):
        with pytest.raises(ValueError, match=says):
            build_report(ReportOptions(run=tiny_run, out=str(tmp_path / "bad"), **kw))
    assert not (tmp_path / "bad").exists()
    # A compared run whose log ends 3 dB lower: the time-to-PSNR target is one both runs reach.
    low = tmp_path / "low"
    shutil.copytree(tiny_run, low)
    rows = [json.loads(ln) for ln in open(os.path.join(tiny_run, "metrics.jsonl"))]
    with open(low / "metrics.jsonl", "w") as fh:
        for row in rows:
            fh.write(json.dumps({**row, "val_psnr": row["val_psnr"] - 3} if "val_psnr" in row else row) + "\n")
    out = tmp_path / "lib"
    out.mkdir()
    rep = build_report(
        ReportOptions(
            run=tiny_run,
            out=str(out),
            budgets=(50, 100),
            strips=(0, 100),  # a 0 % strip (nothing arrived yet) is allowed
            views=1,
            curve_points=2,
            curve_views=1,
            compare=(f"low={low}",),
            progress=False,
        )
    )
    assert rep["budgets"]["100"]["gaussians"] == rep["gaussians"] > 0
    assert json.load(open(out / "report.json"))["budgets"]["100"]["gaussians"] == rep["gaussians"]
    assert (out / "report.md").read_text().startswith("#")
    # Its numbers by hand, from what they are defined as.
    total, n, counts = rep["stream_bytes"], rep["gaussians"], rep["level_counts"]
    assert total == os.path.getsize(os.path.join(tiny_run, "avatar.pavs")) and rep["bytes_per_gaussian"] == total / n
    # Every record: the whole stream but its last block's CRC (bytes_for_count, the fewest bytes
    # holding the records: header + n records + the CRCs of the blocks before the last record's).
    assert rep["budgets"]["100"]["bytes"] == total - 4
    assert rep["budgets"]["50"]["bytes"] <= total / 2 < total
    assert [c["percent"] for c in rep["curve_nvs"]] == [50.0, 100.0]
    assert rep["curve_nvs"][-1]["gaussians"] == n and rep["curve_nvs"][-1]["bytes"] == total - 4
    fh = rep["first_head"]
    for r in (1, 10, 100):  # bytes * 8 bits at r Mbit/s
        assert fh[f"head_seconds_{r}mbit"] == pytest.approx(fh["head_bytes"] * 8 / (r * 1e6), rel=1e-12)
        assert fh[f"base_seconds_{r}mbit"] == pytest.approx(fh["base_bytes"] * 8 / (r * 1e6), rel=1e-12)
    K = fh["coarse_levels"]
    assert K >= 1
    # The root-order cuts: a quarter and a half into each root level (coarse levels, template).
    cuts = {}
    for lv in range(K + 1):
        for frac, name in ((0.25, "25%"), (0.5, "50%")):
            cuts[f"level {lv} + {name}"] = sum(counts[:lv]) + max(1, int(frac * counts[lv]))
    assert rep["ablations"]["root_order"]["cuts"] == cuts
    q = rep["ablations"]["quantisation_100"]
    assert q["psnr_loss_db"] == q["float32"]["psnr"] - q["quantised"]["psnr"]  # what quantising costs
    assert q["bytes_quantised"] == total < q["bytes_float32"]
    assert q["quantised"]["psnr"] == rep["budgets"]["100"]["nvs"]["psnr"]  # the streamed avatar, whole
    d = rep["ablations"]["single_asset_vs_discrete"]
    assert d["discrete_sum_bytes"] == rep["budgets"]["50"]["bytes"] + rep["budgets"]["100"]["bytes"]
    # Level prefixes: every face of the levels up to each (the backdrop keeps retired stand-ins),
    # the last one the whole avatar.
    lp = rep["ablations"]["level_prefixes"]
    assert list(lp["counts"].values()) == np.cumsum(counts).tolist()
    assert lp["nvs"][len(counts) - 1]["psnr"] == rep["budgets"]["100"]["nvs"]["psnr"]
    assert lp["nvs"][0]["psnr"] < lp["nvs"][len(counts) - 1]["psnr"]
    # The random-order ablation: the first 25 % of the Gaussians in a seed-0 random order inside
    # each level, scored like every set (the stream the report wrote, its NVS views).
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.stream.reader import read_stream

    val = Dataset(json.load(open(os.path.join(tiny_run, "config.json")))["data"], "val")
    nvs = SplitRenderer(read_stream(os.path.join(tiny_run, "avatar.pavs"), template_faces=val.faces), val, 1)
    ro = rep["ablations"]["random_order_25"]
    assert ro["gaussians"] == rep["ablations"]["interleaved_order"]["25"]["gaussians"]
    by_hand = random_within_levels(nvs.avatar.forest.level, seed=0)[: ro["gaussians"]]
    assert ro["random"]["psnr"] == nvs.score(np.sort(by_hand))["psnr"]
    finals = [max(r["val_psnr"] for r in rows if "val_psnr" in r)]
    assert rep["time_to_psnr"]["target"] == pytest.approx(finals[0] - 3 - 0.5, abs=1e-9)


def test_done_when_checks_the_budget_table_and_names_the_curve_it_had():
    """The non-decreasing criteria look at the budget table as well as the curve (each on its
    own views), and say how many curve points they saw: a one-point curve used to report 'met
    ... in 1 % steps' having checked nothing."""
    from progressive_avatars.core.evaluate.plots import _steps, done_when

    def budgets(psnr):
        return {str(k): {"nvs": {"psnr": v, "coverage": 0.99}} for k, v in psnr.items()}

    flat = {"1": 20.0, "5": 23.0, "50": 25.0, "100": 25.0}
    r = {"budgets": budgets(flat), "curve_nvs": [{"percent": 100.0, "psnr": 25.0, "coverage": 0.99}]}
    assert done_when(r)["psnr_non_decreasing"]["met"]
    r["budgets"] = budgets(dict(flat, **{"50": 26.0}))  # 50 % a dB above 100 %
    d = done_when(r)["psnr_non_decreasing"]
    assert not d["met"] and abs(d["worst_drop"] - 1.0) < 1e-9 and d["curve_points"] == 1
    assert _steps(d, r["curve_nvs"]) == "the curve's 1 point(s)"
    # A report from before the count was recorded: its own curve says (20 points were called 1 % steps)
    curve = [{"percent": 5.0 * (i + 1)} for i in range(20)]
    assert _steps({}, curve) == "the curve's 20 point(s) (5 % steps)"
    assert _steps({}, [{"percent": float(p)} for p in range(1, 101)]) == "the curve in 1 % steps"


@pytest.mark.slow  # a training run and a subprocess
def test_export_of_a_backdrop_avatar_says_what_the_ply_leaves_out(tiny_dataset, tmp_path):
    """A PLY of a backdrop-stand-in avatar at 100 % holds every Gaussian but the retired
    stand-ins (a depth-sorted viewer cannot draw them behind the rest), and export says so; the
    stream it writes carries them all, flagged (docs/FORMAT.md 2.4)."""
    from plyfile import PlyData

    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.train.trainer import Trainer, config_for

    run = str(tmp_path / "bd")
    Trainer(tiny_dataset, run, config_for("tiny", iterations=20, coarse_backdrop=True)).run(progress=False)
    out = run_export(run, "--stream", tmp_path / "a.pavs", "--ply", tmp_path / "f.ply", "--max-views", 4)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    decoded = read_stream(str(tmp_path / "a.pavs"))
    coarse = decoded.forest.num_coarse
    assert decoded.forest.backdrop and coarse > 0 and decoded.num_gaussians == res["gaussians"]
    assert PlyData.read(str(tmp_path / "f.ply"))["vertex"].count == res["ply_gaussians"] == res["gaussians"] - coarse
    assert f"{coarse:,} retired coarse stand-ins left out of the PLY" in out.stderr


def test_scores_have_their_known_values():
    """The report's headline numbers on hand-made images: PSNR in the mask and on the whole
    image, and mask coverage (rendered alpha >= 0.5 where the mask is >= 0.5)."""
    from types import SimpleNamespace

    from progressive_avatars.core.evaluate.sweep import SplitRenderer
    from progressive_avatars.core.train import metrics

    H, W = 16, 12
    mask = np.zeros((H, W), np.float32)
    mask[:, : W // 2] = 1.0
    truth = np.where(mask[..., None] > 0, 0.1, 0.5).astype(np.float32) * np.ones(3, np.float32)
    rendered = np.zeros((H, W, 3), np.float32)
    assert metrics.psnr(rendered, truth, mask) == pytest.approx(20.0, abs=1e-5)  # MSE 0.01 inside
    assert metrics.psnr(rendered, truth) == pytest.approx(10 * np.log10(1 / 0.13), abs=1e-5)  # 8.8606 dB

    for alpha_inside, coverage in ((0.3, 0.0), (0.6, 1.0), (0.5, 1.0)):
        alpha = np.where(mask > 0, alpha_inside, 0.0).astype(np.float32)
        alpha[0, 0] = 0.0  # one hole in the mask: 1 of 96 mask pixels
        sr = SplitRenderer.__new__(SplitRenderer)
        sr.views = [0, 1]
        sr.dataset = [SimpleNamespace(image=truth, mask=mask)] * 2
        sr.render = lambda view, ids, with_alpha=False, a=alpha: (rendered, 0.001, a)
        out = sr.score(np.arange(3))
        assert out["coverage"] == pytest.approx(max(coverage - 1 / 96, 0.0))
        assert out["psnr"] == pytest.approx(20.0) and out["psnr_full_image"] == pytest.approx(8.8606, abs=1e-4)
        assert out["views"] == 2 and out["render_ms"] == pytest.approx(1.0)
    # A view whose mask is empty has no in-mask score: it read as 120 dB (and coverage 0) and
    # lifted the means; now it is left out of them, and counted.
    empty = np.zeros_like(mask)
    assert np.isnan(metrics.psnr(rendered, truth, empty)) and np.isnan(metrics.ssim(rendered, truth, empty))
    sr.dataset = [SimpleNamespace(image=truth, mask=mask), SimpleNamespace(image=truth, mask=empty)]
    sr.render = lambda view, ids, with_alpha=False: (rendered, 0.001, np.ones((H, W), np.float32))
    out = sr.score(np.arange(3))
    assert out["psnr"] == pytest.approx(20.0) and out["coverage"] == pytest.approx(1.0)
    assert out["views_with_empty_mask"] == 1 and out["psnr_full_image"] == pytest.approx(8.8606, abs=1e-4)
    assert 0 < out["ssim"] < 1


def test_curves_crossover_names_where_uniform_stops_leading():
    """The paper table's sentence under the adaptive-vs-uniform plot: the largest count at which
    uniform's seed mean is level with or above adaptive's (None: adaptive ahead throughout)."""
    from progressive_avatars.core.evaluate.plots import curves_crossover

    xs = [100, 1000, 10000, 100000]
    curve = lambda ys: [{"gaussians": g, "psnr": y} for g, y in zip(xs, ys)]  # noqa: E731
    curves = {
        "adaptive": {0: curve([10, 20, 26, 28]), 1: curve([10, 20, 26, 28])},
        "uniform": {0: curve([11, 21, 25, 27]), 1: curve([11, 21, 25, 27])},
    }
    lo, hi, last = curves_crossover(curves)
    assert (lo, hi) == (100, 100000) and 1000 <= last < 10000  # the means cross between 1k and 10k
    curves["uniform"] = {0: curve([9, 19, 25, 27])}
    assert curves_crossover(curves)[2] is None
    assert curves_crossover({"adaptive": curves["adaptive"]}) is None


def test_report_says_when_depth_has_no_rank_correlation():
    """Every face at one depth (no growth) leaves Spearman's rho undefined: the report said
    "Spearman ρ = nan"; it says why now, and prints the number otherwise."""
    import json

    from progressive_avatars.core.evaluate import plots

    r = json.load(open(os.path.join(ROOT, "docs", "report_cpu", "report.json"), encoding="utf-8"))
    line = [ln for ln in plots.report_markdown(r).splitlines() if ln.startswith("Depth follows detail")]
    assert line and f"Spearman ρ = {r['depth_vs_detail']['spearman']:.3f};" in line[0]
    r["depth_vs_detail"]["spearman"] = float("nan")
    line = [ln for ln in plots.report_markdown(r).splitlines() if ln.startswith("Depth follows detail")]
    assert "nan" not in line[0] and "no rank correlation (every face at one depth" in line[0]


def test_report_says_how_many_views_had_an_empty_mask():
    """Views with an empty mask are left out of the in-mask scores (core/evaluate/sweep.py); the
    report says how many, and says nothing when there are none."""
    import json

    from progressive_avatars.core.evaluate import plots

    r = json.load(open(os.path.join(ROOT, "docs", "report_cpu", "report.json"), encoding="utf-8"))
    assert "empty foreground mask" not in plots.report_markdown(r)
    for e in r["budgets"].values():
        e["nes"]["views_with_empty_mask"] = 2
    text = plots.report_markdown(r)
    assert f"left out of the PSNR, SSIM and coverage above: 2 of {e['nes']['views']} NES views" in text


def _renderer(**attrs):
    sr = SplitRenderer.__new__(SplitRenderer)
    for k, v in attrs.items():
        setattr(sr, k, v)
    return sr


def test_first_n_records_are_the_first_n_faces_of_a_plain_forest():
    verts, faces = sphere_mesh(6, 8)
    forest = random_forest(faces, np.random.default_rng(0), depth=2)
    sr = _renderer(avatar=SimpleNamespace(forest=forest))
    for n in (0, 1, 7, len(faces), forest.num_faces):
        np.testing.assert_array_equal(sr.first(n), np.arange(n))


def test_first_n_records_of_a_backdrop_forest_are_n_faces_growing_by_prefix():
    verts, faces = sphere_mesh(6, 8)
    forest = random_forest(faces, np.random.default_rng(1), depth=2, coarse_from=verts, stand_ins=True)
    forest._set_stand_ins(True, None, backdrop=True)
    assert forest.backdrop
    sr = _renderer(avatar=SimpleNamespace(forest=forest))
    prev = np.zeros(0, np.int64)
    for n in (1, 2, 5, 20, forest.num_faces - 1):
        ids = sr.first(n)
        assert len(ids) == n and len(np.unique(ids)) == n
        assert set(prev.tolist()) <= set(ids.tolist())
        prev = ids


def test_an_empty_prefix_renders_the_background_with_zero_alpha():
    cam = SimpleNamespace(width=4, height=3)
    bg = np.array([0.2, 0.4, 0.6], np.float32)
    forest = SimpleNamespace(render_set=lambda ids: (np.zeros(0, np.int64), None))
    sr = _renderer(avatar=SimpleNamespace(forest=forest), bg=bg,
                   dataset=SimpleNamespace(frame_info=lambda i: SimpleNamespace(camera=cam)))  # fmt: skip
    image, seconds, alpha = sr.render(0, np.zeros(0, np.int64), with_alpha=True)
    assert image.shape == (3, 4, 3) and alpha.shape == (3, 4) and seconds == 0.0
    np.testing.assert_allclose(image, np.broadcast_to(bg, (3, 4, 3)))
    assert not alpha.any()


def test_in_mask_ssim_ignores_pixels_outside_the_mask():
    # Identical in columns 0..19; the mask (columns 0..14) only holds 11x11 windows whose centre
    # lies in columns 5..14, which see columns 0..19 alone: in-mask SSIM is exactly 1.
    rng = np.random.default_rng(0)
    truth = rng.random((30, 40, 3)).astype(np.float32)
    rendered = truth.copy()
    rendered[:, 20:] = rng.random((30, 20, 3))
    mask = np.zeros((30, 40), np.float32)
    mask[:, :15] = 1.0
    sr = _renderer(views=[0], dataset=[SimpleNamespace(image=truth, mask=mask)],
                   render=lambda v, ids, with_alpha=False: (rendered, 0.001, np.ones((30, 40), np.float32)))  # fmt: skip
    out = sr.score(np.arange(1))
    assert out["ssim"] == pytest.approx(1.0, abs=1e-9)
    assert out["ssim_full_image"] < 0.9


def test_full_image_psnr_is_the_mean_over_views():
    # rendered black, truth a constant c: MSE c^2, PSNR -20 log10(c): 20 dB and 40 dB -> mean 30
    H, W = 16, 16
    black = np.zeros((H, W, 3), np.float32)
    views = [
        SimpleNamespace(image=np.full((H, W, 3), c, np.float32), mask=np.ones((H, W), np.float32)) for c in (0.1, 0.01)
    ]
    sr = _renderer(views=[0, 1], dataset=views, render=lambda v, ids, with_alpha=False: (black, 0.001, np.ones((H, W))))
    out = sr.score(np.arange(1), ssim=False)
    assert out["psnr_full_image"] == pytest.approx(30.0, abs=1e-4) and out["psnr"] == pytest.approx(30.0, abs=1e-4)


def test_random_within_levels_shuffles_inside_levels_only():
    level = np.array([2, 0, 1, 0, 2, 1, 0, 1, 2, 0])
    order = random_within_levels(level, seed=3)
    assert sorted(order.tolist()) == list(range(len(level)))
    assert level[order].tolist() == sorted(level.tolist())  # parents (lower levels) first


def test_importance_only_is_descending_importance_stable_on_ties():
    assert importance_only(np.array([0.1, 0.5, 0.3, 0.5])).tolist() == [1, 3, 2, 0]


def _report():
    def split(p):
        return {"psnr": p, "ssim": 0.5 + p / 100}

    budgets = {k: {"nvs": split(p), "nes": split(p - 3), "gaussians": g, "bytes": g * 250, "render_ms": 4.0}
               for k, p, g in (("5", 27.0, 100), ("25", 29.5, 300), ("50", 30.5, 600), ("100", 31.0, 1000))}  # fmt: skip
    return {
        "budgets": budgets,
        "ablations": {
            "random_order_25": {"ranked": {"psnr": 29.5}, "random": {"psnr": 28.5}},
            "importance_only_50": {"levels_then_importance": {"psnr": 30.5}, "importance_only": {"psnr": 30.0}},
            "level_prefixes": {"nvs": {"2": {"psnr": 27.0}}},
        },
        "first_head": {"coarse_levels": 2},
        "level_counts": [10, 20, 70, 900],  # base = the coarse levels and the template: 100
        "gaussians": 1000,
        "base_bytes": 5000,
        "stream_bytes": 250000,
    }


def test_paper_table_gaps_and_growth_by_hand():
    out = paper_table(_report())
    rows, checks = out["table1"], out["checks"]
    assert rows["25"]["nvs_gap"] == pytest.approx(1.5) and rows["5"]["nes_gap"] == pytest.approx(4.0)
    assert checks["NVS gap to 100 % at 25 % (dB)"]["ok"] is True  # 1.5 <= 1.5
    assert checks["NVS gap to 100 % at 5 % (dB)"]["ok"] is False  # 4.0 > 3.0
    g = checks["growth: all Gaussians / base"]
    assert g["ours"] == pytest.approx(10.0) and g["ok"] is False  # 1000 / (10 + 20 + 70) < 12
    assert checks["detail: NVS 100 % minus the base level alone (dB)"]["ours"] == pytest.approx(4.0)
