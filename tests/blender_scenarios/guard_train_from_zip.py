"""Blender session run by test_blender_guard.py, appended to guard_prelude.py (which defines ARGS, R, PKG and the helpers)."""

prefs = bpy.context.preferences.addons[PKG].preferences
st = bpy.context.scene.pa_train
sc = bpy.context.scene
R["extension_dir"] = os.path.dirname(sys.modules[PKG].__file__)


@section("train")
def _():
    R["train"] = {}
    prefs.python_path = ARGS["python"]
    prefs.flame_model = ARGS["flame_model"]
    assert not prefs.train_script  # the extension's own trainer, no checkout script
    for kind, (data, mesh_src, kw) in ARGS["train"].items():
        res, mesh = import_mesh(mesh_src, **kw)
        assert res == ["FINISHED"], res
        # The previous avatar's preview is what is active: the result must go to its mesh.
        assert run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["seed_stream"][kind]) == ["FINISHED"]
        bpy.context.view_layer.objects.active = preview_of(mesh)
        st.data_dir, st.out_dir = data, os.path.join(ARGS["out"], "run_" + kind)
        st.preset, st.iterations = "tiny", 6
        t0 = time.perf_counter()
        res = run_op(bpy.ops.progressive_avatars.train)
        pv = preview_of(mesh)
        R["train"][kind] = {
            "result": res,
            "seconds": time.perf_counter() - t0,
            "message": st.message,
            "loaded": bpy.path.abspath(pv.pa_avatar.filepath),
            "total": pv.pa_avatar.total,
            "instances": instances(pv),
            "status": pv.pa_avatar.status,
            "mesh": mesh.name,
            "previews": [o.name for o in bpy.data.objects if o.pa_avatar.is_preview and o.pa_avatar.source == mesh],
        }
    # Train again into the finished mesh run: refused (the run kept) unless Overwrite Run is ticked.
    st.data_dir, st.out_dir = ARGS["train"]["mesh"][0], os.path.join(ARGS["out"], "run_mesh")
    bpy.context.view_layer.objects.active = bpy.data.objects[R["train"]["mesh"]["mesh"]]
    again = {"refused": run_op(bpy.ops.progressive_avatars.train), "message": st.message}
    st.overwrite = True
    again["overwritten"] = run_op(bpy.ops.progressive_avatars.train)
    st.overwrite = False
    R["train_again"] = again


@section("messages")
def _():
    M = R["messages"] = {}
    bad_python = os.path.join(ARGS["out"], "no", "python3")
    prefs.python_path = bad_python
    st.data_dir, st.out_dir = ARGS["out"], os.path.join(ARGS["out"], "never")
    M["bad_python"] = run_op(bpy.ops.progressive_avatars.train)
    not_exec = os.path.join(ARGS["out"], "not_executable_python")
    with open(not_exec, "w") as fh:
        fh.write("#!/bin/sh\n")
    prefs.python_path = not_exec
    M["python_not_executable"] = [run_op(bpy.ops.progressive_avatars.train), st.running]
    prefs.python_path = ARGS["python"]
    # A training already running in this scene (F3 still finds the operator): a live run is the
    # operator module's record (the scene's flag only mirrors it: undo and saved files restore it)
    ops_train = sys.modules[PKG + ".blender_addon.operators_train"]
    st.running = True
    ops_train._RUNS[sc.session_uid] = ops_train._Run(sc.session_uid)
    M["second_training"] = [run_op(bpy.ops.progressive_avatars.train), st.running]
    ops_train._RUNS.pop(sc.session_uid, None)
    st.running = False
    prefs.flame_model = ""
    res, mesh = import_mesh(ARGS["seq"])
    bpy.context.view_layer.objects.active = mesh
    for key in ("foreign_pavs", "foreign_npz", "empty_pavs"):
        M[key] = run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS[key])
    M["flame_no_model"], _ = import_mesh(ARGS["flame_params"])
    M["mesh_npz_folder"], obj = import_mesh(ARGS["npz_folder"], whole_folder=False)
    M["mesh_npz_folder_frames"] = obj.pa_mesh.num_frames if obj is not None else None
    # Frame range and fps: optional, and kept when not asked for.
    sc.frame_start, sc.frame_end, sc.render.fps = 7, 9, 24
    res, obj = import_mesh(ARGS["seq"], set_frame_range=False)
    M["range_kept"] = [res, sc.frame_start, sc.frame_end, sc.render.fps]
    res, obj = import_mesh(ARGS["seq"], fps=30)
    M["range_set"] = [res, sc.frame_start, sc.frame_end, sc.render.fps, obj.pa_mesh.num_frames]
    # OBJ and PLY sequences (trimesh is blocked here)
    for key in ("obj_folder", "ply_folder"):
        res, obj = import_mesh(ARGS[key], whole_folder=True)
        n = len(obj.data.vertices)
        M[key] = [res, obj.pa_mesh.num_frames, n, len(obj.data.polygons)]
        sc.frame_set(sc.frame_start + 2)
        dg = bpy.context.evaluated_depsgraph_get()
        me = obj.evaluated_get(dg).data
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
        arrays[key] = co.reshape(-1, 3)
    # Avatar paths: absolute in an unsaved file, relative ("//") once saved; a moved project
    # (the .blend and the avatar moved together) still finds its avatar.
    import shutil

    res, mesh = import_mesh(ARGS["seq"])
    bpy.context.view_layer.objects.active = mesh
    M["load_unsaved"] = run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["stream"])
    pv_name = preview_of(mesh).name
    M["path_unsaved"] = bpy.data.objects[pv_name].pa_avatar.filepath
    os.makedirs(os.path.join(ARGS["out"], "proj"), exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(ARGS["out"], "proj", "scene.blend"))
    M["path_saved"] = bpy.data.objects[pv_name].pa_avatar.filepath
    moved = os.path.join(ARGS["out"], "moved")
    os.makedirs(os.path.join(moved, "proj"))
    shutil.copy(os.path.join(ARGS["out"], "proj", "scene.blend"), os.path.join(moved, "proj", "scene.blend"))
    shutil.copy(ARGS["stream"], os.path.join(moved, os.path.basename(ARGS["stream"])))
    bpy.ops.wm.open_mainfile(filepath=os.path.join(moved, "proj", "scene.blend"))
    pv = bpy.data.objects[pv_name]
    pv.pa_avatar.budget = 50.0
    M["moved"] = [bpy.path.abspath(pv.pa_avatar.filepath), pv.pa_avatar.count, pv.pa_avatar.status]
    mesh = pv.pa_avatar.source
    bpy.context.view_layer.objects.active = mesh
    M["load_rel"] = run_op(bpy.ops.object.progressive_avatars_load, filepath=ARGS["stream"])
    pv = preview_of(mesh)
    M["stored_path"] = pv.pa_avatar.filepath
    pv.pa_avatar.budget = 0.0
    bpy.context.view_layer.objects.active = pv
    M["export_zero"] = run_op(bpy.ops.export_scene.progressive_avatars_ply, filepath=os.path.join(ARGS["out"], "z.ply"))
    scene = bpy.context.scene  # the reopened file's
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    addon_prefs = bpy.context.preferences.addons[PKG].preferences
    addon_prefs.python_path = bad_python
    M["bad_python_render"] = run_op(bpy.ops.render.progressive_avatars_splats)
    addon_prefs.python_path = ARGS["python"]
    pv.pa_avatar.budget = 50.0  # PLY export with plyfile blocked
    M["export_half"] = [
        run_op(bpy.ops.export_scene.progressive_avatars_ply, filepath=os.path.join(ARGS["out"], "h.ply")),
        pv.pa_avatar.count,
    ]
    M["tab"] = bpy.types.PA_PT_main.bl_category


np.savez(os.path.join(ARGS["out"], "arrays.npz"), **arrays)
print("PA_REPORT " + json.dumps(R, default=str))
