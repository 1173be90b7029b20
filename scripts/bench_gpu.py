"""The gsplat (CUDA) path against the CPU rasteriser, and GPU training-iteration timings.

    python scripts/bench_gpu.py --out DIR [--quick] [--scene SCENE]
    python scripts/bench_gpu.py --prepare-scene RUN --report REPORT.json --out SCENE   (no GPU needed)

Needs CUDA and an importable gsplat (it JIT-compiles its kernels on first use). Writes
DIR/gpu.json and DIR/gpu.md (a BENCHMARKS section): image/alpha/gradient parity between
``render(backend="cpu")`` and ``render(backend="gsplat")`` on the same head-like scene, gsplat
forward+backward time, and the time of a whole training iteration (binding, render of the
supervised levels, loss, backward, Adam) at the paper's 550x802 with ~150k Gaussians; with
--scene, a trained avatar's Table 1 budgets drawn and animated on the GPU.
"""

from __future__ import annotations

import os
import sys as _sys

_sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _bootstrap  # noqa: E402,F401

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench_render import head_camera, head_scene  # noqa: E402


def _cuda_ms(fn, repeats=20, warmup=3):
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        torch.cuda.synchronize()
        times.append(a.elapsed_time(b))
    return float(np.median(times)), float(np.min(times))


def parity(width, height, n):
    """Same scene, both backends: image/alpha differences and gradient agreement."""
    from progressive_avatars.core.render.rasterize import render

    cam = head_camera(width, height)
    base = [torch.from_numpy(x) for x in head_scene(n, seed=3)]
    bg = torch.tensor([1.0, 1.0, 1.0])
    names = ("means", "quats", "scales", "opacities", "colors")

    def run(device, backend):
        ps = [p.to(device).clone().requires_grad_(True) for p in base]
        out = render(*ps, cam, bg.to(device), backend=backend, compute_contrib=False)
        w = torch.linspace(0.5, 1.5, 3, device=device)  # a non-uniform loss so every gradient is exercised
        ((out.image * w).sum() + out.alpha.sum()).backward()
        return out, {k: p.grad.detach().cpu().double() for k, p in zip(names, ps)}

    t0 = time.perf_counter()
    cpu, gc = run("cpu", "cpu")
    cpu_s = time.perf_counter() - t0
    gpu, gg = run("cuda", "gsplat")
    img_c, img_g = cpu.image.detach().double(), gpu.image.detach().cpu().double()
    al_c, al_g = cpu.alpha.detach().double(), gpu.alpha.detach().cpu().double()
    res = {
        "width": width,
        "height": height,
        "n": n,
        "visible": int((cpu.radii > 0).sum()),
        "image_max_abs": float((img_c - img_g).abs().max()),
        "image_mean_abs": float((img_c - img_g).abs().mean()),
        "alpha_max_abs": float((al_c - al_g).abs().max()),
        "alpha_mean_abs": float((al_c - al_g).abs().mean()),
        "psnr_cpu_vs_gpu": float(10 * np.log10(1.0 / max(float(((img_c - img_g) ** 2).mean()), 1e-20))),
        "cpu_fwd_bwd_s_first": cpu_s,
        "grads": {},
    }
    for k in names:
        a, b = gc[k].reshape(-1), gg[k].reshape(-1)
        cos = float((a @ b) / max(float(a.norm() * b.norm()), 1e-30))
        rel = float((a - b).norm() / max(float(a.norm()), 1e-30))
        res["grads"][k] = {"cosine": cos, "rel_l2": rel}
    return res


def gsplat_timing(width, height, n):
    from progressive_avatars.core.render.rasterize import render

    cam = head_camera(width, height)
    base = [torch.from_numpy(x).cuda() for x in head_scene(n)]

    def fwd():
        with torch.no_grad():
            render(*base, cam, backend="gsplat", compute_contrib=False)

    def fwd_bwd():
        ps = [p.clone().requires_grad_(True) for p in base]
        out = render(*ps, cam, backend="gsplat", compute_contrib=False)
        out.image.sum().backward()

    f_med, f_min = _cuda_ms(fwd)
    fb_med, fb_min = _cuda_ms(fwd_bwd)
    return {
        "width": width,
        "height": height,
        "n": n,
        "fwd_ms_median": f_med,
        "fwd_ms_min": f_min,
        "fwd_bwd_ms_median": fb_med,
        "fwd_bwd_ms_min": fb_min,
    }


def grown_avatar(target, rng):
    """A template (~10k-face sphere, head-sized) grown by uneven splits to depth 4 until ~target faces."""
    from progressive_avatars.core.avatar.forest import Forest
    from progressive_avatars.core.synthetic.shapes import sphere_mesh

    verts, faces = sphere_mesh(70, 72, radius=0.1)
    forest = Forest(faces)
    frac = 1.0
    while forest.num_faces < target and forest.max_level < 4:
        leaves = forest.leaves()
        leaves = leaves[forest.level[leaves] == forest.max_level]
        need = (target - forest.num_faces) / 3
        frac = min(1.0, need / max(len(leaves), 1))
        if forest.max_level < 3:
            frac = min(frac, 0.6)
        forest.split(leaves[rng.random(len(leaves)) < frac])
    forest.split_logits[:] = rng.normal(0, 0.5, forest.split_logits.shape)
    return verts, forest


class _DeviceBinding:
    """The torch face binding (binding_torch, float64 like the numba kernels) on the tensors' device:
    TorchAvatar's own binding runs the numba kernels on the host, so CUDA tensors go there and back."""

    def __init__(self, forest, device):
        from progressive_avatars.core.train.binding_torch import TorchForest

        self.tf = TorchForest(forest, device=device)

    def gaussians(self, vertices, split_logits, d_mu, d_log_scale, d_rot):
        from progressive_avatars.core.train.binding_torch import compose

        t, r, s = self.tf.evaluate(vertices.double(), self.tf.weights(split_logits.double()))
        means, quats, scales = compose(t, r, s, d_mu.double(), d_log_scale.double(), d_rot.double())
        return means.float(), quats.float(), scales.float()


def iteration_timing(width, height, target, levels_mode, binding="host"):
    from progressive_avatars.core.avatar.avatar import Avatar
    from progressive_avatars.core.render.rasterize import render
    from progressive_avatars.core.train import losses
    from progressive_avatars.core.train.model import TorchAvatar
    from progressive_avatars.core.train.trainer import Adam

    rng = np.random.default_rng(0)
    verts, forest = grown_avatar(target, rng)
    av = Avatar.initial(forest, opacity=0.7)
    av.d_log_scale[:] = np.asarray((np.log(0.5), np.log(0.1), np.log(0.5)), np.float32)
    model = TorchAvatar(av, device="cuda")
    if binding == "device":
        model.binding = _DeviceBinding(forest, "cuda")
    opt = Adam(model.params, {k: 1e-3 for k in model.params})
    opt.steps = opt.steps.cuda()
    v = torch.tensor(verts, dtype=torch.float32, device="cuda")
    cam = head_camera(width, height)
    target_img = torch.rand(height, width, 3, device="cuda")
    bg = torch.ones(3, device="cuda")
    top = forest.max_level
    levels = {"finest": [top], "two": [0, top], "all": list(range(top + 1))}[levels_mode]

    def step():
        g = model.gaussians(v)
        loss = torch.zeros((), device="cuda")
        for lvl in levels:
            ids = model.level_ids[lvl]
            out = render(
                g["means"][ids],
                g["quats"][ids],
                g["scales"][ids],
                g["opacities"][ids],
                g["colors"][ids],
                cam,
                bg,
                backend="gsplat",
                compute_contrib=False,
            )
            loss = loss + losses.photometric(out.image, target_img, 0.2)
        loss = loss + 0.01 * losses.position_reg(model.params["d_mu"]) + losses.scale_reg(model.params["d_log_scale"])
        loss.backward()
        opt.step(model.params)

    med, mn = _cuda_ms(step, repeats=20, warmup=3)
    return {
        "width": width,
        "height": height,
        "faces": int(forest.num_faces),
        "depth": int(top),
        "levels": levels,
        "binding": binding,
        "iter_ms_median": med,
        "iter_ms_min": mn,
    }


# ----------------------------------------------------------------------------- a trained avatar
BUDGETS = ("5", "25", "50", "100")  # the paper's Table 1 rows


def prepare_scene(run, report_path, out):
    """Copy what ``avatar_frames`` needs off this machine into `out`: the run's stream, the val
    split's template faces, the vertices of its first views' timesteps, one camera, and the
    Gaussian count of each Table 1 budget from the evaluation report (the dataset itself is too
    large to travel)."""
    import shutil

    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.render.importance import view_subset

    with open(report_path) as fh:
        report = json.load(fh)
    ds = Dataset(runs.run_data_dir(run), "val")
    views = view_subset(len(ds), 16)[:8]
    infos = [ds.frame_info(int(v)) for v in views]
    cam = infos[0].camera
    os.makedirs(out, exist_ok=True)
    shutil.copyfile(os.path.join(run, "avatar.pavs"), os.path.join(out, "avatar.pavs"))
    np.savez(
        os.path.join(out, "scene.npz"),
        faces=np.asarray(ds.faces, np.int64),
        vertices=np.stack([ds.vertices_at(i.timestep_index) for i in infos]).astype(np.float32),
        R=np.asarray(cam.R, np.float64),
        t=np.asarray(cam.t, np.float64),
        background=np.asarray(ds.background, np.float32),
    )
    meta = {
        "run": run,
        "report": report_path,
        "camera": {k: float(getattr(cam, k)) for k in ("fx", "fy", "cx", "cy")}
        | {"width": int(cam.width), "height": int(cam.height)},
        "budgets": {b: int(report["budgets"][b]["gaussians"]) for b in BUDGETS},
        "cpu_render_ms": {b: float(report["budgets"][b]["render_ms"]) for b in BUDGETS},
    }
    with open(os.path.join(out, "scene.json"), "w") as fh:
        json.dump(meta, fh, indent=1)


def avatar_frames(scene):
    """A trained avatar's Table 1 prefixes on the GPU: gsplat forward alone, and a whole animated
    frame (the prefix's faces bound to a new mesh by the torch binding in float64 on the GPU, then
    gsplat), cycling over the scene's meshes. Also how far the GPU frame is from the numpy
    inference path (Gaussian means over the head's size; the images of both renderers)."""
    from progressive_avatars.core.avatar.avatar import sh_to_rgb, sigmoid
    from progressive_avatars.core.avatar.binding import compose as np_compose
    from progressive_avatars.core.avatar.binding import evaluate as np_evaluate
    from progressive_avatars.core.geometry.camera import Camera
    from progressive_avatars.core.render.rasterize import render, render_numpy
    from progressive_avatars.core.stream.reader import read_stream
    from progressive_avatars.core.train.binding_torch import TorchForest, compose

    with open(os.path.join(scene, "scene.json")) as fh:
        meta = json.load(fh)
    arr = np.load(os.path.join(scene, "scene.npz"))
    av = read_stream(os.path.join(scene, "avatar.pavs"), template_faces=arr["faces"])
    cam = Camera(R=arr["R"], t=arr["t"], **meta["camera"])
    forest = av.forest
    dev = "cuda"
    tf = TorchForest(forest, device=dev)
    W_np = forest.weights()
    W = torch.as_tensor(W_np, device=dev)
    verts = torch.as_tensor(arr["vertices"], device=dev, dtype=torch.float64)
    opac = torch.as_tensor(sigmoid(av.opacity_logit), device=dev)
    rgb = torch.as_tensor(sh_to_rgb(av.f_dc), device=dev)
    d = {k: torch.as_tensor(getattr(av, k), device=dev, dtype=torch.float64) for k in ("d_mu", "d_log_scale", "d_rot")}
    bg = torch.as_tensor(arr["background"], device=dev)
    rows = []
    for b in BUDGETS:
        ids_np = forest.drawn(forest.stream_ids(meta["budgets"][b]), records=meta["budgets"][b])
        ids = torch.as_tensor(ids_np, device=dev)
        sub = {k: v[ids] for k, v in d.items()}
        op, col = opac[ids], rgb[ids]
        frame_no = [0]

        def gaussians_of(v):
            t, r, s = tf.evaluate(v, W, ids)
            means, quats, scales = compose(t, r, s, sub["d_mu"], sub["d_log_scale"], sub["d_rot"])
            return means.float(), quats.float(), scales.float()

        def gaussians(i):
            return gaussians_of(verts[i])

        fixed = gaussians(0)

        def draw():
            with torch.no_grad():
                render(*fixed, op, col, cam, bg, backend="gsplat", compute_contrib=False)

        def frame():
            with torch.no_grad():
                i = frame_no[0] = (frame_no[0] + 1) % verts.shape[0]
                render(*gaussians(i), op, col, cam, bg, backend="gsplat", compute_contrib=False)

        r_med, r_min = _cuda_ms(draw, repeats=50, warmup=5)
        f_med, f_min = _cuda_ms(frame, repeats=50, warmup=5)
        # the binding's few dozen small kernels replayed as one CUDA graph (gsplat itself sizes
        # its buffers on the host, so it stays outside): the launch overhead of a frame
        g_med = g_min = graph_err = None
        try:
            static_v = verts[0].clone()
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.no_grad(), torch.cuda.stream(side):
                for _ in range(3):
                    gaussians_of(static_v)
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.no_grad(), torch.cuda.graph(graph):
                static_out = gaussians_of(static_v)

            def frame_graph():
                with torch.no_grad():
                    i = frame_no[0] = (frame_no[0] + 1) % verts.shape[0]
                    static_v.copy_(verts[i])
                    graph.replay()
                    render(*static_out, op, col, cam, bg, backend="gsplat", compute_contrib=False)

            g_med, g_min = _cuda_ms(frame_graph, repeats=50, warmup=5)
            static_v.copy_(verts[3])
            graph.replay()
            graph_err = max(float((a - b).abs().max()) for a, b in zip(static_out, gaussians(3)))
        except Exception as exc:  # noqa: BLE001  capture refused: report the eager frame only
            print("CUDA graph capture failed:", exc, flush=True)
        # the same prefix through the numpy inference path and the CPU rasteriser
        v0 = arr["vertices"][0]
        geo = np_evaluate(forest, v0, ids=ids_np, weights=W_np)
        ref = np_compose(geo.t, geo.r, geo.s, av.d_mu[ids_np], av.d_log_scale[ids_np], av.d_rot[ids_np])
        # over the head's size: a sliver face's scale can be 1e-8 m, below float32 rounding of a position
        size = float(np.linalg.norm(ref.means.max(0) - ref.means.min(0)))
        mean_err = float(np.max(np.linalg.norm(fixed[0].double().cpu().numpy() - ref.means, axis=1)) / size)
        img_c, _, _ = render_numpy(
            ref.means,
            ref.quats,
            ref.scales,
            sigmoid(av.opacity_logit[ids_np]),
            sh_to_rgb(av.f_dc[ids_np]),
            cam,
            arr["background"],
        )
        with torch.no_grad():
            img_g = render(*fixed, op, col, cam, bg, backend="gsplat", compute_contrib=False).image
        mse = float(np.mean((img_c.astype(np.float64) - img_g.double().cpu().numpy()) ** 2))
        rows.append(
            {
                "budget": b,
                "gaussians": int(len(ids_np)),
                "render_ms_median": r_med,
                "render_ms_min": r_min,
                "frame_ms_median": f_med,
                "frame_ms_min": f_min,
                "frame_graph_ms_median": g_med,
                "frame_graph_ms_min": g_min,
                "graph_max_abs_diff": graph_err,
                "cpu_render_ms": meta["cpu_render_ms"][b],
                "means_err_rel_size": mean_err,
                "psnr_cpu_vs_gpu": float(10 * np.log10(1.0 / max(mse, 1e-20))),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return {"run": meta["run"], "report": meta["report"], "width": cam.width, "height": cam.height, "rows": rows}


def markdown(res):
    p = res["parity"]
    lines = [
        "## GPU: gsplat against the CPU rasteriser, and GPU iteration times (scripts/bench_gpu.py)",
        "",
        f"Machine: {res['gpu']}, torch {res['torch']}, gsplat {res['gsplat']}; date {res['date']}; "
        f"command `{res.get('command', 'python scripts/bench_gpu.py --out DIR')}`. The first gsplat call builds its CUDA extension "
        f"(JIT, {res['jit_s']:.0f} s here{'' if res['jit_s'] > 10 else ', already cached'})."
        + (
            f" SCENE was written on the CPU machine by `python scripts/bench_gpu.py --prepare-scene "
            f"{res['avatar']['run']} --report {res['avatar']['report']} --out SCENE`."
            if res.get("avatar")
            else ""
        ),
        "",
        f"Parity on one head-like scene ({p['n']:,} Gaussians, {p['visible']:,} visible, {p['width']}x{p['height']}, "
        "white background; CPU backend float32 inputs vs gsplat):",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| image max / mean abs difference | {p['image_max_abs']:.2e} / {p['image_mean_abs']:.2e} |",
        f"| alpha max / mean abs difference | {p['alpha_max_abs']:.2e} / {p['alpha_mean_abs']:.2e} |",
        f"| PSNR of one image against the other | {p['psnr_cpu_vs_gpu']:.1f} dB |",
    ]
    for k, g in p["grads"].items():
        lines.append(f"| gradient of {k}: cosine / relative L2 difference | {g['cosine']:.5f} / {g['rel_l2']:.2e} |")
    lines += ["", "| gsplat render | median ms | best ms |", "|---|---|---|"]
    for t in res["render"]:
        lines.append(
            f"| {t['width']}x{t['height']}, {t['n']:,} Gaussians, forward | {t['fwd_ms_median']:.2f} | "
            f"{t['fwd_ms_min']:.2f} |"
        )
        lines.append(
            f"| {t['width']}x{t['height']}, {t['n']:,} Gaussians, forward+backward | "
            f"{t['fwd_bwd_ms_median']:.2f} | {t['fwd_bwd_ms_min']:.2f} |"
        )
    lines += [
        "",
        "Whole training iteration (face binding, gsplat per supervised level, L1+SSIM, regularisers, "
        "backward, Adam), 550x802. Binding *host*: TorchAvatar's own, the float64 numba kernels on the "
        "host CPU (the CUDA tensors go there and back each step); *device*: the torch binding "
        "(core/train/binding_torch.py) in float64 on the GPU. The trainer itself runs on the CPU only; "
        "these rows time its step's parts on the GPU:",
        "",
        "| faces (depth) | supervised levels | binding | median ms | best ms |",
        "|---|---|---|---|---|",
    ]
    for t in res["iteration"]:
        lines.append(
            f"| {t['faces']:,} ({t['depth']}) | {t['levels']} | {t.get('binding', 'host')} | "
            f"{t['iter_ms_median']:.1f} | {t['iter_ms_min']:.1f} |"
        )
    av = res.get("avatar")
    if av:
        from progressive_avatars.core.evaluate.sweep import PAPER_TABLE1

        lines += [
            "",
            f"The trained paper-scale avatar (`{av['run']}`; Gaussian counts of the Table 1 budgets from "
            f"`{av['report']}`) at {av['width']}x{av['height']}, forward only: *render* draws fixed Gaussians; "
            "*frame* binds the prefix to the next of 8 tracked meshes on the GPU (torch binding, float64) "
            "and draws it, as an animated avatar does each frame. The paper's FPS are an RTX 4090's "
            "(DESIGN.md); the CPU column is the evaluation's render_numpy on this project's 2-core VM. "
            "Agreement with the numpy inference path on the first mesh: Gaussian means (max distance "
            "over the head's bounding-box diagonal) and the CPU rasteriser's image of the same prefix (PSNR):",
            "",
            "| budget | Gaussians | render ms median / best | frame ms median / best | frame, binding as a CUDA "
            "graph, ms median / best | frame FPS (faster path) | paper FPS | CPU render ms | means error / head size "
            "| image PSNR CPU vs GPU |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in av["rows"]:
            g = r.get("frame_graph_ms_median")
            best = min(r["frame_ms_median"], g) if g else r["frame_ms_median"]
            graph = f"{g:.2f} / {r['frame_graph_ms_min']:.2f}" if g else "capture refused"
            lines.append(
                f"| {r['budget']} % | {r['gaussians']:,} | {r['render_ms_median']:.2f} / {r['render_ms_min']:.2f} | "
                f"{r['frame_ms_median']:.2f} / {r['frame_ms_min']:.2f} | {graph} | {1e3 / best:.0f} | "
                f"{PAPER_TABLE1[r['budget']][6]} | {r['cpu_render_ms']:.0f} | {r['means_err_rel_size']:.1e} | "
                f"{r['psnr_cpu_vs_gpu']:.1f} dB |"
            )
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scene", help="a folder written by --prepare-scene: time a trained avatar's budgets too")
    ap.add_argument(
        "--prepare-scene",
        metavar="RUN",
        help="(no GPU needed) copy RUN's stream, meshes and camera into --out for a later --scene run",
    )
    ap.add_argument("--report", help="with --prepare-scene: the evaluation report.json giving the budgets' counts")
    a = ap.parse_args(_bootstrap.script_args())
    if a.prepare_scene:
        if not a.report:
            raise SystemExit("bench_gpu: --prepare-scene needs --report (the run's evaluation report.json)")
        prepare_scene(a.prepare_scene, a.report, a.out)
        return
    if not torch.cuda.is_available():
        raise SystemExit("bench_gpu: no CUDA device")
    os.makedirs(a.out, exist_ok=True)
    import gsplat

    from progressive_avatars.core.render.rasterize import gsplat_available, render

    assert gsplat_available(), "gsplat does not import"
    t0 = time.perf_counter()  # first call builds gsplat's CUDA extension
    ps = [torch.from_numpy(x).cuda() for x in head_scene(100)]
    render(*ps, head_camera(64, 64), backend="gsplat", compute_contrib=False)
    torch.cuda.synchronize()
    jit = time.perf_counter() - t0
    n = 20000 if a.quick else 170000
    res = {
        "gpu": torch.cuda.get_device_name(0),
        "torch": torch.__version__,
        "gsplat": gsplat.__version__,
        "date": datetime.date.today().isoformat(),
        "jit_s": jit,
        "host": platform.node(),
    }
    print("jit", jit, flush=True)
    res["parity"] = parity(802, 550, n)
    print(json.dumps(res["parity"]), flush=True)
    res["render"] = [gsplat_timing(802, 550, n), gsplat_timing(550, 802, n)]
    print(json.dumps(res["render"]), flush=True)
    target = 20000 if a.quick else 150000
    res["iteration"] = [
        iteration_timing(550, 802, target, m, binding)
        for binding in ("host", "device")
        for m in ("finest", "two", "all")
    ]
    print(json.dumps(res["iteration"]), flush=True)
    res["command"] = "python scripts/bench_gpu.py --out DIR" + (" --scene SCENE" if a.scene else "")
    if a.scene:
        res["avatar"] = avatar_frames(a.scene)
    with open(os.path.join(a.out, "gpu.json"), "w") as fh:
        json.dump(res, fh, indent=1)
    with open(os.path.join(a.out, "gpu.md"), "w") as fh:
        fh.write(markdown(res))
    print(markdown(res))


if __name__ == "__main__":
    main()
