"""The training schedules at their edges: growth never after the last iteration nor lost to a
floating-point product, opacity resets only up to the last growth step, the growth budget's
first step, a resume shorter than its checkpoint, and the log's averages across a resume."""

import json

import numpy as np
import pytest

from progressive_avatars.core.train.policies import Growth
from progressive_avatars.core.train.trainer import Trainer, config_for


def _growth(**kw):
    args = dict(iterations=60, max_depth=2, grow_every=15, grow_start=15, grow_stop=0.8, grad_threshold=0.0)
    args.update(kw)
    return Growth(max_faces=10**6, **args)


def test_growth_is_never_due_after_the_last_iteration():
    g = _growth(grow_stop=1.0)
    assert [it for it in range(1, 61) if g.due(it)] == [15, 30, 45]  # not 60: its faces would never train
    assert g.last_step == 45
    assert _growth().last_step == 45 and _growth(grow_stop=0.1).last_step == -1


def test_growth_window_is_not_cut_by_a_floating_point_product():
    g = _growth(iterations=750, grow_stop=0.58)  # 0.58 * 750 = 434.99999999999994
    assert g.due(435) and g.last_step == 435


def test_growth_budget_starts_at_the_first_real_step():
    base = 1000
    g = _growth(grow_start=0, grow_to=3.0)  # due at 15, 30, 45: three steps, not four
    assert [it for it in range(1, 61) if g.due(it)] == [15, 30, 45]
    assert [g.face_budget(base, it) for it in (15, 30, 45)] == [
        int(base * 3 ** (1 / 3)),
        int(base * 3 ** (2 / 3)),
        3000,
    ]


def test_opacity_resets_stop_at_the_last_growth_step(tiny_dataset, tmp_path):
    cfg = config_for("tiny", opacity_reset_every=16)  # growth due at 15, 30, 45; grow_stop ends the window at 48
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), cfg, check_data=False)
    assert [it for it in range(1, cfg.iterations + 1) if tr._reset_due(it)] == [16, 32]


def test_resume_shorter_than_the_checkpoint_is_refused(tiny_dataset, tmp_path):
    cfg = config_for("tiny", iterations=20, checkpoint_every=10, eval_every=1000)
    run = tmp_path / "run"
    Trainer(tiny_dataset, str(run), cfg, check_data=False).run(progress=False)
    before = (run / "config.json").read_text()
    with pytest.raises(ValueError, match=r"checkpoint is at iteration 20, past --iterations 10"):
        Trainer(tiny_dataset, str(run), config_for("tiny", iterations=10, checkpoint_every=10), resume=True)
    assert (run / "config.json").read_text() == before


def test_log_rows_average_the_same_steps_across_a_resume(tiny_dataset, tmp_path):
    cfg = config_for("tiny", iterations=20, checkpoint_every=5, eval_every=1000, log_every=10)
    Trainer(tiny_dataset, str(tmp_path / "full"), cfg, check_data=False).run(progress=False)
    Trainer(tiny_dataset, str(tmp_path / "part"), cfg, check_data=False).run(progress=False, stop_after=15)
    Trainer(tiny_dataset, str(tmp_path / "part"), cfg, resume=True, check_data=False).run(progress=False)

    def rows(name):
        return {r["iteration"]: r["train_psnr"] for r in map(json.loads, open(tmp_path / name / "metrics.jsonl"))}

    full, part = rows("full"), rows("part")
    assert sorted(full) == sorted(part) == [10, 20]
    np.testing.assert_allclose(part[20], full[20], atol=1e-3)  # steps 11-20, not 16-20 alone
