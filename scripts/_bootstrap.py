"""Make ``progressive_avatars`` importable for scripts, installed or not.

Scripts run as ``python scripts/X.py`` (package installed in the venv, or not) and as
``blender --background --python scripts/X.py -- args`` (Blender's own Python). In the
second case nothing is installed, so the repository root is registered as the package.
Also returns the script's own arguments (after Blender's ``--`` separator when present).
"""

import importlib.util
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# OpenMP threads that spin while waiting starve numba's kernels on a small machine (a 256²
# render went from ~100 ms to ~650 ms); the policy only counts if set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _ensure_package():
    try:
        import progressive_avatars  # noqa: F401

        return
    except ImportError:
        pass
    spec = importlib.util.spec_from_file_location(
        "progressive_avatars", os.path.join(ROOT, "__init__.py"), submodule_search_locations=[ROOT]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["progressive_avatars"] = module
    spec.loader.exec_module(module)


def script_args(argv=None):
    """The script's arguments: everything after ``--`` under Blender, else argv[1:].

    Under ``blender --background --python X.py`` argv[0] is the Blender binary and every
    argument before ``--`` is Blender's own; run as ``python X.py`` argv[0] is the script.
    """
    argv = sys.argv if argv is None else argv
    if "--" in argv:
        return argv[argv.index("--") + 1 :]
    if argv and argv[0].endswith(".py"):
        return argv[1:]
    return []


_ensure_package()
