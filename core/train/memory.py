"""Process memory settings for training processes (torch tier; nothing here is imported by core/
outside train/).

A training step allocates and frees the same large arrays every iteration: the rasteriser's
projection outputs, splat rows and per-Gaussian gradient rows, the binding's outputs, torch's
autograd buffers (each a few to tens of MB at the paper's scale). With glibc's default malloc
settings many of them come back as fresh pages from the kernel on every step and fault in
again: tens of thousands of page faults per paper-scale step, tens of ms of system CPU
(docs/BENCHMARKS.md, "Freed memory kept by training processes"). Keeping freed memory in the
process for the next step removes most of that.
"""

from __future__ import annotations

import ctypes
import platform

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 << 20  # glibc's largest: blocks up to this come from the heap
TRIM_THRESHOLD = 512 << 20  # free memory at the heap's top kept for reuse


def retain_freed_memory() -> bool:
    """Ask glibc's malloc to serve blocks up to MMAP_THRESHOLD from its heap and to keep up to
    TRIM_THRESHOLD of freed memory there instead of returning it to the kernel. Process-wide, so
    only entry points that own their process call it (scripts/train.py, the add-on's training job
    core/train/jobs.py, the training benchmarks), never library code that may run inside Blender
    or an application. Peak memory is unchanged (the arrays are the same; they are reused rather
    than unmapped and mapped again). Returns whether the settings took effect: False where the C
    library is not glibc (macOS, Windows, musl), which keep their own behaviour."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success; the mmap threshold first, since setting it ends glibc's
    # dynamic adjustment of both thresholds.
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
