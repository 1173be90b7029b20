"""Blender session run by test_blender_failures.py (a real file so it can be read, linted and run by hand).

Operators driven into their failure paths (a trainer's non-UTF-8 log, Edit Mode, an edited
mesh): each step records what the operator reported and what it left in the scene; a step
that raises records its traceback and the next one still runs. The sequence import's cursor
progress is recorded on its way through and out of them (and through a plain import).
"""

import contextlib, importlib, json, os, queue, subprocess, sys, time, traceback, types

import stock_blender

root, out, blocked = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
stock_blender.block(blocked)
import bpy
import bmesh
import numpy as np

stock_blender.load_extension(root, "pa_fail")
prefs = importlib.import_module("pa_fail.blender_addon.prefs")
runtime = importlib.import_module("pa_fail.blender_addon.runtime")
rig_builder = importlib.import_module("pa_fail.blender_addon.rig")
preview = importlib.import_module("pa_fail.blender_addon.preview")
sequence_builder = importlib.import_module("pa_fail.blender_addon.sequence")
PA_OT_train = importlib.import_module("pa_fail.blender_addon.operators_train").PA_OT_train
PA_OT_import_sequence = importlib.import_module("pa_fail.blender_addon.operators_import").PA_OT_import_sequence

SEQ, STREAM = os.path.join(out, "seq.npz"), os.path.join(out, "avatar.pavs")
OTHER, SHORTER = os.path.join(out, "reordered.pavs"), os.path.join(out, "shorter.pavs")
MODEL, PARAMS = os.path.join(out, "flame_model.npz"), os.path.join(out, "tracked_flame_params.npz")
OBJ_FRAMES, OBJ_BROKEN = os.path.join(out, "obj_frames"), os.path.join(out, "obj_broken")  # test_blender_failures
FLAME_FOLDER = os.path.join(out, "ga")  # ga/flame_param/*.npz, one file per frame of PARAMS
KINDS = ("objects", "meshes", "armatures", "actions", "shape_keys", "node_groups", "materials", "images")
R = {}


def inventory():
    return {k: sorted(x.name for x in getattr(bpy.data, k)) for k in KINDS}


def added(before):
    now = inventory()
    return {k: sorted(set(now[k]) ^ set(before[k])) for k in KINDS if now[k] != before[k]}


call = stock_blender.call


def shading():
    return [sp.shading.color_type for s in bpy.data.screens for a in s.areas for sp in a.spaces if sp.type == "VIEW_3D"]


step = stock_blender.stepper(R)
activate = stock_blender.activate


class RecordingWindowManager:
    """The window manager, its progress calls recorded on the way (RNA functions cannot be
    replaced on the type or the instance, so the operator is handed this one)."""

    def __init__(self, wm, calls):
        self._wm, self._calls = wm, calls

    def progress_begin(self, low, high):
        self._calls.append(["begin", low, high])
        self._wm.progress_begin(low, high)

    def progress_update(self, value):
        self._calls.append(["update", value])
        self._wm.progress_update(value)

    def progress_end(self):
        self._calls.append(["end"])
        self._wm.progress_end()

    def __getattr__(self, name):
        return getattr(self._wm, name)


class ContextWith:
    """Blender's context with another window manager."""

    def __init__(self, context, window_manager):
        self._context, self.window_manager = context, window_manager

    def __getattr__(self, name):
        return getattr(self._context, name)


@contextlib.contextmanager
def failing(module, name):
    """``module.name`` raising RuntimeError("injected failure") meanwhile."""

    def boom(*args, **kw):
        raise RuntimeError("injected failure")

    kept = getattr(module, name)
    setattr(module, name, boom)
    try:
        yield
    finally:
        setattr(module, name, kept)


def import_progress(**kw):
    """The sequence import's result and the progress calls it made on the window manager."""
    calls, kept = [], PA_OT_import_sequence.execute

    def execute(self, context):
        return kept(self, ContextWith(context, RecordingWindowManager(context.window_manager, calls)))

    PA_OT_import_sequence.execute = execute
    try:
        return call(bpy.ops.import_scene.progressive_avatars_sequence, **kw), calls
    finally:
        PA_OT_import_sequence.execute = kept


for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob)
bpy.ops.import_scene.progressive_avatars_sequence(filepath=SEQ)
MESH = bpy.context.active_object
prefs.python_path = lambda context=None: sys.executable
prefs.user_train_script = lambda context=None: os.path.join(out, "latin1_train.py")
st = bpy.context.scene.pa_train
st.data_dir, st.out_dir = out, os.path.join(out, "run")


@step
def train_non_utf8(r):
    r["first"] = call(bpy.ops.progressive_avatars.train)
    r["running"], r["message"] = st.running, st.message
    r["second"] = call(bpy.ops.progressive_avatars.train)


@step
def train_reader_fails(r):
    def boom(state, line):
        raise RuntimeError("reader failed")

    st.running = False  # what Cancel does: whatever an earlier step left, this one starts free
    kept = PA_OT_train._progress
    PA_OT_train._progress = staticmethod(boom)
    try:
        r["result"] = call(bpy.ops.progressive_avatars.train)
    finally:
        PA_OT_train._progress = kept
    r["running"] = st.running


@step
def train_modal_reader(r):
    # The modal path starts each process with _next_process and drains it with _pump in a
    # thread; timers never fire headless, so the process is awaited here.
    op = types.SimpleNamespace(
        _cmds=[[sys.executable, os.path.join(out, "latin1_chatty.py")]], _env=None, _lines=queue.Queue()
    )
    op._pump = PA_OT_train._pump
    PA_OT_train._next_process(op)
    try:
        r["exit"] = op._proc.wait(timeout=20)
    except subprocess.TimeoutExpired:  # nobody reads its output any more: it blocks on the full pipe
        r["exit"] = "blocked"
        op._proc.kill()
        op._proc.wait()
    lines = []
    while not (lines and lines[-1].startswith("done")):
        try:  # the reader thread may still be draining what the pipe buffered
            lines.append(op._lines.get(timeout=2))
        except queue.Empty:
            break
    r["lines"], r["first"] = len(lines), lines[0] if lines else ""


class ModalTrain:
    """PA_OT_train's modal path on a stand-in (timers never fire headless, so the test calls
    modal() as the window manager would on each tick)."""

    def __init__(self, script, scene):
        self._cmds, self._env = [[sys.executable, os.path.join(out, script)]], None
        self._out = os.path.join(out, "modal_run")  # the stand-in trainers write no avatar
        self._lines, self._timer, self._scene, self.reports = queue.Queue(), "timer", scene, []
        self.removed_timers = []
        if hasattr(self, "_begin"):  # what invoke() does: the run, kept where undo leaves it
            self._begin(scene)

    def report(self, kind, message):
        self.reports.append((sorted(kind)[0], message))


for _name in ("modal", "_tick", "_drain", "_kill", "_stop", "_next_process", "_begin"):
    if _name in PA_OT_train.__dict__:  # (the old code had fewer)
        setattr(ModalTrain, _name, PA_OT_train.__dict__[_name])
ModalTrain._pump, ModalTrain._progress = staticmethod(PA_OT_train._pump), staticmethod(PA_OT_train._progress)


def modal_context(op, scene):
    wm = types.SimpleNamespace(event_timer_remove=op.removed_timers.append)
    return types.SimpleNamespace(scene=scene, screen=None, window_manager=wm)


TIMER = types.SimpleNamespace(type="TIMER")


@step
def train_modal_last_lines(r):
    # A trainer that fails after much output: its last line (the error) must reach the report,
    # though the process ends before the reader thread has drained the pipe.
    scene = bpy.context.scene
    op = ModalTrain("fails_loudly.py", scene)

    def slow_pump(stream, q):  # a busy Blender: the reader lags behind the trainer
        for line in stream:
            time.sleep(0.0002)
            q.put(line)

    op._pump = slow_pump
    scene.pa_train.running = True
    op._next_process()
    op._proc.wait(timeout=30)
    r["result"] = sorted(op.modal(modal_context(op, scene), TIMER))
    r["reports"], r["running"], r["timers"] = op.reports, scene.pa_train.running, op.removed_timers


@step
def train_modal_other_scene(r):
    # Training started in one scene; the user is looking at another (its running is unset).
    scene = bpy.context.scene
    other = bpy.data.scenes.get("Other") or bpy.data.scenes.new("Other")
    op = ModalTrain("slow_train.py", scene)
    scene.pa_train.running = True
    op._next_process()
    ticks = []
    for _ in range(400):
        ticks.append(sorted(op.modal(modal_context(op, other), TIMER)))
        if ticks[-1] != ["PASS_THROUGH"]:
            break
        time.sleep(0.05)
    r["last"], r["ticks"], r["reports"] = ticks[-1], len(ticks), op.reports
    r["exit"] = op._proc.poll()
    r["running"], r["other_running"] = scene.pa_train.running, other.pa_train.running
    r["message"] = scene.pa_train.message


@step
def train_modal_raises(r):
    def boom(state, line):
        raise RuntimeError("reader failed")

    scene = bpy.context.scene
    op = ModalTrain("slow_train.py", scene)
    op._progress = boom
    scene.pa_train.running = True
    op._next_process()
    op._lines.put("it 1/2\n")
    try:
        r["result"] = sorted(op.modal(modal_context(op, scene), TIMER))
    except RuntimeError as exc:
        r["result"] = f"raised: {exc}"
    r["reports"], r["running"], r["timers"] = op.reports, scene.pa_train.running, op.removed_timers
    r["trainer_stopped"] = op._proc.poll() is not None
    if not r["trainer_stopped"]:
        op._proc.kill()
        op._proc.wait()


def count_input(obj):
    mod = obj.modifiers.get(preview.MODIFIER_NAME)
    return mod[preview.input_identifier(mod.node_group, "Count")]


@step
def budget_and_replaced_file(r):
    import shutil

    live = os.path.join(out, "live.pavs")
    shutil.copy(STREAM, live)
    activate(MESH)
    r["load"] = call(bpy.ops.object.progressive_avatars_load, filepath=live, budget=100.0)
    pv = next(c for c in MESH.children if c.pa_avatar.is_preview)
    # Percents that Blender's 32-bit property stores off their decimal by enough to cross a
    # record boundary: the preview must show what a viewer given the typed percent shows.
    b = runtime.entry(pv).budget
    typed = np.round(np.arange(1, 100000) * 0.001, 3)  # every percent with three decimals
    size = os.path.getsize(live)
    near = typed[np.floor(typed * size / 100) != np.floor(typed.astype(np.float32).astype(np.float64) * size / 100)]
    crossing = [float(p) for p in near if b.count_for_percent(float(p)) != b.count_for_percent(float(np.float32(p)))]
    r["crossing"] = len(crossing)
    r["budget_counts"] = []
    for p in crossing[:5]:
        pv.pa_avatar.budget = p
        r["budget_counts"].append([p, pv.pa_avatar.count, count_input(pv), b.count_for_percent(p)])
    # The file replaced by another stream of the same Gaussians (the .blend reopened: the
    # decoded cache is gone): not mixed with the preview's saved attributes, hidden instead.
    pv.pa_avatar.budget = 30.0
    shutil.copy(OTHER, live)
    runtime.forget(pv)
    runtime.apply_budget(pv, bpy.context)
    r["changed_status"], r["changed_count"], r["changed_shown"] = (
        pv.pa_avatar.status,
        pv.pa_avatar.count,
        count_input(pv),
    )
    # A preview saved before the signature existed, its file replaced by a shorter stream
    shutil.copy(SHORTER, live)
    pv.pa_avatar.file_signature = ""
    runtime.forget(pv)
    runtime.apply_budget(pv, bpy.context)
    r["shorter_status"], r["shorter_shown"] = pv.pa_avatar.status, count_input(pv)
    # Loading it again is the remedy
    r["reload"] = call(bpy.ops.object.progressive_avatars_load, filepath=live, budget=30.0)
    pv = next(c for c in MESH.children if c.pa_avatar.is_preview)
    r["reload_status"], r["reload_shown"] = pv.pa_avatar.status, count_input(pv)


@step
def rig_in_edit_mode(r):
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    activate(cube, "EDIT")
    r["result"] = call(
        bpy.ops.import_scene.progressive_avatars_sequence, filepath=PARAMS, as_rig=True, flame_model=MODEL
    )
    obj = bpy.context.active_object
    r["groups"] = len(obj.vertex_groups) if obj is not None and obj is not cube else 0

    # A build that fails late (here: the pose-corrective drivers) takes everything back.
    activate(cube, "EDIT")
    before = inventory()

    def boom(*args):
        raise RuntimeError("injected failure")

    kept = rig_builder._drive_pose_keys
    rig_builder._drive_pose_keys = boom
    try:
        r["failed"] = call(
            bpy.ops.import_scene.progressive_avatars_sequence, filepath=PARAMS, as_rig=True, flame_model=MODEL
        )
    finally:
        rig_builder._drive_pose_keys = kept
    r["failed_added"] = added(before)
    r["failed_mode"] = bpy.context.mode
    r["failed_active"] = bpy.context.active_object.name if bpy.context.active_object else None
    r["failed_selected"] = [o.name for o in bpy.context.selected_objects]
    r["cube"] = cube.name


@step
def sequence_import_fails_late(r):
    # A plain (shape-key) import whose build fails after the mesh exists takes it all back.
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 5, 9
    before = inventory()
    with failing(sequence_builder, "add_sequence_keys"):
        r["result"], r["progress"] = import_progress(filepath=SEQ)
    r["added"] = added(before)
    r["range"] = [scene.frame_start, scene.frame_end]


@step
def import_progress_shown(r):
    # Imports of frame folders: the cursor counts the files read and is put back at the end.
    scene = bpy.context.scene
    r["obj"], r["obj_progress"] = import_progress(filepath=OBJ_FRAMES)
    r["obj_frames"] = bpy.context.active_object.pa_mesh.num_frames
    r["rig"], r["rig_progress"] = import_progress(filepath=FLAME_FOLDER, as_rig=True, flame_model=MODEL)
    # A frame that cannot be read: the import stops there, adds nothing and ends the progress.
    scene.frame_start, scene.frame_end = 5, 9
    before = inventory()
    r["broken"], r["broken_progress"] = import_progress(filepath=OBJ_BROKEN)
    r["broken_added"], r["broken_range"] = added(before), [scene.frame_start, scene.frame_end]

    # An exception no handler expects (here: from the face check) still ends the progress.
    with failing(sequence_builder, "face_problem"):
        r["raised"], r["raised_progress"] = import_progress(filepath=OBJ_FRAMES)
    r["raised_added"] = added(before)


@step
def load_in_edit_mode(r):
    activate(MESH, "EDIT")
    before, attributes = inventory(), sorted(a.name for a in MESH.data.attributes)
    r["result"] = call(bpy.ops.object.progressive_avatars_load, filepath=STREAM)
    r["added"] = added(before)
    r["attributes_kept"] = sorted(a.name for a in MESH.data.attributes) == attributes


@step
def bound_mesh_in_edit_mode(r):
    activate(MESH)
    r["load"] = call(bpy.ops.object.progressive_avatars_load, filepath=STREAM, budget=100.0)
    pv = next(c for c in MESH.children if c.pa_avatar.is_preview)
    activate(MESH, "EDIT")
    pv.pa_avatar.budget = 40.0  # the update callback prints what it raises; the direct call shows it
    r["status_slider"] = pv.pa_avatar.status
    try:
        runtime.apply_budget(pv, bpy.context)
        r["apply_budget"] = "ok"
    except Exception as exc:
        r["apply_budget"] = f"{type(exc).__name__}: {exc}"
    r["status"] = pv.pa_avatar.status
    pv.pa_avatar.budget = 90.0  # more than evaluated: the frame is evaluated on the edited mesh
    r["status_grow"] = pv.pa_avatar.status
    shade = shading()
    r["depth"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    r["depth_shown"] = MESH.pa_mesh.depth_shown
    r["depth_saved"] = MESH.pa_mesh.depth_saved
    r["shading_kept"] = shading() == shade
    r["mesh"] = MESH.name


@step
def preview_in_edit_mode(r):
    pv = next(c for c in MESH.children if c.pa_avatar.is_preview)
    activate(pv)
    pv.pa_avatar.budget = 20.0
    activate(pv, "EDIT")
    r["mesh_edit"], r["preview_edit"] = MESH.data.is_editmode, pv.data.is_editmode
    pv.pa_avatar.budget = 95.0
    try:
        runtime.apply_budget(pv, bpy.context)
        r["apply_budget"] = "ok"
    except Exception as exc:
        r["apply_budget"] = f"{type(exc).__name__}: {exc}"
    r["status"], r["preview"] = pv.pa_avatar.status, pv.name


@step
def frame_change_in_edit_mode(r):
    pv = next(c for c in MESH.children if c.pa_avatar.is_preview)
    scene = bpy.context.scene
    activate(pv)
    pv.pa_avatar.budget = 100.0

    def placed():
        a = np.empty(len(pv.data.vertices) * 3, np.float32)
        pv.data.attributes["position"].data.foreach_get("vector", a)
        return a

    f0, f1 = scene.frame_start, scene.frame_start + 2
    scene.frame_set(f1)
    want = placed()  # frame f1's positions, placed in Object Mode
    scene.frame_set(f0)
    r["frames_differ"] = float(np.abs(placed() - want).max())
    activate(pv, "EDIT")
    scene.frame_set(f1)  # its points live in the edit mesh now: nothing can be written
    activate(pv)  # leaving Edit Mode writes the edit mesh back: frame f0's positions
    bpy.context.view_layer.update()
    r["after_edit"] = float(np.abs(placed() - want).max())
    r["status"] = pv.pa_avatar.status


@step
def depth_on_edited_mesh(r):
    pv = next(c for c in MESH.children if c.pa_avatar.is_preview)
    MESH.pa_mesh.depth_shown, MESH.pa_mesh.depth_saved = False, ""  # whatever an earlier step left
    bm = bmesh.new()
    bm.from_mesh(MESH.data)
    bm.faces.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[bm.faces[0]], context="FACES_ONLY")
    bm.to_mesh(MESH.data)
    bm.free()
    MESH.data.update()
    activate(pv)
    shade = shading()
    r["result"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    r["depth_shown"] = MESH.pa_mesh.depth_shown
    r["depth_saved"] = MESH.pa_mesh.depth_saved
    r["colour_attributes"] = [a.name for a in MESH.data.color_attributes]
    r["shading_kept"] = shading() == shade
    r["again"] = call(bpy.ops.object.progressive_avatars_depth_colors)
    r["mesh"] = MESH.name


R["blocked_loaded"] = stock_blender.loaded(blocked)
print("PA_FAILURES " + json.dumps(R))
