"""Bounded readers for files that may be hostile or broken (numpy only: runs inside Blender).

Every check here happens *before* the expensive step: an npz member's npy header is read and
its declared element count bounded before numpy allocates the array; a JSON document's nesting
depth is measured before the recursive parser runs. Failures are ``ValueError`` naming the
file and the problem, never MemoryError or RecursionError.
"""

from __future__ import annotations

import json
import re
import zipfile
import zlib
from contextlib import contextmanager

import numpy as np

__all__ = [
    "MAX_ARRAY_ELEMENTS",
    "MAX_JSON_DEPTH",
    "MAX_TEXT_LINE",
    "check_line_lengths",
    "check_npz",
    "npz_read_errors",
    "json_depth",
    "loads_json",
    "read_bounded",
]

# One array in any file the project reads holds at most 2^27 elements (1 GiB as float64);
# the largest real arrays (FLAME shapedirs 5023x3x400, a 1M-Gaussian avatar's f_rest) are
# far below. A whole npz is bounded at four times that.
MAX_ARRAY_ELEMENTS = 1 << 27
MAX_NPZ_ELEMENTS = 4 * MAX_ARRAY_ELEMENTS
# Deeper JSON than this is refused before parsing (Python's parser recurses per level).
MAX_JSON_DEPTH = 64

# A text file's line (OBJ, ASCII PLY) longer than this is refused before parsing: real lines are
# tens of bytes, and one giant line would become one giant token in the parser.
MAX_TEXT_LINE = 1 << 16

# Object arrays need pickle (refused by np.load(allow_pickle=False) anyway) and structured
# (void) ones are not data any reader here uses: both are refused from the header.
_REFUSED_KINDS = "OV"


def check_npz(
    path, *, max_elements: int = MAX_ARRAY_ELEMENTS, max_total: int = MAX_NPZ_ELEMENTS, allow_text: tuple = ()
) -> dict:
    """Read every member's npy header of the npz ``path`` and refuse, before anything is
    allocated, object or structured members, members that declare more than
    ``max_elements`` elements (``max_total`` over the file), or more bytes than the archive
    stores. Strings (e.g. a JSON blob, FLAME's ``bs_style``) are allowed: the reader decides
    what it uses. ``allow_text`` is accepted for readability at call sites (members that
    are meant to be text). Returns {member name: (shape, dtype)}."""
    out = {}
    total = 0
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable npz archive ({exc})") from None
    with zf:
        for info in zf.infolist():
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            try:
                with zf.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    if version == (1, 0):
                        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
                    elif version in ((2, 0), (3, 0)):
                        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
                    else:
                        raise ValueError(f"unknown npy version {version}")
            except (ValueError, OSError, EOFError, zipfile.BadZipFile, RuntimeError, NotImplementedError) as exc:
                raise ValueError(f"{path}: member '{name}' has no valid npy header ({exc})") from None
            if dtype.kind in _REFUSED_KINDS or dtype.hasobject:
                raise ValueError(f"{path}: member '{name}' has dtype {dtype}; only plain arrays are read")
            count = 1
            for s in shape:
                count *= int(s)  # Python ints: no overflow
            if count > max_elements:
                raise ValueError(
                    f"{path}: member '{name}' declares {count} elements {tuple(shape)}, "
                    f"over the bound of {max_elements}; refused before allocating"
                )
            total += count
            if total > max_total:
                raise ValueError(f"{path}: members declare {total} elements in all, over the bound of {max_total}")
            if count * dtype.itemsize > info.file_size:
                raise ValueError(
                    f"{path}: member '{name}' declares {count * dtype.itemsize} bytes of data but the "
                    f"archive stores {info.file_size}: truncated or forged"
                )
            out[name] = (tuple(shape), dtype)
        # The headers alone leave a damaged member to fail when numpy reads it, with zipfile's
        # error and no file name; reading each member through checks its CRC now (in chunks).
        try:
            bad = zf.testzip()
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as exc:
            raise ValueError(f"{path}: damaged npz archive ({exc})") from None
        if bad is not None:
            name = bad[:-4] if bad.endswith(".npy") else bad
            raise ValueError(f"{path}: member '{name}' is damaged (its CRC does not match)")
    return out


@contextmanager
def npz_read_errors(path):
    """Around reading a checked npz (check_npz): a member that is missing, or JSON text in it
    that does not parse, becomes a ValueError naming the file, as check_npz's own refusals."""
    try:
        yield
    except KeyError as exc:
        what = str(exc.args[0]) if exc.args else ""
        # numpy's own message says which member is missing; a bare key is an entry of a JSON member
        raise ValueError(f"{path}: incomplete: {what if ' ' in what else f'no entry {what!r}'}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: a text member is not valid JSON ({exc})") from None


_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.S)
# Depth change per byte value: +1 for [ {, -1 for ] }.
_BRACKET_STEP = np.zeros(256, np.int8)
_BRACKET_STEP[[ord("["), ord("{")]] = 1
_BRACKET_STEP[[ord("]"), ord("}")]] = -1
# Bytes per vectorised pass of json_depth: its temporaries stay a few MiB whatever the text's
# size (a stream's metadata may be up to 256 MiB; whole-text int64 arrays cost ~24 bytes per byte).
_DEPTH_CHUNK = 1 << 18


def json_depth(data) -> int:
    """Nesting depth of the JSON text ``data`` (str or bytes), without recursion: strings are
    blanked out, then brackets are counted with a cumulative sum, chunk by chunk, each
    chunk's sum starting from the depth the previous one ended at."""
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else bytes(data)
    raw = _JSON_STRING.sub(b'""', raw)
    b = np.frombuffer(raw, np.uint8)
    depth = best = 0
    for c0 in range(0, len(b), _DEPTH_CHUNK):
        run = np.cumsum(_BRACKET_STEP[b[c0 : c0 + _DEPTH_CHUNK]], dtype=np.int64)
        best = max(best, depth + int(run.max()))
        depth += int(run[-1])
    return best


def loads_json(data, source: str = "<json>", max_depth: int = MAX_JSON_DEPTH):
    """``json.loads`` that refuses documents nested deeper than ``max_depth`` with a
    ValueError naming ``source`` (Python's parser would raise RecursionError)."""
    depth = json_depth(data)
    if depth > max_depth:
        raise ValueError(f"{source}: JSON nested {depth} levels deep, over the limit of {max_depth}")
    try:
        return json.loads(data)
    except RecursionError:  # belt and braces: a depth the scanner could not see
        raise ValueError(f"{source}: JSON nested too deeply") from None


def read_bounded(path, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of ``path``, refusing (before reading) a file larger than ``max_bytes``:
    a reader that parses a whole file in memory then needs a bounded multiple of it."""
    import os

    size = os.path.getsize(path)
    if size > max_bytes:
        raise ValueError(f"{path}: {what} of {size} bytes, over the bound of {max_bytes}; refused before reading")
    with open(path, "rb") as fh:
        return fh.read(max_bytes + 1)[:max_bytes]


def check_line_lengths(data: bytes, source: str, max_line: int = MAX_TEXT_LINE) -> None:
    """Refuse text whose longest line exceeds ``max_line`` bytes (vectorised: one scan of the
    newline positions), naming ``source`` and the line."""
    b = np.frombuffer(data, np.uint8)
    ends = np.concatenate([[-1], np.flatnonzero(b == 10), [len(b)]])
    lengths = np.diff(ends) - 1
    if len(lengths) and lengths.max() > max_line:
        k = int(np.argmax(lengths))
        raise ValueError(
            f"{source}: line {k + 1} is {int(lengths[k])} bytes long, over the bound of {max_line}; refused before parsing"
        )


def file_digest(path) -> str:
    """ "sha256:<hex>" of a file's bytes: what a result derived from the file was made from."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return "sha256:" + h.hexdigest()
