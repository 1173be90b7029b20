"""Static 3DGS PLY splats (SuperSplat, Postshot, gsplat, 3DGS trainers) in the same preview.

The file becomes a point mesh with the preview's attributes (position, rotation, scale,
opacity, linear colour, level 0, rank) and the same Geometry Nodes splat modifier, so the
look, the budget slider, Export Splats PLY and Render Splats work as for an avatar. The
rank (the slider's order) is the file's own order or an importance proxy (opacity ×
volume, core.ply.importance_order). The SH DC coefficients are kept exactly and higher
bands as "pa_sh_rest_k" vectors, so export writes back what was read; the preview draws the
DC colour (the view-independent part, which is all the splat material shows).

numpy only: core.io.ply reads vertex-only PLYs (binary either endian, or ASCII) without plyfile.
The file is taken as Y up (the frame the PLYs of this project are in) and stood up in Blender's
Z-up world by the object's transform, unless the importer's "Y up to Z up" is off. The object is
marked with the custom property "pa_splat_ply"; it has no bound mesh and no frames.
"""

import os

import bpy
import numpy as np
from bpy_extras.io_utils import ImportHelper

from ..core.io import ply as core_ply
from ..core.bridge.budget import fraction_count, typed_percent
from ..core.bridge.splats import srgb_to_linear
from ..core.bridge.transforms import Y_UP_TO_Z_UP, transform_gaussians
from ..core.avatar.avatar import SH_C0
from . import preview, sequence, splat_look

MARK = "pa_splat_ply"
_F_DC = "pa_f_dc"


def is_splat_ply(obj) -> bool:
    return obj is not None and bool(obj.get(MARK))


def _rest_name(k):
    return f"pa_sh_rest_{k}"


def create_splat_object(context, name, g, order="FILE", source_path=""):
    """A preview object showing Gaussians ``g`` (core.ply.read_ply's dict), ranked by
    ``order`` ("FILE" or "IMPORTANCE")."""
    n = len(g["means"])
    if n == 0:
        raise ValueError(f"{source_path or name}: the PLY holds no Gaussians")
    if order == "IMPORTANCE":
        by_rank = core_ply.importance_order(g)
    elif order == "FILE":
        by_rank = np.arange(n)
    else:
        raise ValueError(f"unknown order {order!r} (FILE or IMPORTANCE)")
    rank = np.empty(n, np.int32)
    rank[by_rank] = np.arange(n, dtype=np.int32)
    rgba = np.ones((n, 4), np.float32)
    rgba[:, :3] = srgb_to_linear(g["colors"])
    me = bpy.data.meshes.new(name)
    try:
        return _fill(context, me, name, g, n, rank, rgba, source_path)
    except Exception:  # leave the scene as it was
        obj = bpy.data.objects.get(name)
        if obj is not None and obj.data == me:
            bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(me)
        raise


def _fill(context, me, name, g, n, rank, rgba, source_path):
    me.vertices.add(n)
    for attr_name, (kind, _field, _width) in preview.ATTRIBUTES.items():
        me.attributes.new(attr_name, kind, "POINT")
    rest = np.asarray(g.get("sh_rest", np.zeros((n, 0, 3))), np.float32)
    for k in range(rest.shape[1]):
        me.attributes.new(_rest_name(k), "FLOAT_VECTOR", "POINT")
        me.attributes[_rest_name(k)].data.foreach_set("vector", np.ascontiguousarray(rest[:, k]).ravel())
    me.attributes.new(_F_DC, "FLOAT_VECTOR", "POINT")
    f_dc = g.get("f_dc")
    if f_dc is None:
        f_dc = (np.asarray(g["colors"], np.float64) - 0.5) / SH_C0
    me.attributes[_F_DC].data.foreach_set("vector", np.asarray(f_dc, np.float32).ravel())
    preview.write_attributes(
        me,
        {
            "position": np.asarray(g["means"], np.float32),
            "rotation": np.asarray(g["quats"], np.float32),
            "scale": np.asarray(g["scales"], np.float32),
            "opacity": np.asarray(g["opacities"], np.float32),
            "color": rgba,
            "level": np.zeros(n, np.int32),
            "rank": rank,
        },
    )
    me.update()
    obj = bpy.data.objects.new(name, me)
    context.collection.objects.link(obj)
    obj[MARK] = True
    obj["pa_sh_bands"] = int(rest.shape[1])
    mod = obj.modifiers.new(preview.MODIFIER_NAME, "NODES")
    mod.node_group = preview.splat_group()
    st = obj.pa_avatar
    st.is_preview = True
    st.filepath = source_path
    st.max_level = 0
    st.coarse_levels = 0
    st.budget = 100.0  # the update callback applies it (apply_budget below)
    apply_budget(obj)
    return obj


def apply_budget(obj):
    """Budget slider → the modifier's Count (the first ``count`` ranks) and the readouts."""
    st = obj.pa_avatar
    total = len(obj.data.vertices)
    count = fraction_count(total, typed_percent(st.budget))
    st.count, st.total = count, total
    st.megabytes = core_ply.splat_ply_bytes(count, int(obj.get("pa_sh_bands", 0))) / 1e6
    st.level_reached = 0 if count else -1
    preview.set_count(obj, count)


def _read(me, name, width, dtype=np.float32, field=None):
    attr = me.attributes[name]
    field = field or {"FLOAT_VECTOR": "vector", "QUATERNION": "value", "FLOAT_COLOR": "color"}.get(
        attr.data_type, "value"
    )
    out = np.empty(len(me.vertices) * width, dtype)
    attr.data.foreach_get(field, out)
    return out.reshape(-1, width) if width > 1 else out


def current_gaussians(obj, world=True):
    """The Gaussians the slider shows now, in rank order (core.ply.write_ply's dict)."""
    me = obj.data
    rank = _read(me, "rank", 1, np.int32)
    count = obj.pa_avatar.count
    sel = np.argsort(rank, kind="stable")[:count]
    means = _read(me, "position", 3)[sel]
    quats = _read(me, "rotation", 4)[sel]
    scales = _read(me, "scale", 3)[sel]
    f_dc = _read(me, _F_DC, 3)[sel].astype(np.float64)
    if world:
        means, quats, scales = transform_gaussians(np.array(obj.matrix_world), means, quats, scales)
    k_rest = int(obj.get("pa_sh_bands", 0))
    rest = (
        np.stack([_read(me, _rest_name(k), 3)[sel] for k in range(k_rest)], axis=1)
        if k_rest
        else np.zeros((len(sel), 0, 3), np.float32)
    )
    return {
        "means": np.asarray(means, np.float32),
        "quats": np.asarray(quats, np.float32),
        "scales": np.asarray(scales, np.float32),
        "opacities": _read(me, "opacity", 1)[sel],
        "colors": np.maximum(0.5 + SH_C0 * f_dc, 0.0).astype(np.float32),
        "f_dc": f_dc.astype(np.float32),
        "sh_rest": rest,
    }


class PA_OT_import_splat_ply(bpy.types.Operator, ImportHelper):
    """Import a standard 3DGS PLY as static splats with the avatar preview's look and budget slider"""

    bl_idname = "import_scene.progressive_avatars_splat_ply"
    bl_label = "Import 3DGS PLY (splats)"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".ply"
    filter_glob: bpy.props.StringProperty(default="*.ply", options={"HIDDEN"})
    order: bpy.props.EnumProperty(
        name="Budget order",
        items=(
            ("FILE", "File order", "The budget keeps the PLY's first Gaussians (files written in a progressive order)"),
            ("IMPORTANCE", "Importance", "The budget keeps the most opaque, largest Gaussians first"),
        ),
        default="IMPORTANCE",
    )
    z_up: bpy.props.BoolProperty(
        name="Y up to Z up",
        default=True,
        description="The file is Y up, as the PLYs this extension and scripts/export.py write (the dataset's "
        "world frame): stand it up in Blender's Z-up world, as the sequence importer does. Off: the file's "
        "axes as they are (e.g. for a scene already Z up)",
    )

    def execute(self, context):
        if not self.filepath.strip():
            self.report({"ERROR"}, "Cannot import splats: choose a 3DGS .ply file")
            return {"CANCELLED"}
        path = bpy.path.abspath(self.filepath)
        try:
            g = core_ply.read_ply(path)
            name = os.path.splitext(os.path.basename(path))[0] or "splats"
            obj = create_splat_object(context, name, g, self.order, self.filepath)
            if self.z_up:  # the object's transform, not the points: export writes the file's frame back
                obj.matrix_world = sequence._matrix(Y_UP_TO_Z_UP)
        except Exception as exc:  # nothing was added: read_ply and the checks run before any datablock
            msg = str(exc)  # the readers' messages mostly name the file already
            self.report({"ERROR"}, f"Cannot import splats: {msg}" if path in msg else f"Cannot import {path}: {msg}")
            return {"CANCELLED"}
        for o in context.selected_objects:
            o.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        focal = splat_look.focal_warning(context.scene)  # sets the dilation's focal length
        if focal:
            self.report({"WARNING"}, f"{obj.name}: {focal}")
        bands = int(obj.get("pa_sh_bands", 0))
        self.report(
            {"INFO"},
            f"Imported {obj.pa_avatar.total} Gaussians from {os.path.basename(path)}"
            + (
                f" ({bands} SH coefficients per channel kept for export; the preview shows the DC colour)"
                if bands
                else ""
            ),
        )
        return {"FINISHED"}


def menu_import(self, context):
    self.layout.operator(PA_OT_import_splat_ply.bl_idname, text="3DGS Splats (.ply)")


classes = (PA_OT_import_splat_ply,)
