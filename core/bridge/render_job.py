"""The out-of-Blender side of *Render Splats*: render the Gaussians the add-on saved with the
core rasteriser. Blender tier at module level (numpy); it runs in the configured Python,
which imports core.render (numba) when a job runs.
"""

from __future__ import annotations

import numpy as np


# -- render job (runs in the configured Python, outside Blender) ---------------------------
def render_job(job_path: str, out_path: str) -> None:
    """Render the Gaussians saved by the add-on in ``job_path`` (npz) to ``out_path`` (.npy
    RGBA float32 [H,W,4]) with the core rasteriser, over black: RGB is the splats' (sRGB-encoded)
    colours premultiplied by the coverage A. A ``background`` in the job is not used: the
    add-on's store_image puts the scene's background behind the splats, in scene-linear."""
    from ..geometry.camera import Camera
    from ..io.atomic import atomic_open
    from ..render.rasterize import render_numpy

    with np.load(job_path, allow_pickle=False) as d:
        cam = Camera(d["R"], d["t"], *[float(x) for x in d["intr"]], int(d["size"][0]), int(d["size"][1]))
        # 3DGS clamps SH colours at 0 (PLY splats keep their exact, possibly negative, DC for export).
        colors = np.maximum(d["colors"], 0)
        behind = d["behind"] if "behind" in d.files else None  # retired backdrop stand-ins
        out = render_numpy(
            d["means"],
            d["quats"],
            d["scales"],
            d["opacities"],
            colors,
            cam,
            np.zeros(colors.shape[1], np.float32),
            compute_contrib=False,
            behind=behind,
        )
    image, alpha = out[0], out[1]
    rgba = np.concatenate([np.asarray(image, np.float32), np.asarray(alpha, np.float32)[..., None]], -1)
    # A worker killed mid-write must not leave a truncated array where the add-on loads its image.
    with atomic_open(out_path) as fh:
        np.save(fh, rgba)
