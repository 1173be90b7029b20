"""State stored on objects and scenes, so undo and save/reload keep it."""

import bpy


def _budget_changed(self, context):
    from . import runtime

    if self.id_data.get("pa_splat_ply"):  # static PLY splats: no avatar behind them
        from . import ply_import

        ply_import.apply_budget(self.id_data)
        return
    runtime.apply_budget(self.id_data, context)


class PA_LegendItem(bpy.types.PropertyGroup):
    depth: bpy.props.IntProperty()
    faces: bpy.props.IntProperty()
    color: bpy.props.FloatVectorProperty(subtype="COLOR", size=3, min=0.0, max=1.0)


class PA_MeshState(bpy.types.PropertyGroup):
    """On the animated mesh (the sequence) object."""

    sequence_path: bpy.props.StringProperty(name="Sequence", subtype="FILE_PATH")
    frame_start: bpy.props.IntProperty(name="First frame")
    num_frames: bpy.props.IntProperty(name="Frames")
    depth_legend: bpy.props.CollectionProperty(type=PA_LegendItem)


class PA_AvatarState(bpy.types.PropertyGroup):
    """On the splat preview object (a point per Gaussian, parented to its mesh)."""

    is_preview: bpy.props.BoolProperty(default=False)
    filepath: bpy.props.StringProperty(name="Avatar", subtype="FILE_PATH",
                                       description="Stream or avatar file this preview was loaded from")
    source: bpy.props.PointerProperty(type=bpy.types.Object, name="Mesh",
                                      description="Mesh whose evaluated vertices drive the Gaussians")
    budget: bpy.props.FloatProperty(name="Budget", subtype="PERCENTAGE", min=0.0, max=100.0, default=100.0,
                                    precision=1, update=_budget_changed,
                                    description="Share of the stream shown, as a viewer with this budget would see it")
    # Readouts, written when the budget changes (the panel draws them without any cache).
    count: bpy.props.IntProperty(name="Gaussians")
    total: bpy.props.IntProperty(name="Total")
    megabytes: bpy.props.FloatProperty(name="MB", precision=2)
    level_reached: bpy.props.IntProperty(name="Level reached")
    max_level: bpy.props.IntProperty(name="Levels")
    status: bpy.props.StringProperty(name="Status")


class PA_TrainState(bpy.types.PropertyGroup):
    data_dir: bpy.props.StringProperty(name="Data", subtype="DIR_PATH")
    out_dir: bpy.props.StringProperty(name="Run", subtype="DIR_PATH")
    preset: bpy.props.StringProperty(name="Preset", default="")
    running: bpy.props.BoolProperty(default=False)
    progress: bpy.props.FloatProperty(subtype="PERCENTAGE", min=0, max=100)
    message: bpy.props.StringProperty()


classes = (PA_LegendItem, PA_MeshState, PA_AvatarState, PA_TrainState)


def register_props():
    bpy.types.Object.pa_mesh = bpy.props.PointerProperty(type=PA_MeshState)
    bpy.types.Object.pa_avatar = bpy.props.PointerProperty(type=PA_AvatarState)
    bpy.types.Scene.pa_train = bpy.props.PointerProperty(type=PA_TrainState)


def unregister_props():
    del bpy.types.Scene.pa_train
    del bpy.types.Object.pa_avatar
    del bpy.types.Object.pa_mesh
