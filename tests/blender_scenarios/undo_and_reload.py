"""Blender session run by test_blender_undo.py (a real file so it can be read, linted and run by hand).

What undo, redo and a file load take back, and what they must not: a training in progress
(its trainer and its panel state), the 3D views' colour mode under depth colours; the splats'
focal length (set with the preview and before each render); imports from Edit Mode or of a
file with no faces; the depth filter in the depth legend's terms. Each step records what it
saw; a step that raises records its traceback and the next one still runs. File loads last.
"""

import importlib, json, os, queue, shutil, subprocess, sys, time, traceback, types

import stock_blender

root, out, blocked = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
stock_blender.block(blocked)
import bpy
import numpy as np

PKG = "pa_undo"
stock_blender.load_extension(root, PKG)
prefs = importlib.import_module(PKG + ".blender_addon.prefs")
splat_look = importlib.import_module(PKG + ".blender_addon.splat_look")
sequence_builder = importlib.import_module(PKG + ".blender_addon.sequence")
transforms = importlib.import_module(PKG + ".core.bridge.transforms")
splats = importlib.import_module(PKG + ".core.bridge.splats")
runtime = importlib.import_module(PKG + ".blender_addon.runtime")
preview = importlib.import_module(PKG + ".blender_addon.preview")
reader = importlib.import_module(PKG + ".core.stream.reader")
ops_train = importlib.import_module(PKG + ".blender_addon.operators_train")
ops_avatar = importlib.import_module(PKG + ".blender_addon.operators_avatar")
panels = importlib.import_module(PKG + ".blender_addon.panels")
core_depth = importlib.import_module(PKG + ".core.bridge.depth")
PA_OT_train = ops_train.PA_OT_train

SEQ, STREAM = os.path.join(out, "seq.npz"), os.path.join(out, "avatar.pavs")
COARSE_SEQ, COARSE = os.path.join(out, "coarse_seq.npz"), os.path.join(out, "coarse.pavs")
SPLATS = os.path.join(out, "splats.ply")
KINDS = ("objects", "meshes", "shape_keys", "actions", "materials", "node_groups")
R = {}


def inventory():
    return {k: sorted(x.name for x in getattr(bpy.data, k)) for k in KINDS}


call = stock_blender.call


def views():
    return sorted(
        {sp.shading.color_type for s in bpy.data.screens for a in s.areas for sp in a.spaces if sp.type == "VIEW_3D"}
    )


def set_views(color_type):
    for s in bpy.data.screens:
        for a in s.areas:
            for sp in a.spaces:
                if sp.type == "VIEW_3D":
                    sp.shading.color_type = color_type


step = stock_blender.stepper(R)
activate = stock_blender.activate


def preview_of(mesh):
    return next(c for c in mesh.children if c.pa_avatar.is_preview)


def head_with_preview(r, stream=STREAM, budget=100.0):
    """The sequence imported (onto the active object's place) and ``stream`` loaded onto it at
    ``budget``: (mesh, preview); the operators' results in r["import"], r["load"]."""
    r["import"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=SEQ)
    mesh = bpy.context.active_object
    r["load"] = call(bpy.ops.object.progressive_avatars_load, filepath=stream, budget=budget)
    return mesh, preview_of(mesh)


def shown_count(pv):
    """The Gaussians the preview's modifier shows (its Count input)."""
    mod = pv.modifiers[preview.MODIFIER_NAME]
    return mod[preview.input_identifier(mod.node_group, "Count")]


def misplaced(pv, mesh=None):
    """Largest distance of a point the preview shows from a fresh evaluation of this frame on
    ``mesh`` (default its bound mesh), in the mesh's space."""
    e = runtime.entry(pv)
    fresh = splats.splat_evaluator(e.avatar, None, None, e.order)
    want = fresh(runtime.source_vertices(mesh or pv.pa_avatar.source, bpy.context.evaluated_depsgraph_get())).means
    me = pv.data
    pos = np.empty(len(me.vertices) * 3, np.float32)
    me.attributes["position"].data.foreach_get("vector", pos)
    rank = np.empty(len(me.vertices), np.int32)
    me.attributes["rank"].data.foreach_get("value", rank)
    shown = rank < shown_count(pv)
    return float(np.abs(pos.reshape(-1, 3)[shown] - want[shown]).max(initial=0.0))


class Layout:
    """What a panel's draw() puts in its layout: label texts, operator buttons as [text]."""

    def __init__(self):
        self.log = []

    def row(self, **_kw):
        return self

    def label(self, text="", **_kw):
        self.log.append(text)

    def operator(self, _idname, text="", **_kw):
        self.log.append(f"[{text}]")
        return types.SimpleNamespace()

    def prop(self, *_args, **_kw):
        pass


def depth_panel():
    lay = Layout()
    panels.PA_PT_depth.draw(types.SimpleNamespace(layout=lay), bpy.context)
    return lay.log


class ModalTrain:
    """PA_OT_train's modal path on a stand-in (timers never fire headless, so the test calls
    modal() as the window manager would on each tick)."""

    def __init__(self, script, scene):
        self._cmds, self._env = [[sys.executable, os.path.join(out, script)]], None
        self._out = os.path.join(out, "modal_run")
        self._lines, self._timer, self.reports, self.removed_timers = queue.Queue(), "timer", [], []
        self._scene = scene  # what the old code kept (a Scene reference)
        if hasattr(self, "_begin"):
            self._begin(scene)  # what invoke() does
        else:
            scene.pa_train.running = True
        self._next_process()

    def report(self, kind, message):
        self.reports.append((sorted(kind)[0], message))

    def tick(self):
        wm = types.SimpleNamespace(event_timer_remove=self.removed_timers.append)
        ctx = types.SimpleNamespace(scene=bpy.context.scene, screen=None, window_manager=wm)
        return sorted(self.modal(ctx, types.SimpleNamespace(type="TIMER")))

    def end(self):
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()


for _name in ("modal", "_tick", "_drain", "_kill", "_stop", "_next_process", "_begin"):
    if _name in PA_OT_train.__dict__:  # (the old code had fewer)
        setattr(ModalTrain, _name, PA_OT_train.__dict__[_name])
ModalTrain._pump, ModalTrain._progress = staticmethod(PA_OT_train._pump), staticmethod(PA_OT_train._progress)


def wait_progress(op, scene_name, least, timeout=10.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if op.tick() != ["PASS_THROUGH"]:
            return False
        if bpy.data.scenes[scene_name].pa_train.progress >= least:
            return True
        time.sleep(0.05)
    return False


for ob in list(bpy.data.objects):
    if ob.type != "CAMERA":
        bpy.data.objects.remove(ob)
bpy.ops.mesh.primitive_cube_add()
CUBE = bpy.context.active_object.name
SCENE = bpy.context.scene.name
prefs.python_path = lambda context=None: sys.executable
st = bpy.context.scene.pa_train
st.data_dir, st.out_dir = out, os.path.join(out, "run")


@step
def train_survives_undo(r):
    bpy.ops.ed.undo_push(message="before training")
    op = ModalTrain("long_train.py", bpy.context.scene)
    try:
        r["started"] = wait_progress(op, SCENE, 2.0)
        r["progress_before"] = bpy.data.scenes[SCENE].pa_train.progress
        bpy.data.objects[CUBE].location.x += 1.0  # the user edits something meanwhile...
        bpy.ops.ed.undo_push(message="move cube")
        bpy.ops.ed.undo()  # ...and undoes that edit (the scene's properties go back too)
        sc = bpy.data.scenes[SCENE]
        r["running_after_undo"] = sc.pa_train.running
        r["progress_after_undo"] = sc.pa_train.progress
        r["ticks_after_undo"] = [op.tick() for _ in range(3)]
        r["alive_after_undo"] = op._proc.poll() is None
        r["reports_after_undo"] = list(op.reports)
        r["progress_later"] = bpy.data.scenes[SCENE].pa_train.progress
        bpy.ops.ed.undo_push(message="training goes on")
        bpy.ops.ed.undo()  # a second undo, back to before the training started
        r["running_after_second_undo"] = bpy.data.scenes[SCENE].pa_train.running
        r["second_undo_tick"] = op.tick()
        r["alive_after_second_undo"] = op._proc.poll() is None
        # Train again in this scene: refused, one trainer at a time
        prefs.user_train_script = lambda context=None: os.path.join(out, "long_train.py")
        r["train_again"] = call(bpy.ops.progressive_avatars.train)
        r["cancel"] = call(bpy.ops.progressive_avatars.train_cancel)
        r["cancel_tick"] = op.tick()
        r["reports"] = op.reports
        time.sleep(0.2)
        r["exit_after_cancel"] = op._proc.poll()
        r["running_after_cancel"] = bpy.data.scenes[SCENE].pa_train.running
        r["timers"] = op.removed_timers
    finally:
        op.end()


MESH = None


@step
def depth_colours_undo(r):
    global MESH
    set_views("MATERIAL")  # the user's choice
    r["import"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=SEQ)
    MESH = bpy.context.active_object.name
    r["load"] = call(bpy.ops.object.progressive_avatars_load, filepath=STREAM)
    activate(preview_of(bpy.data.objects[MESH]))
    bpy.ops.ed.undo_push(message="loaded")
    r["show"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    r["views_shown"] = views()
    bpy.ops.ed.undo_push(message="colour by depth")
    bpy.ops.ed.undo()
    mesh = bpy.data.objects[MESH]
    r["shown_after_undo"] = mesh.pa_mesh.depth_shown
    r["views_after_undo"] = views()
    bpy.ops.ed.redo()
    mesh = bpy.data.objects[MESH]
    r["shown_after_redo"] = mesh.pa_mesh.depth_shown
    r["views_after_redo"] = views()
    activate(preview_of(mesh))
    r["hide"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    r["views_after_hide"] = views()


def camera_focal(scene):
    _, settings = splat_look.scene_camera(scene)
    fx, fy, _, _ = transforms.blender_intrinsics(**settings)
    return float(np.sqrt(fx * fy))


def focal_values():
    mat = bpy.data.materials[splat_look.MATERIAL_NAME]
    group = bpy.data.node_groups["PA Splats"] if "PA Splats" in bpy.data.node_groups else None
    vals = [mat.node_tree.nodes[splat_look.FOCAL_NODE].outputs[0].default_value]
    if group is not None and splat_look.FOCAL_NODE in group.nodes:
        vals.append(group.nodes[splat_look.FOCAL_NODE].outputs[0].default_value)
    return vals


@step
def splat_focal(r):
    # The avatar was loaded (previous step) without Splat Render Settings ever running.
    scene = bpy.context.scene
    r["camera_focal"] = camera_focal(scene)
    r["after_load"] = focal_values()
    scene.render.resolution_percentage = 50  # the render's size changes after the load
    r["camera_focal_half"] = camera_focal(scene)
    ours = [h for h in bpy.app.handlers.render_pre if h.__module__.startswith(PKG)]
    for handler in ours:  # what Blender runs before rendering each frame
        handler(scene, None)
    r["render_pre_handlers"] = len(ours)
    r["after_render_pre"] = focal_values()
    scene.render.resolution_percentage = 100
    cam = scene.camera
    scene.camera = None
    warning = getattr(splat_look, "focal_warning", None)
    r["warning_no_camera"] = warning(scene) if warning else "(no focal_warning)"
    r["warning_with_camera"] = "x"
    scene.camera = cam
    r["warning_with_camera"] = warning(scene) if warning else "(no focal_warning)"


@step
def depth_only_in_legend_terms(r):
    activate(bpy.data.objects[MESH])
    r["import"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=COARSE_SEQ)
    mesh = bpy.context.active_object
    r["load"] = call(bpy.ops.object.progressive_avatars_load, filepath=COARSE)
    pv = preview_of(mesh)
    forest = reader.read_stream(COARSE).forest
    k = int(forest.num_coarse_levels)
    r["coarse_levels"] = k
    r["legend"] = [[i.depth, i.faces] for i in mesh.pa_mesh.depth_legend]
    levels = np.empty(len(pv.data.vertices), np.int32)
    pv.data.attributes["level"].data.foreach_get("value", levels)

    def shown():
        ev = pv.evaluated_get(bpy.context.evaluated_depsgraph_get())
        geo = ev.evaluated_geometry()  # (held: the point cloud is its)
        ip = geo.instances_pointcloud()
        return len(ip.points) if ip is not None else 0

    r["all"], r["total"] = shown(), len(levels)
    r["by_depth"] = []
    for d in (0, 1, forest.max_depth, -1, -k):
        pv.pa_avatar.depth_only = d  # in the legend's terms: depth below the template
        r["by_depth"].append([d, shown(), int((levels - k == d).sum()), pv.pa_avatar.depth_only])
    r["on"] = pv.pa_avatar.depth_only_on
    r["level_only"] = pv.pa_avatar.level_only  # stored: the absolute level, as files had it
    pv.pa_avatar.depth_only_on = False
    r["off_shown"], r["off_level_only"] = shown(), pv.pa_avatar.level_only
    # A file saved before: level_only absolute, no coarse_levels stored
    pv.pa_avatar.coarse_levels = -1
    pv.pa_avatar.level_only = k + 1
    r["old_file_depth"] = pv.pa_avatar.depth_only
    pv.pa_avatar.depth_only_on = False


@step
def budget_steps_keep_placed_points(r):
    """The budget slider at a frame whose points are placed binds none of them again (each step
    wrote the mesh's depth attribute; the mesh's re-evaluation called the frame handler, which
    bound and wrote every shown Gaussian again: 0.2-0.4 s a step at the paper's scale). Raised
    past them, after a frame change and after an undo, every shown point sits where a fresh
    evaluation of that frame puts it."""
    binding = importlib.import_module(PKG + ".core.avatar.binding")
    activate(bpy.data.objects[MESH])
    mesh, pv = head_with_preview(r)
    name = mesh.name
    scene = bpy.context.scene
    dg = bpy.context.evaluated_depsgraph_get
    r["total"] = pv.pa_avatar.total

    calls = []  # the Gaussians each evaluation of this preview's evaluators placed (other previews': not)
    real = binding.GaussianEvaluator.__call__
    uid = pv.session_uid

    def counted(ev, verts):
        e = runtime._cache.get(uid)
        if e is not None and (ev is e.evaluator or ev is getattr(e, "full", None)):
            calls.append(ev.n)
        return real(ev, verts)

    binding.GaussianEvaluator.__call__ = counted
    depth = []

    def step_to(budget):
        pv.pa_avatar.budget = budget
        dg()
        a = np.empty(len(mesh.data.polygons), np.int32)
        mesh.data.attributes["pa_depth"].data.foreach_get("value", a)
        depth.append(a.tolist())

    try:
        dg()
        calls.clear()
        for b in (90.0, 70.0, 40.0, 10.0):  # down: every point it shows is placed already
            step_to(b)
        r["down"] = list(calls)
        r["depth_changes"] = sum(a != b for a, b in zip(depth, depth[1:]))
        r["count_10"] = pv.pa_avatar.count
        scene.frame_set(scene.frame_current + 1)  # places the 10 % it shows
        dg()
        calls.clear()
        for b in (30.0, 60.0, 100.0):  # up past them: the first step places every Gaussian
            step_to(b)
        r["up"] = list(calls)
        r["misplaced_up"] = misplaced(pv, mesh)
        step_to(50.0)
        r["count_50"] = pv.pa_avatar.count
        calls.clear()
        scene.frame_set(scene.frame_current + 2)
        dg()
        r["frame"], r["frame_at"] = list(calls), scene.frame_current
        r["misplaced_frame"] = misplaced(pv, mesh)
        bpy.ops.ed.undo_push(message="frame +2")
        step_to(20.0)
        bpy.ops.ed.undo_push(message="budget 20")
        scene.frame_set(scene.frame_current + 3)
        bpy.ops.ed.undo_push(message="frame +3")
        bpy.ops.ed.undo()
        bpy.ops.ed.undo()  # budget 50 at frame +2, the points as that step saved them
        mesh, scene = bpy.data.objects[name], bpy.context.scene
        pv = preview_of(mesh)
        dg()
        r["after_undo"] = [pv.pa_avatar.budget, scene.frame_current]
        r["misplaced_undo"] = misplaced(pv, mesh)
    finally:
        binding.GaussianEvaluator.__call__ = real


@step
def unplaced_points_stay_hidden(r):
    """Points the preview has not placed are never shown: raised in Edit Mode (nothing can be
    written) the budget shows only the points the last frame placed, all of them once it is left;
    a bound mesh with one vertex fewer than the avatar's template hides every point and says so."""
    import bmesh

    runtime = importlib.import_module(PKG + ".blender_addon.runtime")
    preview = importlib.import_module(PKG + ".blender_addon.preview")
    activate(bpy.data.objects[CUBE])
    mesh, pv = head_with_preview(r)
    scene = bpy.context.scene
    mod = pv.modifiers[preview.MODIFIER_NAME]
    key = preview.input_identifier(mod.node_group, "Count")
    pv.pa_avatar.budget = 20.0
    scene.frame_set(scene.frame_current + 1)  # places the 20 % it shows
    bpy.context.evaluated_depsgraph_get()
    r["count_20"], r["shown_20"] = pv.pa_avatar.count, mod[key]
    activate(pv, "EDIT")
    pv.pa_avatar.budget = 90.0
    r["count_90"], r["shown_edit"], r["status_edit"] = pv.pa_avatar.count, mod[key], pv.pa_avatar.status
    activate(pv)
    bpy.context.evaluated_depsgraph_get()
    r["shown_after"] = mod[key]
    # One vertex fewer than the template: 'Shape keys only' reads the mesh's own vertices.
    mesh.shape_key_clear()
    pv.pa_avatar.bind_mode = "SHAPE_KEYS"
    r["vertices"] = len(mesh.data.vertices)
    bm = bmesh.new()
    bm.from_mesh(mesh.data)
    bm.verts.ensure_lookup_table()
    bm.verts.remove(bm.verts[-1])
    bm.to_mesh(mesh.data)
    bm.free()
    mesh.data.update()
    r["refresh_short"] = runtime.refresh(pv, bpy.context.evaluated_depsgraph_get())
    r["status_short"], r["shown_short"] = pv.pa_avatar.status, mod[key]
    bpy.data.objects.remove(pv)
    bpy.data.objects.remove(mesh)


@step
def shape_keys_mixed_as_blender_mixes_them(r):
    """'Shape keys only' mixes the mesh's relative keys as Blender does: each key's offset from
    its own relative key (not always the basis) times its evaluated value, muted and zero keys
    left out. Blender's evaluated mesh (no modifiers) is the reference, and so is that sum by
    hand; keys limited to a vertex group and absolute keys are refused with their reason."""
    runtime = importlib.import_module(PKG + ".blender_addon.runtime")
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2)
    obj = bpy.context.active_object
    n = len(obj.data.vertices)
    rng = np.random.default_rng(4)
    basis = obj.shape_key_add(name="Basis", from_mix=False)
    co = {"Basis": np.empty(n * 3, np.float32)}
    basis.data.foreach_get("co", co["Basis"])
    keys = {}
    for name, value, rel in (("a", 0.5, "Basis"), ("b", 0.25, "a"), ("muted", 0.7, "Basis"), ("off", 0.0, "Basis")):
        kb = keys[name] = obj.shape_key_add(name=name, from_mix=False)
        co[name] = co["Basis"] + rng.normal(0, 0.05, n * 3).astype(np.float32)
        kb.data.foreach_set("co", co[name])
        kb.value, kb.relative_key = value, obj.data.shape_keys.key_blocks[rel]
    keys["muted"].mute = True
    dg = bpy.context.evaluated_depsgraph_get()
    got, problem = runtime.shape_key_vertices(obj, dg)
    want = runtime.source_vertices(obj, dg)  # Blender's own mix
    by_hand = (co["Basis"] + 0.5 * (co["a"] - co["Basis"]) + 0.25 * (co["b"] - co["a"])).reshape(-1, 3)
    r["problem"] = problem
    r["vs_blender"] = float(np.abs(got - want).max())
    r["vs_hand"] = float(np.abs(got - by_hand).max())
    r["hand_vs_blender"] = float(np.abs(by_hand - want).max())
    r["basis_vs_blender"] = float(np.abs(co["Basis"].reshape(-1, 3) - want).max())

    def refused():  # [no vertices returned, the reason]
        verts, why = runtime.shape_key_vertices(obj, bpy.context.evaluated_depsgraph_get())
        return [verts is None, why]

    obj.vertex_groups.new(name="half")
    keys["a"].vertex_group = "half"
    r["vertex_group"] = refused()
    keys["a"].vertex_group = ""
    obj.data.shape_keys.use_relative = False
    r["absolute"] = refused()
    bpy.data.objects.remove(obj)


@step
def import_from_edit_mode(r):
    cube = bpy.data.objects[CUBE]
    activate(cube, "EDIT")
    r["result"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=SEQ)
    r["not_in_object_mode"] = [o.name for o in bpy.data.objects if o.mode != "OBJECT"]
    r["active"] = bpy.context.active_object.name
    # A build that fails late: the scene as it was, the cube back in Edit Mode
    activate(cube, "EDIT")
    before = inventory()

    def boom(*args, **kw):
        raise RuntimeError("injected failure")

    kept = sequence_builder.add_sequence_keys
    sequence_builder.add_sequence_keys = boom
    try:
        r["failed"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=SEQ)
    finally:
        sequence_builder.add_sequence_keys = kept
    r["failed_added"] = {k: v for k, v in inventory().items() if v != before[k]}
    r["failed_mode"] = bpy.context.mode
    r["failed_active"] = bpy.context.active_object.name


@step
def splat_ply_as_sequence(r):
    before = inventory()
    r["result"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=SPLATS)
    r["added"] = {k: v for k, v in inventory().items() if v != before[k]}


@step
def depth_panel_of_ply_splats(r):
    """A PLY splat object has no mesh to colour: the depth panel says so (it said the preview's
    mesh was deleted)."""
    before = set(bpy.data.objects)
    r["result"] = call(bpy.ops.import_scene.progressive_avatars_splat_ply, filepath=SPLATS)
    (splats,) = set(bpy.data.objects) - before
    activate(splats)
    r["panel"] = depth_panel()
    bpy.data.objects.remove(splats)


@step
def linked_duplicates_show_their_own_points(r):
    """Alt+D of a preview shares its mesh: at another budget, or with the head it was duplicated
    with deformed otherwise (its own modifier), each preview shows its own Gaussians on its own
    mesh at this frame; and again after undo takes the duplicates back to sharing."""
    activate(bpy.data.objects[CUBE])
    mesh, pv = head_with_preview(r)
    scene = bpy.context.scene
    activate(pv)
    bpy.ops.object.duplicate(linked=True)
    dup = bpy.context.active_object
    r["shared"] = dup.data == pv.data
    activate(mesh)
    pv.select_set(True)
    bpy.ops.object.duplicate(linked=True)  # the head and its preview
    head2 = bpy.context.active_object
    pv2 = preview_of(head2)
    head2.modifiers.new("Displace", "DISPLACE").strength = 0.05
    names = [o.name for o in (pv, dup, pv2)]
    heads = [head2.name, mesh.name]
    bpy.ops.ed.undo_push(message="linked duplicates")
    dup.pa_avatar.budget = 20.0
    scene.frame_set(scene.frame_current + 1)

    def check():
        objs = [bpy.data.objects[n] for n in names]
        return [misplaced(o) for o in objs] + [len({o.data.name for o in objs})]

    r["after_frame"] = check()
    bpy.ops.ed.undo_push(message="frame")
    bpy.ops.ed.undo()
    scene = bpy.context.scene
    scene.frame_set(scene.frame_current + 1)
    r["after_undo"] = check()
    for name in names + heads:
        bpy.data.objects.remove(bpy.data.objects[name])


@step
def deleted_mesh_said_on_frame_change(r):
    """The bound mesh removed under its preview (Outliner > Delete): a frame change says so
    (the frame handler skipped the preview, silent until the budget moved) and shows only the
    points placed before; undo brings the mesh back and the points follow it again."""
    activate(bpy.data.objects[CUBE])
    mesh, pv = head_with_preview(r)
    names = [pv.name, mesh.name]
    bpy.ops.ed.undo_push(message="loaded")
    bpy.data.objects.remove(mesh)
    bpy.ops.ed.undo_push(message="mesh removed")
    scene = bpy.context.scene
    scene.frame_set(scene.frame_current + 1)
    r["removed"] = [pv.pa_avatar.status, shown_count(pv), pv.pa_avatar.count]
    bpy.ops.ed.undo()
    pv, scene = bpy.data.objects[names[0]], bpy.context.scene
    scene.frame_set(scene.frame_current + 1)
    r["undone"] = [pv.pa_avatar.status, pv.pa_avatar.source.name == names[1], misplaced(pv)]
    # Delete in the 3D View (X) unlinks the mesh from its collections only: the preview's
    # pointer to it (a user) keeps it in the file's data, shown and evaluated by no scene.
    bpy.ops.ed.undo_push(message="frame")
    activate(bpy.data.objects[names[1]])
    r["delete"] = call(bpy.ops.object.delete)
    bpy.ops.ed.undo_push(message="mesh deleted")
    scene.frame_set(scene.frame_current + 1)
    activate(pv)
    r["deleted"] = [
        names[1] in bpy.data.objects,
        pv.pa_avatar.status,
        shown_count(pv),
        pv.pa_avatar.count,
        depth_panel(),
        call(bpy.ops.object.progressive_avatars_depth_colors),
    ]
    bpy.ops.ed.undo()
    pv, scene = bpy.data.objects[names[0]], bpy.context.scene
    scene.frame_set(scene.frame_current + 1)
    r["delete_undone"] = [pv.pa_avatar.status, misplaced(pv)]
    for name in names:
        bpy.data.objects.remove(bpy.data.objects[name])


@step
def depth_written_after_edit_mode(r):
    """The budget moved while the mesh is in Edit Mode: its depth cannot be written then (the
    status says so); once it leaves Edit Mode the depth and legend are the budget's, not the
    previous one's under a status gone empty."""
    activate(bpy.data.objects[CUBE])
    mesh, pv = head_with_preview(r)
    activate(mesh, "EDIT")
    pv.pa_avatar.budget = 20.0
    r["in_edit"] = pv.pa_avatar.status
    activate(mesh)
    bpy.context.evaluated_depsgraph_get()  # the depsgraph handler
    want = core_depth.depth_per_face(reader.read_stream(STREAM).forest, len(mesh.data.polygons), pv.pa_avatar.count)
    got = np.empty(len(mesh.data.polygons), np.int32)
    mesh.data.attributes["pa_depth"].data.foreach_get("value", got)
    d, n = np.unique(want, return_counts=True)
    legend = {i.depth: i.faces for i in mesh.pa_mesh.depth_legend if i.faces}
    r["after"] = [pv.pa_avatar.status, bool(np.array_equal(got, want)), legend == dict(zip(d.tolist(), n.tolist()))]
    r["counts"] = [pv.pa_avatar.count, pv.pa_avatar.total]
    for ob in (pv, mesh):
        bpy.data.objects.remove(ob)


@step
def apply_transform_on_the_mesh(r):
    """Apply Rotation & Scale on the bound mesh leaves the preview its old transform (Blender
    keeps children in place), drawing the Gaussians, placed in the mesh's new space, away from
    it: the status says so, and no longer once undone or once the preview's transform is
    cleared; a preview parented to something else says so too."""
    activate(bpy.data.objects[CUBE])
    r["import"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=SEQ)
    mesh = bpy.context.active_object
    mesh.scale = (2.0, 2.0, 2.0)
    r["load"] = call(bpy.ops.object.progressive_avatars_load, filepath=STREAM, budget=100.0)
    names = [preview_of(mesh).name, mesh.name]
    bpy.ops.ed.undo_push(message="loaded")
    r["apply"] = call(bpy.ops.object.transform_apply, location=False, rotation=True, scale=True)
    bpy.ops.ed.undo_push(message="applied")

    def state():
        scene = bpy.context.scene
        scene.frame_set(scene.frame_current + 1)
        pv, mesh = (bpy.data.objects[n] for n in names)
        apart = not np.allclose(np.array(pv.matrix_world), np.array(mesh.matrix_world), atol=1e-6)
        return [pv.pa_avatar.status, apart, misplaced(pv)]

    r["applied"] = state()
    bpy.ops.ed.undo()
    r["undone"] = state()
    bpy.ops.ed.redo()
    pv = bpy.data.objects[names[0]]
    pv.matrix_basis.identity()  # Object > Clear > All
    r["cleared"] = state()
    elsewhere = bpy.data.objects.new("Elsewhere", None)
    elsewhere.location.z = 1.0
    bpy.context.scene.collection.objects.link(elsewhere)
    pv.parent = elsewhere
    bpy.context.evaluated_depsgraph_get()  # no frame change: the depsgraph handler says it
    r["other_parent_at_once"] = pv.pa_avatar.status
    r["other_parent"] = state()
    # Load Avatar on the mesh replaces its preview, parented to it or not (Clear Parent left it bound
    # and drawing: a second preview was added beside it).
    mesh = bpy.data.objects[names[1]]
    activate(mesh)
    r["reload"] = call(bpy.ops.object.progressive_avatars_load, filepath=STREAM, budget=100.0)
    bound = [o.name for o in bpy.data.objects if o.pa_avatar.is_preview and o.pa_avatar.source == mesh]
    r["bound_after_reload"] = [bound, [c.name for c in mesh.children]]
    for name in bound + [names[1], elsewhere.name]:
        bpy.data.objects.remove(bpy.data.objects[name])


@step
def preview_unparented_from_its_head(r):
    """Clear Parent (Keep Transform) leaves a preview bound to its head and drawing, no longer
    its child: with the head selected the panel and operators still find the preview, and
    moving or rotating the head alone (or through its own parent) says at once, no frame
    change, that the Gaussians are drawn away from it, and no longer once it is back."""
    activate(bpy.data.objects[CUBE])
    mesh, pv = head_with_preview(r)
    activate(pv)
    r["clear"] = call(bpy.ops.object.parent_clear, type="CLEAR_KEEP_TRANSFORM")
    activate(mesh)
    found = ops_avatar.preview_of(bpy.context)
    r["found"] = [pv.parent is None, pv.name, found.name if found is not None else None]
    r["polls"] = [
        panels.PA_PT_avatar.poll(bpy.context),
        panels.PA_PT_depth.poll(bpy.context),
        bpy.ops.object.progressive_avatars_depth_colors.poll(),
        bpy.ops.export_scene.progressive_avatars_ply.poll(),
    ]
    carrier = bpy.data.objects.new("Carrier", None)
    bpy.context.scene.collection.objects.link(carrier)

    def moved(how):  # [status, drawn away from the head by their world matrices]
        how()
        bpy.context.evaluated_depsgraph_get()  # the depsgraph handler, no frame change
        apart = not np.allclose(np.array(pv.matrix_world), np.array(mesh.matrix_world), atol=1e-6)
        return [pv.pa_avatar.status, apart]

    r["moves"] = [
        moved(lambda: setattr(mesh.location, "x", 0.05)),
        moved(lambda: setattr(mesh.location, "x", 0.0)),
        moved(lambda: setattr(mesh.rotation_euler, "z", 0.3)),
        moved(lambda: setattr(mesh.rotation_euler, "z", 0.0)),
        moved(lambda: setattr(mesh, "parent", carrier)),  # the carrier at the origin: nothing moves
        moved(lambda: setattr(carrier.location, "z", 0.1)),
        moved(lambda: setattr(carrier.location, "z", 0.0)),
    ]
    runtime.forget()  # as after a file load: no decoded avatar until a frame or budget change
    r["moves_uncached"] = [
        moved(lambda: setattr(mesh.location, "x", 0.05)),
        moved(lambda: setattr(mesh.location, "x", 0.0)),
    ]
    for ob in (pv, mesh, carrier):
        bpy.data.objects.remove(ob)


@step
def two_previews_on_one_head(r):
    """Two previews bound to one head (Alt+D) at two budgets: the head's one set of depth
    faces, legend and colours stays the depth of one preview, the one Load Avatar made or
    Colour by Depth last chose, whatever the other's budget does; the panel names it when
    the other is selected, Colour by Depth there shows the other's depth instead of hiding;
    with the chosen one deleted, the next budget moved takes the depth over."""
    activate(bpy.data.objects[CUBE])
    mesh, pv = head_with_preview(r)
    activate(pv)
    bpy.ops.object.duplicate(linked=True)
    dup = bpy.context.active_object
    forest = reader.read_stream(STREAM).forest
    r["names"] = [pv.name, dup.name]

    def head():  # [depth is pv's, depth is dup's, legend matches pv's, dup's, depth_preview, shown]
        me = mesh.data
        got = np.empty(len(me.polygons), np.int32)
        me.attributes["pa_depth"].data.foreach_get("value", got)
        legend = {i.depth: i.faces for i in mesh.pa_mesh.depth_legend if i.faces}
        out = []
        for o in (pv, dup):
            want = core_depth.depth_per_face(forest, len(me.polygons), o.pa_avatar.count) if o else None
            out.append(o is not None and np.array_equal(got, want))
        for o in (pv, dup):
            want = core_depth.depth_per_face(forest, len(me.polygons), o.pa_avatar.count) if o else None
            d, n = np.unique(want, return_counts=True) if o else ([], [])
            out.append(o is not None and legend == dict(zip(d.tolist(), n.tolist())))
        return out + [getattr(mesh.pa_mesh, "depth_preview", None), mesh.pa_mesh.depth_shown]

    dup.pa_avatar.budget = 20.0
    r["counts"] = [pv.pa_avatar.count, dup.pa_avatar.count]
    r["depths_differ"] = not np.array_equal(
        *(core_depth.depth_per_face(forest, len(mesh.data.polygons), n) for n in r["counts"])
    )
    r["dup_moved"] = head()
    activate(mesh)
    r["head_panel"] = ops_avatar.preview_of(bpy.context).name
    activate(dup)
    r["dup_panel"] = depth_panel()
    r["show_dup"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    r["shown_dup"] = head()
    pv.pa_avatar.budget = 60.0
    r["pv_moved"] = head()
    activate(pv)
    r["pv_panel"] = depth_panel()
    r["show_pv"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    r["shown_pv"] = head()
    r["hide"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    r["hidden"] = head()
    bpy.data.objects.remove(pv)
    pv = None
    activate(dup)
    r["orphan_panel"] = depth_panel()
    dup.pa_avatar.budget = 50.0
    r["taken_panel"] = depth_panel()
    r["after_delete"] = head()
    activate(mesh)
    made = []
    kept = preview.create_preview_object

    def create(*args):
        made.append(kept(*args).name)
        return bpy.data.objects[made[-1]]

    preview.create_preview_object = create
    try:  # the second over the first, named as the head's preview is
        reload = [call(bpy.ops.object.progressive_avatars_load, filepath=STREAM) for _ in range(2)]
    finally:
        preview.create_preview_object = kept
    new = runtime.bound_previews(mesh)
    r["reloaded"] = [reload, made[-1] if made else None, new[0].name, getattr(mesh.pa_mesh, "depth_preview", None)]
    for ob in new + [mesh]:
        bpy.data.objects.remove(ob)


# -- file loads (the scene is replaced from here on) ----------------------------------------


@step
def file_load_ends_training(r):
    scene = bpy.context.scene
    op = ModalTrain("long_train.py", scene)
    try:
        r["started"] = wait_progress(op, SCENE, 2.0)
        blend = os.path.join(out, "saved while training.blend")
        bpy.ops.wm.save_as_mainfile(filepath=blend)  # Ctrl+S or autosave mid-run
        bpy.ops.wm.open_mainfile(filepath=blend)
        t0 = time.time()
        while op._proc.poll() is None and time.time() - t0 < 10:
            time.sleep(0.05)
        r["exit"] = op._proc.poll()
        st = bpy.context.scene.pa_train
        r["running"], r["progress"], r["message"] = st.running, st.progress, st.message
        try:
            r["tick"] = op.tick()
        except Exception as exc:
            r["tick"] = f"raised {type(exc).__name__}: {exc}"
        r["reports"] = op.reports
        # Train in the reopened file: not refused as "already running"
        prefs.python_path = lambda context=None: sys.executable
        prefs.user_train_script = lambda context=None: os.path.join(out, "quick_train.py")
        st.data_dir, st.out_dir = out, os.path.join(out, "run")
        bpy.context.view_layer.objects.active = None  # no mesh to load the result onto
        r["train"] = call(bpy.ops.progressive_avatars.train)
        r["running_after_train"] = bpy.context.scene.pa_train.running
    finally:
        op.end()


@step
def depth_colours_reopened(r):
    set_views("MATERIAL")
    r["import"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=SEQ)
    mesh = bpy.context.active_object
    name = mesh.name
    r["load"] = call(bpy.ops.object.progressive_avatars_load, filepath=STREAM)
    activate(preview_of(mesh))
    r["show"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    blend = os.path.join(out, "depth shown.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    bpy.ops.wm.open_mainfile(filepath=blend)
    mesh = bpy.data.objects[name]
    r["shown_reopened"], r["views_reopened"] = mesh.pa_mesh.depth_shown, views()
    bpy.ops.ed.undo_push(message="reopened")
    activate(preview_of(mesh))
    r["hide"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    bpy.ops.ed.undo_push(message="hidden")
    r["views_hidden"] = views()
    bpy.ops.ed.undo()  # back to shown: the views show depth colours again
    r["shown_undo"], r["views_undo"] = bpy.data.objects[name].pa_mesh.depth_shown, views()


@step
def save_copy_keeps_avatar_paths(r):
    """Save Copy into another folder writes the avatar path relative to the copy and leaves the
    open file's own: the preview still finds its avatar here after the cache is gone (as after
    any file load), and in the copy."""
    pv = next(o for o in bpy.data.objects if o.pa_avatar.is_preview)
    name, stored = pv.name, pv.pa_avatar.filepath
    copy = os.path.join(out, "copies", "deeper", "copy.blend")
    os.makedirs(os.path.dirname(copy), exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=copy, copy=True)
    r["paths"] = [stored, pv.pa_avatar.filepath]

    def placed():
        runtime.forget()
        scene = bpy.context.scene
        scene.frame_set(scene.frame_current + 1)
        pv = bpy.data.objects[name]
        return [pv.pa_avatar.status, misplaced(pv) if runtime.entry(pv) else None]

    r["here"] = placed()
    bpy.ops.wm.open_mainfile(filepath=copy)
    r["copy"] = placed()


@step
def previews_from_another_blend(r):
    """A head and its preview saved (Relative Paths) beside their avatar, then appended, linked
    and overridden into a file saved in another folder: the appended preview finds its avatar
    (its "//" path was the library's), also from a file saved before filepath_absolute, and
    keeps it once saved and reopened; the linked one shows nothing and says why (Blender keeps
    a linked mesh as the library has it); the overridden one follows its head, at another
    budget too."""
    lib_dir = os.path.join(out, "library")
    os.makedirs(os.path.join(lib_dir, "assets"), exist_ok=True)
    avatar = os.path.join(lib_dir, "assets", "avatar.pavs")
    shutil.copy(STREAM, avatar)
    bpy.ops.wm.read_homefile(use_empty=True)
    mesh, pv = head_with_preview(r, avatar, 60.0)
    names = [pv.name, mesh.name]
    library = os.path.join(lib_dir, "head.blend")
    bpy.ops.wm.save_as_mainfile(filepath=library)
    r["library_path"] = bpy.data.objects[names[0]].pa_avatar.filepath
    older = os.path.join(lib_dir, "older.blend")  # as saved before the absolute path was stored
    bpy.data.objects[names[0]].pa_avatar.filepath_absolute = ""
    bpy.data.libraries.write(older, {bpy.data.objects[n] for n in names})
    shot = os.path.join(out, "shots", "deeper", "shot.blend")
    os.makedirs(os.path.dirname(shot), exist_ok=True)
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=shot)

    def bring(link, blend=library):
        with bpy.data.libraries.load(blend, link=link) as (_, data):
            data.objects = list(names)
        for ob in data.objects:
            bpy.context.scene.collection.objects.link(ob)
        return data.objects[0]

    def shown(pv):
        scene = bpy.context.scene
        scene.frame_set(scene.frame_current + 1)
        return [pv.pa_avatar.status, shown_count(pv), misplaced(pv) if runtime.entry(pv) else None]

    r["appended"] = shown(bring(link=False))
    r["appended_older"] = shown(bring(link=False, blend=older))
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=shot)
    appended = bpy.data.objects[names[0]]
    r["appended_path"] = appended.pa_avatar.filepath
    r["appended_reopened"] = shown(appended)
    linked = bring(link=True)
    r["linked"] = shown(linked)
    linked.override_hierarchy_create(bpy.context.scene, bpy.context.view_layer)
    overridden = next(ob for ob in bpy.data.objects if ob.override_library and ob.pa_avatar.is_preview)
    r["overridden"] = shown(overridden)
    overridden.pa_avatar.budget = 30.0
    r["overridden_budget_status"] = overridden.pa_avatar.status
    r["overridden_budget"] = shown(overridden)


@step
def relative_paths_off(r):
    """Relative Paths off (Preferences > File Paths): Load Avatar stores the absolute path, and
    a path stored relative before (the preference on then) follows the file saved into another
    folder, as Save As remaps Blender's own; reopened, both previews find their avatar."""
    filepaths = bpy.context.preferences.filepaths
    bpy.ops.wm.read_homefile(use_empty=True)
    folder = os.path.join(out, "prefs")
    os.makedirs(os.path.join(folder, "deeper"), exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(folder, "one.blend"))
    names = []
    for relative in (True, False):
        filepaths.use_relative_paths = relative
        r[f"import_{relative}"] = call(bpy.ops.import_scene.progressive_avatars_sequence, filepath=SEQ)
        r[f"load_{relative}"] = call(bpy.ops.object.progressive_avatars_load, filepath=STREAM)
        names.append(preview_of(bpy.context.active_object).name)
    r["stored"] = [bpy.data.objects[n].pa_avatar.filepath for n in names]
    two = os.path.join(folder, "deeper", "two.blend")
    bpy.ops.wm.save_as_mainfile(filepath=two)
    bpy.ops.wm.open_mainfile(filepath=two)
    filepaths.use_relative_paths = True
    scene = bpy.context.scene
    scene.frame_set(scene.frame_current + 1)
    r["reopened"] = [[pv.pa_avatar.filepath, pv.pa_avatar.status] for pv in (bpy.data.objects[n] for n in names)]


R["blocked_loaded"] = stock_blender.loaded(blocked)
print("PA_UNDO " + json.dumps(R))
