"""Build Blender data for a mesh sequence: one mesh, one shape key per frame, cameras."""

from contextlib import contextmanager

import bpy
import numpy as np

from ..core.bridge.transforms import Y_UP_TO_Z_UP, blender_camera


def _keyframe_interp(name):
    return bpy.types.Keyframe.bl_rna.properties["interpolation"].enum_items[name].value


def face_problem(faces) -> str:
    """Why Blender cannot hold these triangles as a valid mesh ("" when it can): a face that
    names one vertex twice, or the same three vertices twice. Such a mesh builds, but Blender
    treats it as corrupt (Edit Mode can hang on it), so the import refuses it up front."""
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    if bad.any():
        i = int(np.argmax(bad))
        return f"face {i} {tuple(int(v) for v in f[i])} uses a vertex twice ({int(bad.sum())} such faces)"
    _, first, inverse = np.unique(np.sort(f, axis=1), axis=0, return_index=True, return_inverse=True)
    dup = first[inverse.reshape(-1)] != np.arange(len(f))
    if dup.any():
        i = int(np.argmax(dup))
        j = int(first[inverse.reshape(-1)[i]])
        return f"face {i} {tuple(int(v) for v in f[i])} repeats face {j}'s vertices ({int(dup.sum())} such faces)"
    return ""


def build_mesh(name, vertices0, faces):
    faces = np.ascontiguousarray(faces, np.int32)
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(vertices0))
    me.vertices.foreach_set("co", np.ascontiguousarray(vertices0, np.float32).ravel())
    me.loops.add(faces.size)
    me.loops.foreach_set("vertex_index", faces.ravel())
    me.polygons.add(len(faces))
    me.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
    me.update()
    return me


def _fcurve(action, owner, path, index=0):
    if hasattr(action, "fcurve_ensure_for_datablock"):  # Blender 4.4+ (layered actions)
        return action.fcurve_ensure_for_datablock(owner, path, index=index)
    return action.fcurves.new(path, index=index)


def add_sequence_keys(obj, vertices, frame_start):
    """One relative shape key per frame, each keyed to 1 on its frame and 0 on its neighbours.

    Relative keys are exact (basis + (key - basis) to float rounding); absolute keys
    (eval_time) place blocks at accumulated float positions and drift by up to ~1e-4 of a
    frame on long sequences, blending neighbours. F-curves address blocks by index: RNA
    resolves `key_blocks["name"]` by a linear name search, quadratic over 1000 curves
    (~45 ms a frame against ~10 ms).
    """
    T = len(vertices)
    obj.shape_key_add(name="Basis", from_mix=False)
    for t in range(T):
        kb = obj.shape_key_add(name=f"frame_{t:05d}", from_mix=False)
        kb.points.foreach_set("co", np.ascontiguousarray(vertices[t], np.float32).ravel())
        kb.value = 0.0  # new keys start at 1.0 in Blender 5.0
        kb.slider_min = 0.0
    key = obj.data.shape_keys
    key.use_relative = True
    ad = key.animation_data_create()
    action = bpy.data.actions.new(f"{obj.name}_sequence")
    ad.action = action
    if hasattr(ad, "action_slot") and ad.action_slot is None and len(action.slots):
        ad.action_slot = action.slots[0]
    lin = _keyframe_interp("LINEAR")
    for t in range(T):
        fc = _fcurve(action, key, f"key_blocks[{t + 1}].value")
        f = frame_start + t
        co = np.array([f - 1, 0.0, f, 1.0, f + 1, 0.0], np.float32)
        if t == 0:
            co = co[2:]
        if t == T - 1:
            co = co[:-2]
        fc.keyframe_points.add(len(co) // 2)
        fc.keyframe_points.foreach_set("co", co)
        fc.keyframe_points.foreach_set("interpolation", [lin] * (len(co) // 2))
        fc.update()
    return key


@contextmanager
def removed_on_failure(kinds=("objects", "meshes", "armatures", "actions")):
    """Should the block raise, every datablock of ``kinds`` it made is removed (objects first:
    they use the rest; a mesh takes its shape keys along), so a failed import adds nothing."""
    before = {kind: set(getattr(bpy.data, kind)) for kind in kinds}
    try:
        yield
    except BaseException:
        for kind in kinds:
            coll = getattr(bpy.data, kind)
            for idb in [x for x in coll if x not in before[kind]]:
                try:
                    coll.remove(idb)
                except (ReferenceError, RuntimeError):  # gone with what used it: the original error matters
                    pass
        raise


def build_sequence_object(context, seq, name, frame_start, z_up=True):
    me = build_mesh(name, seq.vertices[0], seq.faces)
    obj = bpy.data.objects.new(name, me)
    context.collection.objects.link(obj)
    if z_up:
        obj.matrix_world = _matrix(Y_UP_TO_Z_UP)
    if seq.n_frames > 1:
        add_sequence_keys(obj, seq.vertices, frame_start)
    scene = context.scene
    scene.frame_start = frame_start
    scene.frame_end = frame_start + max(seq.n_frames, 1) - 1
    state = obj.pa_mesh
    state.frame_start = frame_start
    state.num_frames = seq.n_frames
    return obj


def _matrix(m):
    from mathutils import Matrix

    return Matrix(np.asarray(m, np.float64).tolist())


def add_camera(context, name, camera, z_up=True):
    s = blender_camera(camera, z_up=z_up)
    cam = bpy.data.cameras.new(name)
    cam.sensor_fit = s["sensor_fit"]
    cam.sensor_width = s["sensor_width"]
    cam.lens = s["lens"]
    cam.shift_x, cam.shift_y = s["shift_x"], s["shift_y"]
    cam.clip_start = 0.01
    obj = bpy.data.objects.new(name, cam)
    obj.matrix_world = _matrix(s["matrix_world"])
    context.collection.objects.link(obj)
    return obj, s
