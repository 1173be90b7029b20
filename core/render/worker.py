"""A long-lived splat renderer for the Blender add-on (runs in the configured Python).

Blender's Python has neither torch nor numba, so "Render Splats" hands its Gaussians to
another interpreter. Starting one per render pays the interpreter, torch and numba start-up
(and, the first time ever, the kernels' compilation) on every click; this worker stays
alive between renders and warms the kernels once, before its first job arrives.

Protocol (JSON lines): the client writes ``{"id": k, "job": npz, "out": npy}`` per render
(the npz as ``core.bridge.render_job`` reads it); the worker answers with
``{"starting": true, "compiling": bool}`` (whether its warm-up compiles the kernels) and
``{"ready": ...}`` once, then per job ``{"id": k, "stage": name, "progress": p}`` lines and a
final ``{"id": k, "done": true, "seconds": s}`` or ``{"id": k, "error": message}``. End of input
ends the worker. Cancelling a render is killing the process: a running kernel cannot be
interrupted, and a fresh worker starts from the on-disk kernel cache.
"""

from __future__ import annotations

import json
import os
import sys
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads (see core/render/rasterize.py)


def _say(out, **msg):
    out.write(json.dumps(msg) + "\n")
    out.flush()


def warm_up():
    """Load (or compile, the first time) every kernel a forward render uses, on a tiny scene: in
    float32 and in float64, since the kernels read float32 inputs as they are and anything else
    (mixed dtypes, as a world-space transform in float64 beside float32 colours gives) as float64."""
    import numpy as np

    from ..geometry.camera import Camera
    from .rasterize import render_numpy

    rng = np.random.default_rng(0)
    n = 16
    cam = Camera(np.eye(3), np.array([0.0, 0.0, 1.0]), 40.0, 40.0, 16.0, 16.0, 32, 32)
    for dtype in (np.float32, np.float64):
        render_numpy(
            rng.normal(0, 0.05, (n, 3)).astype(dtype),
            np.tile(np.array([1, 0, 0, 0], dtype), (n, 1)),
            np.full((n, 3), 0.02, dtype),
            np.full(n, 0.5, dtype),
            np.full((n, 3), 0.5, dtype),
            cam,
            np.zeros(3, dtype),
        )


def serve(inp=None, out=None) -> int:
    inp = inp or sys.stdin
    out = out or sys.stdout
    t0 = time.perf_counter()
    try:
        from . import kernels

        # Before a warm-up that compiles for minutes the first time: the add-on says why it waits.
        _say(out, starting=True, compiling=kernels.uncached(kernels.raster_forward))
        warm_up()
    except Exception as exc:  # no numba/torch, broken install: say so, then exit
        _say(out, ready=False, error=f"{type(exc).__name__}: {exc}")
        return 1
    from ..bridge.render_job import render_job

    _say(out, ready=True, seconds=round(time.perf_counter() - t0, 3), pid=os.getpid())
    for line in inp:
        line = line.strip()
        if not line:
            continue
        try:
            req = json.loads(line)
            k = req["id"]
        except (ValueError, KeyError, TypeError) as exc:
            _say(out, error=f"bad request {line[:80]!r}: {exc}")
            continue
        t = time.perf_counter()
        try:
            _say(out, id=k, stage="rendering", progress=0.5)
            render_job(req["job"], req["out"])
        except Exception as exc:
            _say(out, id=k, error=f"{type(exc).__name__}: {exc}")
            continue
        _say(out, id=k, done=True, seconds=round(time.perf_counter() - t, 3))
    return 0


if __name__ == "__main__":
    sys.exit(serve())
