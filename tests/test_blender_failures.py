"""Operators on their failure paths, in a Blender that has nothing but Blender.

One bpy session (tests/blender_scenarios/operator_failures.py, own BLENDER_USER_* folders as in
test_blender_extension, plyfile/trimesh/PIL/scipy/torch/numba unimportable) drives them: a
trainer whose log holds a byte that is not UTF-8, imports and avatars in Edit Mode, Colour by
Depth on a mesh edited to another face count. A failed operator must say what went wrong,
naming the object, and leave the scene as it was.
"""

import os
import textwrap

import pytest

from tests.test_blender_extension import _bpy_dir, make_inputs, make_rig_inputs, run_scenario, scenario_step

pytestmark = pytest.mark.blender

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BLOCKED = ("plyfile", "trimesh", "PIL", "scipy", "torch", "numba")
LATIN1 = b"warning: cannot open /data/caf\xe9/img.png\n"  # a Latin-1 path in a log line


SCENARIO = os.path.join(
    ROOT, "tests", "blender_scenarios", "operator_failures.py"
)  # run in place: it imports stock_blender


def _write_trainers(out, stream):
    with open(os.path.join(out, "latin1_train.py"), "w") as fh:
        fh.write(
            textwrap.dedent(f"""
            import argparse, os, shutil, sys
            p = argparse.ArgumentParser(); p.add_argument('--data'); p.add_argument('--out'); p.add_argument('--preset')
            a = p.parse_args(); os.makedirs(a.out, exist_ok=True)
            print('it 1/2 loss 0.1', flush=True)
            sys.stdout.buffer.write({LATIN1!r}); sys.stdout.flush()
            print('it 2/2 loss 0.05', flush=True)
            shutil.copy({stream!r}, os.path.join(a.out, 'avatar.pavs'))
        """)
        )
    with open(os.path.join(out, "latin1_chatty.py"), "w") as fh:  # far more than a pipe holds
        fh.write(
            textwrap.dedent(f"""
            import sys
            sys.stdout.buffer.write({LATIN1!r}); sys.stdout.flush()
            for i in range(1, 5001):
                print(f'it {{i}}/5000 loss 0.1 ' + 'x' * 60, flush=True)
            print('done', flush=True)
        """)
        )
    with open(os.path.join(out, "fails_loudly.py"), "w") as fh:  # its error comes after ~350 KB of log
        fh.write(
            textwrap.dedent("""
            import sys
            for i in range(1, 5001):
                print(f'it {i}/5000 loss 0.1 ' + 'x' * 60)
            print('ValueError: the last line says why', flush=True)
            sys.exit(3)
        """)
        )
    with open(os.path.join(out, "slow_train.py"), "w") as fh:
        fh.write(
            textwrap.dedent("""
            import time
            for i in range(1, 11):
                print(f'it {i}/10 loss 0.1', flush=True)
                time.sleep(0.1)
        """)
        )


def _write_frame_folders(out, params_path, seq_path):
    """obj_frames/: 250 OBJ frames of the sequence's mesh; obj_broken/: 8 of them, the 4th no
    mesh; ga/flame_param/: the tracked parameters as one GaussianAvatars npz per frame."""
    import numpy as np

    with np.load(seq_path) as z:
        v, f = z["vertices"][0], z["faces"]
    faces = "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f.tolist())
    for folder, frames in (("obj_frames", 250), ("obj_broken", 8)):
        os.makedirs(os.path.join(out, folder))
        for t in range(frames):
            text = "".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in (v * (1 + 0.001 * t)).tolist()) + faces
            if folder == "obj_broken" and t == 3:
                text = "this is not an obj file\nv 1 2\n"
            with open(os.path.join(out, folder, f"frame_{t:04d}.obj"), "w") as fh:
                fh.write(text)
    with np.load(params_path) as z:
        prm = {k: z[k] for k in z.files}
    os.makedirs(os.path.join(out, "ga", "flame_param"))
    for t in range(len(prm["expr"])):
        frame = {k: (v if k in ("shape", "static_offset") else v[t : t + 1]) for k, v in prm.items()}
        np.savez(os.path.join(out, "ga", "flame_param", f"{t:05d}.npz"), **frame)


def _other_streams(stream, out):
    """The same Gaussians in another order (reordered.pavs), and the first 60 % (shorter.pavs)."""
    import numpy as np

    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.stream.writer import write_stream

    av = read_stream(stream)
    n = av.num_gaussians
    write_stream(os.path.join(out, "reordered.pavs"), av, importance=np.linspace(0, 1, n), quantize=False)
    short = read_stream(stream, percent=60.0)
    write_stream(
        os.path.join(out, "shorter.pavs"), short, importance=np.linspace(1, 0, short.num_gaussians), quantize=False
    )


@pytest.fixture(scope="module")
def rep(tmp_path_factory):
    _bpy_dir()
    tmp = str(tmp_path_factory.mktemp("blender_failures"))
    out = os.path.join(tmp, "out")
    os.makedirs(out)
    seq, stream, _, _ = make_inputs(out)
    _other_streams(stream, out)
    _, params = make_rig_inputs(out)
    _write_frame_folders(out, params, seq)
    _write_trainers(out, stream)
    r, _ = run_scenario(SCENARIO, [ROOT, out, ",".join(BLOCKED)], "PA_FAILURES", tmp)
    assert not r["blocked_loaded"], r["blocked_loaded"]
    return r


def test_train_survives_a_log_line_that_is_not_utf8(rep):
    r = scenario_step(rep, "train_non_utf8")
    assert r["first"] == ["FINISHED"], r["first"]
    assert not r["running"]
    assert r["message"] == "it 2/2 loss 0.05"
    assert r["second"] == ["FINISHED"], r["second"]  # not refused as "already running"


def test_train_is_not_left_running_when_reading_its_output_fails(rep):
    r = scenario_step(rep, "train_reader_fails")
    assert not r["running"]
    assert "reader failed" in r["result"]


def test_modal_train_reader_survives_a_log_line_that_is_not_utf8(rep):
    r = scenario_step(rep, "train_modal_reader")
    assert r["exit"] == 0, "the trainer blocked on a pipe nobody read"
    assert r["lines"] == 5002
    assert "caf\ufffd" in r["first"]


def test_modal_train_reports_the_trainers_last_line(rep):
    r = scenario_step(rep, "train_modal_last_lines")
    assert r["result"] == ["CANCELLED"]
    assert r["reports"] == [["ERROR", "Training failed (exit 3): ValueError: the last line says why"]], r["reports"]
    assert not r["running"] and r["timers"] == ["timer"]


def test_modal_train_runs_on_while_another_scene_is_shown(rep):
    r = scenario_step(rep, "train_modal_other_scene")
    assert r["exit"] == 0, "the training was stopped"
    assert all(kind != "WARNING" or "cancelled" not in msg for kind, msg in r["reports"]), r["reports"]
    assert r["last"] == ["CANCELLED"] and r["ticks"] > 1, r
    # it ran to its end: the stand-in trainer writes no avatar, the one error
    assert len(r["reports"]) == 1 and r["reports"][0][1].startswith("Training finished but wrote no avatar"), r
    assert r["message"] == "it 10/10 loss 0.1"
    assert not r["running"] and not r["other_running"]


def test_modal_train_failing_inside_modal_stops_cleanly(rep):
    r = scenario_step(rep, "train_modal_raises")
    assert r["result"] == ["CANCELLED"], r["result"]
    assert r["reports"] == [["ERROR", "Training stopped: RuntimeError: reader failed"]], r["reports"]
    assert not r["running"] and r["timers"] == ["timer"]
    assert r["trainer_stopped"]


def test_rig_import_from_edit_mode(rep):
    r = scenario_step(rep, "rig_in_edit_mode")
    assert r["result"] == ["FINISHED"], r["result"]
    assert r["groups"] > 0


def test_failed_rig_import_leaves_the_scene_as_it_was(rep):
    r = scenario_step(rep, "rig_in_edit_mode")
    assert "Cannot import" in r["failed"] and "tracked_flame_params.npz" in r["failed"], r["failed"]
    assert "injected failure" in r["failed"] and "Traceback" not in r["failed"], r["failed"]
    assert r["failed_added"] == {}
    assert r["failed_mode"] == "EDIT_MESH"
    assert r["failed_active"] == r["cube"] and r["failed_selected"] == [r["cube"]]


def _updates(calls):
    """The percents shown, checked to be one begin over 0..100 (progress_begin's maximum is at
    most 9998) ... one end around them, whole and rising."""
    assert calls[:1] == [["begin", 0, 100]] and calls[-1:] == [["end"]], calls
    assert [c[0] for c in calls[1:-1]] == ["update"] * (len(calls) - 2), calls
    values = [c[1] for c in calls[1:-1]]
    assert values == sorted(values) and len(set(values)) == len(values), values
    assert all(isinstance(v, int) and 0 <= v <= 100 for v in values), values
    return values


def test_failed_sequence_import_leaves_the_scene_as_it_was(rep):
    r = scenario_step(rep, "sequence_import_fails_late")
    assert "Cannot import" in r["result"] and "seq.npz" in r["result"] and "injected failure" in r["result"], r
    assert r["added"] == {} and r["range"] == [5, 9], r
    assert _updates(r["progress"]) == [100], r["progress"]  # read (one file), then ended on the failure


def test_sequence_import_shows_its_progress(rep):
    r = scenario_step(rep, "import_progress_shown")
    assert r["obj"] == ["FINISHED"] and r["obj_frames"] == 250, r
    values = _updates(r["obj_progress"])
    # 250 files read: once per percent at most, up to 100 % (then ended)
    assert values[-1] == 100 and 50 < len(values) <= 101, values
    assert r["rig"] == ["FINISHED"], r["rig"]
    values = _updates(r["rig_progress"])  # one file per frame of the flame_param folder
    assert values == [12, 25, 37, 50, 62, 75, 87, 100], values


def test_failed_sequence_import_ends_its_progress(rep):
    r = scenario_step(rep, "import_progress_shown")
    assert "Cannot read sequence" in r["broken"] and "frame_0003.obj" in r["broken"], r["broken"]
    assert r["broken_added"] == {} and r["broken_range"] == [5, 9], r
    assert _updates(r["broken_progress"]) == [12, 25, 37], r["broken_progress"]  # 3 of 8 files read
    # an exception out of the operator: Blender reports it; the progress ended all the same
    assert "injected failure" in r["raised"], r["raised"]
    assert r["raised_added"] == {}, r["raised_added"]
    assert _updates(r["raised_progress"])[-1] == 100, r["raised_progress"]


def test_budget_shows_what_a_viewer_of_the_typed_percent_sees(rep):
    r = scenario_step(rep, "budget_and_replaced_file")
    assert r["load"] == ["FINISHED"], r["load"]
    assert r["crossing"] > 0  # percents whose 32-bit value would cross a record boundary exist
    for p, count, shown, want in r["budget_counts"]:
        assert count == want and shown == want, (p, count, shown, want)


def test_a_replaced_avatar_file_is_not_mixed_with_the_preview(rep):
    r = scenario_step(rep, "budget_and_replaced_file")
    assert "live.pavs changed since this preview was loaded" in r["changed_status"], r["changed_status"]
    assert r["changed_count"] == 0 and r["changed_shown"] == 0
    assert "point count does not match" in r["shorter_status"] and r["shorter_shown"] == 0, r
    assert r["reload"] == ["FINISHED"] and r["reload_status"] == "" and r["reload_shown"] > 0, r


def test_load_avatar_refuses_a_mesh_in_edit_mode(rep):
    r = scenario_step(rep, "load_in_edit_mode")
    assert "seq: leave Edit Mode first" in r["result"], r["result"]
    assert r["added"] == {} and r["attributes_kept"]


def test_budget_slider_on_a_mesh_in_edit_mode(rep):
    r = scenario_step(rep, "bound_mesh_in_edit_mode")
    assert r["load"] == ["FINISHED"], r["load"]
    assert r["apply_budget"] == "ok", r["apply_budget"]
    for key in ("status_slider", "status", "status_grow"):
        assert "Edit Mode" in r[key] and "modifiers" not in r[key], (key, r[key])


def test_depth_colours_refuse_a_mesh_in_edit_mode(rep):
    r = scenario_step(rep, "bound_mesh_in_edit_mode")
    assert "Colour by Depth: seq: leave Edit Mode first" in r["depth"], r["depth"]
    assert "Traceback" not in r["depth"]
    assert not r["depth_shown"] and r["depth_saved"] == "" and r["shading_kept"]


def test_budget_slider_on_a_preview_in_edit_mode(rep):
    r = scenario_step(rep, "preview_in_edit_mode")
    assert r["preview_edit"] and not r["mesh_edit"]
    assert r["apply_budget"] == "ok", r["apply_budget"]
    assert r["status"].startswith(r["preview"] + " is in Edit Mode"), r["status"]


def test_a_frame_changed_in_edit_mode_is_placed_on_leaving_it(rep):
    r = scenario_step(rep, "frame_change_in_edit_mode")
    assert r["frames_differ"] > 1e-3, r  # the two frames put the Gaussians in different places
    assert r["after_edit"] < 1e-6, r
    assert r["status"] == "", r["status"]


def test_failed_depth_colours_change_nothing(rep):
    r = scenario_step(rep, "depth_on_edited_mesh")
    assert not r["depth_shown"] and r["depth_saved"] == ""
    assert r["colour_attributes"] == [] and r["shading_kept"]
    assert r["result"].startswith("Error: Colour by Depth: seq: "), r["result"]
    assert "252" in r["result"] and "251" in r["result"]
    assert r["again"] == r["result"]  # still refused, not toggled "off"
