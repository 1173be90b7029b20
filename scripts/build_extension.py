"""Build the Blender extension zip: the Blender tier and blender_addon/ as its package, the
training tier (core/render, core/train) as the inner archive the Train and Render Splats
operators unpack for the configured Python (core/bridge/payload.py).

    python scripts/build_extension.py --out dist [--blender-ext PATH/blender_ext.py]

Blender's own tool (``blender --command extension build``) run on the repository root builds
a zip without the training tier: Train and Render Splats then say so.
"""

import argparse
import importlib.util
import os

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap  # noqa: E402

from progressive_avatars.core.bridge.payload import build_extension  # noqa: E402


def bpy_blender_ext():
    """blender_ext.py of the bpy module installed in this Python (None without bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        return None
    base = list(spec.submodule_search_locations)[0]
    for version in sorted(os.listdir(base), reverse=True):
        path = os.path.join(base, version, "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")
        if os.path.isfile(path):
            return path
    return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="output folder for the zip")
    ap.add_argument("--blender-ext", help="Blender's blender_ext.py (default: the installed bpy module's)")
    args = ap.parse_args(argv)
    # The zip is made after the payload is staged: an --out that cannot be a folder is refused now.
    folder = os.path.abspath(args.out)
    while not os.path.isdir(folder):
        if os.path.lexists(folder):
            ap.error(f"--out {args.out}: {folder} is a file, not a folder")
        folder = os.path.dirname(folder)
    if args.blender_ext and not os.path.isfile(args.blender_ext):
        ap.error(
            f"--blender-ext {args.blender_ext}: not a file (Blender's is its scripts/addons_core/bl_pkg/cli/blender_ext.py)"
        )
    tool = args.blender_ext or bpy_blender_ext()
    if not tool:
        ap.error(
            "blender_ext.py not found (no bpy module here): pass --blender-ext (Blender's scripts/addons_core/bl_pkg/cli/)"
        )
    try:
        print(build_extension(_bootstrap.ROOT, args.out, tool))
    except OSError as exc:  # e.g. a full disk or no permission: a message, not a traceback
        raise SystemExit(f"error: cannot write {exc.filename or args.out}: {exc.strerror or exc}") from None


if __name__ == "__main__":
    main(_bootstrap.script_args())
