"""Generate the embedded synthetic head dataset (mesh mode, GaussianAvatars/VHAP layout).

    python scripts/make_synthetic.py --out runs/synthetic
    python scripts/make_synthetic.py --out runs/synthetic --contact-sheet docs/images/synthetic_contact_sheet.png \
        --closeup docs/images/synthetic_head_closeup.png

Writes canonical_mesh.npz, meshes/, images/, fg_masks/, transforms_{train,val,test}.json,
transforms.json, detail.npz, summary.json and contact_sheet.png into --out.
"""

import argparse
import os
import shutil
import sys

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap

from progressive_avatars.core.synthetic import head as synthetic


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="dataset directory (created)")
    ap.add_argument("--resolution", type=int, default=128, help="image height in pixels (width follows 550:802)")
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--sequences", type=int, default=10)
    ap.add_argument("--frames", type=int, default=8, help="frames per sequence")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--supersample", type=int, default=2, help="samples per pixel axis (anti-aliasing)")
    ap.add_argument("--template-subdivisions", type=int, default=4,
                    help="icosphere subdivisions of the tracked template: 4 = 5120 faces (default), "
                         "3 = 1280 (coarser than the imaged surface, which stays at 4)")
    ap.add_argument("--contact-sheet", default=None, help="also copy the contact sheet PNG here")
    ap.add_argument("--closeup", default=None, help="also render a frontal close-up strip PNG here")
    ap.add_argument("--closeup-height", type=int, default=384)
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    args = ap.parse_args(_bootstrap.script_args(argv))

    summary = synthetic.make_dataset(args.out, resolution=args.resolution, cameras=args.cameras,
                                     sequences=args.sequences, frames=args.frames, seed=args.seed,
                                     progress=not args.quiet, supersample=args.supersample,
                                     template_subdivisions=args.template_subdivisions)
    sheet = synthetic.contact_sheet(args.out, os.path.join(args.out, "contact_sheet.png"))
    if args.contact_sheet:
        os.makedirs(os.path.dirname(os.path.abspath(args.contact_sheet)), exist_ok=True)
        shutil.copyfile(sheet, args.contact_sheet)
    if args.closeup:
        synthetic.render_closeup(args.closeup, height=args.closeup_height)
    s = summary
    print(f"wrote {s['out']}: {s['timesteps']} timesteps x {s['cameras']} cameras = {s['images']} images "
          f"({s['width']}x{s['height']}, {s['supersample']}x{s['supersample']} samples/pixel), "
          f"splits train/val/test = {s['train']}/{s['val']}/{s['test']} "
          f"(held-out camera {s['held_out_camera']}, test sequence {s['test_sequence']}), "
          f"mesh {s['vertices']} vertices / {s['faces']} faces")
    print(f"{s['seconds']:.1f} s, {s['rays'] / 1e6:.1f} M rays ({s['rays_per_second'] / 1e6:.2f} M rays/s, "
          f"{s['intersector']}); contact sheet {sheet}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
