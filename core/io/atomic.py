"""Atomic file writes: write a temporary file beside the target, fsync, then rename.

A crash or an exception mid-write leaves the previous file intact (and no temporary behind).
"""

from __future__ import annotations

import os
from contextlib import contextmanager


@contextmanager
def atomic_open(path, mode: str = "wb"):
    """Open a temporary file for writing; on success it replaces `path` in one rename."""
    path = os.fspath(path)
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        with open(tmp, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def atomic_savez(path, **arrays) -> None:
    """np.savez, atomically (no pickle: object arrays are refused by the readers)."""
    import numpy as np

    with atomic_open(path) as fh:
        np.savez(fh, **arrays)
