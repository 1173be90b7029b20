"""Render Splats as a background job: a persistent worker process (core/render/worker.py in
the configured Python) and a job object the modal operator polls.

Nothing here blocks: the worker's answers arrive on a reader thread and wait in a queue
until ``RenderJob.poll`` drains them (from the operator's timer, or in a loop when Blender
runs without a UI, where timers never fire). The worker outlives each render, so only the
first render of a session pays the interpreter, torch and kernel start-up; the numba kernel
cache lives in the extension's user folder, so even that compiles once per machine.
"""

import json
import os
import queue
import shutil
import subprocess
import tempfile
import threading
import time

import numpy as np

from . import training_tier
from ..core.bridge import payload

_LOADER = payload.loader("from pa_ext.core.render.worker import serve\nsys.exit(serve())\n")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class RenderWorker:
    """One worker process and the queue its stdout lines go to."""

    def __init__(self, python, root=ROOT, cache_dir=None):
        self.python = python
        env = training_tier.runner_env(cache_dir)
        self.messages = queue.Queue()
        self.ready = None  # None: starting; True: warm; False: failed (see .error)
        self.error = ""
        self.started = time.perf_counter()
        self.proc = subprocess.Popen(
            [python, "-c", _LOADER, root, training_tier.folder(root)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
            env=env,
        )
        self._stderr = []
        self.inbox = {}  # job id -> its messages, so several jobs can share one worker
        self.eof = False
        threading.Thread(target=self._read, args=(self.proc.stdout, True), daemon=True).start()
        threading.Thread(target=self._read, args=(self.proc.stderr, False), daemon=True).start()
        self._next = 0

    def _read(self, pipe, is_stdout):
        try:
            self._read_lines(pipe, is_stdout)
        except (ValueError, OSError):  # the pipe was closed by stop()
            pass
        if is_stdout:
            self.messages.put({"eof": True})

    def _read_lines(self, pipe, is_stdout):
        for line in pipe:
            if not is_stdout:
                self._stderr = (self._stderr + [line.rstrip()])[-20:]
                continue
            try:
                msg = json.loads(line)
            except ValueError:  # stray prints from libraries
                continue
            if isinstance(msg, dict):
                self.messages.put(msg)

    def alive(self):
        return self.proc.poll() is None

    def drain(self):
        """Sort the reader thread's messages: worker state here, job messages by job id."""
        while True:
            try:
                msg = self.messages.get_nowait()
            except queue.Empty:
                return
            if msg.get("eof"):
                self.eof = True
            elif "ready" in msg:
                self.ready = bool(msg["ready"])
                self.error = msg.get("error", "")
            elif "id" in msg:
                self.inbox.setdefault(msg["id"], []).append(msg)

    def stderr_tail(self):
        return next((ln for ln in reversed(self._stderr) if ln.strip()), "")

    def submit(self, job, out):
        self._next += 1
        self.proc.stdin.write(json.dumps({"id": self._next, "job": job, "out": out}) + "\n")
        self.proc.stdin.flush()
        return self._next

    def stop(self):
        if self.alive():
            self.proc.kill()
            self.proc.wait(timeout=10)
        for pipe in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            try:
                pipe.close()
            except Exception:
                pass


_workers: dict = {}


def worker_for(python, cache_dir=None):
    """The running worker for this interpreter (started now if there is none or it died)."""
    w = _workers.get(python)
    if w is None or not w.alive() or w.ready is False:
        if w is not None:
            w.stop()
        w = _workers[python] = RenderWorker(python, cache_dir=cache_dir)
    return w


def stop_all():
    for w in _workers.values():
        w.stop()
    _workers.clear()


class RenderJob:
    """One render: its inputs written to a temporary folder, sent to the worker, its state
    (``state``: starting / rendering / done / failed / cancelled; ``progress`` 0..1;
    ``message``) advanced by ``poll``."""

    def __init__(self, python, arrays, cache_dir=None):
        self.tmp = tempfile.mkdtemp(prefix="pa_render_")
        self.job = os.path.join(self.tmp, "job.npz")
        self.out = os.path.join(self.tmp, "image.npy")
        np.savez(self.job, **arrays)
        self.worker = worker_for(python, cache_dir)
        self.id = None
        self.state = "starting"
        self.progress = 0.05
        self.message = "starting the renderer" if self.worker.ready is None else "rendering"
        self.seconds = None
        self.t0 = time.perf_counter()
        self.rgba = None
        if self.worker.ready:
            self._send()

    def _send(self):
        self.id = self.worker.submit(self.job, self.out)
        self.state, self.progress, self.message = "rendering", 0.3, "rendering"

    def _fail(self, message):
        self.state, self.message = "failed", message
        self._cleanup()

    def poll(self):
        """Drain the worker's messages; returns the state."""
        if self.state in ("done", "failed", "cancelled"):
            return self.state
        w = self.worker
        w.drain()
        if self.id is None:  # waiting for the worker to come up
            if w.ready is False:
                self._fail(f"the render process cannot render ({w.python}): {w.error}")
                return self.state
            if w.ready:
                self._send()
        for msg in w.inbox.pop(self.id, []) if self.id is not None else ():
            if "error" in msg:
                self._fail(msg["error"])
                return self.state
            if msg.get("done"):
                try:
                    self.rgba = np.load(self.out)
                except Exception as exc:
                    self._fail(f"no image from the render process: {exc}")
                    return self.state
                self.state, self.progress, self.message = "done", 1.0, "done"
                self.seconds = time.perf_counter() - self.t0
                self._cleanup()
                return self.state
            if "progress" in msg:
                self.progress = max(self.progress, float(msg["progress"]))
                self.message = msg.get("stage", self.message)
        if w.eof:  # the reader saw the end of the worker's output: nothing more will come
            w.drain()
            if not w.inbox.get(self.id):
                self._fail(f"the render process ended: {w.stderr_tail() or 'no message'}")
        return self.state

    def wait(self, timeout=600.0, interval=0.02):
        """Poll until finished (for a Blender without a UI, where timers never fire)."""
        end = time.perf_counter() + timeout
        while self.poll() not in ("done", "failed", "cancelled"):
            if time.perf_counter() > end:
                self.cancel()
                self.message = f"timed out after {timeout:.0f} s"
                break
            time.sleep(interval)
        return self.state

    def cancel(self):
        """Stop now: the worker is killed (a running kernel cannot be interrupted); the next
        render starts a new one."""
        if self.state in ("done", "failed", "cancelled"):
            return
        self.worker.stop()
        _workers.pop(self.worker.python, None)
        self.state, self.message = "cancelled", "cancelled"
        self._cleanup()

    def _cleanup(self):
        shutil.rmtree(self.tmp, ignore_errors=True)


def store_image(rgba, name="PA Splats"):
    """The render (sRGB-encoded RGBA, rows top-down) as a float Blender image, scene-linear."""
    import bpy

    from ..core.bridge.splats import srgb_to_linear

    h, w = rgba.shape[:2]
    img = bpy.data.images.get(name) or bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    if tuple(img.size) != (w, h):
        img.scale(w, h)
    rgba = np.array(rgba, np.float32)
    rgba[..., :3] = srgb_to_linear(rgba[..., :3])  # float images hold scene-linear values
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())  # Blender rows run bottom-up
    img.update()
    return img
