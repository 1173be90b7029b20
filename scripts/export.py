"""Export a trained run: the progressive stream, or a standard 3DGS PLY of one frame.

    python scripts/export.py --run RUN --stream OUT.pavs [--lossless]
    python scripts/export.py --run RUN --ply OUT.ply --budget 25 --frame 0 [--data DIR]

The stream (version 5, docs/FORMAT.md) opens with the coarse levels, then sends any face once its
parent has, by descending importance, computed over the training views on the levels up to each
face's own (pixels weighted by the error of the levels below) and cached in RUN/importance.npy.
Without --stream it is written to RUN/avatar.pavs (the PLY's budget is a prefix of it).
--budget is a percentage of the stream's bytes (header included; any value in [0, 100]: a
budget inside the coarse or template level exports what it holds, a budget with no whole record
an empty but valid PLY, with a note); --frame a timestep index of the dataset (its mesh drives
the Gaussians; one it lacks is refused before any work).
"""

import argparse
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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--data", help="dataset folder (default: the one the run trained on)")
    ap.add_argument("--flame-model", help="FLAME model for FLAME-mode datasets (default: the run's)")
    ap.add_argument("--stream", help="write the progressive stream here")
    ap.add_argument("--lossless", action="store_true", help="float32 records instead of quantised ones")
    ap.add_argument("--ply", help="write a 3DGS PLY of one frame here")
    ap.add_argument("--budget", type=float, default=100.0, help="percent of the stream (PLY export)")
    ap.add_argument("--frame", type=int, default=0, help="timestep index (PLY export)")
    ap.add_argument("--max-views", type=int, default=120, help="training views used for importance")
    ap.add_argument(
        "--drop-sh",
        action="store_true",
        help="stream an avatar trained with SH degree > 0 (records carry its DC colour only)",
    )
    args = ap.parse_args(_bootstrap.script_args() if argv is None else argv)
    if not args.stream and not args.ply:
        ap.error("nothing to do: give --stream and/or --ply")
    if not (0.0 <= args.budget <= 100.0):  # also refuses nan (every comparison is False)
        ap.error(f"--budget is a percentage of the stream's bytes in [0, 100], got {args.budget}")
    if args.max_views < 1:
        ap.error(f"--max-views must be at least 1, got {args.max_views}")

    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.stream.writer import write_stream

    try:
        avatar = runs.load_run_avatar(args.run)
        data = runs.run_data_dir(args.run, args.data)
        ds = Dataset(data, None, flame_model=runs.run_flame_model(args.run, args.flame_model))
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    # A frame the dataset lacks is refused before the importance pass (minutes on a large run)
    # and before any file is written.
    if args.ply and args.frame not in set(int(t) for t in ds.timesteps):
        print(f"error: {data}: no timestep {args.frame} (have {ds.timesteps[0]}..{ds.timesteps[-1]})", file=sys.stderr)
        return 2
    for path in (args.stream, args.ply):  # an output folder that cannot be made fails before the work
        folder = os.path.dirname(os.path.abspath(path)) if path else None
        if folder:
            try:
                os.makedirs(folder, exist_ok=True)
            except OSError as exc:
                return _cannot_write(path, exc)
    try:
        W = runs.run_importance(args.run, avatar, data, max_views=args.max_views)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    stream_path = args.stream or os.path.join(args.run, "avatar.pavs")
    try:
        info = write_stream(
            stream_path,
            avatar,
            W,
            quantize=not args.lossless,
            metadata={"run": os.path.abspath(args.run)},
            drop_sh=args.drop_sh,
            vertices=ds.canonical_vertices,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the previous file, if any, is kept (written whole, then renamed)
        return _cannot_write(stream_path, exc)
    result = {"stream": stream_path, "bytes": os.path.getsize(stream_path), "gaussians": avatar.num_gaussians}
    if args.ply:
        import numpy as np

        from progressive_avatars.core.io.ply import write_ply
        from progressive_avatars.core.avatar.avatar import sh_to_rgb

        part = read_stream(stream_path, percent=args.budget)
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
        if avatar.sh_degree:  # every band, from the trained avatar's faces of this prefix
            # the prefix holds r roots, then the other faces: in the whole stream's decoded
            # avatar (info.order's faces) those are faces 0..r-1 and R..R+(held-r)-1
            k = np.arange(held)
            r = 0 if part is None else part.forest.num_roots
            mine = info.order[np.where(k < r, k, k - r + info.num_roots)][shown]
            g["sh_rest"] = avatar.f_rest[mine]
            g["colors"] = sh_to_rgb(avatar.f_dc[mine])
        try:
            write_ply(args.ply, g)
        except OSError as exc:
            return _cannot_write(args.ply, exc)
        result.update(
            ply=args.ply,
            ply_gaussians=n,
            budget=args.budget,
            frame=args.frame,
            head_complete=bool(part is not None and part.meta["stream"]["head_complete"]),
        )
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
