"""The training loop's bookkeeping and the decisions a step makes, checked against values worked
out by hand from the settings: on which iterations it grows, logs, evaluates, resets and
checkpoints, what a log row and the progress line show, what a resume writes and refuses, how
the position learning rate decays, what the opacity reset and the coarse weight touch, which
faces a step counts, when the stream order is measured again, which in-level prefixes are
drawn, which validation views an evaluation renders, and which settings a resume compares."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from progressive_avatars.core.avatar.avatar import Avatar
from progressive_avatars.core.train.policies import Growth, Supervision
from progressive_avatars.core.train.trainer import Trainer, _lengthened, config_for


def _bookkeeping_trainer(tiny_dataset, out, cfg, calls, resume=False):
    """A Trainer whose step, growth, evaluation and reset only record when the loop calls them:
    the step of iteration i (0-based) reports loss and PSNR i, so a log row's values say which
    steps it averaged."""
    tr = Trainer(tiny_dataset, out, cfg, resume=resume, check_data=False)
    tr.step = lambda: {"loss": float(tr.iteration), "psnr": float(tr.iteration)}
    tr._grow = lambda it: calls["grow"].append(it) or 0
    tr.evaluate = lambda n: calls["eval"].append(tr.iteration) or {"val_psnr": 1.0}
    tr.reset_opacity = lambda: calls["reset"].append(tr.iteration)
    tr.on_checkpoint = calls["checkpoint"].append
    return tr


def test_loop_grows_logs_evaluates_resets_and_checkpoints_on_its_schedule(tiny_dataset, tmp_path):
    """23 iterations, growth every 4 from 8 until 0.8 x 23 = 18.4: after 8, 12, 16. Resets every
    8 up to the last growth step (16, included): 8, 16. Logs every 5 and at the end, evaluations
    every 7 and at the end, checkpoints every 6 and at the end. A log row averages the PSNRs of
    the steps since the previous row and reports the last step's loss."""
    cfg = config_for(
        "tiny",
        iterations=23,
        grow_every=4,
        grow_start=8,
        grow_stop=0.8,
        log_every=5,
        eval_every=7,
        checkpoint_every=6,
        opacity_reset_every=8,
    )
    calls = {"grow": [], "eval": [], "reset": [], "checkpoint": []}
    tr = _bookkeeping_trainer(tiny_dataset, str(tmp_path / "run"), cfg, calls)
    tr.run(progress=False, stop_after=100)  # a stop past the end ends at the end
    assert tr.iteration == 23
    assert calls == {"grow": [8, 12, 16], "eval": [7, 14, 21, 23], "reset": [8, 16], "checkpoint": [6, 12, 18, 23]}
    rows = {r["iteration"]: r for r in map(json.loads, open(tmp_path / "run" / "metrics.jsonl"))}
    assert sorted(rows) == [5, 7, 8, 10, 14, 15, 16, 20, 21, 23]
    logged = {it: (r["loss"], r["train_psnr"]) for it, r in rows.items() if "train_psnr" in r}
    assert logged == {5: (4, 2), 10: (9, 7), 15: (14, 12), 20: (19, 17), 23: (22, 21)}
    assert [it for it, r in rows.items() if "val_psnr" in r] == [7, 14, 21, 23]
    assert {it: r["opacity_reset"] for it, r in rows.items() if "opacity_reset" in r} == {8: 0.01, 16: 0.01}


def test_a_run_stopped_by_an_error_names_its_last_checkpoint(tiny_dataset, tmp_path):
    """train.py's error line says which checkpoint a --resume continues from: the last one the
    loop wrote (every 6: 18), not the one it started from."""
    calls = {"grow": [], "eval": [], "reset": [], "checkpoint": []}
    cfg = config_for("tiny", iterations=23, checkpoint_every=6, eval_every=10**6)
    tr = _bookkeeping_trainer(tiny_dataset, str(tmp_path / "run"), cfg, calls)
    step = tr.step

    def failing_step():
        if tr.iteration == 20:
            raise FloatingPointError("stop")
        return step()

    tr.step = failing_step
    with pytest.raises(FloatingPointError):
        tr.run(progress=False)
    assert calls["checkpoint"] == [6, 12, 18] and tr.checkpoint_iteration == 18


@pytest.mark.parametrize("stop", [10, 12])
def test_a_resume_writes_the_log_and_avatar_of_the_uninterrupted_run(tiny_dataset, tmp_path, stop):
    """Stopped at 10 (a log row and a checkpoint) or 12 (a reset row, between log rows) and
    resumed: the log is the uninterrupted run's, row for row (the row at the checkpoint kept
    once, the next row averaging steps from both sides), the training time goes on from the
    checkpoint's, and the avatar of the stopped run says where it stopped."""
    cfg = config_for(
        "tiny", iterations=20, log_every=5, eval_every=10**6, checkpoint_every=10**6, opacity_reset_every=6
    )

    def rows(name):
        return [
            {k: v for k, v in json.loads(ln).items() if k != "seconds"}
            for ln in open(tmp_path / name / "metrics.jsonl")
        ]

    def calls():
        return {"grow": [], "eval": [], "reset": [], "checkpoint": []}

    _bookkeeping_trainer(tiny_dataset, str(tmp_path / "full"), cfg, calls()).run(progress=False)
    part = _bookkeeping_trainer(tiny_dataset, str(tmp_path / "part"), cfg, calls())
    part.run(progress=False, stop_after=stop)
    assert Avatar.load(tmp_path / "part" / "avatar.npz").meta["iterations"] == stop
    with pytest.raises(ValueError, match=f"past --iterations {stop - 1}"):
        Trainer(tiny_dataset, str(tmp_path / "part"), replace(cfg, iterations=stop - 1), resume=True)
    with open(tmp_path / "part" / "metrics.jsonl", "a") as fh:  # a torn row and one no run writes
        fh.write('[1, 2]\n{"iteration": 3')
    resumed = _bookkeeping_trainer(tiny_dataset, str(tmp_path / "part"), cfg, calls(), resume=True)
    assert resumed.iteration == stop and resumed.elapsed == part.elapsed > 0
    resumed.run(progress=False)
    assert rows("part") == rows("full")
    assert [r["iteration"] for r in rows("full")] == [5, 6, 10, 12, 15, 20]


def test_position_learning_rate_decays_over_the_run(tiny_dataset, tmp_path):
    """Step i (0-based) of an n-iteration run scales the position learning rate by
    lr_final_ratio ** (i / n): 1, 0.01 ** 0.25, 0.1, 0.01 ** 0.75 for 4 iterations; nothing else
    decays."""
    cfg = config_for("tiny", iterations=4, eval_every=10**6, checkpoint_every=10**6)
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), cfg, check_data=False)
    scales, real = [], tr.opt.step
    tr.opt.step = lambda params, lr_scale: scales.append(dict(lr_scale)) or real(params, lr_scale)
    tr.run(progress=False)
    assert [set(s) for s in scales] == [{"d_mu"}] * 4
    np.testing.assert_allclose([s["d_mu"] for s in scales], [1.0, 0.01**0.25, 0.1, 0.01**0.75], rtol=1e-12)


def test_opacity_reset_lowers_only_the_opacities_above_its_value(tiny_dataset, tmp_path):
    """3DGS's reset is min(opacity, 0.01): a Gaussian already fainter keeps its opacity."""
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), config_for("tiny", opacity_reset_every=10), check_data=False)
    logit = tr.model.params["opacity_logit"]
    want = np.resize([0.001, 0.005, 0.5, 0.99], logit.shape[0])
    with torch.no_grad():
        logit.copy_(torch.logit(torch.from_numpy(want)).reshape(logit.shape))
    tr.reset_opacity()
    got = torch.sigmoid(logit.detach()).double().numpy().reshape(-1)
    np.testing.assert_allclose(got, np.minimum(want, 0.01), rtol=1e-5)


def test_coarse_weight_weighs_the_coarse_levels_only(tiny_dataset, tmp_path):
    """coarse_weight 0 leaves the template level's loss as it is: the same first step as
    weighting the two coarse levels 0 by level_weights."""
    kw = dict(eval_every=10**6, checkpoint_every=10**6)
    a = Trainer(tiny_dataset, str(tmp_path / "a"), config_for("tiny", coarse_weight=0.0, **kw), check_data=False)
    b = Trainer(tiny_dataset, str(tmp_path / "b"), config_for("tiny", level_weights=(0, 0, 1), **kw), check_data=False)
    assert a.model.forest.num_coarse_levels == 2 and a.model.forest.max_level == 2
    assert a.step()["loss"] == b.step()["loss"]


def test_growth_statistics_count_a_step_only_for_the_faces_it_drew(tiny_dataset, tmp_path):
    """A face's growth gradient is its mean over the steps that drew it: a Gaussian fainter than
    1/255 draws nothing (3DGS's alpha floor), so a step adds neither gradient nor count to it."""
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), config_for("tiny", coarse_levels=()), check_data=False)
    faint = np.arange(0, tr.model.num_faces, 2)
    with torch.no_grad():
        tr.model.params["opacity_logit"][faint] = float(np.log(1e-3 / (1 - 1e-3)))
    tr.step()
    drawn = np.ones(tr.model.num_faces, bool)
    drawn[faint] = False
    assert not tr.grad_count[faint].any() and not tr.grad_sum[faint].any()
    assert set(np.unique(tr.grad_count[drawn])) <= {0, 1} and tr.grad_count[drawn].mean() > 0.5


def test_evaluation_spreads_its_views_over_the_validation_split(tiny_dataset, tmp_path):
    """eval_views n of the split's 4 views: the first and the last and evenly between them."""
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), config_for("tiny"), check_data=False)
    seen, val = [], tr.val

    class Recorded:
        def __len__(self):
            return len(val)

        def __getitem__(self, i):
            seen.append(i)
            return val[i]

    tr.val = Recorded()
    assert len(val) == 4
    for n, want in ((1, [0]), (2, [0, 3]), (3, [0, 1, 3]), (8, [0, 1, 2, 3])):
        seen.clear()
        assert np.isfinite(tr.evaluate(n)["val_psnr"])
        assert seen == want, n


def test_stream_order_is_measured_again_every_rank_every_iterations(tiny_dataset, tmp_path):
    """With in-level prefix cuts the stream order is measured before the first step and then at
    every multiple of rank_every (3 here; no growth in these 7 steps): iterations 0, 3, 6."""
    cfg = config_for(
        "tiny", prefix_cuts=1, rank_every=3, rank_views=1, grow_start=100, eval_every=10**6, checkpoint_every=10**6
    )
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), cfg, check_data=False)
    measured, real = [], tr._rank
    tr._rank = lambda measure: (measure and measured.append(tr.iteration)) or real(measure)
    tr.run(progress=False, stop_after=7)
    assert measured == [0, 3, 6]


def test_prefix_cuts_show_part_of_their_level(tiny_dataset, tmp_path):
    """An in-level prefix shows 1 .. count - 1 of its level's faces: none would be the level
    before's image, all the level's own, both supervised already."""
    cfg = config_for("tiny", prefix_cuts=2, coarse_stand_ins=False, coarse_backdrop=False)
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), cfg, check_data=False)
    counts = tr.model.forest.level_counts()
    cuts = [cut for _ in range(2000) for cut in tr._cuts()]
    assert {lv for lv, _ in cuts} == set(range(len(counts)))
    assert all(1 <= k <= counts[lv] - 1 for lv, k in cuts)


def test_sampled_supervision_draws_every_coarser_level():
    """ "sampled": the finest level and one coarser one, each of them in turn (level 0 too)."""
    rng = np.random.default_rng(0)
    assert {tuple(Supervision("sampled").levels(3, rng)) for _ in range(200)} == {(0, 3), (1, 3), (2, 3)}


def test_depth_cap_follows_the_growth_window_not_its_last_step():
    """The tiny schedule: growth window 15 .. 0.8 x 60 = 48, steps at 15, 30, 45. Depth 2 opens
    half-way through the window (31.5), so the step at 30 still splits to depth 1 only."""
    g = Growth.from_config(config_for("tiny"))
    assert [g.depth_cap(it) for it in (15, 30, 31, 32, 45)] == [1, 1, 1, 2, 2]


def test_length_note_says_whether_growth_can_still_happen(tmp_path):
    """A resume at the checkpoint of iteration 48, the end of the 60-iteration growth window (a
    40-iteration run's ended at 32): the iterations left are past both, so growth has ended."""
    note = _lengthened(str(tmp_path), config_for("tiny"), 48, 40)
    assert "growth had ended" in note
    assert "growth may go on until iteration 48, not 32" in _lengthened(str(tmp_path), config_for("tiny"), 47, 40)


def test_cuts_and_views_draw_from_unrelated_streams(tiny_dataset, tmp_path):
    """A cut generator seeded as the views' one would repeat the views' numbers, so each step's
    cut would follow from its view."""
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), config_for("tiny", prefix_cuts=1), check_data=False)
    assert not np.array_equal(tr.rng.random(8), tr.cut_rng.random(8))


def test_growth_over_the_face_cap_splits_nothing():
    """A forest already above max_faces (a cap under the template's faces) has no room: no face
    splits, however many are over the threshold."""
    from progressive_avatars.core.avatar.forest import Forest
    from tests.helpers import sphere_mesh

    forest = Forest(sphere_mesh(3, 4)[1])
    n = forest.num_faces
    g = Growth(
        iterations=100, max_depth=2, grow_every=10, grow_start=10, grow_stop=0.5, grad_threshold=0.0, max_faces=n - 6
    )
    assert len(g.pick(forest, np.ones(n), np.ones(n), 10)) == 0


def test_a_checkpoint_without_projected_sizes_holds_no_face_back(tiny_dataset, tmp_path):
    """Checkpoints from before split_min_px have no size record: until the next growth step
    every face counts as large enough, rather than as too small to split."""
    cfg = config_for("tiny", iterations=4, split_min_px=2.0, eval_every=10**6)
    calls = {"grow": [], "eval": [], "reset": [], "checkpoint": []}
    _bookkeeping_trainer(tiny_dataset, str(tmp_path / "run"), cfg, calls).run(progress=False, stop_after=2)
    path = tmp_path / "run" / "checkpoint.npz"
    arrays = dict(np.load(path))
    del arrays["size_px"]
    np.savez(path, **arrays)
    resumed = Trainer(tiny_dataset, str(tmp_path / "run"), cfg, resume=True, check_data=False)
    assert np.all(resumed.size_px >= cfg.split_min_px)


def test_a_resume_adding_cuts_to_stand_ins_that_leave_says_why(tiny_dataset, tmp_path):
    """A run whose coarse faces are stand-ins that leave, resumed with in-level prefix cuts (the
    default mode's option): refused naming the stand-ins, the reason, not only a changed setting."""
    leave = dict(coarse_stand_ins=True, coarse_backdrop=False)
    cfg = config_for("tiny", iterations=2, eval_every=10**6, **leave)
    calls = {"grow": [], "eval": [], "reset": [], "checkpoint": []}
    _bookkeeping_trainer(tiny_dataset, str(tmp_path / "run"), cfg, calls).run(progress=False)
    with pytest.raises(ValueError, match="stand-ins that leave; in-level prefix cuts need"):
        Trainer(tiny_dataset, str(tmp_path / "run"), config_for("tiny", iterations=2, prefix_cuts=1), resume=True)


def test_evaluation_of_views_with_nothing_to_score_logs_no_psnr(tiny_dataset, tmp_path):
    """Validation views whose masks are empty have no PSNR: the row gets none (json.dumps would
    write NaN, which strict JSON readers refuse), not a NaN."""
    from dataclasses import replace as replaced

    tr = Trainer(tiny_dataset, str(tmp_path / "run"), config_for("tiny"), check_data=False)
    val = tr.val

    class Unmasked:
        def __len__(self):
            return len(val)

        def __getitem__(self, i):
            s = val[i]
            return replaced(s, mask=np.zeros_like(s.mask))

    tr.val = Unmasked()
    assert tr.evaluate(2) == {}


def test_every_setting_but_the_resumable_ones_is_recorded_to_be_compared():
    """A resume compares the settings a checkpoint records: all of TrainConfig's fields but the
    ones RESUMABLE names (a field left out could change silently on a resume)."""
    from dataclasses import fields

    from progressive_avatars.core.train.policies import RESUMABLE
    from progressive_avatars.core.train.trainer import TrainConfig, run_settings

    want = {f.name for f in fields(TrainConfig)} - set(RESUMABLE)
    assert set(run_settings(config_for("tiny"))) == want and "grow_to" in want


def test_progress_line_shows_the_logged_average(tiny_dataset, tmp_path, capsys):
    """The progress line (what the Blender add-on shows) gives the last log row's PSNR, the mean
    of steps 20-22 at iteration 23 (21), not the last step's alone (22)."""
    calls = {"grow": [], "eval": [], "reset": [], "checkpoint": []}
    cfg = config_for("tiny", iterations=23, log_every=5, eval_every=10**6, checkpoint_every=10**6)
    tr = _bookkeeping_trainer(tiny_dataset, str(tmp_path / "run"), cfg, calls)
    tr.evaluate = lambda n: {}
    capsys.readouterr()
    tr.run(progress=True)
    last = capsys.readouterr().err.replace("\r", "\n").strip().splitlines()[-1]
    assert "23/23" in last and "psnr=21.00" in last, last
