"""Sequence readers and the transforms_*.json dataset loader, on small files written here."""

import json
import math
import os

import numpy as np
import pytest

from progressive_avatars.core.geometry.camera import Camera
from progressive_avatars.core.io.dataset import Dataset
from progressive_avatars.core.io.validate import sees_mesh
from progressive_avatars.core.io.sequences import (
    DataError,
    MeshSequence,
    MissingFileError,
    read_flame_param_folder,
    read_mesh_folder,
    read_mesh_npz,
    read_nersemble_tracking,
    read_sequence,
    read_vhap_tracked,
)
from progressive_avatars.core.flame.model import flame_forward, load_flame_model

from tests.helpers import sphere_mesh
from tests.test_flame import N_EXPR, N_SHAPE, N_V, random_params, write_flame_pkl  # noqa: E402


@pytest.fixture(scope="module")
def flame_model(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("flame") / "generic_model.pkl")
    write_flame_pkl(path)
    return load_flame_model(path, n_shape=N_SHAPE)


def ga_frame(prm, t):
    """One GaussianAvatars/VHAP per-frame flame_param npz dict from stacked params."""
    return dict(
        translation=prm["translation"][t : t + 1],
        rotation=prm["rotation"][t : t + 1],
        neck_pose=prm["neck_pose"][t : t + 1],
        jaw_pose=prm["jaw_pose"][t : t + 1],
        eyes_pose=prm["eyes_pose"][t : t + 1],
        shape=prm["shape"],
        expr=prm["expr"][t : t + 1],
        static_offset=prm["static_offset"],
    )


# ---------------------------------------------------------------------------- sequences


def test_mesh_npz_reader_and_frame_selection(tmp_path):
    rng = np.random.default_rng(0)
    v = rng.normal(size=(5, 7, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6]], np.int64)
    p = tmp_path / "seq.npz"
    np.savez(p, vertices=v, faces=faces)
    seq = read_sequence(p, frames=[3, 1])
    assert isinstance(seq, MeshSequence) and seq.faces.dtype == np.int32 and seq.vertices.dtype == np.float32
    np.testing.assert_array_equal(seq.vertices, v[[3, 1]])
    np.testing.assert_array_equal(seq.frame_ids, [3, 1])
    assert read_mesh_npz(p).n_frames == 5
    with pytest.raises(DataError, match=r"seq\.npz.*out of range"):
        read_mesh_npz(p, frames=[9])
    v[2, 4, 1] = np.nan
    np.savez(tmp_path / "nan.npz", vertices=v, faces=faces)
    with pytest.raises(DataError, match=r"nan\.npz: vertices contain NaN"):
        read_sequence(tmp_path / "nan.npz")
    np.savez(tmp_path / "badf.npz", vertices=v[:1, :3], faces=faces)
    with pytest.raises(DataError, match=r"badf\.npz: faces index"):
        read_sequence(tmp_path / "badf.npz")


def test_mesh_folder_natural_order_and_lazy(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    base = trimesh.creation.icosahedron()
    d = tmp_path / "frames"
    d.mkdir()
    for i, name in [(1, "f1.obj"), (2, "f2.ply"), (10, "f10.obj")]:
        trimesh.Trimesh(base.vertices * i, base.faces, process=False).export(d / name)
    (d / "f3.obj").write_text("this is not an obj file\nv 1 2\n")  # only read if asked for
    seq = read_sequence(d, frames=[0, 1, 3])
    np.testing.assert_array_equal(seq.frame_ids, [1, 2, 10])
    np.testing.assert_allclose(seq.vertices[2], base.vertices * 10, rtol=1e-6)
    np.testing.assert_array_equal(seq.faces, base.faces)
    with pytest.raises(DataError, match="f3.obj"):
        read_mesh_folder(d, frames=[2])
    other = trimesh.creation.box()
    other.export(d / "f11.obj")
    with pytest.raises(DataError, match=r"f11\.obj: 8 vertices"):
        read_mesh_folder(d, frames=[0, 4])


def test_flame_param_folder(tmp_path, flame_model):
    prm = random_params(4, seed=3)
    fp = tmp_path / "flame_param"
    fp.mkdir()
    for t in range(4):
        np.savez(fp / f"{t * 5:05d}.npz", **ga_frame(prm, t))
    (fp / "00099.npz").write_bytes(b"garbage")  # sorted last; never opened unless asked
    seq = read_sequence(tmp_path, frames=[2, 0], flame_model=flame_model)
    want = flame_forward(
        flame_model, **{k: (v[[2, 0]] if k not in ("shape", "static_offset") else v) for k, v in prm.items()}
    )
    np.testing.assert_allclose(seq.vertices, want, atol=1e-6)
    np.testing.assert_array_equal(seq.frame_ids, [10, 0])
    np.testing.assert_array_equal(seq.faces, flame_model.faces)
    with pytest.raises(DataError, match="00099.npz"):
        read_flame_param_folder(fp, frames=[4], flame_model=flame_model)
    with pytest.raises(DataError, match="need a FLAME model"):
        read_flame_param_folder(fp, frames=[0])


def _recorder():
    calls = []
    return calls, lambda done, total: calls.append((done, total))


def _to_the_end(calls):
    """A reader's progress calls: one total, done rising one step at a time or more, the last (total, total)."""
    assert calls, "no progress reported"
    total = calls[0][1]
    assert all(t == total for _, t in calls), calls
    done = [d for d, _ in calls]
    assert done == sorted(set(done)) and done[0] > 0 and done[-1] == total, calls
    return done


def _obj_folder(d, frames):
    v, f = sphere_mesh(4, 6)
    d.mkdir()
    faces = "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f)
    for t in range(frames):
        (d / f"frame{t}.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v * (1 + t)) + faces)


def test_folder_readers_report_progress_per_file(tmp_path, flame_model, monkeypatch):
    # A 1000-frame folder reads for seconds (Blender's importer shows it): one call per file
    # read (and per chunk of frames FLAME evaluates), ending at (total, total).
    _obj_folder(tmp_path / "obj", 5)
    calls, progress = _recorder()
    seq = read_mesh_folder(tmp_path / "obj", progress=progress)
    assert calls == [(t, 5) for t in range(1, 6)]
    np.testing.assert_array_equal(seq.vertices, read_mesh_folder(tmp_path / "obj").vertices)  # as without
    calls.clear()
    read_sequence(tmp_path / "obj", frames=[3, 1], progress=progress)
    assert calls == [(1, 2), (2, 2)]
    (tmp_path / "obj" / "frame3.obj").write_text("v 1 2\n")
    calls.clear()
    with pytest.raises(DataError, match=r"frame3\.obj"):
        read_sequence(tmp_path / "obj", progress=progress)
    assert calls == [(1, 5), (2, 5), (3, 5)]  # the files before the broken one

    prm = random_params(5, seed=12)
    fp = tmp_path / "ga" / "flame_param"
    fp.mkdir(parents=True)
    for t in range(5):
        np.savez(fp / f"{t:05d}.npz", **ga_frame(prm, t))
    calls.clear()
    seq = read_flame_param_folder(tmp_path / "ga", flame_model=flame_model, progress=progress)
    assert calls == [(1, 10), (2, 10), (3, 10), (4, 10), (5, 10), (10, 10)]  # 5 files, one chunk of 5 frames
    np.testing.assert_array_equal(seq.vertices, read_sequence(tmp_path / "ga", flame_model=flame_model).vertices)
    from progressive_avatars.core.flame import model as flame_module

    monkeypatch.setattr(flame_module, "_CHUNK", 2)
    calls.clear()
    read_sequence(tmp_path / "ga", flame_model=flame_model, progress=progress)
    assert _to_the_end(calls) == [1, 2, 3, 4, 5, 7, 9, 10]  # then chunks of 2, 2 and 1 frames
    calls.clear()
    from progressive_avatars.core.io.sequences import read_flame_track

    read_flame_track(tmp_path / "ga", frames=[4, 0, 2], progress=progress)  # nothing evaluated
    assert calls == [(1, 3), (2, 3), (3, 3)]


def test_single_file_and_dataset_readers_report_progress(tmp_path, flame_model):
    calls, progress = _recorder()
    prm = random_params(3, seed=13)
    np.savez(tmp_path / "tracked.npz", **prm)
    read_sequence(tmp_path / "tracked.npz", flame_model=flame_model, progress=progress)
    assert calls == [(1, 4), (4, 4)]  # the file, then its 3 frames evaluated
    np.savez(tmp_path / "nersemble.npz", **_nersemble(prm))
    from progressive_avatars.core.io.sequences import read_flame_track

    for path in (tmp_path / "nersemble.npz", tmp_path / "tracked.npz"):
        calls.clear()
        read_sequence(path, frames=[2], flame_model=flame_model, progress=progress)
        assert calls == [(1, 2), (2, 2)], path
        calls.clear()
        read_flame_track(path, progress=progress)  # the file, nothing evaluated
        assert calls == [(1, 1)], path
    np.savez(tmp_path / "mesh.npz", vertices=np.zeros((2, 3, 3)), faces=np.array([[0, 1, 2]]))
    calls.clear()
    read_sequence(tmp_path / "mesh.npz", progress=progress)
    assert calls == [(1, 1)]
    root = tmp_path / "ds"
    write_mesh_dataset(root, timesteps=(0, 1, 2, 3))
    calls.clear()
    read_sequence(root, progress=progress)
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]  # one per timestep's geometry


def test_vhap_tracked_matches_per_frame(tmp_path, flame_model):
    T = 5
    prm = random_params(T, seed=4)
    p = tmp_path / "tracked_flame_params_30.npz"
    np.savez(p, timestep_id=np.array([f"{i:05d}" for i in range(100, 100 + T)]), **prm)
    seq = read_sequence(p, frames=[4, 1], flame_model=flame_model)
    np.testing.assert_array_equal(seq.frame_ids, [104, 101])
    for j, t in enumerate([4, 1]):
        np.testing.assert_allclose(seq.vertices[j], flame_forward(flame_model, **ga_frame(prm, t))[0], atol=1e-6)
    # Short key spellings (neck/jaw/eyes) are read too.
    short = {
        ("neck" if k == "neck_pose" else "jaw" if k == "jaw_pose" else "eyes" if k == "eyes_pose" else k): v
        for k, v in prm.items()
    }
    np.savez(tmp_path / "short.npz", **short)
    np.testing.assert_allclose(
        read_vhap_tracked(tmp_path / "short.npz", flame_model=flame_model).vertices,
        flame_forward(flame_model, **prm),
        atol=1e-6,
    )
    bad = dict(prm, jaw_pose=prm["jaw_pose"][:3])
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(DataError, match=r"bad\.npz: 'jaw_pose' has 3 frames"):
        read_vhap_tracked(tmp_path / "bad.npz", flame_model=flame_model)
    wrong_v = dict(prm, static_offset=np.zeros((1, N_V + 3, 3)))
    np.savez(tmp_path / "wrongv.npz", **wrong_v)
    with pytest.raises(DataError, match=r"wrongv\.npz: static_offset"):
        read_vhap_tracked(tmp_path / "wrongv.npz", flame_model=flame_model)


def test_nersemble_tracking(tmp_path, flame_model):
    from scipy.spatial.transform import Rotation

    T = 3
    rng = np.random.default_rng(5)
    prm = random_params(T, seed=5)
    euler = 0.4 * rng.normal(size=(T, 3))
    R = Rotation.from_euler("XYZ", euler).as_matrix()
    d = _nersemble(prm, rotation=euler, rotation_matrices=R, scale=np.array([[1.7]]), frames=np.array([7, 8, 9]))
    np.savez(tmp_path / "tracking.npz", **d)
    local = flame_forward(
        flame_model,
        shape=prm["shape"],
        expr=prm["expr"],
        jaw_pose=prm["jaw_pose"],
        neck_pose=prm["neck_pose"],
        eyes_pose=prm["eyes_pose"],
        dtype=np.float64,
    )
    want = 1.7 * np.einsum("tab,tvb->tva", R, local) + prm["translation"][:, None]
    seq = read_sequence(tmp_path / "tracking.npz", flame_model=flame_model)
    np.testing.assert_allclose(seq.vertices, want, atol=1e-5)
    np.testing.assert_array_equal(seq.frame_ids, [7, 8, 9])
    # Without rotation_matrices the Euler angles (intrinsic XYZ) give the same result.
    del d["rotation_matrices"]
    np.savez(tmp_path / "euler.npz", **d)
    np.testing.assert_allclose(
        read_nersemble_tracking(tmp_path / "euler.npz", frames=[1], flame_model=flame_model).vertices[0],
        want[1],
        atol=1e-5,
    )
    # A NaN or overflowing placement is refused for the rig too (not evaluated there: the rig
    # keeps it as keyframes), naming the file and the key.
    d["rotation_matrices"] = R
    for key, value in (
        ("rotation_matrices", np.nan),
        ("translation", np.inf),
        ("scale", np.nan),
        ("translation", 1e300),
    ):
        bad = dict(d)
        bad[key] = np.array(d[key], np.float64)
        bad[key].reshape(-1)[0] = value
        np.savez(tmp_path / "bad.npz", **bad)
        name = "rotation" if key == "rotation_matrices" else key
        with pytest.raises(DataError, match=rf"bad\.npz: '{name}' placement"):
            read_nersemble_tracking(tmp_path / "bad.npz", evaluate=False)


def test_read_sequence_errors(tmp_path):
    with pytest.raises(MissingFileError, match="missing.npz"):
        read_sequence(tmp_path / "missing.npz")
    np.savez(tmp_path / "odd.npz", foo=np.zeros(3))
    with pytest.raises(DataError, match=r"odd\.npz: unrecognised npz"):
        read_sequence(tmp_path / "odd.npz")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(DataError, match=r"x\.txt: unsupported"):
        read_sequence(tmp_path / "x.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="empty: folder holds neither"):
        read_sequence(tmp_path / "empty")


# ---------------------------------------------------------------------------- dataset

OCTA_F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.int32)
W, H = 96, 80


def octahedron(t):
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    return (0.1 * v * np.array([1.0 + 0.1 * t, 1.2, 0.9]) + np.array([0.01 * t, 0.0, 0.0])).astype(np.float32)


def make_cameras():
    # Off-centre principal points and fx != fy, so an ignored intrinsic shows up as a miss.
    return {
        0: Camera.look_at([0.0, 0.05, 0.6], [0, 0, 0], [0, 1, 0], 150.0, 120.0, 26.0, 54.0, W, H),
        1: Camera.look_at([0.45, -0.05, 0.4], [0, 0, 0], [0, 1, 0], 110.0, 140.0, 68.0, 28.0, W, H),
    }


def raster_mask(cam, verts, faces):
    """Silhouette of a mesh: pixel centres inside any projected triangle (vectorised)."""
    uv, _ = cam.project(verts.astype(np.float64))
    tri = uv[faces]  # [F,3,2]
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    p = np.stack([xs + 0.5, ys + 0.5], -1).reshape(1, -1, 2)

    def edge(a, b):
        return (b[:, None, 0] - a[:, None, 0]) * (p[..., 1] - a[:, None, 1]) - (b[:, None, 1] - a[:, None, 1]) * (
            p[..., 0] - a[:, None, 0]
        )

    e0, e1, e2 = edge(tri[:, 0], tri[:, 1]), edge(tri[:, 1], tri[:, 2]), edge(tri[:, 2], tri[:, 0])
    inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
    return inside.any(0).reshape(cam.height, cam.width)


def write_mesh_dataset(
    root, timesteps=(0, 1, 2), split="train", extensionless=False, top_level_intrinsics=False, background=None
):
    from PIL import Image

    root.mkdir(parents=True, exist_ok=True)
    for sub in ("images", "fg_masks", "meshes"):
        (root / sub).mkdir(exist_ok=True)
    np.savez(root / "canonical_mesh.npz", vertices=octahedron(0), faces=OCTA_F)
    cams = make_cameras()
    frames = []
    for t in timesteps:
        v = octahedron(t)
        np.savez(root / "meshes" / f"{t:05d}.npz", vertices=v)
        for ci, cam in cams.items():
            m = raster_mask(cam, v, OCTA_F)
            img = np.where(m[..., None], np.array([200, 60, 30], np.uint8), np.uint8(255)).astype(np.uint8)
            name = f"{t:05d}_{ci:02d}"
            Image.fromarray(img).save(root / "images" / f"{name}.png")
            Image.fromarray((m * 255).astype(np.uint8)).save(root / "fg_masks" / f"{name}.png")
            fr = dict(
                file_path=f"images/{name}" + ("" if extensionless else ".png"),
                fg_mask_path=f"fg_masks/{name}.png",
                transform_matrix=cam.c2w_opengl().tolist(),
                timestep_index=t,
                camera_index=ci,
                mesh_path=f"meshes/{t:05d}.npz",
            )
            if not top_level_intrinsics:
                fr.update(fl_x=cam.fx, fl_y=cam.fy, cx=cam.cx, cy=cam.cy, w=W, h=H)
            frames.append(fr)
    meta = {"frames": frames}
    if top_level_intrinsics:  # one shared intrinsic set (camera 0's) as the fallback
        c = cams[0]
        meta.update(fl_x=c.fx, fl_y=c.fy, cx=c.cx, cy=c.cy, w=W, h=H)
        meta["frames"] = [f for f in frames if f["camera_index"] == 0]
    if background is not None:
        meta["background"] = background
    (root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    return cams


def centroids(v):
    """Points well inside the (convex) mesh: they project inside its silhouette with margin."""
    c = v.mean(0)
    return np.concatenate([c[None], c + 0.6 * (v - c)])


def test_dataset_round_trip_cameras_hit_masks(tmp_path):
    root = tmp_path / "ds"
    cams = write_mesh_dataset(root, extensionless=True)
    ds = Dataset(root, "train")
    assert len(ds) == 6 and ds.mode == "mesh"
    np.testing.assert_array_equal(ds.timesteps, [0, 1, 2])
    assert ds.faces.dtype == np.int32 and ds.faces.shape == (8, 3)
    np.testing.assert_array_equal(ds.canonical_vertices, octahedron(0))
    np.testing.assert_array_equal(ds.background, [1, 1, 1])
    for ci, cam in cams.items():
        c = ds.cameras[ci]
        np.testing.assert_allclose(c.R, cam.R, atol=1e-12)
        np.testing.assert_allclose(c.t, cam.t, atol=1e-12)
        assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (cam.fx, cam.fy, cam.cx, cam.cy, W, H)
    for s in ds:
        assert s.image.shape == (H, W, 3) and s.image.dtype == np.float32 and s.mask.shape == (H, W)
        assert 0.0 <= s.image.min() and s.image.max() <= 1.0
        np.testing.assert_array_equal(s.vertices, octahedron(s.timestep_index))
        uv, z = s.camera.project(centroids(s.vertices).astype(np.float64))
        assert np.all(z > 0)
        px = np.floor(uv).astype(int)
        assert np.all(s.mask[px[:, 1], px[:, 0]] == 1.0)
        # Control: the same camera with a centred principal point misses the silhouette.
        centred = Camera(s.camera.R, s.camera.t, s.camera.fx, s.camera.fy, W / 2, H / 2, W, H)
        uvc = np.clip(
            np.floor(centred.project(centroids(s.vertices).astype(np.float64))[0]).astype(int), 0, [W - 1, H - 1]
        )
        assert s.mask[uvc[:, 1], uvc[:, 0]].mean() < 0.5
        # Image pixels: mesh colour inside, white background outside.
        np.testing.assert_allclose(s.image[s.mask == 0], 1.0)
    np.testing.assert_array_equal(ds.vertices_at(2), octahedron(2))
    seq = ds.sequence()
    assert seq.vertices.shape == (3, 6, 3)
    seq = read_sequence(root, frames=[2])  # a dataset root reads as its tracked geometry
    np.testing.assert_array_equal(seq.vertices[0], octahedron(2))
    np.testing.assert_array_equal(seq.frame_ids, [2])


def test_dataset_downscale_and_cache(tmp_path):
    root = tmp_path / "ds"
    write_mesh_dataset(root, background=[0.0, 0.5, 1.0])
    ds = Dataset(root, "train", downscale=2.0, cache_images=2)
    np.testing.assert_allclose(ds.background, [0, 0.5, 1])
    s = ds[1]
    assert s.image.shape == (H // 2, W // 2, 3) and s.camera.width == W // 2
    assert s.camera.cx == pytest.approx(ds.frames[1].camera.cx) and s.camera.fx == pytest.approx(ds.cameras[1].fx)
    uv, _ = s.camera.project(centroids(s.vertices).astype(np.float64))
    px = np.floor(uv).astype(int)
    assert np.all(s.mask[px[:, 1], px[:, 0]] >= 0.5)
    # LRU: a hit returns the cached array; the bound evicts the oldest.
    assert ds[1].image is s.image
    ds[2], ds[3]
    assert len(ds._images) == 2 and 1 not in ds._images
    assert ds[1].image is not s.image
    ds0 = Dataset(root, "train", cache_images=0)
    assert ds0[0].image is not ds0[0].image


def test_dataset_image_cache_holds_a_byte_budget(tmp_path):
    """cache_bytes bounds the decoded images kept (LRU by bytes), whatever cache_images allows;
    evicted frames decode again to the same values; a frame larger than the budget is not kept."""
    root = tmp_path / "ds"
    write_mesh_dataset(root)
    plain = Dataset(root, "train", cache_images=0)
    frame = plain[0].image.nbytes + plain[0].mask.nbytes
    budget = int(2.5 * frame)
    ds = Dataset(root, "train", cache_images=100000, cache_bytes=budget)
    assert len(ds) >= 4
    order = [0, 1, 2, 3, 1, 0, 2, 3, 3, 0]
    for i in order:
        s = ds[i]
        np.testing.assert_array_equal(s.image, plain[i].image)
        assert ds.cached_bytes <= budget
        assert ds.cached_bytes == sum(a.nbytes + b.nbytes for a, b in ds._images.values())
    assert list(ds._images) == [3, 0]  # the two most recently used frames
    held = ds[0].image
    assert ds[0].image is held
    tiny = Dataset(root, "train", cache_images=100000, cache_bytes=frame - 1)
    tiny[0]
    assert len(tiny._images) == 0 and tiny.cached_bytes == 0


def test_dataset_top_level_intrinsics_fallback(tmp_path):
    root = tmp_path / "ds"
    cams = write_mesh_dataset(root, top_level_intrinsics=True)
    ds = Dataset(root)
    c = ds.cameras[0]
    assert (c.fx, c.fy, c.cx, c.cy) == (cams[0].fx, cams[0].fy, cams[0].cx, cams[0].cy)


def edit_json(root, split, fn):
    p = root / f"transforms_{split}.json"
    meta = json.loads(p.read_text())
    fn(meta)
    p.write_text(json.dumps(meta))


def test_dataset_bad_inputs(tmp_path):
    from PIL import Image

    root = tmp_path / "ds"
    write_mesh_dataset(root)
    with pytest.raises(MissingFileError, match=r"transforms_val\.json: split 'val' not found"):
        Dataset(root, "val")
    with pytest.raises(MissingFileError, match=r"transforms\.json: the whole-sequence file \(no split asked for\)"):
        Dataset(root, None)  # it said "split 'None' not found"
    (root / "transforms_test.json").write_text(json.dumps({"frames": []}))
    with pytest.raises(DataError, match=r"transforms_test\.json: no frames"):
        Dataset(root, "test")

    edit_json(root, "train", lambda m: m["frames"][2].pop("transform_matrix"))
    with pytest.raises(DataError, match=r"frames\[2\]: missing key 'transform_matrix'"):
        Dataset(root)
    write_mesh_dataset(root)

    os.remove(root / "images" / "00001_00.png")
    ds = Dataset(root)  # a missing image is reported when its frame is read (and by validate)
    with pytest.raises(
        MissingFileError, match=r"images/00001_00\.png: image listed in .*transforms_train\.json not found"
    ):
        ds[2]
    ds[3]  # other frames still load
    write_mesh_dataset(root)

    np.savez(root / "meshes" / "00001.npz", vertices=np.zeros((5, 3), np.float32))
    ds = Dataset(root)
    with pytest.raises(DataError, match=r"00001\.npz: 5 vertices, but the template has 6"):
        ds.vertices_at(1)
    bad = octahedron(1)
    bad[3, 0] = np.inf
    np.savez(root / "meshes" / "00001.npz", vertices=bad)
    with pytest.raises(DataError, match=r"00001\.npz: vertices contain NaN or inf"):
        Dataset(root)[2]
    write_mesh_dataset(root)

    Image.new("RGB", (W + 1, H)).save(root / "images" / "00002_01.png")
    ds = Dataset(root, downscale=2.0)
    with pytest.raises(DataError, match=r"00002_01\.png: image is 97x80, .*says 96x80 or 48x40"):
        ds[5]
    ds[4]  # other frames still load
    write_mesh_dataset(root)

    os.remove(root / "canonical_mesh.npz")
    with pytest.raises(MissingFileError, match=r"canonical_mesh\.npz: file not found"):
        Dataset(root)
    write_mesh_dataset(root)
    edit_json(root, "train", lambda m: [f.pop("w") for f in m["frames"]])
    with pytest.raises(DataError, match=r"frames\[0\]: missing image size"):
        Dataset(root)


def test_dataset_missing_files_listed_with_every_problem(tmp_path):
    """Missing images and masks do not stop indexing at the first one: validation lists every
    missing file together with the other problems (here a truncated PNG) in one error."""
    from progressive_avatars.core.io.validate import dataset_problems, validate_dataset

    root = tmp_path / "ds"
    write_mesh_dataset(root)
    gone = [root / "images" / f"{n}.png" for n in ("00000_00", "00001_01", "00002_00")]
    gone.append(root / "fg_masks" / "00002_01.png")
    for p in gone:
        os.remove(p)
    cut = root / "images" / "00000_01.png"
    cut.write_bytes(cut.read_bytes()[:100])
    ds = Dataset(root)
    problems = dataset_problems(ds, progress=False)
    assert len(problems) == 5, problems
    with pytest.raises(DataError, match=r"5 problem\(s\)") as ei:
        validate_dataset(ds, progress=False)
    text = str(ei.value)
    for p in gone[:3]:
        assert f"{p}: image listed in {ds.json_path} not found" in text
    assert f"{gone[3]}: mask listed in {ds.json_path} not found" in text
    assert f"{cut}: image: cannot be decoded" in text
    with pytest.raises(MissingFileError, match=r"00001_01\.png: image listed in"):
        ds[3]
    # Split between processes (each rank of a training job checks its share): the shares
    # together find exactly the whole check's problems, each once.
    shares = [dataset_problems(ds, progress=False, share=(k, 3)) for k in range(3)]
    assert sorted(sum(shares, [])) == sorted(problems) and all(len(s) < len(problems) for s in shares)
    with pytest.raises(ValueError, match="share"):
        dataset_problems(ds, progress=False, share=(3, 3))


def _set(i, key, value):
    return lambda m: m["frames"][i].__setitem__(key, value)


@pytest.mark.parametrize(
    "edit, message",
    [
        (_set(0, "timestep_index", None), r"frames\[0\]: timestep_index must be a whole number, got None"),
        (_set(2, "timestep_index", "x"), r"frames\[2\]: timestep_index must be a whole number, got 'x'"),
        (_set(1, "camera_index", [0]), r"frames\[1\]: camera_index must be a whole number, got \[0\]"),
        (_set(0, "fl_x", [1, 2]), r"frames\[0\]: fl_x must be a number, got \[1, 2\]"),
        (_set(4, "cx", "mid"), r"frames\[4\]: cx must be a number, got 'mid'"),
        (_set(1, "w", "wide"), r"frames\[1\]: w must be a positive whole number, got 'wide'"),
        (
            _set(3, "transform_matrix", "abc"),
            r"frames\[3\]: transform_matrix must be a 4x4 .*array of numbers, got 'abc'",
        ),
        (
            _set(0, "transform_matrix", [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
            r"frames\[0\]: transform_matrix must be a 4x4 .*got \[\[1, 0, 0, 0\], \[0, 1, 0\]",
        ),
        (_set(0, "file_path", None), r"frames\[0\]: file_path must be a file path \(a string\), got None"),
        (_set(5, "fg_mask_path", 7), r"frames\[5\]: fg_mask_path must be a file path \(a string\), got 7"),
        (_set(2, "mesh_path", None), r"frames\[2\]: mesh_path must be a file path \(a string\), got None"),
        (lambda m: m["frames"].__setitem__(1, 5), r"frames\[1\] must be an object \(one frame\), got 5"),
        (lambda m: m.__setitem__("frames", {"a": 1}), r"'frames' must be a list of frame objects"),
        (lambda m: m.__setitem__("background", "white"), r"'background' must be \[r,g,b\], got 'white'"),
        (lambda m: m.__setitem__("canonical_mesh_path", 3), r"canonical_mesh_path must be a file path"),
    ],
)
def test_dataset_hostile_fields_name_file_frame_and_field(tmp_path, edit, message):
    """A wrong type or shape in transforms_*.json is a DataError naming the file, the frame
    and the field, never a bare TypeError/KeyError/ValueError from deep inside."""
    root = tmp_path / "ds"
    write_mesh_dataset(root)
    edit_json(root, "train", edit)
    with pytest.raises(DataError, match=r"transforms_train\.json: " + message):
        Dataset(root)


def test_dataset_frame_problems_are_listed_together_and_empty_faces_refused(tmp_path):
    root = tmp_path / "ds"
    write_mesh_dataset(root)

    def two(m):
        m["frames"][1]["timestep_index"] = None
        m["frames"][4]["transform_matrix"] = "abc"

    edit_json(root, "train", two)
    with pytest.raises(DataError, match=r"transforms_train\.json: 2 problem\(s\)") as ei:
        Dataset(root)
    assert "frames[1]: timestep_index" in str(ei.value) and "frames[4]: transform_matrix" in str(ei.value)
    # A bad top-level fallback is one problem, not one per frame.
    write_mesh_dataset(root, top_level_intrinsics=True)
    edit_json(root, "train", lambda m: m.__setitem__("fl_x", "abc"))
    with pytest.raises(DataError, match=r"transforms_train\.json: top-level fl_x must be a number, got 'abc'$"):
        Dataset(root)
    write_mesh_dataset(root)
    np.savez(root / "canonical_mesh.npz", vertices=octahedron(0), faces=OCTA_F[:0])
    with pytest.raises(DataError, match=r"canonical_mesh\.npz: the canonical mesh has no faces"):
        Dataset(root)


def test_validate_accepts_the_pixel_formats_the_loader_reads(tmp_path):
    """1-bit PNG masks and CMYK JPEG images are read by Dataset.images, so the pre-training
    check accepts them too (one definition of the readable formats); a float image is refused
    by both."""
    from PIL import Image

    from progressive_avatars.core.io.dataset import IMAGE_MODES
    from progressive_avatars.core.io.validate import dataset_problems

    assert {"1", "CMYK", "YCbCr", "I;16"} <= IMAGE_MODES
    root = tmp_path / "ds"
    write_mesh_dataset(root)
    ref = Dataset(root, cache_images=0)
    masks = [ref.images(i)[1] for i in range(len(ref))]
    for info in ref.frames:
        Image.open(info.mask_path).convert("1").save(info.mask_path)
    img0 = ref.frames[0].image_path
    Image.open(img0).convert("CMYK").save(root / "images" / "cmyk.jpg", quality=100)
    edit_json(root, "train", _set(0, "file_path", "images/cmyk.jpg"))
    ds = Dataset(root, cache_images=0)
    assert Image.open(ds.frames[0].mask_path).mode == "1"
    assert dataset_problems(ds, progress=False) == []
    for i, want in enumerate(masks):
        np.testing.assert_array_equal(ds.images(i)[1], want)  # binary masks read as 0 / 1
    np.testing.assert_allclose(ds.images(0)[0], ref.images(0)[0], atol=0.1)
    Image.open(img0).convert("F").save(root / "images" / "float.tif")
    edit_json(root, "train", _set(0, "file_path", "images/float.tif"))
    ds = Dataset(root, cache_images=0)
    assert dataset_problems(ds, progress=False) == [
        f"{ds.frames[0].image_path}: image has pixel format 'F'; use 8-bit RGB/RGBA/L or 16-bit greyscale PNG"
    ]
    with pytest.raises(DataError, match="pixel format 'F'"):
        ds.images(0)


def test_flame_mode_dataset(tmp_path, flame_model):
    from PIL import Image

    root = tmp_path / "fds"
    (root / "flame_param").mkdir(parents=True)
    (root / "images").mkdir()
    prm = random_params(2, seed=9)
    canon = ga_frame(prm, 0)
    canon.update(expr=np.zeros((1, N_EXPR)), jaw_pose=np.zeros((1, 3)), rotation=np.zeros((1, 3)))
    np.savez(root / "canonical_flame_param.npz", **canon)
    cam = make_cameras()[0]
    frames = []
    for t in range(2):
        np.savez(root / "flame_param" / f"{t:05d}.npz", **ga_frame(prm, t))
        Image.new("RGB", (W, H), (255, 255, 255)).save(root / "images" / f"{t}.png")
        frames.append(
            dict(
                file_path=f"images/{t}.png",
                transform_matrix=cam.c2w_opengl().tolist(),
                fl_x=cam.fx,
                fl_y=cam.fy,
                cx=cam.cx,
                cy=cam.cy,
                w=W,
                h=H,
                timestep_index=t,
                camera_index=0,
                flame_param_path=f"flame_param/{t:05d}.npz",
            )
        )
    (root / "transforms_train.json").write_text(json.dumps({"frames": frames}))
    with pytest.raises(DataError, match="FLAME-mode dataset"):
        Dataset(root)
    ds = Dataset(root, flame_model=flame_model)
    assert ds.mode == "flame"
    np.testing.assert_allclose(ds[1].vertices, flame_forward(flame_model, **ga_frame(prm, 1))[0], atol=1e-6)
    np.testing.assert_allclose(ds.canonical_vertices, flame_forward(flame_model, **canon)[0], atol=1e-6)
    np.testing.assert_array_equal(ds.faces, flame_model.faces)
    np.testing.assert_array_equal(ds[0].mask, 1.0)  # no mask file, no alpha: everything is foreground
    # A file without one of the parameters is refused, naming it (as zeros it moved the head
    # silently: a missing rotation by ~10 cm); the offsets may be left out.
    partial = ga_frame(prm, 1)
    del partial["static_offset"]
    np.savez(root / "flame_param" / "00001.npz", **partial)
    Dataset(root, flame_model=flame_model).vertices_at(1)
    for key in ("rotation", "shape", "expr", "jaw_pose"):
        partial = ga_frame(prm, 1)
        del partial[key]
        np.savez(root / "flame_param" / "00001.npz", **partial)
        with pytest.raises(DataError, match=rf"00001\.npz: FLAME parameters lack {key} "):
            Dataset(root, flame_model=flame_model).vertices_at(1)


def test_background_outside_0_1_is_refused(tmp_path):
    root = tmp_path / "ds"
    write_mesh_dataset(root, background=[255, 255, 255])  # 8-bit values: images would reach 255
    with pytest.raises(DataError, match=r"transforms_train\.json: 'background' must be \[r,g,b\] in \[0,1\]"):
        Dataset(root, "train")


def test_flame_track_reads_parameters_without_a_model(tmp_path, flame_model):
    from progressive_avatars.core.io.sequences import read_flame_track

    prm = random_params(4, seed=8)
    np.savez(tmp_path / "tracked.npz", **prm)
    track = read_flame_track(tmp_path / "tracked.npz", frames=[3, 1])
    assert track.n_frames == 2
    np.testing.assert_array_equal(track.params["expr"], prm["expr"][[3, 1]])
    np.testing.assert_allclose(
        flame_forward(flame_model, **track.params),
        read_sequence(tmp_path / "tracked.npz", frames=[3, 1], flame_model=flame_model).vertices,
    )
    fp = tmp_path / "ga" / "flame_param"
    fp.mkdir(parents=True)
    for t in range(4):
        np.savez(fp / f"{t:05d}.npz", **ga_frame(prm, t))
    np.testing.assert_array_equal(read_flame_track(tmp_path / "ga").params["jaw_pose"], prm["jaw_pose"])
    partial = ga_frame(prm, 2)
    del partial["eyes_pose"]
    np.savez(fp / "00002.npz", **partial)
    with pytest.raises(DataError, match=r"00002\.npz: FLAME parameters lack eyes_pose "):
        read_flame_track(tmp_path / "ga")
    np.savez(tmp_path / "mesh.npz", vertices=np.zeros((2, 3, 3)), faces=np.array([[0, 1, 2]]))
    with pytest.raises(DataError, match=r"mesh\.npz: holds meshes, not FLAME parameters"):
        read_flame_track(tmp_path / "mesh.npz")


def test_missing_dataset_folder_is_named(tmp_path):
    from progressive_avatars.core.io.sequences import MissingFileError

    for split in ("train", None):
        with pytest.raises(MissingFileError, match=r"nope: dataset folder not found"):
            Dataset(str(tmp_path / "nope"), split)


def test_camera_problems_name_values_that_would_project_garbage():
    """NaN/inf intrinsics (camera_angle_x 0 gives fx = inf), a zero, scaled or mirrored
    rotation and absurd translations: each named (validate_dataset lists them before training,
    the Blender camera import refuses them), none missed on a good camera."""
    from progressive_avatars.core.io.validate import camera_problems

    good = dict(R=np.eye(3), t=np.zeros(3), fx=50.0, fy=50.0, cx=16.0, cy=16.0, width=32, height=32)
    assert camera_problems(Camera(**good), "cam") == []
    bad = {
        "principal point cx is nan": dict(cx=np.nan),
        "focal length fx is inf": dict(fx=np.inf),
        "placed beyond": dict(t=np.array([0.0, 0.0, 1e300])),
        "not a rotation": dict(R=np.zeros((3, 3))),
        "not a rotation ": dict(R=2 * np.eye(3)),
        "not a rotation  ": dict(R=np.diag([-1.0, 1.0, 1.0])),
    }
    for what, change in bad.items():
        problems = camera_problems(Camera(**{**good, **change}), "cam")
        assert len(problems) == 1 and what.strip() in problems[0], (what, problems)


def test_validate_checks_each_camera_once_and_names_every_frame(tmp_path):
    """dataset_problems checks each camera once, however many frames share it (16,000 frames:
    1.1 s -> 0.01 s, review_loops_work/bench_validate_cameras.py), and lists for every frame the
    strings camera_problems gives it, in frame order, in every share."""
    from progressive_avatars.core.io.validate import camera_problems, dataset_problems

    root = tmp_path / "ds"
    write_mesh_dataset(root)

    def spoil(m):
        for fr in m["frames"]:
            if fr["camera_index"] == 1:  # a scaled matrix: not a rotation
                fr["transform_matrix"] = (2 * np.array(fr["transform_matrix"])).tolist()
        m["frames"][2]["cx"] = math.inf  # one frame of camera 0: a camera of its own

    edit_json(root, "train", spoil)
    ds = Dataset(root)
    assert len({id(f.camera) for f in ds.frames}) == 3
    for k, n in ((0, 1), (1, 2)):
        want = [p for f in ds.frames[k::n] for p in camera_problems(f.camera, f"{ds.json_path}: frames[{f.index}]")]
        got = [
            p for p in dataset_problems(ds, progress=False, share=(k, n)) if p.startswith(f"{ds.json_path}: frames[")
        ]
        assert got == want and len(want) == (4 if n == 1 else 3), got


def test_cameras_read_without_geometry(tiny_dataset, tmp_path):
    """A camera import needs neither the canonical mesh nor (FLAME mode) a FLAME model."""
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(tiny_dataset, root)
    full = Dataset(str(root), "train").cameras
    os.remove(root / "canonical_mesh.npz")
    with pytest.raises(MissingFileError, match="canonical_mesh.npz"):
        Dataset(str(root), "train")
    bare = Dataset(str(root), "train", geometry=False)
    assert bare.faces is None and sorted(bare.cameras) == sorted(full)
    for k, cam in full.items():
        np.testing.assert_array_equal(bare.cameras[k].R, cam.R)
        assert (bare.cameras[k].fx, bare.cameras[k].width) == (cam.fx, cam.width)


# ------------------------------------------------------------ tracked parameters, checked


def _nersemble(prm, **over):
    d = dict(
        shape=prm["shape"][None],
        expression=prm["expr"],
        jaw=prm["jaw_pose"],
        neck=prm["neck_pose"],
        eyes=prm["eyes_pose"],
        translation=prm["translation"],
        scale=np.array([[1.0]]),
        frames=np.arange(len(prm["expr"])),
    )
    d.update(over)
    return d


def test_vhap_any_key_may_be_one_shared_row(tmp_path, flame_model):
    """The frame count is the longest key's, whichever comes first: a shared global rotation
    (1,3) beside per-frame expressions loads, as a shared translation does."""
    prm = random_params(4, seed=3)
    for key in ("rotation", "translation"):
        path = tmp_path / f"tracked_flame_params_{key}.npz"
        np.savez(path, **dict(prm, **{key: prm[key][:1]}))
        seq = read_vhap_tracked(path, flame_model=flame_model)
        want = flame_forward(flame_model, **dict(prm, **{key: np.repeat(prm[key][:1], 4, 0)}))
        assert seq.n_frames == 4
        np.testing.assert_allclose(seq.vertices, want, atol=1e-6)


def test_flame_param_folder_files_must_agree(tmp_path, flame_model):
    """Every frame's file holds the same widths and the same subject (shape, static offset):
    a file that does not is refused by name, not read as another frame of this subject."""
    prm = random_params(3, seed=4)
    for case in ("width", "shape"):
        folder = tmp_path / case / "flame_param"
        folder.mkdir(parents=True)
        for t in range(3):
            f = ga_frame(prm, t)
            if t == 2 and case == "width":
                f["expr"] = f["expr"][:, :2]
            if t == 2 and case == "shape":
                f["shape"] = f["shape"] + 1.0
            np.savez(folder / f"{t:05d}.npz", **f)
        match = (
            r"00002\.npz: 'expr' has 2 values" if case == "width" else r"00002\.npz: 'shape' differs from 00000\.npz"
        )
        with pytest.raises(DataError, match=match):
            read_flame_param_folder(tmp_path / case, flame_model=flame_model)


def test_nersemble_placement_and_frames_are_checked(tmp_path, flame_model):
    """One scale per sequence, positive; rotations that are rotations; a 1-D expression is one
    frame; whole-number float ids are ids; a frame-id list of another length is refused; a
    pose of the wrong width is refused, not re-cut into other frames."""
    prm = random_params(3, seed=5)
    shear = np.eye(3)
    shear[0, 1] = 0.2
    for name, over, match in (
        ("scales", dict(scale=np.array([1.0, 2.0, 3.0])), "'scale' must be one value"),
        ("zero", dict(scale=np.array([0.0])), "'scale' must be positive"),
        ("shear", dict(rotation_matrices=np.repeat(shear[None], 3, 0)), "must be rotations"),
        ("mirror", dict(rotation_matrices=np.repeat(np.diag([-1.0, 1, 1])[None], 3, 0)), "must be rotations"),
        ("ids", dict(frames=np.array([100, 101])), "'frames' holds 2 frame ids for 3 frames"),
        ("eyes", dict(eyes=prm["eyes_pose"][:, :3]), "'eyes' must have 6 values per frame"),
    ):
        np.savez(tmp_path / f"{name}.npz", **_nersemble(prm, **over))
        with pytest.raises(DataError, match=match):
            read_nersemble_tracking(tmp_path / f"{name}.npz", evaluate=False)
    p1 = random_params(1, seed=7)
    np.savez(tmp_path / "one.npz", **_nersemble(p1, expression=p1["expr"][0], frames=np.array([4])))
    one = read_nersemble_tracking(tmp_path / "one.npz", flame_model=flame_model)
    assert one.n_frames == 1 and list(one.frame_ids) == [4]
    np.savez(tmp_path / "float_ids.npz", **_nersemble(prm, frames=np.array([7.0, 8.0, 9.0])))
    assert list(read_nersemble_tracking(tmp_path / "float_ids.npz", evaluate=False).frame_ids) == [7, 8, 9]
    np.savez(tmp_path / "tracked_flame_params.npz", timestep_id=np.array([1, 2]), **prm)
    with pytest.raises(DataError, match="'timestep_id' holds 2 frame ids for 3 frames"):
        read_vhap_tracked(tmp_path / "tracked_flame_params.npz", evaluate=False)


def test_flame_pose_rows_are_frames(flame_model):
    """An eyes pose of two rows of 3 for two frames is the wrong width, not one frame of 6."""
    prm = random_params(2, seed=6)
    with pytest.raises(ValueError, match="eyes_pose: expected 6 values per frame"):
        flame_forward(flame_model, **dict(prm, eyes_pose=prm["eyes_pose"][:, :3]))
    both = np.concatenate([prm["eyes_pose"][:, :3], prm["eyes_pose"][:, 3:]], 1).reshape(2, 2, 3)
    np.testing.assert_allclose(
        flame_forward(flame_model, **dict(prm, eyes_pose=both)), flame_forward(flame_model, **prm)
    )


def test_rgba_downscale_composites_before_shrinking(tmp_path):
    """An RGBA image (transparent pixels black, as most exporters store them) downscaled: the
    outline is the average of the composited full-size pixels, not darkened by the black of the
    transparent ones (it was composited after shrinking colour and alpha apart: 50/255 off)."""
    from PIL import Image

    root = tmp_path / "rgba"
    (root / "images").mkdir(parents=True)
    (root / "meshes").mkdir()
    verts = np.array([[-0.1, -0.1, -1.0], [0.1, -0.1, -1.0], [0.0, 0.1, -1.0]], np.float32)
    np.savez(root / "canonical_mesh.npz", vertices=verts, faces=np.array([[0, 1, 2]], np.int32))
    np.savez(root / "meshes" / "00000.npz", vertices=verts)
    W, H = 8, 4
    px = np.zeros((H, W, 4), np.uint8)
    px[:, :3] = (200, 40, 40, 255)  # three opaque columns; the edge falls inside a 2x2 block
    Image.fromarray(px, "RGBA").save(root / "images" / "00000_00.png")
    frame = {"file_path": "images/00000_00.png", "transform_matrix": np.eye(4).tolist(), "fl_x": 10.0}
    frame.update(w=W, h=H, timestep_index=0, camera_index=0, mesh_path="meshes/00000.npz")
    (root / "transforms_train.json").write_text(json.dumps({"frames": [frame], "background": [1, 1, 1]}))
    full = Dataset(root, "train")[0].image
    half = Dataset(root, "train", downscale=2.0)[0].image
    np.testing.assert_allclose(half, full.reshape(H // 2, 2, W // 2, 2, 3).mean((1, 3)), atol=1e-6)
    # the same frame under a negative index is one cache entry, not a second decode
    ds = Dataset(root, "train")
    assert ds.images(-1)[0] is ds.images(0)[0] and ds.cached_bytes == full.nbytes + H * W * 4
    with pytest.raises(IndexError, match="frame 1 out of range"):
        ds.images(1)


TRI = np.array([[-0.1, -0.1, -1.0], [0.1, -0.1, -1.0], [0.0, 0.1, -1.0]], np.float32)


def write(root, frames, images=(), meta=None):
    """A one-triangle mesh-mode dataset: ``frames`` (dicts completed with defaults), ``images``
    {relative path: PIL image}."""
    (root / "meshes").mkdir(parents=True, exist_ok=True)
    (root / "images").mkdir(exist_ok=True)
    np.savez(root / "canonical_mesh.npz", vertices=TRI, faces=np.array([[0, 1, 2]], np.int32))
    np.savez(root / "meshes" / "00000.npz", vertices=TRI)
    np.savez(root / "meshes" / "00001.npz", vertices=TRI * 1.1)
    rows = []
    for fr in frames:
        row = {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist(), "timestep_index": 0}
        row.update(camera_index=0, mesh_path="meshes/00000.npz")
        row.update(fr)
        rows.append(row)
    for rel, im in dict(images).items():
        im.save(root / rel)
    (root / "transforms_train.json").write_text(json.dumps(dict(meta or {}, frames=rows)))
    return root


def test_camera_angle_x_is_the_horizontal_field_of_view(tmp_path):
    # fov_x = 2 atan(0.5): fl_x = (w/2) / tan(fov_x/2) = 32 / 0.5 = 64 (not h-based 48); fl_y defaults to fl_x
    root = write(tmp_path / "d", [{"camera_angle_x": 2 * math.atan(0.5), "w": 64, "h": 48}])
    c = Dataset(root, "train").cameras[0]
    assert c.fx == pytest.approx(64.0) and c.fy == pytest.approx(64.0)


def test_principal_point_defaults_to_half_the_size_and_scales_with_downscale(tmp_path):
    root = write(tmp_path / "d", [{"fl_x": 80.0, "fl_y": 90.0, "w": 64, "h": 48}])
    c = Dataset(root, "train").cameras[0]
    assert (c.cx, c.cy, c.width, c.height) == (32.0, 24.0, 64, 48)
    c2 = Dataset(root, "train", downscale=2.0).cameras[0]
    assert (c2.fx, c2.fy, c2.cx, c2.cy, c2.width, c2.height) == pytest.approx((40.0, 45.0, 16.0, 12.0, 32, 24))


def test_transparent_pixels_take_the_datasets_background(tmp_path):
    from PIL import Image

    px = np.zeros((2, 3, 4), np.uint8)
    px[:, 0] = (200, 40, 40, 255)  # opaque
    px[:, 1] = (0, 0, 0, 0)  # transparent (black underneath, as exporters store it)
    px[:, 2] = (100, 100, 100, 51)  # alpha 0.2
    bg = [0.2, 0.4, 0.6]
    root = write(tmp_path / "d", [{"fl_x": 5.0, "w": 3, "h": 2}], {"images/a.png": Image.fromarray(px, "RGBA")},
                 {"background": bg})  # fmt: skip
    s = Dataset(root, "train")[0]
    np.testing.assert_allclose(s.image[0, 0], [200 / 255, 40 / 255, 40 / 255], atol=1e-6)
    np.testing.assert_allclose(s.image[0, 1], bg, atol=1e-6)
    a = 51 / 255
    np.testing.assert_allclose(s.image[1, 2], 100 / 255 * a + np.array(bg) * (1 - a), atol=1e-6)
    np.testing.assert_allclose(s.mask[0], [1.0, 0.0, a], atol=1e-6)


def test_16bit_mask_values_round_to_the_nearest_8bit_level(tmp_path):
    from PIL import Image

    vals = np.array([[0, 200, 32896, 65535]], np.uint16)  # -> round(v*255/65535): 0, 1 (0.78), 128, 255
    mask = Image.fromarray(vals)
    assert mask.mode.startswith("I;16")
    rgb = Image.new("RGB", (4, 1), (10, 20, 30))
    root = write(tmp_path / "d", [{"fl_x": 5.0, "w": 4, "h": 1, "fg_mask_path": "images/m.png"}],
                 {"images/a.png": rgb, "images/m.png": mask})  # fmt: skip
    np.testing.assert_allclose(Dataset(root, "train")[0].mask[0], np.array([0, 1, 128, 255]) / 255, atol=1e-7)


def test_downscaled_mask_is_box_filtered(tmp_path):
    from PIL import Image

    m = np.zeros((2, 4), np.uint8)
    m[0, 0] = m[1, 0] = 255  # left 2x2 block half white; right block all white except one pixel
    m[:, 2:] = 255
    m[1, 3] = 0
    root = write(tmp_path / "d", [{"fl_x": 5.0, "w": 4, "h": 2, "fg_mask_path": "images/m.png"}],
                 {"images/a.png": Image.new("RGB", (4, 2)), "images/m.png": Image.fromarray(m, "L")})  # fmt: skip
    mask = Dataset(root, "train", downscale=2.0)[0].mask
    assert mask.shape == (1, 2)
    np.testing.assert_allclose(mask[0], [0.5, 0.75], atol=1.01 / 255)  # block means, 8-bit rounded


def test_frames_of_one_timestep_must_name_one_mesh(tmp_path):
    frames = [
        {"fl_x": 5.0, "w": 4, "h": 4},
        {"fl_x": 5.0, "w": 4, "h": 4, "camera_index": 1, "mesh_path": "meshes/00001.npz"},
    ]
    root = write(tmp_path / "d", frames)
    with pytest.raises(
        DataError, match=r"frames\[1\]: timestep 0 refers to .*00001\.npz, an earlier frame to .*00000\.npz"
    ):
        Dataset(root, "train")


def test_a_3x4_transform_matrix_reads_as_its_4x4(tmp_path):
    # OpenGL c2w: camera at (0.1, 0.2, 0.3), rotated 90 degrees about y (looks down world -x)
    c2w = np.array([[0, 0, 1, 0.1], [0, 1, 0, 0.2], [-1, 0, 0, 0.3], [0, 0, 0, 1]], float)
    root = write(tmp_path / "d", [{"fl_x": 5.0, "w": 4, "h": 4, "transform_matrix": c2w[:3].tolist()}])
    c = Dataset(root, "train").cameras[0]
    # OpenCV w2c: R = (c2w_R @ diag(1,-1,-1)).T, t = -R @ centre
    R = (c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])).T
    np.testing.assert_allclose(c.R, R, atol=1e-12)
    np.testing.assert_allclose(c.t, -R @ c2w[:3, 3], atol=1e-12)


def test_sees_mesh_bounds_u_by_the_width_and_v_by_the_height():
    # A wide image (100x20), identity pose, principal point (50, 10), f = 10: a point at camera
    # (x, y, 1) lands on pixel (50 + 10x, 10 + 10y).
    cam = Camera(np.eye(3), np.zeros(3), 10.0, 10.0, 50.0, 10.0, 100, 20)
    assert sees_mesh(cam, np.array([[3.0, 0.0, 1.0]]))  # u = 80 (< 100, but > the height 20)
    assert not sees_mesh(cam, np.array([[5.5, 0.0, 1.0]]))  # u = 105: right of the image
    assert not sees_mesh(cam, np.array([[-5.5, 0.0, 1.0]]))  # u = -5: left of it
    assert not sees_mesh(cam, np.array([[0.0, 1.5, 1.0]]))  # v = 25: below it
    assert not sees_mesh(cam, np.array([[0.0, 0.0, -1.0]]))  # behind the camera


def test_frames_of_one_camera_share_the_camera_built_from_their_values(tmp_path):
    """A camera is built once per distinct set of values (matrix and intrinsics), not per frame:
    each frame's camera is the one its own row gives, bit for bit, at every downscale; a frame
    whose values differ (one number, or 1 against 1.0 written) gets its own."""
    root = tmp_path / "ds"
    write_mesh_dataset(root)

    def vary(m):  # camera 0 at timesteps 1 and 2
        at = {(f["timestep_index"], f["camera_index"]): f for f in m["frames"]}
        at[1, 0]["fl_x"] *= 1 + 2**-40
        at[2, 0]["w"] = float(at[2, 0]["w"])  # the same size, written as 64.0

    edit_json(root, "train", vary)
    rows = json.loads((root / "transforms_train.json").read_text())
    for downscale in (1.0, 2.0):
        ds = Dataset(root, downscale=downscale)
        for f, row in zip(ds.frames, rows["frames"]):
            own, size = ds._camera(row, rows, "")
            own = own if downscale == 1.0 else own.scaled(1.0 / downscale)
            assert size == f.full_size
            for name in ("R", "t", "fx", "fy", "cx", "cy", "width", "height"):
                assert np.array_equal(getattr(own, name), getattr(f.camera, name)), name
        n_cams = len({f.camera_index for f in ds.frames})
        assert len({id(f.camera) for f in ds.frames}) == n_cams + 2
