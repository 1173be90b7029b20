"""The stream writer: records (quantised or lossless) in stream order, blocks and their
checksums, written atomically (numpy only: runs in Blender)."""

from __future__ import annotations

import json
import math
import os
import struct
import zlib
from types import SimpleNamespace

import numpy as np

from ..avatar.avatar import Avatar, SH_C0
from ..io.atomic import atomic_open
from .format import (
    DEFAULT_BLOCK,
    FLAG_LOSSLESS,
    FLAG_BACKDROP,
    FLAG_STAND_INS,
    FLAG_TEMPLATE,
    LOG_SCALE_LIMIT,
    LOSSLESS_DTYPE,
    LOSSLESS_RECORD,
    LOSSLESS_ROOT,
    QUANT_DTYPE,
    RANGE_LIMIT,
    QUANT_RECORD,
    QUANT_ROOT,
    QUANT_ROOT_BIT,
    LOSSLESS_ROOT_SLOT,
    MAX_ROOT_FACES,
    StreamInfo,
    VERSION,
    _encode_coarse,
    _encode_header,
    _f32_ceil,
    _f32_floor,
    crc8,
    crc8_indexed,
    max_exceptions,
    quant_ranges,
    template_hash,
)
from .order import interleaved_order, root_keys, stream_order


def _quantize_records(av, bary: np.ndarray, quant: np.ndarray, links: tuple, version: int = VERSION) -> np.ndarray:
    """Quantised records of `av` (per-record parameter arrays in stream order); `links` is
    (parent field, slot field, root flag) per record (_links)."""
    parent, slot, is_root = links
    N = len(parent)
    rec = np.zeros(N, QUANT_DTYPE)
    q = quant_ranges(quant)

    def codes(x, lo, hi, levels):
        span = hi - lo
        safe = np.where(span > 0, span, 1.0)
        c = np.rint((np.clip(x, lo, hi) - lo) / safe * (levels - 1))
        return np.where(span > 0, c, 0).astype(np.uint64)

    mu = codes(av.d_mu.astype(np.float64), *q["mu"], 4096)
    b0 = np.rint(bary[:, 0] * 4095).astype(np.int64)
    b1 = np.minimum(np.rint(bary[:, 1] * 4095).astype(np.int64), 4095 - b0)
    rec["geo"] = (
        mu[:, 0]
        | (mu[:, 1] << np.uint64(12))
        | (mu[:, 2] << np.uint64(24))
        | (b0.astype(np.uint64) << np.uint64(36))
        | (b1.astype(np.uint64) << np.uint64(48))
        | (slot.astype(np.uint64) << np.uint64(60))
    )
    if version >= 5:
        rec["geo"] |= is_root.astype(np.uint64) << np.uint64(QUANT_ROOT_BIT)

    rc = codes(_unit_quaternions(av.d_rot), *q["rot"], 256).astype(np.uint32)
    rec["rot"] = rc[:, 0] | (rc[:, 1] << np.uint32(8)) | (rc[:, 2] << np.uint32(16)) | (rc[:, 3] << np.uint32(24))
    parent = parent.astype(np.uint32)
    rec["parent"] = np.stack([parent & 0xFF, (parent >> 8) & 0xFF, (parent >> 16) & 0xFF], 1).astype(np.uint8)
    rec["ls"] = codes(av.d_log_scale.astype(np.float64), *q["ls"], 256).astype(np.uint8)
    alpha = 1.0 / (1.0 + np.exp(-av.opacity_logit.astype(np.float64)))
    rec["opa"] = np.minimum(np.floor(alpha * 256.0), 255).astype(np.uint8)
    c = 0.5 + SH_C0 * av.f_dc.astype(np.float64)
    rec["col"] = codes(c, *q["c"], 256).astype(np.uint8)
    raw = rec.view(np.uint8).reshape(N, QUANT_RECORD)
    rec["crc"] = crc8_indexed(raw[:, : QUANT_RECORD - 1], 0) if version >= 3 else crc8(raw[:, : QUANT_RECORD - 1])
    return rec


def _lossless_records(av, split_logits, links: tuple, version: int = VERSION) -> np.ndarray:
    parent, slot, is_root = links
    N = len(parent)
    rec = np.zeros(N, LOSSLESS_DTYPE)
    if version >= 5:
        slot = np.where(is_root, LOSSLESS_ROOT_SLOT, slot)
    rec["link"] = parent.astype(np.uint32) | (slot.astype(np.uint32) << np.uint32(30))
    rec["split_logits"] = split_logits
    for name in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc"):
        rec[name] = getattr(av, name)
    if not np.all(np.isfinite(split_logits)):
        raise ValueError("write_stream: split logits contain NaN or inf")
    raw = rec.view(np.uint8).reshape(N, LOSSLESS_RECORD)
    rec["crc"] = crc8_indexed(raw[:, : LOSSLESS_RECORD - 1], 0) if version >= 3 else crc8(raw[:, : LOSSLESS_RECORD - 1])
    return rec


def _links(forest, s: np.ndarray, row_of: np.ndarray, root_value: int, version: int) -> tuple:
    """(parent field, slot field, root flag) of the records, stream position i holding face
    s[i]: a non-root names its parent's stream position and its slot; a root names its row of
    the stored root table (version 3 on; before, the root marker value) with slot 0."""
    N = len(s)
    pos = np.empty(N, np.int64)
    pos[s] = np.arange(N)
    par = forest.parent[s]
    is_root = par < 0
    parent = np.where(is_root, root_value, pos[np.maximum(par, 0)])
    if version >= 3:
        parent[is_root] = row_of[forest.root_ref[s[is_root]]]
    slot = np.where(is_root, 0, forest.slot[s]).astype(np.int64)
    return parent.astype(np.int64), slot, is_root


def _unit_quaternions(d_rot) -> np.ndarray:
    """Rotations as coded (FORMAT.md 3.1): unit length, w >= 0 (q and -q are one rotation;
    this halves w's range), a zero quaternion read as the identity."""
    r = np.asarray(d_rot, np.float64)
    n = np.linalg.norm(r, axis=1, keepdims=True)
    r = np.where(n > 0, r / np.where(n > 0, n, 1.0), np.array([1.0, 0, 0, 0]))
    return np.where(r[:, :1] < 0, -r, r)


# Version 4 robust ranges (FORMAT.md 3.2): a component's fence spans its k-th smallest to k-th
# largest value, k = max(max_exceptions(N), N / 100) (so neither end moves for up to that many
# outliers), widened by that width on either side; values beyond it are escaped (carried exactly
# in the header), the farthest first, at most max_exceptions(N) of them; the range is the hull
# of the rest.
FENCE_TRIM = 0.01
FENCE_WIDEN = 1.0


def _coded_values(av: Avatar) -> np.ndarray:
    """[N,13] float64: each component as the quantised record codes it (EXCEPTION_COMPONENTS
    order): d_mu within +-RANGE_LIMIT, log-scales within +-LOG_SCALE_LIMIT, the colour
    0.5 + SH_C0 f_dc within [0, RANGE_LIMIT] (a renderer clamps negative colour to 0), the
    unit quaternion with w >= 0."""
    c = 0.5 + SH_C0 * av.f_dc.astype(np.float64)
    return np.concatenate(
        [
            np.clip(av.d_mu.astype(np.float64), -RANGE_LIMIT, RANGE_LIMIT),
            np.clip(av.d_log_scale.astype(np.float64), -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT),
            np.clip(c, 0.0, RANGE_LIMIT),
            _unit_quaternions(av.d_rot),
        ],
        axis=1,
    )


def _escapes(x: np.ndarray) -> np.ndarray:
    """[N,13] bool: the values a version 4 stream carries exactly (see FENCE_TRIM)."""
    N = len(x)
    cap = max_exceptions(N)
    k = min(max(cap, math.ceil(FENCE_TRIM * N)), (N - 1) // 2)
    part = np.partition(x, (k, N - 1 - k), axis=0)
    p_lo, p_hi = part[k], part[N - 1 - k]
    # width floor: a (near-)constant component does not escape rounding-level differences
    w = np.maximum(p_hi - p_lo, 1e-6 * np.maximum(np.maximum(np.abs(p_lo), np.abs(p_hi)), 1.0))
    excess = np.maximum((p_lo - FENCE_WIDEN * w) - x, x - (p_hi + FENCE_WIDEN * w))
    score = np.where(excess > 0, excess / w, 0.0).ravel()
    out = score > 0
    if out.sum() > cap:  # keep the cap farthest (in fence widths); the others widen the range
        keep = np.argpartition(-score, cap - 1)[:cap]
        out[:] = False
        out[keep] = True
    return out.reshape(x.shape)


def _quant_table(av: Avatar, version: int = VERSION):
    """(26-float table, exceptions or None). Versions 2-3: each range the min..max of the coded
    values; version 4: robust ranges plus the exceptions table (FORMAT.md 3.2). Either way every
    table value and decoded value stays finite in float32 (limits above)."""
    x = _coded_values(av)
    esc = _escapes(x) if version >= 4 else np.zeros(x.shape, bool)
    lo = np.where(esc, np.inf, x).min(0)
    hi = np.where(esc, -np.inf, x).max(0)
    parts = [lo[0:3], hi[0:3], lo[3:6], hi[3:6], lo[6:9], hi[6:9], lo[9:13], hi[9:13]]
    table = np.concatenate([_f32_floor(p) if i % 2 == 0 else _f32_ceil(p) for i, p in enumerate(parts)])
    table = table.astype(np.float32)
    lim32 = _f32_floor(RANGE_LIMIT)  # (outward rounding must not pass the limits)
    table[6:12] = np.clip(table[6:12], -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT)
    table = np.clip(table, -lim32, lim32)
    if not esc.any():
        return table, None
    rows, comps = np.nonzero(esc)  # row-major: sorted by (record, component)
    params = np.concatenate(
        [
            np.clip(av.d_mu.astype(np.float64), -RANGE_LIMIT, RANGE_LIMIT),
            np.clip(av.d_log_scale.astype(np.float64), -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT),
            np.clip(av.f_dc.astype(np.float64), -RANGE_LIMIT, RANGE_LIMIT),
            _unit_quaternions(av.d_rot),
        ],
        axis=1,
    )
    vals = np.clip(params[rows, comps].astype(np.float32), -lim32, lim32)
    return table, (rows.astype(np.int64), comps.astype(np.uint8), vals)


_PATH_KEYS = ("data", "run")  # metadata entries that hold local folders


# A stand-in makes way once the template faces of its region received hold RETIRE_IMPORTANCE of
# the region's importance and RETIRE_AREA of its area (rest pose). Compared on the default head's
# stand-in run (seed 0, 8 views, 1 % steps, a scratch script; the chosen rule's curves are in
# docs/BENCHMARKS.md, "coarse stand-ins"): waiting for the last template face
# kept stand-ins over nearly finished regions far into the stream (25 %: 23.88 dB); importance
# alone retired some while a third of their region's area was missing (a 0.9 dB dip at 18 %:
# importance measured with the stand-ins present is low where they already look right); area
# alone (0.95) was monotone but 0.5 dB lower at 25 %; both (0.95, 0.8): 25 % 25.16 dB, worst
# 1 % step -0.05 dB.
RETIRE_IMPORTANCE = 0.95
RETIRE_AREA = 0.8
# A backdrop stand-in (it stays, behind the rest) goes behind once its region's template faces
# received hold BACKDROP_RETIRE_IMPORTANCE of the region's importance, whatever their area (what
# is missing then shows the stand-in behind). Compared on both heads' backdrop runs (8 views,
# 1 % steps, a scratch script, 2026-11-27): the last template face kept stand-ins in front of
# finished regions until ~88 % of the default head's stream (25 %: 23.55 dB, 100 %: 25.32);
# the rule above (0.95, 0.8) left dips of 0.23-0.33 dB on the 1,280-face head; 0.99 alone a
# 0.41 dB dip on the default head; 0.999 alone: worst 1 % step -0.05 dB, 25 %: 24.38 dB.
BACKDROP_RETIRE_IMPORTANCE = 0.999


def stand_in_retire(
    forest, s: np.ndarray, vertices=None, importance=None, bounds=(RETIRE_IMPORTANCE, RETIRE_AREA)
) -> np.ndarray:
    """[C] per coarse row of ``forest``: the stream position (order ``s``) at which the template
    faces of its region (coarse.stand_in_regions on the rest-pose ``vertices``) received reach
    ``bounds`` (default RETIRE_IMPORTANCE, RETIRE_AREA) of the region's importance and of its area; without importance,
    its last template face. A region with no template face, or every region when ``vertices`` is
    None, waits for the whole template level."""
    from ..avatar.coarse import stand_in_regions

    C, K = forest.num_coarse, forest.num_coarse_levels
    pos = np.empty(len(s), np.int64)
    pos[s] = np.arange(len(s))
    tmpl = np.flatnonzero(forest.level == K)  # template faces (roots), any order
    tpos = pos[tmpl]
    retire = np.full(C, tpos.max(), np.int64)
    if vertices is None or not C:
        return retire
    faces = forest.template_faces[forest.root_ref[tmpl] - C]
    region = stand_in_regions(vertices, forest.coarse_faces, forest.coarse_counts, faces)
    v = np.asarray(vertices, np.float64)[faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    if importance is None:
        shares = [(np.ones(len(tmpl)), 1.0)]
    else:
        imp = np.maximum(np.asarray(importance, np.float64)[tmpl], 0.0)
        shares = [(imp, bounds[0]), (area, bounds[1])]
    for k in range(K):
        # per region, its template faces in stream order: the first at which every running
        # share reaches its bound (at the latest, the region's last face)
        o = np.lexsort((tpos, region[:, k]))
        reg, p = region[o, k], tpos[o]
        first = np.flatnonzero(np.r_[True, reg[1:] != reg[:-1]])
        n = np.diff(np.r_[first, len(reg)])
        reached = np.ones(len(reg), bool)
        for w, share in shares:
            cum = np.cumsum(w[o])
            within = cum - np.repeat(cum[first] - w[o][first], n)
            total = np.repeat(within[first + n - 1], n)
            reached &= (within >= share * total * (1 - 1e-12)) & (total > 0)
        reached[first + n - 1] = True
        at = np.minimum.reduceat(np.where(reached, np.arange(len(reg)), len(reg)), first)
        retire[reg[first]] = p[at]
    return retire


def write_stream(path, avatar: Avatar, importance=None, **kwargs) -> StreamInfo:
    """Write `avatar` as a stream to `path` (atomically: written whole, then renamed over any
    previous file, which a failure leaves as it was). Returns its header (build_stream)."""
    data, info = build_stream(avatar, importance, **kwargs)
    with atomic_open(path) as fh:
        fh.write(data)
    return info


def build_stream(
    avatar: Avatar,
    importance=None,
    *,
    quantize: bool = True,
    metadata=None,
    embed_template: bool = True,
    records_per_block: int = DEFAULT_BLOCK,
    drop_sh: bool = False,
    root_order: str | None = None,
    vertices=None,
    version: int = VERSION,
) -> tuple[bytes, StreamInfo]:
    """`avatar` as a stream, in memory: (its bytes, its header). `.order` maps each face of
    the avatar a reader decodes (roots first) to this avatar's face, `.stream_order` each
    stream position to this avatar's face. Records carry the DC colour only: an avatar with
    higher SH bands is refused unless ``drop_sh`` (then the metadata says which degree was
    dropped).

    Version 5 (default), given the faces' importance: the coarse levels open the stream, level
    by level in `root_order`, then every other face, the template's included, once its parent
    has been sent, in units of most importance per record (order.interleaved_order). Without
    importance, and in versions 2-4: level by level, roots in `root_order` (root_keys:
    default "auto", importance, else spatial on the rest-pose `vertices`, when either is given,
    else the forest's order), the other levels by descending importance. The avatar's
    training settings (meta "config") stay out of the header (they are in the run folder):
    time to the first whole head counts. The run and data folders are named by their last
    component only: local paths do not travel with a shared file. An avatar whose coarse faces
    are stand-ins needs `vertices`: each stand-in's retire position is its region's there
    (stand_in_retire).
    ``version=4`` writes the previous format (every root first, level by level), ``version=3``
    the one before (min..max quantisation ranges, no exceptions table), ``version=2`` the one
    before that (no coarse levels, roots in template order)."""
    forest = avatar.forest
    if avatar.sh_degree and not drop_sh:
        raise ValueError(
            f"write_stream: the avatar has SH degree {avatar.sh_degree}; stream records carry the "
            "DC colour only (docs/FORMAT.md). Pass drop_sh=True (export.py --drop-sh) to stream "
            "its view-independent colour; a 3DGS PLY keeps every band (export.py --ply, which "
            "needs no --drop-sh without --stream)"
        )
    N = forest.num_faces
    if not 1 <= int(records_per_block) <= 0xFFFF:
        raise ValueError(f"write_stream: records_per_block must be in [1, 65535], got {records_per_block}")
    limit = QUANT_ROOT if quantize else LOSSLESS_ROOT
    if N > limit:
        raise ValueError(f"write_stream: {N} Gaussians exceed this record type's limit of {limit}")
    if max(len(forest.template_faces), forest.num_coarse) > MAX_ROOT_FACES:  # what readers refuse
        raise ValueError(
            f"write_stream: {len(forest.template_faces)} template faces and {forest.num_coarse} coarse faces: "
            f"a stream holds at most {MAX_ROOT_FACES} of each"
        )
    if version not in (2, 3, 4, VERSION):
        raise ValueError(f"write_stream: can write versions 2, 3, 4 and {VERSION}, not {version}")
    C, K = forest.num_coarse, forest.num_coarse_levels
    if forest.num_roots != C + len(forest.template_faces):
        raise ValueError(
            f"write_stream: the avatar holds {forest.num_roots} of its {C + len(forest.template_faces)} "
            "roots (a prefix); streams start from every root"
        )
    if forest.stand_ins and K and version >= 3 and vertices is None:
        # Without the rest pose no stand-in knows its region: every one would stay in front
        # until the last template face, over faces long arrived (a plateau across most of the
        # stream), and nothing would say so.
        raise ValueError(
            "write_stream: the avatar's coarse faces are stand-ins; pass the template's rest-pose "
            "vertices (vertices=, e.g. Dataset(data).canonical_vertices) so that each one makes way "
            "when its region's template faces have arrived"
        )
    if root_order is None:
        known = vertices is not None or importance is not None
        root_order = "auto" if known and version != 2 else "forest"
    if version == 2:
        if K or not np.array_equal(forest.root_ref, np.arange(forest.num_roots)) or root_order != "forest":
            raise ValueError("write_stream: version 2 has no coarse levels and keeps roots in template order")
    keys = root_keys(forest, root_order, importance, vertices)
    if version >= 5 and importance is not None:  # each face as soon as its parent is sent
        s = interleaved_order(forest, importance, keys)
    elif version >= 5 and keys is None and forest.root_rank[-1] != forest.num_roots - 1:
        # An avatar read from a version 5 stream in which a root arrived after a non-root keeps
        # its order. Only coarse levels allow that: without them every root is in the lead, so
        # root_rank cannot tell a read stream from a trained forest, and the else branch below
        # sends the faces level by level (the read order of the non-roots is not kept).
        s = forest.stream_order()
    else:
        s = stream_order(forest, importance, keys)
    # The reader's faces: the roots in stream order, then the others in stream order.
    is_root_s = forest.parent[s] < 0
    order = np.concatenate([s[is_root_s], s[~is_root_s]])
    # The coarse table as stored: each level's rows sorted by vertex (compresses well); roots
    # name their row of [stored coarse table; template].
    row_of = np.arange(C + len(forest.template_faces), dtype=np.int64)
    coarse_rows = forest.coarse_faces
    if C:
        starts = np.concatenate([[0], np.cumsum(forest.coarse_counts)])
        perm = np.concatenate(
            [a + np.lexsort(forest.coarse_faces[a:b].T[::-1]) for a, b in zip(starts[:-1], starts[1:])]
        )
        coarse_rows = forest.coarse_faces[perm]
        row_of[perm] = np.arange(C)
    links = _links(forest, s, row_of, QUANT_ROOT if quantize else LOSSLESS_ROOT, version)
    recs_in = SimpleNamespace(
        **{n: getattr(avatar, n)[s] for n in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc")}
    )

    meta = {k: v for k, v in dict(avatar.meta or {}).items() if k not in ("stream", "config")}
    if avatar.sh_degree:
        meta["sh_degree_dropped"] = avatar.sh_degree
    meta.update(metadata or {})
    for key in _PATH_KEYS:  # a stream is made to be shared: name the folders, not where they lie
        if isinstance(meta.get(key), str):
            meta[key] = os.path.basename(os.path.normpath(meta[key]))
    try:
        meta_blob = json.dumps(meta, sort_keys=True, allow_nan=False).encode("utf-8") if meta else b""
    except (TypeError, ValueError) as exc:
        raise ValueError(f"write_stream: metadata must be JSON-serialisable: {exc}") from None
    tmpl = np.ascontiguousarray(forest.template_faces, "<i4")
    template_blob = zlib.compress(tmpl.tobytes(), 9) if embed_template else b""
    stand_ins = bool(forest.stand_ins and K and version >= 3)
    if forest.stand_ins and not stand_ins:
        raise ValueError(f"write_stream: version {version} cannot carry coarse stand-ins (version 3 or later can)")
    retire = None
    if stand_ins:
        retire = np.empty(C, np.int64)
        bounds = (BACKDROP_RETIRE_IMPORTANCE, 0.0) if forest.backdrop else (RETIRE_IMPORTANCE, RETIRE_AREA)
        retire[row_of[:C]] = stand_in_retire(forest, s, vertices, importance, bounds)  # in the stored rows' order
    flags = (
        (0 if quantize else FLAG_LOSSLESS)
        | (FLAG_TEMPLATE if embed_template else 0)
        | (FLAG_STAND_INS if stand_ins else 0)
        | (FLAG_BACKDROP if stand_ins and forest.backdrop else 0)
    )
    level_counts = tuple(int(c) for c in forest.level_counts())
    if quantize:
        quant, exceptions = _quant_table(recs_in, version)
        recs = _quantize_records(recs_in, forest.barycentrics()[s], quant, links, version)
    else:
        quant, exceptions = None, None
        recs = _lossless_records(recs_in, forest.split_logits[s], links, version)
    R = recs.dtype.itemsize
    info = StreamInfo(
        version,
        flags,
        0,
        N,
        len(tmpl),
        R,
        int(records_per_block),
        level_counts,
        template_hash(tmpl),
        quant,
        meta,
        tmpl.astype(np.int32) if embed_template else None,
        num_coarse_levels=K,
        coarse_faces=coarse_rows.astype(np.int32) if K else None,
        coarse_retire=retire,
        exceptions=exceptions,
    )
    header = _encode_header(info, template_blob, meta_blob, _encode_coarse(coarse_rows, retire) if K else b"")
    raw = recs.tobytes()
    B = info.records_per_block
    prefix = struct.pack("<I", info.header_crc)
    parts = [header]
    for bi in range(info.num_blocks):  # per block, not per record
        block = raw[bi * B * R : min(N, (bi + 1) * B) * R]
        crc = zlib.crc32(block, zlib.crc32(prefix + struct.pack("<I", bi)))
        parts.append(block)
        parts.append(struct.pack("<I", crc))
    data = b"".join(parts)
    assert len(data) == info.total_bytes
    info.order = order
    info.stream_order = s
    return data, info


def encode_stream(avatar: Avatar, importance=None, **kwargs) -> bytes:
    """The stream as bytes (build_stream's: the same encoder as write_stream)."""
    return build_stream(avatar, importance, **kwargs)[0]
