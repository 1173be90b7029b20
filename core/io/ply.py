"""Standard 3DGS PLY export/import (numpy; plyfile only to read files we did not write).

Layout (binary little-endian, float32, one `vertex` element):
  x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 [f_rest_0 .. f_rest_{3K-1}] opacity scale_0 scale_1 scale_2
  rot_0 rot_1 rot_2 rot_3
(f_rest only for avatars with SH bands: K per channel, all of red's first, as 3DGS writes them)
opacity as a logit, scales as logs, rotation w,x,y,z, colour as SH DC (f_dc = (rgb - 0.5)/C0).
Read by SuperSplat, Spark, gsplat tooling and Blender's PLY importer. Writing needs numpy only,
so export works inside Blender, where plyfile is not installed.
"""

from __future__ import annotations

import os

import numpy as np

from .atomic import atomic_open
from .mesh_io import PLY_TYPES
from ..avatar.avatar import SH_C0

PROPERTIES = (
    "x",
    "y",
    "z",
    "nx",
    "ny",
    "nz",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
)
VERTEX_DTYPE = np.dtype([(name, "<f4") for name in PROPERTIES])


def _properties(k_rest: int) -> tuple:
    i = PROPERTIES.index("opacity")
    return PROPERTIES[:i] + tuple(f"f_rest_{j}" for j in range(3 * k_rest)) + PROPERTIES[i:]


_EPS = 1e-7  # keeps logit(0 or 1) and log(0) finite: PLY readers choke on inf


def _rows(gaussians: dict) -> np.ndarray:
    need = ("means", "quats", "scales", "opacities", "colors")
    missing = [k for k in need if k not in gaussians]
    if missing:
        raise ValueError(f"write_ply: gaussians dict misses {missing}")
    means = np.asarray(gaussians["means"], np.float64).reshape(-1, 3)
    n = len(means)
    quats = np.asarray(gaussians["quats"], np.float64).reshape(n, 4)
    scales = np.asarray(gaussians["scales"], np.float64).reshape(n, 3)
    opac = np.asarray(gaussians["opacities"], np.float64).reshape(n)
    colors = np.asarray(gaussians["colors"], np.float64)
    colors = colors.reshape(n, -1) if n else colors.reshape(0, colors.shape[-1] if colors.ndim == 2 else 3)
    if colors.shape[1] != 3:
        raise ValueError(f"write_ply: colors must be RGB [N,3], got {colors.shape}")
    # The SH DC coefficients themselves when given: from colours, a DC below -0.5/C0 would come
    # back clamped (colours are clamped at 0), which changes the colour once higher bands add in.
    f_dc = gaussians.get("f_dc")
    f_dc = (colors - 0.5) / SH_C0 if f_dc is None else np.asarray(f_dc, np.float64).reshape(n, 3)
    rest = np.asarray(gaussians.get("sh_rest", np.zeros((n, 0, 3))), np.float64)
    if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3:
        raise ValueError(f"write_ply: sh_rest must be [N,K,3], got {rest.shape}")
    for name, arr in (
        ("means", means),
        ("quats", quats),
        ("scales", scales),
        ("opacities", opac),
        ("colors", colors),
        ("f_dc", f_dc),
        ("sh_rest", rest),
    ):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"write_ply: {name} contains NaN or inf")
    qn = np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.where(qn > 0, quats / np.where(qn > 0, qn, 1), np.array([1.0, 0, 0, 0]))
    a = np.clip(opac, _EPS, 1 - _EPS)
    K = rest.shape[1]
    rows = np.zeros(n, np.dtype([(name, "<f4") for name in _properties(K)]))
    with np.errstate(over="ignore"):  # checked below, by field
        for c in range(3):
            for k in range(K):
                rows[f"f_rest_{c * K + k}"] = rest[:, k, c]
        for k, c in enumerate("xyz"):
            rows[c] = means[:, k]
            rows[f"scale_{k}"] = np.log(np.maximum(scales[:, k], 1e-30))
            rows[f"f_dc_{k}"] = f_dc[:, k]
    rows["opacity"] = np.log(a / (1 - a))
    for k in range(4):
        rows[f"rot_{k}"] = quats[:, k]
    # Finite in float64 is not finite in the file's float32 (a mean of 1e39 was written as inf,
    # a scale of 1e39 as a log-scale that read_ply, as other readers, refuses).
    for name in rows.dtype.names:
        col = rows[name].astype(np.float64)
        if not np.all(np.isfinite(col)) or (name.startswith("scale_") and np.any(col > _MAX_LOG_SCALE)):
            raise ValueError(f"write_ply: {name} exceeds float32's range (|value| above 3.4e38)")
    return rows


def ply_header(n: int, k_rest: int = 0) -> bytes:
    lines = (
        ["ply", "format binary_little_endian 1.0", "comment ProgressiveAvatars 3DGS export", f"element vertex {n}"]
        + [f"property float {p}" for p in _properties(k_rest)]
        + ["end_header"]
    )
    return ("\n".join(lines) + "\n").encode("ascii")


def write_ply(path, gaussians: dict) -> int:
    """Write activated Gaussians (as from Avatar.gaussians) as a standard 3DGS PLY, atomically.
    Returns the number of Gaussians written."""
    rows = _rows(gaussians)
    path = os.fspath(path)
    with atomic_open(path) as fh:
        fh.write(ply_header(len(rows), (len(rows.dtype.names) - len(PROPERTIES)) // 3))
        fh.write(rows.tobytes())
    return len(rows)


_PLY_SIZES = {
    "char": 1,
    "int8": 1,
    "uchar": 1,
    "uint8": 1,
    "short": 2,
    "int16": 2,
    "ushort": 2,
    "uint16": 2,
    "int": 4,
    "int32": 4,
    "uint": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}
_MAX_PLY_HEADER = 1 << 16


def _check_ply_header(path: str) -> None:
    """Refuse, before any reader allocates, a header whose element counts are malformed or
    need more bytes than the file holds (``element vertex 1e12`` in a 1 KB file)."""
    size = os.path.getsize(path)
    with open(path, "rb") as fh:
        head = fh.read(_MAX_PLY_HEADER)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (bad magic or no end_header in the first {_MAX_PLY_HEADER} bytes)")
    body = size - (head.find(b"\n", end) + 1 if head.find(b"\n", end) >= 0 else len(head))
    lines = head[:end].decode("ascii", "replace").splitlines()
    binary = any(
        ln.split()[:2] in (["format", "binary_little_endian"], ["format", "binary_big_endian"]) for ln in lines
    )
    need, rows, row_bytes = 0, 0, 0
    for line in lines + ["element _end 0"]:
        parts = line.split()
        if parts and parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise ValueError(f"{path}: malformed PLY element line {line.strip()!r} (count must be a whole number)")
            # Lower bound per row: its scalar bytes (a list at least its count) in binary, a
            # character per row in ASCII.
            need += rows * (max(row_bytes, 1) if binary else 1)
            rows, row_bytes = int(parts[2]), 0
        elif len(parts) >= 3 and parts[0] == "property":
            row_bytes += _PLY_SIZES.get(parts[2] if parts[1] == "list" else parts[1], 1)
    if need > body:
        raise ValueError(
            f"{path}: PLY header declares elements needing at least {need} bytes, the file holds "
            f"{body}: truncated or forged, refused before reading"
        )


def _read_vertices(path: str) -> np.ndarray:
    """The vertex element as a structured array: plyfile when available (any PLY flavour),
    else a numpy parser for vertex-only files (binary either endian, or ascii) with scalar
    vertex properties."""
    _check_ply_header(path)
    try:
        from plyfile import PlyData
    except ImportError:
        PlyData = None
    if PlyData is not None:
        try:
            ply = PlyData.read(path)
        except Exception as exc:  # plyfile raises several types for malformed files
            raise ValueError(f"{path}: not a readable PLY file: {exc}") from None
        if "vertex" not in ply:
            raise ValueError(f"{path}: PLY file has no vertex element")
        return ply["vertex"].data
    types = PLY_TYPES
    formats = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file (bad magic)")
        fmt, count, props, element = None, 0, [], None
        while True:
            line = fh.readline()
            if not line:
                raise ValueError(f"{path}: PLY header has no end_header")
            parts = line.decode("ascii", "replace").split()
            if not parts or parts[0] in ("comment", "obj_info"):
                continue
            if parts[0] == "format":
                fmt = parts[1] if len(parts) > 1 else None
            elif parts[0] == "element":
                # The vertex data are read from the end of the header on: any other element,
                # before or after it, would be read as vertices or left unread.
                if len(parts) < 3 or parts[1] != "vertex" or element is not None:
                    raise ValueError(
                        f"{path}: element {' '.join(parts[1:2]) or '(unnamed)'} besides the vertex element: "
                        "without plyfile only vertex-only PLY files are read"
                    )
                element = parts[1]
                count = int(parts[2])
            elif parts[0] == "property" and element == "vertex":
                if parts[1] == "list" or parts[1] not in types:
                    raise ValueError(f"{path}: unsupported vertex property type {parts[1]!r}")
                props.append((parts[2], types[parts[1]]))
            elif parts[0] == "end_header":
                break
        if fmt not in formats or element != "vertex":
            raise ValueError(
                f"{path}: without plyfile only vertex-only PLYs (binary or ascii) are read, got format {fmt!r}"
            )
        order = formats[fmt]
        if order is not None:  # binary: the records as they lie
            dt = np.dtype([(name, order + t) for name, t in props])
            buf = fh.read(count * dt.itemsize)
            if len(buf) < count * dt.itemsize:
                raise ValueError(f"{path}: truncated: {count} vertices declared, {len(buf) // dt.itemsize} present")
            return np.frombuffer(buf, dt)
        # ascii: one line of numbers per vertex
        try:
            vals = np.array(fh.read().split(), dtype=np.float64)
        except ValueError as exc:
            raise ValueError(f"{path}: ascii PLY body holds something that is not a number ({exc})") from None
        if vals.size < count * len(props):
            raise ValueError(f"{path}: truncated: {count} vertices declared, {vals.size // max(len(props), 1)} present")
        vals = vals[: count * len(props)].reshape(count, len(props))
        out = np.empty(count, np.dtype([(name, "<" + t) for name, t in props]))
        for i, (name, _) in enumerate(props):
            out[name] = vals[:, i]
        return out


# exp() of a log-scale above this overflows float32: the scale would be inf.
_MAX_LOG_SCALE = float(np.log(np.finfo(np.float32).max))


def _check_finite(path, v, names):
    """Refuse NaN/inf fields (and log-scales whose scale overflows float32), naming the first
    bad vertex: one such splat turns a whole preview, render or export into garbage."""
    # Normals are unused and quaternions are made unit (or identity) on reading.
    skip = ("nx", "ny", "nz", "rot_0", "rot_1", "rot_2", "rot_3")
    fields = [k for k in names if k.startswith("f_rest_") or (k in PROPERTIES and k not in skip)]
    for k in fields:
        x = np.asarray(v[k], np.float64)
        if k == "opacity":  # ±inf is a valid logit (opacity 0 or 1); NaN is not
            bad = np.isnan(x)
        elif k.startswith("scale_"):
            bad = ~np.isfinite(x) | (x > _MAX_LOG_SCALE)
        else:
            bad = ~np.isfinite(x)
        if bad.any():
            i = int(np.argmax(bad))
            what = "a log-scale whose scale overflows float32" if np.isfinite(x[i]) else "not finite"
            raise ValueError(
                f"{path}: vertex {i} of {len(x)}: {k} = {x[i]!r} is {what} ({int(bad.sum())} such vertices)"
            )


def read_ply(path) -> dict:
    """A 3DGS PLY back as activated Gaussians: means, quats (wxyz, unit), scales, opacities,
    colors (RGB = max(0.5 + C0·f_dc, 0)), f_dc as stored (what write_ply writes back) and
    sh_rest [N,K,3] (K = 0 without f_rest_* fields)."""
    path = os.fspath(path)
    v = _read_vertices(path)
    names = v.dtype.names or ()
    need = [p for p in PROPERTIES if p not in ("nx", "ny", "nz")]
    missing = [p for p in need if p not in names]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    col = lambda *ks: np.stack([np.asarray(v[k], np.float64) for k in ks], axis=1)  # noqa: E731
    quats = col("rot_0", "rot_1", "rot_2", "rot_3")
    big = np.abs(quats).max(axis=1, keepdims=True)  # pre-scaled: a norm of 1e200 must not overflow
    quats = np.where(np.isfinite(big) & (big > 0), quats / np.where(np.isfinite(big) & (big > 0), big, 1), 0.0)
    qn = np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.where(qn > 0, quats / np.where(qn > 0, qn, 1), np.array([1.0, 0, 0, 0]))
    n_rest = sum(1 for nm in names if nm.startswith("f_rest_"))
    if n_rest % 3 or any(f"f_rest_{j}" not in names for j in range(n_rest)):
        raise ValueError(f"{path}: f_rest_* properties must be f_rest_0..f_rest_(3K-1), got {n_rest}")
    K = n_rest // 3
    _check_finite(path, v, names)
    rest = (
        np.stack([col(*(f"f_rest_{c * K + k}" for c in range(3))) for k in range(K)], axis=1)
        if K
        else np.zeros((len(v), 0, 3))
    )
    return {
        "sh_rest": rest.astype(np.float32),
        "means": col("x", "y", "z").astype(np.float32),
        "quats": quats.astype(np.float32),
        "scales": np.exp(col("scale_0", "scale_1", "scale_2")).astype(np.float32),
        "opacities": (1.0 / (1.0 + np.exp(-np.asarray(v["opacity"], np.float64)))).astype(np.float32),
        "colors": np.maximum(0.5 + SH_C0 * col("f_dc_0", "f_dc_1", "f_dc_2"), 0.0).astype(np.float32),
        "f_dc": col("f_dc_0", "f_dc_1", "f_dc_2").astype(np.float32),
    }


# -- static splats in the Blender preview -------------------------------------------------
def importance_order(gaussians: dict) -> np.ndarray:
    """Gaussian indices, most important first, for a PLY that has no stream order: opacity
    times ellipsoid volume (what a splat contributes to the image, up to its footprint);
    ties keep file order."""
    s = np.asarray(gaussians["scales"], np.float64)
    # Volumes in log space: products of three tiny scales underflow float32.
    key = np.log(np.maximum(np.asarray(gaussians["opacities"], np.float64), 1e-12)) + np.log(np.maximum(s, 1e-30)).sum(
        axis=1
    )
    return np.argsort(-key, kind="stable")


def splat_ply_bytes(count: int, k_rest: int) -> int:
    """File size of a PLY holding ``count`` Gaussians with ``k_rest`` SH coefficients per
    channel (what a budget of ``count`` would cost on disk)."""
    return len(ply_header(count, k_rest)) + count * 4 * (len(PROPERTIES) + 3 * k_rest)
