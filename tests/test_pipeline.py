"""The scripts end to end on the tiny run: export (stream + PLY) and the evaluation report."""

import json
import os
import subprocess
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")


def run_script(name, *args):
    out = subprocess.run([sys.executable, os.path.join(ROOT, "scripts", name), *args], capture_output=True, text=True,
                         timeout=600, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_export_and_evaluate(tiny_run, tiny_dataset, tmp_path):
    from plyfile import PlyData

    from progressive_avatars.core import stream
    from progressive_avatars.core.avatar import Avatar

    res = run_script("export.py", "--run", tiny_run, "--stream", str(tmp_path / "a.pavs"), "--ply", str(tmp_path / "f.ply"),
                     "--budget", "100", "--frame", "0", "--max-views", "8")
    trained = Avatar.load(os.path.join(tiny_run, "avatar.npz"))
    assert res["gaussians"] == trained.num_gaussians == res["ply_gaussians"]
    assert res["bytes"] == os.path.getsize(tmp_path / "a.pavs")
    ply = PlyData.read(str(tmp_path / "f.ply"))
    assert ply["vertex"].count == trained.num_gaussians
    decoded = stream.read_stream(str(tmp_path / "a.pavs"))
    # Stream order: level by level, parents first; the same multiset of levels as trained.
    assert np.all(np.diff(decoded.forest.level) >= 0)
    assert np.array_equal(np.bincount(decoded.forest.level), trained.forest.level_counts())

    report_dir = tmp_path / "report"
    run_script("evaluate.py", "--run", tiny_run, "--out", str(report_dir), "--budgets", "25,100", "--views", "2",
               "--curve-points", "3", "--no-progress", "--compare", f"again={tiny_run}",
               "--about", "The tiny run against itself.")
    rep = json.load(open(report_dir / "report.json"))
    assert set(rep["budgets"]) == {"25", "100"}
    full = rep["budgets"]["100"]
    assert full["gaussians"] == trained.num_gaussians
    for key in ("nvs", "nes"):
        assert np.isfinite(full[key]["psnr"]) and 0 < full[key]["ssim"] <= 1
    assert rep["budgets"]["25"]["bytes"] < full["bytes"] <= rep["stream_bytes"]
    assert abs(rep["ablations"]["quantisation_100"]["psnr_loss_db"]) < 0.5
    for png in ("psnr_vs_bytes.png", "strip_nvs.png", "strip_nes.png", "depth.png", "psnr_vs_time.png",
                "quality_vs_gaussians.png"):
        assert (report_dir / png).stat().st_size > 1000, png
    md = (report_dir / "report.md").read_text()
    assert "| 100 % |" in md
    # The tiny dataset's own summary (make_synthetic) is named in the report.
    ds = rep["data_summary"]
    assert "\nThe tiny run against itself.\n" in md
    assert ds["faces"] == len(trained.forest.template_faces) and f"template {ds['faces']:,} faces" in md
    # A compared run (here the same run, unquantised and in training order) scores within the
    # quantisation loss, and the training summary comes from the run's metrics log.
    again = rep["ablations"]["compare"]["again"]
    assert again["gaussians"] == trained.num_gaussians
    assert abs(again["nvs"]["psnr"] - full["nvs"]["psnr"]) < 0.5
    own = rep["training"]["this run"]
    assert own["iterations"] == 60 and own["seconds"] > 0
    assert rep["training"]["again"] == own
    assert "| `again` |" in md and "| `this run` |" in md and "wall time" in md


def test_scripts_report_bad_input(tmp_path):
    out = subprocess.run([sys.executable, os.path.join(ROOT, "scripts", "evaluate.py"), "--run", str(tmp_path),
                          "--out", str(tmp_path / "r")], capture_output=True, text=True, env=ENV)
    assert out.returncode == 2 and "no trained avatar" in out.stderr
    out = subprocess.run([sys.executable, os.path.join(ROOT, "scripts", "export.py"), "--run", str(tmp_path)],
                         capture_output=True, text=True, env=ENV)
    assert out.returncode != 0 and "nothing to do" in out.stderr
