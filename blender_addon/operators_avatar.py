"""Load an avatar onto a mesh, colour faces by depth, export PLY, render splats."""

import hashlib
import os
import tempfile
import urllib.parse

import bpy
import numpy as np
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..core.bridge.budget import check_mesh, load_avatar
from ..core.bridge.depth import depth_per_face
from ..core.bridge.splats import preview_order, static_attributes, without_behind
from ..core.bridge.transforms import camera_from_blender, transform_gaussians
from ..core.avatar.avatar import sh_to_rgb, sigmoid
from . import ADDON_PACKAGE, depth, prefs, preview, runtime, splat_look


def _mesh_target(context):
    obj = context.active_object
    if obj is not None and obj.pa_avatar.is_preview:
        obj = runtime.bound_mesh(obj)
    return obj if obj is not None and obj.type == "MESH" else None


def preview_of(context):
    obj = context.active_object
    if obj is None:
        return None
    if obj.pa_avatar.is_preview:
        return obj
    owner = depth.depth_owner(obj)  # of several bound to it, the one its depth legend describes
    return owner if owner is not None else next(iter(runtime.bound_previews(obj)), None)


def orphan_depth_mesh(context):
    """The active mesh when it shows depth colours but no longer has a preview (deleted)."""
    obj = context.active_object
    if obj is None or obj.type != "MESH" or not obj.pa_mesh.depth_shown or preview_of(context) is not None:
        return None
    return obj


def _fetch(url, template_faces=None):
    """Stream an avatar from a URL into the extension's user cache (online access only),
    verifying it as it arrives (core/http_stream). A transfer that stalls or is cut keeps its
    verified prefix, itself a valid (shorter) stream. Returns (path, message or "")."""
    if not bpy.app.online_access:
        raise PermissionError("Online access is disabled (Preferences > System > Network)")
    from ..core.stream import http as http_stream
    from ..core.stream.reader import StreamReader

    # One file per URL: two previews streamed from .../a/avatar.pavs and .../b/avatar.pavs must
    # not share (and overwrite) one download that both .blend references point to.
    stem, ext = os.path.splitext(os.path.basename(urllib.parse.urlparse(url).path) or "avatar.pavs")
    name = f"{stem}-{hashlib.sha256(url.encode()).hexdigest()[:12]}{ext or '.pavs'}"
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

    try:
        with open(part, "wb") as fh:
            # A deadline: this runs on Blender's UI thread, which a slow server must not hold forever.
            res = http_stream.fetch_stream(url, reader=_Tee(template_faces, source=url), timeout=30.0, deadline=300.0)
    except BaseException:  # e.g. the download folder full: no half-written file stays behind
        if os.path.exists(part):
            os.remove(part)
        raise
    n = res.keepable_gaussians
    if n == 0:  # nothing verified, or the old file's bytes after the server replaced it
        os.remove(part)
        raise RuntimeError(f"no complete Gaussian from {url}: {res.status} {res.message}".strip())
    if not res.reader.complete:  # keep exactly the verified records
        with open(part, "r+b") as fh:
            fh.truncate(res.reader.header.bytes_for_count(n))
    os.replace(part, dest)
    note = "" if res.reader.complete else f"partial stream ({res.status}: {res.message}); kept {n} verified Gaussians"
    return dest, note


mesh_faces = runtime.mesh_faces

_DATA_KINDS = ("objects", "meshes", "node_groups", "materials", "images", "textures")


def _snapshot():
    return {kind: set(getattr(bpy.data, kind)) for kind in _DATA_KINDS}


def _remove_new(before):
    """Remove every datablock made since ``before`` (objects first: they use the rest)."""
    for kind in _DATA_KINDS:
        coll = getattr(bpy.data, kind)
        for idb in [x for x in coll if x not in before[kind]]:
            try:
                coll.remove(idb)
            except (ReferenceError, RuntimeError):
                pass


def stored_path(path):
    """The path to store: relative to the .blend ("//...") once it is saved and Relative Paths
    is on (Preferences > File Paths), so a moved project keeps its avatars; absolute otherwise."""
    path = runtime.resolve(path)
    if bpy.data.filepath and bpy.context.preferences.filepaths.use_relative_paths:
        try:
            return bpy.path.relpath(path)
        except ValueError:  # another drive (Windows)
            return path
    return path


def load_avatar_onto(context, mesh_obj, path, budget=100.0):
    """Create (or replace) the splat preview of ``mesh_obj`` from an avatar/stream file.

    Everything that can fail on the file runs before the scene is touched; should building
    the preview fail anyway, whatever it made is removed and the previous preview stays."""
    depth.require_writable(mesh_obj)
    abspath = runtime.resolve(path)
    faces = mesh_faces(mesh_obj.data)
    avatar, budget_info = load_avatar(abspath, faces)
    signature = runtime.file_signature(abspath)
    try:
        check_mesh(avatar, budget_info, faces)
    except ValueError as exc:
        raise ValueError(f"{abspath}: not made for {mesh_obj.name}: {exc}") from None
    count = budget_info.count_for_slider(budget)
    depth_per_face(avatar.forest, len(faces), count)  # raises before any change
    static = static_attributes(avatar, preview_order(avatar))
    # Replaced: every preview bound to it that can be removed (a linked one cannot).
    old = [o for o in runtime.bound_previews(mesh_obj) if not o.library]
    name = f"{mesh_obj.name}_splats"
    before = _snapshot()
    saved_depth = _save_depth(mesh_obj)
    obj = None
    try:
        obj = preview.create_preview_object(name, mesh_obj, static)
        state = obj.pa_avatar
        state.is_preview = True
        state.filepath = stored_path(abspath)
        state.filepath_absolute = abspath
        state.file_signature = signature
        state.source = mesh_obj
        state.max_level = budget_info.max_level()
        state.coarse_levels = budget_info.max_level() - budget_info.max_depth(avatar.forest)
        state.template_vertices = len(mesh_obj.data.vertices)
        state.template_faces = len(mesh_obj.data.polygons)
        runtime.prime(obj, abspath, avatar, budget_info)
        state.budget = budget  # its update callback sets the count, readouts and evaluates the frame
        depth.apply_depth(mesh_obj, avatar.forest, state.count, budget_info.max_depth(avatar.forest), obj)
    except BaseException:
        if obj is not None:
            runtime.forget(obj)
        _restore_depth(mesh_obj, saved_depth)
        _remove_new(before)
        raise
    for child in old:
        runtime.forget(child)
        me = child.data
        groups = {m.node_group for m in child.modifiers if m.type == "NODES" and m.node_group is not None}
        bpy.data.objects.remove(child)
        if me.users == 0:
            bpy.data.meshes.remove(me)
        for ng in groups:  # its level filter; the splat group stays in use by the new preview
            if ng.users == 0:
                bpy.data.node_groups.remove(ng)
    obj.name = name
    obj.data.name = name
    mesh_obj.pa_mesh.depth_preview = obj.name  # the mesh's depth is its: recorded again under its own name
    splat_look.set_focal(context.scene)  # the dilation's focal length, from the scene camera
    return obj


def _save_depth(mesh_obj):
    me = mesh_obj.data
    attr = me.attributes.get(depth.DEPTH_ATTR)
    if attr is None or attr.domain != "FACE" or attr.data_type != "INT":
        values = None
    else:
        values = np.empty(len(me.polygons), np.int32)
        attr.data.foreach_get("value", values)
    legend = [(i.depth, i.faces, tuple(i.color)) for i in mesh_obj.pa_mesh.depth_legend]
    return values, legend, mesh_obj.pa_mesh.depth_max_level


def _restore_depth(mesh_obj, saved):
    values, legend, top = saved
    me = mesh_obj.data
    attr = me.attributes.get(depth.DEPTH_ATTR)
    if values is None:
        if attr is not None:
            me.attributes.remove(attr)
    elif attr is not None:
        attr.data.foreach_set("value", values)
    st = mesh_obj.pa_mesh
    st.depth_legend.clear()
    for d, n, rgb in legend:
        item = st.depth_legend.add()
        item.depth, item.faces, item.color = d, n, rgb
    st.depth_max_level = top


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
        if not self.url and not path.strip():
            self.report({"ERROR"}, "Cannot load avatar: choose a stream (.pavs) or avatar (.npz) file, or give a URL")
            return {"CANCELLED"}
        try:
            note = ""
            depth.require_writable(mesh_obj)  # before a download it could not use
            if self.url:
                path, note = _fetch(self.url, mesh_faces(mesh_obj.data))
            obj = load_avatar_onto(context, mesh_obj, path, self.budget)
        except Exception as exc:
            self.report({"ERROR"}, f"Cannot load avatar: {exc}")
            return {"CANCELLED"}
        if note:
            self.report({"WARNING"}, note)
        problem = runtime.topology_problem(obj, context.evaluated_depsgraph_get())
        if problem:
            self.report({"WARNING"}, problem)
        focal = splat_look.focal_warning(context.scene)
        if focal:
            self.report({"WARNING"}, f"{obj.name}: {focal}")
        self.report({"INFO"}, f"Loaded {obj.pa_avatar.total} Gaussians onto {mesh_obj.name}")
        return {"FINISHED"}


class PA_OT_depth_colors(bpy.types.Operator):
    """Show or hide the mesh's faces coloured by the avatar's subdivision depth at the current
    budget (faces without a Gaussian yet in their own colour); hiding restores your colours
    and shading. Shown for another preview of the same mesh, they switch to this one's"""

    bl_idname = "object.progressive_avatars_depth_colors"
    bl_label = "Colour by Depth"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return preview_of(context) is not None or orphan_depth_mesh(context) is not None

    def execute(self, context):
        from . import ply_import

        obj = preview_of(context)
        if obj is not None and ply_import.is_splat_ply(obj):
            self.report({"ERROR"}, f"{obj.name}: PLY splats carry no subdivision depth; load an avatar onto a mesh")
            return {"CANCELLED"}
        # No preview: it was deleted while the colours were shown, and they can still go.
        src = runtime.bound_mesh(obj) if obj is not None else orphan_depth_mesh(context)
        if src is None or src.type != "MESH":
            self.report({"ERROR"}, f"{obj.name}: its mesh was deleted; load the avatar onto a mesh again")
            return {"CANCELLED"}
        try:  # hiding writes the mesh's attributes too
            depth.require_writable(src)
        except ValueError as exc:
            self.report({"ERROR"}, f"Colour by Depth: {exc}")
            return {"CANCELLED"}
        # Shown for another preview bound to the mesh: they switch to this one's.
        if src.pa_mesh.depth_shown and depth.depth_owner(src) in (None, obj):
            depth.hide_colors(context, src)
            return {"FINISHED"}
        e = runtime.entry(obj)
        if e is None:
            self.report({"ERROR"}, obj.pa_avatar.status or "Avatar not available")
            return {"CANCELLED"}
        try:
            depth.show_colors(
                context, src, e.avatar.forest, obj.pa_avatar.count, e.budget.max_depth(e.avatar.forest), obj
            )
        except ValueError as exc:
            self.report({"ERROR"}, f"Colour by Depth: {exc}")
            return {"CANCELLED"}
        return {"FINISHED"}


def current_gaussians(context, obj, world=True):
    """The Gaussians the preview shows now (this frame, this budget), as core arrays."""
    from . import ply_import

    if ply_import.is_splat_ply(obj):
        return ply_import.current_gaussians(obj, world)
    e = runtime.entry(obj)
    if e is None:
        raise RuntimeError(obj.pa_avatar.status or "avatar not available")
    count = e.budget.count_for_slider(obj.pa_avatar.budget)
    if not runtime.refresh(obj, context.evaluated_depsgraph_get(), count):
        raise RuntimeError(obj.pa_avatar.status)
    ev = e.placed  # its outputs hold the first e.valid >= count Gaussians on this frame
    # the faces of stream positions 0..count-1, less coarse stand-ins whose region has arrived,
    # or, for backdrop stand-ins, with those behind the rest (Forest.render_set)
    faces, behind = e.avatar.forest.render_set(e.face_at[:count], records=count)
    points = e.point_of_face[faces]
    means, quats, scales = ev.means[points], ev.quats[points], ev.scales[points]
    if world:
        means, quats, scales = transform_gaussians(np.array(obj.matrix_world), means, quats, scales)
    # The model's own colours (sRGB-encoded, what it was trained on), not the preview's linear
    # display colours: export and rendering must reproduce the trained avatar.
    av = e.avatar
    g = {
        "means": np.array(means),
        "quats": np.array(quats),
        "scales": np.array(scales),
        "opacities": sigmoid(av.opacity_logit[faces]).astype(np.float32),
        "colors": sh_to_rgb(av.f_dc[faces]).astype(np.float32),
    }
    if behind is not None:  # the core rasteriser draws them behind; a PLY cannot (without_behind)
        g["behind"] = np.asarray(behind, bool)
    return g


class PA_OT_export_ply(bpy.types.Operator, ExportHelper):
    """Export the Gaussians shown now (current frame and budget) as a standard 3DGS PLY"""

    bl_idname = "export_scene.progressive_avatars_ply"
    bl_label = "Export Splats PLY"
    filename_ext = ".ply"
    filter_glob: bpy.props.StringProperty(default="*.ply", options={"HIDDEN"})
    world_space: bpy.props.BoolProperty(
        name="World space", default=False, description="Blender world space instead of the sequence's own coordinates"
    )

    @classmethod
    def poll(cls, context):
        return preview_of(context) is not None

    def execute(self, context):
        try:
            from ..core.io import ply
        except ImportError:
            self.report({"ERROR"}, "This build has no PLY writer (core/io/ply.py)")
            return {"CANCELLED"}
        pv = preview_of(context)
        if pv.pa_avatar.count == 0:
            self.report(
                {"ERROR"},
                f"Nothing to export: {pv.name}'s Budget is {pv.pa_avatar.budget:.1f} %, "
                "0 Gaussians; raise the Budget slider",
            )
            return {"CANCELLED"}
        try:
            g, left = without_behind(current_gaussians(context, pv, world=self.world_space))
            ply.write_ply(bpy.path.abspath(self.filepath), g)
        except Exception as exc:
            self.report({"ERROR"}, f"PLY export failed: {exc}")
            return {"CANCELLED"}
        note = (
            f" (left out {left} retired backdrop stand-ins: a 3DGS PLY cannot draw them behind the rest)"
            if left
            else ""
        )
        self.report({"INFO"}, f"Wrote {len(g['means'])} Gaussians to {self.filepath}{note}")
        return {"FINISHED"}


MIN_RENDER_SCALE = 1e-12  # the rasteriser takes scales > 0 only


def renderable(g):
    """The Gaussians as the rasteriser takes them, looking as Blender shows them: a splat an
    object transform collapsed to a point (all scales 0, e.g. object scale 0) shows nothing
    and is left out (the rasteriser would still draw its screen-space dilation); one collapsed
    to a disc or a line keeps a tiny positive scale on its collapsed axes."""
    keep = g["scales"].max(axis=1) > 0
    if not keep.all():
        g = {k: v[keep] for k, v in g.items()}
    g["scales"] = np.maximum(g["scales"], np.float32(MIN_RENDER_SCALE))
    return g


def world_background(world):
    """The scene-linear RGB a render shows behind everything for this world (Film > Transparent
    off): its Background shader's Color × Strength, the colour users edit, when the world uses
    nodes (always from Blender 5.0), else its viewport colour ``world.color``; black without a
    world or with nothing connected to its output. A world drawn by a texture or another shader
    gives its viewport colour (the nearest plain colour there is)."""
    if world is None:
        return np.zeros(3, np.float32)
    tree = world.node_tree
    if tree is None or (bpy.app.version < (5, 0, 0) and not world.use_nodes):
        return np.array(world.color[:3], np.float32)
    outputs = [n for n in tree.nodes if n.type == "OUTPUT_WORLD"]
    out = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    socket = out.inputs["Surface"] if out is not None else None
    node = None
    while socket is not None and socket.is_linked:
        node = socket.links[0].from_node
        socket = node.inputs[0] if node.type == "REROUTE" else None
    if node is None or node.type == "REROUTE":  # nothing drawn: Blender renders black
        return np.zeros(3, np.float32)
    colour, strength = node.inputs.get("Color"), node.inputs.get("Strength")
    if node.type != "BACKGROUND" or colour.is_linked or strength.is_linked:
        return np.array(world.color[:3], np.float32)
    return (np.array(colour.default_value[:3], np.float64) * strength.default_value).astype(np.float32)


class PA_OT_render_splats(bpy.types.Operator):
    """Render the splats with ProgressiveAvatars' own rasteriser (runs the configured Python)"""

    bl_idname = "render.progressive_avatars_splats"
    bl_label = "Render Splats"

    wait: bpy.props.BoolProperty(
        name="Wait", default=False, options={"SKIP_SAVE"}, description="Block until the image is ready (scripts)"
    )

    @classmethod
    def poll(cls, context):
        return preview_of(context) is not None and context.scene.camera is not None

    def execute(self, context):
        problem = prefs.python_problem(context, "numba")
        if problem:
            self.report({"ERROR"}, f"Render Splats: {problem}")
            return {"CANCELLED"}
        python = prefs.python_path(context)
        scene = context.scene
        try:
            cam_obj, settings = splat_look.scene_camera(scene)
        except ValueError as exc:
            self.report({"ERROR"}, f"Render Splats: {exc}")
            return {"CANCELLED"}
        w, h = settings["width"], settings["height"]
        try:
            g = renderable(current_gaussians(context, preview_of(context), world=True))
            cam = camera_from_blender(np.array(cam_obj.matrix_world), z_up=False, **settings)
        except Exception as exc:
            self.report({"ERROR"}, f"Render splats: {exc}")
            return {"CANCELLED"}
        # The splats are drawn over black; store_image puts the world behind them in scene-linear.
        self._background = None if scene.render.film_transparent else world_background(scene.world)
        arrays = dict(
            R=cam.R,
            t=cam.t,
            intr=np.array([cam.fx, cam.fy, cam.cx, cam.cy]),
            size=np.array([w, h]),
            background=np.zeros(3, np.float32),
            **g,
        )
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
        render_job.store_image(job.rgba, background=self._background)
        self.report({"INFO"}, f"Rendered {self._count} Gaussians into image 'PA Splats' in {job.seconds:.1f} s")
        return {"FINISHED"}


classes = (PA_OT_load_avatar, PA_OT_depth_colors, PA_OT_export_ply, PA_OT_render_splats)
