"""State stored on objects and scenes, so undo and save/reload keep it."""

import bpy


def _budget_changed(self, context):
    from . import runtime

    if self.id_data.get("pa_splat_ply"):  # static PLY splats: no avatar behind them
        from . import ply_import

        ply_import.apply_budget(self.id_data)
        return
    runtime.apply_budget(self.id_data, context)


def _level_only_changed(self, context):
    from . import depth

    depth.set_level_only(self.id_data, self.level_only)


def coarse_levels(state):
    """How many coarse levels lie above the template in this preview's avatar: absolute level
    = depth below the template + this (the depth legend counts depth; the "level" attribute
    and ``level_only`` absolute levels). Previews saved before it was stored (-1) take it from
    the levels and depths they stored."""
    if state.coarse_levels >= 0:
        return state.coarse_levels
    src = state.source
    if src is None:
        return 0
    return max(state.max_level - src.pa_mesh.depth_max_level, 0)


def _get_depth_only(self):
    return self.level_only - coarse_levels(self) if self.level_only >= 0 else 0


def _set_depth_only(self, value):
    k = coarse_levels(self)
    self.level_only = max(int(value) + k, 0)  # its update callback applies the filter


def _get_depth_only_on(self):
    return self.level_only >= 0


def _set_depth_only_on(self, value):
    if bool(value) != (self.level_only >= 0):
        self.level_only = coarse_levels(self) if value else -1  # on: the template's depth (0)


def _bind_changed(self, context):
    from . import runtime

    runtime.invalidate()
    runtime.apply_budget(self.id_data, context)


class PA_LegendItem(bpy.types.PropertyGroup):
    depth: bpy.props.IntProperty()
    faces: bpy.props.IntProperty()
    color: bpy.props.FloatVectorProperty(subtype="COLOR", size=3, min=0.0, max=1.0)


class PA_MeshState(bpy.types.PropertyGroup):
    """On the animated mesh (the sequence) object."""

    sequence_path: bpy.props.StringProperty(
        name="Sequence", subtype="FILE_PATH", options={"PATH_SUPPORTS_BLEND_RELATIVE"}
    )
    frame_start: bpy.props.IntProperty(name="First frame")
    num_frames: bpy.props.IntProperty(name="Frames")
    depth_legend: bpy.props.CollectionProperty(type=PA_LegendItem)
    depth_max_level: bpy.props.IntProperty()
    # A name, not a pointer: a pointer would keep a deleted preview alive as an orphan (its
    # user) and bring it along whenever the mesh is appended.
    depth_preview: bpy.props.StringProperty(
        description="The preview whose budget the depth attribute, legend and colours describe "
        "(one of the previews bound to this mesh)"
    )
    depth_shown: bpy.props.BoolProperty(name="Depth colours shown", default=False)
    depth_saved: bpy.props.StringProperty(description="Colour and shading settings to restore (JSON)")


class PA_AvatarState(bpy.types.PropertyGroup):
    """On the splat preview object (a point per Gaussian, parented to its mesh)."""

    is_preview: bpy.props.BoolProperty(default=False)
    filepath: bpy.props.StringProperty(
        name="Avatar",
        subtype="FILE_PATH",
        description="Stream or avatar file this preview was loaded from",
        options={"PATH_SUPPORTS_BLEND_RELATIVE"},
    )
    source: bpy.props.PointerProperty(
        type=bpy.types.Object, name="Mesh", description="Mesh whose evaluated vertices drive the Gaussians"
    )
    budget: bpy.props.FloatProperty(
        name="Budget",
        subtype="PERCENTAGE",
        min=0.0,
        max=100.0,
        default=100.0,
        precision=1,
        update=_budget_changed,
        description="Share of the stream shown, as a viewer with this budget would see it",
    )
    # Readouts, written when the budget changes (the panel draws them without any cache).
    count: bpy.props.IntProperty(name="Gaussians")
    total: bpy.props.IntProperty(name="Total")
    megabytes: bpy.props.FloatProperty(name="MB", precision=2)
    level_reached: bpy.props.IntProperty(name="Level reached")
    max_level: bpy.props.IntProperty(name="Levels")
    status: bpy.props.StringProperty(name="Status")
    level_only: bpy.props.IntProperty(
        name="Show level only",
        min=-1,
        default=-1,
        update=_level_only_changed,
        description="Show only the Gaussians of this absolute level, coarse levels included (-1: all); "
        "the panel shows it as depth_only, in the depth legend's terms",
    )
    # What the panel shows of level_only, in the depth legend's terms (not stored: level_only
    # is, so files keep their meaning): the depth below the template, the coarse levels above
    # it as negative depths.
    depth_only_on: bpy.props.BoolProperty(
        name="Show one depth only",
        get=_get_depth_only_on,
        set=_set_depth_only_on,
        description="Show only the Gaussians of one subdivision depth (off: all)",
    )
    depth_only: bpy.props.IntProperty(
        name="Depth",
        get=_get_depth_only,
        set=_set_depth_only,
        description="The depth shown alone, counted as in the depth legend: 0 the template's Gaussians, "
        "1 and more their subdivisions, -1 and less the coarse levels above the template",
    )
    coarse_levels: bpy.props.IntProperty(
        default=-1, description="Coarse levels above the template in the avatar (-1: not stored, older file)"
    )
    bind_mode: bpy.props.EnumProperty(
        name="Follow",
        default="EVALUATED",
        update=_bind_changed,
        items=(
            (
                "EVALUATED",
                "Evaluated mesh",
                "Follow the mesh with all its modifiers; refused (status and "
                "report) when a modifier changes its vertex or face count",
            ),
            (
                "SHAPE_KEYS",
                "Shape keys only",
                "Follow the mesh's shape keys before any modifier (Remesh, "
                "Subdivision Surface, Decimate, but also armatures, are ignored)",
            ),
        ),
        description="Which deformation of the mesh the Gaussians follow",
    )
    template_vertices: bpy.props.IntProperty(description="Vertex count of the mesh the avatar was bound to")
    template_faces: bpy.props.IntProperty(description="Face count of the mesh the avatar was bound to")
    filepath_absolute: bpy.props.StringProperty(
        description="The avatar file's absolute path when it was loaded or last saved: where Avatar points "
        "once appended or made local from a .blend in another folder leaves its relative path pointing nowhere"
    )
    file_signature: bpy.props.StringProperty(
        description="Size and hash of the avatar file when it was loaded: the preview's saved per-point "
        "attributes are that file's"
    )


class PA_TrainState(bpy.types.PropertyGroup):
    data_dir: bpy.props.StringProperty(name="Data", subtype="DIR_PATH", options={"PATH_SUPPORTS_BLEND_RELATIVE"})
    out_dir: bpy.props.StringProperty(name="Run", subtype="DIR_PATH", options={"PATH_SUPPORTS_BLEND_RELATIVE"})
    preset: bpy.props.StringProperty(name="Preset", default="")
    iterations: bpy.props.IntProperty(
        name="Iterations", default=0, min=0, description="Training iterations (0: the preset's)"
    )
    overwrite: bpy.props.BoolProperty(
        name="Overwrite Run",
        default=False,
        description="Start over in a Run folder that already holds a trained run (refused otherwise)",
    )
    resume: bpy.props.BoolProperty(
        name="Resume",
        default=False,
        description="Continue the Run folder's unfinished (cancelled or stopped) training from its checkpoint, "
        "with the same preset",
    )
    running: bpy.props.BoolProperty(default=False)
    progress: bpy.props.FloatProperty(subtype="PERCENTAGE", min=0, max=100)
    message: bpy.props.StringProperty()
    target: bpy.props.PointerProperty(
        type=bpy.types.Object, name="Target", description="The mesh that started training: the result is loaded onto it"
    )


classes = (PA_LegendItem, PA_MeshState, PA_AvatarState, PA_TrainState)


def register_props():
    bpy.types.Object.pa_mesh = bpy.props.PointerProperty(type=PA_MeshState)
    bpy.types.Object.pa_avatar = bpy.props.PointerProperty(type=PA_AvatarState)
    bpy.types.Scene.pa_train = bpy.props.PointerProperty(type=PA_TrainState)


def unregister_props():
    del bpy.types.Scene.pa_train
    del bpy.types.Object.pa_avatar
    del bpy.types.Object.pa_mesh
