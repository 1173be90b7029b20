"""Atomic file writes: write a temporary file beside the target, fsync, then rename.

A crash or an exception mid-write leaves the previous file intact (and no temporary behind).
"""

from __future__ import annotations

import itertools
import os
import re
from contextlib import contextmanager

# Each write's own temporary: two threads of one process writing one path must not share one.
_WRITES = itertools.count()
# What follows ``path.`` in a temporary's name: the writer's pid, and its write number (none in
# the names before per-write numbers). Nothing else: another file is never taken for one.
_TEMP_PART = re.compile(r"([0-9]+)(?:-[0-9]+)?")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists (another user's) or cannot tell: leave its file alone
    return True


def clean_stale_temps(path) -> list:
    """Remove ``path.<pid>-<n>.tmp`` (and older ``path.<pid>.tmp``) files left by writers that were
    killed (their pid is gone); returns the removed paths. A live writer's temporary is never
    touched."""
    path = os.fspath(path)
    folder, base = os.path.split(os.path.abspath(path))
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        if not (name.startswith(base + ".") and name.endswith(".tmp")):
            continue
        part = _TEMP_PART.fullmatch(name[len(base) + 1 : -4])
        pid = int(part[1]) if part else None
        if pid is not None and pid != os.getpid() and not _pid_alive(pid):
            try:
                os.remove(os.path.join(folder, name))
                removed.append(os.path.join(folder, name))
            except OSError:
                pass
    return removed


@contextmanager
def atomic_open(path, mode: str = "wb"):
    """Open a temporary file for writing; on success it replaces `path` in one rename.
    Temporaries of earlier writers of `path` that were killed (pid gone) are removed first."""
    path = os.fspath(path)
    clean_stale_temps(path)
    tmp = f"{path}.{os.getpid()}-{next(_WRITES)}.tmp"
    try:
        with open(tmp, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.remove(tmp)
        if isinstance(exc, OSError) and exc.filename is None:
            exc.filename = path  # a write through the handle names no file: say which one failed
        raise


def atomic_savez(path, **arrays) -> None:
    """np.savez, atomically (no pickle: object arrays are refused here, as the readers refuse
    them). The archive is closed even when a write fails: np.savez leaves it open then, and
    its finaliser later fails on the closed file with a stray "Exception ignored" traceback."""
    import zipfile

    import numpy as np

    with atomic_open(path) as fh:
        archive = zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True)
        try:
            for key, value in arrays.items():
                with archive.open(f"{key}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
        except BaseException:
            try:
                archive.close()  # writes the directory, and fails again on a full disk
            except Exception:
                pass  # the first error is the one to report; close() has let go of the file
            raise
        archive.close()


def os_error_text(exc: OSError, where: str = "writing the output") -> str:
    """One line for a failed read or write: what went wrong and the file (else ``where``)."""
    import errno

    what = {errno.ENOSPC: "disk full", errno.EDQUOT: "disk quota exceeded"}.get(exc.errno, type(exc).__name__)
    return f"{what}: {exc.strerror or exc} ({exc.filename if exc.filename is not None else where})"


def image_format(path) -> str | None:
    """The PIL format that ``path``'s extension names, when PIL can write it (else None)."""
    from PIL import Image

    Image.init()
    fmt = Image.registered_extensions().get(os.path.splitext(os.fspath(path))[1].lower())
    return fmt if fmt in Image.SAVE else None


def atomic_save_image(image, path):
    """Save a PIL ``image`` atomically, in the format ``path``'s extension names (as
    ``Image.save(path)`` picks it): an interrupted write leaves an earlier picture intact."""
    fmt = image_format(path)
    if fmt is None:  # refused before the temporary is made, as Image.save(path) would refuse it
        raise ValueError(f"{path}: not an image extension PIL can write")
    with atomic_open(path, "wb") as fh:
        image.save(fh, format=fmt)
    return path
