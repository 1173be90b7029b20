"""Build a demo .blend: the sequence as a shape-keyed mesh, the avatar's splat preview with its
budget slider, depth colours, and Cycles preview PNGs at a few budgets.

    python scripts/blender_demo.py [--run RUN --data DIR] --out DIR [--size PX] [--samples N] [--budgets 5,25,100]

With --run (a training run folder holding a .pavs stream) and --data (its dataset: the
sequence comes from its test split, cameras from it too) the real avatar is shown; without
them a small built-in avatar on the synthetic head is generated. Blender runs in a child
process with a temporary BLENDER_USER_RESOURCES (the bpy module is one per process).
"""

from __future__ import annotations

import os as _os
import sys as _sys

# Blender's --python does not put the script's folder on sys.path; plain python does.
_sys.path.insert(0, _os.path.dirname(_os.path.abspath(__file__)))
import _bootstrap  # noqa: F401

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def builtin_inputs(folder, frames=24, seed=0):
    """The synthetic head posed over `frames` frames, and a stream of Gaussians on it coloured
    by the head's procedural albedo (a stand-in when no trained run exists)."""
    from progressive_avatars.core.avatar import binding
    from progressive_avatars.core.synthetic import rig, surface, texture
    from progressive_avatars.core.avatar.avatar import SH_C0, Avatar
    from progressive_avatars.core.avatar.forest import Forest
    from progressive_avatars.core.stream.writer import write_stream

    rng = np.random.default_rng(seed)
    v, f = surface.head_template(4)
    verts = np.stack([rig.pose_head(v, rig.sequence_params(0, t, frames)) for t in range(frames)])
    seq = os.path.join(folder, "sequence.npz")
    np.savez(seq, vertices=verts.astype(np.float32), faces=f)
    forest = Forest(f)
    forest.subdivide_uniform(1)
    for _ in range(2):  # deeper where the albedo varies most: eyes, mouth, hair line
        leaves = forest.leaves()
        t = binding.evaluate(forest, v, ids=leaves).t
        detail = np.linalg.norm(texture.albedo(t) - texture.albedo(t * 1.01), axis=1)
        forest.split(leaves[detail > np.quantile(detail, 0.6)])
    geo = binding.evaluate(forest, v)
    av = Avatar.initial(forest)
    N = forest.num_faces
    av.f_dc[:] = (texture.albedo(geo.t) - 0.5) / SH_C0
    av.d_log_scale[:] = np.log(0.55) + rng.normal(0, 0.05, (N, 3))
    av.d_log_scale[:, 1] = np.log(0.12)  # flat along the normal, like trained surface splats
    av.opacity_logit[:] = 3.0
    stream = os.path.join(folder, "builtin_avatar.pavs")
    # Coarse faces first, then large faces: a plausible importance for a demo.
    write_stream(stream, av, importance=geo.s.astype(np.float64))
    return seq, stream


def find_stream(run):
    cands = [os.path.join(dp, fn) for dp, _, fns in os.walk(run) for fn in fns if fn.endswith(".pavs")]
    return max(cands, key=os.path.getmtime) if cands else None


CHILD = r"""
import json, os, sys
sys.path.insert(0, sys.argv[1])
import _bootstrap
import bpy, numpy as np
import progressive_avatars
progressive_avatars.register()
from progressive_avatars.blender_addon import sequence as seq_mod
args = json.loads(sys.argv[2])
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob)
sc = bpy.context.scene
sc.frame_start = 1
res = bpy.ops.import_scene.progressive_avatars_sequence(filepath=args["sequence"])
mesh = bpy.context.active_object
bpy.ops.object.progressive_avatars_load(filepath=args["stream"], budget=25.0)
pv = [c for c in mesh.children if c.pa_avatar.is_preview][0]
cam_obj = None
if args.get("camera"):
    from progressive_avatars.core.geometry.camera import Camera
    c = args["camera"]
    cam_obj, s = seq_mod.add_camera(bpy.context, "dataset_cam", Camera(np.array(c["R"]), np.array(c["t"]), *c["intr"]))
if cam_obj is None:
    cam = bpy.data.cameras.new("demo_cam"); cam.lens = 85
    cam_obj = bpy.data.objects.new("demo_cam", cam); sc.collection.objects.link(cam_obj)
    lo, hi = np.array(mesh.bound_box[0]), np.array(mesh.bound_box[6])
    centre = np.array(mesh.matrix_world) @ np.append((lo + hi) / 2, 1)
    size = float(np.max(hi - lo))
    cam_obj.location = (centre[0], centre[1] - 3.2 * size, centre[2])
    cam_obj.rotation_euler = (np.pi / 2, 0, 0)
sc.camera = cam_obj
world = bpy.data.worlds.new("demo_world"); sc.world = world
sc.render.engine = "CYCLES"; sc.cycles.device = "CPU"; sc.cycles.samples = args["samples"]
sc.cycles.use_denoising = False; sc.cycles.transparent_max_bounces = 128
sc.view_settings.view_transform = "Standard"
sc.render.resolution_x = sc.render.resolution_y = args["size"]; sc.render.resolution_percentage = 100
sc.render.film_transparent = False
mesh.hide_render = True
sc.frame_set(sc.frame_start + (mesh.pa_mesh.num_frames // 2))
pngs = {}
for b in args["budgets"]:
    pv.pa_avatar.budget = float(b)
    path = os.path.join(args["out"], f"preview_{int(b):03d}.png")
    sc.render.filepath = path
    bpy.ops.render.render(write_still=True)
    pngs[b] = {"png": path, "gaussians": pv.pa_avatar.count, "mb": round(pv.pa_avatar.megabytes, 3),
               "level": pv.pa_avatar.level_reached}
pv.pa_avatar.budget = 25.0
mesh.hide_render = False
blend = os.path.join(args["out"], "demo.blend")
bpy.ops.wm.save_as_mainfile(filepath=blend)
print("PA_DEMO " + json.dumps({"blend": blend, "renders": pngs, "total": pv.pa_avatar.total,
                               "legend": [[i.depth, i.faces] for i in mesh.pa_mesh.depth_legend]}))
"""


def _own_args():
    # _bootstrap.script_args() takes any argv[0] starting with "blender" for the Blender
    # binary, which this script's own name does.
    return sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]


def write_strip(result, path):
    """The Cycles previews side by side, each labelled with its budget, Gaussians and megabytes."""
    from PIL import Image

    from progressive_avatars.core.evaluate.plots import labelled_strip

    renders = sorted(result["renders"].items(), key=lambda kv: float(kv[0]))
    panels = [np.asarray(Image.open(r["png"]).convert("RGBA")) for _, r in renders]
    labels = [f"{float(b):g} %: {r['gaussians']:,} Gaussians, {r['mb']:.2f} MB" for b, r in renders]
    return labelled_strip(path, panels, labels, f"Blender preview (Cycles) of {result['total']:,} Gaussians")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run")
    ap.add_argument("--data")
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--budgets", default="5,25,100")
    args = ap.parse_args(_own_args() if argv is None else argv)
    if bool(args.run) != bool(args.data):  # a run alone once fell back to the built-in avatar
        ap.error("--run and --data go together (the run's stream and the dataset whose sequence and camera it shows)")
    stream = find_stream(args.run) if args.run else None
    if args.run and not stream:
        ap.error(f"--run {args.run}: no .pavs stream in that run folder (scripts/export.py --stream writes one)")
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    camera = None
    if stream and args.data:
        from progressive_avatars.core.io.dataset import Dataset

        ds = (
            Dataset(args.data, "test")
            if os.path.exists(os.path.join(args.data, "transforms_test.json"))
            else Dataset(args.data, "train")
        )
        seq = ds.sequence()
        sequence = os.path.join(out, "sequence.npz")
        np.savez(sequence, vertices=seq.vertices, faces=seq.faces)
        c = ds.cameras[sorted(ds.cameras)[0]]
        camera = {"R": c.R.tolist(), "t": c.t.tolist(), "intr": [c.fx, c.fy, c.cx, c.cy, c.width, c.height]}
        source = f"run {args.run}, data {args.data}"
    else:
        sequence, stream = builtin_inputs(out)
        source = "built-in synthetic head avatar"
    payload = {
        "sequence": sequence,
        "stream": stream,
        "out": out,
        "size": args.size,
        "samples": args.samples,
        "budgets": [float(b) for b in args.budgets.split(",")],
        "camera": camera,
    }
    tmp = tempfile.mkdtemp(prefix="pa_demo_user_")
    env = dict(
        os.environ,
        BLENDER_USER_RESOURCES=tmp,
        BLENDER_USER_CONFIG=os.path.join(tmp, "config"),
        BLENDER_USER_SCRIPTS=os.path.join(tmp, "scripts"),
    )
    script = os.path.join(tmp, "demo_child.py")
    with open(script, "w") as fh:
        fh.write(CHILD)
    proc = subprocess.run([sys.executable, script, HERE, json.dumps(payload)], capture_output=True, text=True, env=env)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PA_DEMO ")]
    if proc.returncode != 0 or not lines:
        sys.stderr.write(proc.stdout[-3000:] + proc.stderr[-3000:])
        return 1
    result = json.loads(lines[-1][len("PA_DEMO ") :])
    result["source"] = source
    result["strip"] = write_strip(result, os.path.join(out, "strip.png"))
    with open(os.path.join(out, "demo.json"), "w") as fh:
        json.dump(result, fh, indent=1)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
