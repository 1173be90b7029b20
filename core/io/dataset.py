"""``Dataset``: the GaussianAvatars/VHAP ``transforms_{split}.json`` layout in FLAME mode
(``flame_param_path``) or mesh mode (``mesh_path``), images loaded lazily through an LRU cache
(layout: docs/DATASET.md).

Blender tier at module level (numpy only): Blender's importers read a dataset root's geometry
through ``Dataset.sequence``; PIL is imported only where training and evaluation decode images.
"""

from __future__ import annotations

import os
import zipfile
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..geometry.camera import Camera
from ..flame.model import POSE_WIDTHS, load_flame_model
from .safe_io import loads_json
from .sequences import (
    _ALIASES,
    check_frame_keys,
    _check_faces,
    _check_vertices,
    DataError,
    _evaluate_flame,
    _flame_keys,
    MeshSequence,
    MissingFileError,
    _npz,
    _select,
)

_IMAGE_EXTS = (".png", ".jpg", ".jpeg")
# What a frame's camera is made of (with transform_matrix): per frame, else at the top level.
_CAMERA_KEYS = ("w", "h", "fl_x", "fl_y", "camera_angle_x", "cx", "cy")


@dataclass(frozen=True)
class FrameInfo:
    """One row of ``transforms_{split}.json``, resolved (no pixels loaded)."""

    index: int
    image_path: str
    mask_path: str | None
    camera: Camera  # already scaled for the dataset's downscale
    full_size: tuple  # (w, h) as stored in the JSON
    timestep_index: int
    camera_index: int
    geometry_path: str


@dataclass
class Sample:
    camera: Camera
    image: np.ndarray  # float32 [H,W,3] in [0,1]
    mask: np.ndarray  # float32 [H,W] in [0,1]
    vertices: np.ndarray  # float32 [V,3]
    timestep_index: int
    camera_index: int
    index: int = -1
    image_path: str = ""


# PIL modes the loader reads: 8-bit ones PIL converts to RGB/L itself, and 16-bit greyscale,
# which _to_8bit rescales. validate.py checks images against this same set (via _to_8bit).
_MODES_16BIT = ("I;16", "I;16L", "I;16B", "I")
IMAGE_MODES = frozenset(("RGB", "RGBA", "L", "LA", "P", "1", "CMYK", "YCbCr") + _MODES_16BIT)
_MAX_LISTED = 40  # problems listed in one error; the rest are counted


def _to_8bit(im, path: str, what: str):
    """16-bit greyscale PNGs (PIL modes I;16*, I) rescaled to 8-bit L: PIL's own convert
    clips them at 255, so they would read as pure white. Modes outside IMAGE_MODES are refused."""
    if im.mode in _MODES_16BIT:
        from PIL import Image

        a = np.asarray(im, dtype=np.float64)
        if a.size and (a.min() < 0 or a.max() > 65535):
            raise DataError(f"{path}: {what} has 32-bit pixel values outside 0..65535")
        return Image.fromarray(np.round(a * (255.0 / 65535.0)).astype(np.uint8), "L")
    if im.mode not in IMAGE_MODES:
        raise DataError(f"{path}: {what} has pixel format {im.mode!r}; use 8-bit RGB/RGBA/L or 16-bit greyscale PNG")
    return im


def _listing(problems: list) -> str:
    """Problems one per line (indented), at most _MAX_LISTED of them, the rest counted."""
    listed = "\n  ".join(problems[:_MAX_LISTED])
    more = f"\n  ... and {len(problems) - _MAX_LISTED} more" if len(problems) > _MAX_LISTED else ""
    return f"\n  {listed}{more}"


def _show(value, limit: int = 60) -> str:
    s = repr(value)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _path_field(fr: dict, key: str, where: str) -> str:
    v = fr[key]
    if not isinstance(v, str) or not v:
        raise DataError(f"{where}: {key} must be a file path (a string), got {_show(v)}")
    return v


def _index_field(fr: dict, key: str, where: str) -> int:
    # A fractional value passes here (it indexes as its integer part); validate.py reports it.
    v = fr[key]
    if not _is_number(v) or not np.isfinite(v):
        raise DataError(f"{where}: {key} must be a whole number, got {_show(v)}")
    return int(v)


def _frame_object(fr, where: str) -> dict:
    if not isinstance(fr, dict):
        raise DataError(f"{where} must be an object (one frame), got {_show(fr)}")
    return fr


def _resolve(root: str, rel: str) -> str:
    return os.path.normpath(rel if os.path.isabs(rel) else os.path.join(root, rel))


def _find_image(root: str, rel: str) -> str:
    """The image file ``rel`` names (an extensionless name tries .png, .jpg, .jpeg); the
    resolved path as given when there is none: a missing file is reported when the frame is
    read, and by validate.py with every other problem of the split."""
    p = _resolve(root, rel)
    if not os.path.isfile(p) and not os.path.splitext(p)[1]:
        for ext in _IMAGE_EXTS:
            if os.path.isfile(p + ext):
                return p + ext
    return p


def _not_found(path: str, what: str, json_path: str) -> str:
    return f"{path}: {what} listed in {json_path} not found"


class Dataset:
    """GaussianAvatars/VHAP layout: ``root/transforms_{split}.json`` + images, masks, geometry.

    ``downscale`` divides the image size (2.0: half width and height); intrinsics scale with
    it. Images are decoded on access and kept in an LRU cache of at most ``cache_images`` entries
    (0 disables it) and, when ``cache_bytes`` is given, at most that many bytes of decoded
    image and mask arrays (a paper-scale frame is ~7 MB); per-timestep vertices are cached
    without bound (they are small).
    """

    def __init__(
        self,
        root,
        split: str | None = "train",
        downscale: float = 1.0,
        cache_images: int = 256,
        flame_model=None,
        cache_bytes: int | None = None,
        geometry: bool = True,
    ):
        """``geometry=False`` reads the frames and cameras only (no canonical mesh or FLAME
        model: a camera import needs neither); its geometry attributes are then None."""
        self.root = os.path.abspath(os.fspath(root))
        self.split = split
        if not (downscale > 0):
            raise ValueError(f"downscale must be positive, got {downscale}")
        self.downscale = float(downscale)
        self.cache_images = int(cache_images)
        self.cache_bytes = None if cache_bytes is None else int(cache_bytes)
        self.cached_bytes = 0  # bytes of the arrays in the image cache now
        self._images: OrderedDict[int, tuple] = OrderedDict()
        self._verts: dict[int, np.ndarray] = {}
        self._refined: dict[int, dict] = {}  # timestep -> refined FLAME rows (use_refined_flame)
        # split=None reads transforms.json (VHAP's export of every frame).
        json_path = os.path.join(self.root, "transforms.json" if split is None else f"transforms_{split}.json")
        if not os.path.isdir(self.root):
            raise MissingFileError(f"{self.root}: dataset folder not found")
        if not os.path.isfile(json_path):
            have = (
                sorted(f for f in os.listdir(self.root) if f.startswith("transforms"))
                if os.path.isdir(self.root)
                else []
            )
            what = "the whole-sequence file (no split asked for)" if split is None else f"split '{split}'"
            raise MissingFileError(f"{json_path}: {what} not found (present: {have or 'none'})")
        self.json_path = json_path
        try:
            with open(json_path, "rb") as f:
                meta = loads_json(f.read(), json_path)  # nesting bounded (safe_io)
        except (ValueError, UnicodeDecodeError) as exc:
            raise DataError(f"{json_path}: invalid JSON ({exc})") from exc
        rows = meta.get("frames") if isinstance(meta, dict) else None
        if not rows:
            raise DataError(f"{json_path}: no frames (the '{split}' split is empty)")
        if not isinstance(rows, list):
            raise DataError(f"{json_path}: 'frames' must be a list of frame objects, got {_show(rows)}")
        bg = meta.get("background", [1.0, 1.0, 1.0])
        try:
            self.background = np.asarray(bg, np.float32).reshape(-1)
        except (TypeError, ValueError):
            self.background = np.zeros(0, np.float32)
        if self.background.shape != (3,) or not np.all(np.isfinite(self.background)):
            raise DataError(f"{json_path}: 'background' must be [r,g,b], got {_show(bg)}")
        if np.any(self.background < 0) or np.any(self.background > 1):
            raise DataError(f"{json_path}: 'background' must be [r,g,b] in [0,1] (not 0..255), got {_show(bg)}")

        mesh_mode = "mesh_path" in _frame_object(rows[0], f"{json_path}: frames[0]")
        self.mode = "mesh" if mesh_mode else "flame"
        geo_key = "mesh_path" if mesh_mode else "flame_param_path"
        if not mesh_mode and "flame_param_path" not in rows[0]:
            raise DataError(f"{json_path}: frame 0 has neither 'mesh_path' nor 'flame_param_path'")

        self.flame_model = None
        if not geometry:
            self.canonical_vertices = self.faces = None
        elif mesh_mode:
            rel = meta.get("canonical_mesh_path") or "canonical_mesh.npz"
            if not isinstance(rel, str):
                raise DataError(f"{json_path}: canonical_mesh_path must be a file path (a string), got {_show(rel)}")
            canon_path = _resolve(self.root, rel)
            d = _npz(canon_path)
            for key in ("vertices", "faces"):
                if key not in d:
                    raise DataError(f"{canon_path}: missing key '{key}' (has {sorted(d)})")
            self.canonical_vertices = _check_vertices(d["vertices"], canon_path)
            if self.canonical_vertices.ndim != 2:
                raise DataError(f"{canon_path}: 'vertices' must be [V,3], got {self.canonical_vertices.shape}")
            self.faces = _check_faces(d["faces"], canon_path, self.canonical_vertices.shape[0])
            if not len(self.faces):
                raise DataError(f"{canon_path}: the canonical mesh has no faces ('faces' is empty)")
        else:
            if flame_model is None:
                raise DataError(
                    f"{json_path}: FLAME-mode dataset (flame_param_path) needs a FLAME model file: "
                    "set the FLAME model in the add-on preferences, or pass --flame-model (Dataset(..., flame_model=PATH) in Python)"
                )
            self.flame_model = load_flame_model(flame_model)
            canon_path = os.path.join(self.root, "canonical_flame_param.npz")
            self.canonical_vertices = self._flame_vertices(canon_path)
            self.faces = self.flame_model.faces
        self.n_vertices = 0 if self.canonical_vertices is None else self.canonical_vertices.shape[0]

        # Every frame is read; the problems of all of them make one error.
        frames, cams, geo, problems = [], {}, {}, []
        # Frames that give their camera the same values (the same camera at every timestep) share
        # one Camera: built once per camera, not per frame (16,000 frames at the paper's scale).
        self._made_cameras = {}
        for i, fr in enumerate(rows):
            where = f"{json_path}: frames[{i}]"
            try:
                info = self._frame(i, fr, meta, where, geo_key)
                ts, gpath = info.timestep_index, info.geometry_path
                if ts in geo and geo[ts] != gpath:
                    raise DataError(f"{where}: timestep {ts} refers to {gpath}, an earlier frame to {geo[ts]}")
            except DataError as exc:
                problems.append(str(exc))
                continue
            geo[ts] = gpath
            cams.setdefault(info.camera_index, info.camera)
            frames.append(info)
        del self._made_cameras  # (one entry per distinct camera; the frames hold theirs)
        problems = list(dict.fromkeys(problems))  # a bad top-level fallback is listed once
        if len(problems) == 1:
            raise DataError(problems[0])
        if problems:
            raise DataError(f"{json_path}: {len(problems)} problem(s) in the frames:{_listing(problems)}")
        self.frames = frames
        self.cameras = cams
        self._geometry = geo
        self.timesteps = np.array(sorted(geo), dtype=np.int64)

    # -- metadata ----------------------------------------------------------------------

    def _frame(self, i: int, fr, meta: dict, where: str, geo_key: str) -> FrameInfo:
        fr = _frame_object(fr, where)
        for key in ("file_path", "transform_matrix", "timestep_index", "camera_index", geo_key):
            if key not in fr:
                raise DataError(f"{where}: missing key '{key}'")
        # Keyed on the values' reprs: exact for numbers, and 1 and 1.0 (or True) are told apart.
        key = repr([fr["transform_matrix"], *(fr.get(k, _CAMERA_KEYS) for k in _CAMERA_KEYS)])
        made = self._made_cameras.get(key)
        if made is None:
            cam_full, full_size = self._camera(fr, meta, where)
            cam = cam_full if self.downscale == 1.0 else cam_full.scaled(1.0 / self.downscale)
            made = self._made_cameras[key] = (cam, full_size)
        cam, full_size = made
        img = _find_image(self.root, _path_field(fr, "file_path", where))
        # Without fg_mask_path (or with null / ""), the image's alpha is the mask.
        mask = _find_image(self.root, _path_field(fr, "fg_mask_path", where)) if fr.get("fg_mask_path") else None
        ts = _index_field(fr, "timestep_index", where)
        ci = _index_field(fr, "camera_index", where)
        gpath = _resolve(self.root, _path_field(fr, geo_key, where))
        return FrameInfo(i, img, mask, cam, full_size, ts, ci, gpath)

    def _camera(self, fr: dict, meta: dict, where: str):
        def get(key, whole=False):
            """A number from the frame, else the top level; None where neither has it."""
            v = fr[key] if key in fr else meta.get(key)
            if v is None:
                return None
            if not _is_number(v) or (whole and not (np.isfinite(v) and float(v).is_integer() and v > 0)):
                at = f"{where}: {key}" if key in fr else f"{self.json_path}: top-level {key}"
                raise DataError(f"{at} must be {'a positive whole number' if whole else 'a number'}, got {_show(v)}")
            return int(v) if whole else float(v)

        w, h = get("w", whole=True), get("h", whole=True)
        if w is None or h is None:
            raise DataError(f"{where}: missing image size 'w'/'h' (per frame or at the top level)")
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None and get("camera_angle_x") is not None:
            fx = float(0.5 * w / np.tan(0.5 * get("camera_angle_x")))
        if fx is None:
            raise DataError(f"{where}: missing focal length 'fl_x' (or 'camera_angle_x')")
        fy = fx if fy is None else fy
        cx, cy = get("cx"), get("cy")
        cx = w / 2.0 if cx is None else cx
        cy = h / 2.0 if cy is None else cy
        m = fr["transform_matrix"]
        if not (
            isinstance(m, list)
            and len(m) in (3, 4)
            and all(isinstance(r, list) and len(r) == 4 and all(_is_number(x) for x in r) for r in m)
        ):
            raise DataError(f"{where}: transform_matrix must be a 4x4 (or 3x4) array of numbers, got {_show(m)}")
        c2w = np.asarray(m, dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        try:
            return Camera.from_c2w_opengl(c2w, fx, fy, cx, cy, w, h), (w, h)
        except ValueError as exc:
            raise DataError(f"{where}: {exc}") from exc

    def check_same_mesh(self, faces, what: str) -> None:
        """Refuse this split when its tracked mesh is not ``faces`` (another split's, or an
        avatar's template), named ``what``: each split may name its own canonical_mesh_path, and
        an avatar bound to one mesh cannot follow another (it would fail at the first render)."""
        if self.faces is None:
            return
        faces = np.asarray(faces)
        if faces.shape != self.faces.shape or not np.array_equal(faces, self.faces):
            how = f"{len(faces)} faces" if len(faces) != len(self.faces) else "as many faces, other vertex indices"
            raise DataError(
                f"{self.json_path}: its mesh ({self.n_vertices} vertices, {len(self.faces)} faces) is not "
                f"{what} ({how}); every split must track the same mesh"
            )

    def __len__(self) -> int:
        return len(self.frames)

    def frame_info(self, i: int) -> FrameInfo:
        return self.frames[i]

    # -- geometry ----------------------------------------------------------------------

    def _flame_vertices(self, path: str, ts: int | None = None) -> np.ndarray:
        d = _flame_keys(_npz(path))
        if not d:
            raise DataError(f"{path}: no FLAME parameters (expected keys {', '.join(_ALIASES)})")
        check_frame_keys(d, path)
        refined = self._refined.get(ts)
        if refined is not None:
            d.update(refined)
            path = f"{path} with {refined['source']}"
            del d["source"]
        v = _evaluate_flame(d, self.flame_model, path)
        if v.shape[0] != 1:
            raise DataError(f"{path}: expected parameters of one frame, got {v.shape[0]}")
        return _check_vertices(v[0], path)

    def use_refined_flame(self, path: str) -> int:
        """Pose the timesteps that ``path`` (a run's flame_refined.npz, from ``--refine-flame``)
        covers with its refined expression, joint poses and translation, as training rendered
        them; the files' other keys (shape, offsets) and the other timesteps stay as tracked.
        Returns how many of this split's timesteps it covers."""
        if self.mode != "flame":
            raise DataError(f"{path}: refined FLAME parameters need a FLAME-mode dataset ({self.json_path} is not)")
        keys = ("expr", "translation") + tuple(k for k, _ in POSE_WIDTHS)
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in ("timesteps",) + keys if k not in z.files]
                if missing:
                    raise DataError(f"{path}: not a refined-FLAME file (no {', '.join(missing)})")
                d = {k: np.asarray(z[k], np.float64) for k in keys}
                ts = np.asarray(z["timesteps"]).reshape(-1)
        except DataError:
            raise
        except (OSError, ValueError, zipfile.BadZipFile) as exc:
            raise DataError(f"{path}: cannot read refined FLAME parameters ({exc})") from exc
        for k, v in d.items():
            if v.ndim != 2 or len(v) != len(ts) or not np.all(np.isfinite(v)):
                raise DataError(f"{path}: '{k}' must be finite with one row per timestep ({len(ts)}), got {v.shape}")
        covered = 0
        for i, t in enumerate(ts.tolist()):
            if int(t) in self._geometry:
                self._refined[int(t)] = {k: v[i : i + 1] for k, v in d.items()} | {"source": os.path.basename(path)}
                self._verts.pop(int(t), None)
                covered += 1
        return covered

    def flame_params_at(self, timestep_index: int) -> dict:
        """The tracked FLAME parameters of a timestep (FLAME mode), as stored."""
        ts = int(timestep_index)
        if self.mode != "flame":
            raise DataError(f"{self.json_path}: a mesh-mode dataset has no FLAME parameters")
        if ts not in self._geometry:
            raise KeyError(f"{self.json_path}: no timestep {ts} in split '{self.split}'")
        d = _flame_keys(_npz(self._geometry[ts]))
        if not d:
            raise DataError(f"{self._geometry[ts]}: no FLAME parameters (expected keys {', '.join(_ALIASES)})")
        return d

    def vertices_at(self, timestep_index: int) -> np.ndarray:
        """Mesh vertices float32 [V,3] of a timestep (cached)."""
        ts = int(timestep_index)
        v = self._verts.get(ts)
        if v is not None:
            return v
        if ts not in self._geometry:
            raise KeyError(f"{self.json_path}: no timestep {ts} in split '{self.split}'")
        path = self._geometry[ts]
        if self.mode == "mesh":
            d = _npz(path)
            if "vertices" not in d:
                raise DataError(f"{path}: mesh npz needs 'vertices' [V,3] (has {sorted(d)})")
            v = _check_vertices(d["vertices"], path, self.n_vertices)
            if v.ndim != 2:
                raise DataError(f"{path}: 'vertices' must be [V,3], got {v.shape}")
        else:
            v = self._flame_vertices(path, ts)
            if v.shape[0] != self.n_vertices:
                raise DataError(f"{path}: {v.shape[0]} vertices, canonical has {self.n_vertices}")
        self._verts[ts] = v
        return v

    # -- pixels --------------------------------------------------------------------------

    def _load_pixels(self, info: FrameInfo):
        from PIL import Image  # decoded on demand only

        cam = info.camera
        target = (cam.width, cam.height)
        full = info.full_size

        def read(path, what):
            if not os.path.isfile(path):
                raise MissingFileError(_not_found(path, what, self.json_path))
            try:
                im = Image.open(path)
                im.load()
            except Exception as exc:
                raise DataError(f"{path}: cannot read {what} ({type(exc).__name__}: {exc})") from exc
            if im.size != full and im.size != target:
                want = f"{full[0]}x{full[1]}" + (f" or {target[0]}x{target[1]} (downscaled)" if target != full else "")
                raise DataError(f"{path}: {what} is {im.size[0]}x{im.size[1]}, {self.json_path} says {want}")
            return _to_8bit(im, path, what)

        im = read(info.image_path, "image")
        alpha = None
        if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
            im = im.convert("RGBA")
            alpha = im.getchannel("A")
        rgb = im.convert("RGB")
        if alpha is not None:
            # Transparent pixels take the dataset background, as the renderer's will: composited
            # at full size, so a transparent pixel's own colour (often black) never blurs into
            # the outline when the image is downscaled.
            a = np.asarray(alpha, dtype=np.float32)[..., None] / 255.0
            full_rgb = np.asarray(rgb, dtype=np.float32) / 255.0 * a + self.background * (1.0 - a)
            if rgb.size != target:
                full_rgb = np.stack(
                    [
                        np.asarray(
                            Image.fromarray(np.ascontiguousarray(full_rgb[..., c]), "F").resize(
                                target, Image.Resampling.BOX
                            )
                        )
                        for c in range(3)
                    ],
                    axis=-1,
                )
            image = full_rgb.astype(np.float32)
        else:
            if rgb.size != target:
                rgb = rgb.resize(target, Image.Resampling.BOX)
            image = np.asarray(rgb, dtype=np.float32) / 255.0
        if info.mask_path is not None:
            m = read(info.mask_path, "mask")
            m = m.convert("L")
        else:
            m = alpha
        if m is not None:
            if m.size != target:
                m = m.resize(target, Image.Resampling.BOX)
            mask = np.asarray(m, dtype=np.float32) / 255.0
        else:
            mask = np.ones(image.shape[:2], np.float32)
        return image, mask

    def images(self, i: int):
        """(image float32 [H,W,3], mask float32 [H,W]) of frame i, through the LRU cache."""
        i = self._frame_index(i)  # one cache entry per frame, whichever way it is named
        hit = self._images.get(i)
        if hit is not None:
            self._images.move_to_end(i)
            return hit
        pair = self._load_pixels(self.frames[i])
        size = pair[0].nbytes + pair[1].nbytes
        if self.cache_images > 0 and (self.cache_bytes is None or size <= self.cache_bytes):
            self._images[i] = pair
            self.cached_bytes += size
            while len(self._images) > self.cache_images or (
                self.cache_bytes is not None and self.cached_bytes > self.cache_bytes
            ):
                _, (im, m) = self._images.popitem(last=False)
                self.cached_bytes -= im.nbytes + m.nbytes
        return pair

    def _frame_index(self, i) -> int:
        n = len(self.frames)
        if not -n <= int(i) < n:
            raise IndexError(f"{self.json_path}: frame {i} out of range (0..{n - 1})")
        return int(i) % n

    def __getitem__(self, i: int) -> Sample:
        i = self._frame_index(i)
        info = self.frames[i]
        image, mask = self.images(i)
        return Sample(
            info.camera,
            image,
            mask,
            self.vertices_at(info.timestep_index),
            info.timestep_index,
            info.camera_index,
            i,
            info.image_path,
        )

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def sequence(self, frames=None, *, progress: Callable[[int, int], None] | None = None) -> MeshSequence:
        """The split's geometry as a MeshSequence over its sorted timesteps (``frames``:
        positions in ``self.timesteps``; None = all). ``progress(done, total)`` is called after
        each timestep's geometry (as core/io/sequences.py's readers call it)."""
        ts = self.timesteps[_select(len(self.timesteps), frames, self.json_path)]
        # One mesh file (or one FLAME evaluation) per timestep, each cached.
        rows = []
        for j, t in enumerate(ts.tolist()):
            rows.append(self.vertices_at(t))
            if progress is not None:
                progress(j + 1, len(ts))
        verts = np.stack(rows) if rows else np.zeros((0, self.n_vertices, 3), np.float32)
        return MeshSequence(self.faces, verts, ts, None, self.json_path)
