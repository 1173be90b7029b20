"""Train operator: training in the configured Python (torch is not in Blender).

The extension trains from its own folder (core/train/jobs.py, loaded under a private package
name, so no checkout and no other installed copy is involved; in an installed extension the
training tier comes from its inner archive, unpacked by training_tier.py); a train script set in the
preferences (a checkout's scripts/train.py) is run instead when given. The result is loaded
onto the mesh that started training (stored on the scene, so it survives undo).

A training in progress lives on the Python side (``_RUNS``, keyed by the scene's session id):
undo puts the scene's properties back as they were at an undo step (``running`` unset, an old
progress) and invalidates Scene references, so the modal operator looks its scene up on each
tick and ``restore_runs`` (an undo/redo handler) writes the live state back. Nothing of a run
survives a file load: ``stop_all`` (load_pre) ends the trainers, ``clear_after_load``
(load_post) clears what a file saved mid-run stored.
"""

import glob
import os
import queue
import re
import subprocess
import threading

import bpy

from . import prefs, runtime, training_tier
from ..core.bridge import payload

_PERCENT = re.compile(r"(\d+(?:\.\d+)?)\s*%")
_FRACTION = re.compile(r"(?:iter(?:ation)?|it|step)?\s*[=:]?\s*(\d+)\s*/\s*(\d+)", re.IGNORECASE)


def parse_progress(line):
    """Percent done from a progress line ("it 120/3000", "12.5%"), or None."""
    m = _FRACTION.search(line)
    if m and int(m.group(2)) > 0:
        return min(100.0, 100.0 * int(m.group(1)) / int(m.group(2)))
    m = _PERCENT.search(line)
    return min(100.0, float(m.group(1))) if m else None


def find_result(run_dir):
    """The newest stream/avatar file a run wrote."""
    cands = []
    for pat in ("*.pavs",) if glob.glob(os.path.join(run_dir, "*.pavs")) else ("avatar*.npz",):
        cands += glob.glob(os.path.join(run_dir, pat)) + glob.glob(os.path.join(run_dir, "*", pat))
    cands = [c for c in cands if os.path.isfile(c)]
    return max(cands, key=os.path.getmtime) if cands else None


_RUNNER = payload.loader("from pa_ext.core.train import jobs\nsys.exit(jobs.main(sys.argv[1:]))\n")


def _extension_root():
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _options(st):
    """The Training panel's choices as train.py arguments (both commands take the same)."""
    args = ["--preset", st.preset] if st.preset else []
    if st.iterations:
        args += ["--iterations", str(st.iterations)]
    if st.overwrite:
        args += ["--overwrite"]
    if st.resume:
        args += ["--resume"]
    return args


def _command(context):
    st = context.scene.pa_train
    problem = prefs.python_problem(context, "torch and numba")
    if problem:
        raise RuntimeError(problem)
    python = prefs.python_path(context)
    data, out = bpy.path.abspath(st.data_dir), bpy.path.abspath(st.out_dir)
    if not st.data_dir or not os.path.isdir(data):
        raise RuntimeError(f"Data folder not found: '{data}' (Training > Data)")
    if not st.out_dir:
        raise RuntimeError("Choose a run folder (Training > Run)")
    if st.resume and st.overwrite:
        raise RuntimeError("Resume continues the run, Overwrite Run starts it over: tick one of them")
    model = prefs.flame_model(context)
    if model and not os.path.isfile(model):
        raise RuntimeError(
            f"FLAME model not found: {model} (Preferences > Add-ons > Progressive Avatars > FLAME model)"
        )
    flame = ["--flame-model", model] if model else []
    script = prefs.user_train_script(context)
    if script:
        if not os.path.isfile(script):
            raise RuntimeError(f"Train script not found: {script} (Preferences > Add-ons > Progressive Avatars)")
        cmd = [python, "-u", script, "--data", data, "--out", out] + _options(st)
        cmds = [cmd + flame]
        # Training writes RUN/avatar.npz in creation order; the importance-ordered stream that
        # the budget slider needs comes from scripts/export.py, run next when it is there.
        export = os.path.join(os.path.dirname(script), "export.py")
        if os.path.isfile(export):
            cmds.append(
                [python, "-u", export, "--run", out, "--data", data, "--stream", os.path.join(out, "avatar.pavs")]
                + flame
            )
        return cmds, out, None  # a checkout's own scripts: its usual cache
    try:
        tier = training_tier.folder(_extension_root())
    except OSError as exc:
        raise RuntimeError(str(exc)) from exc
    cmd = [python, "-u", "-c", _RUNNER, _extension_root(), tier, "train", "--data", data, "--out", out]
    cmd += flame + _options(st)
    # Its own numba cache: in a checkout, entries compiled as pa_ext in the sources' __pycache__
    # broke every later command-line run there (training_tier.numba_cache_dir).
    return [cmd], out, training_tier.runner_env()


def _popen(cmd, env):
    # The trainer's log is read as UTF-8 whatever the locale, and a byte that is not (a Latin-1
    # path in a warning) becomes U+FFFD: a decode error would kill the reader mid-run.
    return subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        encoding="utf-8",
        errors="replace",
        bufsize=1,
        env=env,
    )


def _start(context):
    """Remember the mesh training is for (the active mesh, or the active preview's mesh)."""
    st = context.scene.pa_train
    obj = context.active_object
    if obj is not None and obj.pa_avatar.is_preview:
        obj = runtime.bound_mesh(obj)
    st.target = obj if obj is not None and obj.type == "MESH" else None


class _Run:
    """A training in progress: what undo must not take back."""

    def __init__(self, key):
        self.key = key
        self.proc = None
        self.progress, self.message = 0.0, "starting"
        self.stopped = ""  # why it must stop (Cancel, a file load), "" while it runs on


_RUNS = {}  # scene session_uid -> _Run


def _scene_by_key(key):
    """The scene of this session id, or None (deleted); Scene objects held across an undo are
    invalid, the id is not."""
    for scene in bpy.data.scenes:
        if scene.session_uid == key:
            return scene
    return None


def is_running(scene):
    """Whether a training of this Blender session runs in ``scene`` (its ``running`` property
    only mirrors this: undo and files saved mid-run restore stale values)."""
    return scene.session_uid in _RUNS


def _show(run, st):
    """The live run's state on the scene's properties (what the panel draws)."""
    if not st.running:
        st.running = True
    if st.progress != run.progress:
        st.progress = run.progress
    if st.message != run.message:
        st.message = run.message


def restore_runs():
    """After undo/redo: the scenes that train show it again (running, progress, message)."""
    for run in _RUNS.values():
        scene = _scene_by_key(run.key)
        if scene is not None and not run.stopped:
            _show(run, scene.pa_train)


def stop_all(reason="another file was opened"):
    """End every trainer (before a file load: no run carries over into another file)."""
    for run in list(_RUNS.values()):
        run.stopped = run.stopped or reason
        proc = run.proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    _RUNS.clear()


def clear_after_load():
    """After a file load: no training runs in it, whatever it was saved with."""
    for scene in bpy.data.scenes:
        st = scene.pa_train
        if st.running:
            st.running = False
            st.progress = 0.0
            st.message = "Not running: this file was saved while a training ran (Resume continues it)"


def _finish(op, context, rc, out, scene=None):
    st = (scene or context.scene).pa_train
    st.running = False
    if rc != 0:
        op.report({"ERROR"}, f"Training failed (exit {rc}): {st.message}")
        return {"CANCELLED"}
    st.progress = 100.0
    result = find_result(out)
    mesh = st.target  # the mesh that started training, whatever is active now
    if result is None:
        op.report({"ERROR"}, f"Training finished but wrote no avatar in {out}")
        return {"CANCELLED"}
    if mesh is None or mesh.type != "MESH":
        op.report(
            {"WARNING"},
            f"Trained {result}; no mesh to load it onto (none was active when training started, or it was deleted)",
        )
        return {"FINISHED"}
    from .operators_avatar import load_avatar_onto

    try:
        load_avatar_onto(context, mesh, result)
    except Exception as exc:
        op.report({"ERROR"}, f"Trained, but loading {result} onto {mesh.name} failed: {exc}")
        return {"CANCELLED"}
    op.report({"INFO"}, f"Training finished: {result} loaded onto {mesh.name}")
    return {"FINISHED"}


class PA_OT_train(bpy.types.Operator):
    """Train an avatar on a dataset in the configured Python; progress shows in the panel"""

    bl_idname = "progressive_avatars.train"
    bl_label = "Train Avatar"

    _proc = None
    _timer = None
    _lines = None
    _reader = None
    _key = None

    def execute(self, context):
        # Blocking path: background mode, where timers (and so the modal path) never run.
        try:
            cmds, out, env = _command(context)
        except RuntimeError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        st = context.scene.pa_train
        if is_running(context.scene):
            self.report({"ERROR"}, "A training is already running in this scene: wait for it, or cancel it")
            return {"CANCELLED"}
        _start(context)
        st.running = True
        key = context.scene.session_uid
        _RUNS[key] = _Run(key)
        rc, proc = 0, None
        try:
            for cmd in cmds:
                try:
                    proc = _popen(cmd, env)
                except OSError as exc:
                    self.report({"ERROR"}, f"Cannot start training with {cmd[0]}: {exc}")
                    return {"CANCELLED"}
                for line in proc.stdout:
                    self._progress(st, line)
                rc = proc.wait()
                if rc != 0:
                    break
        finally:
            # Whatever went wrong, a stuck flag would refuse every later Train in this scene,
            # and a trainer nobody reads any more would block on its full pipe.
            st.running = False
            _RUNS.pop(key, None)
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
        return _finish(self, context, rc, out)

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        try:
            self._cmds, self._out, self._env = _command(context)
        except RuntimeError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if is_running(context.scene):  # the panel hides Train then; the operator search does not
            self.report({"ERROR"}, "A training is already running in this scene: wait for it, or cancel it")
            return {"CANCELLED"}
        self._lines = queue.Queue()
        self._begin(context.scene)
        try:
            self._next_process()
        except OSError as exc:
            _RUNS.pop(self._key, None)
            context.scene.pa_train.running = False
            self.report({"ERROR"}, f"Cannot start training with {self._cmds[0][0] if self._cmds else 'Python'}: {exc}")
            return {"CANCELLED"}
        _start(context)
        self._timer = context.window_manager.event_timer_add(0.25, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _begin(self, scene):
        """Register the run of ``scene`` (the user may switch scenes while it runs: the
        training scene is the one looked up by this key on each tick, not the shown one)."""
        self._key = scene.session_uid
        run = _RUNS[self._key] = _Run(self._key)
        _show(run, scene.pa_train)

    def _next_process(self):
        self._proc = _popen(self._cmds[0], self._env)
        self._cmds.pop(0)
        run = _RUNS.get(getattr(self, "_key", None))
        if run is not None:
            run.proc = self._proc
        self._reader = threading.Thread(target=self._pump, args=(self._proc.stdout, self._lines), daemon=True)
        self._reader.start()

    @staticmethod
    def _pump(stream, q):
        for line in stream:
            q.put(line)

    @staticmethod
    def _progress(st, line):
        line = line.strip()
        if line:
            st.message = line[-200:]
            p = parse_progress(line)
            if p is not None:
                st.progress = p

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            return self._tick(context)
        except Exception as exc:
            # Whatever failed here, the trainer must not run on unread (it would block on its
            # full pipe) and the scene must not stay "running" (every later Train refused).
            self._kill()
            self._stop(context)
            self.report({"ERROR"}, f"Training stopped: {type(exc).__name__}: {exc}")
            return {"CANCELLED"}

    def cancel(self, context):
        # Blender ends the modal handler (Blender quits, the window closes): so does the trainer.
        self._kill()
        self._stop(context)

    def _tick(self, context):
        run = _RUNS.get(self._key)
        if run is None or run.stopped:  # Cancel, or a file load (stop_all)
            self._kill()
            self._stop(context)
            why = run.stopped if run is not None else "another file was opened"
            self.report({"WARNING"}, "Training cancelled" if why == "cancelled" else f"Training stopped: {why}")
            return {"CANCELLED"}
        scene = _scene_by_key(self._key)
        if scene is None:
            self._kill()
            self._stop(context)
            self.report({"WARNING"}, "Training stopped: its scene was deleted")
            return {"CANCELLED"}
        st = scene.pa_train
        _show(run, st)  # an undo since the last tick put older values there
        self._drain(st)
        for area in context.screen.areas if context.screen else ():
            if area.type == "VIEW_3D":
                area.tag_redraw()
        rc = self._proc.poll()
        if rc is None:
            return {"PASS_THROUGH"}
        # The process has ended, its last lines (the error, on a failure) may still be on their
        # way through the reader thread: all of them are in the panel before the report.
        if self._reader is not None:
            self._reader.join(timeout=5)
        self._drain(st)
        if rc == 0 and self._cmds:
            try:
                self._next_process()
                return {"PASS_THROUGH"}
            except OSError as exc:
                self._stop(context)
                self.report({"ERROR"}, f"Trained, but cannot start the export: {exc}")
                return {"CANCELLED"}
        self._stop(context)
        return _finish(self, context, rc, self._out, scene)

    def _drain(self, st):
        while not self._lines.empty():
            self._progress(st, self._lines.get_nowait())
        run = _RUNS.get(self._key)
        if run is not None:
            run.progress, run.message = st.progress, st.message

    def _kill(self):
        if self._proc is not None and self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()

    def _stop(self, context):
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            self._timer = None
        _RUNS.pop(self._key, None)
        scene = _scene_by_key(self._key)
        if scene is not None:  # None: the training scene was deleted meanwhile
            scene.pa_train.running = False


class PA_OT_train_cancel(bpy.types.Operator):
    """Stop the running training"""

    bl_idname = "progressive_avatars.train_cancel"
    bl_label = "Cancel Training"

    def execute(self, context):
        run = _RUNS.get(context.scene.session_uid)
        if run is not None:
            run.stopped = "cancelled"  # the modal operator stops the trainer on its next tick
        context.scene.pa_train.running = False
        return {"FINISHED"}


classes = (PA_OT_train, PA_OT_train_cancel)
