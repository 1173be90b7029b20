"""Dataset loading throughput: images/s cold (decode from disk) and warm (LRU cache hits).

    python scripts/bench_data.py [--data DIR] [--split train] [--downscale 1] [--quick]

Without --data a small mesh-mode dataset is written to a temporary folder. ``run()`` returns
a Markdown section (machine, command, date, table) for the benchmark report.
"""

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap  # noqa: F401  (makes progressive_avatars importable; must come first)

import argparse
import datetime
import os
import platform
import sys
import tempfile
import time

import numpy as np

from progressive_avatars.core.geometry.camera import Camera
from progressive_avatars.core.io.dataset import Dataset


def _write_tiny_dataset(root: str, cameras: int, timesteps: int, size: int) -> None:
    """A sphere-ish mesh with noisy images and disc masks: realistic PNG decode cost."""
    import json

    from PIL import Image

    rng = np.random.default_rng(0)
    os.makedirs(os.path.join(root, "images"), exist_ok=True)
    os.makedirs(os.path.join(root, "fg_masks"), exist_ok=True)
    os.makedirs(os.path.join(root, "meshes"), exist_ok=True)
    d = rng.normal(size=(642, 3))
    verts = (0.1 * d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    faces = rng.integers(0, len(verts), size=(1280, 3)).astype(np.int32)
    np.savez(os.path.join(root, "canonical_mesh.npz"), vertices=verts, faces=faces)
    ys, xs = np.mgrid[0:size, 0:size]
    disc = (xs - size / 2) ** 2 + (ys - size / 2) ** 2 < (0.35 * size) ** 2
    frames = []
    for t in range(timesteps):
        np.savez(os.path.join(root, "meshes", f"{t:05d}.npz"), vertices=verts * (1 + 0.01 * t))
        for c in range(cameras):
            ang = 2 * np.pi * c / cameras
            cam = Camera.look_at(
                [0.6 * np.sin(ang), 0.0, 0.6 * np.cos(ang)],
                [0, 0, 0],
                [0, 1, 0],
                1.2 * size,
                1.2 * size,
                size / 2,
                size / 2,
                size,
                size,
            )
            img = np.where(disc[..., None], rng.integers(0, 256, (size, size, 3)), 255).astype(np.uint8)
            name = f"{t:05d}_{c:02d}.png"
            Image.fromarray(img).save(os.path.join(root, "images", name))
            Image.fromarray((disc * 255).astype(np.uint8)).save(os.path.join(root, "fg_masks", name))
            frames.append(
                dict(
                    file_path=f"images/{name}",
                    fg_mask_path=f"fg_masks/{name}",
                    transform_matrix=cam.c2w_opengl().tolist(),
                    fl_x=cam.fx,
                    fl_y=cam.fy,
                    cx=cam.cx,
                    cy=cam.cy,
                    w=size,
                    h=size,
                    timestep_index=t,
                    camera_index=c,
                    mesh_path=f"meshes/{t:05d}.npz",
                )
            )
    with open(os.path.join(root, "transforms_train.json"), "w") as f:
        json.dump({"frames": frames}, f)


def _pass(ds: Dataset, n: int) -> float:
    t0 = time.perf_counter()
    for i in range(n):
        s = ds[i]
        assert s.image.shape[2] == 3
    return n / (time.perf_counter() - t0)


def _machine() -> str:
    return f"{platform.node() or 'host'} ({platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, {platform.system()})"


def run(quick: bool = False, data_dir=None, split: str = "train", downscale: float = 1.0) -> str:
    """Benchmark and return a Markdown section."""
    tmp = None
    if data_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_data_")
        size = 128 if quick else 512
        cams, steps = (2, 4) if quick else (4, 8)
        _write_tiny_dataset(tmp.name, cams, steps, size)
        root, what = tmp.name, f"temporary mesh-mode dataset, {cams} cameras x {steps} timesteps, {size}x{size} PNG"
    else:
        root, what = os.fspath(data_dir), f"`{os.fspath(data_dir)}` split `{split}`"
    try:
        t0 = time.perf_counter()
        ds = Dataset(root, split, downscale=downscale, cache_images=10**9)
        open_s = time.perf_counter() - t0
        n = min(len(ds), 16 if quick else 256)
        cold = _pass(ds, n)  # decodes every image and loads every timestep's mesh
        warm = _pass(ds, n)  # all cache hits
        nocache = Dataset(root, split, downscale=downscale, cache_images=0)
        _pass(nocache, min(n, 4))  # meshes cached; measure image decode alone below
        decode = _pass(nocache, n)
        s = ds[0]
        h, w = s.image.shape[:2]
    finally:
        if tmp is not None:
            tmp.cleanup()
    cmd = (
        "python scripts/bench_data.py"
        + (f" --data {data_dir}" if data_dir else "")
        + (" --quick" if quick else "")
        + (f" --downscale {downscale}" if downscale != 1.0 else "")
    )
    lines = [
        "## Dataset loading throughput",
        "",
        f"- machine: {_machine()}",
        f"- command: `{cmd}`",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- data: {what}; {len(ds)} frames, {n} read per pass, images {w}x{h} after downscale {downscale:g}",
        "",
        "| pass | images/s |",
        "|---|---|",
        f"| cold (decode + mesh load) | {cold:.1f} |",
        f"| decode only (no image cache, meshes cached) | {decode:.1f} |",
        f"| warm (LRU cache hits) | {warm:.0f} |",
        "",
        f"Opening the dataset (JSON, cameras, canonical mesh): {open_s * 1000:.1f} ms.",
        "",
    ]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="dataset root (default: a temporary small dataset)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args(_bootstrap.script_args(argv))
    print(run(quick=a.quick, data_dir=a.data, split=a.split, downscale=a.downscale))


if __name__ == "__main__":
    main(sys.argv)
