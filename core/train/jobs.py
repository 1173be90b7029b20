"""Train and export from the installed extension, in an external Python with torch and numba.

    python -m progressive_avatars.core.train.jobs train --data DIR --out RUN [--preset tiny]
        [--flame-model FILE] [--iterations N] [--no-export]

The Blender add-on runs this module from the extension's own folder (no checkout, no
scripts/): it trains (RUN/avatar.npz, as scripts/train.py does) and then writes the
importance-ordered stream RUN/avatar.pavs (as scripts/export.py --stream does), printing
progress lines the add-on parses and, last, "result: RUN/avatar.pavs". Errors exit with code
2 (bad input or settings) or 3 (training or the export stopped: a full disk, NaN; what is kept
to resume from is said) and one line naming the file or setting.
"""

from __future__ import annotations

import argparse
import os
import sys


def _train(args) -> int:
    import contextlib

    from ..io.atomic import os_error_text
    from .distributed import run_lock
    from .trainer import RunExistsError, Trainer, config_for, kept_text, raised_from

    flame = os.path.abspath(args.flame_model) if args.flame_model else None
    if flame and not os.path.isfile(flame):
        print(f"error: FLAME model file not found: {flame} (the add-on's FLAME model preference)", file=sys.stderr)
        return 2
    with contextlib.ExitStack() as stack:
        try:
            cfg = config_for(args.preset, iterations=args.iterations or None, flame_model=flame)
            stack.enter_context(run_lock(args.out))  # one training per run folder (as scripts/train.py)
            trainer = Trainer(args.data, args.out, cfg, resume=args.resume, overwrite=args.overwrite)
        except RunExistsError as exc:
            trained = os.path.exists(os.path.join(args.out, "avatar.npz"))
            unexported = trained and not args.no_export and not os.path.exists(os.path.join(args.out, "avatar.pavs"))
            if args.resume:
                why = str(exc)
            elif not trained:  # cancelled or stopped: its checkpoint can go on
                why = (
                    f"{args.out} holds an unfinished training (checkpoint.npz): tick Resume to continue it, or "
                    "Overwrite Run to start over, or choose another Run folder (Training > Run)"
                )
            elif unexported:  # stopped while its stream was written: Overwrite would discard the avatar
                why = (
                    f"{args.out} holds a trained avatar whose stream (avatar.pavs) was not written: tick Resume to "
                    "write it, or choose another Run folder (Training > Run)"
                )
            else:
                why = (
                    f"{args.out} already holds a trained run: choose another Run folder (Training > Run), "
                    "or tick Overwrite Run to start over"
                )
            print(f"error: {why}", file=sys.stderr)
            return 2
        except (ValueError, FileNotFoundError, RuntimeError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        try:
            trainer.run(progress=True)
        except (KeyboardInterrupt, Exception) as exc:
            # Ctrl-C while a compiled kernel runs arrives wrapped (trainer.raised_from).
            stop = raised_from(exc, KeyboardInterrupt)
            if not (stop or isinstance(exc, (FloatingPointError, OSError))):
                raise
            # One line, last (the add-on reports the last line): not a traceback under a progress bar.
            kept = kept_text(None, trainer.checkpoint_iteration, resume="Resume")  # short: the add-on shows 200 chars
            what = "stopped" if stop else os_error_text(exc, args.out) if isinstance(exc, OSError) else str(exc)
            stopped = "" if isinstance(exc, FloatingPointError) else "; training stopped"  # (its text says so)
            print(f"\nerror: {what}{stopped}, {kept}", file=sys.stderr)
            return 130 if stop else 3
        # The export holds the run's lock too: an Overwrite Run started meanwhile would empty the
        # folder under it and be left with this avatar's stream.
        return _export(args, flame)


def _export(args, flame) -> int:
    from ..io.atomic import os_error_text
    from .trainer import raised_from

    result = os.path.join(args.out, "avatar.npz")
    if not args.no_export:
        from ..io import run as runs
        from ..io.dataset import Dataset
        from ..stream.writer import write_stream

        try:
            avatar = runs.load_run_avatar(args.out)
            print("importance and stream", flush=True)
            W = runs.run_importance(args.out, avatar, args.data, progress=True, flame_model=flame)
            result = os.path.join(args.out, "avatar.pavs")
            rest = Dataset(args.data, None, flame_model=flame).canonical_vertices  # places the stand-ins' retirement
            write_stream(result, avatar, W, metadata={"run": os.path.abspath(args.out)}, drop_sh=True, vertices=rest)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        except (KeyboardInterrupt, Exception) as exc:
            stop = raised_from(exc, KeyboardInterrupt)  # (wrapped when a compiled kernel ran)
            if not (stop or isinstance(exc, OSError)):
                raise
            what = "stopped" if stop else os_error_text(exc, args.out)
            print(
                f"\nerror: {what}; the trained avatar (avatar.npz) is kept: tick Resume to write its stream",
                file=sys.stderr,
            )
            return 130 if stop else 3
    print(f"result: {result}", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="progressive_avatars.core.train.jobs",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = ap.add_subparsers(dest="job", required=True)
    t = sub.add_parser("train", help="train an avatar, then write its stream")
    t.add_argument("--data", required=True, help="dataset folder (transforms_train.json, ...)")
    t.add_argument("--out", required=True, help="run folder to write")
    t.add_argument("--preset", default="cpu", help="tiny | cpu | paper-cpu | paper (default cpu)")
    t.add_argument("--flame-model", help="your FLAME model file, for FLAME-mode datasets")
    t.add_argument("--iterations", type=int, default=0, help="override the preset's iterations (0: keep)")
    t.add_argument("--no-export", action="store_true", help="stop after training (RUN/avatar.npz)")
    t.add_argument("--overwrite", action="store_true", help="start over in a RUN that holds a trained run")
    t.add_argument("--resume", action="store_true", help="continue RUN's unfinished training from its checkpoint")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from .memory import retain_freed_memory

    retain_freed_memory()  # the job owns its process (the add-on starts it)
    return _train(args)


if __name__ == "__main__":
    sys.exit(main())
