r"""Generate the embedded synthetic head dataset (mesh mode, GaussianAvatars/VHAP layout).

    python scripts/make_synthetic.py --out runs/synthetic
    python scripts/make_synthetic.py --out runs/synthetic --contact-sheet docs/images/synthetic_contact_sheet.png \
        --closeup docs/images/synthetic_head_closeup.png
    python scripts/make_synthetic.py --preset paper --out runs/synthetic_paper      # the paper's scale
    python scripts/make_synthetic.py --preset paper --resolution-scale 0.25 --sequences 3 --frames 1 --out DIR

--preset paper: 16 cameras at 550x802 px, 10 sequences of 4 frames (9 train, 1 novel-expression
test; camera 8 held out), the 8192-face paper-scale template (FLAME-like uneven density) and images
ray-cast from its 16x finer displaced surface (core/synthetic/surface.py paper_head), two worker processes.
Options given explicitly override the preset's.

Writes canonical_mesh.npz, meshes/, images/, fg_masks/, transforms_{train,val,test}.json,
transforms.json, detail.npz, summary.json and contact_sheet.png into --out.
"""

import argparse
import math
import os
import sys

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap

from progressive_avatars.core.io.atomic import atomic_save_image, image_format, os_error_text
from progressive_avatars.core.synthetic import dataset


def _cannot_hold(path) -> str | None:
    """Why ``path`` cannot be made (missing folders are made when it is written): its nearest
    existing ancestor is a file, or a folder this process may not write in; None when it can."""
    folder = os.path.dirname(os.path.abspath(path))
    while not os.path.lexists(folder):
        folder = os.path.dirname(folder)
    if not os.path.isdir(folder):
        return f"under {folder}, which is not a folder"
    return None if os.access(folder, os.W_OK | os.X_OK) else f"no permission to write in {folder}"


PRESETS = {
    "default": dict(
        resolution=128,
        cameras=16,
        sequences=10,
        frames=8,
        supersample=2,
        template_subdivisions=4,
        workers=1,
        detail="default",
    ),
    "paper": dict(resolution=802, cameras=16, sequences=10, frames=4, supersample=2, workers=2, detail="paper"),
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="dataset directory (created)")
    ap.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="default",
        help="default: the demo's small dataset; paper: the paper's scale (see above)",
    )
    ap.add_argument(
        "--resolution", type=int, help="image height in pixels (width follows 550:802; default 128, paper 802)"
    )
    ap.add_argument(
        "--resolution-scale",
        type=float,
        default=1.0,
        help="multiply the resolution (e.g. 0.25 for a small version of a preset)",
    )
    ap.add_argument("--cameras", type=int)
    ap.add_argument("--sequences", type=int)
    ap.add_argument("--frames", type=int, help="frames per sequence")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--supersample", type=int, help="samples per pixel axis (anti-aliasing; default 2)")
    ap.add_argument(
        "--template-subdivisions",
        type=int,
        help="icosphere subdivisions of the tracked template (default preset): 4 = 5120 faces (default), "
        "3 = 1280 (coarser than the imaged surface, which stays at 4)",
    )
    ap.add_argument(
        "--surface-levels",
        type=int,
        help="paper preset: subdivisions of the imaged surface beyond the template (default 2: 16x its faces)",
    )
    ap.add_argument("--workers", type=int, help="processes rendering timesteps (default 1, paper 2)")
    ap.add_argument("--contact-sheet", default=None, help="also copy the contact sheet PNG here")
    ap.add_argument("--closeup", default=None, help="also render a frontal close-up strip PNG here")
    ap.add_argument("--closeup-height", type=int, default=384)
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    ap.add_argument("--overwrite", action="store_true", help="generate again into a folder that holds a dataset")
    args = ap.parse_args(_bootstrap.script_args(argv))
    kw = dict(PRESETS[args.preset])
    for key in (
        "resolution",
        "cameras",
        "sequences",
        "frames",
        "supersample",
        "template_subdivisions",
        "workers",
        "surface_levels",
    ):
        if getattr(args, key) is not None:
            kw[key] = getattr(args, key)
    if not (args.resolution_scale > 0 and math.isfinite(args.resolution_scale)):
        ap.error(f"--resolution-scale must be a positive number, got {args.resolution_scale}")
    if args.resolution is not None and args.resolution < 8:
        ap.error(f"--resolution is the image height in pixels, at least 8, got {args.resolution}")
    kw["resolution"] = max(8, int(round(kw["resolution"] * args.resolution_scale)))
    if args.closeup and args.closeup_height < 8:
        ap.error(f"--closeup-height must be at least 8 px, got {args.closeup_height}")
    # The pictures are written after the whole dataset: a path that cannot take one is refused now.
    for option, path in (("--contact-sheet", args.contact_sheet), ("--closeup", args.closeup)):
        if path:
            why = "a folder" if os.path.isdir(path) else _cannot_hold(path)
            if why is None and image_format(path) is None:
                why = "not an image extension PIL can write (.png, .jpg, ...)"
            if why:
                ap.error(f"{option} {path}: {why}")
    if os.path.lexists(args.out) and not os.path.isdir(args.out):
        ap.error(f"--out {args.out}: a file, not a dataset folder")
    if os.path.isdir(args.out):
        why = None if os.access(args.out, os.W_OK | os.X_OK) else "a folder this user cannot write into"
    else:
        why = _cannot_hold(args.out)
    if why:
        ap.error(f"--out {args.out}: {why}")

    try:
        summary = dataset.make_dataset(
            args.out, seed=args.seed, progress=not args.quiet, overwrite=args.overwrite, **kw
        )
    except ValueError as exc:  # counts the generator refuses, before it writes anything
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the folder cannot be written (the transforms come last: no dataset reads)
        print(f"error: {os_error_text(exc, args.out)}", file=sys.stderr)
        return 2
    sheet = dataset.contact_sheet(args.out, os.path.join(args.out, "contact_sheet.png"))
    if args.contact_sheet:
        from PIL import Image

        os.makedirs(os.path.dirname(os.path.abspath(args.contact_sheet)), exist_ok=True)
        with Image.open(sheet) as im:  # in the format its extension names, not always PNG bytes
            atomic_save_image(im, args.contact_sheet)
    if args.closeup:
        dataset.render_closeup(args.closeup, height=args.closeup_height, detail=kw.get("detail", "default"))
    s = summary
    print(
        f"wrote {s['out']}: {s['timesteps']} timesteps x {s['cameras']} cameras = {s['images']} images "
        f"({s['width']}x{s['height']}, {s['supersample']}x{s['supersample']} samples/pixel), "
        f"splits train/val/test = {s['train']}/{s['val']}/{s['test']} "
        f"(held-out camera {s['held_out_camera']}, test sequence {s['test_sequence']}), "
        f"mesh {s['vertices']} vertices / {s['faces']} faces (images ray-cast from {s['imaged_faces']} faces)"
    )
    print(
        f"{s['seconds']:.1f} s, {s['rays'] / 1e6:.1f} M rays ({s['rays_per_second'] / 1e6:.2f} M rays/s, "
        f"{s['intersector']}); contact sheet {sheet}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
