"""Differentiable Gaussian rasteriser: CPU numba kernels, gsplat on CUDA, one function.

``render`` takes *activated* Gaussians (see docs/ARCHITECTURE.md) and a ``Camera`` and returns a
``RenderOutput``. On the CPU the forward and backward are the hand-written kernels of
``render_kernels``; with CUDA tensors and gsplat importable, ``backend="auto"`` uses
``gsplat.rasterization`` instead. Both follow the same rules (EWA + eps2d dilation without
opacity compensation, near-plane culling, alpha from 1/255, a pixel stops before the Gaussian
that takes its transmittance below 1e-4) but one: the CPU kernels clamp alpha at 0.99 as INRIA's
3DGS does, gsplat (1.x) at 0.999, so a pixel under nearly opaque layers can differ by about 1 %
(scripts/bench_gpu.py measures the two on a GPU).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Optional

# numba's parallel kernels run on the OpenMP runtime that torch also loads. Its default
# barrier spinning starves the thread being waited for when the machine is shared: a
# 256x256/40k forward+backward measured ~100 ms with PASSIVE and ~650 ms without, on 2 busy
# cores. The runtime reads this once, when first loaded (usually by `import torch`), so it
# only helps if this module is imported first; entry points should set it themselves.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from . import kernels as rk  # noqa: E402
from ..geometry.camera import Camera  # noqa: E402

__all__ = ["RenderOutput", "render", "render_levels", "render_numpy", "gsplat_available"]


@dataclass
class RenderOutput:
    image: torch.Tensor  # [H, W, C], differentiable
    alpha: torch.Tensor  # [H, W], differentiable
    means2d: torch.Tensor  # [N, 2]; after backward, .grad = dL/d(projected mean) in pixels (densification)
    contrib: Optional[torch.Tensor]  # [N], sum over pixels of alpha*T (no grad)
    radii: torch.Tensor  # [N] int, 0 = culled / not visible
    depth: Optional[torch.Tensor] = None  # [H, W], alpha-normalised camera z (0 where alpha = 0)


# ----------------------------------------------------------------------------- validation


def _shape(x) -> tuple:
    return tuple(x.shape)


def all_finite(x) -> bool:
    """No NaN or inf in x (a tensor or an array). A sum is several times cheaper than
    isfinite().all() and is non-finite whenever an element is; only then (an overflow of huge
    finite values can cause it too) does the exact test decide."""
    if isinstance(x, torch.Tensor):
        if not x.is_floating_point() or math.isfinite(float(x.detach().sum())):
            return True
        return bool(torch.isfinite(x).all())
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        return True
    with np.errstate(over="ignore", invalid="ignore"):
        if math.isfinite(float(x.sum())):
            return True
    return bool(np.isfinite(x).all())


# What render refuses in the Gaussians' values, in the order it reports them (rk.check_gaussians' bits).
_VALUE_ERRORS = (
    (rk.BAD_MEANS, "render: means contain NaN or inf"),
    (rk.BAD_QUATS, "render: quats contain NaN or inf"),
    (rk.ZERO_QUATS, "render: quats must have a non-zero norm whose square is finite"),
    (rk.BAD_SCALES, "render: scales must be finite and > 0 (activated standard deviations)"),
    (rk.BAD_OPACITIES, "render: opacities must be finite and in [0, 1] (activated, not logits)"),
    (rk.BAD_COLORS, "render: colors contain NaN or inf"),
)


def _value_flags(means, quats, scales, opacities, colors) -> int:
    """rk.check_gaussians' bits: one compiled pass over the callers' arrays when they are float32
    or float64 in main memory (the rasteriser's own path), else the same tests as torch or numpy
    operations (CUDA tensors for gsplat, other dtypes)."""
    arrays = _host_arrays(means, quats, scales, opacities, colors)
    if arrays is not None:
        return int(rk.check_gaussians(*arrays))
    flags = 0
    if not all_finite(means):
        flags |= rk.BAD_MEANS
    if not all_finite(quats):
        flags |= rk.BAD_QUATS
    if len(quats):
        qq = (quats * quats).sum(-1)
        if not bool(((qq > 1e-24) & (qq < math.inf)).all()):  # a NaN row fails too
            flags |= rk.ZERO_QUATS
    if not all_finite(scales) or (len(scales) and not bool((scales > 0).all())):
        flags |= rk.BAD_SCALES
    if not all_finite(opacities) or (len(opacities) and not bool(((opacities >= 0) & (opacities <= 1)).all())):
        flags |= rk.BAD_OPACITIES
    if not all_finite(colors):
        flags |= rk.BAD_COLORS
    return flags


def _validate(means, quats, scales, opacities, colors, background, camera, near, eps2d):
    """Raise ValueError on anything the kernels must never see; returns (N, C)."""
    if not isinstance(camera, Camera):
        raise ValueError(f"render: camera must be a core.geometry.camera.Camera, got {type(camera).__name__}")
    if int(camera.width) <= 0 or int(camera.height) <= 0:
        raise ValueError(f"render: image size must be positive, got {camera.width}x{camera.height}")
    if len(_shape(means)) != 2 or _shape(means)[1] != 3:
        raise ValueError(f"render: means must have shape [N, 3], got {list(_shape(means))}")
    n = _shape(means)[0]
    for name, x, tail in (("quats", quats, (4,)), ("scales", scales, (3,)), ("opacities", opacities, ())):
        if _shape(x) != (n,) + tail:
            raise ValueError(
                f"render: {name} must have shape {[n, *tail]} to match means [N={n}, 3], got {list(_shape(x))}"
            )
    if len(_shape(colors)) != 2 or _shape(colors)[0] != n or _shape(colors)[1] < 1:
        raise ValueError(f"render: colors must have shape [N={n}, C] with C >= 1, got {list(_shape(colors))}")
    n_ch = _shape(colors)[1]
    if background is not None and _shape(background) != (n_ch,):
        raise ValueError(
            f"render: background must have shape [{n_ch}] (one value per colour channel), "
            f"got {list(_shape(background))}"
        )
    flags = _value_flags(means, quats, scales, opacities, colors)
    for bit, message in _VALUE_ERRORS:
        if flags & bit:
            raise ValueError(message)
    if background is not None and not all_finite(background):
        raise ValueError("render: background contains NaN or inf")
    if not (near > 0 and np.isfinite(near)):
        raise ValueError(f"render: near must be a positive finite distance, got {near}")
    if not (eps2d >= 0 and np.isfinite(eps2d)):
        raise ValueError(f"render: eps2d must be >= 0, got {eps2d}")
    return n, n_ch


# ----------------------------------------------------------------------------- CPU pipeline


_NUMPY_FLOAT = {torch.float32: np.float32, torch.float64: np.float64}


def float64_array(x) -> np.ndarray:
    """x (a tensor on any device, or an array) as a C-contiguous float64 numpy copy."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(x, dtype=np.float64)


def shared_array(x) -> Optional[np.ndarray]:
    """x as a C-contiguous numpy array on its own memory where compiled kernels can read or write
    it as it is: a CPU tensor or a writeable array (numba types read-only arrays apart, another
    specialisation to compile), float32 or float64; else None. The rasteriser's and the face
    binding's kernels widen every load to float64, so a float32 array gives the bits its float64
    copy would, without the copy's memory traffic."""
    if isinstance(x, torch.Tensor):
        if x.device.type != "cpu":
            return None
        x = x.detach().numpy()
    elif not isinstance(x, np.ndarray) or not x.flags.writeable:
        return None
    return np.ascontiguousarray(x) if x.dtype in (np.float32, np.float64) else None


def _host_arrays(*xs):
    """shared_array of each of xs when all share one dtype, else None (mixed dtypes would
    compile a kernel per combination)."""
    out = [shared_array(x) for x in xs]
    if any(a is None for a in out) or len({a.dtype for a in out}) != 1:
        return None
    return out


def _kernel_arrays(*xs) -> list:
    """The Gaussians' arrays for the kernels: the callers' own memory where _host_arrays can
    share it, float64 copies otherwise."""
    arrays = _host_arrays(*xs)
    return arrays if arrays is not None else [float64_array(x) for x in xs]


def _grad_array(g, shape) -> np.ndarray:
    """An incoming gradient as a C-contiguous array of its own float dtype (zeros when None)."""
    if g is None:
        return np.zeros(shape, np.float32)
    a = g.detach().cpu().numpy()
    return np.ascontiguousarray(a if a.dtype in (np.float32, np.float64) else a.astype(np.float64))


def _camera_args(camera: Camera):
    return (
        np.ascontiguousarray(camera.R, np.float64),
        np.ascontiguousarray(camera.t, np.float64),
        float(camera.fx),
        float(camera.fy),
        float(camera.cx),
        float(camera.cy),
    )


def _tiles(camera: Camera):
    return -(-camera.width // rk.TILE), -(-camera.height // rk.TILE)


class _RecordBuffers:
    """Buffers for the forward's record of composited pairs (rk.raster_forward), which the
    backward replays. Sized from the calls so far in entries per image pixel, and reused: a
    fresh 100+ MB array costs its page faults on every call, more than the replay saves. A
    forward takes a pair of buffers and its backward gives them back (a forward whose backward
    never runs leaves them to the garbage collector). A forward that runs out of room is run
    again with twice the room. Starts at 24 entries per pixel and image (the paper-scale bench
    head takes ~30 at 802x550, the default head ~10 at 88x128)."""

    def __init__(self, per_pixel: float = 24.0):
        self.per_pixel = per_pixel
        self.free: list = []

    def take(self, pixels: int, n_img: int, n_chunks: int):
        size = n_chunks * (int(self.per_pixel * pixels * n_img / n_chunks) + 4096)
        for i, bufs in enumerate(self.free):
            if len(bufs[0]) >= size:
                del self.free[i]
                return bufs
        # see rk.raster_forward's record: 1 - alpha, pixel in the tile, images composited
        return np.empty(size, np.float32), np.empty(size, np.uint8), np.empty(size, np.uint16)

    def learn(self, used: np.ndarray, size: int, pixels: int, n_img: int) -> bool:
        """Whether the record was complete; sizes the next call either way."""
        if used.max() > size // len(used):
            self.per_pixel *= 2.0
            return False
        # Shrinking only slowly: a training step alternates large passes (every Gaussian) with
        # small ones (the coarse stand-ins, a cut inside the template level), and sizing each
        # from the last would run every large one twice.
        self.per_pixel = max(1.0, 1.25 * float(used.max()) * len(used) / (pixels * n_img), 0.95 * self.per_pixel)
        return True

    def give(self, bufs):
        self.free = ([bufs] + self.free)[:2]  # more than two forwards rarely wait for their backward


_record_buffers = _RecordBuffers()


class _Scratch:
    """One float64 array kept for raster_backward's per-pair sums (see its docstring), grown by a
    quarter more than asked when too small. Not thread-safe; neither are the record buffers."""

    def __init__(self):
        self.array = np.empty(0)

    def take(self, size: int) -> np.ndarray:
        if len(self.array) < size:
            self.array = np.empty(int(size * 1.25))
        return self.array


_scratch = _Scratch()


def _sort_key(depth, keep, behind):
    """The depths the sort reads: those of the ``behind`` Gaussians moved past every kept
    depth, so that they composite last and keep their order among themselves."""
    if behind is None:
        return depth
    key = depth.copy()
    key[behind] += (float(depth[keep].max()) if keep.any() else 0.0) + 1.0
    return key


def _cpu_forward(
    means,
    quats,
    scales,
    opacities,
    colors,
    background,
    camera,
    near,
    eps2d,
    with_depth=False,
    glevel=None,
    upto=None,
    record=False,
    pixel_weight=None,
    dtype=np.float64,
    with_contrib=True,
    behind=None,
    last_from=None,
):
    """Forward (float32 or float64 arrays, float64 arithmetic) of one image per entry of
    ``upto`` (image l: Gaussians with glevel <= upto[l], the last only those with glevel >=
    ``last_from`` too when given; default one image of all); returns
    images [L,H,W,C] and alphas [L,H,W] in ``dtype``, the last image's contrib, radii and the
    state the backward needs (``record``: with the composited pairs, so that the backward
    replays them). The contrib weighs each pixel by ``pixel_weight`` [H, W] when given.
    ``behind`` [N] bool or None: those Gaussians composite after all the others."""
    every = glevel is None  # one image of all the Gaussians
    if every:
        glevel, upto = np.zeros(len(means), np.int64), np.zeros(1, np.int64)
    Rc, tc, fx, fy, cx, cy = _camera_args(camera)
    W, H = camera.width, camera.height
    lim = rk.fov_limits(W, H, fx, fy, cx, cy)
    xy, conic, depth, rect, radii, cut = rk.project_forward(
        means, quats, scales, opacities, Rc, tc, fx, fy, cx, cy, lim, W, H, float(near), float(eps2d)
    )
    keep = radii != 0 if every else (radii != 0) & (glevel <= upto.max())
    order = rk.depth_order(_sort_key(depth, keep, behind), keep, rk.sort_parts(len(keep), numba.get_num_threads()))
    if with_depth:  # float64 like depth, and opacities with them (pack_splats takes one dtype)
        colors = np.concatenate([colors, depth[:, None]], axis=1, dtype=np.float64)
        opacities = np.asarray(opacities, np.float64)
        background = np.concatenate([background, [0.0]])
    n_ch = colors.shape[1]
    tiles_x, tiles_y = _tiles(camera)
    parts = rk.sort_parts(len(order), numba.get_num_threads())
    row_of, gaussian = rk.splat_rows(order, rect, tiles_x, tiles_y, parts)
    splats = rk.aligned_splats(len(order), n_ch)
    rk.pack_splats(gaussian, xy, conic, opacities, cut, colors, rect, glevel, splats)
    tile_start, ids = rk.bin_tiles(splats, row_of, tiles_x, tiles_y)
    n_chunks = numba.get_num_threads()
    image = np.empty((len(upto), H, W, n_ch), dtype)
    # Always an array (empty: no weights): an omitted argument is another signature, and numba
    # compiled the whole compositing kernel a second time for it on a first run.
    weight = np.zeros((0, 0)) if pixel_weight is None else np.ascontiguousarray(pixel_weight, np.float64)
    while True:
        bufs = (
            _record_buffers.take(W * H, len(upto), n_chunks)
            if record
            else (np.empty(0, np.float32), np.empty(0, np.uint8), np.empty(0, np.uint16))
        )
        image, t_final, last, contrib, (rec_start, rec_n, used) = rk.raster_forward(
            tile_start,
            ids,
            splats,
            gaussian,
            len(means),
            n_ch,
            background,
            W,
            H,
            tiles_x,
            upto,
            n_chunks,
            *bufs,
            weight,
            image=image,
            contrib=with_contrib,
            last_from=rk.LEVEL_NONE if last_from is None else int(last_from),
        )
        if not record or _record_buffers.learn(used, len(bufs[0]), W * H, len(upto)):
            break
    state = dict(
        splats=splats,
        gaussian=gaussian,
        radii=radii,
        tile_start=tile_start,
        ids=ids,
        t_final=t_final,
        last=last,
        n_ch=n_ch,
        background=background,
        lim=lim,
        upto=upto,
        rec=(*bufs, rec_start, rec_n) if record else None,
    )
    alpha = np.subtract(1.0, t_final, out=np.empty(t_final.shape, dtype), casting="same_kind")
    return image, alpha, contrib, radii, state


def _cpu_backward(
    state,
    means,
    quats,
    scales,
    camera,
    eps2d,
    grad_image,
    grad_alpha,
    with_depth,
    out_dtypes=(np.float64,) * 6,
):
    """Gradients of means, quats, scales, opacities, colours and the last image's screen
    positions, each in its entry of ``out_dtypes`` (the kernels round each float64 sum once into
    it), and of the background."""
    Rc, tc, fx, fy, _, _ = _camera_args(camera)
    tiles_x, _ = _tiles(camera)
    if state["rec"] is None:
        raise RuntimeError("rasteriser backward: the forward kept no record (a second backward through one render?)")
    slot_start = rk.backward_slots(state["tile_start"], state["last"])
    scratch = _scratch.take(rk.scratch_entries(slot_start, state["n_ch"]))
    grads, g_bg = rk.raster_backward(
        state["tile_start"],
        state["ids"],
        state["splats"],
        state["gaussian"],
        len(means),
        state["n_ch"],
        state["background"],
        state["t_final"],
        state["last"],
        grad_image,
        grad_alpha,
        camera.width,
        camera.height,
        tiles_x,
        *state["rec"],
        slot_start,
        scratch,
        upto=state["upto"],
    )
    _record_buffers.give(state["rec"][:3])  # back to the pool for the next forward
    state["rec"] = None
    n, n_col = len(means), state["n_ch"] - int(with_depth)
    g_uv, g_conic = np.empty((n, 2)), np.empty((n, 3))
    g_depth = np.empty(n if with_depth else 0)
    g_opac, g_colors = np.empty(n, out_dtypes[3]), np.empty((n, n_col), out_dtypes[4])
    g_uv_last = np.empty((n, 2), out_dtypes[5])  # the last image's own screen-space gradient
    rk.split_grads(grads, g_uv, g_conic, g_depth, g_opac, g_colors, g_uv_last)
    if with_depth:
        g_bg = g_bg[:-1]
    else:
        g_depth = np.zeros(n)
    g_means, g_quats, g_scales = (np.empty((n, k), dt) for k, dt in zip((3, 4, 3), out_dtypes))
    rk.project_backward(
        means, quats, scales, Rc, tc, fx, fy, state["lim"], float(eps2d), state["radii"], g_uv, g_conic, g_depth,
        g_means, g_quats, g_scales,
    )  # fmt: skip
    return g_means, g_quats, g_scales, g_opac, g_colors, g_bg, g_uv_last


def _will_backward(*tensors) -> bool:
    """Whether autograd will record the render (then the forward keeps its record for the
    backward; under no_grad, evaluation and previews skip that memory)."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        means,
        quats,
        scales,
        opacities,
        colors,
        background,
        means2d,
        camera,
        near,
        eps2d,
        with_depth,
        glevel,
        upto,
        record,
        with_contrib,
        behind,
        last_from,
    ):
        arrays = _kernel_arrays(means, quats, scales, opacities, colors)
        dtype, device = means.dtype, means.device
        image, alpha, contrib, radii, state = _cpu_forward(
            *arrays,
            float64_array(background),
            camera,
            near,
            eps2d,
            with_depth=with_depth,
            glevel=glevel,
            upto=upto,
            record=record,
            dtype=np.float32 if dtype == torch.float32 else np.float64,
            with_contrib=with_contrib,
            behind=behind,
            last_from=last_from,
        )
        ctx.camera, ctx.eps2d, ctx.with_depth = camera, eps2d, with_depth
        ctx.state = state
        # The backward reads these tensors' memory again (no copies): saved, so that torch
        # refuses a backward after an in-place change instead of differentiating other values.
        ctx.save_for_backward(means, quats, scales)
        ctx.kinds = [(x.dtype, x.device) for x in (means, quats, scales, opacities, colors, background, means2d)]
        out_image = torch.from_numpy(image).to(device=device, dtype=dtype)
        out_alpha = torch.from_numpy(alpha).to(device=device, dtype=dtype)
        out_contrib = torch.from_numpy(contrib).to(device=device, dtype=dtype)
        out_radii = torch.from_numpy(radii).to(device=device)
        ctx.mark_non_differentiable(out_contrib, out_radii)
        return out_image, out_alpha, out_contrib, out_radii

    @staticmethod
    def backward(ctx, grad_image, grad_alpha, _grad_contrib, _grad_radii):
        means, quats, scales = _kernel_arrays(*ctx.saved_tensors)
        H, W = ctx.camera.height, ctx.camera.width
        n_out = ctx.state["n_ch"]
        n_img = len(ctx.state["upto"])
        # The incoming gradients keep their dtype (the kernel reads float32 into float64 sums): a
        # float64 copy of every level's image gradient (~75 MB at 550x802, 7 levels) cost more
        # than the copy's arithmetic is worth, and adds no precision to float32 values.
        g_img = _grad_array(grad_image, (n_img, H, W, n_out))
        g_alpha = _grad_array(grad_alpha, (n_img, H, W))
        kinds = [ctx.kinds[i][0] for i in (0, 1, 2, 3, 4, 6)]  # all but the background's
        g_means, g_quats, g_scales, g_opac, g_colors, g_bg, g_uv = _cpu_backward(
            ctx.state,
            means,
            quats,
            scales,
            ctx.camera,
            ctx.eps2d,
            g_img,
            g_alpha,
            ctx.with_depth,
            out_dtypes=tuple(_NUMPY_FLOAT.get(k, np.float64) for k in kinds),
        )

        def out(x, i):
            if not ctx.needs_input_grad[i]:
                return None
            dtype, device = ctx.kinds[i]
            if dtype in _NUMPY_FLOAT:  # converted while made contiguous: one copy, not two
                x = np.ascontiguousarray(x, _NUMPY_FLOAT[dtype])
            return torch.from_numpy(np.ascontiguousarray(x)).to(device=device, dtype=dtype)

        return (
            out(g_means, 0),
            out(g_quats, 1),
            out(g_scales, 2),
            out(g_opac, 3),
            out(g_colors, 4),
            out(g_bg, 5),
            out(g_uv, 6),
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
        )


def render_numpy(
    means,
    quats,
    scales,
    opacities,
    colors,
    camera,
    background=None,
    *,
    near=0.01,
    eps2d=0.3,
    pixel_weight=None,
    compute_contrib=True,
    behind=None,
):
    """Forward only, numpy in and out: (image [H,W,C] float32, alpha [H,W] float32, contrib [N]).
    contrib[g] = sum over pixels of alpha*T of Gaussian g, times ``pixel_weight`` [H, W] per
    pixel when given; None with ``compute_contrib`` False (a faster forward). ``behind``: as in
    ``render``."""
    means, quats, scales, opacities, colors = (np.asarray(x) for x in (means, quats, scales, opacities, colors))
    background = None if background is None else np.asarray(background)
    _validate(means, quats, scales, opacities, colors, background, camera, near, eps2d)
    arrays = _kernel_arrays(means, quats, scales, opacities, colors)
    bg = float64_array(background) if background is not None else np.zeros(arrays[4].shape[1])
    if pixel_weight is not None:
        pixel_weight = np.ascontiguousarray(pixel_weight, np.float64)
        if pixel_weight.shape != (camera.height, camera.width) or not np.all(np.isfinite(pixel_weight)):
            raise ValueError(
                f"render_numpy: pixel_weight must be finite [{camera.height}, {camera.width}], "
                f"got {list(pixel_weight.shape)}"
            )
    image, alpha, contrib, _, _ = _cpu_forward(
        *arrays,
        bg,
        camera,
        near,
        eps2d,
        pixel_weight=pixel_weight,
        dtype=np.float32,
        with_contrib=compute_contrib,
        behind=_behind_mask(behind, len(means), "render_numpy"),
    )
    return image[0], alpha[0], contrib if compute_contrib else None


# ----------------------------------------------------------------------------- gsplat (CUDA)


def gsplat_available() -> bool:
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # any import failure (missing wheel, CUDA build, packaging) means "no gsplat"
        return False
    return True


def _render_gsplat(
    means,
    quats,
    scales,
    opacities,
    colors,
    background,
    camera,
    near,
    eps2d,
    return_depth,
    compute_contrib,
    grad_sink=None,
):
    """``grad_sink`` (leaf [M, 2], rows [N]): the screen-space gradient goes to those rows of
    that leaf (a part of a larger render, _render_backdrop) instead of a leaf of its own."""
    from gsplat import rasterization

    dev, dtype = means.device, means.dtype
    viewmats = torch.as_tensor(camera.viewmat(), dtype=torch.float32, device=dev)[None]
    Ks = torch.as_tensor(camera.K(), dtype=torch.float32, device=dev)[None]
    f32 = [x.float() for x in (means, quats, scales, opacities, colors)]
    common = dict(
        viewmats=viewmats,
        Ks=Ks,
        width=camera.width,
        height=camera.height,
        near_plane=near,
        eps2d=eps2d,
        packed=False,
        rasterize_mode="classic",
    )
    n_ch = colors.shape[1]
    bg = background.float()[None] if background is not None else None
    if return_depth:
        bg = torch.cat([bg, bg.new_zeros(1, 1)], dim=1) if bg is not None else None
    render_colors, render_alphas, meta = rasterization(
        *f32, backgrounds=bg, render_mode="RGB+ED" if return_depth else "RGB", **common
    )
    image = render_colors[0, ..., :n_ch].to(dtype)
    alpha = render_alphas[0, ..., 0].to(dtype)
    depth = render_colors[0, ..., n_ch].to(dtype) if return_depth else None
    n = means.shape[0]
    # gsplat's projected means are an internal, non-leaf tensor [1, N, 2]. The API promises a
    # leaf [N, 2] whose .grad is the screen-space gradient, so mirror the gradient into one.
    means2d = torch.zeros(n, 2, device=dev, dtype=dtype, requires_grad=True)
    m2d = meta["means2d"]
    if m2d.requires_grad:

        def _mirror(grad):
            g = grad.reshape(-1, n, 2)[0].detach().to(dtype)
            if grad_sink is not None:
                leaf, rows = grad_sink
                if leaf.grad is None:
                    leaf.grad = torch.zeros_like(leaf)
                leaf.grad[rows] += g
                return
            means2d.grad = g.clone() if means2d.grad is None else means2d.grad + g

        m2d.register_hook(_mirror)
    radii = (
        meta["radii"].reshape(n, -1).amax(-1).to(torch.int32)
        if meta["radii"].numel()
        else torch.zeros(n, dtype=torch.int32, device=dev)
    )
    contrib = None
    if compute_contrib:
        # sum_pixels alpha*T is the gradient of the summed image w.r.t. a constant per-Gaussian colour.
        probe = torch.zeros(n, 1, device=dev, dtype=torch.float32, requires_grad=True)
        with torch.enable_grad():
            img, _, _ = rasterization(*[x.detach() for x in f32[:4]], probe, **common)
            contrib = torch.autograd.grad(img.sum(), probe)[0][:, 0].to(dtype)
    return RenderOutput(image=image, alpha=alpha, means2d=means2d, contrib=contrib, radii=radii, depth=depth)


# ----------------------------------------------------------------------------- public API


def _behind_mask(behind, n: int, caller: str):
    """``behind`` as a contiguous bool array [n], or None when it selects none or all of them
    (then the plain depth order is the same)."""
    if behind is None:
        return None
    b = np.asarray(behind.detach().cpu().numpy() if isinstance(behind, torch.Tensor) else behind)
    if b.shape != (n,) or b.dtype != np.bool_:
        raise ValueError(f"{caller}: behind must be [N={n}] booleans, got {b.dtype} {list(b.shape)}")
    return np.ascontiguousarray(b) if b.any() and not b.all() else None


def _render_backdrop(
    means, quats, scales, opacities, colors, camera, background, behind, *, near, eps2d, return_depth, compute_contrib,
    backend,
) -> RenderOutput:  # fmt: skip
    """``render`` with the ``behind`` Gaussians composited after all the others, as two
    renders: the others over nothing (premultiplied colour C_f, alpha A_f), then the ``behind``
    ones over the background, seen through what the first leaves: C = C_f + (1 - A_f) C_b,
    A = A_f + (1 - A_f) A_b. The CPU path sorts them last in one pass instead (the same image,
    tests/test_render.py); gsplat orders by depth alone, so its path takes this one. (With
    ``backend`` "cpu", for that test, ``means2d`` gets no gradient.)"""
    dev = means.device
    n = means.shape[0]
    rows = [torch.as_tensor(np.flatnonzero(m), device=dev) for m in (~behind, behind)]
    means2d = torch.zeros(n, 2, device=dev, dtype=means.dtype, requires_grad=True)

    def part(sel, cols, bg, depth, probe=False):
        xs = tuple(x[sel].detach() if probe else x[sel] for x in (means, quats, scales, opacities)) + (cols,)
        if backend == "gsplat":
            return _render_gsplat(
                *xs, bg, camera, near, eps2d, depth, False, grad_sink=None if probe else (means2d, sel)
            )
        return render(*xs, camera, bg, near=near, eps2d=eps2d, return_depth=depth, backend="cpu", compute_contrib=False)

    front = part(rows[0], colors[rows[0]], None, return_depth)
    back = part(rows[1], colors[rows[1]], background, return_depth)
    through = 1.0 - front.alpha
    image = front.image + through[..., None] * back.image
    alpha = front.alpha + through * back.alpha
    depth = None
    if return_depth:
        acc = front.depth * front.alpha + through * back.depth * back.alpha
        depth = torch.where(alpha > 1e-10, acc / alpha.clamp_min(1e-10), torch.zeros_like(acc))
    contrib = None
    if compute_contrib:
        # sum over pixels of alpha*T: the gradient of the composite's sum w.r.t. a constant colour
        contrib = torch.zeros(n, device=dev, dtype=means.dtype)
        with torch.enable_grad():
            for sel, weight in ((rows[0], None), (rows[1], through.detach())):
                probe = torch.zeros(len(sel), 1, device=dev, dtype=means.dtype, requires_grad=True)
                img = part(sel, probe, None, False, probe=True).image[..., 0]
                total = img.sum() if weight is None else (img * weight).sum()
                contrib[sel] = torch.autograd.grad(total, probe)[0][:, 0].to(contrib.dtype)
    radii = torch.zeros(n, dtype=front.radii.dtype, device=dev)
    radii[rows[0]], radii[rows[1]] = front.radii, back.radii
    return RenderOutput(image=image, alpha=alpha, means2d=means2d, contrib=contrib, radii=radii, depth=depth)


def _cpu_inputs(means, colors, background, tensors):
    """The CPU path's background (zeros by default) and screen-space gradient leaf means2d."""
    if background is None:
        background = torch.zeros(colors.shape[1], dtype=means.dtype, device=means.device)
    # Only a graph that will be differentiated needs the screen-space gradient leaf.
    track = torch.is_grad_enabled() and any(x.requires_grad for x in tensors)
    return background, torch.zeros(means.shape[0], 2, dtype=means.dtype, device=means.device, requires_grad=track)


def render(
    means,
    quats,
    scales,
    opacities,
    colors,
    camera,
    background=None,
    *,
    near=0.01,
    eps2d=0.3,
    return_depth=False,
    backend="auto",
    compute_contrib=True,
    behind=None,
) -> RenderOutput:
    """Rasterise activated Gaussians seen by ``camera``.

    means [N,3], quats [N,4] wxyz (normalised here), scales [N,3] > 0 (std-devs, metres),
    opacities [N] in [0,1], colors [N,C], background [C] (default zeros); torch float32 or
    float64. Gradients reach every input that requires grad. ``backend``: "auto" (gsplat for
    CUDA tensors when it imports, else CPU), "cpu" or "gsplat". ``compute_contrib`` False
    leaves ``contrib`` None: on gsplat it costs one more forward+backward pass, on the CPU
    per-pair sums and their gather in the forward. ``behind`` [N] bool (default none): those
    Gaussians composite after all the others, in depth order among themselves: a backdrop, as
    retired coarse stand-ins are (core/avatar/forest.py, Forest.render_set).
    """
    if backend not in ("auto", "cpu", "gsplat"):
        raise ValueError(f"render: backend must be 'auto', 'cpu' or 'gsplat', got {backend!r}")
    tensors = (means, quats, scales, opacities, colors) + ((background,) if background is not None else ())
    if not all(isinstance(x, torch.Tensor) for x in tensors):
        raise ValueError("render: Gaussian parameters must be torch tensors (use render_numpy for numpy)")
    _validate(means, quats, scales, opacities, colors, background, camera, near, eps2d)
    behind = _behind_mask(behind, means.shape[0], "render")
    use_gsplat = backend == "gsplat" or (backend == "auto" and means.is_cuda and gsplat_available())
    if use_gsplat:
        if not (means.is_cuda and gsplat_available()):
            raise ValueError("render: backend='gsplat' needs CUDA tensors and an importable gsplat")
        if behind is not None:
            return _render_backdrop(
                means, quats, scales, opacities, colors, camera, background, behind, near=near, eps2d=eps2d,
                return_depth=return_depth, compute_contrib=compute_contrib, backend="gsplat",
            )  # fmt: skip
        return _render_gsplat(
            means, quats, scales, opacities, colors, background, camera, near, eps2d, return_depth, compute_contrib
        )

    background, means2d = _cpu_inputs(means, colors, background, tensors)
    image, alpha, contrib, radii = _RasterizeCPU.apply(
        means,
        quats,
        scales,
        opacities,
        colors,
        background,
        means2d,
        camera,
        float(near),
        float(eps2d),
        bool(return_depth),
        None,
        None,
        _will_backward(means, quats, scales, opacities, colors, background, means2d),
        bool(compute_contrib),
        behind,
        None,
    )
    image, alpha = image[0], alpha[0]
    contrib = contrib if compute_contrib else None
    depth = None
    if return_depth:
        n_ch = colors.shape[1]
        # Channel n_ch carries sum_i z_i alpha_i T_i; dividing by alpha gives the expected z.
        acc = image[..., n_ch]
        depth = torch.where(alpha > 1e-10, acc / alpha.clamp_min(1e-10), torch.zeros_like(acc))
        image = image[..., :n_ch]
    return RenderOutput(image=image, alpha=alpha, means2d=means2d, contrib=contrib, radii=radii, depth=depth)


def render_levels(
    means,
    quats,
    scales,
    opacities,
    colors,
    camera,
    background=None,
    *,
    level,
    upto,
    near=0.01,
    eps2d=0.3,
    backend="auto",
    compute_contrib=True,
    behind=None,
    last_from=None,
) -> list:
    """Several images of nested subsets in one pass: image k shows the Gaussians whose
    ``level`` [N] (ints, e.g. the forest level of each face) is <= ``upto[k]``, and the last
    image only those whose level is >= ``last_from`` too when given (the whole avatar without
    its coarse stand-ins beside prefixes with them), as ``render`` of that subset would (same
    order, same pixels; values equal up to float64 rounding: a row's exp recurrence starts
    where any of the images still composites). On the CPU the subsets
    share projection, depth sort, tile lists and each pair's alpha; only compositing runs per
    image, in one pass (at most rk.MAX_IMAGES images).

    Returns one RenderOutput per entry of ``upto``. They share ``means2d`` (all N Gaussians),
    whose .grad after backward is the screen-space gradient of the image with the largest
    ``upto`` alone (the one densification reads), and ``radii``; ``contrib`` is that image's
    (None with ``compute_contrib`` False, as in render) and None on the others.
    ``behind``: as in render.
    """
    upto = [int(u) for u in upto]
    if not upto:
        raise ValueError("render_levels: upto must name at least one level")
    if sorted(upto) != upto or len(set(upto)) != len(upto):
        raise ValueError(f"render_levels: upto must be strictly increasing, got {upto}")
    if len(upto) > rk.MAX_IMAGES:
        raise ValueError(f"render_levels: at most {rk.MAX_IMAGES} images in one pass, got {len(upto)}")
    lv = np.asarray(level.detach().cpu().numpy() if isinstance(level, torch.Tensor) else level)
    if lv.shape != (means.shape[0],) or not np.issubdtype(lv.dtype, np.integer):
        raise ValueError(f"render_levels: level must be [N={means.shape[0]}] integers, got {lv.dtype} {list(lv.shape)}")
    tensors = (means, quats, scales, opacities, colors) + ((background,) if background is not None else ())
    if not all(isinstance(x, torch.Tensor) for x in tensors):
        raise ValueError("render_levels: Gaussian parameters must be torch tensors")
    if last_from is not None and not (isinstance(last_from, (int, np.integer)) and last_from <= upto[-1]):
        raise ValueError(f"render_levels: last_from must be an integer <= upto[-1]={upto[-1]}, got {last_from!r}")
    behind = _behind_mask(behind, means.shape[0], "render_levels")
    if backend == "gsplat" or (backend == "auto" and means.is_cuda and gsplat_available()):
        outs = []
        for u in upto:  # gsplat renders each subset on its own
            shown = lv <= u
            if last_from is not None and u == upto[-1]:
                shown &= lv >= last_from
            sel = np.flatnonzero(shown)
            ids = torch.as_tensor(sel, device=means.device)
            outs.append(
                render(
                    means[ids],
                    quats[ids],
                    scales[ids],
                    opacities[ids],
                    colors[ids],
                    camera,
                    background,
                    near=near,
                    eps2d=eps2d,
                    backend=backend,
                    compute_contrib=compute_contrib and u == upto[-1],
                    behind=None if behind is None else behind[sel],
                )
            )
        return outs
    _validate(means, quats, scales, opacities, colors, background, camera, near, eps2d)
    background, means2d = _cpu_inputs(means, colors, background, tensors)
    images, alphas, contrib, radii = _RasterizeCPU.apply(
        means,
        quats,
        scales,
        opacities,
        colors,
        background,
        means2d,
        camera,
        float(near),
        float(eps2d),
        False,
        np.ascontiguousarray(lv, np.int64),
        np.asarray(upto, np.int64),
        _will_backward(means, quats, scales, opacities, colors, background, means2d),
        bool(compute_contrib),
        behind,
        last_from,
    )
    last = len(upto) - 1
    contrib = contrib if compute_contrib else None
    # unbind, not images[k]: the backward of k selects is k zero-filled copies of the whole stack
    # (7 levels at 550x802: ~37 MB each) summed; unbind's backward stacks the k gradients once.
    images, alphas = images.unbind(0), alphas.unbind(0)
    return [
        RenderOutput(
            image=images[k], alpha=alphas[k], means2d=means2d, contrib=contrib if k == last else None, radii=radii
        )
        for k in range(len(upto))
    ]
