"""The Blender extension end to end, with the bpy module in subprocesses.

bpy is one per process and keeps global state, so every Blender session here runs in its
own interpreter with BLENDER_USER_RESOURCES/CONFIG/SCRIPTS in a temporary folder (no real
Blender configuration is read or written). The package is validated and built with
Blender's own blender_ext.py, installed into the clean Blender and driven through its
operators; one session prints a JSON report that the tests below assert on.
"""

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
import zipfile

import numpy as np
import pytest

from tests.helpers import random_forest, sphere_mesh

pytestmark = pytest.mark.blender

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
T_FRAMES = 8
CHECK_FRAMES = (0, 3, 7)


def _bpy_dir():
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("bpy module not installed")
    return list(spec.submodule_search_locations)[0]


def _blender_ext():
    return os.path.join(_bpy_dir(), "5.0", "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")


def _clean_env(tmp):
    env = dict(os.environ)
    for key in ("BLENDER_USER_RESOURCES", "BLENDER_USER_CONFIG", "BLENDER_USER_SCRIPTS", "BLENDER_USER_DATAFILES"):
        env[key] = os.path.join(tmp, key.lower())
        os.makedirs(env[key], exist_ok=True)
    env["PYTHONPATH"] = ""
    return env


def make_inputs(folder):
    """A sphere sequence (mesh npz) and a stream written by core (its template = the mesh)."""
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.stream.format import write_stream

    rng = np.random.default_rng(7)
    v, f = sphere_mesh(10, 14, radius=0.1)
    t = np.arange(T_FRAMES, dtype=np.float64)[:, None, None]
    wobble = np.sin(3 * v[None, :, 1:2] / 0.1 + t) * 0.01
    verts = (v[None] * (1 + 0.05 * t) + wobble + rng.normal(0, 1e-3, (T_FRAMES,) + v.shape)).astype(np.float32)
    seq = os.path.join(folder, "seq.npz")
    np.savez(seq, vertices=verts, faces=f)
    forest = random_forest(f, rng, depth=3, frac=0.4)
    av = Avatar.initial(forest)
    N = forest.num_faces
    av.d_mu[:] = rng.normal(0, 0.2, (N, 3))
    av.d_log_scale[:] = -1.3 + rng.normal(0, 0.2, (N, 3))
    av.d_rot[:] = rng.normal(size=(N, 4))
    av.f_dc[:] = rng.normal(0, 1.2, (N, 3))
    av.opacity_logit[:] = rng.normal(1.5, 0.5, N)
    stream = os.path.join(folder, "avatar.pavs")
    write_stream(stream, av, importance=rng.random(N), quantize=False)
    trainer = os.path.join(folder, "fake_train.py")
    with open(trainer, "w") as fh:
        fh.write(textwrap.dedent(f"""
            import argparse, shutil, os
            p = argparse.ArgumentParser(); p.add_argument('--data'); p.add_argument('--out'); p.add_argument('--preset')
            a = p.parse_args(); os.makedirs(a.out, exist_ok=True)
            for i in range(1, 5):
                print(f'it {{i}}/4 loss 0.1', flush=True)
            shutil.copy({stream!r}, os.path.join(a.out, 'avatar.pavs'))
        """))
    return seq, stream, trainer, verts


def make_rig_inputs(folder):
    """A small FLAME-format model (npz) and a VHAP tracked-parameter file for it."""
    from tests.test_flame import N_SHAPE, make_flame_arrays, random_params

    from progressive_avatars.core.flame.model import _model_from_mapping

    model = _model_from_mapping(make_flame_arrays(seed=3), "test model", N_SHAPE)
    model_path = os.path.join(folder, "flame_model.npz")
    model.save_npz(model_path)
    prm = random_params(T_FRAMES, seed=11, scale=0.4)
    prm["expr"][2, 1] = 14.0  # beyond Blender's slider range: stored scaled
    params_path = os.path.join(folder, "tracked_flame_params.npz")
    np.savez(params_path, **prm)
    return model_path, params_path


SCENARIO = r'''
import json, os, sys, time, traceback
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
    R["operators"] = {name: hasattr(getattr(bpy.ops, name.split(".")[0]), name.split(".")[1]) for name in (
        "import_scene.progressive_avatars_sequence", "import_scene.progressive_avatars_cameras",
        "object.progressive_avatars_load", "object.progressive_avatars_depth_colors",
        "export_scene.progressive_avatars_ply", "render.progressive_avatars_splats",
        "progressive_avatars.train", "progressive_avatars.train_cancel")}
    R["panels"] = [n for n in ("PA_PT_main", "PA_PT_avatar", "PA_PT_depth", "PA_PT_train") if hasattr(bpy.types, n)]
    R["import_menu"] = any("progressive_avatars" in getattr(f, "__module__", "")
                           for f in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize())

pkg = "bl_ext.user_default.progressive_avatars"
ext = sys.modules.get(pkg)
R["extension_dir"] = os.path.dirname(ext.__file__) if ext else None

def verts_of(obj):
    dg = bpy.context.evaluated_depsgraph_get()
    me = obj.evaluated_get(dg).data
    a = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", a)
    return a.reshape(-1, 3)

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
    if n:
        ip.attributes["instance_transform"].data.foreach_get("value", xf)
    # Points are laid out by root face; the rank attribute is their stream position. Return
    # everything in stream order (instances: the points with rank < n, in point order).
    rank = np.empty(len(pv.data.vertices), np.int32)
    pv.data.attributes["rank"].data.foreach_get("value", rank)
    by_rank = np.argsort(rank)
    inst = np.argsort(rank[rank < n])
    xf = xf.reshape(n, 4, 4).transpose(0, 2, 1)[inst]
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
    R["at25"] = {"count": st.count, "total": st.total, "mb": st.megabytes, "level": st.level_reached,
                 "status": st.status}
    R["at25_instances"] = preview_state(pv)[0]
    # slider change timing (count within what is evaluated: only the modifier input moves)
    t0 = time.perf_counter(); st.budget = 20.0; bpy.context.evaluated_depsgraph_get()
    R["slider_seconds"] = time.perf_counter() - t0
    st.budget = 25.0
    for t in (3, 6):
        bpy.context.scene.frame_set(bpy.context.scene.frame_start + t)
        n, pos, rot, scl, xf = preview_state(pv)
        arrays[f"pos_{t}"], arrays[f"rot_{t}"], arrays[f"scl_{t}"], arrays[f"xf_{t}"] = pos, rot, scl, xf
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
    cam_mod = sys.modules[pkg + ".core.geometry.camera"]
    seq_mod = sys.modules[pkg + ".blender_addon.sequence"]
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector
    cam = cam_mod.Camera.look_at([0.1, 0.05, 0.6], [0, 0, 0], [0, 1, 0], 500.0, 500.0, 180.0, 110.0, 320, 240)
    obj, s = seq_mod.add_camera(bpy.context, "test_cam", cam, z_up=True)
    bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y = s["resolution"]
    pts = np.random.default_rng(0).normal(0, 0.05, (20, 3))
    uv_core, _ = cam.project(pts)
    z_up = np.array(sys.modules[pkg + ".core.bridge.preview"].Y_UP_TO_Z_UP)
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
    R["reload"] = {"budget": st.budget, "count": st.count, "filepath": os.path.basename(st.filepath),
                   "source": st.source.name if st.source else None, "is_preview": st.is_preview,
                   "frame": bpy.context.scene.frame_current - bpy.context.scene.frame_start,
                   "instances": preview_state(pv)[0],
                   "attributes": sorted(a.name for a in pv.data.attributes if not a.name.startswith("."))}
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
    world = bpy.data.worlds.new("pa_world"); world.color = (0.0, 0.0, 0.0); bpy.context.scene.world = world
    bpy.context.scene.view_settings.view_transform = "Standard"
    bpy.context.scene.render.engine = "CYCLES"
    bpy.context.scene.cycles.device = "CPU"
    bpy.context.scene.cycles.samples = 8
    bpy.context.scene.cycles.use_denoising = False
    bpy.context.scene.cycles.transparent_max_bounces = 64
    bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y, bpy.context.scene.render.resolution_percentage = 96, 96, 100
    bpy.context.scene.render.threads_mode = "FIXED"; bpy.context.scene.render.threads = 2
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
    res = bpy.ops.render.progressive_avatars_splats()
    img = bpy.data.images["PA Splats"]
    px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
    img.pixels.foreach_get(px)
    arrays["splats_image"] = px.reshape(img.size[1], img.size[0], 4)[::-1]  # rows top-down
    co = bpy.context.scene.camera
    R["splats"] = {"result": list(res), "count": pv.pa_avatar.count, "preview_matrix": [list(r) for r in pv.matrix_world],
                   "camera_matrix": [list(r) for r in co.matrix_world], "lens": co.data.lens,
                   "sensor": co.data.sensor_width, "shift": [co.data.shift_x, co.data.shift_y], "size": list(img.size),
                   "frame": bpy.context.scene.frame_current - bpy.context.scene.frame_start}

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
        R["url"][name] = {"result": list(res), "total": pv.pa_avatar.total, "count": pv.pa_avatar.count,
                          "instances": preview_state(pv)[0], "file": os.path.getsize(bpy.path.abspath(pv.pa_avatar.filepath))}
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
    R["undo"] = {"budget": pv.pa_avatar.budget, "frame": sc.frame_current - sc.frame_start,
                 "file": bpy.path.abspath(pv.pa_avatar.filepath)}
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
    bpy.context.scene.frame_start = 3
    t0 = time.perf_counter()
    res = bpy.ops.import_scene.progressive_avatars_sequence(filepath=params_path, as_rig=True, flame_model=flame_path)
    R["rig_seconds"] = time.perf_counter() - t0
    obj = bpy.context.active_object
    arm = obj.parent
    key = obj.data.shape_keys
    drivers = key.animation_data.drivers
    R["rig"] = {"result": list(res), "keys": [k.name for k in key.key_blocks], "bones": [b.name for b in arm.data.bones],
                "groups": [g.name for g in obj.vertex_groups], "modifiers": [m.type for m in obj.modifiers],
                "drivers": len(drivers), "simple": all(d.driver.is_simple_expression and d.driver.is_valid for d in drivers),
                "rest": [[list(row) for row in b.matrix_local] for b in arm.data.bones], "frame_range": [bpy.context.scene.frame_start, bpy.context.scene.frame_end]}
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
'''.replace("__FRAMES__", repr(CHECK_FRAMES))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = str(tmp_path_factory.mktemp("blender"))
    ext = _blender_ext()
    validate = subprocess.run([sys.executable, ext, "validate", ROOT], capture_output=True, text=True)
    dist = os.path.join(tmp, "dist")
    os.makedirs(dist)
    build = subprocess.run([sys.executable, ext, "build", "--source-dir", ROOT, "--output-dir", dist],
                           capture_output=True, text=True)
    zips = [os.path.join(dist, z) for z in os.listdir(dist) if z.endswith(".zip")]
    out = os.path.join(tmp, "out")
    os.makedirs(out)
    seq, stream, trainer, verts = make_inputs(out)
    flame_path, params_path = make_rig_inputs(out)
    result = {"validate": validate, "build": build, "zips": zips, "out": out, "seq": seq, "stream": stream,
              "verts": verts, "flame": flame_path, "params": params_path, "report": None}
    if build.returncode != 0 or len(zips) != 1:
        return result
    script = os.path.join(tmp, "scenario.py")
    with open(script, "w") as fh:
        fh.write(SCENARIO)
    proc = subprocess.run([sys.executable, script, zips[0], seq, stream, trainer, out, flame_path, params_path],
                          capture_output=True,
                          text=True, env=_clean_env(tmp), timeout=600)
    result["proc"] = proc
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PA_REPORT ")]
    if lines:
        result["report"] = json.loads(lines[-1][len("PA_REPORT "):])
        result["arrays"] = dict(np.load(os.path.join(out, "arrays.npz")))
    return result


def _report(session):
    if session["report"] is None:
        proc = session.get("proc")
        pytest.fail("Blender session produced no report:\n" + (proc.stdout[-3000:] + proc.stderr[-3000:] if proc else
                                                                 session["build"].stdout + session["build"].stderr))
    return session["report"]


def _no_error(rep, name):
    errs = [e for e in rep["errors"] if e.startswith(name + ":")]
    assert not errs, errs[0]


def _stream():
    from progressive_avatars.core.stream import format as stream
    return stream


def test_manifest_validates_and_builds(session):
    assert session["validate"].returncode == 0, session["validate"].stdout + session["validate"].stderr
    assert session["build"].returncode == 0, session["build"].stdout + session["build"].stderr
    (zp,) = session["zips"]
    names = zipfile.ZipFile(zp).namelist()
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert "blender_addon/__init__.py" in names and "core/bridge/preview.py" in names
    leaked = [n for n in names if n.split("/")[0] in ("tests", "scripts", "docs", ".venv", "runs", ".git")
              or "__pycache__" in n or n.endswith(".pyc")]
    assert not leaked, leaked
    # Training and export run from the zip (core/train/jobs.py); the synthetic-data generator and the
    # evaluation report/plots are not shipped.
    assert {"core/train/jobs.py", "core/train/trainer.py", "core/io/run.py", "core/io/mesh_io.py"} <= set(names)
    assert not {"core/synthetic/head.py", "core/evaluate/sweep.py", "core/evaluate/plots.py"} & set(names)


def test_installs_and_enables_in_clean_blender(session):
    rep = _report(session)
    _no_error(rep, "install")
    assert rep["addon_enabled"]
    assert all(rep["operators"].values()), rep["operators"]
    assert len(rep["panels"]) == 4
    assert rep["extension_dir"] and "user_default" in rep["extension_dir"]


def test_import_sequence_positions_exact(session):
    rep = _report(session)
    _no_error(rep, "import")
    verts = session["verts"]
    assert rep["shape_keys"] == T_FRAMES + 1  # Basis + one per frame
    assert rep["frame_range"] == [5, 5 + T_FRAMES - 1]
    for t in CHECK_FRAMES:
        np.testing.assert_allclose(session["arrays"][f"seq_{t}"], verts[t], atol=1e-6, rtol=0)


def test_import_flame_rig(session):
    """As a FLAME rig: the evaluated mesh equals FLAME at every checked frame; edits to an
    expression key and to the jaw bone give what core's rig model says (whose equality with
    FLAME is pinned in test_flame_rig); weights, keys, bones and drivers are what was built."""
    rep = _report(session)
    _no_error(rep, "rig")
    from progressive_avatars.core.flame.model import flame_forward, load_flame_model
    from progressive_avatars.core.flame.rig import build_flame_rig

    model = load_flame_model(session["flame"])
    prm = dict(np.load(session["params"]))
    rig = build_flame_rig(model, prm)
    r = rep["rig"]
    assert "holds meshes, not FLAME parameters" in rep["rig_mesh_sequence"]
    assert r["result"] == ["FINISHED"] and r["modifiers"] == ["ARMATURE"]
    assert r["keys"] == ["Basis"] + rig.expr_key_names() + rig.pose_key_names()
    assert r["bones"] == ["root", "neck", "jaw", "eye_0", "eye_1"] and r["groups"] == r["bones"]
    assert r["drivers"] == 9 * 4 and r["simple"]  # evaluated without Python (no auto-exec needed)
    assert r["frame_range"] == [3, 3 + T_FRAMES - 1]
    for k, m in enumerate(r["rest"]):  # bones rest unrotated at FLAME's joints
        np.testing.assert_allclose(np.array(m)[:3, :3], np.eye(3), atol=1e-6)
        np.testing.assert_allclose(np.array(m)[:3, 3], rig.rest_joints[k], atol=1e-6)
    np.testing.assert_allclose(session["arrays"]["rig_weights"], model.weights, atol=1e-6)
    assert rig.expr_scale[1] > 1  # the 14.0 coefficient went through a scaled key
    want = flame_forward(model, **prm)
    for t in CHECK_FRAMES:
        np.testing.assert_allclose(session["arrays"][f"rig_{t}"], want[t], atol=2e-6, rtol=0)
    rig.expr_values[3, 0] = 2.5
    rig.quaternions[3, 2] = [0.9, 0.3, -0.2, 0.25]
    edited = rig.vertices(frames=[3])[0]
    assert np.abs(edited - want[3]).max() > 1e-3  # the edit is visible
    np.testing.assert_allclose(session["arrays"]["rig_edit_3"], edited, atol=2e-6, rtol=0)


def test_undo_leaves_no_stale_points(session):
    rep = _report(session)
    _no_error(rep, "undo")
    assert rep["undo"]["budget"] == 30.0
    av = _stream().read_stream(rep["undo"]["file"])  # the last URL load: a cut stream
    ref = av.gaussians(session["verts"][rep["undo"]["frame"]])
    np.testing.assert_allclose(session["arrays"]["undo_pos"], ref["means"], atol=1e-5, rtol=0)


def test_budget_shows_stream_count(session):
    rep = _report(session)
    _no_error(rep, "load")
    info = _stream().read_header(session["stream"])
    assert rep["at25"]["count"] == info.count_for_percent(25)
    assert rep["at25_instances"] == info.count_for_percent(25)
    assert rep["at100_instances"] == info.num_records
    assert rep["at25"]["total"] == info.num_records
    assert abs(rep["at25"]["mb"] - info.bytes_for_count(info.count_for_percent(25)) / 1e6) < 1e-9
    assert rep["at25"]["level"] == int(info.level_of(info.count_for_percent(25) - 1))


def test_frames_match_core_evaluation(session):
    rep = _report(session)
    _no_error(rep, "load")
    from progressive_avatars.core.avatar.binding import quat_to_rotmat

    av = _stream().read_stream(session["stream"])
    n = _stream().read_header(session["stream"]).count_for_percent(25)
    verts = session["verts"]
    for t in (3, 6):
        ref = av.gaussians(verts[t])
        a = session["arrays"]
        assert rep[f"instances_{t}"] == n
        np.testing.assert_allclose(a[f"pos_{t}"][:n], ref["means"][:n], atol=1e-5, rtol=0)
        np.testing.assert_allclose(a[f"scl_{t}"][:n], ref["scales"][:n], atol=1e-6, rtol=1e-5)
        dots = np.abs(np.sum(a[f"rot_{t}"][:n] * ref["quats"][:n], axis=1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-5)
        # What Geometry Nodes instances: rotation·diag(scale), translation = mean.
        xf = a[f"xf_{t}"]
        want = quat_to_rotmat(ref["quats"][:n]) * ref["scales"][:n, None, :]
        np.testing.assert_allclose(xf[:, :3, :3], want, atol=1e-5)
        np.testing.assert_allclose(xf[:, :3, 3], ref["means"][:n], atol=1e-5)
    ref = av.gaussians(verts[6])
    np.testing.assert_allclose(session["arrays"]["pos_100_6"], ref["means"], atol=1e-5, rtol=0)


def test_depth_attribute_and_legend(session):
    rep = _report(session)
    _no_error(rep, "load")
    forest = _stream().read_stream(session["stream"]).forest
    np.testing.assert_array_equal(session["arrays"]["depth"], forest.depth_per_root())
    assert rep["depth_color_domain"] == "CORNER"
    assert rep["active_color"] == "pa_depth_color"
    assert [c for _, c in rep["legend"]] == forest.depth_histogram().tolist()


def test_export_ply_current_frame_budget(session):
    rep = _report(session)
    _no_error(rep, "export")
    from progressive_avatars.core.io.ply import read_ply

    g = read_ply(os.path.join(session["out"], "frame.ply"))
    av = _stream().read_stream(session["stream"])
    n = rep["export_count"]
    assert n == _stream().read_header(session["stream"]).count_for_percent(50)
    ref = av.gaussians(session["verts"][2])
    np.testing.assert_allclose(g["means"], ref["means"][:n], atol=1e-5)
    # The model's own colours and opacities (once the preview's linear display colours leaked in).
    np.testing.assert_allclose(g["colors"], ref["colors"][:n], atol=1e-5)
    np.testing.assert_allclose(g["opacities"], ref["opacities"][:n], atol=1e-5)


def test_camera_conversion_projects_like_core(session):
    rep = _report(session)
    _no_error(rep, "camera")
    assert rep["camera_uv_err"] < 1e-3


def test_train_operator_runs_script_and_loads_result(session):
    rep = _report(session)
    _no_error(rep, "train")
    assert rep["train"]["result"] == ["FINISHED"]
    assert rep["train"]["progress"] == 100.0 and not rep["train"]["running"]
    assert rep["train"]["loaded"] == "avatar.pavs"
    _no_error(rep, "errors_reported")
    assert "Cannot load avatar" in rep["missing_file"]


def test_save_reload_keeps_state(session):
    rep = _report(session)
    _no_error(rep, "save_reload")
    r = rep["reload"]
    info = _stream().read_header(session["stream"])
    assert r["is_preview"] and r["source"] == rep["mesh_name"] and r["filepath"] == "avatar.pavs"
    assert r["budget"] == pytest.approx(30.0) and r["count"] == info.count_for_percent(30)
    assert r["instances"] == info.count_for_percent(30)
    assert {"rotation", "scale", "opacity", "color", "level", "rank"} <= set(r["attributes"])
    assert r["instances_60"] == r["count_60"] == info.count_for_percent(60)
    av = _stream().read_stream(session["stream"])
    n = r["count_60"]
    np.testing.assert_allclose(session["arrays"]["reload_pos_4"][:n], av.gaussians(session["verts"][4])["means"][:n],
                               atol=1e-5)
    # Depth follows the budget: the deepest level among the first count_60 Gaussians per face.
    from progressive_avatars.core.bridge.preview import depth_per_face

    want = depth_per_face(av.forest, av.forest.num_roots, n)
    np.testing.assert_array_equal(session["arrays"]["reload_depth"], want)
    assert (want >= 0).all() and not np.array_equal(want, av.forest.depth_per_root())


def test_cycles_renders_show_coloured_splats(session):
    rep = _report(session)
    _no_error(rep, "render")
    from PIL import Image

    lit = {}
    for b in (5, 100):
        img = np.asarray(Image.open(os.path.join(session["out"], f"render_{b}.png")).convert("RGB"), np.float32) / 255
        border = np.concatenate([img[0], img[-1], img[:, 0], img[:, -1]])
        bg = np.median(border, axis=0)
        assert np.abs(border - bg).max() < 0.1, f"{b}%: the background is not clean"
        lit[b] = np.abs(img - bg).max(axis=2) > 0.1
        assert lit[b].mean() > 0.02, f"{b}%: almost nothing visible"
        chroma = img.max(axis=2) - img.min(axis=2)
        assert chroma[lit[b]].mean() > 0.08, f"{b}%: splats are not coloured"
    assert lit[100].mean() > 1.5 * lit[5].mean()


def test_render_splats_operator_matches_core_render(session):
    rep = _report(session)
    _no_error(rep, "render_splats")
    from progressive_avatars.core.bridge import preview as preview_data
    from progressive_avatars.core.render.rasterize import render_numpy

    r = rep["splats"]
    assert r["result"] == ["FINISHED"]
    av = _stream().read_stream(session["stream"])
    n = r["count"]
    assert n == _stream().read_header(session["stream"]).count_for_percent(50)
    g = av.gaussians(session["verts"][r["frame"]], ids=np.arange(n))
    means, quats, scales = preview_data.transform_gaussians(np.array(r["preview_matrix"]), g["means"], g["quats"], g["scales"])
    w, h = r["size"]
    cam = preview_data.camera_from_blender(np.array(r["camera_matrix"]), r["lens"], r["sensor"], *r["shift"], w, h,
                                           z_up=False)
    image, alpha = render_numpy(means, quats, scales, g["opacities"], g["colors"], cam, np.zeros(3, np.float32))[:2]
    got = session["arrays"]["splats_image"]
    assert alpha.max() > 0.5 and (alpha > 0.01).mean() > 0.05  # the head is in view, not a blank frame
    # Rendered with the model's (sRGB) colours, stored scene-linear as Blender float images are.
    np.testing.assert_allclose(got[..., :3], preview_data.srgb_to_linear(image), atol=1e-4)
    np.testing.assert_allclose(got[..., 3], alpha, atol=1e-4)


def test_preview_follows_a_modifier_deformation(session):
    """Whatever Blender evaluates: a modifier added to the mesh moves the preview (the
    depsgraph handler), and removing it moves it back."""
    rep = _report(session)
    _no_error(rep, "mesh_edit")
    av = _stream().read_stream(session["stream"])
    a = session["arrays"]
    assert np.abs(a["edit_verts"] - a["unedit_verts"]).max() > 1e-3  # the twist really deformed the mesh
    np.testing.assert_allclose(a["edit_pos"], av.gaussians(a["edit_verts"])["means"], atol=1e-5)
    np.testing.assert_allclose(a["unedit_pos"], av.gaussians(a["unedit_verts"])["means"], atol=1e-5)


def test_url_streaming_keeps_the_verified_prefix(session):
    """Load from a loopback HTTP server: refused while online access is off; a whole stream
    loads whole; a connection cut midway keeps exactly the verified records."""
    rep = _report(session)
    _no_error(rep, "url")
    assert "Online access is disabled" in rep["url_offline"]
    info = _stream().read_header(session["stream"])
    whole, cut = rep["url"]["avatar.pavs"], rep["url"]["cut.pavs"]
    assert whole["result"] == ["FINISHED"] and whole["total"] == whole["instances"] == info.num_records
    assert whole["file"] == info.total_bytes
    half = info.total_bytes // 2
    n = max(k for k in range(info.num_records + 1) if info.bytes_for_count(k) <= half)
    assert cut["result"] == ["FINISHED"] and cut["total"] == cut["instances"] == n > 0
    assert cut["file"] == info.bytes_for_count(n)
