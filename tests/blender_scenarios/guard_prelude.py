"""Blender session run by test_blender_guard.py (a real file so it can be read, linted and run by hand)."""

import importlib.abc, sys

BLOCKED = __BLOCKED__


class _Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{name} is blocked: a stock Blender does not have it")


for _m in [m for m in sys.modules if m.split(".")[0] in BLOCKED]:
    del sys.modules[_m]
sys.meta_path.insert(0, _Block())
import json, os, time, traceback
import numpy as np
import bpy

ARGS = json.loads(sys.argv[-1])
R = {"errors": []}
arrays = {}
PKG = "bl_ext.user_default.progressive_avatars"


def section(name):
    def deco(fn):
        try:
            fn()
        except Exception:
            R["errors"].append(name + ": " + traceback.format_exc())

    return deco


def run_op(op, **kw):
    """Operator result, or the first line of the error it reported."""
    try:
        return list(op(**kw))
    except RuntimeError as exc:
        return str(exc).splitlines()[0]


bpy.ops.extensions.package_install_files(filepath=ARGS["zip"], repo="user_default", enable_on_install=True)
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob)
R["blocked_loaded"] = sorted({m.split(".")[0] for m in sys.modules} & set(BLOCKED))


def scene_state():
    """Everything a failed operator must leave as it was."""
    out = {
        kind: sorted(x.name for x in getattr(bpy.data, kind))
        for kind in ("objects", "meshes", "materials", "node_groups", "images", "collections")
    }
    out["attributes"] = {
        o.name: sorted(a.name for a in o.data.attributes) for o in bpy.data.objects if o.type == "MESH"
    }
    out["legend"] = {o.name: [[i.depth, i.faces] for i in o.pa_mesh.depth_legend] for o in bpy.data.objects}
    return out


def preview_of(mesh):
    pvs = [c for c in mesh.children if c.pa_avatar.is_preview]
    return pvs[0] if pvs else None


def instances(pv):
    dg = bpy.context.evaluated_depsgraph_get()
    geo = pv.evaluated_get(dg).evaluated_geometry()
    ip = geo.instances_pointcloud()
    if ip is not None:
        return len(ip.points)
    pc = geo.pointcloud
    return len(pc.points) if pc is not None else 0


def positions(pv):
    """Preview positions in stream order (the rank attribute)."""
    me = pv.data
    pos = np.empty(len(me.vertices) * 3, np.float32)
    me.attributes["position"].data.foreach_get("vector", pos)
    rank = np.empty(len(me.vertices), np.int32)
    me.attributes["rank"].data.foreach_get("value", rank)
    return pos.reshape(-1, 3)[np.argsort(rank)]


def import_mesh(path, **kw):
    for ob in bpy.context.selected_objects:
        ob.select_set(False)
    res = run_op(bpy.ops.import_scene.progressive_avatars_sequence, filepath=path, **kw)
    return res, bpy.context.active_object
