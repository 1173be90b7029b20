"""Numba CPU kernels of the tile rasteriser: projection, tile binning, compositing, backward.

Every kernel computes in float64 (the caller converts once; only the forward's record of
composited pairs is float32, see raster_forward): the per-pixel work is
scalar code that does not vectorise, so float64 costs little and keeps the hand-written
backward close to a float64 reference. Rules shared with gsplat and the dense test
reference (core/render/reference.py), which must stay in step with this file:

- EWA splatting: cov2d = J Rc R S S R^T Rc^T J^T + eps2d*I, with gsplat's clamp of x/z, y/z to
  1.3x the field of view inside the Jacobian (the mean itself is not clamped). No opacity
  compensation for the dilation.
- Culled (radius 0): camera z < near, opacity < 1/255, non-positive det, or no pixel centre
  where alpha can reach 1/255.
- Pixel (i, j) is sampled at its centre (i + 0.5, j + 0.5). alpha = min(0.99, o*exp(power))
  (INRIA's 3DGS; gsplat clamps at 0.999); alpha < 1/255 is skipped; a pixel stops *before* the
  Gaussian that would take its transmittance below 1e-4 (as 3DGS/gsplat do).
- Per tile, Gaussians are composited in ascending camera z (stable: ties keep index order).

Pixel boxes are exact, not 3-sigma guesses: alpha >= 1/255 needs power >= -ln(255 o), i.e.
the Mahalanobis radius r <= sqrt(2 ln(255 o)), whose ellipse spans r*sqrt(cov2d_xx) in x.
So binning never drops a pixel that the dense reference would composite.

Parallel loops never share an accumulator: projection runs over blocks of Gaussians, the
rasteriser over tiles, and each (tile, Gaussian) pair writes its own slot of a per-intersection
buffer that a pass sums afterwards in pair order (in parallel over ranges of Gaussians). No
atomics, deterministic sums, and no thread ids
(get_thread_id would stop numba from caching the kernels). Tiles are split statically between
threads: numba's dynamic chunking (parallel_chunksize) measured several times slower here; the
tiles are interleaved first (_spread_tiles) so that each static share sees all of the image.

Work per tile is trimmed twice: a tilted Gaussian visits only the chord of its ellipse on
each row (not its bounding box), cut to the pixels still compositing (per-row bit masks; rows
whose pixels have all stopped are skipped). An ellipse close to axis-aligned (cb^2 <=
CHORD_RHO2 ca cc: its box is at most 1.41 chords wide) walks its box row instead when it is
the last image's alone: the few pixels more cost less than the square root and the branches of
a chord per row (docs/BENCHMARKS.md, "Rasteriser kernels"); the nested-image walk keeps the
chords, whose skipped pixels each cost a pass over the images. The backward walks nothing: the
forward records every composited (Gaussian, pixel) pair with its 1 - alpha, and the backward
replays those pairs back to front (raster_forward's record, raster_backward).

The tile kernels read the Gaussians as packed rows (pack_splats: two cache lines per Gaussian
instead of one line in each of seven arrays), grouped by screen tile so that neighbouring
tiles share runs of rows, and ask for the rows a few pairs ahead before they need them
(_prefetch): without that, the first read of each pair's Gaussian was the forward's and the
backward's largest single cost.

The nested images of one pass (the levels of a forest: image l shows the Gaussians with
glevel <= upto[l]) are composited together, not one after another: a Gaussian walks its
chords and computes its alphas once per tile, then composites them into every image it
belongs to where the pixel still runs, and the record lists each pair once with the images
that took it. With every level supervised this about halves the forward and cuts a third off
the backward against walking and replaying each image on its own (docs/BENCHMARKS.md,
"Rasteriser kernels, every level"). The Gaussians that only the last image shows (the finer
levels, most of an avatar; with a single image every Gaussian) take a walk and a replay of
their own inside the same tile kernels, on that image's state alone: the per-image bits and
loops would cost them about a quarter more.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros
from numba.extending import intrinsic, overload

TILE = 16
TILE_SHIFT = 4  # the replay splits record pixels by shifts (a // in numba is Python's floor division,
# a few instructions more per record entry)
assert TILE == 1 << TILE_SHIFT
BLOCK = 1024  # Gaussians per parallel work item in the projection kernels
BIN_CHUNKS = 16  # slices of the depth order binned in parallel
SPREAD = 4  # tile rows interleaved between the threads' static shares (see _spread_tiles)
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
# Single-image walks take a row's chord only for ellipses tilted more than this (cb^2 / (ca cc), the
# squared correlation); the rest walk the pixel box's row (see the module docstring).
CHORD_RHO2 = 0.5
# Box-walked splats with at least this many rows in a tile follow exp(power) down the rows by
# products (5 exps a tile instead of 2 a row; _forward_tile).
RECUR_ROWS = 4
# The glue passes (input check, depth sort, splat-row grouping) run in parallel only from this
# many items: each parallel step wakes the threads, which costs more than it saves below about
# this size (measured at the cpu preset's and the bench head's sizes).
PARALLEL_MIN = 65536
LEVEL_NONE = -(1 << 62)  # raster_forward's last_from when the last image leaves no level out
MAX_IMAGES = 16  # images of one raster_forward: the record keeps each pair's images as uint16 bits
# Only explicit prange loops run in parallel: numba would otherwise turn every np.zeros and
# array expression into its own parallel region, and each launch is costly on a busy machine.
_PARALLEL = dict(
    prange=True,
    numpy=False,
    reduction=False,
    setitem=False,
    stencil=False,
    fusion=False,
    comprehension=False,
    inplace_binop=False,
)
PREFETCH = 4  # (tile, Gaussian) pairs ahead whose splat rows a tile kernel asks the cache for
PREFETCH_PACK = 16  # Gaussians ahead whose rows pack_splats asks the cache for
REPLAY_CHUNKS = 64  # raster_backward's parallel work items (runs of tiles sharing one allocation of tile state)
GATHER_PARTS = 4  # ranges of splat rows whose per-pair sums are gathered in parallel
# Slack on the pixel box so that rounding can never drop a pixel at the exact boundary.
_BOX_SLACK = 1.0 + 1e-6

# Columns of the packed splat rows (pack_splats; rows grouped by screen tile, see splat_rows):
# what the tile kernels read of one visible Gaussian. The first 64-byte line holds what a chord
# walk needs, the second the pixel box, level and colours, so that a (tile, Gaussian) pair
# touches two adjacent cache lines instead of one line in each of seven per-Gaussian arrays.
S_U, S_V, S_CA, S_CB, S_CC, S_OPAC, S_DCONIC, S_ECUT = 0, 1, 2, 3, 4, 5, 6, 7
S_X0, S_X1, S_Y0, S_Y1, S_LEVEL, S_COLOR = 8, 9, 10, 11, 12, 13


def splat_width(n_ch: int) -> int:
    """Row width of pack_splats' array for n_ch colour channels: whole 64-byte lines."""
    return -(-(S_COLOR + n_ch) // 8) * 8


# Gradient record per Gaussian written by raster_backward: d/du, d/dv, d/dconic (a, b, c),
# d/dopacity, then d/dcolor[0..C).
G_U, G_V, G_CA, G_CB, G_CC, G_OPAC, G_COLOR = 0, 1, 2, 3, 4, 5, 6
# raster_backward's per-pair geometry buffer: G_U..G_OPAC, then d/du, d/dv of the last image.
_GEO_U_LAST = G_COLOR
_GEO_WIDTH = G_COLOR + 2


def fov_limits(width, height, fx, fy, cx, cy):
    """gsplat's Jacobian clamp: x/z, y/z kept within the frustum widened by 30 % of tan(fov/2)."""
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    return np.array(
        [
            cx / fx + 0.3 * tan_x,  # x/z >= -this
            (width - cx) / fx + 0.3 * tan_x,  # x/z <= this
            cy / fy + 0.3 * tan_y,
            (height - cy) / fy + 0.3 * tan_y,
        ]
    )


@intrinsic
def _prefetch(typingctx, arr, index):
    """Ask the CPU to bring the cache line of arr[index] (a C array, an index tuple as long as
    its dimensions, no bounds check) into its caches; the code goes on without waiting.

    numba has no prefetch of its own. The tile kernels need it: a tile takes its Gaussians in
    depth order, which jumps between the rows of the tiles around it, and each pair's first
    read of its row waited for memory (with the per-Gaussian arrays of before, a fifth of the
    forward's and a sixth of the backward's samples in a perf profile of the bench head);
    the row of the pair a few places ahead is known long before it is read."""
    if not (
        isinstance(arr, types.Array)
        and isinstance(index, types.UniTuple)
        and index.count == arr.ndim
        and isinstance(index.dtype, types.Integer)
    ):
        return None

    def codegen(context, builder, sig, args):
        aryty, idxty = sig.args
        ary = context.make_array(aryty)(context, builder, args[0])
        idx = [context.cast(builder, i, idxty.dtype, types.intp) for i in cgutils.unpack_tuple(builder, args[1])]
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, idx, wraparound=False)
        i8p = ir.PointerType()  # opaque pointer (LLVM >= 15)
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])  # read, keep, data
        return context.get_dummy_value()

    return types.void(arr, index), codegen


def uncached(*kernels) -> bool:
    """Whether any of these compiled kernels is missing from numba's cache (none compiled for
    this source and numba version yet), so that its first call compiles it. Asking compiles
    nothing. False where numba's cache cannot be inspected (its internals changed)."""
    try:
        return any(not k._cache._cache_file._load_index() for k in kernels)  # an empty index: compiles
    except Exception:
        return False


@njit(cache=True)
def _prefetch_splat(splats, ids, k, first, end):
    """Prefetch the first two lines of the splat row of pair k (all of it with up to three
    colours), when k lies in the tile's pairs [first, end)."""
    if first <= k < end:
        s = np.int64(ids[k])
        _prefetch(splats, (s, 0))
        _prefetch(splats, (s, 8))


# The per-Gaussian helpers of the projection kernels take arrays, and LLVM leaves such calls in
# place; numba's own inlining lets their 3x3 scratch live in registers (projection forward and
# backward about twice as fast, bit for bit the same, in an A/B run on the bench head).
@njit(cache=True, inline="always")
def _camera_factor(q, s, Rc, R, Mc):
    """Fill R = R(q/|q|) and Mc = Rc R diag(s) (so the camera-space covariance is Mc Mc^T).

    Returns |q| and the normalised quaternion, which the backward needs. q and s may be float32
    (the rasteriser reads the caller's arrays): every load is widened, so the arithmetic is the
    float64 a float64 copy of them would get.
    """
    q0 = np.float64(q[0])
    q1 = np.float64(q[1])
    q2 = np.float64(q[2])
    q3 = np.float64(q[3])
    qn = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    # One division and four products, not four divisions: a division is the slowest operation
    # here (within an ulp of q/|q|).
    inv = 1.0 / qn
    w = q0 * inv
    x = q1 * inv
    y = q2 * inv
    z = q3 * inv
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)
    for i in range(3):
        for j in range(3):
            Mc[i, j] = (Rc[i, 0] * R[0, j] + Rc[i, 1] * R[1, j] + Rc[i, 2] * R[2, j]) * np.float64(s[j])
    return qn, w, x, y, z


@njit(cache=True)
def _jacobian(x, y, z, fx, fy, lim):
    """Non-zero entries of the 2x3 projection Jacobian, and whether x/z, y/z were left unclamped."""
    rz = 1.0 / z
    rx = x * rz
    ry = y * rz
    kx = min(lim[1], max(-lim[0], rx))
    ky = min(lim[3], max(-lim[2], ry))
    return fx * rz, -fx * kx * rz, fy * rz, -fy * ky * rz, kx, ky, kx == rx, ky == ry


@njit(cache=True, inline="always")
def _project_one(
    g,
    means,
    quats,
    scales,
    opacities,
    Rc,
    tc,
    fx,
    fy,
    cx,
    cy,
    lim,
    width,
    height,
    near,
    eps2d,
    R,
    Mc,
    xy,
    conic,
    depth,
    rect,
    radii,
    cut,
):
    """One Gaussian of project_forward (R, Mc: scratch); False where it is culled (then only
    its depth is written)."""
    mx, my, mz = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
    px = Rc[0, 0] * mx + Rc[0, 1] * my + Rc[0, 2] * mz + tc[0]
    py = Rc[1, 0] * mx + Rc[1, 1] * my + Rc[1, 2] * mz + tc[1]
    pz = Rc[2, 0] * mx + Rc[2, 1] * my + Rc[2, 2] * mz + tc[2]
    depth[g] = pz
    o = np.float64(opacities[g])
    if not (pz >= near) or not (o >= ALPHA_MIN):
        return False
    _camera_factor(quats[g], scales[g], Rc, R, Mc)
    j00, j02, j11, j12, _, _, _, _ = _jacobian(px, py, pz, fx, fy, lim)
    a = eps2d
    b = 0.0
    c = eps2d
    for k in range(3):
        r0 = j00 * Mc[0, k] + j02 * Mc[2, k]
        r1 = j11 * Mc[1, k] + j12 * Mc[2, k]
        a += r0 * r0
        b += r0 * r1
        c += r1 * r1
    det = a * c - b * b
    if not (det > 0.0) or not math.isfinite(det):
        return False
    rz = 1.0 / pz
    u = fx * px * rz + cx
    v = fy * py * rz + cy
    level = math.log(255.0 * o)
    reach = math.sqrt(2.0 * level) * _BOX_SLACK
    ex = reach * math.sqrt(a)
    ey = reach * math.sqrt(c)
    # Pixel centres i + 0.5 inside [u - ex, u + ex]; clamp before int() so huge boxes are safe.
    lo_x = max(u - ex - 0.5, -1.0)
    hi_x = min(u + ex - 0.5, float(width))
    lo_y = max(v - ey - 0.5, -1.0)
    hi_y = min(v + ey - 0.5, float(height))
    i0 = max(0, int(math.ceil(lo_x)))
    i1 = min(width - 1, int(math.floor(hi_x)))
    j0 = max(0, int(math.ceil(lo_y)))
    j1 = min(height - 1, int(math.floor(hi_y)))
    if i0 > i1 or j0 > j1:
        return False
    xy[g, 0] = u
    xy[g, 1] = v
    inv_det = 1.0 / det
    conic[g, 0] = c * inv_det
    conic[g, 1] = -b * inv_det
    conic[g, 2] = a * inv_det
    rect[g, 0] = i0
    rect[g, 1] = j0
    rect[g, 2] = i1
    rect[g, 3] = j1
    radii[g] = int(math.ceil(min(max(ex, ey), 1e9)))
    cut[g] = -level
    return True


# check_gaussians' bits: what render refuses in the Gaussians' values.
BAD_MEANS, BAD_QUATS, ZERO_QUATS, BAD_SCALES, BAD_OPACITIES, BAD_COLORS = 1, 2, 4, 8, 16, 32


@njit(parallel=_PARALLEL, cache=True)
def check_gaussians(means, quats, scales, opacities, colors):
    """One pass over the render inputs: the bits of the tests that fail (non-finite means, quats,
    scales or colours; a quaternion whose squared norm, in float64, is <= 1e-24; scales <= 0;
    opacities outside [0, 1], NaN included). From PARALLEL_MIN Gaussians on, blocks in
    parallel, their bits or-ed."""
    n = means.shape[0]
    if n < PARALLEL_MIN:
        return _check_block(means, quats, scales, opacities, colors, 0, n)
    nb = (n + BLOCK - 1) // BLOCK
    block_flags = np.zeros(nb, np.int64)
    for blk in prange(nb):
        block_flags[blk] = _check_block(means, quats, scales, opacities, colors, blk * BLOCK, min(n, (blk + 1) * BLOCK))
    flags = 0
    for blk in range(nb):
        flags |= block_flags[blk]
    return flags


@njit(cache=True)
def _check_block(means, quats, scales, opacities, colors, lo, hi):
    """check_gaussians' bits of Gaussians lo..hi-1."""
    flags = 0
    for g in range(lo, hi):
        for k in range(3):
            if not math.isfinite(means[g, k]):
                flags |= BAD_MEANS
            if not scales[g, k] > 0.0 or not math.isfinite(scales[g, k]):
                flags |= BAD_SCALES
        qq = 0.0
        for k in range(4):
            q = np.float64(quats[g, k])
            if not math.isfinite(q):
                flags |= BAD_QUATS
            qq += q * q
        if not (qq > 1e-24 and qq < math.inf):  # |q|^2 overflowing: q / |q| would be 0, the identity
            flags |= ZERO_QUATS
        if not (opacities[g] >= 0.0 and opacities[g] <= 1.0):
            flags |= BAD_OPACITIES
        for k in range(colors.shape[1]):
            if not math.isfinite(colors[g, k]):
                flags |= BAD_COLORS
    return flags


@njit(parallel=_PARALLEL, cache=True)
def project_forward(means, quats, scales, opacities, Rc, tc, fx, fy, cx, cy, lim, width, height, near, eps2d):
    """Per Gaussian: 2D mean, conic (inverse cov2d as a, b, c), camera z, pixel box, radius.

    rect[g] = (i0, j0, i1, j1), the inclusive range of pixel columns/rows that can receive
    alpha >= 1/255, already clipped to the image; radii[g] = 0 marks a culled Gaussian;
    cut[g] = -ln(255 o), the exponent below which alpha < 1/255.
    """
    n = means.shape[0]
    # Uninitialised, each row written once below (zeros for a culled Gaussian): zero-filled
    # arrays were ~13 MB of serial memset in front of the parallel loop at 170k Gaussians.
    xy = np.empty((n, 2))
    conic = np.empty((n, 3))
    depth = np.empty(n)
    rect = np.empty((n, 4), np.int32)
    radii = np.empty(n, np.int32)
    cut = np.empty(n)
    for blk in prange((n + BLOCK - 1) // BLOCK):
        R = np.empty((3, 3))
        Mc = np.empty((3, 3))
        for g in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            if not _project_one(
                g,
                means,
                quats,
                scales,
                opacities,
                Rc,
                tc,
                fx,
                fy,
                cx,
                cy,
                lim,
                width,
                height,
                near,
                eps2d,
                R,
                Mc,
                xy,
                conic,
                depth,
                rect,
                radii,
                cut,
            ):
                xy[g, 0] = xy[g, 1] = 0.0
                conic[g, 0] = conic[g, 1] = conic[g, 2] = 0.0
                rect[g, 0] = rect[g, 1] = rect[g, 2] = rect[g, 3] = 0
                radii[g] = 0
                cut[g] = 0.0
    return xy, conic, depth, rect, radii, cut


@njit(cache=True)
def _count_kept(keep, lo, hi):
    c = 0
    for g in range(lo, hi):
        if keep[g]:
            c += 1
    return c


@njit(cache=True)
def _gather_kept(keep, bits, lo, hi, at, order, key):
    """The kept indices of lo..hi-1 and their keys, from position ``at`` on."""
    for g in range(lo, hi):
        if keep[g]:
            order[at] = g
            key[at] = bits[g]
            at += 1


@njit(cache=True)
def _count_digits(key, lo, hi, counts):
    """counts[p, d]: how many of key[lo:hi] have digit d at position p (11 bits each)."""
    for q in range(lo, hi):
        k = key[q]
        for p in range(counts.shape[0]):
            counts[p, (k >> np.uint64(11 * p)) & np.uint64(2047)] += 1


@njit(cache=True)
def _pass_counts(key, lo, hi, shift, counts):
    """counts[d] = how many of key[lo:hi] have (key >> shift) & 2047 == d."""
    counts[:] = 0
    for q in range(lo, hi):
        counts[(key[q] >> shift) & np.uint64(2047)] += 1


@njit(cache=True)
def _scatter_digits(key, order, lo, hi, shift, cursor, out_order, out_key):
    """One counting-sort pass over key[lo:hi]: each key (and its index) to its digit's cursor."""
    for q in range(lo, hi):
        k = key[q]
        d = (k >> shift) & np.uint64(2047)
        r = cursor[d]
        cursor[d] = r + 1
        out_order[r] = order[q]
        out_key[r] = k


@njit(parallel=_PARALLEL, cache=True)
def depth_order(depth, keep, parts=1):
    """Indices g with keep[g], ascending in depth[g], ties in index order: the same as
    ``np.flatnonzero(keep)[np.argsort(depth[keep], kind="stable")]``, for depths > 0 (a kept
    Gaussian lies beyond the near plane). LSD radix sort on the float64 bits, which order
    positive floats as their values, 11 bits a pass; passes where every key has the same
    digit are skipped (depths share their sign and most exponent bits). The keys travel with
    the indices, so each pass reads them in sequence.

    With ``parts`` > 1 each step runs on that many contiguous parts at once: every part counts
    its digits and scatters its keys after the parts before it within each digit, which keeps
    the sort stable, so the result is the same for any number of parts. Each parallel step is
    a wake-up of the threads, which costs more than it saves on small inputs (callers pass 1
    there: sort_parts); with one part nothing runs in parallel."""
    n = keep.shape[0]
    parts = max(1, min(parts, n))
    span = (n + parts - 1) // parts
    kept = np.zeros(parts, np.int64)
    if parts > 1:
        for c in prange(parts):
            kept[c] = _count_kept(keep, c * span, min(n, (c + 1) * span))
    else:
        kept[0] = _count_kept(keep, 0, n)
    first = np.empty(parts, np.int64)
    m = 0
    for c in range(parts):
        first[c] = m
        m += kept[c]
    order = np.empty(m, np.int64)
    key = np.empty(m, np.uint64)
    bits = depth.view(np.uint64)
    if parts > 1:
        for c in prange(parts):
            _gather_kept(keep, bits, c * span, min(n, (c + 1) * span), first[c], order, key)
    else:
        _gather_kept(keep, bits, 0, n, 0, order, key)
    if m < 2:
        return order
    parts = max(1, min(parts, m))
    span = (m + parts - 1) // parts
    # Every part's digits at every position in one read: they decide which passes sort anything
    # (a position where one digit holds every key is skipped), and with one part they are the
    # counts of every pass (the order inside the part does not change what it holds).
    counts = np.zeros((parts, 6, 2048), np.int64)
    if parts > 1:
        for c in prange(parts):
            _count_digits(key, c * span, min(m, (c + 1) * span), counts[c])
    else:
        _count_digits(key, 0, m, counts[0])
    varies = np.zeros(6, np.bool_)
    first_pass = 6
    for p in range(5, -1, -1):
        for d in range(2048):
            x = 0
            for c in range(parts):
                x += counts[c, p, d]
            if x > 0:
                varies[p] = x < m
                break
        if varies[p]:
            first_pass = p
    spare = np.empty(m, np.int64)
    spare_key = np.empty(m, np.uint64)
    for p in range(6):
        if not varies[p]:
            continue
        shift = np.uint64(11 * p)
        if parts > 1 and p > first_pass:  # the keys moved between parts in the passes before
            for c in prange(parts):
                _pass_counts(key, c * span, min(m, (c + 1) * span), shift, counts[c, p])
        total = 0
        for d in range(2048):
            for c in range(parts):
                x = counts[c, p, d]
                counts[c, p, d] = total
                total += x
        if parts > 1:
            for c in prange(parts):
                _scatter_digits(key, order, c * span, min(m, (c + 1) * span), shift, counts[c, p], spare, spare_key)
        else:
            _scatter_digits(key, order, 0, m, shift, counts[0, p], spare, spare_key)
        order, spare = spare, order
        key, spare_key = spare_key, key
    return order


def sort_parts(m: int, threads: int) -> int:
    """How many parts depth_order and splat_rows should sort m keys in: the thread count from
    PARALLEL_MIN keys on, else 1."""
    return threads if m >= PARALLEL_MIN else 1


@njit(cache=True)
def _tile_keys(order, rect, tiles_x, tiles_y, lo, hi, key, counts):
    """The centre tile of each Gaussian of ranks lo..hi-1 (key) and how many fall in each tile."""
    for q in range(lo, hi):
        g = order[q]
        tx = min((rect[g, 0] + rect[g, 2]) // 2 // TILE, tiles_x - 1)
        ty = min((rect[g, 1] + rect[g, 3]) // 2 // TILE, tiles_y - 1)
        key[q] = ty * tiles_x + tx
        counts[key[q]] += 1


@njit(cache=True)
def _place_rows(order, key, lo, hi, cursor, row_of, gaussian):
    for q in range(lo, hi):
        r = cursor[key[q]]
        cursor[key[q]] = r + 1
        row_of[q] = r
        gaussian[r] = order[q]


@njit(parallel=_PARALLEL, cache=True)
def splat_rows(order, rect, tiles_x, tiles_y, parts=1):
    """Where pack_splats puts each visible Gaussian: grouped by the tile that holds the centre
    of its pixel box, front to back within a group. Returns row_of [m] (the row of the Gaussian
    of depth rank q, order[q]) and gaussian [m] (the Gaussian of each row).

    A tile's Gaussians are spread over the whole depth order, so rows in depth order would
    put every pair of a tile in a different part of memory; grouped by screen position, a
    tile and its neighbours read a few contiguous runs of rows instead. A stable counting sort,
    on ``parts`` contiguous slices of the depth order at once (as depth_order; one: serial):
    the same rows for any number of parts."""
    m = order.shape[0]
    n_tiles = tiles_x * tiles_y
    parts = max(1, min(parts, m))
    span = (m + parts - 1) // parts
    counts = np.zeros((parts, n_tiles), np.int64)
    key = np.empty(m, np.int64)
    if parts > 1:
        for c in prange(parts):
            _tile_keys(order, rect, tiles_x, tiles_y, c * span, min(m, (c + 1) * span), key, counts[c])
    else:
        _tile_keys(order, rect, tiles_x, tiles_y, 0, m, key, counts[0])
    total = 0
    for t in range(n_tiles):
        for c in range(parts):
            x = counts[c, t]
            counts[c, t] = total
            total += x
    row_of = np.empty(m, np.int64)
    gaussian = np.empty(m, np.int64)
    if parts > 1:
        for c in prange(parts):
            _place_rows(order, key, c * span, min(m, (c + 1) * span), counts[c], row_of, gaussian)
    else:
        _place_rows(order, key, 0, m, counts[0], row_of, gaussian)
    return row_of, gaussian


@njit(parallel=_PARALLEL, cache=True)
def pack_splats(order, xy, conic, opacities, cut, colors, rect, glevel, out):
    """Fill ``out`` [len(order), >= splat_width(C)] (rows S_*) with the visible Gaussians: row
    k is Gaussian order[k] (splat_rows' ``gaussian``). The tile kernels read these rows instead
    of the per-Gaussian arrays: each Gaussian is then two adjacent cache lines, and the
    Gaussians of neighbouring tiles lie near each other (docs/BENCHMARKS.md, "Rasteriser
    kernels"). ``out`` comes from the caller, 64-byte aligned (aligned_splats), so that a row
    starts a line."""
    m = order.shape[0]
    n_ch = colors.shape[1]
    for blk in prange((m + BLOCK - 1) // BLOCK):
        end = min(m, (blk + 1) * BLOCK)
        for k in range(blk * BLOCK, end):
            if k + PREFETCH_PACK < end:  # the rows of a Gaussian further on: order is random access
                h = order[k + PREFETCH_PACK]
                _prefetch(xy, (h, 0))
                _prefetch(conic, (h, 0))
                _prefetch(opacities, (h,))
                _prefetch(cut, (h,))
                _prefetch(colors, (h, 0))
                _prefetch(rect, (h, 0))
                _prefetch(glevel, (h,))
            g = order[k]
            ca = conic[g, 0]
            cb = conic[g, 1]
            cc = conic[g, 2]
            out[k, S_U] = xy[g, 0]
            out[k, S_V] = xy[g, 1]
            out[k, S_CA] = ca
            out[k, S_CB] = cb
            out[k, S_CC] = cc
            out[k, S_OPAC] = opacities[g]
            out[k, S_DCONIC] = cb * cb - ca * cc
            out[k, S_ECUT] = -2.0 * ca * cut[g]
            out[k, S_X0] = rect[g, 0]
            out[k, S_X1] = rect[g, 2]
            out[k, S_Y0] = rect[g, 1]
            out[k, S_Y1] = rect[g, 3]
            out[k, S_LEVEL] = glevel[g]
            for ch in range(n_ch):
                out[k, S_COLOR + ch] = colors[g, ch]
    return out


def aligned_splats(m: int, n_ch: int) -> np.ndarray:
    """An uninitialised [m, splat_width(n_ch)] float64 array whose rows start 64-byte lines."""
    width = splat_width(n_ch)
    buf = np.empty(m * width + 8)
    skip = (-buf.ctypes.data % 64) // 8
    return buf[skip : skip + m * width].reshape(m, width)


@njit(cache=True)
def _splat_tiles(splats, row_of, q, end):
    """Row k of depth rank q and the tiles its box covers (tx0, tx1, ty0, ty1, inclusive);
    asks for the row PREFETCH_PACK ranks on while it is below ``end``."""
    if q + PREFETCH_PACK < end:
        _prefetch(splats, (row_of[q + PREFETCH_PACK], S_X0))
    k = row_of[q]
    tx0 = int(splats[k, S_X0]) // TILE
    tx1 = int(splats[k, S_X1]) // TILE
    return k, tx0, tx1, int(splats[k, S_Y0]) // TILE, int(splats[k, S_Y1]) // TILE


@njit(parallel=_PARALLEL, cache=True)
def bin_tiles(splats, row_of, tiles_x, tiles_y):
    """Counting sort of (tile, splat) pairs into per-tile lists.

    The splat rows are taken front to back (``row_of[q]``: the row of depth rank q, see
    splat_rows), in BIN_CHUNKS contiguous slices of the depth order binned in parallel; slice
    c's entries precede slice c+1's inside every tile, so each tile's list stays depth-sorted.
    Returns tile_start [T+1] and the flat splat rows (ids: rows of ``splats``).
    """
    n_tiles = tiles_x * tiles_y
    m = splats.shape[0]
    n_chunks = BIN_CHUNKS
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for ch in prange(n_chunks):
        end = m * (ch + 1) // n_chunks
        for q in range(m * ch // n_chunks, end):
            _, tx0, tx1, ty0, ty1 = _splat_tiles(splats, row_of, q, end)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    counts[ch, ty * tiles_x + tx] += 1
    tile_start = np.empty(n_tiles + 1, np.int64)
    cursor = np.empty((n_chunks, n_tiles), np.int64)
    total = 0
    for t in range(n_tiles):
        tile_start[t] = total
        for ch in range(n_chunks):
            cursor[ch, t] = total
            total += counts[ch, t]
    tile_start[n_tiles] = total
    ids = np.empty(total, np.int32)
    for ch in prange(n_chunks):
        end = m * (ch + 1) // n_chunks
        for q in range(m * ch // n_chunks, end):
            k, tx0, tx1, ty0, ty1 = _splat_tiles(splats, row_of, q, end)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    t = ty * tiles_x + tx
                    ids[cursor[ch, t]] = k
                    cursor[ch, t] += 1
    return tile_start, ids


@njit(cache=True)
def _row_start(dy, u, ca, cb, cc, a):
    """exp(power) at column a of a row and exp(step), step = power(a + 1) - power(a).

    Along a row power = -(ca dx^2 + cc dy^2)/2 - cb dx dy is quadratic in dx, so the step falls
    by ca per column and exp(power) follows as gauss *= exp(step), exp(step) *= exp(-ca): two
    exps per row (and exp(-ca) per Gaussian) instead of one per pixel. With eps2d > 0 the conic
    is bounded (ca <= 1/eps2d) and a walk stays inside one tile row, so nothing overflows: a walk
    starts on its row's chord or, for an ellipse walked by its box (_forward_tile), inside that
    box, where power >= -2 ln(255) / (1 - rho) >= -38 (rho^2 <= CHORD_RHO2; exp underflows only
    below -745); the product drifts by a few ulps over a tile row. power <= 0 for a positive
    definite conic, so alpha = o * exp(power) < 1/255 is the whole cut-off test. Only the
    forward walks rows: the backward replays the values it recorded.
    """
    p_base = -0.5 * cc * dy * dy
    p_lin = -cb * dy
    dx = a + 0.5 - u
    power = p_base + dx * (p_lin - 0.5 * ca * dx)
    step = p_lin - ca * dx - 0.5 * ca
    return math.exp(power), math.exp(step)


@njit(cache=True)
def _row_span(dy, half_u, cb, inv_ca, d_conic, e_cut, i0, i1):
    """Columns of one pixel row whose centres lie on the ellipse's chord power >= cut, within
    [i0, i1]; empty when first > last. Bounding boxes of thin, tilted splats are mostly empty,
    so this trims the work per row; the per-pixel alpha test stays authoritative.

    power >= cut  <=>  ca dx^2 + 2 cb dy dx + cc dy^2 + 2 cut <= 0, dx = i + 0.5 - u, whose
    roots are dx = (-cb dy -+ sqrt(dy^2 (cb^2 - ca cc) - 2 ca cut)) / ca. The caller passes the
    per-Gaussian constants half_u = u - 0.5, inv_ca = 1/ca, d_conic = cb^2 - ca cc and
    e_cut = -2 ca cut, which leaves one sqrt and no division per row."""
    disc = dy * dy * d_conic + e_cut
    if not disc >= 0.0:  # also NaN
        return i0, i0 - 1
    root = math.sqrt(disc)
    mid = half_u - cb * dy * inv_ca
    half = root * inv_ca + 1e-6
    lo = max(mid - half, i0 - 1.0)
    hi = min(mid + half, i1 + 1.0)
    return max(i0, int(math.ceil(lo))), min(i1, int(math.floor(hi)))


@njit(cache=True)
def _tile_bounds(t, tiles_x, width, height):
    x0 = (t % tiles_x) * TILE
    y0 = (t // tiles_x) * TILE
    return x0, y0, min(x0 + TILE, width), min(y0 + TILE, height)


@njit(cache=True)
def _splat(s, splats, x0, x1, y0, y1):
    """What a tile's walk needs of splat row s: its pixel box cut to the tile (i0, i1, j0, j1),
    centre and conic, and _row_span's per-Gaussian constants (half_u, inv_ca, d_conic, e_cut)."""
    u = splats[s, S_U]
    ca = splats[s, S_CA]
    return (
        max(int(splats[s, S_X0]), x0),
        min(int(splats[s, S_X1]), x1 - 1),
        max(int(splats[s, S_Y0]), y0),
        min(int(splats[s, S_Y1]), y1 - 1),
        u,
        splats[s, S_V],
        ca,
        splats[s, S_CB],
        splats[s, S_CC],
        u - 0.5,
        1.0 / ca,
        splats[s, S_DCONIC],
        splats[s, S_ECUT],
    )


@njit(cache=True)
def _splat_shape(splats, s):
    """Centre (u, v), conic (ca, cb, cc) and opacity of splat row s."""
    return (
        splats[s, S_U],
        splats[s, S_V],
        splats[s, S_CA],
        splats[s, S_CB],
        splats[s, S_CC],
        splats[s, S_OPAC],
    )


@njit(cache=True)
def _record_alpha(entry):
    """(alpha, 1 - alpha, clamped) of a record entry (raster_forward keeps 1 - alpha, or -1
    where alpha was clamped to ALPHA_MAX)."""
    keep = np.float64(entry)
    if keep < 0.0:
        return ALPHA_MAX, 1.0 - ALPHA_MAX, True
    return 1.0 - keep, keep, False


@njit(cache=True, inline="always")
def _add_moments(g, dx, dy, sx, sy, sxx, sxy, syy):
    """The moments of _moment_grads with one pixel's g = d/dpower at (dx, dy) added."""
    gx = g * dx
    gy = g * dy
    return sx + gx, sy + gy, sxx + gx * dx, sxy + gx * dy, syy + gy * dy


@njit(cache=True)
def _moment_grads(ca, cb, cc, sx, sy, sxx, sxy, syy):
    """d/du, d/dv and d/dconic (a, b, c) of a pair from the sums over its pixels of g dx, g dy,
    g dx^2, g dx dy and g dy^2, g = d/dpower: power = -(ca dx^2 + cc dy^2)/2 - cb dx dy,
    dx = px - u, dy = py - v. (Summing per row and combining at each row's end, as before, took
    a branch per record entry that mispredicts at every row end: about 3 % of the backward.)"""
    return ca * sx + cb * sy, cb * sx + cc * sy, -0.5 * sxx, -sxy, -0.5 * syy


@njit(cache=True)
def _write_slot(geo_isect, col_isect, s, gu, gv, gca, gcb, gcc, go, gcol, gu_top, gv_top):
    """A pair's gradient sums into its slot s of raster_backward's scratch."""
    geo_isect[s, G_U] = gu
    geo_isect[s, G_V] = gv
    geo_isect[s, G_CA] = gca
    geo_isect[s, G_CB] = gcb
    geo_isect[s, G_CC] = gcc
    geo_isect[s, G_OPAC] = go
    for ch in range(gcol.shape[0]):
        col_isect[s, ch] = gcol[ch]
    geo_isect[s, _GEO_U_LAST] = gu_top
    geo_isect[s, _GEO_U_LAST + 1] = gv_top


@njit(cache=True)
def _forward_tile(
    t,
    tile_start,
    ids,
    splats,
    n_ch,
    background,
    width,
    height,
    tiles_x,
    T,
    acc,
    k_last,
    active,
    n_done,
    pmask,
    contrib_isect,
    image,
    t_final,
    last,
    upto,
    rec_keep,
    rec_pix,
    rec_img,
    rec_start,
    rec_n,
    pos,
    cap_end,
    pix_weight,
    last_from,
):
    """Composite one tile front to back for every image at once: image l takes the Gaussians
    with glevel <= upto[l] (upto strictly increasing, so a Gaussian's images are a suffix of
    them), the last image only those with glevel >= ``last_from`` too. Each Gaussian walks
    the chords of its ellipse once, skipping rows whose pixels have stopped in all of its
    images (bit masks per image in ``active`` [L, TILE], per pixel in ``pmask``); its alpha
    at a pixel is computed once and composited into each of its images where that pixel still
    runs. The exp recurrence of a row starts at the first pixel still
    running in any of those images, so an image can differ from a render of its subset alone
    by a few ulps (never more: the recurrence drifts by ulps over a tile row). A Gaussian that
    only the last image shows (every Gaussian of a single image) walks that image's state alone.
    ``contrib_isect`` (when not empty) gets each pair's sum of alpha*T in the last image, each
    pixel weighted by ``pix_weight`` [H, W] (when not empty).

    With ``pos`` >= 0 every composited pair is recorded for the backward (see raster_forward)
    from entry ``pos`` on; returns the next free entry, or -1 once ``cap_end`` is reached."""
    n_img = upto.shape[0]
    weighted = pix_weight.shape[0] > 0
    want_contrib = contrib_isect.shape[0] > 0
    x0, y0, x1, y1 = _tile_bounds(t, tiles_x, width, height)
    tw = x1 - x0
    n_pix = tw * (y1 - y0)
    all_img = (np.int64(1) << n_img) - 1
    for p in range(n_pix):
        pmask[p] = all_img
        for im in range(n_img):
            T[p, im] = 1.0
            for ch in range(n_ch):
                acc[p, im, ch] = 0.0
    for im in range(n_img):
        for r in range(TILE):
            active[im, r] = (1 << tw) - 1 if r < y1 - y0 else 0
        n_done[im] = 0
        k_last[im] = tile_start[t] - 1
    n_live = n_img  # images with a pixel still compositing
    # The last image's own state (contiguous rows of T, acc, active) for the Gaussians that
    # only it shows: most of an avatar (its finer levels), and every Gaussian of a single image.
    # Those walk as for one image, without per-image loops and masks.
    top = n_img - 1
    top_bit = np.int64(1) << top
    T_top = T[:, top]
    acc_top = acc[:, top]
    active_top = active[top]
    k_end = tile_start[t + 1]
    for k in range(tile_start[t], k_end):
        _prefetch_splat(splats, ids, k + PREFETCH, k, k_end)
        g = ids[k]
        gl = splats[g, S_LEVEL]
        im0 = 0
        while im0 < n_img and upto[im0] < gl:
            im0 += 1
        if im0 == n_img:
            continue
        im_end = n_img  # one past the Gaussian's last image
        if gl < last_from:
            if im0 == top:
                continue
            im_end = top
        i0, i1, j0, j1, u, v, ca, cb, cc, half_u, inv_ca, d_conic, e_cut = _splat(g, splats, x0, x1, y0, y1)
        o = splats[g, S_OPAC]
        e_ca = -1.0  # exp(-ca), computed on the first row walked
        wsum = 0.0
        first = pos
        c0 = splats[g, S_COLOR]
        c1 = splats[g, S_COLOR + min(1, n_ch - 1)]
        c2 = splats[g, S_COLOR + min(2, n_ch - 1)]
        box = ((1 << (i1 + 1 - x0)) - 1) ^ ((1 << (i0 - x0)) - 1) if i0 <= i1 else 0
        chord = cb * cb > CHORD_RHO2 * ca * cc
        if im0 == top:
            hit = False
            # A box-walked splat over several rows of the tile follows exp(power) and exp(step) at
            # the box's first column i0 from row to row by products (power there is quadratic in
            # dy too: _row_start's doc) instead of two exps per row; the box keeps power >= -38
            # at i0, so nothing underflows, and the products drift by ulps over a tile.
            recur = not chord and j1 - j0 >= RECUR_ROWS - 1
            j_at = j0 - 1  # the row g_i0, d_i0, s_i0 hold (none yet)
            g_i0 = d_i0 = s_i0 = e_cc = e_cb = 1.0
            for j in range(j0, j1 + 1):
                r = j - y0
                if active_top[r] == 0:
                    continue
                dy = j + 0.5 - v
                if chord:
                    a, b = _row_span(dy, half_u, cb, inv_ca, d_conic, e_cut, i0, i1)
                    if a > b:
                        continue
                    live = active_top[r] & (((1 << (b + 1 - x0)) - 1) ^ ((1 << (a - x0)) - 1))
                else:
                    live = active_top[r] & box
                if live == 0:
                    continue
                # Only from the first to the last pixel still compositing (the backward replays
                # the record, so the walk need not match anything).
                a = x0 + trailing_zeros(live)
                b = x0 + 63 - leading_zeros(live)
                if e_ca < 0.0:
                    e_ca = math.exp(-ca)
                row = r * tw - x0
                pix = r * TILE - x0
                if pos >= 0 and pos + (b + 1 - a) > cap_end:
                    pos = -1  # the record cannot hold this row: the caller runs the forward again
                if recur:
                    if j_at < j0:  # the first row walked: start at column i0 of this row
                        dx0 = i0 + 0.5 - u
                        g_i0, s_i0 = _row_start(dy, u, ca, cb, cc, i0)
                        d_i0 = math.exp(-0.5 * cc * (2.0 * dy + 1.0) - cb * dx0)
                        e_cc = math.exp(-cc)
                        e_cb = math.exp(-cb)
                        j_at = j
                    while j_at < j:
                        g_i0 *= d_i0
                        d_i0 *= e_cc
                        s_i0 *= e_cb
                        j_at += 1
                    gauss = g_i0
                    e_step = s_i0
                    for _ in range(a - i0):  # on to the first pixel still compositing
                        gauss *= e_step
                        e_step *= e_ca
                else:
                    gauss, e_step = _row_start(dy, u, ca, cb, cc, a)
                for i in range(a, b + 1):
                    p = row + i
                    gs = gauss
                    gauss *= e_step
                    e_step *= e_ca
                    if not (live >> (i - x0)) & 1:  # stopped before this Gaussian
                        continue
                    alpha = o * gs
                    if not alpha >= ALPHA_MIN:
                        continue
                    clamped = alpha > ALPHA_MAX
                    if clamped:
                        alpha = ALPHA_MAX
                    Tp = T_top[p]
                    t_next = Tp * (1.0 - alpha)
                    if t_next < T_MIN:
                        active_top[r] &= ~(1 << (i - x0))
                        pmask[p] &= ~top_bit
                        n_done[top] += 1
                        if n_done[top] == n_pix:
                            n_live -= 1
                        continue
                    if pos >= 0:
                        rec_keep[pos] = -1.0 if clamped else 1.0 - alpha
                        rec_pix[pos] = pix + i
                        rec_img[pos] = top_bit
                        pos += 1
                    w = alpha * Tp
                    if n_ch == 3:  # the common case, unrolled
                        acc_top[p, 0] += w * c0
                        acc_top[p, 1] += w * c1
                        acc_top[p, 2] += w * c2
                    else:
                        for ch in range(n_ch):
                            acc_top[p, ch] += w * splats[g, S_COLOR + ch]
                    wsum += w * pix_weight[j, i] if weighted else w
                    T_top[p] = t_next
                    hit = True
            if hit:
                k_last[top] = k
            if want_contrib:
                contrib_isect[k] = wsum
            if pos > first:
                rec_start[k] = first
                rec_n[k] = pos - first
            if n_live == 0:
                break
            continue
        img_mask = ((np.int64(1) << im_end) - 1) ^ ((np.int64(1) << im0) - 1)
        took_any = 0
        for j in range(j0, j1 + 1):
            r = j - y0
            union = 0
            for im in range(im0, im_end):
                union |= active[im, r]
            if union == 0:
                continue
            dy = j + 0.5 - v
            a, b = _row_span(dy, half_u, cb, inv_ca, d_conic, e_cut, i0, i1)
            if a > b:
                continue
            span = ((1 << (b + 1 - x0)) - 1) ^ ((1 << (a - x0)) - 1)
            live = union & span
            if live == 0:
                continue
            # From the first to the last pixel still compositing in any of the Gaussian's images
            # (the backward replays the record, so the walk need not match anything).
            a = x0 + trailing_zeros(live)
            b = x0 + 63 - leading_zeros(live)
            if e_ca < 0.0:
                e_ca = math.exp(-ca)
            row = r * tw - x0
            pix = r * TILE - x0
            if pos >= 0 and pos + (b + 1 - a) > cap_end:
                pos = -1  # the record cannot hold this row: the caller runs the forward again
            gauss, e_step = _row_start(dy, u, ca, cb, cc, a)
            for i in range(a, b + 1):
                gs = gauss
                gauss *= e_step
                e_step *= e_ca
                p = row + i
                m = pmask[p] & img_mask
                if m == 0:
                    continue
                alpha = o * gs
                if not alpha >= ALPHA_MIN:
                    continue
                clamped = alpha > ALPHA_MAX
                if clamped:
                    alpha = ALPHA_MAX
                keep = 1.0 - alpha
                took = 0
                while m:
                    im = trailing_zeros(m)
                    m &= m - 1
                    Tp = T[p, im]
                    t_next = Tp * keep
                    if t_next < T_MIN:  # stops before this Gaussian
                        active[im, r] &= ~(np.int64(1) << (i - x0))
                        pmask[p] &= ~(np.int64(1) << im)
                        n_done[im] += 1
                        if n_done[im] == n_pix:
                            n_live -= 1
                        continue
                    took |= np.int64(1) << im
                    w = alpha * Tp
                    if n_ch == 3:  # the common case, unrolled
                        acc[p, im, 0] += w * c0
                        acc[p, im, 1] += w * c1
                        acc[p, im, 2] += w * c2
                    else:
                        for ch in range(n_ch):
                            acc[p, im, ch] += w * splats[g, S_COLOR + ch]
                    if want_contrib and im == n_img - 1:
                        wsum += w * pix_weight[j, i] if weighted else w
                    T[p, im] = t_next
                took_any |= took
                if took and pos >= 0:
                    rec_keep[pos] = -1.0 if clamped else keep
                    rec_pix[pos] = pix + i
                    rec_img[pos] = took
                    pos += 1
        while took_any:
            k_last[trailing_zeros(took_any)] = k
            took_any &= took_any - 1
        if want_contrib:
            contrib_isect[k] = wsum
        if pos > first:
            rec_start[k] = first
            rec_n[k] = pos - first
        if n_live == 0:
            break
    for im in range(n_img):
        last[im, t] = k_last[im]
        for j in range(y0, y1):
            for i in range(x0, x1):
                p = (j - y0) * tw + i - x0
                for ch in range(n_ch):
                    image[im, j, i, ch] = acc[p, im, ch] + T[p, im] * background[ch]
                t_final[im, j, i] = T[p, im]
    return pos


@njit(cache=True)
def _spread_tiles(n_tiles, tiles_x):
    """Tile order for the static split of prange: tile rows r, r + SPREAD, r + 2 SPREAD, ... for
    r = 0 .. SPREAD - 1, each row left to right, so that each thread's contiguous share takes
    rows from all of the image instead of one band (the head's busiest rows would otherwise
    fall to one thread), while neighbouring tiles of a row still follow each other (they share
    Gaussians, which then stay in cache). Which thread runs a tile changes no result."""
    order = np.empty(n_tiles, np.int64)
    n_rows = (n_tiles + tiles_x - 1) // tiles_x
    i = 0
    for r0 in range(SPREAD):
        for row in range(r0, n_rows, SPREAD):
            for t in range(row * tiles_x, min(n_tiles, (row + 1) * tiles_x)):
                order[i] = t
                i += 1
    return order


def _image_out(image, n_img, height, width, n_ch):
    """raster_forward's images: the caller's array (float32 or float64) or a new float64 one."""


@overload(_image_out)
def _image_out_impl(image, n_img, height, width, n_ch):
    if isinstance(image, (types.NoneType, types.Omitted)):
        return lambda image, n_img, height, width, n_ch: np.empty((n_img, height, width, n_ch))
    return lambda image, n_img, height, width, n_ch: image


@njit(parallel=_PARALLEL, cache=True)
def raster_forward(
    tile_start,
    ids,
    splats,
    order,
    n,
    n_ch,
    background,
    width,
    height,
    tiles_x,
    upto,
    n_chunks,
    rec_keep,
    rec_pix,
    rec_img,
    pix_weight=None,
    image=None,
    contrib=True,
    last_from=LEVEL_NONE,
):
    """Front-to-back compositing, parallel over tiles, of one image per entry of ``upto``:
    image l composites the Gaussians g with glevel[g] <= upto[l] (levels of a forest share
    the projection, depth order and tile lists; a level only skips entries), and the last image
    only those with glevel[g] >= ``last_from`` too (a whole avatar without the levels below).
    The Gaussians come as pack_splats' rows (``splats``, glevel and n_ch colours included; row k is Gaussian
    order[k] of n) and bin_tiles' lists of rows.

    Returns images [L,H,W,C] (background included; written into ``image`` when given, float32
    or float64, else a new float64 array), final transmittance [L,H,W], the flat index (into
    ``ids``) of the last pair each tile composited at any of its pixels [L, tiles] (its first
    pair's index - 1: none; the backward starts there),
    the per-Gaussian contribution sum_pixels alpha*T of the last image (each pixel weighted by
    ``pix_weight`` [H, W] when given; with ``contrib`` False an empty array: training never
    reads it, and its per-pair sums and their gather are a measurable part of the forward),
    and the record.

    The record (when rec_keep, rec_pix and rec_img, the caller's buffers, are not empty) lists
    every composited (pair, pixel) once for all images, for raster_backward: 1 - alpha, the
    share of light the pair lets through (-1 where alpha was clamped to 0.99), the pixel (row *
    TILE + column in the tile) and the images that composited it (bit l: image l; a pixel may
    have stopped in some of the pair's images and not in others); pair k at entries
    rec_start[k] .. + rec_n[k], row by row. rec_keep may be float32 (rasterize.py's buffers
    are): rounding 1 - alpha rather than alpha keeps the backward's T_before = T_after /
    (1 - alpha) within one float32 rounding per layer however opaque the layer. The backward
    replays the pairs instead of walking the ellipses again (no chords, exps or skipped
    pixels), so the forward is free to trim its walk. The tiles are cut into ``n_chunks``
    static shares, one per thread, each filling its own slice of the buffers; ``used`` gives
    the entries each share took, or its capacity + 1 where it ran out (the record is then
    incomplete: the caller calls again with larger buffers). At most MAX_IMAGES images."""
    n_tiles = tile_start.shape[0] - 1
    n_img = upto.shape[0]
    if n_img > MAX_IMAGES:
        raise ValueError("raster_forward: more than MAX_IMAGES images in one pass")
    # Written in ``image``'s precision where the caller gives one [L, H, W, C] (float32 for a
    # float32 render: no float64 copy to convert afterwards); compositing stays float64.
    images = _image_out(image, n_img, height, width, n_ch)
    t_final = np.empty((n_img, height, width))
    last = np.empty((n_img, n_tiles), np.int64)
    contrib_isect = np.zeros(ids.shape[0] if contrib else 0)  # pairs after a tile's early exit stay 0
    pw = np.zeros((0, 0)) if pix_weight is None else pix_weight
    chunk_cap = min(rec_keep.shape[0], rec_pix.shape[0], rec_img.shape[0]) // n_chunks
    rec = chunk_cap > 0
    rec_start = np.zeros(ids.shape[0] if rec else 0, np.int64)
    rec_n = np.zeros(ids.shape[0] if rec else 0, np.int32)
    used = np.zeros(n_chunks, np.int64)
    spread = _spread_tiles(n_tiles, tiles_x)
    per = -(-n_tiles // n_chunks)
    for c in prange(n_chunks):
        T = np.empty((TILE * TILE, n_img))
        acc = np.empty((TILE * TILE, n_img, n_ch))
        k_last = np.empty(n_img, np.int64)
        pmask = np.empty(TILE * TILE, np.int64)
        active = np.empty((n_img, TILE), np.int64)
        n_done = np.empty(n_img, np.int64)
        pos = c * chunk_cap if rec else -1
        cap_end = (c + 1) * chunk_cap
        for it in range(c * per, min(n_tiles, (c + 1) * per)):
            nxt = _forward_tile(
                spread[it],
                tile_start,
                ids,
                splats,
                n_ch,
                background,
                width,
                height,
                tiles_x,
                T,
                acc,
                k_last,
                active,
                n_done,
                pmask,
                contrib_isect,
                images,
                t_final,
                last,
                upto,
                rec_keep,
                rec_pix,
                rec_img,
                rec_start,
                rec_n,
                pos,
                cap_end,
                pw,
                last_from,
            )
            if pos >= 0:
                used[c] = nxt - c * chunk_cap if nxt >= 0 else chunk_cap + 1
            pos = nxt
    sums = np.zeros(n if contrib else 0)  # summed per Gaussian in pair order, its rows in parallel parts
    if contrib:
        m = splats.shape[0]
        for part in prange(GATHER_PARTS):
            lo = m * part // GATHER_PARTS
            hi = m * (part + 1) // GATHER_PARTS
            for k in range(ids.shape[0]):
                s = ids[k]
                if lo <= s < hi:
                    sums[order[s]] += contrib_isect[k]
    return images, t_final, last, sums, (rec_start, rec_n, used)


@njit(cache=True)
def _replay_tile(
    t,
    tile_start,
    ids,
    splats,
    n_ch,
    background,
    t_final,
    last,
    grad_image,
    grad_alpha,
    width,
    height,
    tiles_x,
    T,
    gimg,
    g_rest,
    gcol,
    geo_isect,
    col_isect,
    slot,
    gbg,
    rec_keep,
    rec_pix,
    rec_img,
    rec_start,
    rec_n,
    split,
):
    """The backward of one tile from the forward's record: the pairs the forward composited, back
    to front per pixel, a Gaussian's pixels row by row (each row summed before it is added), every
    image at once. A pair's alpha (hence its 1/(1 - alpha) and its pixel offset) is shared by its
    images; transmittance, the incoming gradients and g_rest (raster_backward) are each image's own.
    Gaussians above level ``split`` show in the last image only (with one image: all of them)
    and replay on its state alone, without per-image loops."""
    n_img = t_final.shape[0]
    top = n_img - 1
    x0, y0, x1, y1 = _tile_bounds(t, tiles_x, width, height)
    k_max = -1
    for im in range(n_img):
        k_max = max(k_max, last[im, t])
        for j in range(y0, y1):
            for i in range(x0, x1):
                p = (j - y0) * TILE + i - x0
                tn = t_final[im, j, i]
                T[im, p] = tn
                d = grad_alpha[im, j, i] * tn
                for ch in range(n_ch):
                    gi = grad_image[im, j, i, ch]
                    d -= gi * (tn * background[ch])
                    gimg[im, p, ch] = gi
                    gbg[ch] += gi * tn
                g_rest[im, p] = d
    T_top = T[top]
    gimg_top = gimg[top]
    g_rest_top = g_rest[top]
    k_first = tile_start[t]
    for k in range(k_max, k_first - 1, -1):
        _prefetch_splat(splats, ids, k - PREFETCH, k_first, k_max + 1)
        m = rec_n[k]
        if m == 0:
            continue
        g = ids[k]
        u, v, ca, cb, cc, o = _splat_shape(splats, g)
        go = 0.0
        for ch in range(n_ch):
            gcol[ch] = 0.0
        gc0 = 0.0
        gc1 = 0.0
        gc2 = 0.0
        c0 = splats[g, S_COLOR]
        c1 = splats[g, S_COLOR + min(1, n_ch - 1)]
        c2 = splats[g, S_COLOR + min(2, n_ch - 1)]
        # Moments of g = d/dpower over the pair's pixels (see _moment_grads); each entry adds to
        # them directly, so the loop has no branch at row ends.
        sx = 0.0
        sy = 0.0
        sxx = 0.0
        sxy = 0.0
        syy = 0.0
        fu = (x0 + 0.5) - u  # dx of the tile's first column
        fv = (y0 + 0.5) - v
        if splats[g, S_LEVEL] > split:
            for e in range(rec_start[k], rec_start[k] + m):
                p = np.int64(rec_pix[e])  # the tile state is indexed as the record (row * TILE + column)
                r = p >> TILE_SHIFT
                col = p & (TILE - 1)
                alpha, keep, clamped = _record_alpha(rec_keep[e])
                dx = col + fu
                dy = r + fv
                inv = 1.0 / keep
                T_before = T_top[p] * inv
                w = alpha * T_before
                if n_ch == 3:
                    gi0 = gimg_top[p, 0]
                    gi1 = gimg_top[p, 1]
                    gi2 = gimg_top[p, 2]
                    gc0 += w * gi0
                    gc1 += w * gi1
                    gc2 += w * gi2
                    cg = c0 * gi0 + c1 * gi1 + c2 * gi2
                else:
                    cg = 0.0
                    for ch in range(n_ch):
                        gcol[ch] += w * gimg_top[p, ch]
                        cg += splats[g, S_COLOR + ch] * gimg_top[p, ch]
                d = g_rest_top[p]
                g_a = d * inv + cg * T_before
                g_rest_top[p] = d - cg * w
                T_top[p] = T_before
                if clamped:
                    continue
                g_pow = alpha * g_a  # d/dpower; d/dopacity is g_pow / o
                go += g_pow
                sx, sy, sxx, sxy, syy = _add_moments(g_pow, dx, dy, sx, sy, sxx, sxy, syy)
            gu, gv, gca, gcb, gcc = _moment_grads(ca, cb, cc, sx, sy, sxx, sxy, syy)
            go /= o
            if n_ch == 3:
                gcol[0] = gc0
                gcol[1] = gc1
                gcol[2] = gc2
            _write_slot(geo_isect, col_isect, slot + k, gu, gv, gca, gcb, gcc, go, gcol, gu, gv)
            continue
        tx = 0.0  # the same moments for the last image alone (its screen-space gradient)
        ty = 0.0
        for e in range(rec_start[k], rec_start[k] + m):
            p = np.int64(rec_pix[e])
            r = p >> TILE_SHIFT
            col = p & (TILE - 1)
            alpha, keep, clamped = _record_alpha(rec_keep[e])
            inv = 1.0 / keep
            g_all = 0.0  # d/dalpha summed over the pair's images
            g_top = 0.0
            imgs = np.int64(rec_img[e])
            while imgs:
                im = trailing_zeros(imgs)
                imgs &= imgs - 1
                T_before = T[im, p] * inv
                w = alpha * T_before
                if n_ch == 3:
                    gi0 = gimg[im, p, 0]
                    gi1 = gimg[im, p, 1]
                    gi2 = gimg[im, p, 2]
                    gc0 += w * gi0
                    gc1 += w * gi1
                    gc2 += w * gi2
                    cg = c0 * gi0 + c1 * gi1 + c2 * gi2
                else:
                    cg = 0.0
                    for ch in range(n_ch):
                        gcol[ch] += w * gimg[im, p, ch]
                        cg += splats[g, S_COLOR + ch] * gimg[im, p, ch]
                d = g_rest[im, p]
                g_a = d * inv + cg * T_before
                g_rest[im, p] = d - cg * w
                T[im, p] = T_before
                g_all += g_a
                if im == top:
                    g_top = g_a
            if clamped:
                continue
            dx = col + fu
            dy = r + fv
            g_pow = alpha * g_all  # d/dpower; d/dopacity is g_pow / o
            go += g_pow
            sx, sy, sxx, sxy, syy = _add_moments(g_pow, dx, dy, sx, sy, sxx, sxy, syy)
            g_pow = alpha * g_top
            tx += g_pow * dx
            ty += g_pow * dy
        gu, gv, gca, gcb, gcc = _moment_grads(ca, cb, cc, sx, sy, sxx, sxy, syy)
        gu_top, gv_top, _, _, _ = _moment_grads(ca, cb, cc, tx, ty, 0.0, 0.0, 0.0)
        go /= o
        if n_ch == 3:
            gcol[0] = gc0
            gcol[1] = gc1
            gcol[2] = gc2
        _write_slot(geo_isect, col_isect, slot + k, gu, gv, gca, gcb, gcc, go, gcol, gu_top, gv_top)


def scratch_entries(slot_start, n_ch: int) -> int:
    """Size of raster_backward's scratch for the slots of backward_slots() and n_ch colours."""
    return int(slot_start[-1]) * (_GEO_WIDTH + n_ch)


@njit(cache=True)
def backward_slots(tile_start, last):
    """Where each tile's pairs keep their gradient sums in raster_backward's scratch: slot
    slot_start[t] + (k - tile_start[t]) for pair k of tile t. Only pairs up to the last index
    the tile composited (in any image of raster_forward's ``last`` [L, tiles]) get a slot (less
    than half of all pairs on a head). Returns slot_start [T + 1] (its last entry: the number of
    slots)."""
    n_tiles = tile_start.shape[0] - 1
    slot_start = np.empty(n_tiles + 1, np.int64)
    n_slots = 0
    for t in range(n_tiles):
        k_last = tile_start[t] - 1
        for im in range(last.shape[0]):
            k_last = max(k_last, last[im, t])
        slot_start[t] = n_slots
        n_slots += k_last + 1 - tile_start[t]
    slot_start[n_tiles] = n_slots
    return slot_start


def _below_top(upto, n_img):
    """The highest level an image below the last one shows (Gaussians above it show in the last
    image only): -1 for a single image; without ``upto`` (several images) a level none has."""


@overload(_below_top)
def _below_top_impl(upto, n_img):
    if isinstance(upto, (types.NoneType, types.Omitted)):
        return lambda upto, n_img: -1 if n_img == 1 else 1 << 62
    return lambda upto, n_img: upto[n_img - 2] if n_img >= 2 else -1


@njit(parallel=_PARALLEL, cache=True)
def raster_backward(
    tile_start,
    ids,
    splats,
    order,
    n,
    n_ch,
    background,
    t_final,
    last,
    grad_image,
    grad_alpha,
    width,
    height,
    tiles_x,
    rec_keep,
    rec_pix,
    rec_img,
    rec_start,
    rec_n,
    slot_start,
    scratch,
    upto=None,
):
    """Back-to-front pass per pixel (3DGS) over the pairs the forward recorded (raster_forward's
    record, complete): from the saved final T, T before Gaussian i is T_after / (1 - alpha_i),
    and the colour behind it is accumulated as we go. Per pixel and Gaussian i
    (C = sum_i c_i a_i T_i + T_N bg, A = 1 - T_N):

      dC/dc_i = a_i T_i
      dC/da_i = c_i T_i - (colour behind i, background included) / (1 - a_i)
      dA/da_i = T_N / (1 - a_i)

    With incoming gradients gC, gA of the pixel, dL/da_i = (gC . c_i) T_i + g_rest / (1 - a_i),
    g_rest = gA T_N - gC . (colour behind i): one number per pixel, updated Gaussian by Gaussian,
    instead of the colour behind in every channel (a load and a store per channel and record
    entry fewer; docs/BENCHMARKS.md, 'Rasteriser kernels').

    then a = o * exp(power) (no gradient where clamped to 0.99) and
    power = -(ca dx^2 + cc dy^2)/2 - cb dx dy, dx = px - u, dy = py - v.
    Images are those of raster_forward (t_final, last, grad_image and grad_alpha carry a
    leading image axis; the record lists each pair once with its images); their gradients
    add up. Returns per-Gaussian gradients
    [N, 6 + C + 2] (layout G_*, then d/du, d/dv of the last image alone) and d/dbackground [C].

    ``upto`` (raster_forward's, when given) lets the Gaussians that only the last image shows
    replay on that image alone, without per-image loops (the same sums).

    ``slot_start`` is backward_slots(); ``scratch`` (float64, at least slot_start[-1] *
    (_GEO_WIDTH + C) entries, else one is allocated) holds the per-pair sums: the caller keeps
    it between calls because a fresh array of that size (tens of MB at 802x550) is page-faulted
    in on every call.
    """
    n_tiles = tile_start.shape[0] - 1
    n_img = t_final.shape[0]
    width_g = G_COLOR + n_ch + 2
    n_slots = slot_start[n_tiles]
    per_slot = _GEO_WIDTH + n_ch
    if scratch.shape[0] < n_slots * per_slot:
        scratch = np.empty(n_slots * per_slot)
    geo_isect = scratch[: n_slots * _GEO_WIDTH].reshape((n_slots, _GEO_WIDTH))
    col_isect = scratch[n_slots * _GEO_WIDTH : n_slots * per_slot].reshape((n_slots, n_ch))
    gbg_tile = np.zeros((n_tiles, n_ch))
    split = _below_top(upto, n_img)
    spread = _spread_tiles(n_tiles, tiles_x)
    n_chunks = min(n_tiles, REPLAY_CHUNKS)
    for c in prange(n_chunks):  # runs of the (spread) tiles, each with its own tile state
        T = np.empty((n_img, TILE * TILE))
        gimg = np.empty((n_img, TILE * TILE, n_ch))
        g_rest = np.empty((n_img, TILE * TILE))
        gcol = np.empty(n_ch)
        for it in range(n_tiles * c // n_chunks, n_tiles * (c + 1) // n_chunks):
            t = spread[it]
            geo_isect[slot_start[t] : slot_start[t + 1]] = 0.0
            col_isect[slot_start[t] : slot_start[t + 1]] = 0.0
            _replay_tile(
                t,
                tile_start,
                ids,
                splats,
                n_ch,
                background,
                t_final,
                last,
                grad_image,
                grad_alpha,
                width,
                height,
                tiles_x,
                T,
                gimg,
                g_rest,
                gcol,
                geo_isect,
                col_isect,
                slot_start[t] - tile_start[t],
                gbg_tile[t],
                rec_keep,
                rec_pix,
                rec_img,
                rec_start,
                rec_n,
                split,
            )
    # Summed per splat row, then moved to Gaussian order. A row's pairs add up in tile order
    # (deterministic); the rows are split into GATHER_PARTS ranges summed in parallel, each part
    # scanning every pair for its own rows.
    m = splats.shape[0]
    sums = np.zeros((m, width_g))
    for part in prange(GATHER_PARTS):
        lo = m * part // GATHER_PARTS
        hi = m * (part + 1) // GATHER_PARTS
        for t in range(n_tiles):
            s0 = slot_start[t] - tile_start[t]
            for k in range(tile_start[t], tile_start[t] + slot_start[t + 1] - slot_start[t]):
                g = ids[k]
                if g < lo or g >= hi:
                    continue
                for q in range(G_COLOR):
                    sums[g, q] += geo_isect[s0 + k, q]
                for ch in range(n_ch):
                    sums[g, G_COLOR + ch] += col_isect[s0 + k, ch]
                sums[g, G_COLOR + n_ch] += geo_isect[s0 + k, _GEO_U_LAST]
                sums[g, G_COLOR + n_ch + 1] += geo_isect[s0 + k, _GEO_U_LAST + 1]
    grads = np.zeros((n, width_g))
    for blk in prange((m + BLOCK - 1) // BLOCK):
        for r in range(blk * BLOCK, min(m, (blk + 1) * BLOCK)):
            for q in range(width_g):
                grads[order[r], q] = sums[r, q]
    gbg = np.zeros(n_ch)
    for t in range(n_tiles):
        for ch in range(n_ch):
            gbg[ch] += gbg_tile[t, ch]
    return grads, gbg


@njit(parallel=_PARALLEL, cache=True)
def split_grads(grads, g_uv, g_conic, g_depth, g_opac, g_colors, g_uv_last):
    """raster_backward's rows [N, G_COLOR + C + 2] split in one pass into what project_backward
    takes (g_uv [N,2], g_conic [N,3], g_depth [N] or empty: no depth channel among the C) and
    what the caller returns (g_opac [N], g_colors [N, C or C-1], g_uv_last [N,2]), each in its
    own array's dtype. Column slices of the wide rows, copied one at a time, read every row's
    cache lines once per slice."""
    n = grads.shape[0]
    n_col = g_colors.shape[1]
    depth = g_depth.shape[0] > 0
    last = grads.shape[1] - 2
    for blk in prange((n + BLOCK - 1) // BLOCK):
        for r in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            g_uv[r, 0] = grads[r, G_U]
            g_uv[r, 1] = grads[r, G_V]
            g_conic[r, 0] = grads[r, G_CA]
            g_conic[r, 1] = grads[r, G_CB]
            g_conic[r, 2] = grads[r, G_CC]
            g_opac[r] = grads[r, G_OPAC]
            for ch in range(n_col):
                g_colors[r, ch] = grads[r, G_COLOR + ch]
            if depth:
                g_depth[r] = grads[r, G_COLOR + n_col]
            g_uv_last[r, 0] = grads[r, last]
            g_uv_last[r, 1] = grads[r, last + 1]


@njit(cache=True, inline="always")
def _project_backward_one(
    g,
    means,
    quats,
    scales,
    Rc,
    tc,
    fx,
    fy,
    lim,
    eps2d,
    grad_uv,
    grad_conic,
    grad_depth,
    R,
    Mc,
    A,
    GA,
    GM,
    g_means,
    g_quats,
    g_scales,
):
    """One Gaussian of project_backward (R, Mc, A, GA, GM: scratch)."""
    mx, my, mz = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
    px = Rc[0, 0] * mx + Rc[0, 1] * my + Rc[0, 2] * mz + tc[0]
    py = Rc[1, 0] * mx + Rc[1, 1] * my + Rc[1, 2] * mz + tc[1]
    pz = Rc[2, 0] * mx + Rc[2, 1] * my + Rc[2, 2] * mz + tc[2]
    qn, qw, qx, qy, qz = _camera_factor(quats[g], scales[g], Rc, R, Mc)
    j00, j02, j11, j12, kx, ky, x_free, y_free = _jacobian(px, py, pz, fx, fy, lim)
    a = eps2d
    b = 0.0
    c = eps2d
    for k in range(3):
        A[0, k] = j00 * Mc[0, k] + j02 * Mc[2, k]
        A[1, k] = j11 * Mc[1, k] + j12 * Mc[2, k]
        a += A[0, k] * A[0, k]
        b += A[0, k] * A[1, k]
        c += A[1, k] * A[1, k]
    inv_det = 1.0 / (a * c - b * b)
    qa = c * inv_det
    qb = -b * inv_det
    qc = a * inv_det
    ga = grad_conic[g, 0]
    gb = 0.5 * grad_conic[g, 1]
    gc = grad_conic[g, 2]
    # -Q G Q for symmetric 2x2 Q = [[qa, qb], [qb, qc]], G = [[ga, gb], [gb, gc]].
    m00 = qa * ga + qb * gb
    m01 = qa * gb + qb * gc
    m10 = qb * ga + qc * gb
    m11 = qb * gb + qc * gc
    s00 = -(m00 * qa + m01 * qb)
    s01 = -(m00 * qb + m01 * qc)
    s11 = -(m10 * qb + m11 * qc)
    for k in range(3):
        GA[0, k] = 2.0 * (s00 * A[0, k] + s01 * A[1, k])
        GA[1, k] = 2.0 * (s01 * A[0, k] + s11 * A[1, k])
    gj00 = GA[0, 0] * Mc[0, 0] + GA[0, 1] * Mc[0, 1] + GA[0, 2] * Mc[0, 2]
    gj02 = GA[0, 0] * Mc[2, 0] + GA[0, 1] * Mc[2, 1] + GA[0, 2] * Mc[2, 2]
    gj11 = GA[1, 0] * Mc[1, 0] + GA[1, 1] * Mc[1, 1] + GA[1, 2] * Mc[1, 2]
    gj12 = GA[1, 0] * Mc[2, 0] + GA[1, 1] * Mc[2, 1] + GA[1, 2] * Mc[2, 2]
    # dL/dMc = J^T GA has rows (j00 GA0, j11 GA1, j02 GA0 + j12 GA1); dL/dM = Rc^T dL/dMc.
    for k in range(3):
        r0 = j00 * GA[0, k]
        r1 = j11 * GA[1, k]
        r2 = j02 * GA[0, k] + j12 * GA[1, k]
        for i in range(3):
            GM[i, k] = Rc[0, i] * r0 + Rc[1, i] * r1 + Rc[2, i] * r2
    s0, s1, s2 = np.float64(scales[g, 0]), np.float64(scales[g, 1]), np.float64(scales[g, 2])
    for k in range(3):
        g_scales[g, k] = GM[0, k] * R[0, k] + GM[1, k] * R[1, k] + GM[2, k] * R[2, k]
    d00 = GM[0, 0] * s0
    d01 = GM[0, 1] * s1
    d02 = GM[0, 2] * s2
    d10 = GM[1, 0] * s0
    d11 = GM[1, 1] * s1
    d12 = GM[1, 2] * s2
    d20 = GM[2, 0] * s0
    d21 = GM[2, 1] * s1
    d22 = GM[2, 2] * s2
    # dR/dq of the rotation in _camera_factor, contracted with dL/dR = (d_ij).
    gw = 2.0 * (-qz * d01 + qy * d02 + qz * d10 - qx * d12 - qy * d20 + qx * d21)
    gx = 2.0 * (qy * d01 + qz * d02 + qy * d10 - 2.0 * qx * d11 - qw * d12 + qz * d20 + qw * d21 - 2.0 * qx * d22)
    gy = 2.0 * (-2.0 * qy * d00 + qx * d01 + qw * d02 + qx * d10 + qz * d12 - qw * d20 + qz * d21 - 2.0 * qy * d22)
    gz = 2.0 * (-2.0 * qz * d00 - qw * d01 + qx * d02 + qw * d10 - 2.0 * qz * d11 + qy * d12 + qx * d20 + qy * d21)
    # Through q/|q|: drop the radial part, scale by 1/|q|.
    dot = gw * qw + gx * qx + gy * qy + gz * qz
    inv_qn = 1.0 / qn
    g_quats[g, 0] = (gw - dot * qw) * inv_qn
    g_quats[g, 1] = (gx - dot * qx) * inv_qn
    g_quats[g, 2] = (gy - dot * qy) * inv_qn
    g_quats[g, 3] = (gz - dot * qz) * inv_qn
    # Camera-space mean: u = fx x/z + cx, v = fy y/z + cy, J00 = fx/z, J11 = fy/z, and
    # J02 = -fx kx / z with kx = x/z unless clamped (then kx is a constant); same for y.
    rz = 1.0 / pz
    rz2 = rz * rz
    gu = grad_uv[g, 0]
    gv = grad_uv[g, 1]
    gpx = gu * fx * rz
    gpy = gv * fy * rz
    gpz = -(gu * fx * px + gv * fy * py) * rz2 - (gj00 * fx + gj11 * fy) * rz2 + grad_depth[g]
    if x_free:
        gpx -= gj02 * fx * rz2
        gpz += gj02 * 2.0 * fx * kx * rz2
    else:
        gpz += gj02 * fx * kx * rz2
    if y_free:
        gpy -= gj12 * fy * rz2
        gpz += gj12 * 2.0 * fy * ky * rz2
    else:
        gpz += gj12 * fy * ky * rz2
    for i in range(3):
        g_means[g, i] = Rc[0, i] * gpx + Rc[1, i] * gpy + Rc[2, i] * gpz


@njit(parallel=_PARALLEL, cache=True)
def project_backward(
    means, quats, scales, Rc, tc, fx, fy, lim, eps2d, radii, grad_uv, grad_conic, grad_depth, g_means, g_quats, g_scales
):
    """Chain rule from (u, v), conic and camera z back to means, quats (wxyz, unnormalised) and
    scales, written into g_means [N,3], g_quats [N,4], g_scales [N,3] (float32 or float64: the
    sums are float64 and each value is rounded once, where a float64 result and a separate
    conversion cost a pass over 10 values a Gaussian and their memory).

    With A = J Mc (2x3), cov2d = A A^T + eps2d I, conic Q = cov2d^-1:
      dL/dcov2d = -Q G_Q Q      (G_Q symmetric: the off-diagonal scalar's gradient split in two)
      dL/dA = 2 dL/dcov2d A,  dL/dJ = dL/dA Mc^T,  dL/dMc = J^T dL/dA
      Mc = Rc R S:  dL/dM = Rc^T dL/dMc,  dL/dR_ij = dL/dM_ij s_j,  dL/ds_j = sum_i dL/dM_ij R_ij
    and J depends on the camera-space mean through 1/z and the (possibly clamped) x/z, y/z.
    Culled Gaussians (radius 0) get zero gradients.
    """
    n = means.shape[0]
    for blk in prange((n + BLOCK - 1) // BLOCK):
        R = np.empty((3, 3))
        Mc = np.empty((3, 3))
        A = np.empty((2, 3))
        GA = np.empty((2, 3))
        GM = np.empty((3, 3))
        for g in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            if radii[g] == 0:
                for k in range(3):
                    g_means[g, k] = 0.0
                    g_scales[g, k] = 0.0
                for k in range(4):
                    g_quats[g, k] = 0.0
            else:
                _project_backward_one(
                    g,
                    means,
                    quats,
                    scales,
                    Rc,
                    tc,
                    fx,
                    fy,
                    lim,
                    eps2d,
                    grad_uv,
                    grad_conic,
                    grad_depth,
                    R,
                    Mc,
                    A,
                    GA,
                    GM,
                    g_means,
                    g_quats,
                    g_scales,
                )
