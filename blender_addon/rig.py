"""Build a FLAME rig in Blender from core's :class:`flame_rig.FlameRig`: a mesh with
expression and pose-corrective shape keys, skinned to a keyed armature.

Expression keys are keyed from the tracking; pose-corrective keys are driven by the bones'
quaternions (simple expressions, evaluated without Python), so editing either the
expression sliders or the bone rotations gives FLAME's own result.
"""

import bpy
import numpy as np

from ..core.bridge.transforms import Y_UP_TO_Z_UP
from . import sequence

# Entry (a, b) of R - I from a quaternion (w, x, y, z), normalised so that interpolated
# (non-unit) keys still give a rotation.
_NORM = "(w*w+x*x+y*y+z*z)"
_R_MINUS_I = {
    (0, 0): f"-2*(y*y+z*z)/{_NORM}",
    (0, 1): f"2*(x*y-w*z)/{_NORM}",
    (0, 2): f"2*(x*z+w*y)/{_NORM}",
    (1, 0): f"2*(x*y+w*z)/{_NORM}",
    (1, 1): f"-2*(x*x+z*z)/{_NORM}",
    (1, 2): f"2*(y*z-w*x)/{_NORM}",
    (2, 0): f"2*(x*z-w*y)/{_NORM}",
    (2, 1): f"2*(y*z+w*x)/{_NORM}",
    (2, 2): f"-2*(x*x+y*y)/{_NORM}",
}


def _keyed_curve(action, owner, path, index, frames, values, interp):
    fc = sequence._fcurve(action, owner, path, index)
    n = len(frames)
    fc.keyframe_points.add(n)
    co = np.empty(2 * n, np.float32)
    co[0::2] = frames
    co[1::2] = values
    fc.keyframe_points.foreach_set("co", co)
    fc.keyframe_points.foreach_set("interpolation", np.full(n, interp, np.int32))
    fc.update()
    return fc


def _new_action(owner, name):
    ad = owner.animation_data_create()
    action = bpy.data.actions.new(name)
    ad.action = action
    return action


def _add_armature(context, rig, name):
    arm = bpy.data.armatures.new(f"{name}_rig")
    arm_obj = bpy.data.objects.new(f"{name}_rig", arm)
    context.collection.objects.link(arm_obj)
    extent = float(np.ptp(rig.basis, axis=0).max()) if rig.basis.size else 1.0
    length = 0.1 * extent if extent > 0 else 0.01
    view_layer = context.view_layer
    previous = view_layer.objects.active
    view_layer.objects.active = arm_obj
    with context.temp_override(active_object=arm_obj, object=arm_obj, selected_objects=[arm_obj]):
        bpy.ops.object.mode_set(mode="EDIT")
        try:
            bones = []
            for k, bone_name in enumerate(rig.bone_names):
                eb = arm.edit_bones.new(bone_name)
                head = rig.rest_joints[k]
                # Pointing along +Y with no roll: the rest orientation is the identity, which
                # makes a bone's local rotation FLAME's joint rotation.
                eb.head = head.tolist()
                eb.tail = (head + np.array([0.0, length, 0.0])).tolist()
                eb.roll = 0.0
                eb.use_deform = True
                if rig.parents[k] >= 0:
                    eb.parent = bones[rig.parents[k]]
                    eb.use_connect = False
                bones.append(eb)
        finally:
            bpy.ops.object.mode_set(mode="OBJECT")
    view_layer.objects.active = previous
    for pb in arm_obj.pose.bones:
        pb.rotation_mode = "QUATERNION"
    return arm_obj


def _add_vertex_groups(context, obj, rig):
    """Skinning weights as vertex groups: each written as a point attribute with foreach_set,
    then converted by Blender (vertex groups have no bulk setter of their own)."""
    me = obj.data
    for k, bone_name in enumerate(rig.bone_names):
        w = rig.weights[:, k]
        if not np.any(w > 0):
            continue
        attr = me.attributes.new(bone_name, "FLOAT", "POINT")
        attr.data.foreach_set("value", np.ascontiguousarray(w, np.float32))
        me.attributes.active = attr
        with context.temp_override(object=obj, active_object=obj):
            result = bpy.ops.geometry.attribute_convert(mode="VERTEX_GROUP")
        if "FINISHED" not in result or bone_name not in obj.vertex_groups:
            raise RuntimeError(f"Blender did not convert the weights of '{bone_name}' into a vertex group")


def _add_shape_keys(obj, rig):
    obj.shape_key_add(name="Basis", from_mix=False)
    basis = rig.basis.astype(np.float64)
    groups = ((rig.expr_key_names(), rig.expr_deltas, -10.0, 10.0), (rig.pose_key_names(), rig.pose_deltas, -2.0, 2.0))
    for names, deltas, lo, hi in groups:
        for key_name, delta in zip(names, deltas):
            kb = obj.shape_key_add(name=key_name, from_mix=False)
            kb.points.foreach_set("co", np.ascontiguousarray(basis + delta, np.float32).ravel())
            kb.slider_min, kb.slider_max = lo, hi
            kb.value = 0.0
    obj.data.shape_keys.use_relative = True
    return obj.data.shape_keys


def _drive_pose_keys(key, arm_obj, rig):
    names = rig.pose_key_names()
    i = 0
    for k in range(1, rig.n_joints):
        for a in range(3):
            for b in range(3):
                fc = key.key_blocks[names[i]].driver_add("value")
                drv = fc.driver
                drv.type = "SCRIPTED"
                for comp in "wxyz":
                    var = drv.variables.new()
                    var.name = comp
                    var.type = "TRANSFORMS"
                    t = var.targets[0]
                    t.id = arm_obj
                    t.bone_target = rig.bone_names[k]
                    t.transform_type = f"ROT_{comp.upper()}"
                    t.transform_space = "TRANSFORM_SPACE"
                    t.rotation_mode = "QUATERNION"
                drv.expression = _R_MINUS_I[(a, b)]
                i += 1


_DATA_KINDS = ("objects", "meshes", "armatures", "actions")


def build_rig_objects(context, rig, name, frame_start, z_up=True):
    """Mesh and armature objects for ``rig``; returns (mesh object, armature object).

    Leaves Edit Mode (or any other) first: Blender turns weights into vertex groups in Object
    Mode only. Should the build fail, whatever it made is removed and the mode restored."""
    view_layer = context.view_layer
    active = view_layer.objects.active
    mode = active.mode if active is not None else "OBJECT"
    if mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    try:
        with sequence.removed_on_failure(_DATA_KINDS):
            return _build(context, rig, name, frame_start, z_up)
    except BaseException:
        view_layer.objects.active = active
        if mode != "OBJECT":
            bpy.ops.object.mode_set(mode=mode)
        raise


def _build(context, rig, name, frame_start, z_up):
    me = sequence.build_mesh(name, rig.basis, rig.faces)
    obj = bpy.data.objects.new(name, me)
    context.collection.objects.link(obj)
    arm_obj = _add_armature(context, rig, name)
    if z_up:
        arm_obj.matrix_world = sequence._matrix(Y_UP_TO_Z_UP)
    obj.parent = arm_obj
    obj.matrix_parent_inverse.identity()
    _add_vertex_groups(context, obj, rig)
    key = _add_shape_keys(obj, rig)
    mod = obj.modifiers.new("FLAME", "ARMATURE")
    mod.object = arm_obj
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False

    T = rig.n_frames
    frames = frame_start + np.arange(T, dtype=np.float64)
    lin = sequence._keyframe_interp("LINEAR")
    if T:
        action = _new_action(key, f"{name}_expressions")
        for e, key_name in enumerate(rig.expr_key_names()):
            _keyed_curve(action, key, f'key_blocks["{key_name}"].value', 0, frames, rig.expr_values[:, e], lin)
        action = _new_action(arm_obj, f"{name}_pose")
        for k, bone_name in enumerate(rig.bone_names):
            base = f'pose.bones["{bone_name}"].'
            for c in range(3):
                _keyed_curve(action, arm_obj, base + "location", c, frames, rig.locations[:, k, c], lin)
            for c in range(4):
                _keyed_curve(action, arm_obj, base + "rotation_quaternion", c, frames, rig.quaternions[:, k, c], lin)
            if rig.parents[k] < 0 and np.any(rig.scales[:, k] != 1.0):
                for c in range(3):
                    _keyed_curve(action, arm_obj, base + "scale", c, frames, rig.scales[:, k], lin)
    _drive_pose_keys(key, arm_obj, rig)

    scene = context.scene
    scene.frame_start = frame_start
    scene.frame_end = frame_start + max(T, 1) - 1
    state = obj.pa_mesh
    state.frame_start = frame_start
    state.num_frames = T
    return obj, arm_obj
