"""Blender session run by test_blender_splat_look.py (a real file so it can be read, linted and run by hand)."""

import importlib.util, json, os, sys, traceback

root, src, out = sys.argv[1:4]
import bpy
import numpy as np

spec = importlib.util.spec_from_file_location(
    "pa_look", os.path.join(root, "__init__.py"), submodule_search_locations=[root]
)
pkg = importlib.util.module_from_spec(spec)
sys.modules["pa_look"] = pkg
spec.loader.exec_module(pkg)
pkg.register()
ply_import = sys.modules["pa_look.blender_addon.ply_import"]
look = sys.modules["pa_look.blender_addon.splat_look"]
pdata = sys.modules["pa_look.core.bridge.transforms"]
R = {}
try:
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    sc = bpy.context.scene
    with np.load(src) as d:
        g = {k: d[k] for k in d.files}
    obj = ply_import.create_splat_object(bpy.context, "splats", g)
    cam = bpy.data.cameras.new("cam")
    cam.lens = 50
    co = bpy.data.objects.new("cam", cam)
    sc.collection.objects.link(co)
    co.location = (0.0, -0.6, 0.0)
    co.rotation_euler = (np.pi / 2, 0.0, 0.0)
    sc.camera = co
    world = bpy.data.worlds.new("w")
    sc.world = world
    for node in world.node_tree.nodes if world.node_tree else ():
        if node.type == "BACKGROUND":
            node.inputs["Color"].default_value = (0, 0, 0, 1)
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = 32
    sc.cycles.use_denoising = False
    sc.render.resolution_x = sc.render.resolution_y = 64
    sc.render.resolution_percentage = 100
    R["changed"] = sorted(look.configure_scene(sc))  # after the resolution: the focal length in pixels
    sc.render.threads_mode = "FIXED"
    sc.render.threads = 2
    sc.render.filepath = os.path.join(out, "cycles.png")
    bpy.ops.render.render(write_still=True)
    c = pdata.camera_from_blender(
        np.array(co.matrix_world), cam.lens, cam.sensor_width, cam.shift_x, cam.shift_y, 64, 64, z_up=False
    )
    R["camera"] = {"R": c.R.tolist(), "t": c.t.tolist(), "intr": [c.fx, c.fy, c.cx, c.cy]}
    R["material_method"] = bpy.data.materials["PA Splat"].surface_render_method

    # The hull Geometry Nodes made: each instance's world matrix (rotation x per-axis hull
    # scale) and the camera's distance to each splat, to check the hull covers the splat as
    # the rasteriser draws it (dilated, out to its 1/255 cut-off).
    def instances(key):
        dg = bpy.context.evaluated_depsgraph_get()
        mats = []
        for inst in dg.object_instances:  # (each item is only valid during the iteration)
            if inst.is_instance and inst.parent.original == obj:
                mats.append(np.array(inst.matrix_world))
                if key + "_vertices" not in R:
                    me = inst.object.data
                    R[key + "_vertices"] = [list(v.co) for v in me.vertices]
                    R[key + "_faces"] = [list(p.vertices) for p in me.polygons]
        R[key + "_matrices"] = [m[:3, :3].tolist() for m in mats]
        R[key + "_origins"] = [m[:3, 3].tolist() for m in mats]

    # The viewport shows the ellipsoids by default (cards face the scene camera, renders use them).
    mod = obj.modifiers["PA Splats"]

    def set_input(name, value):
        key = next(i.identifier for i in mod.node_group.interface.items_tree if getattr(i, "name", "") == name)
        mod[key] = value
        obj.update_tag()

    instances("viewport_default")
    set_input("Cards in Viewport", True)
    instances("cards")
    set_input("Cards in Viewport", False)
    R["camera_location"] = list(co.location)
    R["camera_rotation"] = np.array(co.matrix_world)[:3, :3].tolist()
    R["focal_px"] = 64 * cam.lens / cam.sensor_width
    # The opt-in As Trained compositing: sRGB colours blended as they are, Raw view transform.
    R["changed_trained"] = sorted(look.configure_scene(sc, as_trained=True))
    R["view_transform_trained"] = sc.view_settings.view_transform
    sc.render.filepath = os.path.join(out, "cycles_trained.png")
    bpy.ops.render.render(write_still=True)
    # The ellipsoid hulls (Camera Cards off): evaluated, not rendered.
    set_input("Camera Cards", False)
    instances("ellipsoids")
except Exception:
    R["error"] = traceback.format_exc()
print("PA_LOOK " + json.dumps(R))
