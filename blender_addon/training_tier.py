"""Where the configured Python finds the training tier (core/render, core/train) for Train and
Render Splats: the extension's own folder in a checkout; in an installed extension, its inner
archive unpacked into the extension's user folder (core/bridge/payload.py)."""

import os
import zipfile

from ..core.bridge import payload

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _user_dir():
    try:
        import bpy

        from . import ADDON_PACKAGE

        return bpy.utils.extension_path_user(ADDON_PACKAGE, path="training_tier", create=True)
    except Exception:  # not installed as an extension
        path = os.path.join(os.path.expanduser("~"), ".cache", "progressive_avatars", "training_tier")
        os.makedirs(path, exist_ok=True)
        return path


def folder(root=ROOT) -> str:
    """The folder whose core/ holds render/ and train/ ("" when ``root`` holds them itself).
    OSError naming the archive when it is missing or damaged."""
    if all(os.path.isfile(os.path.join(root, "core", t, "__init__.py")) for t in payload.TIERS):
        return ""
    archive = os.path.join(root, payload.PAYLOAD)
    try:
        return payload.unpack(archive, _user_dir())
    except (ValueError, zipfile.BadZipFile) as exc:
        raise OSError(f"{archive}: damaged training tier ({exc}); reinstall the extension") from exc
