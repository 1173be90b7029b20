"""File > Import: a tracked sequence as a shape-keyed mesh; a dataset's cameras."""

import os

import bpy
from bpy_extras.io_utils import ImportHelper

from . import prefs, sequence


def cursor_progress(wm):
    """A reader's ``progress(done, total)`` shown as Blender's cursor progress, begun over 0..100
    (progress_begin takes a maximum of at most 9998), updated once per percent at most."""
    shown = -1

    def progress(done, total):
        nonlocal shown
        percent = 100 * done // total if total > 0 else 100
        if percent != shown:
            shown = percent
            wm.progress_update(percent)

    return progress


class PA_OT_import_sequence(bpy.types.Operator, ImportHelper):
    """Import a tracked FLAME or mesh sequence as one mesh with a shape key per frame"""

    # One key per scene frame, in the file's frame order: the tracked timestep ids are not used
    # as frame numbers (a sequence tracked every 3rd video frame plays contiguously; set the
    # frame rate to match).

    bl_idname = "import_scene.progressive_avatars_sequence"
    bl_label = "Import FLAME Sequence"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filter_glob: bpy.props.StringProperty(default="*.npz;*.obj;*.ply", options={"HIDDEN"})
    whole_folder: bpy.props.BoolProperty(
        name="Whole folder",
        default=False,
        description="Read every OBJ/PLY (or FLAME parameter) file in the chosen file's folder as frames",
    )
    flame_model: bpy.props.StringProperty(
        name="FLAME model",
        subtype="FILE_PATH",
        description="Needed for FLAME parameter files; defaults to the preferences",
    )
    as_rig: bpy.props.BoolProperty(
        name="As FLAME rig",
        default=False,
        description="FLAME parameter files only: import expression and pose-corrective shape keys and a keyed "
        "armature instead of one shape key per frame, so expressions and joints can be edited",
    )
    z_up: bpy.props.BoolProperty(name="Y up to Z up", default=True)
    set_frame_range: bpy.props.BoolProperty(
        name="Set frame range",
        default=True,
        description="Set the scene's frame range to the imported frames (off: keep the scene's range)",
    )
    fps: bpy.props.IntProperty(
        name="Frame rate",
        default=0,
        min=0,
        max=1000,
        description="Frames per second of the sequence, set as the scene's frame rate (0: keep the scene's; "
        "tracked sequences do not store one). Each tracked frame takes one scene frame, whatever its timestep id",
    )

    def execute(self, context):
        # A 1000-frame folder reads for seconds with the UI frozen: the cursor shows how far
        # (core's readers call back per file); ended on every path, an exception's included.
        wm = context.window_manager
        wm.progress_begin(0, 100)
        try:
            return self._import(context, cursor_progress(wm))
        finally:
            wm.progress_end()

    def _import(self, context, progress):
        from ..core.io import sequences
        from ..core.flame import model as flame
        from ..core.flame import rig as flame_rig

        if not self.filepath.strip():
            self.report({"ERROR"}, "Cannot read sequence: choose a sequence file (or a folder of frames)")
            return {"CANCELLED"}
        path = bpy.path.abspath(self.filepath)
        if self.whole_folder and os.path.isfile(path):
            path = os.path.dirname(path)
        model = bpy.path.abspath(self.flame_model) if self.flame_model else (prefs.flame_model(context) or None)
        if self.as_rig and not model:
            self.report(
                {"ERROR"}, "Import as FLAME rig needs a FLAME model file (operator option or add-on preferences)"
            )
            return {"CANCELLED"}
        try:
            rig = None
            if self.as_rig:
                seq = sequences.read_flame_track(path, progress=progress)
                try:
                    rig = flame_rig.build_flame_rig(flame.load_flame_model(model), seq.params)
                except ValueError as exc:  # parameters that do not fit the model
                    raise sequences.DataError(f"{path}: {exc}") from exc
            else:
                seq = sequences.read_sequence(path, flame_model=model, progress=progress)
        except Exception as exc:  # the readers' messages name the file and the problem
            self.report({"ERROR"}, f"Cannot read sequence: {exc}")
            return {"CANCELLED"}
        if seq.n_frames == 0:
            self.report({"ERROR"}, f"{path}: no frames")
            return {"CANCELLED"}
        faces = rig.faces if rig is not None else seq.faces
        if len(faces) == 0:  # e.g. a 3DGS splat PLY: its points read as vertices
            self.report(
                {"ERROR"},
                f"Cannot import {path}: it has points but no faces, so it is no mesh sequence "
                "(a 3DGS splat PLY? Import it with File > Import > 3DGS Splats (.ply))",
            )
            return {"CANCELLED"}
        problem = sequence.face_problem(faces)
        if problem:
            self.report({"ERROR"}, f"Cannot read sequence: {path}: {problem}; Blender cannot hold such a mesh")
            return {"CANCELLED"}
        scene = context.scene
        kept_range = (scene.frame_start, scene.frame_end)
        name = os.path.splitext(os.path.basename(path.rstrip("/\\")))[0] or "sequence"
        selected = list(context.selected_objects)
        if rig is not None:
            from . import rig as rig_builder

            try:
                obj, _ = rig_builder.build_rig_objects(context, rig, name, context.scene.frame_start, self.z_up)
            except Exception as exc:  # Blender's own operators run inside (mode switch, weight conversion)
                scene.frame_start, scene.frame_end = kept_range
                self.report({"ERROR"}, f"Cannot import {path} as a FLAME rig: {exc}")
                return {"CANCELLED"}
            if rig.ignored:
                self.report(
                    {"WARNING"},
                    f"Not representable in a rig, left out: {', '.join(rig.ignored)} "
                    "(import without 'As FLAME rig' to keep them)",
                )
        else:
            # Leave Edit Mode (or any other) first, as the rig builder does: the new mesh
            # becomes the active object, and another one left in Edit Mode would stay there.
            view_layer = context.view_layer
            active = view_layer.objects.active
            mode = active.mode if active is not None else "OBJECT"
            if mode != "OBJECT":
                bpy.ops.object.mode_set(mode="OBJECT")
            try:
                with sequence.removed_on_failure():
                    obj = sequence.build_sequence_object(context, seq, name, context.scene.frame_start, self.z_up)
            except Exception as exc:
                scene.frame_start, scene.frame_end = kept_range
                view_layer.objects.active = active
                if mode != "OBJECT":
                    bpy.ops.object.mode_set(mode=mode)
                self.report({"ERROR"}, f"Cannot import {path}: {exc}")
                return {"CANCELLED"}
        for ob in selected:
            ob.select_set(False)
        if not self.set_frame_range:  # the builders set it; put the scene's back
            scene.frame_start, scene.frame_end = kept_range
        if self.fps:
            scene.render.fps, scene.render.fps_base = self.fps, 1.0
        obj.pa_mesh.sequence_path = self.filepath if not self.whole_folder else path
        context.view_layer.objects.active = obj
        obj.select_set(True)
        self.report(
            {"INFO"},
            f"Imported {seq.n_frames} frames, {len(obj.data.vertices)} vertices, {len(obj.data.polygons)} faces",
        )
        return {"FINISHED"}


class PA_OT_import_cameras(bpy.types.Operator):
    """Add the cameras of a GaussianAvatars/VHAP dataset (transforms_*.json) as Blender cameras"""

    bl_idname = "import_scene.progressive_avatars_cameras"
    bl_label = "Import Dataset Cameras"
    bl_options = {"REGISTER", "UNDO"}

    directory: bpy.props.StringProperty(subtype="DIR_PATH")
    split: bpy.props.StringProperty(name="Split", default="train")
    z_up: bpy.props.BoolProperty(name="Y up to Z up", default=True)

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from ..core.io.dataset import Dataset

        root = bpy.path.abspath(self.directory)
        from ..core.io.validate import camera_problems

        try:  # cameras need neither the meshes nor a FLAME model
            ds = Dataset(root, self.split, geometry=False)
        except Exception as exc:
            self.report({"ERROR"}, f"Cannot read dataset cameras: {exc}")
            return {"CANCELLED"}
        cams = ds.cameras
        problems = [p for i, c in sorted(cams.items()) for p in camera_problems(c, f"{ds.json_path}: camera {i}")]
        if problems:  # NaN intrinsics or a zero matrix would make cameras that frame nothing
            self.report({"ERROR"}, "Cannot import dataset cameras: " + "; ".join(problems[:5]))
            return {"CANCELLED"}
        settings = None
        for idx in sorted(cams):
            _, settings = sequence.add_camera(context, f"cam_{idx:02d}", cams[idx], self.z_up)
        if settings is not None:
            r = context.scene.render
            r.resolution_x, r.resolution_y = settings["resolution"]
            r.pixel_aspect_x, r.pixel_aspect_y = settings["pixel_aspect"]
        sizes = {(c.width, c.height) for c in cams.values()}
        if len(sizes) > 1:  # Blender has one resolution per scene, not per camera
            last = max(cams)
            self.report(
                {"WARNING"},
                f"The cameras' images differ in size ({', '.join(f'{w}x{h}' for w, h in sorted(sizes))}); the scene "
                f"resolution is cam_{last:02d}'s: set it to a camera's own size before rendering from it",
            )
        self.report({"INFO"}, f"Added {len(cams)} cameras")
        return {"FINISHED"}


def menu_import(self, context):
    self.layout.operator(PA_OT_import_sequence.bl_idname, text="FLAME Sequence (ProgressiveAvatars)")
    self.layout.operator(PA_OT_import_cameras.bl_idname, text="Dataset Cameras (ProgressiveAvatars)")


classes = (PA_OT_import_sequence, PA_OT_import_cameras)
