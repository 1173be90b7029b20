"""Training: adaptive subdivision, multi-level supervision, atomic checkpoints, resume.

One iteration: pick a training view, evaluate every face's Gaussian on that timestep's mesh,
render the cumulative set of each supervised level, sum the photometric losses, add the
regularisers, step Adam. Screen-space gradients of the finest render are accumulated on
leaves; every `grow_every` iterations leaves whose mean gradient exceeds the threshold are
split, under a depth cap that rises from 1 to `max_depth`. With `views_per_step` > 1, or under
torchrun (core/train/distributed.py), one iteration is a batch of views and the step takes
the mean of their gradients.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from . import losses
from .adam import Adam
from ..avatar.avatar import PARAM_NAMES
from ..io.dataset import Dataset
from ..io.atomic import atomic_open, atomic_savez
from ..avatar.forest import Forest
from .distributed import Dist, check_same, digest
from .model import TorchAvatar
from .policies import RESUMABLE, Growth, Supervision
from ..render.kernels import MAX_IMAGES
from ..render.rasterize import all_finite, render, render_levels


@dataclass
class TrainConfig:
    iterations: int = 4000
    max_depth: int = 3
    grow_every: int = 200
    grow_start: int = 200
    grow_stop: float = 0.75  # fraction of iterations after which the forest is frozen
    grad_threshold: float = 1e-3  # mean NDC-space |d loss / d mean2d| that triggers a split
    max_faces: int = 60000
    # > 0: split by a budget, up to this factor times the base faces at the last growth step
    # (a geometric schedule; policies.Growth); 0: the gradient threshold alone decides.
    grow_to: float = 0.0
    # > 0: a leaf splits only if its Gaussian's projected size (largest standard deviation in
    # pixels, the most over the views since the last growth step) reaches this. Children
    # start a third of their parent's area, so below ~2 px they are sub-pixel, and measured on
    # the paper-scale head (docs/BENCHMARKS.md, "Where the image comes from, level by level")
    # the depth-3 and -4 Gaussians that unlimited growth made (57 % of the stream, median
    # sigma 0.6-1.2 px, two thirds nearly transparent) carry 10 % of the image. Yet 2 px there
    # lost at every budget (-0.12 dB against the unlimited run at the same Gaussian count, growth
    # 15.4x as the budget could not be filled; "Supervision and the growth size floor"): off (0).
    split_min_px: float = 0.0
    # > 0: every this many iterations while the forest grows, every Gaussian's opacity is cut to
    # at most opacity_reset_to and its Adam moments cleared, as the training GaussianAvatars (and
    # so the paper) inherits from 3DGS does (its opacity_reset_interval: 60k of 600k iterations,
    # growth every 2k). After a reset parents and children regrow together and share the image,
    # which is what makes the paper's finest-only prefixes collapse; measured at the paper's scale
    # (docs/BENCHMARKS.md, "The opacity reset and finest-only supervision") it does that here too
    # (finest-only -5 dB at 25-50 % of the stream), but it costs multi-level training 2.7-3.3 dB
    # there and 0.2-0.35 dB at 100 %. The multi-level gain it exposes at 35 % in the paper's level
    # order grows with the recovery after the last reset and levels off near 4.5 dB (6k to 20k
    # iterations: "The opacity reset with a 20k recovery"); in our stream order it is ~0. Off (0).
    opacity_reset_every: int = 0
    opacity_reset_to: float = 0.01
    supervision: str = "all"  # all | sampled | base | finest (policies.Supervision)
    # The last fraction of the iterations (after growth) supervises the finest level alone and
    # keeps the base faces' Gaussians (coarse and template levels, the roots) as they are, so
    # the finer levels finish for the whole avatar while the base prefixes stay what multi-level
    # training made them. Off (0) by default: at the paper's scale 0.3 gained 0.2 dB at 50-100 % of
    # the stream and lost 0.25 at 5-10 % (docs/BENCHMARKS.md, "Supervision modes at the paper's
    # scale"), a trade, not a gain.
    finest_tail: float = 0.0
    uniform: bool = False  # ablation: split every leaf when the cap rises, ignore gradients
    # Coarse levels above the template (DESIGN.md 7), as fractions of the template's face count,
    # built once from the canonical mesh; () turns them off (the paper's levels, older runs).
    # 1/16 rather than 1/8 for the second: measured on the default head (docs/BENCHMARKS.md, issue
    # 16), the first template-level Gaussians add more at 5 % of the stream than the coarse ones they
    # replace, and the smaller coarse table shortens the header (5 %: 2.86 dB below 100 % against 3.65,
    # both ranked by whole-avatar importance, as then).
    coarse_levels: tuple = (1 / 32, 1 / 16)
    # Multiplies w_l of the coarse levels in the multi-level loss. 0.5 measured on the default head
    # with cumulative coarse levels (docs/BENCHMARKS.md, issue 16, in git history): 1.0 gained
    # 0.3-0.5 dB at 5 % but cost 0.1-0.2 dB at 100 % against the run without coarse levels. Stand-ins
    # (below, an option) learn from their own levels' images only, so there it only weighs those images
    # against the regularisers, which every face shares.
    coarse_weight: float = 0.5
    # Coarse faces as stand-ins (Forest.drawn): images of the template level and finer leave
    # them out, and a stream reader drops each once the template faces of its region have
    # arrived (docs/FORMAT.md 2.4), so they fill short prefixes and cost nothing at 100 %.
    # Measured on both heads (docs/BENCHMARKS.md, issue 16, "coarse stand-ins"), stand-ins that
    # leave bring the 1,280-face head's 5 % budget within 3 dB of its 100 % and cost nothing
    # there, but a retiring stand-in can leave the prefix slightly worse than the one before
    # (coverage -0.004, PSNR -0.05..-0.12 dB in 1 % steps), which cumulative levels never do.
    # Off (with coarse_backdrop) means cumulative coarse levels, in every prefix, as the paper's
    # (train.py --coarse-mode cumulative).
    coarse_stand_ins: bool = True
    # Stand-ins that, once retired, stay behind every other Gaussian instead of leaving
    # (Forest.render_set): the images of the template level and finer show them as a backdrop,
    # and a stream sends each behind once its region's template faces hold 99.9 % of the region's
    # importance (docs/FORMAT.md 2.4), so a prefix never loses what it drew. Implies
    # coarse_stand_ins. The default, with backdrop_cuts and whole_without_backdrop: measured on
    # both heads (docs/BENCHMARKS.md, issue 16, "backdrop stand-ins", three seeds each) 5 % is
    # within 1.7-2.3 dB of 100 % (cumulative levels: 2.8-3.2 on the 1,280-face head), coverage
    # >= 0.97 from 2 %, no 1 % step down beyond 0.05 dB; the coarse cost at 100 % is +0.07 dB
    # (1,280-face) and +0.05 dB (5,120-face) mean over seeds, per seed -0.06..+0.15 (over the
    # nine runs of this training so far: +0.06 and +0.095).
    coarse_backdrop: bool = True
    # Extra images per step whose prefix ends *inside* a level: the levels below it plus the
    # first k faces of a random level (k uniform), in the order the stream will send them (each
    # level by importance measured on the levels up to its own, as core/render/importance.py).
    # The level-by-level loss supervises only prefixes that end at a level's end; a stream cut
    # anywhere else renders a set no loss has seen (issue 16). Off by default: measured on the
    # default and the coarse-template head (docs/BENCHMARKS.md, issue 16 sections), with coarse
    # levels and the residual-weighted ranking they move the short budgets by -0.2..+0.8 dB and
    # cost 0.1 dB at 100 % on the default head and 13-20 % per step; without coarse levels they
    # lift 5 % of the stream by about 5 dB.
    prefix_cuts: int = 0
    prefix_cut_weight: float = 1.0  # multiplies an in-level prefix's loss weight (its level's w_l)
    # With backdrop stand-ins, this many more in-level prefixes per step that end inside the
    # template level: there a stream shows the stand-ins of regions still missing faces in depth
    # order among the faces that have arrived, a state no level's image shows. Without them
    # the 5,120-face head's 10 % and 25 % budgets lost 0.6-1.1 dB against cumulative levels; with
    # one (and whole_without_backdrop) 10 %: 23.8-24.0 dB against 23.8, 25 %: 24.4 against 24.6,
    # 5 %: 23.0-23.2 against 22.4 (docs/BENCHMARKS.md, issue 16, "backdrop stand-ins"). Each is a
    # render of its own, and the stream order is re-measured every rank_every iterations.
    backdrop_cuts: int = 1
    # With backdrop stand-ins, the whole avatar's image leaves them out (as stand-ins that leave),
    # so the finished avatar stands on its own: a 3DGS PLY or the Blender preview, which cannot
    # draw a Gaussian behind the rest and so leave retired stand-ins out, show it as the stream
    # does. With them behind (False, as first measured) the 5,120-face head's finished avatar
    # leaned on them: 23.87 dB without them against 24.84 with (seed 0, 16 views, a scratch
    # script, 2026-11-28); trained without them, 24.81 against 24.80. It shares the other
    # images' render pass (render_levels' last_from).
    whole_without_backdrop: bool = True
    # How often the training re-measures that order (and after every growth step), on
    # rank_views spread training views.
    rank_every: int = 250
    rank_views: int = 8
    sh_degree: int = 0  # view-dependent colour bands (0..3); the stream carries degree 0
    sh_every: int = 1000  # one more active SH band every this many iterations (as 3DGS)
    flame_model: str | None = None  # the user's FLAME model, for FLAME-mode datasets (flame_param_path)
    refine_flame: bool = False  # learn per-timestep expression/pose/translation corrections (FLAME mode)
    # w_l of the multi-level loss, by level index; levels past the end take the last entry
    # (empty: every level 1).
    level_weights: tuple = ()
    lambda_ssim: float = 0.2
    position_reg: float = 0.01
    scale_reg: float = 1.0
    lr: dict = field(
        default_factory=lambda: {
            "split_logits": 1e-2,
            "d_mu": 5e-3,
            "d_log_scale": 2e-2,
            "d_rot": 1e-3,
            "opacity_logit": 5e-2,
            "f_dc": 2.5e-3 * 4,
            "f_rest": 2.5e-3 * 4 / 20,
            "flame_expr": 1e-3,
            "flame_pose": 1e-5,
            "flame_translation": 1e-6,
        }
    )
    lr_final_ratio: float = 0.01  # position lr decays exponentially to this fraction
    seed: int = 0
    downscale: float = 1.0
    log_every: int = 50
    eval_every: int = 500
    eval_views: int = 8
    checkpoint_every: int = 500
    image_cache_mb: float = 2048.0  # decoded training images kept in memory (LRU); the rest are re-read
    # Training views per iteration and process: under torchrun the effective batch is this times
    # the world size; the gradients are the mean over the batch (1: the single-view step).
    views_per_step: int = 1


PRESETS = {
    # Seconds: for tests and smoke runs.
    "tiny": dict(
        iterations=60,
        max_depth=2,
        grow_every=15,
        grow_start=15,
        grow_stop=0.8,
        max_faces=20000,
        log_every=10,
        eval_every=30,
        eval_views=2,
        checkpoint_every=20,
        sh_every=20,
    ),
    # The synthetic default on a 2-core CPU (<= 30 min). Growth by the gradient threshold, not
    # by a budget: a budget to 25,600 faces on every head (tried 2026-11-24, docs/BENCHMARKS.md,
    # issue 16) met the 5 % criterion on the 1,280-face head only by making the stream longer,
    # with no more quality at equal bytes and 0.07 dB less at 100 %.
    "cpu": dict(
        iterations=4000,
        max_depth=3,
        grow_every=150,
        grow_start=150,
        grow_stop=0.7,
        max_faces=40000,
        grad_threshold=2e-4,
        log_every=25,
        eval_every=250,
        eval_views=8,
        checkpoint_every=250,
    ),
    # The paper-scale synthetic head (make_synthetic.py --preset paper: 8192-face template, 540
    # training images of 550x802) on a 2-core CPU: depth 4, growth every 500 iterations until 70 %
    # of 6,000, by a budget to 18x the base (the paper grows 16.7x; records are fixed-size, so
    # the base is <= 6 % of the record bytes only from ~17x). The budget, not grad_threshold
    # (here only a floor), sets the growth: the first run (threshold 2e-4 alone, all levels
    # supervised, 2026-11-23) grew 4.3x in 6,000 iterations at ~1.0 s each; with a 2e-5 floor
    # the last growth step found fewer leaves above it than its budget allowed (16.5x). Sampled
    # supervision (the finest and one coarser level per step) halves a step at ~150k faces
    # against all levels (docs/BENCHMARKS.md, training iteration). The image cache is held to
    # 1 GiB (~150 of the 540 frames; decoding a frame again costs far less than an iteration).
    # Measured (2026-11-23, runs/paper3, 2 cores, partly shared): 3,908 s of training, peak RSS
    # 2.1 GB, growth 18.0x (8,950 -> 161,098 faces), validation PSNR 27.52 dB.
    # Cumulative coarse levels, as issue 17's table measured them (backdrop stand-ins, the
    # default elsewhere, are unmeasured at this scale).
    "paper-cpu": dict(
        coarse_stand_ins=False,
        coarse_backdrop=False,
        iterations=6000,
        max_depth=4,
        grow_every=500,
        grow_start=500,
        grow_stop=0.7,
        max_faces=170000,
        grow_to=18.0,
        grad_threshold=1e-5,
        supervision="sampled",
        log_every=50,
        eval_every=1000,
        eval_views=8,
        checkpoint_every=500,
        image_cache_mb=1024.0,
    ),
    # GPU, the paper's depth. Cumulative coarse levels: the backdrop's two-render gsplat path
    # (core/render/rasterize.py) has not yet run on a GPU.
    "paper": dict(
        coarse_stand_ins=False,
        coarse_backdrop=False,
        iterations=60000,
        max_depth=4,
        grow_every=2000,
        grow_start=2000,
        grow_stop=0.8,
        max_faces=250000,
        log_every=100,
        eval_every=5000,
        eval_views=16,
        checkpoint_every=5000,
    ),
}


# Loss weights: beyond these the loss underflows to 0 (nothing trains) or the gradients
# overflow the optimiser's float32 moments (everything freezes), both without an error.
MIN_WEIGHT, MAX_WEIGHT = 1e-6, 1e6


def _weight_ok(x: float) -> bool:
    return x == 0 or MIN_WEIGHT <= x <= MAX_WEIGHT  # False for NaN and inf


def config_for(preset: str, **overrides) -> TrainConfig:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    cfg = replace(TrainConfig(), **PRESETS[preset])
    cfg = replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    if not cfg.coarse_levels:  # no coarse levels, no mode (a --no-coarse run's settings stay as they were)
        cfg = replace(cfg, coarse_stand_ins=False, coarse_backdrop=False)
    elif cfg.coarse_backdrop:  # backdrop stand-ins are stand-ins
        cfg = replace(cfg, coarse_stand_ins=True)
    if not _weight_ok(cfg.coarse_weight):
        raise ValueError(f"coarse weight must be 0 or in [{MIN_WEIGHT:g}, {MAX_WEIGHT:g}], got {cfg.coarse_weight}")
    if int(cfg.views_per_step) < 1:
        raise ValueError(f"views per step must be >= 1, got {cfg.views_per_step}")
    if min(int(cfg.log_every), int(cfg.eval_every), int(cfg.checkpoint_every)) < 1 or int(cfg.eval_views) < 0:
        # (a 0 interval divided by zero at the first iteration, negative views failed at the first evaluation)
        raise ValueError(
            f"log, evaluation and checkpoint intervals must be >= 1 and evaluation views >= 0, got "
            f"{cfg.log_every}, {cfg.eval_every}, {cfg.checkpoint_every} and {cfg.eval_views}"
        )
    if int(cfg.iterations) < 0 or int(cfg.seed) < 0:
        raise ValueError(f"iterations and seed must be >= 0, got {cfg.iterations} and {cfg.seed}")
    if not (math.isfinite(cfg.image_cache_mb) and cfg.image_cache_mb >= 0):
        raise ValueError(f"image cache must be a finite number of MB >= 0, got {cfg.image_cache_mb}")
    if not _weight_ok(cfg.prefix_cut_weight):
        raise ValueError(
            f"prefix cut weight must be 0 or in [{MIN_WEIGHT:g}, {MAX_WEIGHT:g}], got {cfg.prefix_cut_weight}"
        )
    if int(cfg.prefix_cuts) < 0 or int(cfg.rank_every) < 1 or int(cfg.rank_views) < 1:
        raise ValueError(
            f"prefix cuts must be >= 0, rank_every and rank_views >= 1, got "
            f"{cfg.prefix_cuts}, {cfg.rank_every}, {cfg.rank_views}"
        )
    if int(cfg.backdrop_cuts) < 0:
        raise ValueError(f"backdrop cuts must be >= 0, got {cfg.backdrop_cuts}")
    if cfg.prefix_cuts and cfg.coarse_levels and cfg.coarse_stand_ins and not cfg.coarse_backdrop:
        raise ValueError(
            "in-level prefix cuts supervise cumulative or backdrop coarse levels only: stand-ins that leave "
            "are not drawn in a cut; use --coarse-mode cumulative or backdrop, or drop --prefix-cuts"
        )
    images = len(cfg.coarse_levels) + 1 + int(cfg.max_depth) + int(cfg.prefix_cuts)
    if images > MAX_IMAGES:  # render_levels composites at most MAX_IMAGES nested images a pass
        raise ValueError(
            f"a step may render {images} images (coarse levels {len(cfg.coarse_levels)} + template + depth "
            f"{cfg.max_depth} + prefix cuts {cfg.prefix_cuts}); at most {MAX_IMAGES}: lower the depth or the cuts"
        )
    Supervision(cfg.supervision)  # unknown modes and growth settings fail here, before any work
    Growth.from_config(cfg)  # before the finest tail, whose bound grow_stop sets
    if not (math.isfinite(cfg.finest_tail) and 0 <= cfg.finest_tail < 1 - cfg.grow_stop + 1e-12):
        raise ValueError(
            f"finest tail must be in [0, 1 - grow_stop] (it starts after the last growth step), got "
            f"{cfg.finest_tail} with grow_stop {cfg.grow_stop}"
        )
    if int(cfg.opacity_reset_every) < 0 or not (0 < cfg.opacity_reset_to < 1):
        raise ValueError(
            f"opacity reset: every must be >= 0 iterations (0: off) and the opacity in (0, 1), got "
            f"{cfg.opacity_reset_every} and {cfg.opacity_reset_to}"
        )
    w = tuple(float(x) for x in cfg.level_weights)
    if not all(_weight_ok(x) for x in w) or (w and max(w) == 0):
        raise ValueError(f"level weights must be 0 or in [{MIN_WEIGHT:g}, {MAX_WEIGHT:g}], not all 0, got {list(w)}")
    return replace(cfg, level_weights=w)


def level_weight(cfg: TrainConfig, level: int) -> float:
    w = cfg.level_weights
    return float(w[min(level, len(w) - 1)]) if w else 1.0


def _check_finite(it: int, **tensors):
    for name, t in tensors.items():
        if t is not None and not all_finite(t):
            raise FloatingPointError(f"iteration {it}: {name} became NaN/inf; training stopped")


def _log_iteration(line: str) -> float:
    """The iteration of a metrics.jsonl line; a torn line (a kill mid-write) counts as after
    every checkpoint, so resuming drops it instead of failing on it."""
    try:
        rec = json.loads(line)
        return float(rec.get("iteration", 0)) if isinstance(rec, dict) else math.inf
    except (ValueError, TypeError):
        return math.inf


_RUN_OUTPUTS = ("checkpoint.npz", "avatar.npz", "avatar.pavs", "flame_refined.npz")


def run_settings(cfg: TrainConfig) -> dict:
    """The settings that define a run, as JSON values; the FLAME model by its content, so a
    moved file still resumes and another model with the same faces does not."""
    out = {k: v for k, v in json.loads(json.dumps(asdict(cfg))).items() if k not in RESUMABLE}
    if cfg.flame_model:
        out["flame_model"] = _file_digest(cfg.flame_model)
    return out


def _file_digest(path: str) -> str:
    from ..io.safe_io import file_digest

    try:
        return file_digest(path)
    except OSError:
        return os.path.abspath(path)  # unreadable: the dataset load reports it


def _config_json_settings(out_dir: str) -> dict | None:
    """A checkpoint written before the settings travelled in it: config.json's, if readable
    (the FLAME model by its path then, which cannot be compared with a digest: left out)."""
    try:
        with open(os.path.join(out_dir, "config.json"), encoding="utf-8") as fh:
            cfg = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(cfg, dict):
        return None
    known = {f for f in TrainConfig.__dataclass_fields__ if f not in RESUMABLE and f != "flame_model"}
    return {k: v for k, v in cfg.items() if k in known}


def _position_decay(cfg: TrainConfig, it: int) -> float:
    """The position learning rate's factor at iteration ``it``: exponential to lr_final_ratio."""
    return cfg.lr_final_ratio ** (it / max(1, cfg.iterations))


def _lengthened(out_dir: str, cfg: TrainConfig, iteration: int, was: int | None = None) -> str | None:
    """A note when a resume changes the run's length: the schedules are fractions of it (the
    position learning rate's decay, growth's end and depth cap, the resets while it grows), so
    the rest of the run follows the new length's schedule from ``iteration`` on and the whole is
    not the run a fresh start with that length would make. ``was``: the length the checkpoint
    was trained with (its state records it; older checkpoints: config.json's, which a resume
    stopped before its first checkpoint has already rewritten)."""
    if not isinstance(was, int) or isinstance(was, bool):
        try:
            with open(os.path.join(out_dir, "config.json"), encoding="utf-8") as fh:
                was = int(json.load(fh)["iterations"])
        except (OSError, ValueError, KeyError, TypeError):
            return None
    if was == cfg.iterations:
        return None
    old, new = Growth.from_config(replace(cfg, iterations=was)).last, Growth.from_config(cfg).last
    growth = (
        f"growth may go on until iteration {new}, not {old}"
        if iteration < max(old, new)
        else "growth had ended and does not restart"
    )
    decay = _position_decay(cfg, iteration) / _position_decay(replace(cfg, iterations=was), iteration)
    return (
        f"note: {out_dir}: resumed at iteration {iteration} with {cfg.iterations} iterations instead of {was}: "
        f"the schedules follow the new length from here ({growth}; the position learning rate steps by "
        f"{decay:.2g}x), so the run is not what a fresh {cfg.iterations}-iteration run would be"
    )


def _rebatched(out_dir: str, was, world_size: int, views_per_step: int) -> str | None:
    """A note when a resume changes the views each step averages over (processes x views per
    step): allowed, as one process with twice the views is the same step as two processes, but
    from here the run is not the one it was."""
    now = world_size * views_per_step
    if not isinstance(was, int) or isinstance(was, bool) or was == now:
        return None
    return (
        f"note: {out_dir}: resumed with {now} views per step ({world_size} process(es) x {views_per_step}) "
        f"instead of the {was} it was trained with: each step's gradient averages another batch from here"
    )


def _check_same_settings(source: str, was: dict | None, now: dict) -> None:
    if not was:
        return
    diff = [f"{k} {was[k]!r} -> {now.get(k)!r}" for k in sorted(was) if k in now and was[k] != now[k]]
    if diff:
        raise ValueError(
            f"{source}: --resume with settings other than the run's: {'; '.join(diff)}. Resume with the options "
            "the run was started with (its config.json), or train into a new --out folder "
            f"(a resume may change only {', '.join(RESUMABLE)})"
        )


def _remove_run_outputs(out_dir: str, everything: bool) -> None:
    """A fresh start: the metrics log of an earlier start, and with ``everything`` (--overwrite)
    the replaced run's checkpoint, avatar, stream and importance caches too, so a kill before
    the new run's first checkpoint cannot leave the old checkpoint beside the new config.json
    for a --resume to continue on the new data."""
    names = ["metrics.jsonl"]
    if everything:
        names += _RUN_OUTPUTS
        try:
            names += [
                n for n in os.listdir(out_dir) if n.startswith("importance") and n.endswith((".npz", ".npy", ".json"))
            ]
        except OSError:
            pass
    for name in names:
        path = os.path.join(out_dir, name)
        if os.path.isfile(path):
            os.remove(path)


class RunExistsError(ValueError):
    """Training without resume into a run folder that holds a checkpoint or a trained avatar."""


def _split_digest(path: str) -> str:
    """A training split's content: its JSON re-written canonically (keys sorted, no spaces), so a
    split only re-saved by another tool still resumes; the file's bytes when it is not JSON."""
    import hashlib

    try:
        with open(path, encoding="utf-8") as fh:
            text = json.dumps(json.load(fh), sort_keys=True, separators=(",", ":"))
    except (OSError, ValueError):
        return _file_digest(path)
    return "json-sha256:" + hashlib.sha256(text.encode()).hexdigest()


def _checkpoint_state(path: str) -> dict:
    """A checkpoint's state record, read alone (empty when it cannot be: loading the checkpoint
    reports the damage)."""
    from ..io.safe_io import check_npz

    try:
        check_npz(path, allow_text=("state_json",))
        with np.load(path, allow_pickle=False) as d:
            state = json.loads(str(d["state_json"]))
        return state if isinstance(state, dict) else {}
    except Exception:
        return {}


def _check_same_data(out_dir: str, data_dir: str, state: dict) -> str | None:
    """--resume must continue on the dataset the run was started on: the content of its training
    split, which checkpoints record (older ones: the folder config.json names). A changed split
    under the same folder would train other frames and put FLAME corrections on other timesteps;
    a copy of the dataset elsewhere resumes, with the note this returns."""
    try:
        with open(os.path.join(out_dir, "config.json"), encoding="utf-8") as fh:
            was = json.load(fh).get("data")
    except (OSError, ValueError, AttributeError):
        was = None  # no readable config: the checkpoint's template check still applies
    was = was if isinstance(was, str) else None
    now = os.path.abspath(data_dir)
    moved = bool(was) and os.path.realpath(was) != os.path.realpath(now)
    split = os.path.join(now, "transforms_train.json")
    recorded = state.get("train_split")
    if isinstance(recorded, str) and os.path.isfile(split):
        if _split_digest(split) != recorded:
            where = f" (trained on {was})" if moved else ""
            raise ValueError(
                f"{split} is not the training split this run was started on{where}: its frames, cameras or "
                "timesteps changed; resume on the dataset the run was started on, or train into a new --out folder"
            )
        return f"note: {out_dir}: resuming on {now}, a copy of {was} (the same training split)" if moved else None
    if moved:
        raise ValueError(
            f"{out_dir}: --resume with a different --data: this run was trained on {was}, not {now}; "
            "resume with the same --data, or train into a new --out folder"
        )
    return None


def kernels_uncached() -> bool:
    """Whether training's compiled kernels are missing from numba's cache, so that the first
    iteration compiles them: on a machine's first run of a version that takes minutes
    (docs/BENCHMARKS.md, "First-run kernel compilation"), while the progress shows 0 %."""
    from ..render import kernels
    from . import binding_kernels

    return kernels.uncached(kernels.raster_forward, kernels.raster_backward, binding_kernels.bind_backward)


def raised_from(exc: BaseException, kind: type) -> bool:
    """Whether ``exc`` is a ``kind`` or was raised while handling one: a signal's exception (Ctrl-C's
    KeyboardInterrupt, torchrun's SIGTERM) raised while a compiled kernel runs reaches the caller
    wrapped (SystemError: "returned a result with an exception set", the original as its context)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, kind):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def kept_text(out: str | None, checkpoint: int | None, any_processes: bool = False, resume: str = "--resume") -> str:
    """What a stopped run leaves to resume from (the end of its error line); ``out`` None
    leaves the folder out, ``resume`` names the way to continue (the add-on's Resume box)."""
    if checkpoint is None:
        return "no checkpoint was written yet"
    more = ", with any number of processes" if any_processes else ""
    where = f" in {out}" if out else ""
    return f"the last checkpoint{where} (iteration {checkpoint}) is kept; {resume} continues from it{more}"


def _check_uniform_room(cfg: TrainConfig, template_faces: int, coarse_faces: int) -> None:
    """A uniform run must fit every face to its depth under the face cap: the cap would cut
    the last split by face index, leaving one block of the template deeper than the rest."""
    need = coarse_faces + template_faces * (3 ** (cfg.max_depth + 1) - 1) // 2
    if need > cfg.max_faces:
        raise ValueError(
            f"--uniform to depth {cfg.max_depth} needs {need:,} faces ({template_faces:,} template faces, "
            f"each split {cfg.max_depth} times, and {coarse_faces:,} coarse ones), above --max-faces "
            f"{cfg.max_faces:,}: pass --max-faces {need} or more, or a smaller --max-depth"
        )


class NoRoomError(ValueError):
    """The run folder's disk cannot hold what the run will write."""


def _faces_bound(cfg: TrainConfig, roots: int, template_faces: int, faces_now: int) -> int:
    """The most faces this run can reach: growth's cap (``Growth.budget``'s target, or the
    face cap) and full subdivision to ``max_depth``, whichever is fewer."""
    full = roots + template_faces * (3 ** (cfg.max_depth + 1) - 3) // 2
    cap = cfg.max_faces if cfg.uniform or cfg.grow_to <= 0 else min(cfg.max_faces, int(cfg.grow_to * roots))
    return max(faces_now, min(full, cap))


def run_bytes(faces: int, width: int) -> int:
    """About the most disk a run of ``faces`` faces with ``width`` values each needs at once:
    the last checkpoint's temporary beside the previous checkpoint (values and Adam moments in
    float32, Adam steps and four float64 statistics, forest rows), the avatar, its three
    importance files (float64) and its stream (~25 B a face), and 8 MB for logs."""
    checkpoint = faces * (12 * width + 61)
    return 2 * checkpoint + faces * (4 * width + 21) + faces * (25 + 24) + 8 * 2**20


def _check_disk_room(out_dir: str, cfg: TrainConfig, model) -> None:
    """Refuse a run whose checkpoints and avatar will not fit on the disk, before the hours of
    training that would end in a full disk. The outputs already in the folder are replaced, so
    their space counts as free."""
    import shutil

    f = model.forest
    faces = _faces_bound(cfg, f.num_roots, len(f.template_faces), f.num_faces)
    need = run_bytes(faces, sum(int(np.prod(t.shape[1:])) for t in model.params.values()))
    held = 0
    for n in os.listdir(out_dir):
        if n in _RUN_OUTPUTS or (n.startswith("importance") and n.endswith((".npz", ".npy", ".json"))):
            try:
                held += os.path.getsize(os.path.join(out_dir, n))
            except OSError:  # replaced or removed meanwhile (an evaluation writing its cache)
                pass
    free = shutil.disk_usage(out_dir).free + held
    if free < need:
        raise NoRoomError(
            f"{out_dir}: the disk has {free / 2**20:,.0f} MB free for this run, which needs about "
            f"{need / 2**20:,.0f} MB (checkpoints and avatar of up to {faces:,} faces): free some space or "
            "train into another --out folder"
        )


def _cut_generator(seed: int) -> np.random.Generator:
    """The in-level prefix cuts' own generator. Cuts drawn from the views' generator shifted
    every later view draw, so runs of one seed with and without cuts saw different views and
    the studies' paired-by-seed comparisons were not paired (docs/BENCHMARKS.md, issue 16)."""
    return np.random.default_rng([seed, 1])


def _check_gaussians(it: int, g: dict):
    """The activated Gaussians before they reach the rasteriser (which would refuse them with
    a ValueError): a scale that overflowed to inf, or a NaN, stops training cleanly."""
    with torch.no_grad():
        _check_finite(it, **{f"Gaussian {k}": v for k, v in g.items()})
        bad = g["scales"] <= 0
        if bool(bad.any()):
            raise FloatingPointError(f"iteration {it}: Gaussian scales underflowed to 0; training stopped")


class Trainer:
    def __init__(
        self,
        data_dir: str,
        out_dir: str,
        config: TrainConfig,
        resume: bool = False,
        check_data: bool = True,
        progress: bool = False,
        dist: Dist | None = None,
        overwrite: bool = False,
        coarse_mode_given: bool = False,
    ):
        """``coarse_mode_given``: the config's coarse mode was asked for (train.py --coarse-mode),
        so a resume must match the run's; otherwise a resume takes the run's own mode (a run
        trained before the preset's default changed resumes without naming it)."""
        self.data_dir, self.out_dir, self.cfg = data_dir, out_dir, config
        # A run folder that holds a checkpoint or a trained avatar is not started over by a
        # forgotten --resume: its first checkpoint would replace what hours of training made.
        if not resume and not overwrite:
            held = [n for n in ("checkpoint.npz", "avatar.npz") if os.path.exists(os.path.join(out_dir, n))]
            if held:
                raise RunExistsError(
                    f"{out_dir} already holds a run ({', '.join(held)}): --resume continues it; to start "
                    "over, train into another --out folder or pass --overwrite"
                )
        if resume and not os.path.exists(os.path.join(out_dir, "checkpoint.npz")):
            if os.path.exists(os.path.join(out_dir, "avatar.npz")):  # resuming would start it over
                raise RunExistsError(
                    f"{out_dir} holds a trained avatar (avatar.npz) but no checkpoint.npz to resume from; "
                    "train into another --out folder, or pass --overwrite without --resume to start over"
                )
        # World size 1 unless a torchrun job is given: then only rank 0 writes the run folder.
        self.dist = dist or Dist()
        main = self.dist.is_main
        # Policies first: a wrong supervision mode or growth setting fails before any file is made.
        self.supervision = Supervision(config.supervision)
        self.growth = Growth.from_config(config)
        os.makedirs(out_dir, exist_ok=True)
        self.ckpt_path = os.path.join(out_dir, "checkpoint.npz")
        moved, trained, batch = None, None, None
        if resume and os.path.exists(self.ckpt_path):
            state = _checkpoint_state(self.ckpt_path)
            moved = _check_same_data(out_dir, data_dir, state)
            trained = state.get("iterations")  # the length its schedules followed
            batch = state.get("effective_batch")
        self.train = Dataset(
            data_dir,
            "train",
            downscale=config.downscale,
            cache_images=100000,
            flame_model=config.flame_model,
            cache_bytes=int(config.image_cache_mb * 2**20),
        )
        self.train_split = _split_digest(self.train.json_path)
        # No validation split is fine; a broken one is an error, not silently dropped.
        if os.path.isfile(os.path.join(self.train.root, "transforms_val.json")):
            self.val = Dataset(
                data_dir, "val", downscale=config.downscale, cache_images=64, flame_model=config.flame_model
            )
            self.val.check_same_mesh(self.train.faces, f"{self.train.json_path}'s")
        else:
            self.val = None
        if check_data:
            # Every rank checks its share: one rank checking a large dataset alone would keep the
            # others waiting at the first collective past its timeout (PA_DIST_TIMEOUT).
            from ..io.validate import validate_dataset

            for ds in (self.train, self.val):
                if ds is not None:
                    validate_dataset(ds, progress=progress and main, share=(self.dist.rank, self.dist.world_size))
        self.background = torch.tensor(np.asarray(self.train.background, np.float32))
        self.refiner = None
        if config.refine_flame:
            if self.train.mode != "flame":
                raise ValueError(
                    f"{data_dir}: FLAME refinement needs a FLAME-mode dataset (flame_param_path "
                    "frames) and --flame-model"
                )
            from .flame_refine import FlameRefiner

            self.refiner = FlameRefiner(self.train, config.lr)
        self.log_path = os.path.join(out_dir, "metrics.jsonl")
        self.rank_importance = None  # the order of the in-level prefixes (prefix_cuts)
        self.stream_key = None
        self.checkpoint_iteration = None  # the iteration of the last checkpoint written or loaded
        self.recent_psnr = []  # training PSNRs since the last log row
        self.on_checkpoint = None  # called with the iteration after each checkpoint (rank 0)
        if resume and os.path.exists(self.ckpt_path):
            self._load_checkpoint()
            if self.iteration > config.iterations:  # before config.json is rewritten below
                raise ValueError(
                    f"{self.ckpt_path}: the checkpoint is at iteration {self.iteration}, past --iterations "
                    f"{config.iterations}; resume with at least {self.iteration} (the avatar of iteration "
                    f"{self.iteration} is in {out_dir}/avatar.npz once the run has finished)"
                )
            f = self.model.forest
            if f.stand_ins and not f.backdrop and config.prefix_cuts:
                raise ValueError(
                    f"{out_dir}: this run's coarse faces are stand-ins that leave; in-level prefix cuts need "
                    "cumulative or backdrop ones"
                )
            mode = (f.stand_ins, f.backdrop)
            if f.num_coarse and not coarse_mode_given and mode != (config.coarse_stand_ins, config.coarse_backdrop):
                config = self.cfg = replace(
                    config, coarse_stand_ins=f.stand_ins, coarse_backdrop=f.backdrop
                )  # its kind
            self.settings = run_settings(config)
            _check_same_settings(self.ckpt_path, self.run_settings, self.settings)
            if main:
                _check_disk_room(out_dir, config, self.model)
                notes = (
                    moved,
                    _lengthened(out_dir, config, self.iteration, trained),
                    _rebatched(out_dir, batch, self.dist.world_size, config.views_per_step),
                )
                for note in notes:
                    if note:
                        print(note, file=sys.stderr)
        else:
            if resume and main:  # a mistyped --out would otherwise start hours of training without a word
                print(f"note: {out_dir} holds no checkpoint.npz: --resume starts a new run", file=sys.stderr)
            coarse = None
            if config.coarse_levels:
                from ..avatar.coarse import build_coarse

                cf, counts = build_coarse(self.train.canonical_vertices, self.train.faces, config.coarse_levels)
                coarse = (cf, counts, None) if counts else None
            if config.uniform:
                _check_uniform_room(config, len(self.train.faces), len(coarse[0]) if coarse else 0)
            self.model = TorchAvatar.from_template(
                self.train.faces,
                sh_degree=config.sh_degree,
                coarse=coarse,
                stand_ins=config.coarse_stand_ins,
                backdrop=config.coarse_backdrop,
            )
            self.opt = Adam(self.model.params, config.lr)
            self.rng = np.random.default_rng(config.seed)
            self.cut_rng = _cut_generator(config.seed)
            self.iteration = 0
            self.elapsed = 0.0
            self._reset_accumulators()
            self.settings = run_settings(config)
            if main:  # the room first: a refused --overwrite leaves the replaced run as it was
                _check_disk_room(out_dir, config, self.model)
                _remove_run_outputs(out_dir, everything=overwrite)  # else a log left by a kill before any checkpoint
        if self.dist.world_size > 1:
            # Same settings and start on every rank (template init or checkpoint), or stop before
            # any step: a rank started with another seed or batch would train something else.
            values = self.dist.gather_digest(self._settings_digest(data_dir))
            if len(set(values)) > 1:
                odd = [r for r, v in enumerate(values) if v != values[0]]
                raise RuntimeError(
                    f"rank(s) {', '.join(map(str, odd))} were started with other training options or data than "
                    "rank 0 (seed, iterations, views per step, ...): start every process of the job with the same command"
                )
            self._check_ranks_agree("parameters and optimiser state", self._state_digest())
        if main:
            if self.checkpoint_iteration is not None:  # resumed
                self._trim_log()
            with atomic_open(os.path.join(out_dir, "config.json"), "w") as fh:
                json.dump(
                    {
                        "data": os.path.abspath(data_dir),
                        **asdict(config),
                        "world_size": self.dist.world_size,
                        "effective_batch": self.dist.world_size * config.views_per_step,
                    },
                    fh,
                    indent=1,
                )

    # -- growth ---------------------------------------------------------------------------
    def _reset_accumulators(self):
        n = self.model.num_faces
        self.grad_sum = np.zeros(n)
        self.grad_count = np.zeros(n)
        self.size_px = np.zeros(n)  # the largest projected sigma seen (split_min_px)

    def depth_cap(self, it: int) -> int:
        return Growth.from_config(self.cfg).depth_cap(it)

    def _grow(self, it: int) -> int:
        d = self.dist
        self._fold_accumulators()
        # Decided once, on rank 0 (it holds the summed statistics), and broadcast.
        pick = (
            self.growth.pick(self.model.forest, self.grad_sum, self.grad_count, it, self.size_px) if d.is_main else None
        )
        pick = d.broadcast_ints(pick)
        if len(pick):
            self.model.split(pick)
            self.opt.grow(self.model.params)
        self._reset_accumulators()
        if d.world_size > 1:
            f = self.model.forest
            self.forest_digests = self._check_ranks_agree("forests after growth", digest(f.parent, f.slot), it)
        return len(pick)

    def _reset_due(self, it: int) -> bool:
        """Whether every opacity is cut after iteration ``it``: on the schedule, while the forest
        grows (as 3DGS resets only while it densifies), never at the last iteration."""
        every = int(self.cfg.opacity_reset_every)
        return every > 0 and it % every == 0 and it <= self.growth.last_step and it < self.cfg.iterations

    @torch.no_grad()
    def reset_opacity(self):
        """Cut every Gaussian's opacity to at most ``opacity_reset_to`` and clear its Adam moments
        (the steps stay, as 3DGS keeps them), so the optimiser brings back what the images need."""
        p = self.cfg.opacity_reset_to
        logit = self.model.params["opacity_logit"]
        logit.clamp_(max=math.log(p / (1 - p)))
        self.opt.m["opacity_logit"].zero_()
        self.opt.v["opacity_logit"].zero_()

    def _fold_accumulators(self):
        """Sum the ranks' growth statistics into rank 0's (the others restart from zero), so the
        sums are the job's at a growth step and in a checkpoint, whatever the world size."""
        if self.dist.world_size > 1:
            self.dist.sum_arrays_(self.grad_sum, self.grad_count)
            self.dist.max_arrays_(self.size_px)
            if not self.dist.is_main:
                self.grad_sum[:] = 0
                self.grad_count[:] = 0
                self.size_px[:] = 0

    def _state_digest(self) -> int:
        f, o = self.model.forest, self.opt
        arrays = [f.parent, f.slot, o.steps.numpy()]
        for name, t in sorted(self.model.params.items()):
            arrays += [t.detach().numpy(), o.m[name].numpy(), o.v[name].numpy()]
        if self.refiner is not None:  # the FLAME corrections and their optimiser state
            arrays += [np.asarray(v) for _, v in sorted(self.refiner.state().items())]
        return digest(*arrays)

    def _settings_digest(self, data_dir: str) -> int:
        text = json.dumps({**asdict(self.cfg), "data": os.path.abspath(data_dir)}, sort_keys=True, default=str)
        return digest(np.frombuffer(text.encode(), np.uint8))

    def _check_ranks_agree(self, what: str, value: int, it: int | None = None) -> list:
        values = self.dist.gather_digest(value)
        check_same(what, values, self.iteration if it is None else it)
        return values

    # -- one step -------------------------------------------------------------------------
    def _in_tail(self, it: int) -> bool:
        return self.cfg.finest_tail > 0 and it >= self.cfg.iterations * (1 - self.cfg.finest_tail)

    def _levels(self) -> list[int]:
        forest = self.model.forest
        if self._in_tail(self.iteration):
            return [forest.max_level]
        return self.supervision.levels(forest.max_level, self.rng, forest.num_coarse_levels)

    def _cuts(self) -> list[tuple[int, int]]:
        """The step's in-level prefixes: (level, how many of its faces they show, 1 .. count - 1)."""
        forest = self.model.forest
        extra = int(self.cfg.backdrop_cuts) if forest.backdrop else 0
        if not (self.cfg.prefix_cuts or extra):
            return []
        counts = forest.level_counts()
        out = []
        for i in range(self.cfg.prefix_cuts + extra):
            lv = int(self.cut_rng.integers(0, len(counts))) if i < self.cfg.prefix_cuts else forest.num_coarse_levels
            if counts[lv] >= 2:
                out.append((lv, int(self.cut_rng.integers(1, counts[lv]))))
        return out

    def _rank(self, measure: bool):
        """Position of each face in the level-by-level stream order (version 4's: each level by
        importance measured on the levels up to its own), measuring the importance again on
        spread training views when ``measure``. Version 5 streams interleave the levels when
        written; supervising interleaved prefixes instead measured worse (docs/BENCHMARKS.md)."""
        from ..render.importance import face_importance
        from ..stream.order import root_keys, stream_order

        forest = self.model.forest
        if measure:
            av = self.model.to_avatar()
            self.rank_importance = face_importance(av, self.train, self.cfg.rank_views, progress=False)
        imp = self.rank_importance
        perm = stream_order(forest, imp, root_keys(forest, "auto", imp))
        key = np.empty(len(perm), np.int64)
        key[perm] = np.arange(len(perm))
        self.stream_key = key
        if forest.backdrop:
            # each stand-in's stream position from which it renders behind, as a writer sets it
            from ..stream.writer import BACKDROP_RETIRE_IMPORTANCE, stand_in_retire

            retire = stand_in_retire(
                forest, perm, self.train.canonical_vertices, imp, (BACKDROP_RETIRE_IMPORTANCE, 0.0)
            )
            coarse = np.flatnonzero(forest.level < forest.num_coarse_levels)
            self.cut_retire = (coarse, retire[forest.root_ref[coarse]])

    def _cut_behind(self, u: int) -> np.ndarray | None:
        """[N] the backdrop stand-ins behind the rest in the prefix of stream positions <= ``u``
        (those whose region was complete by then; None when none is): what Forest.render_set of
        that stream prefix gives."""
        coarse, retire = self.cut_retire
        behind = np.zeros(self.model.num_faces, bool)
        behind[coarse[retire <= u]] = True
        return behind if behind.any() else None

    def _render_images(self, g, camera, upto, image_levels, is_cut, order_key, in_stream_order) -> list:
        """The step's images, one per entry of ``upto`` (ascending prefixes of ``order_key``), as a
        stream shows them. One projection, sort and tile binning is shared by every image it can
        be: without stand-ins, all of them. Plain stand-ins: the coarse levels render apart (their
        Gaussians only) and the template level and finer leave them out. Backdrop stand-ins: the
        coarse levels, the template level and finer (stand-ins behind the rest) and the whole
        avatar without them (whole_without_backdrop: the last image leaves their keys out) share
        one pass, since stand-ins behind everything keep their depth order among themselves; each
        cut inside the template level is its own render (the stand-ins of regions not yet complete
        composite in depth order with the faces there)."""
        model = self.model
        forest = model.forest
        K = forest.num_coarse_levels if forest.stand_ins else 0
        names = ("means", "quats", "scales", "opacities", "colors")
        kinds = [
            "coarse" if lv < K else "cut" if cut and lv == K and forest.backdrop else "finer"
            for lv, cut in zip(image_levels, is_cut)
        ]
        by_upto = {}
        for u, kind in zip(upto, kinds):
            if kind == "cut":
                (by_upto[u],) = render_levels(
                    *(g[k] for k in names),
                    camera,
                    self.background,
                    level=order_key,
                    upto=[u],
                    compute_contrib=False,
                    behind=self._cut_behind(u),
                )
        coarse_up = [u for u, kind in zip(upto, kinds) if kind == "coarse"]
        finer_up = [u for u, kind in zip(upto, kinds) if kind == "finer"]
        opacities, behind = model.finer_inputs(g["opacities"])
        whole = model.num_faces - 1 if in_stream_order else forest.max_level
        alone = bool(behind is not None and self.cfg.whole_without_backdrop and finer_up and finer_up[-1] == whole)
        if coarse_up and not forest.backdrop:
            sub = model.stand_in_ids
            outs = render_levels(
                *(g[k][sub] for k in names),
                camera,
                self.background,
                level=np.asarray(order_key)[sub.numpy()],
                upto=coarse_up,
                compute_contrib=False,
            )
            by_upto.update(zip(coarse_up, outs))
        shared = coarse_up + finer_up if forest.backdrop else finer_up
        last_from = None
        if alone:  # the stand-ins' keys come first, in level and in stream order alike
            key, finer = np.asarray(order_key), forest.level >= forest.num_coarse_levels
            last_from = int(key[finer].min())
            if key[~finer].max() >= last_from:
                raise RuntimeError("trainer: a stand-in's key follows a finer face's (the order is broken)")
        if shared:
            outs = render_levels(
                *(g[k] for k in names[:3]),
                opacities,
                g["colors"],
                camera,
                self.background,
                level=order_key,
                upto=shared,
                compute_contrib=False,  # training reads no contrib (a faster forward)
                behind=behind,
                last_from=last_from,
            )
            by_upto.update(zip(shared, outs))
        return [by_upto[u] for u in upto]

    def _views(self) -> list[int]:
        """This rank's training views of the iteration: one draw of the whole batch (world size
        x views per step) from the generator every rank shares, sliced by rank, so ranks see
        different views and N ranks x b views are the views of 1 process x N*b."""
        b, d = self.cfg.views_per_step, self.dist
        if b * d.world_size == 1:
            return [int(self.rng.integers(len(self.train)))]  # the single-view draw, as it always was
        batch = self.rng.integers(len(self.train), size=b * d.world_size)
        return [int(i) for i in batch[d.rank * b : (d.rank + 1) * b]]

    def step(self) -> dict:
        c, it = self.cfg, self.iteration
        views = self._views()
        self.model.active_sh_degree = min(c.sh_degree, it // max(1, c.sh_every))
        levels = self._levels()
        top = self.model.forest.max_level
        cuts = [] if self._in_tail(it) else self._cuts()  # the tail supervises the finest image alone
        if cuts:
            imp = self.rank_importance
            if imp is None or len(imp) != self.model.num_faces or it % c.rank_every == 0:
                with torch.no_grad():  # diverged parameters stop here as below (to_avatar would refuse them)
                    _check_gaussians(it, self.model.gaussians(self._vertices(self.train[views[0]])))
                self._rank(measure=True)  # also right after a growth step
            elif self.stream_key is None:
                self._rank(measure=False)  # resumed: the checkpoint's importance
            # Every image as a prefix of the stream order: levels end at their cumulative counts.
            counts = self.model.forest.level_counts()
            ends = np.cumsum(counts)
            images = {int(ends[lv]) - 1: (lv, False) for lv in levels}  # last position shown: (level, cut)
            for lv, k in cuts:
                images.setdefault(int(ends[lv] - counts[lv]) + k - 1, (lv, True))
            upto = sorted(images)
            image_levels, is_cut = [images[u][0] for u in upto], [images[u][1] for u in upto]
            order_key = self.stream_key
        else:
            upto, image_levels, order_key = levels, levels, self.model.forest.level
            is_cut = [False] * len(levels)
        p = self.model.params
        b = len(views)
        loss_sum, psnr_sum = 0.0, 0.0
        for view in views:
            sample = self.train[view]
            target = torch.from_numpy(sample.image)
            target_window = losses.TargetWindow(target)  # shared by the levels' losses
            g = self.model.gaussians(self._vertices(sample), sample.camera.center)
            _check_gaussians(it, g)
            loss = torch.zeros(())
            finest = None
            outs = self._render_images(g, sample.camera, upto, image_levels, is_cut, order_key, bool(cuts))
            for lvl, out, cut in zip(image_levels, outs, is_cut):
                ids = self.model.level_ids[top]  # every level's output covers all faces (means2d, radii)
                w = level_weight(c, lvl) * (c.coarse_weight if lvl < self.model.forest.num_coarse_levels else 1.0)
                w *= c.prefix_cut_weight if cut else 1.0
                if w:
                    loss = loss + w * losses.photometric(out.image, target, c.lambda_ssim, target_window)
                finest = (ids, out)  # the last image is the finest level
            loss = (
                loss
                + c.position_reg * losses.position_reg(p["d_mu"])
                + c.scale_reg * losses.scale_reg(p["d_log_scale"])
            )
            _check_finite(it, loss=loss)
            if b > 1:
                loss = loss / b  # the batch's mean; gradients accumulate over its views
            loss.backward()
            ids, out = finest
            grad2d = out.means2d.grad
            if grad2d is not None:
                # Per-pixel units, independent of image size: normalise by the image extent; and of
                # the level's loss weight, so the growth threshold means the same whatever w_l; and
                # of the batch (one view's gradient, as a single-view step measures it).
                scale = 0.5 * max(sample.camera.width, sample.camera.height) / max(level_weight(c, top), 1e-12)
                norm = torch.linalg.vector_norm(grad2d, dim=-1).numpy() * (scale * b)
                seen = out.radii.numpy() > 0
                idx = ids.numpy()[seen]
                # bincount, not np.add.at: ufunc.at with float32 values into float64 takes its
                # slow path (~13 ms per view at 150k faces); the sums are the same either way.
                n = len(self.grad_sum)
                self.grad_sum += np.bincount(idx, norm[seen], minlength=n)
                self.grad_count += np.bincount(idx, minlength=n)
                if c.split_min_px > 0:  # one Gaussian per face: idx has no repeats
                    cam = sample.camera
                    seen_t = torch.from_numpy(seen)
                    z = g["means"].detach()[seen_t].double().numpy() @ cam.R[2] + cam.t[2]
                    sigma = g["scales"].detach()[seen_t].amax(-1).double().numpy() * cam.fx / np.maximum(z, 1e-9)
                    self.size_px[idx] = np.maximum(self.size_px[idx], sigma)
            loss_sum += float(loss.item())
            mse = torch.mean((out.image.detach() - target) ** 2).item()
            psnr_sum += 10 * math.log10(1 / max(mse, 1e-12))
        stats = np.array([loss_sum, psnr_sum / b])
        if self.dist.world_size > 1:
            self._average_gradients(stats)
        for name in self.opt.nonfinite_gradients(p):
            _check_finite(it, **{f"gradient of {name}": p[name].grad})
        if self.refiner is not None:
            _check_finite(it, **self.refiner.gradients())
            self.refiner.step()
            _check_finite(it, **self.refiner.corrections())
        decay = _position_decay(c, it)
        # In the finest tail the roots' Gaussians are put back after the step (their split points
        # still move: they place the children, not the roots' own Gaussians).
        R = self.model.forest.num_roots if self._in_tail(it) else 0
        kept = {name: t.detach()[:R].clone() for name, t in p.items() if name != "split_logits"} if R else {}
        went_bad = self.opt.step(p, {"d_mu": decay})  # the parameters it left with a NaN or an inf
        with torch.no_grad():
            for name, rows in kept.items():
                p[name][:R] = rows
        for name in went_bad:
            _check_finite(it, **{name: p[name]})
            raise FloatingPointError(
                f"iteration {it}: the optimiser's second moment of {name} overflowed (a gradient above ~1e20: "
                "a loss weight far too large?); training stopped"
            )
        return {"loss": float(stats[0]), "psnr": float(stats[1])}

    def _average_gradients(self, stats: np.ndarray):
        """Mean of the ranks' gradients (each already the mean over its own views), so every
        rank takes the same optimiser step; `stats` (loss, PSNR) become the ranks' mean too."""
        n = self.dist.world_size
        tensors = [t for _, t in sorted(self.model.params.items())]
        if self.refiner is not None:
            tensors += [self.refiner.delta[k] for k in sorted(self.refiner.delta)]
        # A parameter no view touched has no gradient on any rank (the same structure everywhere).
        have = [t for t in tensors if t.grad is not None]
        if have:
            flat = torch.cat([t.grad.reshape(-1) for t in have])
            self.dist.all_reduce_sum_(flat).div_(n)
            o = 0
            for t in have:
                t.grad = flat[o : o + t.grad.numel()].view_as(t.grad).to(t.grad.dtype, copy=True)
                o += t.numel()
        s = self.dist.all_reduce_sum_(torch.from_numpy(stats))
        stats[:] = s.numpy() / n

    def _vertices(self, sample) -> torch.Tensor:
        if self.refiner is not None and self.refiner.has(sample.timestep_index):
            return self.refiner.vertices(sample.timestep_index)
        return torch.from_numpy(sample.vertices)

    # -- evaluation -----------------------------------------------------------------------
    @torch.no_grad()
    def evaluate(self, n_views: int) -> dict:
        from .metrics import defined_mean, psnr

        if self.val is None:
            return {}
        pick = np.linspace(0, len(self.val) - 1, min(n_views, len(self.val))).astype(int)
        values = []
        for i in pick:
            s = self.val[int(i)]
            g = self.model.gaussians(self._vertices(s), s.camera.center)
            opacities, behind = self.model.finer_inputs(g["opacities"])  # the whole avatar: Forest.render_set()
            out = render(
                g["means"], g["quats"], g["scales"], opacities, g["colors"], s.camera, self.background,
                compute_contrib=False, behind=behind,
            )  # fmt: skip
            values.append(psnr(out.image.numpy(), s.image, s.mask))
        score = defined_mean(values)  # views with an empty mask have no in-mask PSNR
        return {"val_psnr": score} if np.isfinite(score) else {}

    # -- persistence ----------------------------------------------------------------------
    def _save_checkpoint(self):
        arrays = self.model.forest.state()
        for name, t in self.model.params.items():
            arrays["param_" + name] = t.detach().numpy()
            arrays["adam_m_" + name] = self.opt.m[name].numpy()
            arrays["adam_v_" + name] = self.opt.v[name].numpy()
        arrays["adam_steps"] = self.opt.steps.numpy()
        if self.refiner is not None:
            arrays.update(self.refiner.state())
        arrays["grad_sum"] = self.grad_sum
        arrays["grad_count"] = self.grad_count
        arrays["size_px"] = self.size_px
        if self.rank_importance is not None:
            arrays["rank_importance"] = self.rank_importance
        arrays["state_json"] = np.array(
            json.dumps(
                {
                    "iteration": self.iteration,
                    "elapsed": self.elapsed,
                    "rng": self.rng.bit_generator.state,
                    "cut_rng": self.cut_rng.bit_generator.state,
                    "recent_psnr": list(self.recent_psnr),
                    "world_size": self.dist.world_size,
                    "settings": self.settings,
                    "iterations": self.cfg.iterations,
                    "effective_batch": self.dist.world_size * self.cfg.views_per_step,
                    "train_split": self.train_split,
                }
            )
        )
        atomic_savez(self.ckpt_path, **arrays)

    def _load_checkpoint(self):
        from ..io.safe_io import check_npz, npz_read_errors

        check_npz(self.ckpt_path, allow_text=("state_json",))
        with npz_read_errors(self.ckpt_path), np.load(self.ckpt_path, allow_pickle=False) as d:
            self._load_checkpoint_from(d)

    def _load_checkpoint_from(self, d):
        from ..avatar.avatar import Avatar

        def rows(name: str, shape: tuple, dtype) -> np.ndarray:
            # The compiled Adam pass writes rows without bounds checks: a member of the wrong
            # shape would corrupt memory, not fail.
            a = d[name]
            if a.shape != shape or a.dtype.kind != "f":
                raise ValueError(
                    f"{self.ckpt_path}: member '{name}' is {a.dtype}{list(a.shape)}, expected a float array "
                    f"{list(shape)}; the checkpoint is damaged: train into a new --out folder"
                )
            return a.astype(dtype, copy=True)

        forest = Forest.from_state(d, source=self.ckpt_path)
        if not np.array_equal(forest.template_faces, np.asarray(self.train.faces)):
            raise ValueError(
                f"{self.ckpt_path}: the checkpoint's template mesh ({len(forest.template_faces)} "
                f"faces) is not {self.data_dir}'s ({len(self.train.faces)} faces); resume with the "
                "--data it was trained on, or train into a new --out folder"
            )
        try:
            av = Avatar(
                forest,
                *(d["param_" + n] for n in PARAM_NAMES),
                f_rest=d["param_f_rest"] if "param_f_rest" in d else None,
            )
        except ValueError as exc:
            raise ValueError(f"{self.ckpt_path}: {exc}") from None
        if av.sh_degree != self.cfg.sh_degree:
            raise ValueError(
                f"{self.ckpt_path}: checkpoint has SH degree {av.sh_degree}, the configuration "
                f"{self.cfg.sh_degree}; resume with the same --sh-degree"
            )
        self.model = TorchAvatar(av)
        params = self.model.params
        n = forest.num_faces
        with torch.no_grad():
            logits = params["split_logits"]
            logits.copy_(
                torch.from_numpy(rows("param_split_logits", tuple(logits.shape), logits.detach().numpy().dtype))
            )
        self.opt = Adam(params, self.cfg.lr)
        for name, p in params.items():
            shape, dtype = tuple(p.shape), p.detach().numpy().dtype
            self.opt.m[name] = torch.from_numpy(rows("adam_m_" + name, shape, dtype))
            self.opt.v[name] = torch.from_numpy(rows("adam_v_" + name, shape, dtype))
        self.opt.steps = torch.from_numpy(rows("adam_steps", (n,), np.float64))
        self.grad_sum, self.grad_count = rows("grad_sum", (n,), np.float64), rows("grad_count", (n,), np.float64)
        # (checkpoints before split_min_px: no face is held back until the next growth step)
        self.size_px = rows("size_px", (n,), np.float64) if "size_px" in d else np.full(n, np.inf)
        if "rank_importance" in d:  # (measured before the last growth it may be shorter: step() measures again)
            self.rank_importance = rows("rank_importance", d["rank_importance"].shape[:1], np.float64)
        if not self.dist.is_main:  # the job's sums live on rank 0 (whatever world size wrote them)
            self.grad_sum[:] = 0
            self.grad_count[:] = 0
            self.size_px[:] = 0
        if self.refiner is not None:
            self.refiner.load_state(d, self.ckpt_path)
        state = json.loads(str(d["state_json"]))
        self.run_settings = state.get("settings") or _config_json_settings(self.out_dir)
        self.iteration, self.elapsed = state["iteration"], state["elapsed"]
        self.checkpoint_iteration = self.iteration
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = state["rng"]
        self.cut_rng = _cut_generator(self.cfg.seed)  # (checkpoints before it drew cuts from rng)
        if "cut_rng" in state:
            self.cut_rng.bit_generator.state = state["cut_rng"]
        self.recent_psnr = [float(x) for x in state.get("recent_psnr", [])]

    def _trim_log(self):
        """Drop the log lines written after the checkpoint (they will be written again); only
        once the resume is accepted: a refused one changes nothing in the run folder."""
        if os.path.exists(self.log_path):
            with open(self.log_path) as fh:
                lines = [ln.rstrip("\n") + "\n" for ln in fh if _log_iteration(ln) <= self.iteration]
            with atomic_open(self.log_path, "w") as fh:
                fh.writelines(lines)

    def _log(self, record: dict):
        record["world_size"] = self.dist.world_size
        with open(self.log_path, "a") as fh:
            fh.write(json.dumps(record) + "\n")

    def save_avatar(self) -> str:
        path = os.path.join(self.out_dir, "avatar.npz")
        meta = {
            "data": os.path.abspath(self.data_dir),
            "iterations": self.iteration,
            "train_seconds": self.elapsed,
            "config": asdict(self.cfg),
        }
        if self.refiner is not None:  # first: the avatar, written last, marks the pair complete
            refined = self.refiner.refined_arrays() | {"iteration": np.asarray(self.iteration, np.int64)}
            atomic_savez(os.path.join(self.out_dir, "flame_refined.npz"), **refined)
        self.model.to_avatar(meta).save(path)
        return path

    # -- loop -----------------------------------------------------------------------------
    def run(self, progress: bool = True, stop_after: int | None = None) -> dict:
        """Train to the configured iteration count (or `stop_after` more iterations)."""
        from tqdm import tqdm

        c, main = self.cfg, self.dist.is_main
        end = c.iterations if stop_after is None else min(c.iterations, self.iteration + stop_after)
        # Said in the bar, whose line is what the Blender add-on shows: a first iteration that
        # compiles would otherwise sit at 0 % for minutes without a word.
        # (On CUDA gsplat renders the steps: the CPU kernels compile later, if at all.)
        on_cpu = all(t.device.type == "cpu" for t in self.model.params.values())
        cold = progress and main and on_cpu and self.iteration < end and kernels_uncached()
        bar = tqdm(
            total=c.iterations,
            initial=self.iteration,
            disable=not (progress and main),
            dynamic_ncols=True,
            desc="train (compiling the kernels, once for this version)" if cold else "train",
        )
        try:  # the bar is closed before an error propagates: the error line comes after it, not under it
            recent = self.recent_psnr  # (restored on resume: the next log row averages the same steps)
            while self.iteration < end:
                t0 = time.perf_counter()
                stats = self.step()
                if cold:
                    bar.set_description("train", refresh=False)
                    cold = False
                self.iteration += 1
                it = self.iteration
                grown, growth = 0, None
                if self.growth.due(it):
                    grown = self._grow(it)
                    if self.dist.world_size > 1:  # the forest every rank holds after this growth step
                        growth = {"split": grown, "forest_digest_by_rank": [f"{v:016x}" for v in self.forest_digests]}
                self.elapsed += time.perf_counter() - t0
                recent.append(stats["psnr"])
                record = None
                if it % c.log_every == 0 or it == c.iterations:
                    counts = self.model.forest.level_counts().tolist()
                    record = {
                        "iteration": it,
                        "seconds": round(self.elapsed, 3),
                        "loss": stats["loss"],
                        "train_psnr": float(np.mean(recent)),
                        "faces": int(sum(counts)),
                        "level_counts": counts,
                    }
                    recent.clear()
                if main and (it % c.eval_every == 0 or it == c.iterations):
                    record = record or {"iteration": it, "seconds": round(self.elapsed, 3)}
                    record.update(self.evaluate(c.eval_views))
                if growth:
                    record = record or {"iteration": it, "seconds": round(self.elapsed, 3)}
                    record["growth"] = growth
                reset = self._reset_due(it)
                if reset:  # after the evaluation, which shows what the iterations made; before the checkpoint
                    self.reset_opacity()
                    record = record or {"iteration": it, "seconds": round(self.elapsed, 3)}
                    record["opacity_reset"] = self.cfg.opacity_reset_to
                if record and main:
                    self._log(record)
                    bar.set_postfix(
                        loss=f"{stats['loss']:.4f}",
                        psnr=f"{record.get('train_psnr', stats['psnr']):.2f}",
                        levels="/".join(map(str, self.model.forest.level_counts())),
                        refresh=False,
                    )
                if grown and main:
                    bar.write(
                        f"iteration {it}: split {grown} faces, depth cap {self.depth_cap(it)}, "
                        f"{self.model.num_faces} Gaussians"
                    )
                bar.update(1)
                if it % c.checkpoint_every == 0 or it == end:
                    if self.dist.world_size > 1:
                        self._fold_accumulators()
                        self._check_ranks_agree("parameters and optimiser state", self._state_digest())
                    if main:
                        self._save_checkpoint()
                    if self.dist.world_size > 1:  # the others learn that rank 0's save went through
                        self.dist.broadcast_ints(np.array([it]) if main else None)
                    self.checkpoint_iteration = it
                    if main and self.on_checkpoint is not None:
                        self.on_checkpoint(it)
        finally:
            bar.close()
        path = self.save_avatar() if main else os.path.join(self.out_dir, "avatar.npz")
        return {
            "avatar": path,
            "world_size": self.dist.world_size,
            "iterations": self.iteration,
            "seconds": self.elapsed,
            "level_counts": self.model.forest.level_counts().tolist(),
        }
