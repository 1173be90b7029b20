"""The embedded default dataset: a procedural, rigged, textured head rendered from 16 views.

Everything the product trains, measures and tests on by default comes from here, so the
data has to exercise the method the way NeRSemble + FLAME do:

- the template is watertight and unevenly tessellated (dense eyes and mouth, coarse scalp
  and neck), so adaptive subdivision has to compensate for the tessellation;
- the appearance mixes smooth skin with high-frequency regions (hair strands, stubble,
  sharp eyes and lips, a striped collar and text-like marks) and is defined in the
  template's canonical coordinates, so it sticks to the surface under animation;
- a small rig (jaw, blink, smile/pucker, head rotation and translation) drives ten
  sequences, the last of which mixes expressions no training sequence shows;
- ground truth is ray cast with supersampling, so images and coverage masks are
  anti-aliased and exact for the mesh the dataset ships.

The layout written by `make_dataset` is the GaussianAvatars/VHAP one in mesh mode (see
docs/ARCHITECTURE.md and the shared design's "Data conventions").
This module writes it (shape.py, rig.py, texture.py and raycast.py make what it writes).
Reporting tier: numpy + trimesh (embree through `embreex` when installed); PIL/tqdm only when writing.
"""

from __future__ import annotations

import json
import os
import re
import time

import numpy as np

from ..geometry.camera import Camera
from ..io.atomic import atomic_open

from .raycast import held_out_camera, image_size, make_cameras, render_views
from .rig import neutral_params, pose_head, sequence_name, sequence_params
from .surface import head_template, paper_head, PAPER_SURFACE_LEVELS
from .texture import face_detail, paper_albedo


def _to_u8(a):
    return np.clip(np.round(np.asarray(a) * 255.0), 0, 255).astype(np.uint8)


def _frame_record(cam: Camera, T: int, C: int, S: int) -> dict:
    name = f"{T:05d}_{C:02d}.png"
    return {
        "file_path": f"images/{name}",
        "fg_mask_path": f"fg_masks/{name}",
        "transform_matrix": cam.c2w_opengl().tolist(),
        "fl_x": float(cam.fx),
        "fl_y": float(cam.fy),
        "cx": float(cam.cx),
        "cy": float(cam.cy),
        "w": int(cam.width),
        "h": int(cam.height),
        "timestep_index": int(T),
        "camera_index": int(C),
        "mesh_path": f"meshes/{T:05d}.npz",
        "sequence": int(S),
    }


_JOB = None  # what forked generation workers render (set by make_dataset)
MAX_SUPERSAMPLE = 8
MAX_RESOLUTION = 4096  # image height; the paper's is 802
# What makes a folder a dataset, written last (the transforms) and after them (the summary).
_DATASET_FILES = (
    "transforms_train.json",
    "transforms_val.json",
    "transforms_test.json",
    "transforms.json",
    "summary.json",
)
MAX_TEMPLATE_SUBDIVISIONS = 7  # 327,680 faces: about half a minute to build, then the ray casts
MAX_SURFACE_LEVELS = 4  # the paper head's imaged surface: 8,192 x 4^4 = 2.1 M faces


def _write_timestep(job, s, f, stats):
    """Pose, ray cast and write one timestep: its mesh, and an image and a mask per camera."""
    from PIL import Image

    out, frames = job["out"], job["frames"]
    T = s * frames + f
    params = sequence_params(s, f, frames, job["sequences"], job["seed"])
    tv, rv = job["tv"], job["rv"]
    verts = pose_head(tv, params)
    np.savez(os.path.join(out, "meshes", f"{T:05d}.npz"), vertices=verts)
    shown = verts if rv.shape == tv.shape else pose_head(rv, params)
    images, masks = render_views(
        shown,
        job["rf"],
        job["cams"],
        canonical=rv,
        supersample=job["supersample"],
        stats=stats,
        albedo_fn=job["albedo_fn"],
    )
    for C in range(len(job["cams"])):
        name = f"{T:05d}_{C:02d}.png"
        Image.fromarray(_to_u8(images[C]), "RGB").save(os.path.join(out, "images", name))
        Image.fromarray(_to_u8(masks[C]), "L").save(os.path.join(out, "fg_masks", name))


# Everything the generator writes into its folder: the dataset files, the meshes and pictures.
_GENERATED_TOP = {*_DATASET_FILES, "canonical_mesh.npz", "detail.npz", "contact_sheet.png"}
_GENERATED_IN = {
    "images": re.compile(r"\d{5}_\d{2}\.png"),
    "fg_masks": re.compile(r"\d{5}_\d{2}\.png"),
    "meshes": re.compile(r"\d{5}\.npz"),
}


_TEMPORARY = re.compile(r"\.\d+(-\d+)?\.tmp$")  # an atomic write's temporary, left by a killed generation


def _foreign_files(out: str) -> list[str]:
    """The entries of ``out`` (relative paths) that the generator does not write; none for a
    missing or empty folder, an earlier synthetic dataset or an interrupted generation."""
    if not os.path.isdir(out):
        return []
    names = sorted(os.listdir(out))
    if not {"canonical_mesh.npz", *_DATASET_FILES} & set(names):  # written first: else none of it is ours
        return names
    foreign = []
    for name in names:
        path = os.path.join(out, name)
        if name in _GENERATED_IN and os.path.isdir(path):
            pattern = _GENERATED_IN[name]
            foreign += [f"{name}/{n}" for n in sorted(os.listdir(path)) if not pattern.fullmatch(n)]
        elif not (_TEMPORARY.sub("", name) in _GENERATED_TOP and os.path.isfile(path)):
            foreign.append(name)
    return foreign


def _remove_generated(out: str) -> None:
    """Remove what an earlier generation wrote (the caller checked that nothing else is there)."""
    if not os.path.isdir(out):
        return
    for name in os.listdir(out):
        if _TEMPORARY.sub("", name) in _GENERATED_TOP and os.path.isfile(os.path.join(out, name)):
            os.remove(os.path.join(out, name))
    for sub, pattern in _GENERATED_IN.items():
        folder = os.path.join(out, sub)
        if os.path.isdir(folder):
            for n in os.listdir(folder):
                if pattern.fullmatch(n):
                    os.remove(os.path.join(folder, n))


def _timestep_from_job(step):
    stats: dict = {}
    _write_timestep(_JOB, *step, stats=stats)
    return stats.get("rays", 0), stats.get("hits", 0), stats.get("intersector", "none")


def make_dataset(
    out,
    resolution: int = 128,
    cameras: int = 16,
    sequences: int = 10,
    frames: int = 8,
    seed: int = 0,
    progress: bool = True,
    supersample: int = 2,
    template_subdivisions: int = 4,
    detail: str = "default",
    workers: int = 1,
    surface_levels: int = PAPER_SURFACE_LEVELS,
    overwrite: bool = False,
) -> dict:
    """Write the synthetic mesh-mode dataset into ``out``; returns a summary dict.

    Global timestep T = sequence * frames + frame. Splits: the last sequence is the test
    (novel expression) sequence, camera ``cameras // 2`` the held-out (novel view) camera.

    ``template_subdivisions`` sets the tracked mesh written to the dataset (4: 5120 faces,
    3: 1280). The images are always ray-cast from a mesh of at least 4 subdivisions, so a
    coarser template is a chord approximation of the imaged surface, as a tracked FLAME
    mesh is of a real head; both come from the same pointwise rig, so they move together.

    ``detail="paper"``: the paper-scale head instead (``paper_head``: an 8192-face template
    with FLAME-like uneven density, images ray-cast from a 16x finer displaced surface with
    ``paper_albedo``); ``template_subdivisions`` is then ignored, ``surface_levels`` sets how
    much finer the imaged surface is (each level 4x the faces). ``workers`` > 1 renders
    timesteps in that many forked processes (the files are the same).

    Every argument is checked before anything is written. A folder that already holds a
    dataset (its transforms JSONs) is refused unless ``overwrite``; then those JSONs go first,
    and as they are written last, an interrupted regeneration never leaves old poses beside
    new images as a dataset that loads.
    """
    if detail not in ("default", "paper"):
        raise ValueError(f"make_dataset: detail must be 'default' or 'paper', got {detail!r}")

    if sequences < 2 or cameras < 2 or frames < 1:
        raise ValueError("make_dataset needs at least 2 sequences, 2 cameras and 1 frame")
    if detail == "default" and not 0 <= template_subdivisions <= MAX_TEMPLATE_SUBDIVISIONS:
        # Each subdivision quadruples the faces, and the images are ray-cast from the template
        # itself: 9 subdivisions (5.2 M faces) ran silently for many minutes before this check.
        raise ValueError(
            f"make_dataset: template_subdivisions must be 0-{MAX_TEMPLATE_SUBDIVISIONS} "
            f"(20 to {20 * 4**MAX_TEMPLATE_SUBDIVISIONS:,} faces; 4 gives the default 5,120), got {template_subdivisions}"
        )
    if detail == "paper" and not 0 <= surface_levels <= MAX_SURFACE_LEVELS:
        raise ValueError(
            f"make_dataset: surface_levels must be 0-{MAX_SURFACE_LEVELS} (each level 4x the imaged "
            f"surface's faces; the paper preset's is {PAPER_SURFACE_LEVELS}), got {surface_levels}"
        )
    if not (isinstance(supersample, (int, np.integer)) and 1 <= supersample <= MAX_SUPERSAMPLE):
        raise ValueError(f"make_dataset: supersample must be a whole number 1-{MAX_SUPERSAMPLE}, got {supersample!r}")
    if not (isinstance(resolution, (int, np.integer)) and 8 <= resolution <= MAX_RESOLUTION):
        # The ray buffers grow with resolution² x supersample²: 100,000 px asked for 204 GiB.
        raise ValueError(f"make_dataset: resolution (image height) must be 8-{MAX_RESOLUTION} px, got {resolution!r}")
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ValueError(f"make_dataset: seed must be a whole number >= 0, got {seed!r}")
    if int(workers) < 1:
        raise ValueError(f"make_dataset: workers must be at least 1, got {workers}")
    t0 = time.perf_counter()
    out = os.fspath(out)
    held = [n for n in _DATASET_FILES if os.path.isfile(os.path.join(out, n))]
    if held and not overwrite:
        raise ValueError(
            f"{out} already holds a dataset ({', '.join(held)}): pass --overwrite to generate it again, "
            "or choose another --out"
        )
    foreign = _foreign_files(out)
    if foreign:  # the generator would write among them, and replace those with its own names
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise ValueError(
            f"{out} holds files the generator did not write ({shown}): choose an empty or new --out folder"
        )
    for name in held:  # the transforms first: an interrupted clean-up leaves no dataset that reads
        os.remove(os.path.join(out, name))
    _remove_generated(out)  # an earlier (larger or interrupted) generation's frames would stay behind
    for sub in ("images", "fg_masks", "meshes"):
        os.makedirs(os.path.join(out, sub), exist_ok=True)
    if detail == "paper":
        tv, tf, rv, rf = paper_head(surface_levels=surface_levels)
        albedo_fn = paper_albedo
    else:
        tv, tf = head_template(template_subdivisions)
        rv, rf = head_template(max(4, int(template_subdivisions)))
        albedo_fn = None
    np.savez(os.path.join(out, "canonical_mesh.npz"), vertices=tv, faces=tf)
    np.savez(os.path.join(out, "detail.npz"), face_detail=face_detail(tv, tf, albedo_fn=albedo_fn))
    cams = make_cameras(cameras, resolution)
    held = held_out_camera(cameras)
    test_seq = sequences - 1
    seq_info = [
        {
            "index": s,
            "name": sequence_name(s, sequences),
            "split": "test" if s == test_seq else "train",
            "timestep_start": s * frames,
            "num_timesteps": frames,
        }
        for s in range(sequences)
    ]
    splits = {"train": [], "val": [], "test": []}
    everything = []
    stats: dict = {}
    steps = [(s, f) for s in range(sequences) for f in range(frames)]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(steps), desc="synthetic head", unit="timestep")
    job = dict(
        out=out,
        frames=frames,
        sequences=sequences,
        seed=seed,
        tv=tv,
        rv=rv,
        rf=rf,
        cams=cams,
        supersample=supersample,
        albedo_fn=albedo_fn,
    )
    for s, f in steps:
        T = s * frames + f
        for C, cam in enumerate(cams):
            rec = _frame_record(cam, T, C, s)
            everything.append(rec)
            if s == test_seq:
                splits["test"].append(rec)
            elif C == held:
                splits["val"].append(rec)
            else:
                splits["train"].append(rec)
    if int(workers) > 1 and len(steps) > 1:
        # fork: the workers share the surface built above instead of rebuilding it
        import multiprocessing as mp

        global _JOB
        _JOB = job
        with mp.get_context("fork").Pool(min(int(workers), len(steps))) as pool:
            for rays, hits, kind in pool.imap_unordered(_timestep_from_job, steps):
                stats["rays"] = stats.get("rays", 0) + rays
                stats["hits"] = stats.get("hits", 0) + hits
                stats["intersector"] = kind
                if bar is not None:
                    bar.update(1)
        _JOB = None
    else:
        for step in steps:
            _write_timestep(job, *step, stats=stats)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()

    def write(name, recs, seqs):
        doc = {
            "background": [1.0, 1.0, 1.0],
            "mode": "mesh",
            "canonical_mesh_path": "canonical_mesh.npz",
            "sequences": [seq_info[i] for i in seqs],
            "timestep_indices": sorted({r["timestep_index"] for r in recs}),
            "camera_indices": sorted({r["camera_index"] for r in recs}),
            "frames": recs,
        }
        # Atomic: a half-written JSON would make the folder look like a dataset. The per-frame
        # files are not (an fsync each): until these JSONs exist nothing loads them.
        with atomic_open(os.path.join(out, name), "w") as fh:
            json.dump(doc, fh, indent=1)

    train_seqs = list(range(sequences - 1))
    write("transforms_train.json", splits["train"], train_seqs)
    write("transforms_val.json", splits["val"], train_seqs)
    write("transforms_test.json", splits["test"], [test_seq])
    write("transforms.json", everything, list(range(sequences)))
    seconds = time.perf_counter() - t0
    w, h = image_size(resolution)
    summary = {
        "out": out,
        "width": w,
        "height": h,
        "cameras": cameras,
        "sequences": sequences,
        "frames": frames,
        "timesteps": len(steps),
        "images": len(everything),
        "train": len(splits["train"]),
        "val": len(splits["val"]),
        "test": len(splits["test"]),
        "held_out_camera": held,
        "test_sequence": test_seq,
        "vertices": int(len(tv)),
        "faces": int(len(tf)),
        "supersample": supersample,
        "rays": int(stats.get("rays", 0)),
        "detail": detail,
        "imaged_faces": int(len(rf)),
        "intersector": stats.get("intersector", "none"),
        "seed": int(seed),
        "seconds": seconds,
        "rays_per_second": stats.get("rays", 0) / max(seconds, 1e-9),
    }
    with atomic_open(os.path.join(out, "summary.json"), "w") as fh:
        json.dump(summary, fh, indent=1)
    return summary


def contact_sheet(dataset_dir, path, rows: int = 4) -> str:
    """All cameras (columns) x ``rows`` timesteps from different sequences, labelled."""
    from PIL import Image, ImageDraw

    with open(os.path.join(dataset_dir, "transforms.json")) as fh:
        doc = json.load(fh)
    seqs = doc["sequences"]
    n_seq = len(seqs)
    try:  # the seed the frames were posed with (summary.json; datasets made before it was kept: 0)
        with open(os.path.join(dataset_dir, "summary.json")) as fh:
            seed = int(json.load(fh).get("seed", 0))
    except (OSError, ValueError, TypeError):
        seed = 0
    picks = sorted({int(round(k * (n_seq - 1) / max(rows - 1, 1))) for k in range(rows)})
    by_key = {(r["timestep_index"], r["camera_index"]): r for r in doc["frames"]}
    cams = sorted({r["camera_index"] for r in doc["frames"]})
    chosen = []
    for si in picks:
        info = seqs[si]
        n = info["num_timesteps"]
        # the frame of strongest expression, so rows differ visibly
        best = max(range(n), key=lambda f: _activity(sequence_params(si, f, n, n_seq, seed)))
        chosen.append((info, info["timestep_start"] + best))
    first = by_key[(chosen[0][1], cams[0])]
    w, h = first["w"], first["h"]
    left, top = 96, 14
    sheet = Image.new("RGB", (left + w * len(cams), top + h * len(chosen)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for ci, C in enumerate(cams):
        draw.text((left + ci * w + 2, 1), f"cam {C}", fill=(0, 0, 0))
    for ri, (info, T) in enumerate(chosen):
        draw.text((2, top + ri * h + 2), f"t={T}", fill=(0, 0, 0))
        draw.text((2, top + ri * h + 14), info["name"][:15], fill=(0, 0, 0))
        draw.text((2, top + ri * h + 26), info["split"], fill=(0, 0, 0))
        for ci, C in enumerate(cams):
            rec = by_key[(T, C)]
            tile = Image.open(os.path.join(dataset_dir, rec["file_path"])).convert("RGB")
            sheet.paste(tile, (left + ci * w, top + ri * h))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    from ..io.atomic import atomic_save_image

    return atomic_save_image(sheet, path)


def _activity(p):
    return p["jaw"] + p["blink"] + abs(p["smile"]) + sum(abs(a) for a in p["rotation"]) / 25.0


def render_closeup(path, height: int = 384, supersample: int = 3, detail: str = "default") -> str:
    """A frontal close-up strip: neutral, jaw open + blink, smile, pucker + turn (``detail="paper"``:
    the paper-scale head's imaged surface and albedo)."""
    from PIL import Image

    if detail == "paper":
        _, _, tv, tf = paper_head()
    else:
        tv, tf = head_template()
    albedo_fn = paper_albedo if detail == "paper" else None
    w = int(round(height * 0.8))
    f = height / 0.30
    cam = Camera.look_at((0.0, 0.0, 1.0), (0.0, -0.01, 0.0), (0.0, 1.0, 0.0), f, f, w / 2.0, height / 2.0, w, height)
    poses = [
        neutral_params(),
        {"jaw": 1.0, "blink": 1.0},
        {"smile": 1.0},
        {"smile": -1.0, "rotation": (20.0, 0.0, 0.0)},
    ]
    tiles = []
    for p in poses:
        img, _ = render_views(pose_head(tv, p), tf, [cam], canonical=tv, supersample=supersample, albedo_fn=albedo_fn)
        tiles.append(_to_u8(img[0]))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    from ..io.atomic import atomic_save_image

    return atomic_save_image(Image.fromarray(np.concatenate(tiles, axis=1), "RGB"), path)
