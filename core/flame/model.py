"""FLAME head model: loading the user's own model file and the forward pass (numpy).

The model file (``generic_model.pkl`` of FLAME 2020, ``flame2023.pkl``, or an ``.npz`` with
the same keys) belongs to the user: it is never shipped or downloaded. The pickles date from
Python 2 and hold numpy arrays, a scipy.sparse ``J_regressor`` and, in FLAME 2020, chumpy
``Ch`` arrays. Unpickling runs whatever callables a file names, so a tampered model file
could run code; :func:`load_flame_model` therefore uses a restricted unpickler that resolves
only array-reconstruction globals and stand-ins for scipy.sparse and chumpy classes (neither
package is imported), and refuses every other global before it can be called.

Forward pass: standard FLAME/SMPL linear blend skinning with pose correctives, batched over
T frames. Joints: 0 global (``rotation``), 1 neck, 2 jaw, 3 and 4 eyes (``eyes_pose`` holds
both, 3 + 3 values). ``static_offset`` / ``dynamic_offset`` are per-vertex offsets added to the
template before skinning (VHAP / GaussianAvatars), ``translation`` is added after.

numpy only: this module runs inside Blender. The torch twin is ``flame_torch.py``.
"""

from __future__ import annotations

import _compat_pickle
import io
import os
import pickle
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..io.safe_io import MAX_ARRAY_ELEMENTS, check_npz
from ..geometry.rotations import axis_angle_to_matrix  # noqa: F401

__all__ = [
    "FlameModelError",
    "UnsafePickleError",
    "FlameModel",
    "load_flame_model",
    "axis_angle_to_matrix",
    "flame_forward",
    "FLAME_PARAM_KEYS",
    "POSE_WIDTHS",
]

# Shape components come first in FLAME's shapedirs; 300 in every released model.
DEFAULT_N_SHAPE = 300
# Frames per chunk in the forward pass: bounds the [T,V,12] skinning temporary (~30 MB at
# FLAME size) without a per-frame Python loop.
_CHUNK = 64

FLAME_PARAM_KEYS = (
    "shape",
    "expr",
    "rotation",
    "neck_pose",
    "jaw_pose",
    "eyes_pose",
    "translation",
    "static_offset",
    "dynamic_offset",
)

# The joint poses' keys and widths, in FLAME's joint order (global, neck, jaw, both eyes).
POSE_WIDTHS = (("rotation", 3), ("neck_pose", 3), ("jaw_pose", 3), ("eyes_pose", 6))


class FlameModelError(ValueError):
    """A FLAME model file is missing, malformed or inconsistent."""


class UnsafePickleError(FlameModelError, pickle.UnpicklingError):
    """A pickle asked for a global outside the allow-list (it could run code)."""


# --------------------------------------------------------------------------------------
# Restricted unpickling


class _Captured:
    """Stand-in for a foreign class (chumpy, scipy.sparse): records the pickled state and
    runs none of the original class's code."""

    origin = "?"

    def __new__(cls, *args, **kwargs):
        obj = object.__new__(cls)
        obj.args = args
        obj.state = None
        return obj

    def __setstate__(self, state):
        self.state = state

    def __repr__(self):
        return f"<captured {self.origin}>"


class _ChumpyStub(_Captured):
    pass


class _SparseStub(_Captured):
    pass


_STUB_CACHE: dict[tuple[str, str], type] = {}


def _stub_class(base: type, module: str, name: str) -> type:
    key = (module, name)
    cls = _STUB_CACHE.get(key)
    if cls is None:
        cls = type(f"Captured_{name}", (base,), {"origin": f"{module}.{name}"})
        _STUB_CACHE[key] = cls
    return cls


# Array payloads are rebuilt here from checked parts, never by numpy's own unpickling: a
# pickled ``numpy.dtype`` state can set the object flag so that raw bytes are read as
# object pointers (memory corruption), and ``_reconstruct``/``scalar`` accept any dtype.
# So ``numpy.dtype`` resolves to a recorder that becomes a plain numeric dtype only, arrays
# are built from their raw bytes after the shape and byte count are checked, and sizes are
# bounded (safe_io.MAX_ARRAY_ELEMENTS) before anything is allocated.
_DTYPE_SPEC = re.compile(r"^[<>|=]?(b1|\?|[iuf][1248]|f16|[bBhHiIlLqQefdg])$")
_MAX_DIMS = 32


class _DtypeSpec:
    """What ``numpy.dtype(spec, align, copy)`` plus its BUILD state asked for."""

    def __init__(self, spec=None, align=False, copy=False):
        self.spec = spec.decode("latin1") if isinstance(spec, bytes) else spec
        self.state = None

    def __setstate__(self, state):
        self.state = state

    def resolve(self) -> np.dtype:
        spec = self.spec
        if not isinstance(spec, str) or not _DTYPE_SPEC.match(spec):
            raise pickle.UnpicklingError(f"array dtype {spec!r} refused: only plain numeric dtypes are read")
        dt = np.dtype(spec)
        st = self.state
        if st is not None:
            # (version, byteorder, subdescr, names, fields, elsize, alignment, flags): only the
            # byte order is taken; anything structured or flagged is refused, not trusted.
            if not isinstance(st, tuple) or len(st) < 2 or any(x is not None for x in st[2:5]):
                raise pickle.UnpicklingError(f"array dtype {spec!r} with a structured or unknown state refused")
            order = st[1].decode("latin1") if isinstance(st[1], bytes) else st[1]
            if order in ("<", ">"):
                dt = dt.newbyteorder(order)
            elif order not in ("|", "="):
                raise pickle.UnpicklingError(f"array dtype byte order {order!r} refused")
        if dt.kind not in "biuf":
            raise pickle.UnpicklingError(f"array dtype {dt} refused: only plain numeric dtypes are read")
        return dt


def _as_dtype(d) -> np.dtype:
    if isinstance(d, _DtypeSpec):
        return d.resolve()
    if isinstance(d, (str, bytes)):
        return _DtypeSpec(d).resolve()
    raise pickle.UnpicklingError(f"array payload with a non-dtype descriptor {type(d).__name__}")


def _checked_shape(shape) -> tuple:
    if isinstance(shape, int):
        shape = (shape,)
    if (
        not isinstance(shape, tuple)
        or len(shape) > _MAX_DIMS
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)
    ):
        raise pickle.UnpicklingError(f"array shape {shape!r} refused")
    count = 1
    for s in shape:
        count *= s
    if count > MAX_ARRAY_ELEMENTS:
        raise pickle.UnpicklingError(f"array of {count} elements refused (bound {MAX_ARRAY_ELEMENTS})")
    return shape


def _array_from_bytes(raw, dtype: np.dtype, shape: tuple, fortran: bool) -> np.ndarray:
    if isinstance(raw, str):  # Python 2 str payloads, decoded as latin1
        raw = raw.encode("latin1")
    if not isinstance(raw, (bytes, bytearray, memoryview)):
        raise pickle.UnpicklingError(f"array payload of type {type(raw).__name__} refused (object arrays are not read)")
    raw = bytes(raw)
    want = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if len(raw) != want:
        raise pickle.UnpicklingError(f"array payload holds {len(raw)} bytes, shape {shape} of {dtype} needs {want}")
    return np.frombuffer(raw, dtype=dtype).reshape(shape, order="F" if fortran else "C").copy()


class _NdarrayToken:
    """Stands for ``numpy.ndarray`` in a pickle: only a marker for ``_reconstruct``, not callable."""


class _ArrayStub:
    """An ndarray being unpickled: ``_reconstruct`` makes it, BUILD hands it the state, from
    which a checked plain array is built at once."""

    def __init__(self):
        self.array = None

    def __setstate__(self, state):
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise pickle.UnpicklingError("array state refused")
        shape, dtype, fortran, raw = state[-4:]
        self.array = _array_from_bytes(raw, _as_dtype(dtype), _checked_shape(shape), bool(fortran))


def _np_frombuffer(buf, dtype, shape, order):
    # What numpy's own pickle protocol-5 helper does, minus anything but plain arrays.
    return _array_from_bytes(buf, _as_dtype(dtype), _checked_shape(shape), order == "F")


def _np_reconstruct(subtype, shape, dtype):
    if subtype is not _NdarrayToken:
        raise pickle.UnpicklingError(f"array reconstruction of a non-ndarray type {subtype!r}")
    return _ArrayStub()


def _np_scalar(dtype, data=None):
    dt = _as_dtype(dtype)
    arr = _array_from_bytes(data if data is not None else b"", dt, (), False)
    return arr[()]


def _codecs_encode(obj, encoding="utf-8", errors="strict"):
    # Python 3 protocol-2 pickles spell bytes as _codecs.encode(str, 'latin1').
    if not isinstance(obj, str) or str(encoding).lower().replace("-", "") not in ("latin1", "ascii", "utf8"):
        raise pickle.UnpicklingError("_codecs.encode used for something other than bytes")
    return obj.encode(encoding, errors)


def _copyreg_reconstructor(cls, base, state):
    # Protocol 0/1 spelling of "make an empty instance": only our stand-ins may be made.
    if not (isinstance(cls, type) and issubclass(cls, _Captured)) or base is not object or state is not None:
        raise pickle.UnpicklingError(f"copy_reg._reconstructor on a disallowed type {cls!r}")
    return cls.__new__(cls)


_NUMPY_MODULES = ("numpy.core.multiarray", "numpy._core.multiarray")
_SPARSE_NAME = re.compile(r"^(csc|csr|coo)_(matrix|array)$")


def _allowed_global(module: str, name: str):
    """The object a pickle may reference as ``module.name``, or None when refused."""
    if module in _NUMPY_MODULES:
        return {"_reconstruct": _np_reconstruct, "scalar": _np_scalar}.get(name)
    if module in ("numpy.core.numeric", "numpy._core.numeric") and name == "_frombuffer":
        return _np_frombuffer
    if module == "numpy":
        return {"ndarray": _NdarrayToken, "dtype": _DtypeSpec}.get(name)
    if module == "_codecs" and name == "encode":
        return _codecs_encode
    if module in ("copy_reg", "copyreg") and name == "_reconstructor":
        return _copyreg_reconstructor
    if module in ("__builtin__", "builtins"):
        return {"object": object, "set": set, "frozenset": frozenset, "complex": complex}.get(name)
    if module == "collections" and name == "OrderedDict":
        from collections import OrderedDict

        return OrderedDict
    if module.startswith("scipy.sparse") and _SPARSE_NAME.match(name):
        return _stub_class(_SparseStub, module, name)
    if (module == "chumpy" or module.startswith("chumpy.")) and name.isidentifier():
        return _stub_class(_ChumpyStub, module, name)
    return None


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file, source: str):
        super().__init__(file, encoding="latin1")
        self._source = source

    def find_class(self, module, name):
        # Report and check Python 3 spellings (__builtin__ -> builtins, copy_reg -> copyreg).
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
        obj = _allowed_global(module, name)
        if obj is None:
            raise UnsafePickleError(
                f"{self._source}: refused to load global '{module}.{name}': a FLAME model pickle "
                "may only hold numpy arrays, scipy.sparse matrices and chumpy arrays; anything "
                "else could run code on load. If the file is genuine, convert it to .npz "
                "(FlameModel.save_npz) on a trusted machine."
            )
        return obj

    def persistent_load(self, pid):
        raise UnsafePickleError(f"{self._source}: refused a persistent id in the pickle")


def restricted_load(path: str):
    """Unpickle ``path`` with the allow-list (Python 2 strings decoded as latin1)."""
    with open(path, "rb") as f:
        data = f.read()
    try:
        return _RestrictedUnpickler(io.BytesIO(data), path).load()
    except UnsafePickleError:
        raise
    except Exception as exc:  # truncated or corrupt pickles raise a zoo of types
        raise FlameModelError(f"{path}: not a readable FLAME pickle ({type(exc).__name__}: {exc})") from exc


def _sparse_to_dense(stub: _SparseStub, source: str, key: str, depth: int) -> np.ndarray:
    st = stub.state if isinstance(stub.state, dict) else {}
    shape = st.get("_shape", st.get("shape"))
    kind = stub.origin.rsplit(".", 1)[-1][:3]
    if shape is None:
        raise FlameModelError(f"{source}: sparse '{key}' ({stub.origin}) has no shape in its pickled state")
    # The shape is checked before the dense array exists: a forged (1e6, 1e6) is refused here.
    try:
        shape = tuple(int(s) for s in shape)
    except (TypeError, ValueError, OverflowError):
        raise FlameModelError(f"{source}: sparse '{key}' ({stub.origin}) has a malformed shape") from None
    if len(shape) != 2 or min(shape) < 0 or shape[0] * shape[1] > MAX_ARRAY_ELEMENTS:
        raise FlameModelError(
            f"{source}: sparse '{key}' ({stub.origin}) declares shape {shape}: refused "
            f"(two dimensions, at most {MAX_ARRAY_ELEMENTS} elements dense)"
        )
    part = lambda name: _to_array(st[name], source, f"{key}.{name}", depth + 1)  # noqa: E731
    try:
        if kind in ("csc", "csr"):
            data, indices, indptr = part("data"), part("indices").astype(np.int64), part("indptr").astype(np.int64)
            n_major = shape[1] if kind == "csc" else shape[0]
            if (
                indptr.shape != (n_major + 1,)
                or indptr[0] != 0
                or np.any(np.diff(indptr) < 0)
                or indptr[-1] != len(indices)
                or len(indices) != len(data)
            ):
                raise ValueError("inconsistent indptr / indices / data")
            major = np.repeat(np.arange(n_major), np.diff(indptr))
            rows, cols = (indices, major) if kind == "csc" else (major, indices)
        else:
            coords = st.get("coords")
            rows, cols = coords if coords is not None else (st["row"], st["col"])
            rows = _to_array(rows, source, key, depth + 1).astype(np.int64)
            cols = _to_array(cols, source, key, depth + 1).astype(np.int64)
            data = part("data")
        data = data.astype(np.float64)
        if not (rows.shape == cols.shape == data.shape and rows.ndim == 1):
            raise ValueError("row, column and data lengths differ")
        if len(rows) and (rows.min() < 0 or rows.max() >= shape[0] or cols.min() < 0 or cols.max() >= shape[1]):
            raise ValueError(f"an index lies outside the shape {shape}")
        out = np.zeros(shape, dtype=np.float64)
        np.add.at(out, (rows, cols), data)  # duplicates sum, as in scipy
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise FlameModelError(f"{source}: sparse '{key}' ({stub.origin}) is malformed: {exc}") from exc
    return out


_MAX_NESTING = 40  # stand-ins inside stand-ins, lists inside lists: more is a hostile file


def _list_elements(value, source: str, key: str) -> int:
    """Leaf count of nested lists/tuples, shared sublists counted once per reference but
    walked once (memo), refusing self-references and nesting deeper than _MAX_NESTING."""
    memo: dict[int, int] = {}
    stack = [(value, 0, False)]
    active: set[int] = set()
    while stack:
        node, depth, done = stack.pop()
        if done:
            active.discard(id(node))
            memo[id(node)] = sum(memo[id(c)] if isinstance(c, (list, tuple)) else 1 for c in node)
            if memo[id(node)] > MAX_ARRAY_ELEMENTS:
                raise FlameModelError(f"{source}: '{key}' holds more than {MAX_ARRAY_ELEMENTS} list elements")
            continue
        if id(node) in memo:
            continue
        if id(node) in active:
            raise FlameModelError(f"{source}: '{key}' is a list that contains itself")
        if depth > _MAX_NESTING:
            raise FlameModelError(f"{source}: '{key}' nests lists more than {_MAX_NESTING} deep")
        active.add(id(node))
        stack.append((node, depth, True))
        stack.extend((c, depth + 1, False) for c in node if isinstance(c, (list, tuple)))
    return memo[id(value)]


def _to_array(value, source: str, key: str, depth: int = 0):
    """Plain numeric numpy array from an unpickled value (array, chumpy stand-in, sparse
    stand-in, nested lists of numbers); anything else is refused with FlameModelError."""
    if depth > _MAX_NESTING:
        raise FlameModelError(f"{source}: '{key}' nests stand-ins more than {_MAX_NESTING} deep (or refers to itself)")
    if isinstance(value, _ArrayStub):
        if value.array is None:
            raise FlameModelError(f"{source}: '{key}' is an array without its data")
        return value.array
    if isinstance(value, _SparseStub):
        return _sparse_to_dense(value, source, key, depth)
    if isinstance(value, _ChumpyStub):
        st = value.state
        if isinstance(st, dict) and "x" in st:
            return _to_array(st["x"], source, key, depth + 1)
        raise FlameModelError(
            f"{source}: '{key}' is a chumpy expression ({value.origin}) rather than a plain chumpy "
            "array; it cannot be evaluated without chumpy. Convert the model to .npz with chumpy "
            "installed (np.savez with each array as np.asarray(...))."
        )
    if isinstance(value, np.ndarray):  # from an npz (already checked) or a protocol-5 payload
        arr = value
    elif isinstance(value, (list, tuple)):
        _list_elements(value, source, key)
        try:
            arr = np.asarray(value)
        except (ValueError, TypeError, RecursionError) as exc:
            raise FlameModelError(f"{source}: '{key}' is not a numeric array ({type(exc).__name__})") from None
    elif isinstance(value, (bool, int, float, np.generic)):
        arr = np.asarray(value)
    else:
        raise FlameModelError(f"{source}: '{key}' holds a {type(value).__name__}, not a numeric array")
    if arr.dtype.kind not in "biuf":
        raise FlameModelError(f"{source}: '{key}' is not a numeric array (dtype {arr.dtype})")
    return arr


# --------------------------------------------------------------------------------------
# Model


@dataclass
class FlameModel:
    """A FLAME-like linear blend skinning model (arrays float64 unless noted).

    v_template [V,3]; faces int32 [F,3]; shapedirs [V,3,S+E] (first ``n_shape`` shape,
    the rest expression); posedirs [V,3,9*(J-1)]; J_regressor [J,V] dense; weights [V,J];
    parents int64 [J] (parents[0] = -1, parents[j] < j).
    """

    v_template: np.ndarray
    faces: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    J_regressor: np.ndarray
    weights: np.ndarray
    parents: np.ndarray
    n_shape: int
    source: str = ""

    def __post_init__(self):
        src = self.source or "FLAME model"
        self.v_template = np.ascontiguousarray(self.v_template, np.float64)
        V = self.v_template.shape[0] if self.v_template.ndim == 2 else -1
        if self.v_template.ndim != 2 or self.v_template.shape[1] != 3:
            raise FlameModelError(f"{src}: v_template must be [V,3], got {self.v_template.shape}")
        faces = np.asarray(self.faces)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise FlameModelError(f"{src}: faces must be [F,3], got {faces.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= V):
            raise FlameModelError(f"{src}: faces index outside 0..{V - 1}")
        self.faces = faces.astype(np.int32)
        sd = np.asarray(self.shapedirs, np.float64)
        if sd.ndim == 2 and sd.shape[0] == V * 3:
            sd = sd.reshape(V, 3, -1)
        if sd.ndim != 3 or sd.shape[:2] != (V, 3):
            raise FlameModelError(f"{src}: shapedirs must be [V,3,K] with V={V}, got {sd.shape}")
        self.shapedirs = sd
        self.J_regressor = np.asarray(self.J_regressor, np.float64)
        J = self.J_regressor.shape[0]
        if self.J_regressor.shape != (J, V):
            raise FlameModelError(f"{src}: J_regressor must be [J,{V}], got {self.J_regressor.shape}")
        self.weights = np.asarray(self.weights, np.float64)
        if self.weights.shape != (V, J):
            raise FlameModelError(f"{src}: weights must be [{V},{J}], got {self.weights.shape}")
        pd = np.asarray(self.posedirs, np.float64)
        P = 9 * (J - 1)
        if pd.ndim == 2 and pd.shape == (P, V * 3):  # some exports store the flattened transpose
            pd = pd.T.reshape(V, 3, P)
        if pd.shape != (V, 3, P):
            raise FlameModelError(f"{src}: posedirs must be [{V},3,{P}] (9*(J-1)), got {pd.shape}")
        self.posedirs = pd
        parents = np.asarray(self.parents).astype(np.int64).reshape(-1)
        if parents.shape != (J,):
            raise FlameModelError(f"{src}: kintree/parents must list {J} joints, got {parents.shape}")
        parents = parents.copy()
        parents[0] = -1
        if J > 1 and np.any(parents[1:] >= np.arange(1, J)) or np.any(parents[1:] < 0):
            raise FlameModelError(f"{src}: joint parents must precede their children, got {parents.tolist()}")
        self.parents = parents
        K = self.shapedirs.shape[2]
        self.n_shape = int(min(max(int(self.n_shape), 0), K))
        for name in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise FlameModelError(f"{src}: {name} contains NaN or inf")
        # Flattened bases so blendshapes are one matrix product per chunk of frames.
        self._shape_basis = np.ascontiguousarray(self.shapedirs.reshape(V * 3, K).T)  # [K, V*3]
        self._pose_basis = np.ascontiguousarray(pd.reshape(V * 3, P).T)  # [P, V*3]

    @property
    def n_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def n_joints(self) -> int:
        return self.J_regressor.shape[0]

    @property
    def n_expr(self) -> int:
        return self.shapedirs.shape[2] - self.n_shape

    def save_npz(self, path: str) -> None:
        """Write the model as a plain .npz (no pickles): the safe form to keep around."""
        kintree = np.stack([self.parents, np.arange(self.n_joints)]).astype(np.int64)
        np.savez(
            path,
            v_template=self.v_template,
            f=self.faces,
            shapedirs=self.shapedirs,
            posedirs=self.posedirs,
            J_regressor=self.J_regressor,
            weights=self.weights,
            kintree_table=kintree,
            n_shape=np.int64(self.n_shape),
        )

    def forward(self, **params) -> np.ndarray:
        """Vertices float32 [T,V,3]; see :func:`flame_forward` for the parameters."""
        return flame_forward(self, **params)


def _first(d: dict, *names):
    for n in names:
        if n in d:
            return d[n]
    return None


def _model_from_mapping(d: dict, source: str, n_shape: int | None) -> FlameModel:
    missing = [k for k in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights") if k not in d]
    if _first(d, "f", "faces") is None:
        missing.append("f")
    if _first(d, "kintree_table", "parents") is None:
        missing.append("kintree_table")
    if missing:
        raise FlameModelError(
            f"{source}: not a FLAME model, missing keys {missing} "
            f"(has {sorted(k for k in d if isinstance(k, str))[:40]})"
        )
    arr = {k: _to_array(d[k], source, k) for k in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights")}
    faces = _to_array(_first(d, "f", "faces"), source, "f")
    if "kintree_table" in d:
        kt = _to_array(d["kintree_table"], source, "kintree_table")
        if kt.ndim != 2 or kt.shape[0] != 2:
            raise FlameModelError(f"{source}: kintree_table must be [2,J], got {kt.shape}")
        # Row 0 holds parents (root: uint32 max or -1), row 1 joint ids in any order.
        if not np.array_equal(np.sort(kt[1]), np.arange(kt.shape[1])):
            raise FlameModelError(
                f"{source}: kintree_table's second row must number the joints 0..{kt.shape[1] - 1} once each, "
                f"got {kt[1].tolist()}"
            )
        order = np.argsort(kt[1])
        parents = kt[0][order].astype(np.int64)
    else:
        parents = _to_array(d["parents"], source, "parents").astype(np.int64)
    if n_shape is None:
        stored = d.get("n_shape")
        n_shape = int(np.asarray(_to_array(stored, source, "n_shape"))) if stored is not None else DEFAULT_N_SHAPE
    return FlameModel(
        arr["v_template"],
        faces,
        arr["shapedirs"],
        arr["posedirs"],
        arr["J_regressor"],
        arr["weights"],
        parents,
        n_shape,
        source,
    )


def load_flame_model(path, n_shape: int | None = None) -> FlameModel:
    """Load the user's FLAME model: ``.pkl`` (restricted unpickler) or ``.npz``.

    ``n_shape`` is where shapedirs splits into shape and expression components (default:
    the ``n_shape`` stored in an npz, else 300, capped at the number of components).
    """
    if isinstance(path, FlameModel):
        return path
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(
            f"{path}: FLAME model file not found (FLAME is not shipped; point to your own "
            "generic_model.pkl / flame2023.pkl)"
        )
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic.startswith(b"PK"):
        try:
            check_npz(path)  # headers first: nothing huge or non-numeric is allocated
            with np.load(path, allow_pickle=False) as z:
                d = {k: z[k] for k in z.files}
        except ValueError as exc:
            raise FlameModelError(
                f"{path}: npz arrays must be plain numeric arrays (no pickled objects): {exc}"
            ) from exc
    else:
        d = restricted_load(path)
        if not isinstance(d, dict):
            raise FlameModelError(f"{path}: expected a dict of arrays at the top of the pickle, got {type(d).__name__}")
    try:
        return _model_from_mapping(d, path, n_shape)
    except (RecursionError, MemoryError) as exc:  # backstop: the checks above should come first
        raise FlameModelError(
            f"{path}: refused, the model's arrays are too large or too deeply nested ({type(exc).__name__})"
        ) from None


# --------------------------------------------------------------------------------------
# Forward


def _frames_of(arrays: dict) -> int:
    T = 1
    for k, v in arrays.items():
        if v.shape[0] != 1:
            if T not in (1, v.shape[0]):
                raise ValueError(f"FLAME parameters disagree on the number of frames ({k}: {v.shape[0]} vs {T})")
            T = v.shape[0]
    return T


def _coeffs(x, n_model: int, T: int, what: str) -> np.ndarray:
    """[T, n_model] from [n] / [1,n] / [T,n] coefficients: zero-padded, or truncated when
    the dropped coefficients are zero (a model with fewer components)."""
    out = np.zeros((T, n_model))
    if x is None:
        return out
    x = np.asarray(x, np.float64)
    x = x.reshape(1, -1) if x.ndim <= 1 else x.reshape(x.shape[0], -1)
    if x.shape[0] not in (1, T):
        raise ValueError(f"{what}: expected 1 or {T} rows of coefficients, got {x.shape[0]}")
    n = min(n_model, x.shape[1])
    if x.shape[1] > n_model and np.any(x[:, n_model:] != 0):
        last = int(np.flatnonzero(np.any(x != 0, axis=0))[-1]) + 1
        raise ValueError(
            f"{what} has non-zero coefficients up to number {last} (of {x.shape[1]}) but the model has only "
            f"{n_model} {what} components"
        )
    out[:, :n] = x[:, :n]
    return out


def _pose(x, T: int, width: int, what: str) -> np.ndarray:
    if x is None:
        return np.zeros((T, width))
    x = np.asarray(x, np.float64)
    if not np.size(x):
        x = np.zeros((1, width))
    # Rows are frames: [T,6] or [T,2,3] eyes; one frame may be [6], [2,3] or [J,3] (its first
    # axis then is not the frame count). Never rows re-cut from other rows: with two frames a
    # [2,3] eyes_pose is two frames of the wrong width, not one frame for both.
    if x.ndim <= 1 or (x.size == width and x.shape[0] != T):
        x = x.reshape(1, -1)
    else:
        x = x.reshape(x.shape[0], -1)
    if x.shape[1] != width:
        raise ValueError(f"{what}: expected {width} values per frame, got shape {x.shape}")
    if x.shape[0] not in (1, T):
        raise ValueError(f"{what}: expected 1 or {T} rows of {width}, got {x.shape}")
    return np.broadcast_to(x, (T, width))


def _offset(x, T: int, V: int, what: str):
    if x is None:
        return None
    x = np.asarray(x, np.float64)
    x = x.reshape((-1,) + x.shape[-2:]) if x.ndim >= 2 else x
    if x.ndim != 3 or x.shape[1:] != (V, 3) or x.shape[0] not in (1, T):
        hint = (
            " (GaussianAvatars' teeth-augmented FLAME has 5143 vertices; plain FLAME 5023)"
            if x.ndim == 3 and x.shape[1] != V
            else ""
        )
        raise ValueError(f"{what}: expected [1|T,{V},3], got {x.shape}{hint}")
    return x


def prepare_params(
    model: FlameModel,
    shape=None,
    expr=None,
    rotation=None,
    neck_pose=None,
    jaw_pose=None,
    eyes_pose=None,
    translation=None,
    static_offset=None,
    dynamic_offset=None,
    pose=None,
):
    """Normalise FLAME parameters to float64 arrays with a leading frame axis T.

    Returns (T, betas [T,K], full pose [T,J,3], translation [T,3], offsets [1|T,V,3] or None).
    ``pose`` [T,J*3] overrides the named joint poses (for models whose joints differ from FLAME's).
    """
    V, J = model.n_vertices, model.n_joints
    raw = {
        "shape": shape,
        "expr": expr,
        "rotation": rotation,
        "neck_pose": neck_pose,
        "jaw_pose": jaw_pose,
        "eyes_pose": eyes_pose,
        "translation": translation,
        "pose": pose,
        "dynamic_offset": dynamic_offset,
    }
    # The frame count is read the way _pose and _offset read each array: one frame's worth of
    # pose values ([2,3] eyes, [J,3] pose) and a [V,3] dynamic offset are one frame, not 2, J or V.
    widths = dict(POSE_WIDTHS, translation=3, pose=3 * J)
    arrays = {}
    for k, v in raw.items():
        if v is not None:
            v = np.asarray(v, np.float64)
            if v.ndim <= 1 or v.size == widths.get(k):
                v = v.reshape(1, -1)
            elif k == "dynamic_offset":
                v = v.reshape((-1,) + v.shape[-2:])
            arrays[k] = v
    T = _frames_of(arrays)
    betas = np.concatenate(
        [
            _coeffs(arrays.get("shape"), model.n_shape, T, "shape"),
            _coeffs(arrays.get("expr"), model.n_expr, T, "expression"),
        ],
        axis=1,
    )
    if pose is not None:
        full = _pose(pose, T, 3 * J, "pose").reshape(T, J, 3)
    else:
        if J != 5:
            raise ValueError(f"the model has {J} joints, not FLAME's 5: pass pose=[T,{3 * J}] explicitly")
        full = np.concatenate(
            [
                _pose(rotation, T, 3, "rotation"),
                _pose(neck_pose, T, 3, "neck_pose"),
                _pose(jaw_pose, T, 3, "jaw_pose"),
                _pose(eyes_pose, T, 6, "eyes_pose"),
            ],
            axis=1,
        ).reshape(T, 5, 3)
    transl = _pose(translation, T, 3, "translation")
    offsets = _offset(static_offset, T, V, "static_offset")
    dyn = _offset(dynamic_offset, T, V, "dynamic_offset")
    if dyn is not None:
        offsets = dyn if offsets is None else offsets + dyn
    for name, a in (("betas", betas), ("pose", full), ("translation", transl), ("offsets", offsets)):
        if a is not None and not np.all(np.isfinite(a)):
            raise ValueError(f"FLAME {name} contain NaN or inf")
    return T, betas, full, transl, offsets


def _skin_chunk(model: FlameModel, betas, full_pose, transl, offsets) -> np.ndarray:
    T = betas.shape[0]
    V, J = model.n_vertices, model.n_joints
    v_shaped = model.v_template + (betas @ model._shape_basis).reshape(T, V, 3)
    if offsets is not None:
        v_shaped = v_shaped + offsets
    joints = model.J_regressor @ v_shaped  # [T,J,3] (matmul broadcasts over T)
    R = axis_angle_to_matrix(full_pose)  # [T,J,3,3]
    feat = (R[:, 1:] - np.eye(3)).reshape(T, -1)  # pose corrective feature (non-root joints)
    v_posed = v_shaped + (feat @ model._pose_basis).reshape(T, V, 3)
    rel = joints.copy()
    rel[:, 1:] -= joints[:, model.parents[1:]]
    local = np.zeros((T, J, 4, 4))
    local[:, :, :3, :3] = R
    local[:, :, :3, 3] = rel
    local[:, :, 3, 3] = 1.0
    G = np.empty_like(local)
    G[:, 0] = local[:, 0]
    for j in range(1, J):  # kinematic chain: a handful of joints, each step batched over T
        G[:, j] = G[:, model.parents[j]] @ local[:, j]
    # Skinning transforms relative to the rest pose: x -> G (x - joint).
    A = G[:, :, :3, :].copy()  # [T,J,3,4]
    A[..., 3] -= np.einsum("tjab,tjb->tja", G[:, :, :3, :3], joints)
    Tv = (model.weights @ A.reshape(T, J, 12)).reshape(T, V, 3, 4)
    verts = np.einsum("tvab,tvb->tva", Tv[..., :3], v_posed) + Tv[..., 3]
    return verts + transl[:, None, :]


def flame_forward(
    model: FlameModel,
    shape=None,
    expr=None,
    rotation=None,
    neck_pose=None,
    jaw_pose=None,
    eyes_pose=None,
    translation=None,
    static_offset=None,
    dynamic_offset=None,
    pose=None,
    dtype=np.float32,
    *,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """FLAME vertices [T,V,3] for T frames (computed in float64, returned as ``dtype``).

    shape [S] or [1|T,S]; expr [1|T,E]; rotation, neck_pose, jaw_pose, translation [1|T,3]
    (axis-angle); eyes_pose [1|T,6]; static_offset [1,V,3]; dynamic_offset [1|T,V,3].
    Missing parameters are zero. Fewer coefficients than the model has are zero-padded.
    ``progress(done, T)``, when given, is called after each chunk of frames evaluated.
    """
    T, betas, full, transl, offsets = prepare_params(
        model, shape, expr, rotation, neck_pose, jaw_pose, eyes_pose, translation, static_offset, dynamic_offset, pose
    )
    out = np.empty((T, model.n_vertices, 3), dtype=dtype)
    for s in range(0, T, _CHUNK):
        e = min(T, s + _CHUNK)
        off = None if offsets is None else (offsets if offsets.shape[0] == 1 else offsets[s:e])
        out[s:e] = _skin_chunk(model, betas[s:e], full[s:e], transl[s:e], off)
        if progress is not None:
            progress(e, T)
    return out
