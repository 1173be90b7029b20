"""Train a progressive avatar.

    python scripts/train.py --data DIR --out RUN [--preset tiny|cpu|paper-cpu|paper] [--resume] [...]
    blender --background --python scripts/train.py -- --data DIR --out RUN ...
    torchrun --nproc-per-node N scripts/train.py --data DIR --out RUN ...   (data-parallel over views)

Writes RUN/avatar.npz (the trained avatar, no pickle), RUN/metrics.jsonl (one JSON object
per logged iteration), RUN/checkpoint.npz (atomic; --resume continues from it) and
RUN/config.json; RUN/resources.jsonl gets one line per invocation (wall seconds, peak resident
memory of the process), rewritten at every checkpoint, so a killed invocation still counts up to
its last checkpoint. Under torchrun every process renders its own views of each iteration
(effective batch: processes x --views-per-step), rank 0 alone writes RUN, and config.json and
every metrics line record the world size; --resume takes any number of processes. A second
training of the same RUN (another process, another job) is refused while one runs.
"""

import argparse
import json
import sys

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap

# --coarse-mode: (coarse_stand_ins, coarse_backdrop) of the training config
COARSE_MODES = {"cumulative": (False, False), "stand-ins": (True, False), "backdrop": (True, True)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="dataset folder (transforms_train.json, ...)")
    ap.add_argument("--out", required=True, help="run folder to write")
    ap.add_argument("--preset", default="cpu", help="tiny | cpu | paper-cpu | paper (default cpu)")
    ap.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint.npz")
    ap.add_argument(
        "--overwrite",
        action="store_true",
        help="start over in a RUN that already holds a checkpoint or avatar (refused without it)",
    )
    ap.add_argument("--iterations", type=int)
    ap.add_argument("--max-depth", type=int)
    ap.add_argument("--supervision", choices=["all", "sampled", "base", "finest"])
    ap.add_argument(
        "--finest-tail",
        type=float,
        help="last fraction of the iterations that supervises the finest level alone, the base faces kept as they are",
    )
    ap.add_argument(
        "--uniform",
        action="store_true",
        help="ablation: uniform subdivision to --max-depth (every face; --max-faces must hold them all)",
    )
    ap.add_argument(
        "--level-weights",
        type=_weights,
        metavar="W0,W1,...",
        help="per-level loss weights by level index; later levels take the last (default all 1)",
    )
    ap.add_argument(
        "--coarse-levels",
        type=_weights,
        metavar="F1,F2,...",
        help="coarse levels above the template, as fractions of its face count (default 1/32,1/16)",
    )
    ap.add_argument("--no-coarse", action="store_true", help="no coarse levels (the paper's levels; ablation)")
    ap.add_argument(
        "--coarse-mode",
        choices=sorted(COARSE_MODES),
        help="how the coarse levels render (docs/FORMAT.md 2.4): cumulative (in every prefix and in the finished "
        "avatar, as the paper's levels), stand-ins (each makes way once the template faces of its region have "
        "arrived) or backdrop (stand-ins that then stay behind every other Gaussian); default backdrop (cumulative in "
        "the paper presets)",
    )
    for mode in ("stand-ins", "backdrop"):
        ap.add_argument(
            f"--coarse-{mode}", dest="coarse_mode", action="store_const", const=mode, help=f"--coarse-mode {mode}"
        )
    ap.add_argument("--coarse-weight", type=float, help="factor on the coarse levels' loss weights (default 0.5)")
    ap.add_argument(
        "--prefix-cuts",
        type=int,
        metavar="N",
        help="N more images per step whose prefix ends inside a random level, in stream order (default 0)",
    )
    ap.add_argument("--prefix-cut-weight", type=float, help="factor on the in-level prefixes' loss weights (default 1)")
    ap.add_argument(
        "--whole-with-backdrop",
        action="store_true",
        help="with --coarse-mode backdrop, train the whole avatar's image with the stand-ins behind it too "
        "(default: without them, so a PLY of the finished avatar shows what the stream does)",
    )
    ap.add_argument(
        "--backdrop-cuts",
        type=int,
        metavar="N",
        help="with --coarse-mode backdrop, N more images per step whose prefix ends inside the template level (default 1)",
    )
    ap.add_argument("--grad-threshold", type=float)
    ap.add_argument("--max-faces", type=int)
    ap.add_argument(
        "--grow-to",
        type=float,
        metavar="X",
        help="grow by a budget to X times the base faces (largest gradients above the threshold); 0: threshold only",
    )
    ap.add_argument(
        "--split-min-px",
        type=float,
        metavar="PX",
        help="split only leaves whose Gaussian reaches PX pixels (largest sigma) in some training view; 0: any size",
    )
    ap.add_argument(
        "--grow-stop",
        type=float,
        metavar="F",
        help="fraction of the iterations after which the forest stops growing (the depth cap reaches "
        "--max-depth there; the rest trains the grown forest)",
    )
    ap.add_argument(
        "--opacity-reset-every",
        type=int,
        metavar="N",
        help="every N iterations while the forest grows, cut every opacity to 0.01 (as 3DGS and "
        "GaussianAvatars train); 0: never (default)",
    )
    ap.add_argument("--seed", type=int)
    ap.add_argument(
        "--flame-model",
        help="your FLAME model file (generic_model.pkl / flame2023.pkl / .npz), "
        "for FLAME-mode datasets (flame_param_path)",
    )
    ap.add_argument(
        "--refine-flame",
        action="store_true",
        help="learn per-timestep corrections of the tracked FLAME expression, pose and translation",
    )
    ap.add_argument(
        "--sh-degree",
        type=int,
        choices=[0, 1, 2, 3],
        help="view-dependent colour bands (default 0; the stream carries the DC colour only)",
    )
    ap.add_argument("--image-cache-mb", type=float, help="memory for decoded training images (LRU by bytes)")
    ap.add_argument(
        "--views-per-step",
        type=int,
        help="training views per iteration and process (default 1; under torchrun the batch is this x processes)",
    )
    ap.add_argument(
        "--threads",
        type=int,
        help="torch and numba threads per process (default: all cores; under torchrun cores // processes per node)",
    )
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(_bootstrap.script_args() if argv is None else argv)
    import time

    t0 = time.perf_counter()

    from progressive_avatars.core.train.distributed import Dist
    from progressive_avatars.core.train.trainer import config_for

    try:
        cfg = config_for(
            args.preset,
            iterations=args.iterations,
            max_depth=args.max_depth,
            supervision=args.supervision,
            finest_tail=args.finest_tail,
            level_weights=args.level_weights,
            uniform=args.uniform or None,
            grad_threshold=args.grad_threshold,
            max_faces=args.max_faces,
            grow_to=args.grow_to,
            split_min_px=args.split_min_px,
            grow_stop=args.grow_stop,
            opacity_reset_every=args.opacity_reset_every,
            seed=args.seed,
            sh_degree=args.sh_degree,
            coarse_levels=() if args.no_coarse else args.coarse_levels,
            coarse_weight=args.coarse_weight,
            **dict(zip(("coarse_stand_ins", "coarse_backdrop"), COARSE_MODES.get(args.coarse_mode, (None, None)))),
            prefix_cuts=args.prefix_cuts,
            prefix_cut_weight=args.prefix_cut_weight,
            backdrop_cuts=args.backdrop_cuts,
            whole_without_backdrop=False if args.whole_with_backdrop else None,
            refine_flame=args.refine_flame or None,
            image_cache_mb=args.image_cache_mb,
            flame_model=_os.path.abspath(args.flame_model) if args.flame_model else None,
            views_per_step=args.views_per_step,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.threads is not None and args.threads < 1:
        print(f"error: --threads must be at least 1, got {args.threads}", file=sys.stderr)
        return 2
    from progressive_avatars.core.train.memory import retain_freed_memory

    retain_freed_memory()  # this process trains: freed arrays are reused by the next step
    try:
        dist = Dist.from_env(threads=args.threads)  # world size 1 without torchrun
    except ValueError as exc:  # a bad PA_DIST_TIMEOUT: before joining the job
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rc = _train(args, cfg, dist, t0)
    if rc == 0:  # after a failure the group is left to the process exit (a dead peer cannot say goodbye)
        dist.close()
    return rc


def _train(args, cfg, dist, t0):
    who = f"rank {dist.rank}: " if dist.world_size > 1 else ""
    if dist.world_size > 1:
        import signal

        signal.signal(signal.SIGTERM, _stopped_by_launcher)
    resources = _Resources(args.out, t0)
    made = dist.is_main and not _os.path.exists(args.out)
    try:
        return _train_locked(args, cfg, dist, resources, who)
    finally:
        if made:
            _remove_unstarted(args.out)


def _remove_unstarted(out):
    """A run folder this invocation made and never started (bad --data, a refused setting): gone
    again, rather than left holding only its lock file."""
    try:
        if set(_os.listdir(out)) <= {".train.lock"}:
            if _os.path.exists(_os.path.join(out, ".train.lock")):
                _os.remove(_os.path.join(out, ".train.lock"))
            _os.rmdir(out)
    except OSError:
        pass


def _train_locked(args, cfg, dist, resources, who):
    import contextlib

    from progressive_avatars.core.io.atomic import os_error_text
    from progressive_avatars.core.train.distributed import run_lock
    from progressive_avatars.core.train.trainer import Trainer, kept_text, raised_from

    trainer = None
    with contextlib.ExitStack() as stack:
        try:
            if dist.is_main:  # the writer of RUN holds its lock for the whole run
                stack.enter_context(run_lock(args.out))
            trainer = Trainer(
                args.data,
                args.out,
                cfg,
                resume=args.resume,
                progress=not args.no_progress,
                dist=dist,
                overwrite=args.overwrite,
                coarse_mode_given=args.coarse_mode is not None,
            )
            if dist.is_main:
                trainer.on_checkpoint = resources.write
                if args.overwrite and not args.resume and _os.path.exists(resources.path):
                    _os.remove(resources.path)  # the replaced run's invocations
        except (ValueError, FileNotFoundError) as exc:
            print(f"error: {who}{exc}", file=sys.stderr)
            return 2
        except OSError as exc:
            print(f"error: {who}{os_error_text(exc, args.out)}", file=sys.stderr)
            return 2
        except RuntimeError as exc:  # the run folder is locked by another training; ranks disagree
            print(f"error: {who}{_lost_peer(exc, args.out) or exc}", file=sys.stderr)
            return 2
        except _Stopped:
            print(f"error: {who}stopped by the launcher before training began", file=sys.stderr)
            return 143
        try:
            summary = trainer.run(progress=not args.no_progress)
        except FloatingPointError as exc:  # NaN/inf: the message says training stopped
            kept = kept_text(args.out, trainer.checkpoint_iteration, dist.world_size > 1)
            print(f"error: {who}{exc}, {kept}", file=sys.stderr)
            return 3
        except OSError as exc:
            kept = kept_text(args.out, trainer.checkpoint_iteration, dist.world_size > 1)
            print(f"error: {who}{os_error_text(exc, args.out)}; training stopped, {kept}", file=sys.stderr)
            return 3
        except RuntimeError as exc:  # a rank died or hung (gloo), or the ranks' state diverged
            print(f"error: {who}{_lost_peer(exc, args.out, trainer.checkpoint_iteration) or exc}", file=sys.stderr)
            return 4
        except Exception as exc:
            # Ctrl-C, or the handler's _Stopped, while a compiled kernel ran reaches us wrapped
            # (SystemError: "returned a result with an exception set", the signal's as its context).
            if raised_from(exc, KeyboardInterrupt):
                return _stopped_by_ctrl_c(args, trainer, dist)
            if not raised_from(exc, _Stopped):
                raise
            kept = kept_text(args.out, trainer.checkpoint_iteration, True)
            print(
                f"error: {who}stopped by the launcher (SIGTERM: torchrun stops every process of the job when one "
                f"fails, its report names the root cause, or when it is stopped itself); training stopped at "
                f"iteration {trainer.iteration}, {kept}",
                file=sys.stderr,
            )
            return 143
        except KeyboardInterrupt:
            return _stopped_by_ctrl_c(args, trainer, dist)
        summary["peak_rss_mb"] = _peak_rss_mb()
        if dist.is_main:
            resources.write(summary["iterations"])  # under the run's lock, as everything written to RUN
    if not dist.is_main:
        return 0
    print(json.dumps(summary))
    return 0


def _stopped_by_ctrl_c(args, trainer, dist) -> int:
    from progressive_avatars.core.train.trainer import kept_text

    kept = kept_text(args.out, trainer.checkpoint_iteration, dist.world_size > 1)
    print(f"\nstopped (Ctrl-C) at iteration {trainer.iteration}; {kept}", file=sys.stderr)
    return 130


class _Stopped(Exception):
    """SIGTERM from torchrun: another process of the job failed."""


def _stopped_by_launcher(signum, frame):
    raise _Stopped()


def _lost_peer(exc: RuntimeError, out: str, checkpoint: int | None = None) -> str | None:
    """A clear line for a collective that failed because another process of the job died or
    stopped answering (None for other errors)."""
    import torch.distributed as td

    from progressive_avatars.core.train.trainer import kept_text

    text = str(exc).lower()
    peer = ("gloo", "nccl", "connection reset", "connection closed", "timed out", "timeout", "socket")
    if not (isinstance(exc, getattr(td, "DistError", ())) or any(w in text for w in peer)):
        return None
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    kept = kept_text(out, checkpoint, True)
    return f"another process of this torchrun job died or stopped answering ({first}); training stopped, {kept}"


class _Resources:
    """This invocation's row of RUN/resources.jsonl (wall seconds, peak RSS, iterations),
    replaced in place at every checkpoint and at the end (written whole to a temporary file,
    then renamed: a crash mid-write keeps the old file)."""

    def __init__(self, out: str, t0: float):
        import time

        self.path, self.t0 = _os.path.join(out, "resources.jsonl"), t0
        self.row_id = f"{time.time():.6f}-{_os.getpid()}"

    def write(self, iterations: int) -> None:
        import time

        rows = []
        if _os.path.exists(self.path):
            with open(self.path) as fh:
                rows = [ln for ln in fh.read().splitlines() if ln.strip() and f'"{self.row_id}"' not in ln]
        row = {
            "wall_seconds": round(time.perf_counter() - self.t0, 1),
            "peak_rss_mb": _peak_rss_mb(),
            "iterations": iterations,
            "invocation": self.row_id,
        }
        tmp = self.path + ".tmp"
        with open(tmp, "w") as fh:
            fh.write("\n".join([*rows, json.dumps(row)]) + "\n")
        _os.replace(tmp, self.path)


def _peak_rss_mb():
    """Peak resident memory of this process in MiB (ru_maxrss is KiB on Linux, bytes on macOS)."""
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 2**10), 1)


def _weights(text):
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


if __name__ == "__main__":
    sys.exit(main())
