"""Render Splats as a background job: a persistent worker process (core/render/worker.py in
the configured Python) and a job object the modal operator polls.

Nothing here blocks: the worker's answers arrive on a reader thread and wait in a queue
until ``RenderJob.poll`` drains them (from the operator's timer, or in a loop when Blender
runs without a UI, where timers never fire). The worker outlives each render, so only the
first render of a session pays the interpreter, torch and kernel start-up; the numba kernel
cache lives in the extension's user folder, so even that compiles once per machine.
"""

import atexit
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
        self.compiling = False  # while starting: its warm-up compiles the kernels (a first run)
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
            elif "starting" in msg:
                self.compiling = bool(msg.get("compiling"))
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


_jobs: set = set()  # jobs not finished yet: their folders go when the add-on stops


def stop_all():
    """Stop every worker (the add-on is disabled, Blender quits); unfinished jobs are cancelled
    and their folders removed."""
    for job in list(_jobs):
        job.cancel()
    for w in _workers.values():
        w.stop()
    _workers.clear()


atexit.register(stop_all)  # Blender quits (it does not unregister extensions): no folder left


class RenderJob:
    """One render: its inputs written to a temporary folder, sent to the worker, its state
    (``state``: starting / rendering / done / failed / cancelled; ``progress`` 0..1;
    ``message``) advanced by ``poll``."""

    def __init__(self, python, arrays, cache_dir=None):
        self.tmp = tempfile.mkdtemp(prefix="pa_render_")
        self.job = os.path.join(self.tmp, "job.npz")
        self.out = os.path.join(self.tmp, "image.npy")
        self.id = None
        self.state = "starting"
        self.progress = 0.05
        self.message = "starting the renderer"
        self.seconds = None
        self.t0 = time.perf_counter()
        self.rgba = None
        try:  # a full disk, or a Python that cannot start (OSError): no folder left behind
            np.savez(self.job, **arrays)
            self.worker = worker_for(python, cache_dir)
        except BaseException:
            self._cleanup()
            raise
        _jobs.add(self)
        if self.worker.ready is not None:
            self.message = "rendering"
        if self.worker.ready:
            self._send()

    def _send(self):
        try:
            self.id = self.worker.submit(self.job, self.out)
        except (OSError, ValueError) as exc:  # the worker died since: a broken or closed pipe
            self._fail(f"the render process ended: {self.worker.stderr_tail() or exc}")
            return
        self.state, self.progress, self.message = "rendering", 0.3, "rendering"

    def _fail(self, message):
        self.state, self.message = "failed", message
        self._cleanup()

    def poll(self):
        """Drain the worker's messages; returns the state."""
        if self.state in ("done", "failed", "cancelled"):
            return self.state
        try:
            return self._poll()
        except Exception as exc:  # never leave the job (and its folder) behind half-read
            self._fail(f"the render job broke: {type(exc).__name__}: {exc}")
            return self.state

    def _poll(self):
        w = self.worker
        w.drain()
        if self.id is None:  # waiting for the worker to come up
            if w.ready is False:
                self._fail(f"the render process cannot render ({w.python}): {w.error}")
                return self.state
            if w.ready:
                self._send()
                if self.state == "failed":
                    return self.state
            elif w.compiling:
                self.message = "starting the renderer: compiling its kernels (once for this version)"
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
        try:
            while self.poll() not in ("done", "failed", "cancelled"):
                if time.perf_counter() > end:
                    self.cancel()
                    self.message = f"timed out after {timeout:.0f} s"
                    break
                time.sleep(interval)
        except BaseException:  # Ctrl+C in a script: stop the render, remove its folder
            self.cancel()
            raise
        return self.state

    def cancel(self):
        """Stop now: the worker is killed (a running kernel cannot be interrupted); the next
        render starts a new one."""
        if self.state in ("done", "failed", "cancelled"):
            return
        self.state, self.message = "cancelled", "cancelled"
        try:
            self.worker.stop()
        finally:
            if _workers.get(self.worker.python) is self.worker:
                del _workers[self.worker.python]
            self._cleanup()

    def _cleanup(self):
        """Remove the job's folder (inputs and image); every way a job ends comes here."""
        _jobs.discard(self)
        shutil.rmtree(self.tmp, ignore_errors=True)


def store_image(rgba, background=None, name="PA Splats"):
    """Put a render into the float image ``name`` (made, or resized, as needed) and return it.

    ``rgba`` [H, W, 4], rows top-down, is what the render job returns (``RenderJob.rgba``): the
    splats' colours as the avatar learned them (sRGB-encoded) blended front to back over black,
    so RGB is premultiplied by the coverage A (the 4th channel) in that sRGB-encoded space.

    The image holds premultiplied scene-linear RGBA and says so (``alpha_mode`` 'PREMUL'), as
    Blender's own render results do: its compositor, "Save As Render" and ``save_render`` read
    a float image's pixels as premultiplied whatever its alpha_mode (checked in Blender 5.0), and
    with 'PREMUL' its image editor shows them that way too. Each pixel's own colour RGB / A is decoded from sRGB to linear,
    then multiplied by A again (decoding the premultiplied RGB would darken every
    semi-transparent edge: a red splat at A 0.39 stored 0.13 instead of 0.39).

    ``background`` (what is behind the splats):
      - None: nothing; the image is transparent where the splats are (as Film > Transparent).
      - three floats in Blender's scene-linear colour space, e.g. ``world.color[:3]`` exactly as
        bpy gives it: used as they are (never decoded from, or encoded to, sRGB here), put
        behind the splats in scene-linear (RGB + (1 - A) * background) with A set to 1, as
        Blender renders a world background (Film > Transparent off).
    """
    import bpy

    from ..core.bridge.splats import srgb_to_linear

    rgba = np.asarray(rgba, np.float32)
    if rgba.ndim != 3 or rgba.shape[2] != 4:
        raise ValueError(f"store_image: rgba must be [H, W, 4], got {list(rgba.shape)}")
    if background is not None:
        background = np.asarray(background, np.float32)
        if background.shape != (3,) or not np.all(np.isfinite(background)):
            raise ValueError(f"store_image: background must be 3 finite scene-linear values, got {background!r}")
    alpha = np.clip(rgba[..., 3:], 0.0, 1.0)
    colour = np.divide(rgba[..., :3], alpha, out=np.zeros_like(rgba[..., :3]), where=alpha > 0)  # straight
    out = np.empty(rgba.shape, np.float32)
    out[..., :3] = srgb_to_linear(colour) * alpha  # linear, premultiplied again
    out[..., 3:] = alpha
    if background is not None:
        out[..., :3] += (1.0 - alpha) * background
        out[..., 3] = 1.0
    h, w = rgba.shape[:2]
    img = bpy.data.images.get(name) or bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    if img.alpha_mode != "PREMUL":  # an image kept from an older version said STRAIGHT
        img.alpha_mode = "PREMUL"
    if tuple(img.size) != (w, h):
        img.scale(w, h)
    img.pixels.foreach_set(np.ascontiguousarray(out[::-1]).ravel())  # Blender rows run bottom-up
    img.update()
    return img
