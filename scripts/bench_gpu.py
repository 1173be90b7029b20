"""The gsplat (CUDA) path against the CPU rasteriser, and GPU training-iteration timings.

    python scripts/bench_gpu.py --out DIR [--quick]

Needs CUDA and an importable gsplat (it JIT-compiles its kernels on first use). Writes
DIR/gpu.json and DIR/gpu.md (a BENCHMARKS section): image/alpha/gradient parity between
``render(backend="cpu")`` and ``render(backend="gsplat")`` on the same head-like scene, gsplat
forward+backward time, and the time of a whole training iteration (binding, render of the
supervised levels, loss, backward, Adam) at the paper's 550x802 with ~150k Gaussians.
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


def iteration_timing(width, height, target, levels_mode):
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
        "iter_ms_median": med,
        "iter_ms_min": mn,
    }


def markdown(res):
    p = res["parity"]
    lines = [
        "## GPU: gsplat against the CPU rasteriser, and GPU iteration times (scripts/bench_gpu.py)",
        "",
        f"Machine: {res['gpu']}, torch {res['torch']}, gsplat {res['gsplat']}; date {res['date']}; "
        f"command `python scripts/bench_gpu.py --out DIR`. The first gsplat call builds its CUDA extension "
        f"(JIT, {res['jit_s']:.0f} s here{'' if res['jit_s'] > 10 else ', already cached'}).",
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
        "Whole training iteration on the GPU (torch face binding on CUDA, gsplat per supervised level, "
        "L1+SSIM, regularisers, backward, Adam), 550x802:",
        "",
        "| faces (depth) | supervised levels | median ms | best ms |",
        "|---|---|---|---|",
    ]
    for t in res["iteration"]:
        lines.append(
            f"| {t['faces']:,} ({t['depth']}) | {t['levels']} | {t['iter_ms_median']:.1f} | {t['iter_ms_min']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args(_bootstrap.script_args())
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
    res["iteration"] = [iteration_timing(550, 802, 20000 if a.quick else 150000, m) for m in ("finest", "two", "all")]
    print(json.dumps(res["iteration"]), flush=True)
    with open(os.path.join(a.out, "gpu.json"), "w") as fh:
        json.dump(res, fh, indent=1)
    with open(os.path.join(a.out, "gpu.md"), "w") as fh:
        fh.write(markdown(res))
    print(markdown(res))


if __name__ == "__main__":
    main()
