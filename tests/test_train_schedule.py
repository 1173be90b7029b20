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


def test_depth_cap_rises_from_one_to_max_depth_between_grow_start_and_stop():
    """Depth d opens (d - 1) / max_depth of the way from grow_start (100) to the end of the
    growth window (grow_stop x iterations = 500): depth 2 from 233.3, depth 3 from 366.7."""
    g = Growth(
        iterations=1000, max_depth=3, grow_every=1, grow_start=100, grow_stop=0.5, grad_threshold=0.0, max_faces=10**6
    )
    caps = {it: g.depth_cap(it) for it in (0, 100, 233, 234, 366, 367, 500, 900)}
    assert caps == {0: 1, 100: 1, 233: 1, 234: 2, 366: 2, 367: 3, 500: 3, 900: 3}


def test_uniform_growth_starts_at_once():
    """Uniform growth (the ablation) ignores grow_start: due at every multiple of grow_every in
    the window, its last step the last of them; adaptive growth starting after the window never
    grows."""
    kw = dict(
        iterations=100, max_depth=2, grow_every=10, grow_start=200, grow_stop=0.5, grad_threshold=0.0, max_faces=10**6
    )
    uniform = Growth(uniform=True, **kw)
    assert [it for it in range(1, 101) if uniform.due(it)] == [10, 20, 30, 40, 50] and uniform.last_step == 50
    adaptive = Growth(**kw)
    assert not any(adaptive.due(it) for it in range(1, 101)) and adaptive.last_step == -1
