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


def numba_cache_dir() -> str:
    """The numba cache of the processes that import the extension under its private package name
    ("pa_ext": the render worker, the Train runner). Never the sources' __pycache__: numba keys
    cache entries by source file, not by module, and an entry compiled as pa_ext names that
    module, so in a checkout a later ``python scripts/train.py`` (package progressive_avatars)
    would load it and fail with "No module named 'pa_ext'"."""
    try:
        import bpy

        from . import ADDON_PACKAGE

        return bpy.utils.extension_path_user(ADDON_PACKAGE, path="numba_cache", create=True)
    except Exception:  # not installed as an extension (a checkout)
        path = os.path.join(os.path.expanduser("~"), ".cache", "progressive_avatars", "numba_worker")
        os.makedirs(path, exist_ok=True)
        return path


def runner_env(cache_dir=None) -> dict:
    """The environment of a process that imports the extension as "pa_ext" (the render worker, the
    Train runner): spin-free OpenMP waits and its own numba cache (``cache_dir``, default
    numba_cache_dir())."""
    env = dict(os.environ)
    # OpenMP threads that spin while waiting starve numba's kernels on a small machine.
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    env["NUMBA_CACHE_DIR"] = cache_dir or numba_cache_dir()
    return env
