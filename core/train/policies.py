"""Growth and supervision as policy objects, validated when they are made (training tier).

The trainer asks a ``Supervision`` which levels one step renders and supervises, and a
``Growth`` when to split and which leaves. Both are built from ``TrainConfig`` fields (kept
as plain strings and numbers so run folders' config.json stay readable), and an unknown
value is an error at construction, before any work, not a silent fallback. RESUMABLE names
the settings a resumed run may change (the others define the run).
"""

from __future__ import annotations

import numpy as np

# What a run may change when it is resumed: how long it trains, how it logs and checkpoints, its
# memory and batch (a resume may use any number of processes). Everything else defines the run
# (the model, the losses, the schedule's shape, the seed's random stream); changed on a resume,
# it would silently mix two trainings, or fail mid-run where the fresh start refuses it at once.
RESUMABLE = (
    "iterations",
    "log_every",
    "eval_every",
    "eval_views",
    "checkpoint_every",
    "image_cache_mb",
    "views_per_step",
)

SUPERVISION_MODES = ("all", "sampled", "base", "finest")


class Supervision:
    """all: every cumulative level (the multi-level loss); sampled: the finest and one random
    coarser level per step; base: the finest and one random level of the base (the coarse
    levels and the template level, 0 .. ``base_level``), an ablation: the base prefixes are the
    ones finest-only training leaves poor, yet at the paper's scale this scored below "sampled"
    at every budget, the base's included (docs/BENCHMARKS.md, "Supervision modes at the paper's
    scale"); finest: the finest level only (the paper's ablation)."""

    def __init__(self, mode: str):
        if mode not in SUPERVISION_MODES:
            raise ValueError(f"supervision must be one of {', '.join(SUPERVISION_MODES)}, got {mode!r}")
        self.mode = mode

    def levels(self, top: int, rng: np.random.Generator, base_level: int = 0) -> list[int]:
        if self.mode == "finest" or top == 0:
            return [top]
        if self.mode == "sampled":
            return sorted({top, int(rng.integers(0, top))})
        if self.mode == "base":
            return sorted({top, int(rng.integers(0, min(base_level, top - 1) + 1))})
        return list(range(top + 1))


class Growth:
    """Adaptive (split leaves whose mean screen-space gradient exceeds the threshold, largest
    first within the face budget) or uniform (every leaf under the depth cap: the ablation).
    The depth cap rises from 1 to max_depth between grow_start and grow_stop.

    With ``grow_to`` > 0 the adaptive split count follows a budget instead of the threshold
    alone: after growth step i of n the forest holds up to base * (total / base) ** (i / n) faces
    (base: the roots, coarse ones included; total: min(max_faces, grow_to * base)), taking the
    largest mean gradients that still exceed the threshold. A threshold tuned on one image size
    and loss scale grows another scene by an unpredictable factor (4.3x instead of ~17x on the
    paper-scale head, issue 17); the stream's shape (how small the base is against the whole)
    should be set by the user, not found by it."""

    def __init__(
        self,
        *,
        iterations: int,
        max_depth: int,
        grow_every: int,
        grow_start: int,
        grow_stop: float,
        grad_threshold: float,
        max_faces: int,
        uniform: bool = False,
        grow_to: float = 0.0,
        min_px: float = 0.0,
    ):
        if grow_every < 1 or max_depth < 0 or max_faces < 0 or not 0 <= grow_stop <= 1:
            raise ValueError(
                f"growth: grow_every >= 1, max_depth >= 0, max_faces >= 0 and grow_stop in [0, 1] "
                f"(got {grow_every}, {max_depth}, {max_faces}, {grow_stop})"
            )
        if not np.isfinite(grad_threshold) or grad_threshold < 0:
            raise ValueError(f"growth: grad_threshold must be finite and >= 0, got {grad_threshold}")
        if not np.isfinite(grow_to) or not (grow_to == 0 or grow_to >= 1):
            raise ValueError(f"growth: grow_to must be 0 (off) or a factor >= 1, got {grow_to}")
        self.grow_to = float(grow_to)
        if not np.isfinite(min_px) or min_px < 0:
            raise ValueError(f"growth: split_min_px must be finite and >= 0, got {min_px}")
        self.min_px = float(min_px)
        self.iterations, self.max_depth, self.grow_every = int(iterations), int(max_depth), int(grow_every)
        self.grow_start, self.grow_stop = int(grow_start), float(grow_stop)
        # the last iteration after which the forest may grow (floored with a little slack: 0.58 * 750
        # is 434.99999999999994 in floating point, and the growth step at 435 was lost)
        self.last = int(np.floor(self.grow_stop * self.iterations + 1e-9))
        self.grad_threshold, self.max_faces, self.uniform = float(grad_threshold), int(max_faces), bool(uniform)

    @classmethod
    def from_config(cls, cfg) -> "Growth":
        return cls(
            iterations=cfg.iterations,
            max_depth=cfg.max_depth,
            grow_every=cfg.grow_every,
            grow_start=cfg.grow_start,
            grow_stop=cfg.grow_stop,
            grad_threshold=cfg.grad_threshold,
            max_faces=cfg.max_faces,
            uniform=cfg.uniform,
            grow_to=cfg.grow_to,
            min_px=cfg.split_min_px,
        )

    def due(self, it: int) -> bool:
        """Whether the forest grows after iteration ``it`` (uniform growth starts at once)."""
        # (never after the last iteration: its faces would never be trained)
        return (
            (self.uniform or it >= self.grow_start)
            and it % self.grow_every == 0
            and it <= self.last
            and it < self.iterations
        )

    @property
    def last_step(self) -> int:
        """The last iteration due() holds for (-1 when none does): what the growth schedule
        really ends at, below ``last`` unless it falls on a multiple of grow_every."""
        end = min(self.last, self.iterations - 1)
        start = 0 if self.uniform else self.grow_start
        step = end - end % self.grow_every
        return step if step >= max(start, self.grow_every) else -1

    def depth_cap(self, it: int) -> int:
        span = max(1, self.last - self.grow_start)
        return int(min(self.max_depth, 1 + (max(0, it - self.grow_start) * self.max_depth) // span))

    def pick(self, forest, grad_sum: np.ndarray, grad_count: np.ndarray, it: int, size_px=None) -> np.ndarray:
        """Sorted ids of the leaves to split after iteration ``it``; with ``min_px`` only those
        whose ``size_px`` (projected sigma in pixels) reaches it (adaptive growth only)."""
        leaves = forest.splittable()  # never coarse faces
        leaves = leaves[forest.depth[leaves] < self.depth_cap(it)]
        if self.min_px > 0 and not self.uniform:
            if size_px is None:
                raise ValueError("growth: split_min_px needs the faces' projected sizes")
            leaves = leaves[np.asarray(size_px)[leaves] >= self.min_px]
        if self.uniform:
            pick = leaves
        else:
            mean = grad_sum[leaves] / np.maximum(grad_count[leaves], 1)
            over = mean > self.grad_threshold
            # Largest gradients first when the face budget would be exceeded.
            pick = leaves[over][np.argsort(-mean[over], kind="stable")]
        room = max(0, (self.face_budget(forest.num_roots, it) - forest.num_faces) // 3)  # a split adds 3
        return np.sort(pick[:room])

    def face_budget(self, base: int, it: int) -> int:
        """The most faces the forest may hold after the growth step at iteration ``it``."""
        if self.uniform or self.grow_to == 0:
            return self.max_faces
        # the first due() iteration (the trainer asks after iteration 1 on, never after 0)
        first = max(self.grow_every, -(-self.grow_start // self.grow_every) * self.grow_every)
        steps = max(1, (self.last_step - first) // self.grow_every + 1)
        step = min(steps, max(1, (it - first) // self.grow_every + 1))
        # The schedule aims at the capped total, so a cap below base * grow_to is reached at the
        # last growth step, not early: reached early, the depth cap (which rises over the same
        # steps) would leave the deepest levels empty.
        target = min(float(self.max_faces), base * self.grow_to)
        if target <= base or step >= steps:  # exactly the target at the end (no rounding below it)
            return int(min(self.max_faces, max(target, base)))
        return min(self.max_faces, int(base * (target / base) ** (step / steps)))
