"""Undo, redo and file loads against what lives outside the scene's data, in a Blender that
has nothing but Blender.

One bpy session (tests/blender_scenarios/undo_and_reload.py, own BLENDER_USER_* folders as in
test_blender_extension, plyfile/trimesh/PIL/scipy/torch/numba unimportable): a training in
progress across undo and across saving and reopening the file, depth colours' view shading
across undo/redo and reopening, the splats' focal length (dilation) without Splat Render
Settings, imports from Edit Mode and of a splat PLY, and the depth filter in the legend's terms.
"""

import os
import shutil
import textwrap

import numpy as np
import pytest

from tests.test_blender_extension import _bpy_dir, make_inputs, run_scenario, scenario_step

pytestmark = pytest.mark.blender

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BLOCKED = ("plyfile", "trimesh", "PIL", "scipy", "torch", "numba")
SCENARIO = os.path.join(ROOT, "tests", "blender_scenarios", "undo_and_reload.py")  # run in place


def _coarse_inputs(out):
    """A small sphere sequence and a stream whose forest has coarse levels above the template."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.stream.writer import write_stream
    from progressive_avatars.core.synthetic.shapes import random_forest, sphere_mesh

    rng = np.random.default_rng(3)
    v, f = sphere_mesh(10, 14, radius=0.1)
    np.savez(os.path.join(out, "coarse_seq.npz"), vertices=np.stack([v, v * 1.01]).astype(np.float32), faces=f)
    forest = random_forest(f, rng, depth=3, frac=0.4, coarse_from=v, stand_ins=True)
    assert forest.num_coarse_levels >= 2
    av = Avatar.initial(forest)
    av.d_log_scale[:] = -1.3
    av.opacity_logit[:] = 1.0
    write_stream(
        os.path.join(out, "coarse.pavs"), av, importance=rng.random(forest.num_faces), quantize=False, vertices=v
    )


def _splat_ply(out):
    from progressive_avatars.core.io.ply import write_ply

    rng = np.random.default_rng(1)
    n = 40
    q = rng.normal(size=(n, 4))
    write_ply(
        os.path.join(out, "splats.ply"),
        {
            "means": rng.normal(0, 0.1, (n, 3)),
            "quats": q / np.linalg.norm(q, axis=1, keepdims=True),
            "scales": np.full((n, 3), 0.01),
            "opacities": np.full(n, 0.8),
            "colors": np.full((n, 3), 0.5),
        },
    )


def _trainers(out, stream):
    with open(os.path.join(out, "long_train.py"), "w") as fh:  # ~8 s unless stopped
        fh.write(
            textwrap.dedent("""
            import time
            for i in range(1, 81):
                print(f'it {i}/80 loss 0.1', flush=True)
                time.sleep(0.1)
        """)
        )
    with open(os.path.join(out, "quick_train.py"), "w") as fh:
        fh.write(
            textwrap.dedent(f"""
            import argparse, os, shutil
            p = argparse.ArgumentParser(); p.add_argument('--data'); p.add_argument('--out')
            a, _ = p.parse_known_args(); os.makedirs(a.out, exist_ok=True)
            print('it 1/1 loss 0.1', flush=True)
            shutil.copy({stream!r}, os.path.join(a.out, 'avatar.pavs'))
        """)
        )


@pytest.fixture(scope="module")
def rep(tmp_path_factory):
    _bpy_dir()
    tmp = str(tmp_path_factory.mktemp("blender_undo"))
    out = os.path.join(tmp, "out")
    os.makedirs(out)
    _, stream, _, _ = make_inputs(out)
    _coarse_inputs(out)
    _splat_ply(out)
    _trainers(out, stream)
    r, proc = run_scenario(SCENARIO, [ROOT, out, ",".join(BLOCKED)], "PA_UNDO", tmp)
    r["stdout"] = proc.stdout
    assert not r["blocked_loaded"], r["blocked_loaded"]
    shutil.rmtree(tmp, ignore_errors=True)
    return r


def test_undo_during_training_keeps_the_trainer_and_its_panel(rep):
    r = scenario_step(rep, "train_survives_undo")
    assert r["started"], r
    # Undo put the scene back to before the training; the live run shows again at once
    assert r["running_after_undo"] and r["progress_after_undo"] == r["progress_before"] > 0, r
    assert r["ticks_after_undo"] == [["PASS_THROUGH"]] * 3, r
    assert r["alive_after_undo"] and r["reports_after_undo"] == [], r
    assert r["progress_later"] >= r["progress_before"], r
    assert r["running_after_second_undo"] and r["second_undo_tick"] == ["PASS_THROUGH"], r
    assert r["alive_after_second_undo"], r
    assert "already running" in r["train_again"], r["train_again"]


def test_cancel_still_stops_a_training_that_lived_through_undo(rep):
    r = scenario_step(rep, "train_survives_undo")
    assert r["cancel"] == ["FINISHED"] and r["cancel_tick"] == ["CANCELLED"], r
    assert r["reports"] == [["WARNING", "Training cancelled"]], r["reports"]
    assert r["exit_after_cancel"] is not None, "the trainer still runs after Cancel"
    assert not r["running_after_cancel"] and r["timers"] == ["timer"], r


def test_a_file_saved_mid_training_reopens_not_running(rep):
    r = scenario_step(rep, "file_load_ends_training")
    assert r["started"], r
    assert not r["running"] and r["progress"] == 0.0, r
    assert "saved while a training ran" in r["message"], r["message"]
    assert r["train"] == ["FINISHED"], r["train"]  # not refused as "already running"
    assert not r["running_after_train"]


def test_a_file_load_ends_the_training_it_leaves(rep):
    r = scenario_step(rep, "file_load_ends_training")
    assert r["exit"] is not None, "the trainer outlived the file it trained for"
    assert r["tick"] == ["CANCELLED"], r["tick"]
    assert r["reports"] == [["WARNING", "Training stopped: another file was opened"]], r["reports"]


def test_undoing_depth_colours_restores_the_view_shading(rep):
    r = scenario_step(rep, "depth_colours_undo")
    assert r["show"] == ["FINISHED"] and r["views_shown"] == ["VERTEX"], r
    assert not r["shown_after_undo"] and r["views_after_undo"] == ["MATERIAL"], r
    assert r["shown_after_redo"] and r["views_after_redo"] == ["VERTEX"], r
    assert r["hide"] == ["FINISHED"] and r["views_after_hide"] == ["MATERIAL"], r


def test_depth_colours_across_reopen_and_undo(rep):
    r = scenario_step(rep, "depth_colours_reopened")
    assert r["shown_reopened"] and r["views_reopened"] == ["VERTEX"], r
    assert r["hide"] == ["FINISHED"] and r["views_hidden"] == ["MATERIAL"], r
    assert r["shown_undo"] and r["views_undo"] == ["VERTEX"], r


def test_splat_focal_is_the_scene_cameras_without_splat_render_settings(rep):
    r = scenario_step(rep, "splat_focal")
    f, half = r["camera_focal"], r["camera_focal_half"]
    assert abs(half - f / 2) < 1e-3 * f
    assert len(r["after_load"]) == 2 and all(abs(v - f) < 1e-3 * f for v in r["after_load"]), r
    assert r["render_pre_handlers"] == 1
    assert all(abs(v - half) < 1e-3 * half for v in r["after_render_pre"]), r  # the render's size
    assert "no camera" in r["warning_no_camera"] and "dilation" in r["warning_no_camera"], r
    assert r["warning_with_camera"] == "", r
    assert "splat focal length not set" not in rep["stdout"].lower()


def test_depth_only_counts_depth_as_the_legend_does(rep):
    r = scenario_step(rep, "depth_only_in_legend_terms")
    k = r["coarse_levels"]
    assert r["load"] == ["FINISHED"] and k >= 2, r
    legend_depths = {d for d, _ in r["legend"]}
    assert {0, 1} <= legend_depths, r["legend"]
    assert 0 < r["all"] <= r["total"]  # (coarse stand-ins retire once what replaces them arrived)
    for d, shown, want, read_back in r["by_depth"]:
        assert want > 0, (d, r["by_depth"])
        assert shown == want and read_back == d, (d, shown, want, read_back)
    assert r["on"] and r["level_only"] == 0, r  # last asked: depth -k, the coarsest level (absolute 0)
    assert r["off_shown"] == r["all"] and r["off_level_only"] == -1, r
    assert r["old_file_depth"] == 1, r  # level_only stored absolute (k + 1): depth 1


def test_import_from_edit_mode_leaves_no_mesh_in_edit_mode(rep):
    r = scenario_step(rep, "import_from_edit_mode")
    assert r["result"] == ["FINISHED"], r["result"]
    assert r["not_in_object_mode"] == [] and r["active"].startswith("seq"), r
    assert "injected failure" in r["failed"], r["failed"]
    assert r["failed_added"] == {} and r["failed_mode"] == "EDIT_MESH" and r["failed_active"] == "Cube", r


def test_a_splat_ply_is_refused_as_a_sequence(rep):
    r = scenario_step(rep, "splat_ply_as_sequence")
    assert "splats.ply" in r["result"] and "no faces" in r["result"], r["result"]
    assert "3DGS" in r["result"] and "Traceback" not in r["result"], r["result"]
    assert r["added"] == {}, r["added"]


def test_depth_panel_of_ply_splats_says_they_have_no_depth(rep):
    r = scenario_step(rep, "depth_panel_of_ply_splats")
    assert r["result"] == ["FINISHED"], r
    assert r["panel"] == ["PLY splats carry no subdivision depth"], r["panel"]


def test_budget_steps_bind_no_placed_point_again(rep):
    r = scenario_step(rep, "budget_steps_keep_placed_points")
    assert r["load"] == ["FINISHED"] and r["depth_changes"] >= 2, r  # the steps rewrote the depth attribute
    assert r["down"] == [], r  # no Gaussian evaluated: all placed at this frame
    assert r["up"] == [r["total"]], r  # once, every Gaussian; the later steps show them
    assert r["frame"] == [r["count_50"]] and 0 < r["count_50"] < r["total"], r  # a frame: what it shows
    assert r["after_undo"] == [50.0, r["frame_at"]], r
    for key in ("misplaced_up", "misplaced_frame", "misplaced_undo"):
        assert r[key] < 1e-6, (key, r[key])


def test_shape_keys_only_mixes_relative_keys_as_blender_does(rep):
    r = scenario_step(rep, "shape_keys_mixed_as_blender_mixes_them")
    assert r["problem"] == "" and r["basis_vs_blender"] > 0.01, r  # the keys moved the mesh
    assert r["hand_vs_blender"] < 1e-6 and r["vs_blender"] < 1e-6 and r["vs_hand"] < 1e-6, r
    assert r["vertex_group"][0] and "'a' is limited to a vertex group" in r["vertex_group"][1], r
    assert r["absolute"][0] and "absolute shape keys" in r["absolute"][1], r


def test_points_not_placed_stay_hidden(rep):
    r = scenario_step(rep, "unplaced_points_stay_hidden")
    assert r["load"] == ["FINISHED"] and 0 < r["count_20"] < r["count_90"], r
    assert r["shown_20"] == r["count_20"], r
    assert r["shown_edit"] == r["count_20"] and "Edit Mode" in r["status_edit"], r  # the 20 % placed
    assert r["shown_after"] == r["count_90"], r
    n = r["vertices"]
    assert r["refresh_short"] is False and r["shown_short"] == 0, r
    assert r["status_short"].endswith(f"has {n - 1} vertices; the avatar needs {n}"), r


def test_linked_duplicates_show_their_own_points(rep):
    r = scenario_step(rep, "linked_duplicates_show_their_own_points")
    assert r["load"] == ["FINISHED"] and r["shared"], r
    for key in ("after_frame", "after_undo"):
        *misplaced, meshes = r[key]
        assert max(misplaced) < 1e-6 and meshes == 3, (key, r[key])


def test_save_copy_keeps_the_open_files_avatar_paths(rep):
    r = scenario_step(rep, "save_copy_keeps_avatar_paths")
    assert r["paths"][0].startswith("//") and r["paths"][1] == r["paths"][0], r
    for key in ("here", "copy"):
        status, misplaced = r[key]
        assert status == "" and misplaced < 1e-6, (key, r[key])


def test_an_appended_preview_finds_its_avatar(rep):
    r = scenario_step(rep, "previews_from_another_blend")
    assert r["load"] == ["FINISHED"] and r["library_path"] == "//assets/avatar.pavs", r
    for key in ("appended", "appended_older", "appended_reopened"):
        status, shown, misplaced = r[key]
        assert status == "" and shown > 0 and misplaced < 1e-6, (key, r[key])
    assert r["appended_path"] == "//../../library/assets/avatar.pavs", r  # relative to the file it is in now


def test_a_linked_preview_says_it_cannot_follow_and_an_overridden_one_follows(rep):
    r = scenario_step(rep, "previews_from_another_blend")
    status, shown, _ = r["linked"]
    assert "is linked from head.blend" in status and "Make Local" in status and shown == 0, r["linked"]
    status, shown, misplaced = r["overridden"]
    assert status == "" and shown > 0 and misplaced < 1e-6, r["overridden"]
    status = r["overridden_budget_status"]  # the head's depth cannot be written: said, not raised
    assert status.startswith("Depth not shown:") and "linked library" in status, status
    _, shown, misplaced = r["overridden_budget"]
    assert 0 < shown < r["overridden"][1] and misplaced < 1e-6, r["overridden_budget"]


def test_a_deleted_mesh_is_said_on_frame_change(rep):
    r = scenario_step(rep, "deleted_mesh_said_on_frame_change")
    status, shown, count = r["removed"]
    assert status == "No mesh bound" and shown == count > 0, r  # all placed at load: still shown
    status, same_mesh, misplaced = r["undone"]
    assert status == "" and same_mesh and misplaced < 1e-6, r


def test_a_mesh_deleted_in_the_3d_view_is_said_deleted(rep):
    r = scenario_step(rep, "deleted_mesh_said_on_frame_change")
    assert r["delete"] == ["FINISHED"], r
    kept, status, shown, count, panel, colour = r["deleted"]
    assert kept, r  # the orphan Blender keeps for the preview's pointer: not a mesh to follow
    assert status == "No mesh bound" and shown == count > 0, r
    assert panel == ["The preview's mesh was deleted"], panel
    assert "its mesh was deleted" in colour, colour  # Colour by Depth: nothing painted on the orphan
    status, misplaced = r["delete_undone"]
    assert status == "" and misplaced < 1e-6, r


def test_depth_is_written_once_the_mesh_leaves_edit_mode(rep):
    r = scenario_step(rep, "depth_written_after_edit_mode")
    count, total = r["counts"]
    assert r["load"] == ["FINISHED"] and 0 < count < total, r
    assert r["in_edit"].startswith("Depth not shown:") and "leave Edit Mode first" in r["in_edit"], r
    assert r["after"] == ["", True, True], r  # the 20 % depth and legend (the 100 % ones stayed)


def test_a_preview_left_apart_from_its_mesh_says_so(rep):
    r = scenario_step(rep, "apply_transform_on_the_mesh")
    assert r["load"] == ["FINISHED"] and r["apply"] == ["FINISHED"], r
    for key in ("applied", "other_parent"):
        status, apart, misplaced = r[key]  # placed on the mesh, drawn elsewhere
        assert apart and "is not where seq" in status and misplaced < 1e-6, (key, r[key])
    for key in ("undone", "cleared"):
        status, apart, misplaced = r[key]
        assert not apart and status == "" and misplaced < 1e-6, (key, r[key])
    assert r["other_parent_at_once"] == r["other_parent"][0], r
    assert r["reload"] == ["FINISHED"], r
    bound, children = r["bound_after_reload"]
    assert len(bound) == 1 and bound == children, r["bound_after_reload"]  # the re-parented one replaced


def test_relative_paths_off_stores_absolute_and_still_remaps_relative_ones(rep):
    r = scenario_step(rep, "relative_paths_off")
    assert r["load_True"] == r["load_False"] == ["FINISHED"], r
    relative, absolute = r["stored"]
    assert relative == "//../avatar.pavs" and os.path.isabs(absolute) and not absolute.startswith("//"), r["stored"]
    assert r["reopened"] == [["//../../avatar.pavs", ""], [absolute, ""]], r["reopened"]


def test_the_head_finds_its_preview_after_clear_parent(rep):
    r = scenario_step(rep, "preview_unparented_from_its_head")
    assert r["load"] == ["FINISHED"] and r["clear"] == ["FINISHED"], r
    unparented, name, found = r["found"]
    assert unparented and found == name, r["found"]  # the head selected: its preview's panel
    assert r["polls"] == [True] * 4, r["polls"]  # Avatar and Depth panels, Colour by Depth, Export PLY


def test_moving_the_head_of_an_unparented_preview_says_at_once_that_they_are_apart(rep):
    r = scenario_step(rep, "preview_unparented_from_its_head")
    name = r["found"][1]
    # moved, back, rotated, back, parented in place, its parent moved, back
    assert [apart for _, apart in r["moves"]] == [True, False, True, False, False, True, False], r["moves"]
    assert [apart for _, apart in r["moves_uncached"]] == [True, False], r["moves_uncached"]
    for status, apart in r["moves"] + r["moves_uncached"]:
        assert (f"{name} is not where seq" in status) == apart and (status == "") == (not apart), r


def test_two_previews_on_one_head_show_the_depth_of_one_and_say_which(rep):
    r = scenario_step(rep, "two_previews_on_one_head")
    pv, dup = r["names"]
    assert r["load"] == ["FINISHED"] and r["depths_differ"], r  # 100 % and 20 % colour faces differently
    # [depth is pv's, is dup's, legend is pv's, is dup's, depth_preview, shown]
    assert r["dup_moved"] == [True, False, True, False, pv, False], r  # the Alt+D copy's budget: not its
    assert r["head_panel"] == pv, r
    assert f"Depth of {pv} at 100.0 %" in r["dup_panel"] and "[Colour by Depth]" in r["dup_panel"], r["dup_panel"]
    assert r["show_dup"] == ["FINISHED"] and r["shown_dup"] == [False, True, False, True, dup, True], r
    assert r["pv_moved"] == [False, True, False, True, dup, True], r  # pv at 60 %: dup's stays shown
    assert f"Depth of {dup} at 20.0 %" in r["pv_panel"] and "[Colour by Depth]" in r["pv_panel"], r["pv_panel"]
    assert r["show_pv"] == ["FINISHED"] and r["shown_pv"] == [True, False, True, False, pv, True], r  # switched
    assert r["hide"] == ["FINISHED"] and r["hidden"][4:] == [pv, False], r
    # The chosen one deleted: its legend is said to be a gone preview's until a budget moves
    assert f"Depth of {pv}, not a preview of this mesh now: move a budget" in r["orphan_panel"], r["orphan_panel"]
    assert r["after_delete"] == [False, True, False, True, dup, False], r
    assert not any(t.startswith("Depth of") for t in r["taken_panel"]), r["taken_panel"]
    # Load Avatar over a preview: the new one, made beside it under another name, then renamed
    reload, made_as, named, recorded = r["reloaded"]
    assert reload == [["FINISHED"]] * 2 and made_as != named and recorded == named, r["reloaded"]
