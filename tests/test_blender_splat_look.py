"""The splat look in Cycles against our rasteriser, on anisotropic, rotated splats.

A few dozen Gaussians of trained proportions (flat ellipsoids at all orientations, a range
of opacities, some overlapping) are imported as static splats (blender_addon/ply_import)
and rendered by Cycles on the CPU with the splat material, camera cards and render settings
(blender_addon/splat_look, preview); core.render.render_numpy renders the same Gaussians
from the same camera. The material evaluates each Gaussian exactly on the view ray and the
cards composite in view-depth order, so the two agree up to the rasteriser's affine (EWA)
projection and Cycles' pixel filter and sampling, once both composite in the same space:
by default Cycles blends scene-linear colours (then the Standard view transform encodes
sRGB), so the reference is the rasteriser run on linear colours and encoded afterwards; the
opt-in As Trained mode blends the sRGB colours as they are (Raw view transform), against
the plain rasteriser. The avatar-scale figures come from scripts/splat_look.py.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.helpers import BPY_CHILD_PRELUDE, run_bpy_child
from tests.test_blender_extension import _bpy_dir, _clean_env

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _scenario(name):
    with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "blender_scenarios", name)) as fh:
        return fh.read()


CHILD = _scenario("splat_look.py")


def _splats(rng, n=60):
    d = rng.normal(size=(n, 3))
    means = 0.1 * d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.2, 1.0, (n, 1))
    scales = np.exp(rng.normal(np.log(0.02), 0.4, (n, 3)))
    scales[np.arange(n), rng.integers(0, 3, n)] *= 0.08  # flat, like trained surface splats
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return {
        "means": means.astype(np.float32),
        "quats": q.astype(np.float32),
        "scales": scales.astype(np.float32),
        "opacities": rng.uniform(0.2, 0.98, n).astype(np.float32),
        "colors": rng.uniform(0.05, 0.95, (n, 3)).astype(np.float32),
    }


def test_cycles_splat_look_matches_the_rasteriser(tmp_path):
    _bpy_dir()
    from PIL import Image

    from progressive_avatars.core.geometry.camera import Camera
    from progressive_avatars.core.render.rasterize import render_numpy

    g = _splats(np.random.default_rng(2))
    src = str(tmp_path / "splats.npz")
    np.savez(src, **g)
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    proc = subprocess.run(
        [sys.executable, str(script), ROOT, src, str(tmp_path)],
        capture_output=True,
        text=True,
        env=_clean_env(str(tmp_path)),
        timeout=300,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PA_LOOK ")]
    assert lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    rep = json.loads(lines[-1][len("PA_LOOK ") :])
    assert "error" not in rep, rep["error"]
    assert rep["material_method"] == "DITHERED"
    assert "view_transform" in rep["changed"] and "cycles.transparent_max_bounces" in rep["changed"]
    c = rep["camera"]
    cam = Camera(np.array(c["R"]), np.array(c["t"]), *c["intr"], 64, 64)
    from progressive_avatars.core.bridge.splats import srgb_to_linear

    lin, alpha, _ = render_numpy(
        g["means"], g["quats"], g["scales"], g["opacities"], srgb_to_linear(g["colors"]), cam, np.zeros(3, np.float32)
    )
    lin = np.clip(lin, 0, 1)
    ref = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)  # what Standard writes
    got = np.asarray(Image.open(tmp_path / "cycles.png").convert("RGB"), np.float32) / 255
    mask = alpha > 0.05
    assert mask.mean() > 0.1  # the splats are in view
    err = (got - ref) ** 2
    psnr = 10 * np.log10(1 / err[mask].mean())
    print(f"Cycles vs rasteriser: {psnr:.2f} dB over {mask.mean():.0%} of the image")
    assert psnr > 33, psnr  # the cards (3-sigma ellipsoid hulls measured 30.6 dB here)
    # Nothing drawn where the rasteriser has nothing within a pixel (no hull edges, no back
    # faces; Cycles' pixel filter spreads a splat's faint tail about a pixel further).
    near = np.zeros_like(alpha, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near |= np.roll(alpha, (dy, dx), axis=(0, 1)) > 1e-3
    assert got[~near].max() < 0.05

    # The cards cover the dilated footprint out to the rasteriser's cut-off; the ellipsoids
    # (Camera Cards off) are the splat's 3σ hulls.
    _cards_cover_the_dilated_footprint(g, rep)
    _ellipsoids_are_3_sigma_hulls(g, rep)
    # The viewport (any view, orbiting) shows the ellipsoids unless Cards in Viewport is on; the
    # render above used the cards (its 25+ dB depend on them).
    assert rep["viewport_default_faces"] == rep["ellipsoids_faces"]
    np.testing.assert_allclose(rep["viewport_default_matrices"], rep["ellipsoids_matrices"], atol=1e-6)

    # As Trained: sRGB-encoded colours composited as they are, shown raw, is how the avatar was
    # trained: the plain rasteriser (sRGB colours, no encoding afterwards) is the reference.
    assert rep["view_transform_trained"] == "Raw" and "splat colours as trained" in rep["changed_trained"]
    srgb, _, _ = render_numpy(
        g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], cam, np.zeros(3, np.float32)
    )
    trained = np.asarray(Image.open(tmp_path / "cycles_trained.png").convert("RGB"), np.float32) / 255
    err = (trained - np.clip(srgb, 0, 1)) ** 2
    psnr_trained = 10 * np.log10(1 / err[mask].mean())
    print(f"As Trained vs the sRGB-blending rasteriser: {psnr_trained:.2f} dB")
    assert psnr_trained > 28, psnr_trained
    # ... and it really is a different image from the default (linear blending) one.
    assert np.abs(trained - got)[mask].mean() > 0.01


def _cards_cover_the_dilated_footprint(g, rep):
    """Camera cards: a quad per splat parallel to the image plane through its centre, with
    half-extents along the camera's x and y of k·sqrt(cᵀΣc + ε) (k the rasteriser's 1/255
    cut-off radius, ε its 0.3 px² dilation at the splat's distance): the footprint's extent."""
    from progressive_avatars.core.geometry.rotations import quat_to_rotmat

    v = np.array(rep["cards_vertices"])
    assert len(rep["cards_faces"]) == 1 and np.allclose(np.abs(v[:, :2]), 1) and np.allclose(v[:, 2], 0)
    m = np.array(rep["cards_matrices"])  # camera rotation times (ext_x, ext_y, 1)
    assert m.shape == (len(g["means"]), 3, 3)
    dists = np.linalg.norm(np.array(rep["cards_origins"])[:, None] - g["means"][None], axis=2)
    order = np.argmin(dists, 1)
    assert len(set(order)) == len(order) and dists.min(1).max() < 1e-6  # one card per splat, at its centre
    cam = np.array(rep["camera_rotation"])
    ext = np.linalg.norm(m, axis=1)[:, :2]
    assert np.allclose(m[:, :, :2] / ext[:, None, :], cam[None, :, :2], atol=1e-4)  # parallel to the image
    rot = quat_to_rotmat(g["quats"][order].astype(np.float64))
    cov = np.einsum("nij,nj,nkj->nik", rot, g["scales"][order].astype(np.float64) ** 2, rot)
    dist = np.linalg.norm(g["means"][order] - np.array(rep["camera_location"]), axis=1)
    eps = 0.3 * (dist / rep["focal_px"]) ** 2
    cut = np.sqrt(2 * np.log(255 * g["opacities"][order]))
    need = cut[:, None] * np.sqrt(np.einsum("ia,nij,ja->na", cam[:, :2], cov, cam[:, :2]) + eps[:, None])
    assert np.allclose(ext, need, rtol=1e-3), np.abs(ext / need - 1).max()
    # The dilation matters here: without it some cards would be much too small.
    bare = cut[:, None] * np.sqrt(np.einsum("ia,nij,ja->na", cam[:, :2], cov, cam[:, :2]))
    assert (need > 1.2 * bare).any()


def _ellipsoids_are_3_sigma_hulls(g, rep):
    """Camera Cards off: an ico-sphere of radius 3 per splat in its own frame, scaled by σ (the
    undilated Gaussian: larger hulls composite worse in Cycles, docs/BLENDER_SPLATS.md)."""
    from progressive_avatars.core.geometry.rotations import quat_to_rotmat

    v = np.array(rep["ellipsoids_vertices"])
    assert len(rep["ellipsoids_faces"]) == 80  # Detail 2
    assert np.allclose(np.linalg.norm(v, axis=1), 3.0, rtol=1e-4)
    m = np.array(rep["ellipsoids_matrices"])  # rotation times σ per axis (column norms)
    assert m.shape == (len(g["means"]), 3, 3)
    order = np.argmin(np.linalg.norm(np.array(rep["ellipsoids_origins"])[:, None] - g["means"][None], axis=2), 1)
    assert len(set(order)) == len(order)  # instances matched one to one with the splats
    np.testing.assert_allclose(np.linalg.norm(m, axis=1), g["scales"][order], rtol=1e-3)
    rot = m / np.linalg.norm(m, axis=1, keepdims=True)  # columns: the splat's own axes
    assert np.allclose(np.abs(np.einsum("nij,nij->nj", rot, quat_to_rotmat(g["quats"][order]))), 1, atol=1e-3)


_FOCAL_CHILD = (
    BPY_CHILD_PRELUDE
    + r"""
load_extension("pa_focal")
ply_import = sys.modules["pa_focal.blender_addon.ply_import"]
look = sys.modules["pa_focal.blender_addon.splat_look"]
R = {"cases": {}}
try:
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    sc = bpy.context.scene
    with np.load(os.path.join(out, "splats.npz")) as d:
        g = {k: d[k] for k in d.files}
    ply_import.create_splat_object(bpy.context, "splats", g)
    camd = bpy.data.cameras.new("cam")
    cam = bpy.data.objects.new("cam", camd)
    sc.collection.objects.link(cam)
    sc.camera = cam
    cases = {
        "auto 200x100": dict(res=(200, 100)),
        "auto 100x200": dict(res=(100, 200)),
        "vertical 200x100": dict(res=(200, 100), fit="VERTICAL"),
        "horizontal 100x200": dict(res=(100, 200), fit="HORIZONTAL"),
        "pixel aspect 2:1": dict(res=(120, 100), aspect=(2.0, 1.0)),
        "pixel aspect 1:2 vertical": dict(res=(120, 100), aspect=(1.0, 2.0), fit="VERTICAL"),
        "percentage 50": dict(res=(300, 200), pct=50, fit="VERTICAL"),
    }
    for tag, c in cases.items():
        r = sc.render
        r.resolution_x, r.resolution_y = c["res"]
        r.resolution_percentage = c.get("pct", 100)
        r.pixel_aspect_x, r.pixel_aspect_y = c.get("aspect", (1.0, 1.0))
        camd.sensor_fit = c.get("fit", "AUTO")
        camd.lens, camd.sensor_width, camd.sensor_height = 40.0, 36.0, 20.0
        res = list(bpy.ops.render.progressive_avatars_splat_settings())
        w = r.resolution_x * r.resolution_percentage // 100
        h = r.resolution_y * r.resolution_percentage // 100
        # Blender's own framing: the camera frame (camera space, at depth -z) spans the image.
        frame = camd.view_frame(scene=sc)
        xs, ys, z = [v.x for v in frame], [v.y for v in frame], -frame[0].z
        focal = [n.outputs[0].default_value for n in look._value_nodes(look.FOCAL_NODE)]
        R["cases"][tag] = {
            "result": res,
            "focal": focal,
            "fx": w * z / (max(xs) - min(xs)),
            "fy": h * z / (max(ys) - min(ys)),
            "pct": r.resolution_percentage,
        }
    before = [n.outputs[0].default_value for n in look._value_nodes(look.FOCAL_NODE)]
    camd.type = "ORTHO"
    R["ortho"] = {"result": list(bpy.ops.render.progressive_avatars_splat_settings())}
    try:
        look.scene_camera(sc)
    except Exception as exc:
        R["ortho"]["why"] = f"{type(exc).__name__}: {exc}"
    R["ortho"]["unchanged"] = before == [n.outputs[0].default_value for n in look._value_nodes(look.FOCAL_NODE)]
except Exception:
    R["error"] = traceback.format_exc()
print("PA_FOCAL " + json.dumps(R))
"""
)


def test_splat_focal_follows_blenders_framing(tmp_path):
    """Splat Render Settings sets the splats' dilation focal length (pixels) as Blender frames
    the render: the sensor height for sensor fit Vertical, the fitted side for Auto, and with
    non-square pixels the geometric mean of fx and fy; an orthographic camera leaves it
    unset and the operator says why (not "already set")."""
    _bpy_dir()
    g = _splats(np.random.default_rng(4), n=8)
    np.savez(tmp_path / "splats.npz", **g)
    rep, stdout = run_bpy_child(_FOCAL_CHILD, tmp_path, "PA_FOCAL", _clean_env(str(tmp_path)), name="focal.py")
    for tag, c in rep["cases"].items():
        assert c["result"] == ["FINISHED"], tag
        assert len(c["focal"]) == 2, tag  # the material's node and the Geometry Nodes group's
        if c["pct"] == 100:  # view_frame frames the unscaled resolution (same aspect here)
            np.testing.assert_allclose(c["focal"], np.sqrt(c["fx"] * c["fy"]), rtol=1e-5, err_msg=tag)
    np.testing.assert_allclose(rep["cases"]["vertical 200x100"]["focal"], 40.0 / 20.0 * 100, rtol=1e-6)
    np.testing.assert_allclose(rep["cases"]["percentage 50"]["focal"], 40.0 / 20.0 * 100, rtol=1e-6)
    assert rep["ortho"]["result"] == ["FINISHED"] and rep["ortho"]["unchanged"]
    assert "orthographic" in rep["ortho"]["why"]
    assert "splat focal length not set" in stdout and "orthographic" in stdout
