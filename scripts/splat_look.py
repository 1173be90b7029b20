"""How close Blender's splat look is to our rasteriser: a Cycles render of the add-on's
preview at 100 % against core.render.render_numpy of the same Gaussians from the same camera.

    python scripts/splat_look.py --run RUN --data DATA --out DIR [--size 256] [--samples 32]
                                 [--root ADDON_ROOT]

The sequence and camera come from the dataset's test split (its first camera, middle frame).
Blender (the bpy module) runs in a child process with a temporary user folder; it imports the
sequence, loads the run's stream at 100 %, sets the splat render settings, renders with Cycles
on the CPU and saves the Gaussians it shows and its camera. This process renders those with
the core rasteriser and reports PSNR inside the head mask (rasteriser alpha > 0.5) and over
the whole image, writes both images and a side-by-side PNG (Blender | rasteriser | 4x abs
difference) and a JSON summary. --root picks the add-on source tree (default: this checkout),
to measure an older version of the look the same way.
"""

from __future__ import annotations

import os as _os
import sys as _sys

_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap  # noqa: F401,E402

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))

CHILD = r"""
import importlib.util, json, os, sys, time
args = json.loads(sys.argv[1])
root = args["root"]
spec = importlib.util.spec_from_file_location("pa_look", os.path.join(root, "__init__.py"),
                                              submodule_search_locations=[root])
pkg = importlib.util.module_from_spec(spec); sys.modules["pa_look"] = pkg; spec.loader.exec_module(pkg)
import bpy, numpy as np
pkg.register()
seq_mod = sys.modules["pa_look.blender_addon.sequence"]
ops = sys.modules["pa_look.blender_addon.operators_avatar"]
def first(*names):  # module names moved between add-on versions (the tier layout)
    for name in names:
        try:
            return importlib.import_module(name)
        except ImportError:
            pass
    raise ImportError(names)
pdata = first("pa_look.core.bridge.transforms", "pa_look.core.bridge.preview", "pa_look.core.preview_data")
Camera = first("pa_look.core.geometry.camera", "pa_look.core.camera").Camera
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob)
sc = bpy.context.scene
sc.frame_start = 1
bpy.ops.import_scene.progressive_avatars_sequence(filepath=args["sequence"])
mesh = bpy.context.active_object
bpy.ops.object.progressive_avatars_load(filepath=args["stream"], budget=100.0)
pv = [c for c in mesh.children if c.pa_avatar.is_preview][0]
c = args["camera"]
cam_obj, s = seq_mod.add_camera(bpy.context, "dataset_cam", Camera(np.array(c["R"]), np.array(c["t"]), *c["intr"]))
sc.camera = cam_obj
world = bpy.data.worlds.new("look_world"); world.color = (0, 0, 0); sc.world = world
for node in (world.node_tree.nodes if world.node_tree else ()):  # the rasteriser's black background
    if node.type == "BACKGROUND":
        node.inputs["Color"].default_value = (0, 0, 0, 1)
sc.render.engine = "CYCLES"; sc.cycles.device = "CPU"; sc.cycles.samples = args["samples"]
sc.cycles.use_denoising = False
sc.render.resolution_x, sc.render.resolution_y = s["resolution"]
sc.render.resolution_percentage = 100
sc.render.threads_mode = "FIXED"; sc.render.threads = 2
mesh.hide_render = True
sc.frame_set(sc.frame_start + args["frame"])
pv.pa_avatar.budget = 100.0
look = sys.modules.get("pa_look.blender_addon.splat_look")
default_filter = sc.cycles.filter_width
report = {"count": pv.pa_avatar.count, "variants": {}}
for v in args["variants"]:
    kw = {"min_transparent_bounces": args["min_bounces"]} if args["min_bounces"] else {}
    if v.get("as_trained"):
        kw["as_trained"] = True
    elif look is not None and "as_trained" in look.configure_scene.__code__.co_varnames:
        kw["as_trained"] = False
    if look is not None:
        changed = look.configure_scene(sc, **kw)
    else:  # an older add-on: the settings its own demo used
        sc.view_settings.view_transform = "Standard"; sc.cycles.transparent_max_bounces = 128; changed = {}
    mod = pv.modifiers[0]
    for name, value in v.get("inputs", {}).items():  # the splat modifier's inputs (Detail, ...)
        key = next(i.identifier for i in mod.node_group.interface.items_tree if getattr(i, "name", None) == name)
        mod[key] = value
    for name, value in v.get("nodes", {}).items():  # value nodes in the splat group (pa_extent, ...)
        mod.node_group.nodes[name].outputs[0].default_value = value
    pv.update_tag()
    sc.cycles.filter_width = v.get("filter") or args["filter"] or default_filter
    sc.render.filepath = os.path.join(args["out"], "cycles_" + v["name"] + ".png")
    t0 = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    report["variants"][v["name"]] = {"seconds": time.perf_counter() - t0,
                                     "changed": {k: [str(a), str(b)] for k, (a, b) in changed.items()}}
    print("PA_LOOK_VARIANT", v["name"], report["variants"][v["name"]]["seconds"], flush=True)
g = ops.current_gaussians(bpy.context, pv, world=True)
w, h = s["resolution"]
cam = pdata.camera_from_blender(np.array(cam_obj.matrix_world), cam_obj.data.lens, cam_obj.data.sensor_width,
                                cam_obj.data.shift_x, cam_obj.data.shift_y, w, h, z_up=False)
np.savez(os.path.join(args["out"], "gaussians.npz"), R=cam.R, t=cam.t, intr=[cam.fx, cam.fy, cam.cx, cam.cy],
         size=[w, h], **g)
print("PA_LOOK " + json.dumps(report))
"""


def _own_args():
    return sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]


def psnr(a, b, mask=None):
    err = (a - b) ** 2
    mse = float(err[mask].mean()) if mask is not None else float(err.mean())
    return 10 * np.log10(1.0 / max(mse, 1e-12))


DOC_TEXT = """\
## How the splat look works

*Load Progressive Avatar* and *Import 3DGS PLY* make a point per Gaussian; the **PA Splats**
Geometry Nodes modifier instances a hull on each point that covers the splat exactly as far
as the rasteriser draws it: out to k = sqrt(2 ln(255·opacity)) standard deviations (where
its alpha falls below 1/255, the rasteriser's cut-off: 3.33 at the 0.99 clamp, less for
fainter splats, so faint splats cost Cycles less) of the *dilated* Gaussian, σ² + ε, with
ε = 0.3·(d/f)² the rasteriser's 0.3 px² dilation in world units (d the distance to the
active camera, f the camera's focal length in pixels, the group's `pa_focal_px` value).
Both numbers are written by *Splat Render Settings*: press it again after changing the
camera or the resolution. The hull decides only what is covered and, in Cycles, the order
in which splats composite (Cycles composites surfaces in the order rays hit them); the
material computes the splat itself.

- **Camera Cards** (on by default): a flat quad through each splat's centre, parallel to
  the camera's image plane, with half-extents k·sqrt(cᵀΣc + ε) along the camera's x and y
  axes c (the footprint's extent). Every ray meets a card at its splat's view depth, so the
  splats composite in order of view depth, exactly as the rasteriser sorts them, and each
  ray crosses one surface per splat instead of two. Exact for the scene camera; seen from
  elsewhere the cards stand at an angle and clip their splats, so by default they are used
  for renders only (Geometry Nodes' *Is Viewport*): the viewport, orbiting freely, shows the
  ellipsoids. *Cards in Viewport* shows the cards there too (look through the camera).
- **Ellipsoids** (*Camera Cards* off): a closed ico-sphere hull (*Detail* sets its
  subdivisions) of radius 3σ of the undilated Gaussian, in the splat's own frame. Right
  from every view, but Cycles then composites in the order rays *enter* the hulls, which
  puts a large splat in front of the smaller ones around it, and the hull cuts sub-pixel
  splats' dilation short: the table's Camera Cards off row. Hulls that cover the dilated
  splat out to the cut-off (k·sqrt(σ² + ε), as the cards do) measured worse still, and
  slower (this section at commit 74a28ff, row "Camera Cards off"): they reorder more.

*Points Only* skips the instancing for speed in heavy scenes. `tests/test_blender_splat_look.py`
checks the cards' placement and extents and the ellipsoids' on the evaluated instances.

The **PA Splat** material (`blender_addon/splat_look.py`) evaluates the Gaussian on the
view ray itself, in world space: with x = hit point − centre (*Geometry > Position* and the
instance's `pa_center`), D the view direction (*Geometry > Incoming*), and the splat's axes
A_i = σ_i r_i (`pa_axis_x/y/z`, written by the Geometry Nodes in world space, so moving,
rotating or scaling the object is fine), the dilated Gaussian has weights
w_i = 1/(σ_i² + ε) along r_i (ε = 0.3·(z/f)², z the view depth from *Camera Data*, f the
material's `pa_focal_px`), and the ray passes its centre at squared Mahalanobis distance
d² = Σ w x'² − (Σ w x'D')²/Σ w D'² (x'_i = r_i·x, D'_i = r_i·D). The splat's alpha is
opacity · exp(−d²/2), clamped at 0.99 and dropped below 1/255 like the rasteriser's; back
faces are transparent, so each Gaussian counts once with either hull. That is the oriented
ellipse with its Gaussian falloff, independent of the hull's shape. Colour is the point's
`color` attribute (scene-linear, converted from the avatar's sRGB colours, clipped to
[0, 1]) as *Emission* strength 1, mixed with *Transparent* by alpha: splats are unlit, as
in training.

**Compositing space.** By default Blender composites the splats in scene-linear light
(correct for a scene with other objects and lights) and the *Standard* view transform
encodes the result to sRGB. The avatar was trained compositing sRGB-encoded colours (as the
rasteriser does), so where splats are semi-transparent over each other the two differ: a
faint splat edge is brighter when blended in linear light and encoded afterwards. That is
most of what remains in the table's default row. **As Trained** (the button next to
*Splat Render Settings*, or `configure_scene(scene, as_trained=True)`) sets the material's
`pa_as_trained` value to 1, so it emits the sRGB-encoded colour (the sRGB transfer
function in shader nodes), and the *Raw* view transform, which writes the composited values
without encoding: the splats then blend exactly as in training. The price: everything else
in the scene is shown raw too (linear values unencoded: dark), and light from lit objects
does not mix with the splats correctly. Use it to judge the avatar itself or render it
alone (a separate view layer or scene), not for a lit shot. Press *Splat Render Settings*
to go back to the default.

**Render settings** (*Splat Render Settings* button in the Avatar panel,
`splat_look.configure_scene`): view transform *Standard* (AgX/Filmic would tone-map the
avatar's colours, the "low-contrast" look), Cycles *Transparent* max bounces and *min*
transparent bounces 512 (Cycles' default of 8 stops rays inside the head, the "dark" look;
a lower minimum lets Russian roulette end rays at random, the "grain").

**EEVEE** (cannot run headless here, so not measured): the same material works unchanged;
its *Render Method* is set to **Dithered** (stochastic, order-independent transparency),
because EEVEE sorts blended surfaces per object, not per instance, so *Blended* would
composite splats of one avatar in the wrong order. Dithered converges to the correct
compositing over samples: use ≥ 64 render samples (viewport ≥ 16), and keep *Backface
Culling* on (set by the material). *Transparent shadows* is on; splats cast no light.
"""


def _section(path, key, body):
    """Replace (or append) the section between this key's markers in a markdown file."""
    start, end = f"<!-- {key} -->", f"<!-- /{key} -->"
    text = open(path).read() if os.path.exists(path) else "# The splat look and Render Splats in Blender\n\n"
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text and end in text:
        text = text[: text.index(start)] + block + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    with open(path + ".tmp", "w") as fh:
        fh.write(text)
    os.replace(path + ".tmp", path)


def _blender_render(root, payload, out):
    """Run the child for one add-on source tree; returns (child report, {variant: Cycles image}, Gaussians)."""
    from PIL import Image

    os.makedirs(out, exist_ok=True)
    payload = dict(payload, root=os.path.abspath(root), out=out)
    tmp = tempfile.mkdtemp(prefix="pa_look_user_")
    try:
        env = dict(
            os.environ,
            BLENDER_USER_RESOURCES=tmp,
            BLENDER_USER_CONFIG=os.path.join(tmp, "config"),
            BLENDER_USER_SCRIPTS=os.path.join(tmp, "scripts"),
        )
        script = os.path.join(tmp, "look_child.py")
        with open(script, "w") as fh:
            fh.write(CHILD)
        proc = subprocess.run([sys.executable, script, json.dumps(payload)], capture_output=True, text=True, env=env)
    finally:  # Blender's user folder is only for this child
        shutil.rmtree(tmp, ignore_errors=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PA_LOOK ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"Blender child failed for {root}:\n" + proc.stdout[-3000:] + proc.stderr[-3000:])
    child = json.loads(lines[-1][len("PA_LOOK ") :])
    images = {
        name: np.asarray(Image.open(os.path.join(out, f"cycles_{name}.png")).convert("RGB"), np.float32) / 255.0
        for name in child["variants"]
    }
    with np.load(os.path.join(out, "gaussians.npz")) as d:
        g = {key: d[key] for key in d.files}
    return child, images, g


LABELS = {
    "default": "this add-on (world-space splat material, Camera Cards to the 1/255 cut-off, splat render settings)",
    "ellipsoids": "this add-on with *Camera Cards* off (closed ellipsoid hulls, right from any view)",
    "as_trained": "this add-on, *As Trained* (sRGB colours composited as-is, Raw view transform; opt-in)",
}


def _variant(text):
    """NAME or NAME:JSON (keys: as_trained, inputs, nodes, filter, label), for experiments."""
    name, _, spec = text.partition(":")
    return dict(json.loads(spec) if spec else {}, name=name)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument(
        "--size", type=int, default=256, help="longer image side in pixels (the dataset camera is scaled to it)"
    )
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--filter", type=float, default=0.0, help="Cycles pixel filter width (0: Blender's default)")
    ap.add_argument("--root", default=os.path.dirname(HERE))
    ap.add_argument(
        "--min-bounces", type=int, default=0, help="Cycles min transparent bounces (0: the add-on's setting)"
    )
    ap.add_argument(
        "--baseline-root",
        action="append",
        default=[],
        help="also measure the look of this (older) add-on source tree, same run (repeatable)",
    )
    ap.add_argument("--as-trained", action="store_true", help="also render with the opt-in As Trained compositing")
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        type=_variant,
        help="extra render NAME:JSON of this tree (experiments)",
    )
    ap.add_argument("--side-by-side", help="write the side-by-side PNG here (default OUT/side_by_side.png)")
    ap.add_argument("--doc", help="write the results into this markdown file's splat-look section")
    args = ap.parse_args(_own_args() if argv is None else argv)
    if args.size < 1:
        ap.error(f"--size is the longer image side in pixels, at least 1, got {args.size}")
    if args.side_by_side:  # written after the Blender renders: a path that cannot take it is refused now
        from progressive_avatars.core.io.atomic import image_format

        if os.path.isdir(args.side_by_side) or image_format(args.side_by_side) is None:
            ap.error(f"--side-by-side {args.side_by_side}: not a picture file name PIL can write (.png, .jpg, ...)")
    from PIL import Image

    from progressive_avatars.core.io.atomic import atomic_save_image
    from progressive_avatars.core.io.atomic import atomic_open
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.geometry.camera import Camera
    from progressive_avatars.core.render.rasterize import render_numpy

    sys.path.insert(0, HERE)
    from blender_demo import find_stream

    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    stream = find_stream(args.run)
    if stream is None:
        raise SystemExit(f"{args.run}: no .pavs stream in this run")
    split = "test" if os.path.exists(os.path.join(args.data, "transforms_test.json")) else "train"
    ds = Dataset(args.data, split)
    seq = ds.sequence()
    sequence = os.path.join(out, "sequence.npz")
    np.savez(sequence, vertices=seq.vertices, faces=seq.faces)
    cam_id = sorted(ds.cameras)[0]
    c = ds.cameras[cam_id]
    k = args.size / max(c.width, c.height)
    camera = {
        "R": c.R.tolist(),
        "t": c.t.tolist(),
        "intr": [c.fx * k, c.fy * k, c.cx * k, c.cy * k, int(round(c.width * k)), int(round(c.height * k))],
    }
    frame = len(seq.vertices) // 2
    payload = {
        "sequence": sequence,
        "stream": os.path.abspath(stream),
        "samples": args.samples,
        "camera": camera,
        "frame": frame,
        "filter": args.filter,
        "min_bounces": args.min_bounces,
    }
    # Baselines first, then this tree: each Blender child renders its variants back to back.
    renders = []  # (label, root, variant, image, seconds, changed)
    g = None
    same = True
    for root in args.baseline_root:
        base_child, base_imgs, base_g = _blender_render(
            root, dict(payload, variants=[{"name": "default"}]), os.path.join(out, "baseline_" + os.path.basename(root))
        )
        if g is not None:
            same &= all(np.array_equal(g[key], base_g[key]) for key in ("means", "quats", "scales", "opacities"))
        g = g if g is not None else base_g
        v = base_child["variants"]["default"]
        renders.append((f"before (`{os.path.basename(root)}`)", root, "default", base_imgs["default"], v["seconds"], v))
    variants = [{"name": "default"}] + ([{"name": "as_trained", "as_trained": True}] if args.as_trained else [])
    child, imgs, new_g = _blender_render(
        args.root, dict(payload, variants=variants + args.variant), os.path.join(out, "new")
    )
    if g is not None:
        same &= all(np.array_equal(g[key], new_g[key]) for key in ("means", "quats", "scales", "opacities"))
    g = new_g
    for name, img in imgs.items():
        v = child["variants"][name]
        label = next((x.get("label") for x in args.variant if x["name"] == name), None)
        renders.append((LABELS.get(name, label or name), args.root, name, img, v["seconds"], v))
    cam = Camera(g["R"], g["t"], *[float(x) for x in g["intr"]], int(g["size"][0]), int(g["size"][1]))
    t0 = time.perf_counter()
    image, alpha, _ = render_numpy(
        g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], cam, np.zeros(3, np.float32)
    )
    raster_s = time.perf_counter() - t0
    ref = np.clip(image, 0, 1)
    mask = alpha > 0.5
    atomic_save_image(Image.fromarray((ref * 255 + 0.5).astype(np.uint8)), os.path.join(out, "rasteriser.png"))
    shown = [r for r in renders if r[2] in ("default", "as_trained")]
    default = next(r[3] for r in renders if r[1] == args.root and r[2] == "default")
    panels = [r[3] for r in shown] + [ref, np.clip(np.abs(default - ref) * 4, 0, 1)]
    side_png = os.path.abspath(args.side_by_side or os.path.join(out, "side_by_side.png"))
    os.makedirs(os.path.dirname(side_png), exist_ok=True)
    atomic_save_image(Image.fromarray((np.concatenate(panels, axis=1) * 255 + 0.5).astype(np.uint8)), side_png)
    result = {
        "rows": [
            {
                "look": label,
                "root": os.path.abspath(root),
                "variant": name,
                "psnr_head_mask_db": round(psnr(img, ref, mask), 2),
                "psnr_full_db": round(psnr(img, ref), 2),
                "cycles_seconds": round(seconds, 1),
                "settings_changed": v["changed"],
            }
            for label, root, name, img, seconds, v in renders
        ],
        "panels": [r[0] for r in shown] + ["our rasteriser", "4 × abs(default − rasteriser)"],
        "same_gaussians": bool(same),
        "mask_fraction": round(float(mask.mean()), 4),
        "gaussians": child["count"],
        "size": [cam.width, cam.height],
        "samples": args.samples,
        "filter_width": args.filter or "default",
        "rasteriser_seconds": round(raster_s, 2),
        "stream": stream,
        "frame": frame,
        "camera": cam_id,
        "side_by_side": side_png,
    }
    result["machine"] = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared with other jobs)"
    result["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    result["command"] = "python scripts/splat_look.py " + shlex.join(_own_args() if argv is None else argv)
    with atomic_open(os.path.join(out, "look.json"), "w") as fh:
        json.dump(result, fh, indent=1)
    print(json.dumps(result, indent=1))
    if args.doc:
        _write_doc(args.doc, result)
    return 0


def _write_doc(path, r):
    rel = os.path.relpath(r["side_by_side"], os.path.dirname(os.path.abspath(path)))
    w, h = r["size"]

    def label(x):
        return x["look"] if x["look"].startswith("before") else LABELS.get(x["variant"], x["look"])

    table = "\n".join(
        f"| {label(x)} | {x['psnr_head_mask_db']:.2f} | {x['psnr_full_db']:.2f} | {x['cycles_seconds']:.0f} |"
        for x in r["rows"]
    )
    short = {"default": "default (Camera Cards)", "as_trained": "As Trained"}
    shown = [
        x["look"] if x["look"].startswith("before") else short[x["variant"]] for x in r["rows"] if x["variant"] in short
    ]
    panels = " | ".join(shown + ["our rasteriser", "4 × abs(default − rasteriser)"])
    body = f"""## Cycles against our rasteriser

A Cycles render (CPU, {r["samples"]} samples, no denoising, pixel filter {r["filter_width"]}) of the preview at
100 % ({r["gaussians"]:,} Gaussians, stream `{r["stream"]}`, test camera {r["camera"]}, frame {r["frame"]}) against
`core.render.render_numpy` of the same Gaussians from the same camera at {w}×{h} px, black background. PSNR
over the head mask (rasteriser alpha > 0.5, {100 * r["mask_fraction"]:.0f} % of the image) and over the whole
image; all rows rendered in the same run, one after the other ("before": the add-on source tree of an
earlier commit, `git archive COMMIT | tar -x -C DIR`); Cycles seconds on {r["machine"]}: the
machine was shared with 3 other agents' jobs, so the seconds are noisy: compare rows, not runs.

| look | PSNR head mask (dB) | PSNR image (dB) | Cycles s |
|---|---|---|---|
{table}

![{panels}]({rel})

{panels}. Written by `{r["command"]}` on {r["date"]}.

{DOC_TEXT}"""
    _section(path, "splat-look", body)


if __name__ == "__main__":
    sys.exit(main())
