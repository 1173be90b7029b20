"""Export a trained run: the progressive stream, and/or a standard 3DGS PLY of one frame.

    python scripts/export.py --run RUN --stream OUT.pavs [--lossless] [--drop-sh]
    python scripts/export.py --run RUN --ply OUT.ply --budget 25 --frame 0 [--data DIR]

The stream (version 5, docs/FORMAT.md) opens with the coarse levels, then sends any face once its
parent has, by descending importance, computed over the training views on the levels up to each
face's own (pixels weighted by the error of the levels below) and cached in RUN/importance.npz.
An export writes the files it is given and no other: --ply alone writes the PLY only, and leaves
any stream of the run (RUN/avatar.pavs, perhaps a lossless one) as it is: one frame's PLY is no
reason to replace a stream the user did not name. The PLY holds a prefix of the stream this
command would write with --stream (encoded in memory: quantised, or with --lossless float32;
the same command with --stream writes that very stream). --budget is a percentage of that
stream's bytes (header included; any value in [0, 100]: a budget inside the coarse or template
level exports what it holds, a budget with no whole record an empty but valid PLY, with a
note); --frame a timestep index of the dataset (its mesh drives the Gaussians; one it lacks is
refused before any work). The PLY is in the dataset's world frame (Y up for the synthetic data and
GaussianAvatars/VHAP datasets); the SH DC coefficients are written as trained (not clamped), so
higher bands add to them as in 3DGS.

A failed export changes nothing: every output path (an existing folder there, a folder that
cannot be made, --stream and --ply naming one file) and every refusal (a missing frame, an
avatar with SH bands streamed without --drop-sh) is checked before any work; output folders
are made and files written only once everything is computed, each file atomically (written
whole, then renamed over the old one), the PLY before the stream's rename, so a PLY that cannot
be written leaves the stream as it was. An avatar trained with SH degree > 0: a PLY keeps every
band of it (no flag needed); stream records carry the DC colour only, so --stream needs
--drop-sh to say that is meant.

The stream embeds the template (docs/FORMAT.md 2): a reader needs no tracked mesh to decode it.
scripts/evaluate.py scores, and writes as RUN/avatar.pavs over this one, a stream without it
(its budgets count what a receiver that has the mesh is sent); its --embed-template writes the
very bytes this command does.

An output path that is one of the run's own files (avatar.npz, checkpoint.npz, config.json,
metrics.jsonl, importance*, ...: any file in the run folder but a stream or a PLY) or a file
of the dataset is refused.
"""

import argparse
import contextlib
import errno
import json
import os
import sys

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap


def _cannot_write(path, exc: OSError) -> int:
    print(f"error: cannot write {path}: {exc.strerror or exc}", file=sys.stderr)
    return 2


def _unwritable(path) -> OSError | None:
    """Why `path` cannot be written as a file, checked without changing anything (None: it
    can, as far as can be told): it is a folder, or its nearest existing ancestor is not a
    folder this process may create entries in (missing folders are made at write time)."""
    full = os.path.abspath(path)
    if os.path.isdir(full):
        return IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR))
    folder = os.path.dirname(full)
    while not os.path.lexists(folder):
        folder = os.path.dirname(folder)
    if not os.path.isdir(folder):
        return NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR))
    if not os.access(folder, os.W_OK | os.X_OK):
        return PermissionError(errno.EACCES, os.strerror(errno.EACCES))
    return None


def _input_file(path, run, data) -> str | None:
    """What writing ``path`` would destroy that the run or the dataset reads ("a file of the
    run RUN", "a file of the dataset DATA"), or None. In the run folder only earlier exports (a
    stream, a PLY) may be replaced: everything else there (avatar.npz, checkpoint.npz,
    config.json, the logs, the importance caches) is the trained run itself."""
    if not os.path.isfile(path):
        return None
    real = os.path.realpath(path)
    if os.path.dirname(real) == os.path.realpath(run):
        return None if os.path.splitext(real)[1].lower() in (".pavs", ".ply") else f"a file of the run {run}"
    folder = os.path.realpath(data)
    return f"a file of the dataset {data}" if os.path.commonpath([real, folder]) == folder else None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--data", help="dataset folder (default: the one the run trained on)")
    ap.add_argument("--flame-model", help="FLAME model for FLAME-mode datasets (default: the run's)")
    ap.add_argument(
        "--stream",
        help="write the progressive stream here, its template embedded (readable without the mesh; "
        "evaluate.py's stream leaves it out unless --embed-template); without it, no stream is written",
    )
    ap.add_argument(
        "--lossless",
        action="store_true",
        help="float32 records instead of quantised ones (the stream's, and so the PLY's values and budget bytes)",
    )
    ap.add_argument("--ply", help="write a 3DGS PLY of one frame here")
    ap.add_argument("--budget", type=float, default=100.0, help="percent of the stream (PLY export)")
    ap.add_argument("--frame", type=int, default=0, help="timestep index (PLY export)")
    ap.add_argument("--max-views", type=int, default=120, help="training views used for importance")
    ap.add_argument(
        "--drop-sh",
        action="store_true",
        help="stream an avatar trained with SH degree > 0 (records carry its DC colour only; a PLY keeps "
        "every band and needs no --drop-sh)",
    )
    args = ap.parse_args(_bootstrap.script_args() if argv is None else argv)
    if not args.stream and not args.ply:
        ap.error("nothing to do: give --stream and/or --ply")
    if not (0.0 <= args.budget <= 100.0):  # also refuses nan (every comparison is False)
        ap.error(f"--budget is a percentage of the stream's bytes in [0, 100], got {args.budget}")
    if args.max_views < 1:
        ap.error(f"--max-views must be at least 1, got {args.max_views}")

    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.atomic import atomic_open
    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.stream.writer import build_stream

    # Every output path is checked before any work (and before anything is written or made).
    outputs = [p for p in (args.stream, args.ply) if p]
    for path in outputs:
        problem = _unwritable(path)
        if problem is not None:
            return _cannot_write(path, problem)
    if len(outputs) == 2 and os.path.realpath(args.stream) == os.path.realpath(args.ply):
        print(f"error: --stream and --ply name the same file ({args.ply})", file=sys.stderr)
        return 2
    try:
        avatar = runs.load_run_avatar(args.run)
        data = runs.run_data_dir(args.run, args.data)
        ds = runs.run_dataset(args.run, data, None, runs.run_flame_model(args.run, args.flame_model))
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for option, path in (("--stream", args.stream), ("--ply", args.ply)):
        what = path and _input_file(path, args.run, data)
        if what:
            print(
                f"error: {option} {path}: {what}, which an export must not overwrite: choose another path",
                file=sys.stderr,
            )
            return 2
    # A frame the dataset lacks, or a stream that would drop SH bands unasked, is refused before
    # the importance pass (minutes on a large run) and before any file is written.
    if args.ply and args.frame not in set(int(t) for t in ds.timesteps):
        print(f"error: {data}: no timestep {args.frame} (have {ds.timesteps[0]}..{ds.timesteps[-1]})", file=sys.stderr)
        return 2
    if args.stream and avatar.sh_degree and not args.drop_sh:
        print(
            f"error: --stream {args.stream}: the avatar has SH degree {avatar.sh_degree}; stream records carry "
            "the DC colour only (docs/FORMAT.md). Pass --drop-sh to stream its view-independent colour "
            "(a PLY keeps every band: --ply without --stream needs no --drop-sh)",
            file=sys.stderr,
        )
        return 2
    try:
        W = runs.run_importance(args.run, avatar, data, max_views=args.max_views, flame_model=args.flame_model)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:  # in memory: written (--stream) only once the PLY, if any, is
        stream_bytes, info = build_stream(
            avatar,
            W,
            quantize=not args.lossless,
            metadata={"run": os.path.abspath(args.run)},
            drop_sh=args.drop_sh or not args.stream,  # a PLY takes every band from the avatar itself
            vertices=ds.canonical_vertices,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = {"stream": args.stream, "bytes": len(stream_bytes), "gaussians": avatar.num_gaussians}
    g = None
    if args.ply:
        import numpy as np

        from progressive_avatars.core.avatar.avatar import sh_to_rgb

        part = read_stream(stream_bytes, percent=args.budget)
        held = 0 if part is None else part.num_gaussians
        shown = np.zeros(0, np.int64) if part is None else part.forest.drawn()  # no retired stand-ins
        n = len(shown)
        if part is None:  # the budget holds no whole record (e.g. less than the header)
            print(
                f"note: {args.budget:g} % of the stream ({int(args.budget / 100 * info.total_bytes):,} of "
                f"{info.total_bytes:,} bytes) holds no whole Gaussian (the header alone is {info.header_size:,} "
                f"bytes, the first whole head {info.head_bytes:,}); writing an empty PLY",
                file=sys.stderr,
            )
            z = np.zeros((0, 3), np.float32)
            g = {
                "means": z,
                "quats": np.zeros((0, 4), np.float32),
                "scales": z,
                "opacities": np.zeros(0, np.float32),
                "colors": z,
            }
        else:
            g = part.gaussians(ds.vertices_at(args.frame), ids=shown)
            behind = part.forest.render_set()[1]
            if behind is not None:  # backdrop stand-ins (docs/FORMAT.md 2.4)
                print(
                    f"note: {int(behind.sum()):,} retired coarse stand-ins left out of the PLY: this avatar draws "
                    "them behind every other Gaussian, which a depth-sorted 3DGS viewer cannot; the PLY "
                    "shows less where they would show through",
                    file=sys.stderr,
                )
        if avatar.sh_degree:  # every band, from the trained avatar's faces of this prefix
            # the prefix holds r roots, then the other faces: in the whole stream's decoded
            # avatar (info.order's faces) those are faces 0..r-1 and R..R+(held-r)-1
            k = np.arange(held)
            r = 0 if part is None else part.forest.num_roots
            mine = info.order[np.where(k < r, k, k - r + info.num_roots)][shown]
            g["sh_rest"] = avatar.f_rest[mine]
            g["colors"] = sh_to_rgb(avatar.f_dc[mine])
            g["f_dc"] = avatar.f_dc[mine]  # as trained: the bands add to it before any clamp
        result.update(
            ply=args.ply,
            ply_gaussians=n,
            budget=args.budget,
            frame=args.frame,
            head_complete=bool(part is not None and part.meta["stream"]["head_complete"]),
        )
    # Everything is computed: write. The stream's temporary is written first and renamed last,
    # after the PLY (itself atomic), so a PLY that cannot be written leaves the stream as it was.
    from progressive_avatars.core.io.ply import write_ply

    where, ply_written = None, False
    try:
        with contextlib.ExitStack() as stack:
            if args.stream:
                where = args.stream
                os.makedirs(os.path.dirname(os.path.abspath(args.stream)), exist_ok=True)
                stack.enter_context(atomic_open(args.stream)).write(stream_bytes)
            if args.ply:
                where = args.ply
                os.makedirs(os.path.dirname(os.path.abspath(args.ply)), exist_ok=True)
                write_ply(args.ply, g)
                ply_written = True
            where = args.stream  # its fsync and rename, on leaving
    except OSError as exc:
        if ply_written:
            print(f"note: the PLY {args.ply} was written; the stream was not", file=sys.stderr)
        return _cannot_write(where, exc)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
