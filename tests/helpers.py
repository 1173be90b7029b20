"""Builders shared by the tests (they live in the library so benchmarks can use them too)."""

from progressive_avatars.core.synthetic.shapes import depth6_precision, random_forest, sphere_mesh  # noqa: F401


# The start of a script run as a child bpy process (argv: the checkout root, an output folder):
# load_extension(name) registers the checkout's extension as the package `name`.
BPY_CHILD_PRELUDE = r"""
import importlib.util, json, os, sys, traceback
root, out = sys.argv[1:3]
import bpy
import numpy as np


def load_extension(name):
    spec = importlib.util.spec_from_file_location(name, os.path.join(root, "__init__.py"), submodule_search_locations=[root])
    pkg = importlib.util.module_from_spec(spec)
    sys.modules[name] = pkg
    spec.loader.exec_module(pkg)
    pkg.register()
    return pkg
"""


def run_bpy_child(text, folder, tag, env, name="child.py"):
    """Run ``text`` (starting with BPY_CHILD_PRELUDE) as a bpy child process on the checkout,
    output folder ``folder``; return its last "TAG {json}" report line, parsed (asserting
    there is one and that it carries no "error"), and its stdout."""
    import json
    import os
    import subprocess
    import sys

    script = os.path.join(str(folder), name)
    with open(script, "w") as fh:
        fh.write(text)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run(
        [sys.executable, script, root, str(folder)], capture_output=True, text=True, env=env, timeout=300
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(tag + " ")]
    assert lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    rep = json.loads(lines[-1][len(tag) + 1 :])
    assert "error" not in rep, rep["error"]
    return rep, proc.stdout
