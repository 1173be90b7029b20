"""The training tier as data inside the extension zip. Blender tier (stdlib only).

Blender imports only the Blender tier, so the zip's importable package holds nothing else.
Train and Render Splats run in the configured Python, which needs core/render and core/train
too: they travel in one inner archive (``PAYLOAD``, built by scripts/build_extension.py), which
the add-on unpacks into the extension's user folder, keyed by the archive's hash, and appends
to the private package's ``core`` path when it starts that Python (``loader``).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import zipfile

PAYLOAD = "training_tier.pyz"  # not *.zip: the manifest keeps built zips out of the extension
TIERS = ("render", "train")  # the core/ folders the payload holds
_DONE = ".unpacked"


def build_payload(root: str, path: str) -> list[str]:
    """Write the training tier under ``root`` (core/render, core/train: .py files) to the
    archive ``path``, reproducibly (sorted, fixed timestamps), so one tree gives one hash.
    Returns the archive's member names."""
    names = []
    for tier in TIERS:
        base = os.path.join(root, "core", tier)
        if not os.path.isfile(os.path.join(base, "__init__.py")):
            raise FileNotFoundError(f"{base}: no training-tier package to pack")
        for folder, dirs, files in os.walk(base):
            dirs[:] = sorted(d for d in dirs if d != "__pycache__")
            names += [
                os.path.relpath(os.path.join(folder, f), root).replace(os.sep, "/") for f in files if f.endswith(".py")
            ]
    names.sort()
    tmp = path + ".tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for name in names:
            info = zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with open(os.path.join(root, name), "rb") as fh:
                z.writestr(info, fh.read())
    os.replace(tmp, path)
    return names


def _digest(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def unpack(payload: str, user_dir: str) -> str:
    """The folder holding the payload's core/render and core/train, unpacked into
    ``user_dir/<hash>`` once (atomically: a temporary folder renamed when complete); folders
    of other versions are removed."""
    if not os.path.isfile(payload):
        raise FileNotFoundError(
            f"{payload}: the extension has no training tier; build it with scripts/build_extension.py"
        )
    key = _digest(payload)
    dest = os.path.join(user_dir, key)
    if not os.path.isfile(os.path.join(dest, _DONE)):
        os.makedirs(user_dir, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=".unpack-", dir=user_dir)
        try:
            with zipfile.ZipFile(payload) as z:
                for name in z.namelist():
                    parts = name.split("/")
                    if (
                        name.startswith("/")
                        or ".." in parts
                        or len(parts) < 3
                        or parts[0] != "core"
                        or parts[1] not in TIERS
                    ):
                        raise ValueError(f"{payload}: unexpected member {name!r}")
                z.extractall(tmp)
            open(os.path.join(tmp, _DONE), "w").close()
            if os.path.isdir(dest) and not os.path.isfile(os.path.join(dest, _DONE)):  # an incomplete earlier attempt
                shutil.rmtree(dest, ignore_errors=True)
            os.replace(tmp, dest)  # fails onto a folder another process completed meanwhile: kept
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            if not os.path.isfile(os.path.join(dest, _DONE)):  # another process may have won the race
                raise
    for other in os.listdir(user_dir):
        if other != key and not other.startswith(".unpack-"):
            shutil.rmtree(os.path.join(user_dir, other), ignore_errors=True)
    return dest


def loader(body: str) -> str:
    """Code for ``python -c CODE EXTENSION_ROOT TIER_FOLDER ARGS...``: imports the extension
    under the private name ``pa_ext`` (never a checkout or another installed copy), adds
    TIER_FOLDER/core (the unpacked payload; empty when the root has the training tier itself)
    to ``pa_ext.core``'s path, removes both arguments, then runs ``body``."""
    return (
        "import importlib, importlib.util, sys\n"
        "root, tier = sys.argv[1], sys.argv[2]\n"
        "del sys.argv[1:3]\n"
        "spec = importlib.util.spec_from_file_location('pa_ext', root + '/__init__.py', submodule_search_locations=[root])\n"
        "m = importlib.util.module_from_spec(spec); sys.modules['pa_ext'] = m; spec.loader.exec_module(m)\n"
        "if tier:\n"
        "    importlib.import_module('pa_ext.core').__path__.append(tier + '/core')\n" + body
    )


# Files of the repository root that go into the extension (blender_manifest.toml's
# paths_exclude_pattern then drops caches, tests and every tier Blender does not import).
_SHIPPED = ("__init__.py", "blender_manifest.toml", "README.md", "blender_addon", "core")


def build_extension(root: str, output_dir: str, blender_ext: str, python: str | None = None) -> str:
    """Build the extension zip from the checkout ``root`` with Blender's own extension tool
    (``blender_ext.py``): its package holds the Blender tier and blender_addon/, plus the
    training tier as the archive ``PAYLOAD``. Returns the zip's path; RuntimeError with the
    tool's output when it fails."""
    import subprocess
    import sys

    os.makedirs(output_dir, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="pa_ext_build_") as stage:
        for name in _SHIPPED:
            src = os.path.join(root, name)
            if os.path.isdir(src):
                shutil.copytree(src, os.path.join(stage, name), ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            elif os.path.isfile(src):
                shutil.copy2(src, os.path.join(stage, name))
        build_payload(root, os.path.join(stage, PAYLOAD))
        out = subprocess.run(
            [python or sys.executable, blender_ext, "build", "--source-dir", stage, "--output-dir", output_dir],
            capture_output=True,
            text=True,
        )
    made = [n for n in os.listdir(output_dir) if n.endswith(".zip") and os.path.join(output_dir, n) in out.stdout]
    if out.returncode != 0 or len(made) != 1:
        raise RuntimeError(f"{blender_ext} build failed (exit {out.returncode}):\n{out.stdout}{out.stderr}")
    return os.path.join(output_dir, made[0])
