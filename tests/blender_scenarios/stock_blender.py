"""What a Blender scenario starts with: a Blender that has nothing but Blender (numpy and bpy),
and the extension loaded from its folder under a package name of the scenario's choosing.

The scenarios run as files from this folder (so Python finds this module beside them)."""

import importlib.util
import os
import sys


def block(names):
    """Importing any of ``names`` fails from now on, as it would in a stock Blender."""

    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in names:
                raise ImportError(f"{name} is blocked (not in a stock Blender)")
            return None

    sys.meta_path.insert(0, Block())


def load_extension(root, package):
    """Import the extension at ``root`` as ``package`` and register it."""
    spec = importlib.util.spec_from_file_location(
        package, os.path.join(root, "__init__.py"), submodule_search_locations=[root]
    )
    pkg = importlib.util.module_from_spec(spec)
    sys.modules[package] = pkg
    spec.loader.exec_module(pkg)
    pkg.register()
    return pkg


def loaded(names):
    """The blocked modules that got imported anyway (must be none)."""
    return sorted(m for m in sys.modules if m.split(".")[0] in names)


def stepper(results):
    """A decorator that runs a scenario step at once, recording into ``results[step name]`` (its
    traceback under "error" if it raised) and leaving Object Mode behind it."""
    import traceback

    import bpy

    def step(fn):
        r = results[fn.__name__] = {}
        try:
            fn(r)
        except Exception:
            r["error"] = traceback.format_exc()
        if bpy.context.mode != "OBJECT" and bpy.context.active_object is not None:
            bpy.ops.object.mode_set(mode="OBJECT")
        return fn

    return step


def activate(obj, mode="OBJECT"):
    """``obj`` alone selected and active, in ``mode``."""
    import bpy

    if bpy.context.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    for o in bpy.context.selected_objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    if mode != "OBJECT":
        bpy.ops.object.mode_set(mode=mode)


def call(op, **kw):
    """The operator's result, or the message it reported (background Blender raises it)."""
    try:
        return sorted(op(**kw))
    except RuntimeError as exc:
        return str(exc)
