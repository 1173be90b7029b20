"""Blender session run by test_blender_extension.py (a real file so it can be read, linted and run by hand)."""

import importlib, json, os, sys, time, traceback
import numpy as np
import bpy

zip_path, seq_path, stream_path, trainer, out, flame_path, params_path = sys.argv[-7:]
R = {"errors": []}


def section(name):
    def deco(fn):
        t0 = time.perf_counter()
        try:
            fn()
        except Exception:
            R["errors"].append(name + ": " + traceback.format_exc())
        R.setdefault("seconds", {})[name] = round(time.perf_counter() - t0, 3)

    return deco


@section("install")
def _():
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    R["addon_enabled"] = "bl_ext.user_default.progressive_avatars" in bpy.context.preferences.addons
    R["operators"] = {
        name: hasattr(getattr(bpy.ops, name.split(".")[0]), name.split(".")[1])
        for name in (
            "import_scene.progressive_avatars_sequence",
            "import_scene.progressive_avatars_cameras",
            "object.progressive_avatars_load",
            "object.progressive_avatars_depth_colors",
            "export_scene.progressive_avatars_ply",
            "render.progressive_avatars_splats",
            "progressive_avatars.train",
            "progressive_avatars.train_cancel",
        )
    }
    R["panels"] = [n for n in ("PA_PT_main", "PA_PT_avatar", "PA_PT_depth", "PA_PT_train") if hasattr(bpy.types, n)]
    R["import_menu"] = any(
        "progressive_avatars" in getattr(f, "__module__", "")
        for f in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
    )


pkg = "bl_ext.user_default.progressive_avatars"
ext = sys.modules.get(pkg)
R["extension_dir"] = os.path.dirname(ext.__file__) if ext else None


def verts_of(obj):
    dg = bpy.context.evaluated_depsgraph_get()
    me = obj.evaluated_get(dg).data
    a = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", a)
    return a.reshape(-1, 3)


LAST = {}  # preview_state's splat arrays (centre and axes) of its last call


def preview_state(pv):
    dg = bpy.context.evaluated_depsgraph_get()
    geo = pv.evaluated_get(dg).evaluated_geometry()  # must outlive the point cloud taken from it
    ip = geo.instances_pointcloud()
    n = len(ip.points) if ip is not None else 0
    pos = np.empty(len(pv.data.vertices) * 3, np.float32)
    pv.data.attributes["position"].data.foreach_get("vector", pos)
    rot = np.empty(len(pv.data.vertices) * 4, np.float32)
    pv.data.attributes["rotation"].data.foreach_get("value", rot)
    scl = np.empty(len(pv.data.vertices) * 3, np.float32)
    pv.data.attributes["scale"].data.foreach_get("vector", scl)
    xf = np.zeros(n * 16, np.float32)
    # The splat itself as the material reads it (world space): centre and σ-scaled axes,
    # brought back into the preview object's space, as a 4x4 [A_x A_y A_z centre].
    splat = np.zeros((n, 4, 4), np.float32)
    if n:
        ip.attributes["instance_transform"].data.foreach_get("value", xf)
        to_local = np.linalg.inv(np.array(pv.matrix_world))
        for col, name in enumerate(("pa_axis_x", "pa_axis_y", "pa_axis_z", "pa_center")):
            v = np.empty(n * 3, np.float32)
            ip.attributes[name].data.foreach_get("vector", v)
            v = v.reshape(n, 3)
            splat[:, :3, col] = v @ to_local[:3, :3].T + (to_local[:3, 3] if col == 3 else 0)
    # Points are laid out by root face; the rank attribute is their stream position. Return
    # everything in stream order (instances: the points with rank < n, in point order).
    rank = np.empty(len(pv.data.vertices), np.int32)
    pv.data.attributes["rank"].data.foreach_get("value", rank)
    by_rank = np.argsort(rank)
    inst = np.argsort(rank[rank < n])
    xf = xf.reshape(n, 4, 4).transpose(0, 2, 1)[inst]
    LAST["splat"] = splat[inst]
    return n, pos.reshape(-1, 3)[by_rank], rot.reshape(-1, 4)[by_rank], scl.reshape(-1, 3)[by_rank], xf


arrays = {}
for ob in list(bpy.data.objects):  # the factory startup cube/light/camera would enclose the head
    bpy.data.objects.remove(ob)


@section("import")
def _():
    bpy.context.scene.frame_start = 5
    t0 = time.perf_counter()
    bpy.ops.import_scene.progressive_avatars_sequence(filepath=seq_path)
    R["import_seconds"] = time.perf_counter() - t0
    obj = bpy.context.active_object
    R["mesh_name"] = obj.name
    R["frame_range"] = [bpy.context.scene.frame_start, bpy.context.scene.frame_end]
    R["shape_keys"] = len(obj.data.shape_keys.key_blocks)
    R["key_values_at_import"] = sorted({round(k.value, 6) for k in obj.data.shape_keys.key_blocks[1:]})
    for t in __FRAMES__:
        bpy.context.scene.frame_set(bpy.context.scene.frame_start + t)
        arrays[f"seq_{t}"] = verts_of(obj)


@section("load")
def _():
    mesh = bpy.data.objects[R["mesh_name"]]
    bpy.context.view_layer.objects.active = mesh
    res = bpy.ops.object.progressive_avatars_load(filepath=stream_path, budget=25.0)
    pv = [c for c in mesh.children if c.pa_avatar.is_preview][0]
    R["preview_name"] = pv.name
    st = pv.pa_avatar
    R["load_result"] = list(res)
    R["at25"] = {
        "count": st.count,
        "total": st.total,
        "mb": st.megabytes,
        "level": st.level_reached,
        "status": st.status,
    }
    R["at25_instances"] = preview_state(pv)[0]
    # slider change timing (count within what is evaluated: only the modifier input moves)
    t0 = time.perf_counter()
    st.budget = 20.0
    bpy.context.evaluated_depsgraph_get()
    R["slider_seconds"] = time.perf_counter() - t0
    st.budget = 25.0
    for t in (3, 6):
        bpy.context.scene.frame_set(bpy.context.scene.frame_start + t)
        n, pos, rot, scl, xf = preview_state(pv)
        arrays[f"pos_{t}"], arrays[f"rot_{t}"], arrays[f"scl_{t}"], arrays[f"xf_{t}"] = pos, rot, scl, xf
        arrays[f"splat_{t}"] = LAST["splat"]
        R[f"instances_{t}"] = n
    st.budget = 100.0
    n, pos, rot, scl, xf = preview_state(pv)
    R["at100_instances"] = n
    arrays["pos_100_6"] = pos
    d = np.empty(len(mesh.data.polygons), np.int32)
    mesh.data.attributes["pa_depth"].data.foreach_get("value", d)
    arrays["depth"] = d
    bpy.ops.object.progressive_avatars_depth_colors()  # a toggle: load no longer paints the mesh
    R["depth_color_domain"] = mesh.data.color_attributes["pa_depth_color"].domain
    R["active_color"] = mesh.data.color_attributes.active_color_name
    R["legend"] = [[i.depth, i.faces] for i in mesh.pa_mesh.depth_legend]


@section("export")
def _():
    pv = bpy.data.objects[R["preview_name"]]
    bpy.context.view_layer.objects.active = pv
    pv.pa_avatar.budget = 50.0
    bpy.context.scene.frame_set(bpy.context.scene.frame_start + 2)
    bpy.ops.export_scene.progressive_avatars_ply(filepath=os.path.join(out, "frame.ply"))
    R["export_count"] = pv.pa_avatar.count


@section("camera")
def _():
    cam_mod = importlib.import_module(pkg + ".core.geometry.camera")  # not imported by the add-on itself
    seq_mod = sys.modules[pkg + ".blender_addon.sequence"]
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    cam = cam_mod.Camera.look_at([0.1, 0.05, 0.6], [0, 0, 0], [0, 1, 0], 500.0, 500.0, 180.0, 110.0, 320, 240)
    obj, s = seq_mod.add_camera(bpy.context, "test_cam", cam, z_up=True)
    bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y = s["resolution"]
    pts = np.random.default_rng(0).normal(0, 0.05, (20, 3))
    uv_core, _ = cam.project(pts)
    z_up = np.array(importlib.import_module(pkg + ".core.bridge.transforms").Y_UP_TO_Z_UP)
    uv_bl = []
    for p in pts:
        q = z_up[:3, :3] @ p
        c = world_to_camera_view(bpy.context.scene, obj, Vector(q.tolist()))
        uv_bl.append([c.x * 320, (1 - c.y) * 240])
    R["camera_uv_err"] = float(np.abs(np.array(uv_bl) - uv_core).max())
    bpy.data.objects.remove(obj)


@section("train")
def _():
    prefs = bpy.context.preferences.addons[pkg].preferences
    prefs.python_path = sys.executable
    prefs.train_script = trainer
    st = bpy.context.scene.pa_train
    st.data_dir = out
    st.out_dir = os.path.join(out, "run")
    bpy.context.view_layer.objects.active = bpy.data.objects[R["mesh_name"]]
    res = bpy.ops.progressive_avatars.train()
    R["train"] = {"result": list(res), "progress": st.progress, "message": st.message, "running": st.running}
    pv = [c for c in bpy.data.objects[R["mesh_name"]].children if c.pa_avatar.is_preview][0]
    R["train"]["loaded"] = os.path.basename(pv.pa_avatar.filepath)
    R["preview_name"] = pv.name


@section("errors_reported")
def _():
    try:
        bpy.ops.object.progressive_avatars_load(filepath=os.path.join(out, "missing.pavs"))
        R["missing_file"] = "no error"
    except RuntimeError as exc:  # operator reports ERROR -> RuntimeError under bpy.ops
        R["missing_file"] = str(exc).splitlines()[0]


@section("save_reload")
def _():
    pv = bpy.data.objects[R["preview_name"]]
    pv.pa_avatar.budget = 30.0
    bpy.context.scene.frame_set(bpy.context.scene.frame_start + 1)
    path = os.path.join(out, "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    pv = bpy.data.objects[R["preview_name"]]
    st = pv.pa_avatar
    R["reload"] = {
        "budget": st.budget,
        "count": st.count,
        "filepath": os.path.basename(st.filepath),
        "source": st.source.name if st.source else None,
        "is_preview": st.is_preview,
        "frame": bpy.context.scene.frame_current - bpy.context.scene.frame_start,
        "instances": preview_state(pv)[0],
        "attributes": sorted(a.name for a in pv.data.attributes if not a.name.startswith(".")),
    }
    st.budget = 60.0
    bpy.context.scene.frame_set(bpy.context.scene.frame_start + 4)
    n, pos, *_ = preview_state(pv)
    R["reload"]["instances_60"] = n
    R["reload"]["count_60"] = st.count
    arrays["reload_pos_4"] = pos
    mesh = bpy.data.objects[R["mesh_name"]]
    d = np.empty(len(mesh.data.polygons), np.int32)
    mesh.data.attributes["pa_depth"].data.foreach_get("value", d)
    arrays["reload_depth"] = d


@section("render")
def _():
    pv = bpy.data.objects[R["preview_name"]]
    mesh = bpy.data.objects[R["mesh_name"]]
    mesh.hide_render = True
    cam = bpy.data.cameras.new("render_cam")
    cam.lens = 50
    co = bpy.data.objects.new("render_cam", cam)
    bpy.context.scene.collection.objects.link(co)
    co.location = (0.0, -0.75, 0.0)
    co.rotation_euler = (np.pi / 2, 0.0, 0.0)
    bpy.context.scene.camera = co
    world = bpy.data.worlds.new("pa_world")
    world.color = (0.0, 0.0, 0.0)
    bpy.context.scene.world = world
    bpy.context.scene.view_settings.view_transform = "Standard"
    bpy.context.scene.render.engine = "CYCLES"
    bpy.context.scene.cycles.device = "CPU"
    bpy.context.scene.cycles.samples = 8
    bpy.context.scene.cycles.use_denoising = False
    bpy.context.scene.cycles.transparent_max_bounces = 64
    (
        bpy.context.scene.render.resolution_x,
        bpy.context.scene.render.resolution_y,
        bpy.context.scene.render.resolution_percentage,
    ) = 96, 96, 100
    bpy.context.scene.render.threads_mode = "FIXED"
    bpy.context.scene.render.threads = 2
    for b in (5, 100):
        pv.pa_avatar.budget = float(b)
        bpy.context.scene.render.filepath = os.path.join(out, f"render_{b}.png")
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        R[f"render_{b}_seconds"] = time.perf_counter() - t0
        R[f"render_{b}_count"] = pv.pa_avatar.count


@section("render_splats")
def _():
    pv = bpy.data.objects[R["preview_name"]]
    bpy.context.preferences.addons[pkg].preferences.python_path = sys.executable  # has numba
    bpy.context.view_layer.objects.active = pv
    pv.pa_avatar.budget = 50.0
    bpy.context.scene.frame_set(bpy.context.scene.frame_start + 3)
    bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y = 80, 64
    bpy.context.scene.render.film_transparent = True  # the splats alone (the world: test_blender_render_job)
    res = bpy.ops.render.progressive_avatars_splats()
    img = bpy.data.images["PA Splats"]
    px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
    img.pixels.foreach_get(px)
    arrays["splats_image"] = px.reshape(img.size[1], img.size[0], 4)[::-1]  # rows top-down
    co = bpy.context.scene.camera
    R["splats"] = {
        "result": list(res),
        "count": pv.pa_avatar.count,
        "preview_matrix": [list(r) for r in pv.matrix_world],
        "camera_matrix": [list(r) for r in co.matrix_world],
        "lens": co.data.lens,
        "sensor": co.data.sensor_width,
        "shift": [co.data.shift_x, co.data.shift_y],
        "size": list(img.size),
        "alpha_mode": img.alpha_mode,
        "frame": bpy.context.scene.frame_current - bpy.context.scene.frame_start,
    }


@section("mesh_edit")
def _():
    # A deformation that is neither a shape key nor the frame: a modifier added to the mesh.
    # The depsgraph handler must carry the preview along with the evaluated (deformed) mesh.
    mesh = bpy.data.objects[R["mesh_name"]]
    pv = bpy.data.objects[R["preview_name"]]
    pv.pa_avatar.budget = 100.0
    mod = mesh.modifiers.new("bend", "SIMPLE_DEFORM")
    mod.deform_method, mod.angle = "TWIST", 0.8
    bpy.context.view_layer.update()
    arrays["edit_verts"] = verts_of(mesh)
    arrays["edit_pos"] = preview_state(pv)[1]
    mesh.modifiers.remove(mod)
    bpy.context.view_layer.update()
    arrays["unedit_pos"] = preview_state(pv)[1]
    arrays["unedit_verts"] = verts_of(mesh)


@section("url")
def _():
    import http.server, threading

    data = open(stream_path, "rb").read()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            body = data if self.path == "/avatar.pavs" else data[: len(data) // 2]  # /cut.pavs: dies midway
            self.send_response(200)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(body)
            self.wfile.flush()
            self.close_connection = True

        def log_message(self, *args):
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{srv.server_address[1]}"
    mesh = bpy.data.objects[R["mesh_name"]]
    bpy.context.view_layer.objects.active = mesh
    bpy.context.preferences.system.use_online_access = False
    try:
        bpy.ops.object.progressive_avatars_load(url=base + "/avatar.pavs")
        R["url_offline"] = "no error"
    except RuntimeError as exc:
        R["url_offline"] = str(exc).splitlines()[0]
    bpy.context.preferences.system.use_online_access = True
    R["url"] = {}
    for name in ("avatar.pavs", "cut.pavs"):
        res = bpy.ops.object.progressive_avatars_load(url=f"{base}/{name}", budget=100.0)
        pv = [c for c in mesh.children if c.pa_avatar.is_preview][0]
        R["url"][name] = {
            "result": list(res),
            "total": pv.pa_avatar.total,
            "count": pv.pa_avatar.count,
            "instances": preview_state(pv)[0],
            "file": os.path.getsize(bpy.path.abspath(pv.pa_avatar.filepath)),
        }
    srv.shutdown()


@section("undo")
def _():
    # Undo brings back preview attributes as they were at the step; whatever the cache had
    # evaluated since must not be trusted (points past the step's budget hold an old frame).
    mesh = bpy.data.objects[R["mesh_name"]]
    pv = [c for c in mesh.children if c.pa_avatar.is_preview][0]
    name = pv.name
    sc = bpy.context.scene
    pv.pa_avatar.budget = 100.0
    sc.frame_set(sc.frame_start + 1)
    pv.pa_avatar.budget = 30.0
    sc.frame_set(sc.frame_start + 5)
    bpy.ops.ed.undo_push(message="budget 30 at frame 5")
    pv.pa_avatar.budget = 100.0
    bpy.ops.ed.undo_push(message="budget 100")
    bpy.ops.ed.undo()
    pv, sc = bpy.data.objects[name], bpy.context.scene  # undo replaced the Python objects
    R["undo"] = {
        "budget": pv.pa_avatar.budget,
        "frame": sc.frame_current - sc.frame_start,
        "file": bpy.path.abspath(pv.pa_avatar.filepath),
    }
    pv.pa_avatar.budget = 100.0
    arrays["undo_pos"] = preview_state(pv)[1]


@section("rig")
def _():
    for ob in bpy.context.selected_objects:
        ob.select_set(False)
    try:
        bpy.ops.import_scene.progressive_avatars_sequence(filepath=seq_path, as_rig=True, flame_model=flame_path)
        R["rig_mesh_sequence"] = "no error"
    except RuntimeError as exc:
        R["rig_mesh_sequence"] = str(exc).splitlines()[0]
    try:
        bad = os.path.join(os.path.dirname(flame_path), "flame_badface.npz")
        bpy.ops.import_scene.progressive_avatars_sequence(filepath=params_path, as_rig=True, flame_model=bad)
        R["rig_bad_faces"] = "no error"
    except RuntimeError as exc:
        R["rig_bad_faces"] = str(exc).splitlines()[0]
    bpy.context.scene.frame_start = 3
    t0 = time.perf_counter()
    res = bpy.ops.import_scene.progressive_avatars_sequence(filepath=params_path, as_rig=True, flame_model=flame_path)
    R["rig_seconds"] = time.perf_counter() - t0
    obj = bpy.context.active_object
    arm = obj.parent
    key = obj.data.shape_keys
    drivers = key.animation_data.drivers
    R["rig"] = {
        "result": list(res),
        "keys": [k.name for k in key.key_blocks],
        "bones": [b.name for b in arm.data.bones],
        "groups": [g.name for g in obj.vertex_groups],
        "modifiers": [m.type for m in obj.modifiers],
        "drivers": len(drivers),
        "simple": all(d.driver.is_simple_expression and d.driver.is_valid for d in drivers),
        "rest": [[list(row) for row in b.matrix_local] for b in arm.data.bones],
        "frame_range": [bpy.context.scene.frame_start, bpy.context.scene.frame_end],
    }
    w = np.zeros((len(obj.data.vertices), len(obj.vertex_groups)), np.float32)
    for g in obj.vertex_groups:  # test-side read-back only
        for i in range(len(obj.data.vertices)):
            try:
                w[i, g.index] = g.weight(i)
            except RuntimeError:
                pass
    arrays["rig_weights"] = w
    for t in __FRAMES__:
        bpy.context.scene.frame_set(3 + t)
        arrays[f"rig_{t}"] = verts_of(obj)

    # Artist edits at frame 3+3: an expression coefficient and the jaw's rotation (its
    # pose-corrective keys follow the bone through their drivers).
    def curve(owner, path, index=0):
        return owner.animation_data.action.fcurve_ensure_for_datablock(owner, path, index=index)

    fc = curve(key, 'key_blocks["expr_000"].value')
    fc.keyframe_points[3].co[1] = 2.5
    fc.update()
    q = [0.9, 0.3, -0.2, 0.25]
    for c in range(4):
        fc = curve(arm, 'pose.bones["jaw"].rotation_quaternion', c)
        fc.keyframe_points[3].co[1] = q[c]
        fc.update()
    bpy.context.scene.frame_set(3 + 3)
    arrays["rig_edit_3"] = verts_of(obj)


np.savez(os.path.join(out, "arrays.npz"), **arrays)
print("PA_REPORT " + json.dumps(R, default=str))
