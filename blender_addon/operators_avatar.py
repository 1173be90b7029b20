"""Load an avatar onto a mesh, colour faces by depth, export PLY, render splats."""

import os
import tempfile
import urllib.parse

import bpy
import numpy as np
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..core import preview_data
from ..core.avatar import sh_to_rgb, sigmoid
from . import ADDON_PACKAGE, depth, prefs, preview, runtime


def _mesh_target(context):
    obj = context.active_object
    if obj is not None and obj.pa_avatar.is_preview:
        obj = obj.pa_avatar.source
    return obj if obj is not None and obj.type == "MESH" else None


def _preview_of(context):
    obj = context.active_object
    if obj is None:
        return None
    if obj.pa_avatar.is_preview:
        return obj
    for child in obj.children:
        if child.pa_avatar.is_preview:
            return child
    return None


def _fetch(url):
    """Stream an avatar from a URL into the extension's user cache (online access only),
    verifying it as it arrives (core/http_stream). A transfer that stalls or is cut keeps its
    verified prefix, itself a valid (shorter) stream. Returns (path, message or "")."""
    if not bpy.app.online_access:
        raise PermissionError("Online access is disabled (Preferences > System > Network)")
    from ..core import http_stream
    from ..core.stream import StreamReader

    name = os.path.basename(urllib.parse.urlparse(url).path) or "avatar.pavs"
    try:
        folder = bpy.utils.extension_path_user(ADDON_PACKAGE, path="downloads", create=True)
    except (ValueError, AttributeError):  # not installed as an extension
        folder = tempfile.mkdtemp(prefix="pa_dl_")
    dest = os.path.join(folder, name)
    part = dest + ".part"

    class _Tee(StreamReader):  # the bytes go to the file as they are fed
        def feed(self, chunk):
            fh.write(chunk)
            return super().feed(chunk)

    with open(part, "wb") as fh:
        res = http_stream.fetch_stream(url, reader=_Tee(source=url), timeout=30.0)
    n = res.num_gaussians
    if n == 0:
        os.remove(part)
        raise RuntimeError(f"no complete Gaussian from {url}: {res.status} {res.message}".strip())
    if not res.reader.complete:  # keep exactly the verified records
        with open(part, "r+b") as fh:
            fh.truncate(res.reader.header.bytes_for_count(n))
    os.replace(part, dest)
    note = "" if res.reader.complete else f"partial stream ({res.status}: {res.message}); kept {n} verified Gaussians"
    return dest, note


def mesh_faces(me):
    """Triangle vertex indices [F,3] (quads and n-gons cannot be an avatar's template)."""
    totals = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_total", totals)
    if len(totals) and (totals != 3).any():
        raise ValueError(f"{me.name} has non-triangle faces; avatars bind to triangle templates")
    idx = np.empty(len(me.loops), np.int32)
    me.loops.foreach_get("vertex_index", idx)
    return idx.reshape(-1, 3)


def load_avatar_onto(context, mesh_obj, path, budget=100.0):
    """Create (or replace) the splat preview of ``mesh_obj`` from an avatar/stream file."""
    abspath = runtime.resolve(path)
    avatar, budget_info = preview_data.load_avatar(abspath)
    preview_data.check_mesh(avatar, budget_info, mesh_faces(mesh_obj.data))
    for child in list(mesh_obj.children):
        if child.pa_avatar.is_preview:
            runtime.forget(child)
            me = child.data
            bpy.data.objects.remove(child)
            if me.users == 0:
                bpy.data.meshes.remove(me)
    static = preview_data.static_attributes(avatar, preview_data.preview_order(avatar))
    obj = preview.create_preview_object(f"{mesh_obj.name}_splats", mesh_obj, static)
    state = obj.pa_avatar
    state.is_preview = True
    state.filepath = path
    state.source = mesh_obj
    state.max_level = avatar.forest.max_level
    runtime.prime(obj, path, avatar, budget_info)
    state.budget = budget  # its update callback sets the count, readouts and evaluates the frame
    depth.apply_depth(mesh_obj, avatar.forest)
    return obj


class PA_OT_load_avatar(bpy.types.Operator, ImportHelper):
    """Load a progressive avatar (stream or .npz) onto the active mesh as a splat preview"""

    bl_idname = "object.progressive_avatars_load"
    bl_label = "Load Progressive Avatar"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: bpy.props.StringProperty(default="*.pavs;*.npz", options={"HIDDEN"})
    url: bpy.props.StringProperty(name="URL", description="Stream from a URL instead (needs online access)")
    budget: bpy.props.FloatProperty(name="Budget", subtype="PERCENTAGE", min=0, max=100, default=100)

    @classmethod
    def poll(cls, context):
        return _mesh_target(context) is not None

    def execute(self, context):
        mesh_obj = _mesh_target(context)
        path = self.filepath
        try:
            note = ""
            if self.url:
                path, note = _fetch(self.url)
            obj = load_avatar_onto(context, mesh_obj, path, self.budget)
        except Exception as exc:
            self.report({"ERROR"}, f"Cannot load avatar: {exc}")
            return {"CANCELLED"}
        if note:
            self.report({"WARNING"}, note)
        self.report({"INFO"}, f"Loaded {obj.pa_avatar.total} Gaussians onto {mesh_obj.name}")
        return {"FINISHED"}


class PA_OT_depth_colors(bpy.types.Operator):
    """Colour the mesh's faces by the avatar's subdivision depth (Solid mode: Attribute colour)"""

    bl_idname = "object.progressive_avatars_depth_colors"
    bl_label = "Colour by Depth"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _preview_of(context) is not None

    def execute(self, context):
        obj = _preview_of(context)
        e = runtime.entry(obj)
        if e is None:
            self.report({"ERROR"}, obj.pa_avatar.status or "Avatar not available")
            return {"CANCELLED"}
        try:
            depth.apply_depth(obj.pa_avatar.source, e.avatar.forest)
        except ValueError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for area in context.screen.areas if context.screen else ():
            for space in area.spaces:
                if space.type == "VIEW_3D":
                    space.shading.color_type = "VERTEX"
        return {"FINISHED"}


def current_gaussians(context, obj, world=True):
    """The Gaussians the preview shows now (this frame, this budget), as core arrays."""
    from . import ply_import

    if ply_import.is_splat_ply(obj):
        return ply_import.current_gaussians(obj, world)
    e = runtime.entry(obj)
    if e is None:
        raise RuntimeError(obj.pa_avatar.status or "avatar not available")
    count = e.budget.count_for_percent(obj.pa_avatar.budget)
    if not runtime.refresh(obj, context.evaluated_depsgraph_get(), count):
        raise RuntimeError(obj.pa_avatar.status)
    ev = e.evaluator
    points = e.point_of_rank[:count]  # the preview rows of ranks 0..count-1
    means, quats, scales = ev.means[points], ev.quats[points], ev.scales[points]
    if world:
        means, quats, scales = preview_data.transform_gaussians(np.array(obj.matrix_world), means, quats, scales)
    # The model's own colours (sRGB-encoded, what it was trained on), not the preview's linear
    # display colours: export and rendering must reproduce the trained avatar.
    av = e.avatar
    return {"means": np.array(means), "quats": np.array(quats), "scales": np.array(scales),
            "opacities": sigmoid(av.opacity_logit[:count]).astype(np.float32),
            "colors": sh_to_rgb(av.f_dc[:count]).astype(np.float32)}


class PA_OT_export_ply(bpy.types.Operator, ExportHelper):
    """Export the Gaussians shown now (current frame and budget) as a standard 3DGS PLY"""

    bl_idname = "export_scene.progressive_avatars_ply"
    bl_label = "Export Splats PLY"
    filename_ext = ".ply"
    filter_glob: bpy.props.StringProperty(default="*.ply", options={"HIDDEN"})
    world_space: bpy.props.BoolProperty(name="World space", default=False,
                                        description="Blender world space instead of the sequence's own coordinates")

    @classmethod
    def poll(cls, context):
        return _preview_of(context) is not None

    def execute(self, context):
        try:
            from ..core import ply
        except ImportError:
            self.report({"ERROR"}, "This build has no PLY writer (core/ply.py)")
            return {"CANCELLED"}
        try:
            g = current_gaussians(context, _preview_of(context), world=self.world_space)
            ply.write_ply(bpy.path.abspath(self.filepath), g)
        except Exception as exc:
            self.report({"ERROR"}, f"PLY export failed: {exc}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Wrote {len(g['means'])} Gaussians to {self.filepath}")
        return {"FINISHED"}


class PA_OT_render_splats(bpy.types.Operator):
    """Render the splats with ProgressiveAvatars' own rasteriser (runs the configured Python)"""

    bl_idname = "render.progressive_avatars_splats"
    bl_label = "Render Splats"

    wait: bpy.props.BoolProperty(name="Wait", default=False, options={"SKIP_SAVE"},
                                 description="Block until the image is ready (scripts)")

    @classmethod
    def poll(cls, context):
        return _preview_of(context) is not None and context.scene.camera is not None

    def execute(self, context):
        python = prefs.python_path(context)
        if not python or not os.path.isfile(python):
            self.report({"ERROR"}, "Set a Python with numba in the add-on preferences to render splats")
            return {"CANCELLED"}
        scene = context.scene
        cam_obj = scene.camera
        r = scene.render
        w = int(r.resolution_x * r.resolution_percentage / 100)
        h = int(r.resolution_y * r.resolution_percentage / 100)
        try:
            g = current_gaussians(context, _preview_of(context), world=True)
            cam = preview_data.camera_from_blender(np.array(cam_obj.matrix_world), cam_obj.data.lens,
                                                   cam_obj.data.sensor_width, cam_obj.data.shift_x,
                                                   cam_obj.data.shift_y, w, h, z_up=False)
        except Exception as exc:
            self.report({"ERROR"}, f"Render splats: {exc}")
            return {"CANCELLED"}
        world = scene.world
        bg = np.array(world.color[:3] if world else (0, 0, 0), np.float32)
        arrays = dict(R=cam.R, t=cam.t, intr=np.array([cam.fx, cam.fy, cam.cx, cam.cy]), size=np.array([w, h]),
                      background=bg, **g)
        # A persistent worker renders (render_job): control returns at once; the modal
        # timer polls it. Without a UI (timers never fire) or with wait=True it is awaited.
        from . import render_job

        try:
            self._job = render_job.RenderJob(python, arrays)
        except OSError as exc:
            self.report({"ERROR"}, f"Splat render failed: cannot start {python}: {exc}")
            return {"CANCELLED"}
        self._count = len(g["means"])
        if self.wait or bpy.app.background or context.window is None:
            self._job.wait()
            return self._finish(context)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, 100)
        context.workspace.status_text_set("Rendering splats… Esc to cancel")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC":
            job.cancel()
        elif event.type != "TIMER":
            return {"PASS_THROUGH"}
        state = job.poll()
        context.window_manager.progress_update(int(100 * job.progress))
        if state in ("done", "failed", "cancelled"):
            context.window_manager.event_timer_remove(self._timer)
            context.window_manager.progress_end()
            context.workspace.status_text_set(None)
            return self._finish(context)
        return {"PASS_THROUGH"}

    def cancel(self, context):  # Blender ends the modal (file load, quit): stop the render too
        self._job.cancel()
        context.window_manager.event_timer_remove(self._timer)
        context.window_manager.progress_end()
        context.workspace.status_text_set(None)

    def _finish(self, context):
        from . import render_job

        job = self._job
        if job.state == "cancelled":
            self.report({"WARNING"}, f"Splat render {job.message}")
            return {"CANCELLED"}
        if job.state != "done":
            self.report({"ERROR"}, f"Splat render failed: {job.message}")
            return {"CANCELLED"}
        render_job.store_image(job.rgba)
        self.report({"INFO"}, f"Rendered {self._count} Gaussians into image 'PA Splats' in {job.seconds:.1f} s")
        return {"FINISHED"}


classes = (PA_OT_load_avatar, PA_OT_depth_colors, PA_OT_export_ply, PA_OT_render_splats)
