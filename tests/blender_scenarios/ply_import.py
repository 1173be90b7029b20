"""Blender session run by test_blender_ply.py (a real file so it can be read, linted and run by hand)."""

import json, os, sys, traceback

import stock_blender

root, ply_path, out, blocked = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4].split(",")
stock_blender.block(blocked)
import bpy
import numpy as np

stock_blender.load_extension(root, "pa_blk")
R = {"errors": []}
A = {}
try:
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    res = bpy.ops.import_scene.progressive_avatars_splat_ply(filepath=ply_path, order="IMPORTANCE")
    obj = bpy.context.active_object
    R["import"] = list(res)
    st = obj.pa_avatar
    R["total"], R["bands"] = st.total, int(obj["pa_sh_bands"])
    me = obj.data

    def read(name, width, dtype=np.float32, field="value"):
        a = np.empty(len(me.vertices) * width, dtype)
        me.attributes[name].data.foreach_get(field, a)
        return a.reshape(-1, width) if width > 1 else a

    A["position"] = read("position", 3, field="vector")
    A["rank"] = read("rank", 1, np.int32)
    A["color"] = read("color", 4, field="color")
    st.budget = 40.0
    R["count_40"], R["mb_40"] = st.count, st.megabytes
    mod = obj.modifiers["PA Splats"]
    ng = mod.node_group
    key = next(
        i.identifier for i in ng.interface.items_tree if getattr(i, "name", "") == "Count" and i.in_out == "INPUT"
    )
    R["modifier_count"] = mod[key]
    dg = bpy.context.evaluated_depsgraph_get()
    R["instances"] = sum(
        1 for inst in dg.object_instances if inst.is_instance and inst.parent and inst.parent.original == obj
    )
    exp = os.path.join(out, "export_40.ply")
    R["export"] = list(bpy.ops.export_scene.progressive_avatars_ply(filepath=exp, world_space=False))
    obj.location = (1.0, 2.0, 3.0)
    bpy.context.view_layer.update()
    expw = os.path.join(out, "export_40_world.ply")
    R["export_world"] = list(bpy.ops.export_scene.progressive_avatars_ply(filepath=expw, world_space=True))
    res2 = bpy.ops.import_scene.progressive_avatars_splat_ply(filepath=ply_path, order="FILE")
    o2 = bpy.context.active_object
    rk = np.empty(len(o2.data.vertices), np.int32)
    o2.data.attributes["rank"].data.foreach_get("value", rk)
    A["rank_file"] = rk
    o2.pa_avatar.budget = 0.0
    R["count_0"] = o2.pa_avatar.count
    # The same splats from other tools: ASCII and big-endian (no plyfile here); the file is Y up
    # and stood up by the object's transform unless told otherwise
    R["z_up"] = [round(v, 6) for v in obj.matrix_world.to_euler()] == [round(1.5707963267948966, 6), 0.0, 0.0]
    for name in ("splats_ascii", "splats_big_endian"):
        try:
            R[f"import_{name}"] = list(
                bpy.ops.import_scene.progressive_avatars_splat_ply(
                    filepath=os.path.join(out, name + ".ply"), order="FILE"
                )
            )
        except RuntimeError as exc:
            R[f"import_{name}"] = str(exc)
            continue
        o3 = bpy.context.active_object
        p3 = np.empty(len(o3.data.vertices) * 3, np.float32)
        o3.data.attributes["position"].data.foreach_get("vector", p3)
        A[f"position_{name}"] = p3.reshape(-1, 3)
    bpy.ops.import_scene.progressive_avatars_splat_ply(filepath=ply_path, order="FILE", z_up=False)
    R["z_up_off_identity"] = bpy.context.active_object.matrix_world.is_identity
    # A broken file: a clear message naming it, and nothing added to the scene.
    bad = os.path.join(out, "bad.ply")
    with open(bad, "wb") as fh:
        fh.write(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n2\n3\n")
    n_before = len(bpy.data.objects), len(bpy.data.meshes)
    try:
        R["bad"] = list(bpy.ops.import_scene.progressive_avatars_splat_ply(filepath=bad))
    except RuntimeError as exc:
        R["bad_message"] = str(exc)
    R["bad_left_scene"] = (len(bpy.data.objects), len(bpy.data.meshes)) == n_before
    R["blocked_loaded"] = stock_blender.loaded(blocked)
except Exception:
    R["errors"].append(traceback.format_exc())
np.savez(os.path.join(out, "arrays.npz"), **A)
print("PA_PLY " + json.dumps(R))
