"""Blender session run by test_blender_guard.py, appended to guard_prelude.py (which defines ARGS, R, PKG and the helpers)."""

res, mesh = import_mesh(ARGS["seq"])
R["import"] = res
sc = bpy.context.scene
bpy.context.view_layer.objects.active = mesh
ext = sys.modules[PKG + ".blender_addon.depth"]


@section("cuts")
def _():
    R["cuts"] = {}
    for name, path in ARGS["cuts"].items():
        bpy.context.view_layer.objects.active = mesh
        before = scene_state()
        res = run_op(bpy.ops.object.progressive_avatars_load, filepath=path, budget=100.0)
        r = {"result": res}
        pv = preview_of(mesh)
        if res == ["FINISHED"]:
            sc.frame_set(sc.frame_start + 1)
            r.update(
                total=pv.pa_avatar.total, count=pv.pa_avatar.count, instances=instances(pv), status=pv.pa_avatar.status
            )
            arrays[f"pos_{name}"] = positions(pv)
            d = np.empty(len(mesh.data.polygons), np.int32)
            mesh.data.attributes["pa_depth"].data.foreach_get("value", d)
            arrays[f"depth_{name}"] = d
            r["legend"] = [[i.depth, i.faces] for i in mesh.pa_mesh.depth_legend]
            r["slider"] = {}
            for p in (0.0, 1.0, 2.0, 5.0, 20.0, 60.0, 100.0):  # the slider on a cut stream
                pv.pa_avatar.budget = p
                r["slider"][str(p)] = [pv.pa_avatar.count, instances(pv), pv.pa_avatar.status]
            pv.pa_avatar.budget = 100.0
            bpy.data.objects.remove(pv)  # next case starts from the bare mesh
        else:
            r["unchanged"] = scene_state() == before
            r["preview_left"] = pv is not None
        R["cuts"][name] = r


@section("url")
def _():
    import http.server, threading

    blobs = {os.path.basename(p): open(p, "rb").read() for p in ARGS["url_streams"]}

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # /NAME/CUT: NAME's first CUT bytes, then the connection dies
            _, name, cut = self.path.split("/")
            data = blobs[name]
            self.send_response(200)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data[: int(cut)])
            self.wfile.flush()
            self.close_connection = True

        def log_message(self, *args):
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{srv.server_address[1]}"
    bpy.context.preferences.system.use_online_access = True
    R["url"] = {}
    for key, (name, cut) in ARGS["url_cuts"].items():
        bpy.context.view_layer.objects.active = mesh
        before = scene_state()
        res = run_op(bpy.ops.object.progressive_avatars_load, url=f"{base}/{name}/{cut}", budget=100.0)
        r = {"result": res}
        pv = preview_of(mesh)
        if res == ["FINISHED"]:
            r.update(
                total=pv.pa_avatar.total,
                instances=instances(pv),
                file=os.path.getsize(bpy.path.abspath(pv.pa_avatar.filepath)),
            )
            arrays[f"urlpos_{key}"] = positions(pv)
            bpy.data.objects.remove(pv)
        else:
            r["unchanged"] = scene_state() == before
        R["url"][key] = r
    # Two previews streamed from URLs that end alike (.../bare.pavs/N, .../full.pavs/N): each
    # keeps its own download, so neither file is overwritten by the other.
    made = []
    for name in ("bare.pavs", "full.pavs"):
        res, m = import_mesh(ARGS["seq"])
        bpy.context.view_layer.objects.active = m
        res = run_op(
            bpy.ops.object.progressive_avatars_load, url=f"{base}/{name}/{ARGS['url_same_tail']}", budget=100.0
        )
        pv = preview_of(m)
        made += [m, pv]
        R.setdefault("url_same_tail", []).append(
            [name, res, bpy.path.abspath(pv.pa_avatar.filepath), pv.pa_avatar.total]
        )
    for r in R["url_same_tail"]:  # the file each preview refers to, after both loads
        r.append(os.path.getsize(r[2]))
    for o in made:
        bpy.data.objects.remove(o)
    srv.shutdown()


@section("rollback")
def _():
    # A failure while building the preview (after every check on the file passed): nothing
    # new is left and the preview that was there stays.
    bpy.context.view_layer.objects.active = mesh
    assert run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["cuts"]["level1"]) == ["FINISHED"]
    old = preview_of(mesh).name
    before = scene_state()
    orig = ext.apply_depth

    def boom(*a, **k):
        raise RuntimeError("injected failure")

    ext.apply_depth = boom
    try:
        res = run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["cuts"]["level2"])
    finally:
        ext.apply_depth = orig
    R["rollback"] = {
        "result": res,
        "unchanged": scene_state() == before,
        "diff": [k for k in before if scene_state()[k] != before[k]],
        "old_kept": preview_of(mesh).name == old,
    }


@section("depth_toggle")
def _():
    bpy.context.view_layer.objects.active = mesh
    run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["cuts"]["template_mid"])
    pv = preview_of(mesh)
    user = mesh.data.color_attributes.new("user_paint", "BYTE_COLOR", "POINT")
    mesh.data.color_attributes.active_color = user
    spaces = [sp for s in bpy.data.screens for a in s.areas for sp in a.spaces if sp.type == "VIEW_3D"]
    for sp in spaces:
        sp.shading.color_type = "OBJECT"
    bpy.context.view_layer.objects.active = pv
    R["toggle_on"] = run_op(bpy.ops.object.progressive_avatars_depth_colors)
    me = mesh.data
    col = np.empty(len(me.loops) * 4, np.float32)
    me.color_attributes["pa_depth_color"].data.foreach_get("color", col)
    arrays["depth_colors_corner"] = col.reshape(-1, 4).copy()
    d = np.empty(len(me.polygons), np.int32)
    me.attributes["pa_depth"].data.foreach_get("value", d)
    arrays["depth_toggle"] = d
    R["on"] = {
        "active": me.color_attributes.active_color_name,
        "shading": sorted({sp.shading.color_type for sp in spaces}),
        "legend": [[i.depth, i.faces, list(i.color)] for i in mesh.pa_mesh.depth_legend],
        "views": len(spaces),
    }
    pv.pa_avatar.budget = 20.0  # colours follow the budget (20 %: inside the template level of this cut)
    me.color_attributes["pa_depth_color"].data.foreach_get("color", col)
    arrays["depth_colors_low"] = col.reshape(-1, 4).copy()
    R["on_low_count"] = pv.pa_avatar.count
    pv.pa_avatar.budget = 100.0
    R["toggle_off"] = run_op(bpy.ops.object.progressive_avatars_depth_colors)
    R["off"] = {
        "active": me.color_attributes.active_color_name,
        "shading": sorted({sp.shading.color_type for sp in spaces}),
        "colour_attrs": sorted(a.name for a in me.color_attributes),
    }
    # Level k only
    R["levels"] = {}
    run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["full"])
    pv = preview_of(mesh)
    for k in (0, 1, 2, -1):
        pv.pa_avatar.level_only = k
        R["levels"][str(k)] = [instances(pv), [m.name for m in pv.modifiers]]
    # The mesh deleted under the preview: an error report, no traceback
    bpy.context.view_layer.objects.active = pv
    bpy.data.objects.remove(mesh)
    R["deleted_mesh"] = run_op(bpy.ops.object.progressive_avatars_depth_colors)


@section("topology")
def _():
    res, mesh = import_mesh(ARGS["seq"])
    bpy.context.view_layer.objects.active = mesh
    assert run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["full"]) == ["FINISHED"]
    pv = preview_of(mesh)
    sc.frame_set(sc.frame_start + 1)
    R["topology"] = {"clean": [pv.pa_avatar.status, instances(pv)]}
    setups = {"REMESH": dict(mode="VOXEL", voxel_size=0.01), "SUBSURF": dict(levels=1), "DECIMATE": dict(ratio=0.5)}
    for kind, settings in setups.items():
        mod = mesh.modifiers.new(f"my_{kind.lower()}", kind)
        for k, v in settings.items():
            setattr(mod, k, v)
        bpy.context.view_layer.update()
        sc.frame_set(sc.frame_start)  # a new frame: the handler must refuse, not bind wrongly
        r = {"status": pv.pa_avatar.status, "instances": instances(pv)}
        pv.pa_avatar.bind_mode = "SHAPE_KEYS"
        sc.frame_set(sc.frame_start + 1)
        r["shape_keys"] = [pv.pa_avatar.status, instances(pv)]
        arrays[f"topo_pos_{kind}"] = positions(pv)
        pv.pa_avatar.bind_mode = "EVALUATED"
        print(f"PA_LOAD_WITH {kind}")
        r["load"] = run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["full"])
        pv = preview_of(mesh)
        r["load_status"] = pv.pa_avatar.status
        mesh.modifiers.remove(mesh.modifiers[f"my_{kind.lower()}"])
        bpy.context.view_layer.update()
        sc.frame_set(sc.frame_start + 1)
        r["removed"] = [pv.pa_avatar.status, instances(pv)]
        R["topology"][kind] = r
    # A Subdivision Surface that subdivides nothing in the viewport (render levels only) is fine.
    mod = mesh.modifiers.new("render_only", "SUBSURF")
    mod.levels, mod.render_levels = 0, 2
    bpy.context.view_layer.update()
    sc.frame_set(sc.frame_start)
    R["topology"]["render_only_subsurf"] = [pv.pa_avatar.status, instances(pv)]
    bpy.data.objects.remove(pv)
    bpy.data.objects.remove(mesh)


@section("slips")
def _():
    """What an artist does by accident: delete the mesh or the preview under the other, reload
    over a level filter, forget to pick a file, save with relative paths."""
    rt = sys.modules[PKG + ".blender_addon.runtime"]
    out = {}
    # Triangles Blender cannot hold (a vertex twice; one triangle twice) are refused up front.
    d = dict(np.load(ARGS["seq"]))
    for kind in ("repeated_vertex", "duplicate_face"):
        f = d["faces"].copy()
        if kind == "repeated_vertex":
            f[5] = [f[5][0], f[5][0], f[5][1]]
        else:
            f[9] = np.roll(f[3], 1)
        bad = os.path.join(ARGS["out"], f"{kind}.npz")
        np.savez(bad, vertices=d["vertices"], faces=f)
        before = scene_state()
        res, _ = import_mesh(bad)
        out[kind] = [res, scene_state() == before]
    res, m = import_mesh(ARGS["seq"])
    bpy.context.view_layer.objects.active = m
    out["no_file"] = run_op(bpy.ops.object.progressive_avatars_load, filepath="")
    # The mesh deleted at 25 %, then the slider raised: only placed Gaussians are drawn. (A load
    # places every Gaussian; a frame change those it shows.)
    run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["full"], budget=25.0)
    pv = preview_of(m)
    sc = bpy.context.scene
    sc.frame_set(sc.frame_start + 1 if sc.frame_current == sc.frame_start else sc.frame_start)
    shown = instances(pv)
    bpy.data.objects.remove(m)
    pv.pa_avatar.budget = 100.0
    out["mesh_gone"] = [shown, instances(pv), pv.pa_avatar.count, pv.pa_avatar.status]
    bpy.data.objects.remove(pv)
    # A level filter, then a reload: the old preview's filter group goes with it.
    res, m = import_mesh(ARGS["seq"])
    bpy.context.view_layer.objects.active = m
    run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["full"])
    preview_of(m).pa_avatar.level_only = 1
    run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["full"])
    out["groups_after_reload"] = sorted(g.name for g in bpy.data.node_groups if g.users == 0)
    # Depth colours shown, then the preview deleted: the mesh can still hide them.
    pv = preview_of(m)
    bpy.context.view_layer.objects.active = pv
    run_op(bpy.ops.object.progressive_avatars_depth_colors)
    bpy.data.objects.remove(pv)
    bpy.context.view_layer.objects.active = m
    out["orphan_poll"] = bpy.ops.object.progressive_avatars_depth_colors.poll()
    out["orphan_hide"] = run_op(bpy.ops.object.progressive_avatars_depth_colors)
    out["orphan_after"] = [m.pa_mesh.depth_shown, sorted(a.name for a in m.data.color_attributes)]
    # Decoded avatars of deleted previews are not kept: one load, one entry.
    run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["full"])
    live = {o.session_uid for o in bpy.data.objects if o.pa_avatar.is_preview}
    out["cache"] = [len(live), sorted(rt._cache) == sorted(live)]
    # Relative paths: saved, then loaded into the saved file (Blender warns on a path property
    # that does not take "//").
    print("PA_SAVE_BEGIN")
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(ARGS["out"], "slips.blend"))
    bpy.context.view_layer.objects.active = bpy.data.objects[m.name]
    out["saved_load"] = run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["full"])
    out["stored"] = preview_of(bpy.data.objects[m.name]).pa_avatar.filepath
    print("PA_SAVE_END")
    R["slips"] = out


@section("backdrop")
def _():
    # A stream of backdrop stand-ins (the default training): Render Splats draws the retired
    # ones behind the rest, as the stream's renderer does; a PLY export leaves them out.
    for ob in list(bpy.data.objects):  # a scene of its own: the sequence imported again
        bpy.data.objects.remove(ob)
    _, mesh = import_mesh(ARGS["seq"])
    bpy.context.view_layer.objects.active = mesh
    res = run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["backdrop"], budget=100.0)
    pv = preview_of(mesh)
    sc.frame_set(sc.frame_start + 1)
    bpy.context.preferences.addons[PKG].preferences.python_path = ARGS["python"]  # has numba
    corners = np.array([mesh.matrix_world @ v.co for v in mesh.data.vertices])
    center, radius = corners.mean(0), np.ptp(corners, 0).max()
    camd = bpy.data.cameras.new("bd_cam")
    cam = bpy.data.objects.new("bd_cam", camd)
    sc.collection.objects.link(cam)
    sc.camera = cam
    cam.location = (center[0], center[1] - 2.5 * radius, center[2])
    cam.rotation_euler = (np.pi / 2, 0.0, 0.0)  # looking along +Y at the head
    sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = 64, 80, 100
    sc.render.film_transparent = True
    bpy.context.view_layer.objects.active = pv
    bpy.context.view_layer.update()
    render = run_op(bpy.ops.render.progressive_avatars_splats, wait=True)
    img = bpy.data.images["PA Splats"]
    px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
    img.pixels.foreach_get(px)
    arrays["backdrop_image"] = px.reshape(img.size[1], img.size[0], 4)[::-1]  # rows top-down
    ply_path = os.path.join(ARGS["out"], "backdrop.ply")
    R["backdrop"] = {
        "load": res,
        "render": render,
        "count": pv.pa_avatar.count,
        "instances": instances(pv),
        "preview_matrix": [list(r) for r in pv.matrix_world],
        "camera_matrix": [list(r) for r in cam.matrix_world],
        "lens": camd.lens,
        "sensor": camd.sensor_width,
        "shift": [camd.shift_x, camd.shift_y],
        "size": list(img.size),
        "frame": sc.frame_current - sc.frame_start,
        "ply": run_op(bpy.ops.export_scene.progressive_avatars_ply, filepath=ply_path),
        "ply_path": ply_path,
    }


np.savez(os.path.join(ARGS["out"], "arrays.npz"), **arrays)
print("PA_REPORT " + json.dumps(R, default=str))
