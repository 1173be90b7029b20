"""The synthetic default dataset: template, rig, appearance detail and the written files."""

import json
import os

import numpy as np
import pytest
import trimesh
from PIL import Image

from progressive_avatars.core.synthetic import dataset, raycast, rig, surface, texture
from progressive_avatars.core.geometry.camera import Camera


@pytest.fixture(scope="module")
def template():
    return surface.head_template()


def _face_regions(v, f):
    c = v[f].mean(axis=1)
    x, y, z = c.T
    eyes = (z > 0.06) & (np.abs(y - 0.018) < 0.008) & (np.abs(np.abs(x) - 0.032) < 0.012)
    mouth = (z > 0.06) & (np.abs(y - surface.MOUTH_Y) < 0.008) & (np.abs(x) < 0.022)
    back = (z < -0.05) & (y > -0.05)
    cheeks = (z > 0.03) & (np.abs(np.abs(x) - 0.05) < 0.01) & (np.abs(y + 0.025) < 0.01)
    scalp = y > 0.09
    return dict(eyes=eyes, mouth=mouth, back=back, cheeks=cheeks, scalp=scalp)


def test_template_watertight_sized_and_uneven(template):
    v, f = template
    assert v.dtype == np.float32 and f.dtype == np.int32
    assert 2000 <= len(f) <= 6000
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward winding
    lo, hi = mesh.bounds
    assert 0.08 < hi[0] < 0.1 and hi[1] > 0.1 and lo[1] < -0.2 and hi[2] > 0.1  # head, neck, nose
    area = mesh.area_faces
    r = _face_regions(v, f)
    for name in ("eyes", "mouth", "back"):
        assert r[name].sum() > 20, name
    fine = np.median(area[r["eyes"] | r["mouth"]])
    assert np.median(area[r["back"]]) > 3.0 * fine
    assert np.degrees(mesh.face_angles.min()) > 1.0  # no slivers


def test_rig_smooth_finite_and_jaw_opens(template):
    v, _ = template
    assert np.array_equal(rig.pose_head(v, rig.neutral_params()), v)
    # lowest frontal vertex of the face (above the throat)
    chin = np.argmin(np.where((v[:, 2] > 0.06) & (np.abs(v[:, 0]) < 0.01) & (v[:, 1] > -0.14), v[:, 1], np.inf))
    assert -0.13 < v[chin, 1] < -0.09
    opened = rig.pose_head(v, {"jaw": 1.0})
    assert opened[chin, 1] < v[chin, 1] - 0.01
    forehead = np.argmax(np.where(v[:, 2] > 0.05, v[:, 1], -np.inf))
    assert np.allclose(opened[forehead], v[forehead], atol=1e-6)
    full = {"jaw": 1.0, "blink": 1.0, "smile": 1.0, "rotation": (25.0, 15.0, 10.0), "translation": (0.02, 0.01, 0.0)}
    prev = rig.pose_head(v, rig.neutral_params())
    for a in np.linspace(0.05, 1.0, 20):  # small parameter steps move vertices by small amounts
        p = {
            "jaw": a,
            "blink": a,
            "smile": a,
            "rotation": tuple(a * np.array(full["rotation"])),
            "translation": tuple(a * np.array(full["translation"])),
        }
        cur = rig.pose_head(v, p)
        assert np.all(np.isfinite(cur))
        assert np.abs(cur - prev).max() < 0.012
        prev = cur
    for smile in (-1.0, 1.0):
        assert np.all(np.isfinite(rig.pose_head(v, {"smile": smile})))
    # sequences are smooth in time and the test sequence differs from all training ones
    seq = [rig.sequence_params(0, k, 8) for k in range(8)]
    jaws = np.array([p["jaw"] for p in seq])
    assert np.abs(np.diff(jaws)).max() < 0.6 and jaws.max() > 0.5


def test_detail_higher_on_scalp_eyes_lips_than_cheeks(template):
    v, f = template
    d = texture.face_detail(v, f)
    assert d.shape == (len(f),) and d.dtype == np.float32 and np.all(np.isfinite(d))
    r = _face_regions(v, f)
    cheeks = np.mean(d[r["cheeks"]])
    for name in ("scalp", "eyes", "mouth"):
        assert np.mean(d[r[name]]) > 4.0 * cheeks, name


def test_coarse_template_dataset_tracks_the_same_imaged_head(tmp_path):
    """--template-subdivisions 3: a 1280-face tracked mesh whose vertices are a subset of the
    imaged 5120-face surface in every frame (same rig), and the very same images."""
    kw = dict(resolution=24, cameras=2, sequences=2, frames=2, progress=False)
    dataset.make_dataset(tmp_path / "fine", **kw)
    summary = dataset.make_dataset(tmp_path / "coarse", template_subdivisions=3, **kw)
    assert summary["faces"] == 1280 and summary["vertices"] == 642
    with np.load(tmp_path / "coarse" / "canonical_mesh.npz") as z:
        assert z["faces"].shape == (1280, 3) and z["faces"].max() == 641
    with np.load(tmp_path / "coarse" / "detail.npz") as z:
        assert z["face_detail"].shape == (1280,)
    for T in range(4):
        with (
            np.load(tmp_path / "coarse" / "meshes" / f"{T:05d}.npz") as c,
            np.load(tmp_path / "fine" / "meshes" / f"{T:05d}.npz") as f,
        ):
            assert np.array_equal(c["vertices"], f["vertices"][:642])
    for name in sorted(os.listdir(tmp_path / "fine" / "images")):
        a = np.asarray(Image.open(tmp_path / "fine" / "images" / name))
        b = np.asarray(Image.open(tmp_path / "coarse" / "images" / name))
        assert np.array_equal(a, b), name


def test_tiny_dataset(tmp_path):
    out = tmp_path / "ds"
    summary = dataset.make_dataset(out, resolution=32, cameras=4, sequences=2, frames=2, progress=False)
    assert summary["images"] == 2 * 2 * 4
    v, f = surface.head_template()
    with np.load(out / "canonical_mesh.npz") as z:
        assert z["faces"].dtype == np.int32 and z["vertices"].dtype == np.float32
        assert z["vertices"].shape == v.shape and np.array_equal(z["faces"], f)
    with np.load(out / "detail.npz") as z:
        assert z["face_detail"].shape == (len(f),)
    docs = {}
    for split in ("train", "val", "test", ""):
        name = f"transforms_{split}.json" if split else "transforms.json"
        with open(out / name) as fh:
            docs[split] = json.load(fh)
        assert docs[split]["background"] == [1.0, 1.0, 1.0]
        assert isinstance(docs[split]["sequences"], list)
    held = raycast.held_out_camera(4)
    train, val, test = docs["train"]["frames"], docs["val"]["frames"], docs["test"]["frames"]
    # 1 training sequence x 2 frames x 3 cameras; held-out camera on training timesteps; test sequence x all cameras
    assert len(train) == 1 * 2 * 3 and len(val) == 1 * 2 * 1 and len(test) == 1 * 2 * 4
    assert len(docs[""]["frames"]) == 16
    assert all(fr["camera_index"] != held and fr["sequence"] == 0 for fr in train)
    assert all(fr["camera_index"] == held and fr["sequence"] == 0 for fr in val)
    assert all(fr["sequence"] == 1 for fr in test) and {fr["camera_index"] for fr in test} == set(range(4))
    assert sorted(fr["timestep_index"] for fr in docs[""]["frames"])[::4] == [0, 1, 2, 3]

    facing_hits = []
    for fr in docs[""]["frames"]:
        for key in ("file_path", "fg_mask_path", "mesh_path"):
            assert os.path.exists(out / fr[key]), fr[key]
        assert fr["file_path"] == f"images/{fr['timestep_index']:05d}_{fr['camera_index']:02d}.png"
        img = np.asarray(Image.open(out / fr["file_path"]))
        mask = np.asarray(Image.open(out / fr["fg_mask_path"]))
        assert img.shape == (fr["h"], fr["w"], 3) and img.dtype == np.uint8
        assert mask.shape == (fr["h"], fr["w"]) and mask.dtype == np.uint8
        assert (fr["w"], fr["h"]) == (22, 32) and isinstance(fr["cx"], float)
        assert 0 < mask.mean() / 255 < 0.8 and len(np.unique(mask)) > 2  # anti-aliased coverage
        assert np.all(img[mask == 0] == 255)  # composited over white
        cam = Camera.from_c2w_opengl(
            fr["transform_matrix"], fr["fl_x"], fr["fl_y"], fr["cx"], fr["cy"], fr["w"], fr["h"]
        )
        with np.load(out / fr["mesh_path"]) as z:
            verts = z["vertices"]
        assert verts.shape == v.shape
        vn = surface.vertex_normals(verts, f)
        facing = np.einsum("nd,nd->n", vn, cam.center - verts) > 0
        uv, depth = cam.project(verts[facing])
        assert np.all(depth > 0)
        i, j = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (i >= 0) & (i < fr["w"]) & (j >= 0) & (j < fr["h"])
        assert inside.mean() > 0.98
        facing_hits.append((mask[j[inside], i[inside]] > 0).mean())
    assert np.mean(facing_hits) > 0.97


def test_render_views_pixel_centres_and_coverage(template):
    v, f = template
    cams = raycast.make_cameras(2, resolution=24)
    images, masks = raycast.render_views(v, f, cams, supersample=1)
    assert images.shape == (2, 24, 16, 3) and masks.shape == (2, 24, 16)
    assert set(np.unique(masks)) <= {0.0, 1.0}
    origins, dirs = raycast.camera_rays(cams[0], 1)
    uv, _ = cams[0].project(origins[0, 0] + dirs * 1.0)
    j, i = np.mgrid[0:24, 0:16]
    assert np.allclose(uv[..., 0], i + 0.5) and np.allclose(uv[..., 1], j + 0.5)


@pytest.mark.slow
def test_paper_head_flame_sized_uneven_and_finer_imaged_surface():
    """The paper-scale head: an 8192-face watertight template with FLAME-like uneven density
    (eyes, mouth and nose several times denser than the scalp, back of the head and neck), and
    an imaged surface 4x finer per subdivision level whose first vertices are the template's,
    displaced off it by millimetres where the template is coarse (hair, ears, collar)."""
    tv, tf, fv, ff = surface.paper_head(surface_levels=1)  # one level finer keeps the test quick
    assert 8000 <= len(tf) <= 12000 and len(ff) == 4 * len(tf)
    mesh = trimesh.Trimesh(tv, tf, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert trimesh.Trimesh(fv, ff, process=False).is_watertight
    area = mesh.area_faces
    r = _face_regions(tv, tf)
    fine = np.median(area[r["eyes"] | r["mouth"]])
    for name in ("back", "scalp"):
        assert np.median(area[r[name]]) > 6.0 * fine, name
    assert np.degrees(mesh.face_angles.min()) > 2.0
    off = np.linalg.norm(fv[: len(tv)] - tv, axis=1)
    scalp = tv[:, 1] > 0.09
    cheeks = (tv[:, 2] > 0.03) & (np.abs(np.abs(tv[:, 0]) - 0.05) < 0.01) & (np.abs(tv[:, 1] + 0.025) < 0.01)
    assert 0.001 < np.median(off[scalp]) < 0.004  # hair volume the template lacks
    assert off[cheeks].max() < 1e-5
    # the paper albedo adds sub-millimetre detail on the hair and the shirt: colours 0.3 mm
    # apart differ more than under the default albedo
    pts = fv[(fv[:, 1] > 0.09) | (fv[:, 1] < -0.212)].astype(np.float64)
    step = np.array([0.0003, 0.0002, 0.0001])
    jump = {
        name: np.abs(fn(pts) - fn(pts + step)).mean()
        for name, fn in (("paper", texture.paper_albedo), ("default", texture.albedo))
    }
    assert jump["paper"] > 1.5 * jump["default"], jump


def test_make_synthetic_script_refuses_bad_counts(tmp_path):
    """Bad counts are refused with a message and exit 2, no traceback and no folder (they raised a
    traceback, and --resolution 0 was quietly made 8 px)."""
    import subprocess
    import sys

    script = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scripts", "make_synthetic.py")
    for args, says in (
        (["--cameras", "1"], "needs at least 2 sequences, 2 cameras and 1 frame"),
        (["--resolution", "0"], "--resolution is the image height in pixels, at least 8"),
        (["--template-subdivisions", "9"], "template_subdivisions must be 0-7"),
        (["--template-subdivisions", "-1"], "template_subdivisions must be 0-7"),
        (["--preset", "paper", "--surface-levels", "6"], "surface_levels must be 0-4"),
    ):
        out = subprocess.run(
            [sys.executable, script, "--out", str(tmp_path / "d"), "--quiet", *args], capture_output=True, text=True
        )
        assert out.returncode == 2 and says in out.stderr and "Traceback" not in out.stderr, (args, out.stderr)
        assert not (tmp_path / "d").exists()
    if os.path.isdir("/proc/self"):  # a folder that cannot be made, though its parent looks writable to root
        out = subprocess.run(
            [sys.executable, script, "--out", "/proc/pa_dataset", "--quiet", "--resolution", "8"],
            capture_output=True,
            text=True,
        )
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
        assert out.stderr.strip().splitlines()[-1].startswith("error: FileNotFoundError: No such file or directory")


def test_generation_checks_its_arguments_first_and_does_not_mix_datasets(tmp_path):
    """Nonsense options are refused before anything is written; a folder holding a dataset is
    not generated into again without overwrite, and with it the old transforms go first, so an
    interrupted regeneration cannot leave old poses beside new images as a loadable dataset."""
    kw = dict(resolution=16, cameras=2, sequences=2, frames=1, progress=False, template_subdivisions=1)
    for bad, match in (
        (dict(supersample=0), "supersample"),
        (dict(resolution=100000), "resolution"),
        (dict(seed=-1), "seed"),
        (dict(workers=0), "workers"),
    ):
        with pytest.raises(ValueError, match=match):
            dataset.make_dataset(tmp_path / "bad", **{**kw, **bad})
        assert not (tmp_path / "bad").exists()
    out = tmp_path / "ds"
    dataset.make_dataset(out, **kw)
    with pytest.raises(ValueError, match="already holds a dataset"):
        dataset.make_dataset(out, **{**kw, "seed": 3})

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    import unittest.mock

    with unittest.mock.patch.object(dataset, "make_cameras", interrupted), pytest.raises(KeyboardInterrupt):
        dataset.make_dataset(out, overwrite=True, **kw)
    assert not any(n.startswith("transforms") for n in os.listdir(out))  # nothing that loads as a dataset
    dataset.make_dataset(out, overwrite=True, **{**kw, "frames": 2})
    assert (out / "transforms_train.json").exists()
    # A smaller dataset generated over it leaves none of the larger one's frames behind.
    big = set(os.listdir(out / "images"))
    dataset.make_dataset(out, overwrite=True, **kw)
    small = set(os.listdir(out / "images"))
    assert small < big and small == {p.name for p in (out / "fg_masks").iterdir()}
    used = {f["file_path"] for split in ("train", "val", "test") for f in _frames(out, split)}
    assert {f"images/{n}" for n in small} == used
    # A folder of the user's own files is not written into (it replaced files of the same names).
    mine = tmp_path / "mine"
    (mine / "images").mkdir(parents=True)
    (mine / "images" / "00000_00.png").write_bytes(b"the user's picture")
    (mine / "notes.txt").write_text("keep")
    for over in (False, True):
        with pytest.raises(ValueError, match=r"holds files the generator did not write \(images, notes.txt\)"):
            dataset.make_dataset(mine, overwrite=over, **kw)
    os.remove(mine / "notes.txt")  # names like the generator's, but no generation began here
    with pytest.raises(ValueError, match=r"did not write \(images\)"):
        dataset.make_dataset(mine, **kw)
    assert (mine / "images" / "00000_00.png").read_bytes() == b"the user's picture"
    assert os.listdir(mine) == ["images"]
    (out / "images" / "mine.png").write_bytes(b"x")  # beside a generation's own files
    with pytest.raises(ValueError, match=r"did not write \(images/mine.png\)"):
        dataset.make_dataset(out, overwrite=True, **kw)


def _frames(out, split):
    with open(out / f"transforms_{split}.json") as fh:
        return json.load(fh)["frames"]


def test_a_transforms_json_is_whole_or_absent(tmp_path):
    """Interrupted while the transforms JSONs are written (the last step), the folder holds no
    half-written JSON: each one there parses and no temporary is left behind."""
    import unittest.mock

    kw = dict(resolution=16, cameras=2, sequences=2, frames=1, progress=False, template_subdivisions=1)
    out = tmp_path / "ds"
    real_dump, calls = json.dump, []

    def dump_then_fail(obj, fh, **k):
        calls.append(1)
        if len(calls) == 2:  # transforms_val.json: half of it written, then the interrupt
            fh.write(json.dumps(obj)[:100])
            raise KeyboardInterrupt
        return real_dump(obj, fh, **k)

    with unittest.mock.patch.object(dataset.json, "dump", dump_then_fail), pytest.raises(KeyboardInterrupt):
        dataset.make_dataset(out, **kw)
    names = os.listdir(out)
    assert "transforms_train.json" in names and "transforms_val.json" not in names, names
    assert not [n for n in names if n.endswith(".tmp")], names
    for n in names:
        if n.endswith(".json"):
            with open(out / n) as fh:
                json.load(fh)


def test_contact_sheet_picks_frames_of_the_datasets_own_seed(tmp_path, monkeypatch):
    """The sheet shows each chosen sequence at its strongest expression: posed with the seed the
    dataset was made with (summary.json keeps it), not seed 0."""
    kw = dict(resolution=16, cameras=2, sequences=4, frames=6, progress=False, template_subdivisions=1)
    out = tmp_path / "ds"
    summary = dataset.make_dataset(out, seed=7, **kw)
    assert summary["seed"] == 7 and json.loads((out / "summary.json").read_text())["seed"] == 7
    seen = []
    real = dataset.sequence_params
    monkeypatch.setattr(
        dataset, "sequence_params", lambda *a, **k: seen.append(a[4:] + tuple(k.values())) or real(*a, **k)
    )
    dataset.contact_sheet(str(out), str(tmp_path / "sheet.png"))
    assert seen and all(s == (7,) for s in seen), set(seen)
