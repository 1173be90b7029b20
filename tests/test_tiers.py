"""The product's central rule: what Blender imports never pulls in torch, numba or any package
a stock Blender lacks. Every Blender-tier module is imported in a fresh process with those
packages blocked, and ruff's banned-module-level-imports rule checks the same per folder."""

import json
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


def _tier_tree(root, extra=(), order=1, mtime=None):
    """A checkout's training tier in miniature (plus what must stay out of the payload),
    its files written in the given order with the given modification time."""
    files = [
        "core/render/__init__.py",
        "core/render/z.py",
        "core/render/sub/b.py",
        "core/render/notes.txt",
        "core/render/__pycache__/z.cpython-311.pyc",
        "core/train/__init__.py",
        "core/train/a.py",
        "core/io/skip.py",
        *extra,
    ]
    for name in files[::order]:
        path = os.path.join(root, name)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as fh:
            fh.write(f"# {name}\n")
        if mtime is not None:
            os.utime(path, (mtime, mtime))
    return str(root)


def test_payload_holds_the_training_tiers_modules_reproducibly(tmp_path):
    """build_payload packs core/render and core/train's .py files (no data, caches or other
    tiers), in sorted order, and one tree gives one archive whenever and in whatever order its
    files were written; a checkout without a tier's package is refused."""
    import zipfile

    from progressive_avatars.core.bridge import payload

    a = _tier_tree(tmp_path / "a", mtime=1_600_000_000)
    b = _tier_tree(tmp_path / "b", order=-1, mtime=1_700_000_000)
    want = [
        "core/render/__init__.py",
        "core/render/sub/b.py",
        "core/render/z.py",
        "core/train/__init__.py",
        "core/train/a.py",
    ]
    assert payload.build_payload(a, str(tmp_path / "a.pyz")) == want
    assert payload.build_payload(b, str(tmp_path / "b.pyz")) == want
    with zipfile.ZipFile(tmp_path / "a.pyz") as z:
        assert z.namelist() == want
    assert (tmp_path / "a.pyz").read_bytes() == (tmp_path / "b.pyz").read_bytes()
    os.remove(os.path.join(a, "core", "train", "__init__.py"))
    with pytest.raises(FileNotFoundError, match="no training-tier package to pack"):
        payload.build_payload(a, str(tmp_path / "c.pyz"))


def test_unpack_once_per_payload_and_refuse_foreign_members(tmp_path):
    """unpack: once per archive (a second call finds the folder done and leaves it), again over
    an attempt left incomplete, a new folder for another archive (the old version's removed,
    another process's unpacking in progress left alone); members outside core/render and
    core/train are refused and leave nothing behind."""
    import zipfile

    from progressive_avatars.core.bridge import payload

    user = tmp_path / "user"
    pa = str(tmp_path / "a.pyz")
    payload.build_payload(_tier_tree(tmp_path / "a"), pa)
    d1 = payload.unpack(pa, str(user))
    assert open(os.path.join(d1, "core", "train", "a.py")).read() == "# core/train/a.py\n"
    open(os.path.join(d1, "mark"), "w").close()
    assert payload.unpack(pa, str(user)) == d1 and os.path.exists(os.path.join(d1, "mark"))  # not unpacked again
    os.remove(os.path.join(d1, ".unpacked"))  # an attempt that did not finish
    assert payload.unpack(pa, str(user)) == d1
    assert not os.path.exists(os.path.join(d1, "mark")) and os.path.exists(os.path.join(d1, ".unpacked"))
    pb = str(tmp_path / "b.pyz")
    payload.build_payload(_tier_tree(tmp_path / "b", extra=("core/train/new.py",)), pb)
    (user / ".unpack-other").mkdir()  # another process, still unpacking
    d2 = payload.unpack(pb, str(user))
    assert d2 != d1 and os.path.exists(os.path.join(d2, "core", "train", "new.py"))
    assert sorted(os.listdir(user)) == sorted([".unpack-other", os.path.basename(d2)])
    for i, member in enumerate(
        ("core/train/../../evil.py", "core/render", "core/io/x.py", "core/x.py", "/core/train/x.py")
    ):
        bad = str(tmp_path / f"bad{i}.pyz")
        with zipfile.ZipFile(bad, "w") as z:
            z.writestr("core/train/a.py", "")
            z.writestr(member, "")
        with pytest.raises(ValueError, match="unexpected member"):
            payload.unpack(bad, str(user))
        assert sorted(os.listdir(user)) == sorted([".unpack-other", os.path.basename(d2)]), member


def test_unpack_keeps_the_folder_another_process_completed(tmp_path, monkeypatch):
    """Two add-ons starting at once unpack the same archive: the one that finishes second finds
    the folder complete and keeps it (the first one's training may be importing from it),
    instead of removing it as an incomplete attempt and moving its own copy in."""
    from progressive_avatars.core.bridge import payload

    user = str(tmp_path / "user")
    pa = str(tmp_path / "a.pyz")
    payload.build_payload(_tier_tree(tmp_path / "a"), pa)
    real = payload.tempfile.mkdtemp
    other = []

    def mkdtemp(**kw):
        tmp = real(**kw)
        if not other:  # meanwhile the other process unpacks the same archive, and starts a run from it
            monkeypatch.setattr(payload.tempfile, "mkdtemp", real)
            other.append(payload.unpack(pa, user))
            open(os.path.join(other[0], "running"), "w").close()
        return tmp

    monkeypatch.setattr(payload.tempfile, "mkdtemp", mkdtemp)
    d = payload.unpack(pa, user)
    assert d == other[0] and os.path.exists(os.path.join(d, "running"))
    assert os.listdir(user) == [os.path.basename(d)]  # the second copy went away


def test_loader_passes_the_remaining_arguments_and_the_tier_folder(tmp_path):
    """loader(): the extension under pa_ext, TIER_FOLDER/core appended to pa_ext.core's path
    only when given, and the command's own arguments in sys.argv[1:]."""
    from progressive_avatars.core.bridge import payload

    ext = tmp_path / "ext"
    (ext / "core").mkdir(parents=True)
    (ext / "__init__.py").write_text("")
    (ext / "core" / "__init__.py").write_text("")
    body = "import json, pa_ext.core as c\nprint(json.dumps([sys.argv[1:], list(c.__path__)]))\n"
    for tier, path in (("", [str(ext / "core")]), ("/t", [str(ext / "core"), "/t/core"])):
        out = subprocess.run(
            [sys.executable, "-c", payload.loader(body), str(ext), tier, "a", "--b"], capture_output=True, text=True
        )
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout) == [["a", "--b"], path]


def test_build_extension_ships_the_payload_and_reports_a_failed_tool(tmp_path):
    """build_extension stages the shipped files and the payload for Blender's tool (here a
    stand-in that zips its source folder and exits with the code it is given), returns the zip
    it made, and refuses a build the tool reports failed even when a zip was written."""
    import zipfile

    from progressive_avatars.core.bridge import payload

    root = _tier_tree(tmp_path / "root")
    for name in ("__init__.py", "blender_manifest.toml", "README.md", "blender_addon/__init__.py"):
        os.makedirs(os.path.dirname(os.path.join(root, name)) or root, exist_ok=True)
        with open(os.path.join(root, name), "w") as fh:
            fh.write("")
    tool = tmp_path / "tool.py"
    tool.write_text(
        textwrap.dedent("""
        import os, shutil, sys
        a = sys.argv
        src, out = a[a.index("--source-dir") + 1], a[a.index("--output-dir") + 1]
        zpath = shutil.make_archive(os.path.join(out, "ext-1.0"), "zip", src)
        print("created", zpath)
        sys.exit(int(os.environ.get("TOOL_EXIT", "0")))
    """)
    )
    z = payload.build_extension(root, str(tmp_path / "ok"), str(tool))
    with zipfile.ZipFile(z) as zf:
        names = set(zf.namelist())
    assert {"README.md", "blender_manifest.toml", "__init__.py", payload.PAYLOAD, "core/train/a.py"} <= names
    os.environ["TOOL_EXIT"] = "1"
    try:
        with pytest.raises(RuntimeError, match=r"build failed \(exit 1\)"):
            payload.build_extension(root, str(tmp_path / "bad"), str(tool))
    finally:
        del os.environ["TOOL_EXIT"]
