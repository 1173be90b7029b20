"""OBJ and PLY mesh readers in numpy (no trimesh: this runs inside a stock Blender).

Both return (vertices [V,3] float64, faces [F,3] int64) with vertices in file order and
faces in file order; quads are split into two triangles (a, b, c), (c, d, a) in place (as trimesh did).
Parsing is done by regular expressions and numpy over the whole text or buffer, never by a
Python loop over vertices or faces. Errors name the file and the problem; hostile files (too
large, giant lines, absurd indices, non-finite coordinates) are refused before or while parsing
with bounded memory (core/io/safe_io.py), never with MemoryError or a traceback.
"""

from __future__ import annotations

import os
import re

import numpy as np

from .safe_io import check_line_lengths, read_bounded

# A mesh file is parsed in memory: refuse larger ones before reading (a 1M-vertex OBJ is ~60 MB).
MAX_MESH_BYTES = 1 << 30


class MeshFormatError(ValueError):
    """A mesh file this reader cannot use (the message names the file)."""


def read_mesh(path, reuse: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``reuse``: one dict handed to every frame of a sequence (read_obj_bytes)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: file not found")
    low = path.lower()
    if not low.endswith((".obj", ".ply")):
        raise MeshFormatError(f"{path}: not an .obj or .ply mesh")
    try:
        data = read_bounded(path, MAX_MESH_BYTES, "mesh file")
    except ValueError as exc:
        raise MeshFormatError(str(exc)) from None
    if low.endswith(".obj"):
        v, f = read_obj_bytes(data, path, reuse)
    elif low.endswith(".ply"):
        v, f = read_ply_bytes(data, path)
    else:
        raise MeshFormatError(f"{path}: not an .obj or .ply mesh")
    if len(v) == 0:
        raise MeshFormatError(f"{path}: mesh has no vertices")
    if not np.all(np.isfinite(v)):
        bad = int(np.flatnonzero(~np.isfinite(v).all(1))[0])
        raise MeshFormatError(f"{path}: vertex {bad} has a NaN or infinite coordinate")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise MeshFormatError(f"{path}: face vertex indices outside 0..{len(v) - 1}")
    return v, f


def _triangles(poly: np.ndarray, sizes: np.ndarray, path: str) -> np.ndarray:
    """[P,4] corner indices (the 4th unused for triangles) and each polygon's size (3 or 4)
    → triangles in polygon order, quads as (a, b, c), (c, d, a)."""
    if len(sizes) and not np.isin(sizes, (3, 4)).all():
        bad = int(np.flatnonzero(~np.isin(sizes, (3, 4)))[0])
        raise MeshFormatError(f"{path}: face {bad} has {int(sizes[bad])} corners; only triangles and quads are read")
    per = np.where(sizes == 4, 2, 1)
    first = np.repeat(np.arange(len(sizes)), per)
    second = np.zeros(len(first), bool)
    second[np.cumsum(per)[sizes == 4] - 1] = True  # the (c, d, a) half of each quad
    p = poly[first]
    tri = np.where(second[:, None], p[:, [2, 3, 0]], p[:, :3])
    return tri.astype(np.int64)


# -- OBJ -----------------------------------------------------------------------------------
# Vertex and face lines as "\n" + the line, searched in the text with a newline put before it:
# a pattern that starts with a literal lets the regex engine skip from newline to newline, where
# "^" with re.M tries every byte (2-6x slower on a frame of a mesh sequence).
_OBJ_V = re.compile(rb"\n[ \t]*v[ \t]+(\S+)[ \t]+(\S+)[ \t]+(\S+)")
_OBJ_V_LINE = re.compile(rb"\n[ \t]*v[ \t]")
_OBJ_FIRST_F = re.compile(rb"\n[ \t]*f[ \t]")
_OBJ_F = re.compile(rb"^[ \t]*f[ \t]", re.M)
_C = rb"(-?\d+)(?:/[-\d/]*)?"
_OBJ_TRI_QUAD = re.compile(
    rb"^[ \t]*f[ \t]+" + _C + rb"[ \t]+" + _C + rb"[ \t]+" + _C + rb"(?:[ \t]+" + _C + rb")?[ \t]*(?:#[^\n]*)?\r?$",
    re.M,
)


_OBJ_V_OR_F = re.compile(rb"^[ \t]*([vf])[ \t]", re.M)


def read_obj_bytes(data: bytes, path: str = "<obj>", reuse: dict | None = None):
    """``reuse``: a dict shared by the frames of a sequence. A file whose text from its first
    face line on is byte for byte the last parsed one's, with as many vertices, has its faces
    (negative indices included: as many vertex lines precede each face line): they are not
    parsed again, three quarters of the time a frame of a sequence takes."""
    try:
        check_line_lengths(data, path)
    except ValueError as exc:
        raise MeshFormatError(str(exc)) from None
    lines = b"\n" + data
    coords = _OBJ_V.findall(lines)
    n_v = len(_OBJ_V_LINE.findall(lines))
    if len(coords) != n_v:
        raise MeshFormatError(f"{path}: {n_v - len(coords)} vertex lines hold fewer than 3 coordinates")
    try:
        v = np.array(coords, dtype=np.float64).reshape(-1, 3)
    except ValueError as exc:
        raise MeshFormatError(f"{path}: unreadable vertex coordinates ({exc})") from None
    if not np.all(np.isfinite(v)):
        bad = int(np.flatnonzero(~np.isfinite(v).all(1))[0])
        raise MeshFormatError(f"{path}: vertex {bad} has a NaN or infinite coordinate {v[bad].tolist()}")
    tail = None
    if reuse is not None:
        first = _OBJ_FIRST_F.search(lines)  # at its newline, which data lacks: its line's start in data
        tail = data[first.start() :] if first else b""
        if reuse.get("n_vertices") == len(v) and reuse.get("tail") == tail:
            return v, reuse["faces"]
    f = _obj_faces(data, path, len(v))
    if reuse is not None:
        reuse.update(tail=tail, n_vertices=len(v), faces=f)
    return v, f


def _obj_faces(data: bytes, path: str, n_vertices: int) -> np.ndarray:
    n_lines = len(_OBJ_F.findall(data))
    rows = _OBJ_TRI_QUAD.findall(data)
    if len(rows) != n_lines:
        raise MeshFormatError(
            f"{path}: {n_lines - len(rows)} face lines are neither triangles nor quads "
            "(or are unreadable); only triangles and quads are read"
        )
    if not rows:
        return np.zeros((0, 3), np.int64)
    cells = np.array(rows, dtype=bytes)  # [F,4], the 4th empty for triangles
    sizes = np.where(cells[:, 3] == b"", 3, 4)
    cells[:, 3] = np.where(sizes == 4, cells[:, 3], cells[:, 0])
    if cells.dtype.itemsize > 18:  # (the longest cell) beyond int64, and beyond any vertex count
        raise MeshFormatError(f"{path}: a face names a vertex index with more than 18 digits")
    idx = cells.astype(np.int64)
    if np.any(idx == 0):
        raise MeshFormatError(f"{path}: a face names vertex 0 (OBJ indices start at 1; negative ones count back)")
    # OBJ is 1-based; a negative index counts back from the last vertex defined before its face
    # line (not from the file's last: a file of several objects differs)
    back = n_vertices
    if (idx < 0).any():
        is_v = np.array(_OBJ_V_OR_F.findall(data)) == b"v"  # the v and f lines in file order
        back = np.cumsum(is_v)[~is_v][:, None]
    idx = np.where(idx < 0, idx + back, idx - 1)
    if idx.min() < 0 or idx.max() >= n_vertices:
        raise MeshFormatError(
            f"{path}: face vertex indices outside 1..{n_vertices} (or a negative one before the first vertex line)"
        )
    return _triangles(idx, sizes, path)


# -- PLY -----------------------------------------------------------------------------------
PLY_TYPES = {  # PLY scalar type -> numpy type without byte order (core/io/ply.py reads with it too)
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def _ply_header(data: bytes, path: str):
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MeshFormatError(f"{path}: not a PLY file (no 'ply' magic / 'end_header')")
    body = data.index(b"\n", end) + 1
    fmt, elements = None, []
    for line in data[:end].decode("ascii", "replace").splitlines():  # header lines, a handful
        w = line.split()
        if not w:
            continue
        if w[0] == "format":
            fmt = w[1]
        elif w[0] == "element":
            if len(w) != 3 or not w[2].isdigit():
                raise MeshFormatError(
                    f"{path}: malformed PLY element line {line.strip()!r} (count must be a whole number)"
                )
            elements.append((w[1], int(w[2]), []))
        elif w[0] == "property" and elements:
            if w[1] == "list":
                elements[-1][2].append((w[4], ("list", PLY_TYPES.get(w[2]), PLY_TYPES.get(w[3]))))
            else:
                elements[-1][2].append((w[2], PLY_TYPES.get(w[1])))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshFormatError(f"{path}: unsupported PLY format {fmt!r}")
    for name, _n, props in elements:
        if any(t is None or (isinstance(t, tuple) and None in t) for _p, t in props):
            raise MeshFormatError(f"{path}: element '{name}' has a property of unknown type")
    return fmt, elements, body


def read_ply_bytes(data: bytes, path: str = "<ply>"):
    fmt, elements, pos = _ply_header(data, path)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise MeshFormatError(f"{path}: PLY has no vertex element")
    if fmt == "ascii":
        try:
            check_line_lengths(data[pos:], path)
        except ValueError as exc:
            raise MeshFormatError(str(exc)) from None
        return _ply_ascii(data[pos:], elements, path)
    end = "<" if fmt == "binary_little_endian" else ">"
    v = f = None
    for name, n, props in elements:
        lists = [p for p in props if isinstance(p[1], tuple)]
        if not lists:
            dt = np.dtype([(p, end + t) for p, t in props])
            if pos + dt.itemsize * n > len(data):
                raise MeshFormatError(f"{path}: element '{name}' declares {n} rows, more than the file holds")
            arr = np.frombuffer(data, dt, count=n, offset=pos)
            pos += dt.itemsize * n
            if name == "vertex":
                if not {"x", "y", "z"} <= set(arr.dtype.names):
                    raise MeshFormatError(f"{path}: vertex element lacks x, y, z")
                v = np.stack([arr["x"], arr["y"], arr["z"]], 1).astype(np.float64)
            continue
        if name != "face" or len(props) != 1:
            if name == "face":
                raise MeshFormatError(f"{path}: face element with properties besides its index list")
            break  # an unknown list element after the mesh: nothing we need follows
        _p, (_l, count_t, index_t) = props[0]
        if n == 0:
            f = np.zeros((0, 3), np.int64)
            continue
        if pos + np.dtype(count_t).itemsize > len(data):
            raise MeshFormatError(f"{path}: the face element is cut short")
        k = int(np.frombuffer(data, end + count_t, count=1, offset=pos)[0])
        _check_corners(k, path)
        dt = np.dtype([("n", end + count_t), ("i", end + index_t, (k,))])
        if pos + dt.itemsize * n > len(data):
            raise MeshFormatError(
                f"{path}: the face element is cut short or its polygons differ in size (first has {k} corners)"
            )
        arr = np.frombuffer(data, dt, count=n, offset=pos)
        if (arr["n"] != k).any():
            raise MeshFormatError(f"{path}: faces with different corner counts (first has {k})")
        pos += dt.itemsize * n
        poly = np.zeros((n, 4), np.int64)
        poly[:, :k] = arr["i"][:, :4]
        f = _triangles(poly, np.full(n, k), path)
    if v is None:
        raise MeshFormatError(f"{path}: PLY has no vertex element")
    return v, (np.zeros((0, 3), np.int64) if f is None else f)


def _check_corners(k: int, path: str) -> None:
    """Refuse a first polygon that is not a triangle or a quad before its size shapes an array
    (a forged count would otherwise ask numpy for billions of columns)."""
    if k not in (3, 4):
        raise MeshFormatError(f"{path}: face 0 has {k} corners; only triangles and quads are read")


def _ply_ascii(text: bytes, elements, path):
    lines = text.split(b"\n")
    at = 0
    v = f = None
    for name, n, props in elements:
        block = lines[at : at + n]
        at += n
        if len(block) < n:
            raise MeshFormatError(f"{path}: element '{name}' is cut short ({len(block)} of {n} rows)")
        if name == "vertex":
            cols = [p for p, _t in props]
            if not {"x", "y", "z"} <= set(cols):
                raise MeshFormatError(f"{path}: vertex element lacks x, y, z")
            width = len(cols)
            try:
                arr = np.array(b" ".join(block).split(), dtype=np.float64).reshape(n, width)
            except ValueError:
                raise MeshFormatError(f"{path}: vertex rows do not all hold {width} numbers") from None
            v = arr[:, [cols.index(c) for c in ("x", "y", "z")]]
        elif name == "face":
            if len(props) != 1 or not isinstance(props[0][1], tuple):
                raise MeshFormatError(f"{path}: face element with properties besides its index list")
            if n == 0:
                f = np.zeros((0, 3), np.int64)
                continue
            try:
                k = int(block[0].split()[0])
            except (ValueError, IndexError):
                raise MeshFormatError(f"{path}: the first face row does not start with its corner count") from None
            _check_corners(k, path)
            try:
                arr = np.array(b" ".join(block).split(), dtype=np.int64).reshape(n, k + 1)
            except ValueError:
                raise MeshFormatError(f"{path}: faces with different corner counts (first has {k})") from None
            if (arr[:, 0] != k).any():
                raise MeshFormatError(f"{path}: faces with different corner counts (first has {k})")
            poly = np.zeros((n, 4), np.int64)
            poly[:, :k] = arr[:, 1 : 1 + min(k, 4)]
            f = _triangles(poly, np.full(n, k), path)
    return v, (np.zeros((0, 3), np.int64) if f is None else f)
