"""The product's central rule: what Blender imports never pulls in torch, numba or any package
a stock Blender lacks. Every Blender-tier module is imported in a fresh process with those
packages blocked, and ruff's banned-module-level-imports rule checks the same per folder."""

import os
import shutil
import subprocess
import sys
import textwrap

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BLOCKED = ("torch", "numba", "trimesh", "PIL", "scipy", "matplotlib", "plyfile", "tqdm")
BLENDER_TIER = ("geometry", "avatar", "stream", "io", "flame", "bridge")

# Run in a subprocess: a blocked name must fail at import wherever it is imported from.
IMPORT_ALL = textwrap.dedent("""
    import importlib, importlib.abc, os, pkgutil, sys
    BLOCKED = {blocked!r}

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"blocked in the Blender tier: {{name}}")
            return None

    for name in list(sys.modules):
        if name.split(".")[0] in BLOCKED:
            del sys.modules[name]
    sys.meta_path.insert(0, Block())
    import progressive_avatars.core as core
    names = []
    for pkg in {tier!r}:
        mod = importlib.import_module("progressive_avatars.core." + pkg)
        names.append(mod.__name__)
        for info in pkgutil.iter_modules(mod.__path__, mod.__name__ + "."):
            names.append(info.name)
    if {with_bpy!r}:
        import bpy  # noqa: F401
        addon = importlib.import_module("progressive_avatars.blender_addon")
        for info in pkgutil.iter_modules(addon.__path__, addon.__name__ + "."):
            names.append(info.name)
    for name in names:
        importlib.import_module(name)
    leaked = sorted(n for n in sys.modules if n.split(".")[0] in BLOCKED)
    assert not leaked, leaked
    print("imported", len(names))
""")


def _run(with_bpy):
    code = IMPORT_ALL.format(blocked=BLOCKED, tier=BLENDER_TIER, with_bpy=with_bpy)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)


def test_blender_tier_imports_without_training_packages():
    out = _run(with_bpy=False)
    assert out.returncode == 0, out.stdout + out.stderr
    assert int(out.stdout.split()[-1]) >= 15  # every Blender-tier module was imported


@pytest.mark.slow
@pytest.mark.blender
def test_blender_addon_imports_without_training_packages():
    pytest.importorskip("bpy")
    out = _run(with_bpy=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_tier_folders_say_their_tier():
    for pkg in os.listdir(os.path.join(ROOT, "core")):
        init = os.path.join(ROOT, "core", pkg, "__init__.py")
        if os.path.isfile(init):
            doc = open(init).read()
            assert "tier" in doc.lower(), f"{init}: the package docstring must name its tier"


def test_ruff_bans_training_imports_in_the_blender_tier(tmp_path):
    """The lint rule (pyproject [tool.ruff]) catches a module-level torch import in a Blender-tier
    module and nowhere else; the tree itself is clean."""
    ruff = shutil.which("ruff") or os.path.join(os.path.dirname(sys.executable), "ruff")
    if not os.path.exists(ruff):
        pytest.skip("ruff is not installed")
    clean = subprocess.run([ruff, "check", "--select", "TID253", "."], cwd=ROOT, capture_output=True, text=True)
    assert clean.returncode == 0, clean.stdout + clean.stderr
    bad = os.path.join(ROOT, "core", "stream", "_tier_probe.py")
    try:
        with open(bad, "w") as fh:
            fh.write("import torch  # noqa: F401\n")
        caught = subprocess.run([ruff, "check", "--select", "TID253", bad], cwd=ROOT, capture_output=True, text=True)
    finally:
        os.remove(bad)
    assert caught.returncode != 0 and "torch" in caught.stdout, caught.stdout


def test_code_is_formatted():
    """ruff format (pyproject [tool.ruff], line length 120) leaves every file as it is."""
    ruff = shutil.which("ruff") or os.path.join(os.path.dirname(sys.executable), "ruff")
    if not os.path.exists(ruff):
        pytest.skip("ruff is not installed")
    out = subprocess.run([ruff, "format", "--check", "."], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def _blender_ext():
    import importlib.util

    spec = importlib.util.find_spec("bpy")  # finds the module without importing it
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("bpy module not installed (its blender_ext.py builds the zip)")
    base = list(spec.submodule_search_locations)[0]
    return os.path.join(base, "5.0", "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")


def test_extension_zip_ships_the_blender_tier_and_the_training_tier_as_data(tmp_path):
    """The zip's importable package is exactly the Blender tier and blender_addon/: Blender can
    never import render/ or train/ from it. The training tier is the inner archive, and the
    loader the Train and Render Splats operators run finds it once unpacked (no checkout)."""
    import zipfile

    from progressive_avatars.core.bridge import payload

    zpath = payload.build_extension(ROOT, str(tmp_path / "dist"), _blender_ext())
    with zipfile.ZipFile(zpath) as z:
        names = z.namelist()
        inner = z.read(payload.PAYLOAD)
        z.extractall(tmp_path / "ext")
    py = [n for n in names if n.endswith(".py")]
    core_pkgs = {n.split("/")[1] for n in py if n.startswith("core/") and n.count("/") == 2}
    assert core_pkgs == set(BLENDER_TIER), core_pkgs
    assert all(n == "__init__.py" or n.split("/")[0] in ("blender_addon", "core") for n in py), py
    assert "core/__init__.py" in py and "blender_addon/__init__.py" in py
    # Every Blender-tier and add-on module of the checkout is shipped, nothing else.
    want = []
    for top in [os.path.join("core", p) for p in BLENDER_TIER] + ["blender_addon"]:
        want += [
            os.path.join(top, f).replace(os.sep, "/") for f in os.listdir(os.path.join(ROOT, top)) if f.endswith(".py")
        ]
    assert sorted(py) == sorted(want + ["__init__.py", "core/__init__.py"])
    # The payload: exactly the training tier's modules.
    (tmp_path / "inner.pyz").write_bytes(inner)
    with zipfile.ZipFile(tmp_path / "inner.pyz") as z:
        members = sorted(z.namelist())
    want = sorted(
        f"core/{t}/{f}" for t in payload.TIERS for f in os.listdir(os.path.join(ROOT, "core", t)) if f.endswith(".py")
    )
    assert members == want
    # Unpacked into a user folder (once: the same folder the second time), the loader imports the
    # training tier from there under the private package name, the rest from the extension.
    ext = str(tmp_path / "ext")
    tier = payload.unpack(os.path.join(ext, payload.PAYLOAD), str(tmp_path / "user"))
    assert payload.unpack(os.path.join(ext, payload.PAYLOAD), str(tmp_path / "user")) == tier
    body = "import pa_ext.core.train.jobs as j, pa_ext.core.io.run as r\nprint(j.__file__)\nprint(r.__file__)\n"
    block = "import sys; sys.modules['progressive_avatars'] = None\n"  # no checkout
    out = subprocess.run(
        [sys.executable, "-c", block + payload.loader(body), ext, tier],
        capture_output=True,
        text=True,
        cwd=str(tmp_path),
    )
    assert out.returncode == 0, out.stdout + out.stderr
    jobs, run = out.stdout.split()
    assert jobs == os.path.join(tier, "core", "train", "jobs.py") and run == os.path.join(ext, "core", "io", "run.py")


def test_architecture_module_map_matches_the_folders():
    """docs/ARCHITECTURE.md's module map names every core module and no module that is gone
    (a row may list siblings: "core/train/model.py, losses.py")."""
    doc = open(os.path.join(ROOT, "docs", "ARCHITECTURE.md")).read()
    named = set()
    for row in doc.splitlines():
        if row.startswith("| core/"):
            parts = [p.strip() for p in row.split("|")[1].split(",")]
            base = os.path.dirname(parts[0])
            named |= {p if "/" in p else f"{base}/{p}" for p in parts}
    present = set()
    for folder, _, files in os.walk(os.path.join(ROOT, "core")):
        rel = os.path.relpath(folder, ROOT).replace(os.sep, "/")
        present |= {f"{rel}/{f}" for f in files if f.endswith(".py") and f != "__init__.py"}
    assert not present - named, f"modules missing from the map: {sorted(present - named)}"
    assert not named - present, f"the map names modules that do not exist: {sorted(named - present)}"
