"""The command-line tools refuse bad paths and options before any long work, naming the option,
and write their pictures and arrays atomically (a review's confirmed defects, each test failing
on the old scripts)."""

import errno
import os
import runpy
import shutil
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _script(name):
    """scripts/NAME's globals, run as a module (not as __main__); sys.path as it was."""
    saved = list(sys.path)
    try:
        return runpy.run_path(os.path.join(ROOT, "scripts", name), run_name=name[:-3] + "_script")
    finally:
        sys.path[:] = saved


def _exit_code(call):
    """The status ``call`` ends with: its return value, or SystemExit's code (argparse errors)."""
    try:
        return call()
    except SystemExit as exc:
        return exc.code


@pytest.fixture
def run_copy(tiny_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    return run


@pytest.fixture
def no_rendering(monkeypatch):
    """The importance pass (the first long work of export and evaluate) fails the test."""
    from progressive_avatars.core.io import run as runs

    def started(*a, **k):
        raise AssertionError("the importance pass started before the inputs were checked")

    monkeypatch.setattr(runs, "run_importance", started)


def _torn_write(data=b"\x89PNG\r\n"):
    """A writer that puts a few bytes out, then fails as a full disk does (to a path or a file)."""

    def write(*args, **kw):
        target = next(a for a in args if isinstance(a, (str, os.PathLike)) or hasattr(a, "write"))
        if hasattr(target, "write"):
            target.write(data)
        else:
            with open(target, "wb") as fh:
                fh.write(data)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    return write


def _intact(path, before):
    folder = os.path.dirname(path)
    return open(path, "rb").read() == before and not [n for n in os.listdir(folder) if n.endswith(".tmp")]


# -- export ---------------------------------------------------------------------------------


def test_export_refuses_outputs_that_are_the_runs_or_the_datasets_files(run_copy, tiny_dataset, capsys):
    export = _script("export.py")["main"]
    run = str(run_copy)
    theirs = [os.path.join(run, n) for n in ("avatar.npz", "checkpoint.npz", "config.json", "metrics.jsonl")]
    theirs = [p for p in theirs if os.path.exists(p)]
    theirs += [os.path.join(tiny_dataset, "transforms_train.json")]
    theirs += [os.path.join(run, "..", "run", "avatar.npz")]  # another spelling of the same file
    assert len(theirs) >= 4
    for option in ("--stream", "--ply"):
        for path in theirs:
            before = open(path, "rb").read()
            rc = export(["--run", run, option, path, "--max-views", "2"])
            err = capsys.readouterr().err
            assert rc == 2 and f"error: {option} {path}: a file of the " in err, (option, path, err)
            assert open(path, "rb").read() == before
    # An earlier export in the run folder is replaced as before.
    assert export(["--run", run, "--ply", os.path.join(run, "f.ply"), "--max-views", "2"]) == 0
    assert export(["--run", run, "--ply", os.path.join(run, "f.ply"), "--max-views", "2"]) == 0


# -- export and evaluate: one stream for the same options -------------------------------------


@pytest.fixture(scope="module")
def exported_and_evaluated(tiny_run, tmp_path_factory):
    """A run exported (--stream, default options), then evaluated with --embed-template and a
    curve of 8 points (12.5 % steps)."""
    from progressive_avatars.core.evaluate.report import ReportOptions, build_report

    base = tmp_path_factory.mktemp("embedded")
    run = base / "run"
    shutil.copytree(tiny_run, run)
    export = _script("export.py")["main"]
    assert export(["--run", str(run), "--stream", str(base / "export.pavs")]) == 0
    opts = ReportOptions(
        run=str(run),
        out=str(base / "report"),
        budgets=(100,),
        strips=(100,),
        views=1,
        curve_points=8,
        curve_views=1,
        embed_template=True,
        progress=False,
    )
    build_report(opts)
    return base, run


def test_export_writes_the_bytes_evaluate_scores_with_embed_template(exported_and_evaluated):
    """export.py's stream embeds the template (the docs said evaluate wrote "the same bytes when
    export.py wrote it with the same options", which held only with evaluate's --embed-template)."""
    from progressive_avatars.core.stream.reader import read_stream

    base, run = exported_and_evaluated
    assert (run / "avatar.pavs").read_bytes() == (base / "export.pavs").read_bytes()
    assert read_stream(str(base / "export.pavs")).num_gaussians > 0  # no mesh needed to read it
    for name in ("export.py", "evaluate.py"):
        text = open(os.path.join(ROOT, "scripts", name)).read()
        assert "--embed-template" in text and "same bytes when\nexport.py wrote it with the same options" not in text
    demo = open(os.path.join(ROOT, "scripts", "run_demo.sh")).read()
    # the demo leaves the run the exported (self-contained) stream, not the report's
    assert demo.index("scripts/evaluate.py") < demo.index("scripts/export.py")


def test_report_curve_labels_keep_fractional_percents(exported_and_evaluated):
    base, _ = exported_and_evaluated
    md = (base / "report" / "report.md").read_text()
    line = next(ln for ln in md.splitlines() if ln.startswith("12.5: "))
    labels = [item.split(":")[0] for item in line.split(", ")]
    assert labels == ["12.5", "25", "37.5", "50", "62.5", "75", "87.5", "100"], line


# -- evaluate ---------------------------------------------------------------------------------


def test_report_checks_every_other_run_up_front(tiny_run, tmp_path, no_rendering):
    from progressive_avatars.core.evaluate.report import ReportOptions, build_report

    empty = tmp_path / "empty"
    empty.mkdir()
    missing = str(tmp_path / "missing")
    out = tmp_path / "out"
    refined = tmp_path / "refined"  # a run trained with --refine-flame: scored on other meshes
    refined.mkdir()
    shutil.copy(os.path.join(tiny_run, "avatar.npz"), refined / "avatar.npz")
    np.savez(refined / "flame_refined.npz", timesteps=np.arange(2))
    for kw, says in (
        (dict(compare=(f"r={refined}",)), f"--compare {refined}: trained with other FLAME refinement"),
        (dict(compare=("runs/x",)), "--compare runs/x: expected NAME=RUN"),
        (dict(compare=(f"a={tiny_run}", "=" + tiny_run)), f"--compare ={tiny_run}: expected NAME=RUN"),
        (dict(compare=(f"a={empty}",)), f"--compare {empty}: {empty / 'avatar.npz'}: no trained avatar"),
        (dict(budget_compare=("b",)), "--budget-compare b: expected NAME=RUN"),
        (dict(budget_compare=(f"b={missing}",)), f"--budget-compare {missing}: not a run folder"),
        (dict(no_coarse_run=missing), f"--no-coarse-run {missing}: not a run folder"),
        (dict(paper_table=True, finest_only=str(empty)), f"--finest-only {empty}: "),
        (dict(paper_table=True, finest_only=tiny_run, multi_level=missing), f"--multi-level {missing}: "),
        (dict(paper_table=True, uniform=(tiny_run,)), f"--uniform {tiny_run}: expected NAME=RUN"),
        (dict(paper_table=True, adaptive=(f"a_seed1={missing}",)), f"--adaptive {missing}: not a run folder"),
    ):
        with pytest.raises(ValueError) as exc:
            build_report(ReportOptions(run=tiny_run, out=str(out), progress=False, **kw))
        assert str(exc.value).startswith(says), (kw, str(exc.value))
        assert not out.exists()


def test_evaluate_checks_run_and_benchmarks_before_making_out(tiny_run, tmp_path, capsys, no_rendering):
    evaluate = _script("evaluate.py")["main"]
    out = tmp_path / "out"
    assert evaluate(["--run", str(tmp_path / "typo"), "--out", str(out)]) == 2
    assert "no trained avatar" in capsys.readouterr().err and not out.exists()
    assert evaluate(["--run", tiny_run, "--out", str(out), "--compare", "runs/x"]) == 2
    assert "error: --compare runs/x: expected NAME=RUN" in capsys.readouterr().err and not out.exists()
    for bench, says in ((tmp_path, "a folder"), (tmp_path / "no" / "b.md", "no folder")):
        rc = _exit_code(lambda: evaluate(["--run", tiny_run, "--out", str(out), "--benchmarks", str(bench)]))
        err = capsys.readouterr().err
        assert rc == 2 and f"error: --benchmarks {bench}: {says}" in err, err
        assert not out.exists()


# -- make_synthetic ---------------------------------------------------------------------------


def test_make_synthetic_checks_its_paths_first_and_writes_pictures_in_their_format(tmp_path, capsys):
    from PIL import Image

    main = _script("make_synthetic.py")["main"]
    small = ["--resolution", "8", "--cameras", "2", "--sequences", "2", "--frames", "1", "--supersample", "1"]
    small += ["--template-subdivisions", "1", "--quiet"]
    afile = tmp_path / "afile"
    afile.write_text("x")
    ds = tmp_path / "ds"
    for args, says in (
        (["--out", str(afile)], f"--out {afile}: a file, not a dataset folder"),
        (["--out", str(afile / "sub")], f"--out {afile / 'sub'}: under {afile}, which is not a folder"),
        (["--out", str(ds), "--resolution-scale", "inf"], "--resolution-scale must be a positive number"),
        (["--out", str(ds), "--contact-sheet", str(tmp_path)], f"--contact-sheet {tmp_path}: a folder"),
        (
            ["--out", str(ds), "--contact-sheet", str(tmp_path / "s.xyz")],
            f"--contact-sheet {tmp_path / 's.xyz'}: not an image",
        ),
        (["--out", str(ds), "--closeup", str(afile / "c.png")], f"--closeup {afile / 'c.png'}: under {afile}"),
    ):
        rc = _exit_code(lambda: main(["make_synthetic.py", *args, *small]))
        err = capsys.readouterr().err
        assert rc == 2 and f"error: {says}" in err, (args, err)
        assert not ds.exists() and afile.read_text() == "x"
    sheet = tmp_path / "pics" / "sheet.jpg"
    assert main(["make_synthetic.py", "--out", str(ds), "--contact-sheet", str(sheet), *small]) == 0
    with Image.open(sheet) as im:
        assert im.format == "JPEG"  # it was the PNG's bytes under a .jpg name


# -- build_extension, splat_look --------------------------------------------------------------


def test_build_extension_refuses_an_out_that_is_a_file(tmp_path, capsys):
    main = _script("build_extension.py")["main"]
    afile = tmp_path / "afile"
    afile.write_text("x")
    for out in (afile, afile / "dist"):
        rc = _exit_code(lambda: main(["--out", str(out), "--blender-ext", str(afile)]))
        err = capsys.readouterr().err
        assert rc == 2 and f"error: --out {out}: {afile} is a file, not a folder" in err, err


def test_build_extension_names_a_missing_blender_ext(tmp_path, capsys):
    """A --blender-ext path that is not a file is named (it said "blender_ext.py not found: pass
    --blender-ext" to a user who had passed it, and exited 1 without "error:")."""
    main = _script("build_extension.py")["main"]
    missing = tmp_path / "blender" / "blender_ext.py"
    for tool in (missing, tmp_path):  # no such file; a folder
        rc = _exit_code(lambda: main(["--out", str(tmp_path / "dist"), "--blender-ext", str(tool)]))
        err = capsys.readouterr().err
        assert rc == 2 and f"error: --blender-ext {tool}: not a file" in err, err
    assert not (tmp_path / "dist").exists()


def test_splat_look_refuses_size_below_1_and_removes_blenders_user_folder(tmp_path, own_tmp, capsys, monkeypatch):
    g = _script("splat_look.py")
    out = tmp_path / "look"
    rc = _exit_code(
        lambda: g["main"](["--run", str(tmp_path), "--data", str(tmp_path), "--out", str(out), "--size", "0"])
    )
    assert rc == 2 and "error: --size" in capsys.readouterr().err and not out.exists()
    for bad in (str(tmp_path), str(tmp_path / "look.txt")):  # a folder; an extension PIL cannot write
        rc = _exit_code(
            lambda: g["main"](
                ["--run", str(tmp_path), "--data", str(tmp_path), "--out", str(out), "--side-by-side", bad]
            )
        )
        assert rc == 2 and "error: --side-by-side" in capsys.readouterr().err and not out.exists()

    def blender_fails(cmd, **kw):
        return subprocess.CompletedProcess(cmd, 1, "", "no bpy here")

    monkeypatch.setattr(subprocess, "run", blender_fails)
    with pytest.raises(RuntimeError, match="Blender child failed"):
        g["_blender_render"](ROOT, {}, str(out))
    assert os.listdir(own_tmp) == []


# -- atomic pictures and arrays ---------------------------------------------------------------


def test_full_resolution_strip_write_is_atomic(tmp_path, monkeypatch):
    from PIL import Image

    from progressive_avatars.core.evaluate import plots

    class Renderer:
        views = [0]

        class Sample:
            image = np.zeros((16, 12, 3), np.float32)

        dataset = [Sample()]

        def render(self, view, ids):
            return np.zeros((16, 12, 3), np.float32), None

        def first(self, n):
            return np.arange(n)

    class Info:
        def count_for_percent(self, b):
            return 1

    path = str(tmp_path / "strip.png")
    Image.new("RGB", (4, 4)).save(path)
    before = open(path, "rb").read()
    monkeypatch.setattr(Image.Image, "save", _torn_write())
    with pytest.raises(OSError):
        plots.full_resolution_strip(path, Renderer(), Info(), [100.0])
    assert _intact(path, before)


def test_synthetic_pictures_are_written_atomically(tiny_dataset, tmp_path, monkeypatch):
    from PIL import Image

    from progressive_avatars.core.synthetic import dataset

    path = str(tmp_path / "picture.png")
    Image.new("RGB", (4, 4)).save(path)
    before = open(path, "rb").read()
    monkeypatch.setattr(Image.Image, "save", _torn_write())
    for write in (
        lambda: dataset.contact_sheet(tiny_dataset, path, rows=2),
        lambda: dataset.render_closeup(path, height=8, supersample=1),
    ):
        with pytest.raises(OSError):
            write()
        assert _intact(path, before)


def test_render_job_writes_its_image_atomically(tmp_path, monkeypatch):
    from progressive_avatars.core.bridge.render_job import render_job
    from progressive_avatars.core.render import rasterize

    monkeypatch.setattr(rasterize, "render_numpy", lambda *a, **k: (np.zeros((2, 3, 3)), np.zeros((2, 3))))
    job = tmp_path / "job.npz"
    z = np.zeros((1, 3), np.float32)
    g = dict(means=z, quats=np.zeros((1, 4), np.float32), scales=z, opacities=np.zeros(1, np.float32), colors=z)
    np.savez(job, R=np.eye(3), t=np.zeros(3), intr=[10.0, 10.0, 1.5, 1.0], size=[3, 2], **g)
    out = str(tmp_path / "image.npy")
    np.save(out, np.ones((2, 3, 4), np.float32))
    before = open(out, "rb").read()
    monkeypatch.setattr(np, "save", _torn_write(b"\x93NUMPY"))
    with pytest.raises(OSError):
        render_job(str(job), out)
    assert _intact(out, before)


def test_evaluation_scores_the_stream_it_wrote_when_another_process_replaces_it(tiny_run, tmp_path, monkeypatch):
    """evaluate.py wrote RUN/avatar.pavs and read it back: an export or another evaluation of the
    same run replacing the file in between (run at once on one run) made the report describe the
    other stream (its size, template embedded or not) under this one's options."""
    import contextlib

    from progressive_avatars.core.evaluate.report import ReportOptions, build_report
    from progressive_avatars.core.io import atomic
    from progressive_avatars.core.stream import writer

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    real = atomic.atomic_open

    @contextlib.contextmanager
    def and_then_an_export(path, *a, **k):
        with real(path, *a, **k) as fh:
            yield fh
        if os.path.basename(path) == "avatar.pavs":  # another process's export lands right after
            with open(path, "ab") as out:
                out.write(b"\0" * 5000)

    monkeypatch.setattr(atomic, "atomic_open", and_then_an_export)
    monkeypatch.setattr(writer, "atomic_open", and_then_an_export)
    opts = ReportOptions(
        run=str(run),
        out=str(tmp_path / "report"),
        budgets=(100,),
        strips=(100,),
        views=1,
        curve_points=4,
        curve_views=1,
        progress=False,
    )
    report = build_report(opts)
    assert report["stream_bytes"] == os.path.getsize(run / "avatar.pavs") - 5000  # its own bytes, not the file's
