"""3D View N-panel: sequence, avatar budget, depth legend, export/render, training."""

import bpy

from . import depth, operators_avatar, ply_import, runtime

CATEGORY = "Progressive Avatars"  # the sidebar tab, as the README names it


class _Base:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = CATEGORY


class PA_PT_main(_Base, bpy.types.Panel):
    bl_label = "ProgressiveAvatars"

    def draw(self, context):
        col = self.layout.column(align=True)
        col.operator("import_scene.progressive_avatars_sequence", icon="IMPORT")
        col.operator("import_scene.progressive_avatars_cameras", icon="CAMERA_DATA")
        col.operator("object.progressive_avatars_load", icon="POINTCLOUD_DATA")
        col.operator("import_scene.progressive_avatars_splat_ply", icon="IMPORT")
        obj = context.active_object
        if obj is not None and obj.type == "MESH" and obj.pa_mesh.num_frames:
            self.layout.label(text=f"{obj.name}: {obj.pa_mesh.num_frames} frames from {obj.pa_mesh.frame_start}")


class PA_PT_avatar(_Base, bpy.types.Panel):
    bl_label = "Avatar"
    bl_parent_id = "PA_PT_main"

    @classmethod
    def poll(cls, context):
        return operators_avatar.preview_of(context) is not None

    def draw(self, context):
        obj = operators_avatar.preview_of(context)
        st = obj.pa_avatar
        lay = self.layout
        lay.prop(st, "budget", slider=True)
        grid = lay.grid_flow(columns=2, align=True)
        grid.label(text="Gaussians")
        grid.label(text=f"{st.count:,} / {st.total:,}")
        grid.label(text="Size")
        grid.label(text=f"{st.megabytes:.2f} MB")
        # In the depth legend's terms: depth below the template (coarse levels negative).
        from .properties import coarse_levels

        k = coarse_levels(st)
        grid.label(text="Depth reached")
        grid.label(text=f"{st.level_reached - k} of {st.max_level - k}" if st.level_reached >= 0 else "none")
        mod = obj.modifiers.get("PA Splats")
        if mod is not None and mod.node_group is not None:
            from .preview import input_identifier

            for name in ("Size", "Camera Cards", "Cards in Viewport", "Detail", "Points Only"):
                try:
                    lay.prop(mod, f'["{input_identifier(mod.node_group, name)}"]', text=name)
                except KeyError:
                    pass
        lay.prop(st, "bind_mode")
        if st.status:  # long reasons (the topology guard's) wrap instead of being clipped
            import textwrap

            col = lay.column(align=True)
            for i, line in enumerate(textwrap.wrap(st.status, 48)):
                col.label(text=line, icon="ERROR" if i == 0 else "BLANK1")
        row = lay.row(align=True)
        row.operator("export_scene.progressive_avatars_ply", icon="EXPORT")
        row.operator("render.progressive_avatars_splats", icon="RENDER_STILL")
        row = lay.row(align=True)
        row.operator("render.progressive_avatars_splat_settings", icon="SHADING_RENDERED")
        row.operator("render.progressive_avatars_splat_settings", text="As Trained").as_trained = True


class PA_PT_depth(_Base, bpy.types.Panel):
    bl_label = "Subdivision Depth"
    bl_parent_id = "PA_PT_main"

    @classmethod
    def poll(cls, context):
        return (
            operators_avatar.preview_of(context) is not None or operators_avatar.orphan_depth_mesh(context) is not None
        )

    def draw(self, context):
        obj = operators_avatar.preview_of(context)
        lay = self.layout
        if obj is None:
            lay.label(text="The avatar preview was deleted", icon="ERROR")
            lay.operator("object.progressive_avatars_depth_colors", icon="COLOR", text="Hide Depth Colours")
            return
        if ply_import.is_splat_ply(obj):  # bound to no mesh by nature, not deleted
            lay.label(text="PLY splats carry no subdivision depth", icon="INFO")
            return
        src = runtime.bound_mesh(obj)
        if src is None:
            lay.label(text="The preview's mesh was deleted", icon="ERROR")
            return
        owner = depth.depth_owner(src)
        shown = src.pa_mesh.depth_shown and owner in (None, obj)  # else the button shows this one's
        lay.operator(
            "object.progressive_avatars_depth_colors",
            icon="COLOR",
            text="Hide Depth Colours" if shown else "Colour by Depth",
            depress=shown,
        )
        row = lay.row(align=True)
        row.prop(obj.pa_avatar, "depth_only_on", text="Show depth only")
        sub = row.row(align=True)
        sub.active = obj.pa_avatar.depth_only_on
        sub.prop(obj.pa_avatar, "depth_only", text="")
        recorded = src.pa_mesh.depth_preview
        if owner is not None and owner != obj:  # another preview bound to the mesh
            lay.label(text=f"Depth of {owner.name} at {owner.pa_avatar.budget:.1f} %", icon="INFO")
        elif owner is None and recorded and recorded != obj.name and len(src.pa_mesh.depth_legend):
            # Its preview deleted, renamed or rebound: the legend is still its until a budget moves.
            lay.label(text=f"Depth of {recorded}, not a preview of this mesh now: move a budget", icon="INFO")
        legend = src.pa_mesh.depth_legend
        total = max(sum(item.faces for item in legend), 1)
        for item in legend:
            row = lay.row(align=True)
            sw = row.row()
            sw.enabled = False
            sw.prop(item, "color", text="")
            bar = "█" * int(round(20 * item.faces / total))
            what = "not arrived" if item.depth < 0 else f"depth {item.depth}"
            row.label(text=f"{what}: {item.faces:,}  {bar}")


class PA_PT_train(_Base, bpy.types.Panel):
    bl_label = "Training"
    bl_parent_id = "PA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        st = context.scene.pa_train
        lay = self.layout
        lay.prop(st, "data_dir")
        lay.prop(st, "out_dir")
        lay.prop(st, "preset")
        lay.prop(st, "iterations")
        row = lay.row()
        row.prop(st, "resume")
        row.prop(st, "overwrite")
        if st.running:
            lay.progress(factor=st.progress / 100.0, text=f"{st.progress:.0f}%")
            lay.operator("progressive_avatars.train_cancel", icon="CANCEL")
        else:
            lay.operator("progressive_avatars.train", icon="PLAY")
        if st.message:
            lay.label(text=st.message)


classes = (PA_PT_main, PA_PT_avatar, PA_PT_depth, PA_PT_train)
