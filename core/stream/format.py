"""The progressive avatar stream: importance order, writer, reader (numpy only: runs in Blender).

The byte layout is specified once, in docs/FORMAT.md; this module implements it. In short:
a checksummed header, then fixed-size records (one Gaussian per forest face) in stream order
(level 0 in template order, then each level by descending importance), grouped in blocks
that end with a CRC-32, each record also ending with a CRC-8 so that every whole record of a
truncated stream can be verified.

Decoding is vectorised: records are viewed with a structured dtype and every field is decoded
by whole-array operations over all new records; the only Python loops run per block (CRC-32)
or per level, never per record.
"""

from __future__ import annotations

import bisect
import hashlib
import json
import math
import os
import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

from ..io.atomic import atomic_open
from ..avatar.avatar import Avatar, PARAM_NAMES, SH_C0
from ..avatar.forest import Forest
from ..io.safe_io import loads_json


class StreamError(ValueError):
    """The bytes are not a valid stream: the header, a record or a block failed verification
    (what an HTTP download reports as "corrupt")."""


class TemplateMismatch(ValueError):
    """A valid stream made for another template than the mesh it is bound to."""


MAGIC = b"PAVS\r\n\x1a\n"
VERSION = 3  # what the writer writes
READ_VERSIONS = (1, 2, 3)  # what the reader reads (1: smallest-three rotations, 2: no coarse levels; FORMAT.md 7)
FLAG_LOSSLESS = 1
FLAG_TEMPLATE = 2
KNOWN_FLAGS = FLAG_LOSSLESS | FLAG_TEMPLATE
FIXED_HEADER = struct.Struct("<8sHHIIIHHHH16sII")
FIXED_SIZE = FIXED_HEADER.size  # 56: versions 1 and 2; version 3 adds u32 coarse_length
FIXED_SIZE_V3 = FIXED_SIZE + 4
QUANT_TABLE_SIZE = {1: 18 * 4, 2: 26 * 4, 3: 26 * 4}  # by version
# |log-scale| bound of header ranges: exp() of more overflows float32 (88.7) in a renderer; the
# writer clamps to it, readers refuse a header beyond it (FORMAT.md 3.1).
LOG_SCALE_LIMIT = 80.0
MAX_HEADER = 256 << 20
DEFAULT_BLOCK = 256
QUANT_RECORD = 23
LOSSLESS_RECORD = 73
QUANT_ROOT = 0xFFFFFF
LOSSLESS_ROOT = 0x3FFFFFFF

QUANT_DTYPE = np.dtype(
    {
        "names": ["geo", "rot", "parent", "ls", "opa", "col", "crc"],
        "formats": ["<u8", "<u4", ("u1", 3), ("u1", 3), "u1", ("u1", 3), "u1"],
        "offsets": [0, 8, 12, 15, 18, 19, 22],
        "itemsize": QUANT_RECORD,
    }
)
LOSSLESS_DTYPE = np.dtype(
    {
        "names": ["link", "split_logits", "d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc", "crc"],
        "formats": ["<u4", ("<f4", 3), ("<f4", 3), ("<f4", 3), ("<f4", 4), "<f4", ("<f4", 3), "u1"],
        "offsets": [0, 4, 16, 28, 40, 56, 60, 72],
        "itemsize": LOSSLESS_RECORD,
    }
)
# The quantised record as (possibly unaligned, overlapping) little words, one per code, so that
# every code is one load plus at most one shift or mask, vectorised over a whole record range:
# mx = u16@0 & 0xFFF, my = u16@1 >> 4, mz = u16@3 & 0xFFF, b0 = u16@4 >> 4, b1 = u16@6 & 0xFFF,
# top = u8@7 >> 4 (slot, reserved bits), r0 = u16@8 & 0x3FF, r1 = (u16@9 >> 2) & 0x3FF,
# r2 = (u16@10 >> 4) & 0x3FF, big = u8@11 >> 6 (version 1), rq = u8[4]@8 (version 2),
# parent = u32@12 & 0xFFFFFF (FORMAT.md 3.1).
_QUANT_WORDS = np.dtype(
    {
        "names": ["mx", "my", "mz", "b0", "b1", "top", "r0", "r1", "r2", "big", "rq", "p32", "ls", "opa", "col"],
        "formats": [
            "<u2",
            "<u2",
            "<u2",
            "<u2",
            "<u2",
            "u1",
            "<u2",
            "<u2",
            "<u2",
            "u1",
            ("u1", 4),
            "<u4",
            ("u1", 3),
            "u1",
            ("u1", 3),
        ],
        "offsets": [0, 1, 3, 4, 6, 7, 8, 9, 10, 11, 8, 12, 15, 18, 19],
        "itemsize": QUANT_RECORD,
    }
)
assert QUANT_DTYPE.itemsize == QUANT_RECORD and LOSSLESS_DTYPE.itemsize == LOSSLESS_RECORD


# -- checksums ----------------------------------------------------------------------------
def _make_crc8_table() -> np.ndarray:
    t = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        t = np.where(t & 0x80, (t << 1) ^ 0x07, t << 1) & 0xFF
    return t.astype(np.uint8)


_CRC8 = _make_crc8_table()


def _crc8_position_tables(k: int) -> np.ndarray:
    """[k,256] tables: CRC-8 contribution of byte value v at position j of a k-byte message.

    CRC-8 with init 0 and no final xor is linear over GF(2), so a message's CRC is the xor of
    its bytes' contributions: all positions resolve in one gather and one xor-reduction.
    """
    out = np.empty((k, 256), np.uint8)
    out[k - 1] = _CRC8  # the last byte passes through the table once
    for j in range(k - 2, -1, -1):  # each earlier byte once more per following byte
        out[j] = _CRC8[out[j + 1]]
    return out


_CRC8_POS: dict = {}


def crc8(rows) -> np.ndarray:
    """CRC-8 (poly 0x07, init 0) of each row of a [n,k] uint8 array, vectorised over rows."""
    rows = np.asarray(rows, np.uint8)
    if rows.ndim == 1:
        rows = rows[None]
    k = rows.shape[1]
    tab = _CRC8_POS.get(k)
    if tab is None:
        tab = _CRC8_POS[k] = (_crc8_position_tables(k).ravel(), np.arange(k) * 256)
    flat, offs = tab
    return np.bitwise_xor.reduce(flat[rows + offs], axis=1) if len(rows) else np.zeros(0, np.uint8)


_CRC8_INDEX: dict = {}


def crc8_indexed(rows, first_index: int) -> np.ndarray:
    """Version 3 record check: CRC-8 of u32le(record index) ‖ row, for rows of records
    first_index, first_index+1, ... By linearity (init 0, no xorout) it is the row's CRC-8
    xor the index bytes' contributions at positions 0..3 of the longer message."""
    rows = np.asarray(rows, np.uint8)
    if rows.ndim == 1:
        rows = rows[None]
    k = rows.shape[1]
    tab = _CRC8_INDEX.get(k)
    if tab is None:
        tab = _CRC8_INDEX[k] = _crc8_position_tables(k + 4)[:4].copy()
    idx = np.arange(first_index, first_index + len(rows), dtype=np.uint32)
    out = crc8(rows)
    for j in range(4):
        out ^= tab[j][(idx >> np.uint32(8 * j)) & np.uint32(0xFF)]
    return out


def _crc8_bytewise(data: bytes) -> int:
    """Reference CRC-8 of one message, byte by byte (tests, and the FORMAT.md check value)."""
    c = 0
    for b in data:
        c = int(_CRC8[c ^ b])
    return c


def template_hash(faces) -> bytes:
    """First 16 bytes of SHA-256 of the template faces as int32 little-endian [F,3]."""
    f = np.ascontiguousarray(np.asarray(faces).reshape(-1, 3), dtype="<i4")
    return hashlib.sha256(f.tobytes()).digest()[:16]


# -- decoding constants (FORMAT.md 3.1: float32 arithmetic, bit-exact in any IEEE-754 reader) --
_SQRT1_2 = 1.0 / math.sqrt(2.0)
_ROT_STEP = np.float32(2.0 * _SQRT1_2 / 1023.0)  # version 1 rotations
_ROT_LO = np.float32(-_SQRT1_2)
_OPA_ALPHA = (np.arange(256) + 0.5) / 256.0
_OPA_LUT = np.log(_OPA_ALPHA / (1.0 - _OPA_ALPHA)).astype(np.float32)
_BARY_LUT = np.log(np.maximum(np.arange(4096, dtype=np.float64), 2.0**-20) / 4095.0).astype(np.float32)
_BARY_LUT_REV = np.ascontiguousarray(_BARY_LUT[::-1])  # [s] = _BARY_LUT[4095 - s]


def quant_ranges(quant) -> dict:
    """The header's quantisation table as {field: (lo, hi)} float64 arrays: mu, ls, c (3 each)
    and, from version 2 (26 floats instead of 18), rot (4: w, x, y, z)."""
    q = np.asarray(quant, np.float64).ravel()
    if len(q) not in (18, 26):
        raise StreamError(f"quantisation table of {len(q)} floats (expected 18 or 26)")
    out = {name: (q[6 * k : 6 * k + 3], q[6 * k + 3 : 6 * k + 6]) for k, name in enumerate(("mu", "ls", "c"))}
    if len(q) == 26:
        out["rot"] = (q[18:22], q[22:26])
    return out


def quant_steps(quant) -> dict:
    """Per-field (lo, step) float32 pairs of FORMAT.md 3.1 from the header's table."""
    r = quant_ranges(quant)
    (mu_lo, mu_hi), (ls_lo, ls_hi), (c_lo, c_hi) = r["mu"], r["ls"], r["c"]
    f32 = np.float32
    out = {
        "mu": (mu_lo.astype(f32), ((mu_hi - mu_lo) / 4095.0).astype(f32)),
        "ls": (ls_lo.astype(f32), ((ls_hi - ls_lo) / 255.0).astype(f32)),
        "fdc": (((c_lo - 0.5) / SH_C0).astype(f32), ((c_hi - c_lo) / (255.0 * SH_C0)).astype(f32)),
    }
    if "rot" in r:
        lo, hi = r["rot"]
        out["rot"] = (lo.astype(f32), ((hi - lo) / 255.0).astype(f32))
    return out


def _f32_floor(x):
    """Largest float32 <= x (so a stored lo never lies above the data)."""
    x = np.asarray(x, np.float64)
    y = x.astype(np.float32)
    return np.where(y.astype(np.float64) > x, np.nextafter(y, np.float32(-np.inf)), y).astype(np.float32)


def _f32_ceil(x):
    x = np.asarray(x, np.float64)
    y = x.astype(np.float32)
    return np.where(y.astype(np.float64) < x, np.nextafter(y, np.float32(np.inf)), y).astype(np.float32)


# -- header -------------------------------------------------------------------------------
@dataclass
class StreamInfo:
    """A stream's header, plus the budget arithmetic of FORMAT.md section 6."""

    version: int
    flags: int
    header_size: int
    num_records: int
    num_template_faces: int
    record_size: int
    records_per_block: int
    level_counts: tuple
    template_hash: bytes
    quant: np.ndarray | None = field(default=None, repr=False, compare=False)  # header_crc covers it
    metadata: dict = field(default_factory=dict)
    template_faces: np.ndarray | None = field(default=None, repr=False, compare=False)
    header_crc: int = 0
    order: np.ndarray | None = field(default=None, repr=False, compare=False)
    num_coarse_levels: int = 0  # version 3: levels 0..K-1 are coarse, level K the template
    coarse_faces: np.ndarray | None = field(default=None, repr=False, compare=False)  # [C,3], grouped by level

    @property
    def num_roots(self) -> int:
        """Root records: every coarse level and the template level (records 0..num_roots-1)."""
        return int(sum(self.level_counts[: self.num_coarse_levels + 1]))

    @property
    def head_records(self) -> int:
        """Records of the first whole head: the coarsest level (the template level when there
        are no coarse levels)."""
        return int(self.level_counts[0])

    @property
    def head_bytes(self) -> int:
        """Bytes to the first whole head, header included."""
        return self.bytes_for_count(self.head_records)

    @property
    def lossless(self) -> bool:
        return bool(self.flags & FLAG_LOSSLESS)

    @property
    def template_embedded(self) -> bool:
        return bool(self.flags & FLAG_TEMPLATE)

    @property
    def block_bytes(self) -> int:
        return self.records_per_block * self.record_size + 4

    @property
    def num_blocks(self) -> int:
        return -(-self.num_records // self.records_per_block)

    @property
    def total_bytes(self) -> int:
        return self.header_size + self.num_records * self.record_size + 4 * self.num_blocks

    @property
    def num_levels(self) -> int:
        return len(self.level_counts)

    @property
    def base_bytes(self) -> int:
        """Bytes needed for the whole base level (every template face, and the coarse levels)."""
        return self.bytes_for_count(self.num_roots)

    @property
    def bytes_per_gaussian(self) -> float:
        return self.total_bytes / self.num_records

    @property
    def template_hash_hex(self) -> str:
        return self.template_hash.hex()

    def record_offset(self, i: int) -> int:
        """Byte offset of record i."""
        return self.header_size + i * self.record_size + 4 * (i // self.records_per_block)

    def count_for_bytes(self, k) -> int:
        """Records wholly contained in the first k bytes."""
        k = int(k)
        if k < self.header_size:
            return 0
        u = k - self.header_size
        S, B = self.block_bytes, self.records_per_block
        return min(self.num_records, (u // S) * B + min((u % S) // self.record_size, B))

    def count_for_percent(self, p) -> int:
        """Records wholly within the first p % of the stream's bytes: what "p %" means."""
        p = float(p)
        if not 0.0 <= p <= 100.0:
            raise ValueError(f"count_for_percent: percent must be in [0, 100], got {p}")
        return self.count_for_bytes(math.floor(p / 100.0 * self.total_bytes))

    def bytes_for_count(self, n) -> int:
        """Fewest bytes holding the first n records."""
        n = int(n)
        if not 0 <= n <= self.num_records:
            raise ValueError(f"bytes_for_count: n must be in [0, {self.num_records}], got {n}")
        if n == 0:
            return self.header_size
        return self.header_size + n * self.record_size + 4 * ((n - 1) // self.records_per_block)

    def percent_for_count(self, n) -> float:
        """Smallest percent whose budget holds n records (inverse of count_for_percent)."""
        need = self.bytes_for_count(n)
        p = 100.0 * need / self.total_bytes
        # floor(p/100*total) may land one byte short after rounding: nudge up until it holds.
        for _ in range(1000):
            if self.count_for_percent(min(p, 100.0)) >= n or p >= 100.0:
                break
            p = float(np.nextafter(p, 200.0))
        return float(min(p, 100.0))

    def level_of(self, index) -> np.ndarray:
        """Level of each stream index."""
        cum = np.cumsum(self.level_counts)
        return np.searchsorted(cum, np.asarray(index), side="right").astype(np.int8)

    def level_ends(self) -> np.ndarray:
        """Record count at the end of each level (cumulative level counts)."""
        return np.cumsum(np.asarray(self.level_counts, np.int64))

    def block_end_for_count(self, n: int) -> int:
        """Bytes up to the end of the block holding record n-1 (its CRC included)."""
        if n <= 0:
            return self.header_size
        bi = (n - 1) // self.records_per_block
        return min(self.header_size + (bi + 1) * self.block_bytes, self.total_bytes)

    def summary(self) -> dict:
        return {
            "version": self.version,
            "lossless": self.lossless,
            "records": self.num_records,
            "template_faces": self.num_template_faces,
            "levels": list(self.level_counts),
            "record_size": self.record_size,
            "records_per_block": self.records_per_block,
            "header_bytes": self.header_size,
            "total_bytes": self.total_bytes,
            "bytes_per_gaussian": self.bytes_per_gaussian,
            "base_bytes": self.base_bytes,
            "template_hash": self.template_hash_hex,
            "template_embedded": self.template_embedded,
            "coarse_levels": self.num_coarse_levels,
            "head_records": self.head_records,
            "head_bytes": self.head_bytes,
        }


StreamHeader = StreamInfo


def _encode_header(info: StreamInfo, template_blob: bytes, meta_blob: bytes, coarse_blob: bytes = b"") -> bytes:
    L = len(info.level_counts)
    v3 = info.version >= 3
    parts = [
        None,  # fixed part, filled once the size is known
        np.asarray(info.level_counts, "<u4").tobytes(),
        b"" if info.lossless else np.asarray(info.quant, "<f4").tobytes(),
        coarse_blob,
        template_blob,
        meta_blob,
    ]
    fixed = FIXED_SIZE_V3 if v3 else FIXED_SIZE
    size = fixed + 4 * L + len(parts[2]) + len(coarse_blob) + len(template_blob) + len(meta_blob) + 4
    parts[0] = FIXED_HEADER.pack(
        MAGIC,
        info.version,
        info.flags,
        size,
        info.num_records,
        info.num_template_faces,
        info.record_size,
        info.records_per_block,
        L,
        info.num_coarse_levels if v3 else 0,
        info.template_hash,
        len(meta_blob),
        len(template_blob),
    )
    if v3:
        parts[0] += struct.pack("<I", len(coarse_blob))
    body = b"".join(parts)
    crc = zlib.crc32(body)
    info.header_size = size
    info.header_crc = crc
    return body + struct.pack("<I", crc)


def _check_magic(buf, source: str) -> None:
    k = min(len(buf), len(MAGIC))
    if bytes(buf[:k]) != MAGIC[:k]:
        raise StreamError(f"{source}: not a ProgressiveAvatars stream (bad magic at offset 0: {bytes(buf[:k])!r})")


def _fixed_size(buf) -> int:
    """Bytes of the fixed header part (the version is at offset 8: 56 before version 3, 60 from it)."""
    if len(buf) >= 10 and struct.unpack_from("<H", buf, 8)[0] >= 3:
        return FIXED_SIZE_V3
    return FIXED_SIZE


def _header_size_if_known(buf, source: str):
    """header_size once the fixed part has arrived (checked), else None."""
    if len(buf) < FIXED_SIZE or len(buf) < _fixed_size(buf):
        return None
    return _parse_fixed(buf, source)["header_size"]


def _parse_fixed(buf, source: str):
    _check_magic(buf, source)
    (magic, version, flags, hsize, N, F0, R, B, L, reserved, thash, M, T) = FIXED_HEADER.unpack_from(buf, 0)
    K, CL = 0, 0  # version 3: coarse levels (offset 30, reserved before) and coarse table bytes
    if version >= 3 and version in READ_VERSIONS:
        K, reserved = reserved, 0
        CL = struct.unpack_from("<I", buf, FIXED_SIZE)[0]
    if version not in READ_VERSIONS:
        raise StreamError(
            f"{source}: stream format version {version} is not supported (this reader: "
            f"{', '.join(map(str, READ_VERSIONS))})"
        )
    if flags & ~KNOWN_FLAGS:
        raise StreamError(f"{source}: unknown header flags 0x{flags:04x} at offset 10")
    lossless = bool(flags & FLAG_LOSSLESS)
    want_R = LOSSLESS_RECORD if lossless else QUANT_RECORD
    problems = []
    if R != want_R:
        problems.append(f"record size {R} (expected {want_R})")
    if N < 1 or F0 < 1 or F0 > N:
        problems.append(f"counts N={N}, F0={F0}")
    if not lossless and N > QUANT_ROOT:
        problems.append(f"N={N} exceeds the quantised record's 24-bit parent index")
    if lossless and N > LOSSLESS_ROOT:
        problems.append(f"N={N} exceeds the lossless record's 30-bit parent index")
    if B < 1 or L < 1 or reserved != 0:
        problems.append(f"records_per_block={B}, num_levels={L}, reserved={reserved}")
    if bool(T) != bool(flags & FLAG_TEMPLATE):
        problems.append(f"template length {T} disagrees with flag bit 1")
    if K >= L or bool(K) != bool(CL):
        problems.append(f"coarse levels {K} with {L} levels and a coarse table of {CL} bytes")
    fixed = FIXED_SIZE_V3 if version >= 3 else FIXED_SIZE
    expect = fixed + 4 * L + (0 if lossless else QUANT_TABLE_SIZE[version]) + CL + T + M + 4
    if hsize != expect or hsize > MAX_HEADER:
        problems.append(f"header size {hsize} (fields imply {expect}, limit {MAX_HEADER})")
    if problems:
        raise StreamError(f"{source}: invalid stream header: " + "; ".join(problems))
    return dict(
        version=version,
        flags=flags,
        header_size=hsize,
        num_records=N,
        num_template_faces=F0,
        record_size=R,
        records_per_block=B,
        num_levels=L,
        template_hash=thash,
        M=M,
        T=T,
        K=K,
        CL=CL,
        fixed=fixed,
    )


def _parse_header(buf, source: str) -> StreamInfo:
    """Parse and verify a complete header (buf holds at least header_size bytes)."""
    f = _parse_fixed(buf, source)
    H = f["header_size"]
    stored = struct.unpack_from("<I", buf, H - 4)[0]
    actual = zlib.crc32(bytes(buf[: H - 4]))
    if stored != actual:
        raise StreamError(
            f"{source}: header checksum mismatch (stored 0x{stored:08x}, computed 0x{actual:08x}, "
            f"header bytes 0..{H - 1}): the header is corrupted"
        )
    pos = f["fixed"]
    L, K = f["num_levels"], f["K"]
    counts = np.frombuffer(bytes(buf[pos : pos + 4 * L]), "<u4").astype(np.int64)
    pos += 4 * L
    if counts[K] != f["num_template_faces"] or counts.sum() != f["num_records"] or np.any(counts < 1):
        raise StreamError(
            f"{source}: level counts {counts.tolist()} disagree with N={f['num_records']}, "
            f"F0={f['num_template_faces']} (template level {K})"
        )
    quant = None
    if not f["flags"] & FLAG_LOSSLESS:
        size = QUANT_TABLE_SIZE[f["version"]]
        quant = np.frombuffer(bytes(buf[pos : pos + size]), "<f4").astype(np.float32)
        pos += size
        ranges = quant_ranges(quant)
        if (
            not np.all(np.isfinite(quant))
            or any(np.any(lo > hi) for lo, hi in ranges.values())
            or np.any(np.abs(np.concatenate(ranges["ls"])) > LOG_SCALE_LIMIT)
        ):
            raise StreamError(
                f"{source}: invalid quantisation ranges in the header (lo > hi, not finite, or a "
                f"log-scale beyond +-{LOG_SCALE_LIMIT:g}): {quant.tolist()}"
            )
    coarse = None
    if K:
        coarse = _decode_coarse(bytes(buf[pos : pos + f["CL"]]), int(counts[:K].sum()), source)
        pos += f["CL"]
    template = None
    if f["T"]:
        blob = bytes(buf[pos : pos + f["T"]])
        pos += f["T"]
        want = 12 * f["num_template_faces"]
        try:
            d = zlib.decompressobj()
            raw = d.decompress(blob, want + 1)  # bounded: a hostile blob cannot inflate past the template
        except zlib.error as exc:
            raise StreamError(f"{source}: embedded template does not decompress: {exc}") from None
        if len(raw) != want:
            raise StreamError(f"{source}: embedded template holds {len(raw)} bytes, expected {want}")
        template = np.frombuffer(raw, "<i4").reshape(-1, 3).astype(np.int32)
        if template_hash(template) != f["template_hash"]:
            raise StreamError(f"{source}: embedded template does not match the header's template hash")
    meta = {}
    if f["M"]:
        try:
            meta = loads_json(bytes(buf[pos : pos + f["M"]]).decode("utf-8"), f"{source}: metadata")
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise StreamError(f"{source}: metadata is not valid UTF-8 JSON: {exc}") from None
        except ValueError as exc:  # nested too deeply: loads_json's message names the source
            raise StreamError(str(exc)) from None
        if not isinstance(meta, dict):
            raise StreamError(f"{source}: metadata must be a JSON object")
    if coarse is not None and template is not None and coarse.max() > template.max():
        raise StreamError(
            f"{source}: coarse triangles name vertex {coarse.max()}, the template has {template.max() + 1} vertices"
        )
    return StreamInfo(
        f["version"],
        f["flags"],
        H,
        f["num_records"],
        f["num_template_faces"],
        f["record_size"],
        f["records_per_block"],
        tuple(int(c) for c in counts),
        f["template_hash"],
        quant,
        meta,
        template,
        stored,
        num_coarse_levels=K,
        coarse_faces=coarse,
    )


def _encode_coarse(tris) -> bytes:
    """FORMAT.md 2.3: zlib of int32 LE columns (a[i] - a[i-1], b - a, c - a) of the [C,3]
    coarse table (a[-1] = 0). Rows sorted by their first vertex make small numbers."""
    t = np.asarray(tris, np.int64).reshape(-1, 3)
    a = t[:, 0]
    cols = np.concatenate([np.diff(a, prepend=0), t[:, 1] - a, t[:, 2] - a]).astype("<i4")
    return zlib.compress(cols.tobytes(), 9)


def _decode_coarse(blob: bytes, C: int, source: str) -> np.ndarray:
    want = 12 * C
    try:
        raw = zlib.decompressobj().decompress(blob, want + 1)  # bounded, as the template
    except zlib.error as exc:
        raise StreamError(f"{source}: coarse triangle table does not decompress: {exc}") from None
    if len(raw) != want:
        raise StreamError(f"{source}: coarse triangle table holds {len(raw)} bytes, expected {want} ({C} triangles)")
    cols = np.frombuffer(raw, "<i4").astype(np.int64).reshape(3, C)
    a = np.cumsum(cols[0])
    t = np.stack([a, a + cols[1], a + cols[2]], axis=1)
    if C and (t.min() < 0 or t.max() > 0x7FFFFFFF):
        raise StreamError(f"{source}: coarse triangle table holds invalid vertex indices")
    return t.astype(np.int32)


def check_template(header: StreamInfo, faces) -> None:
    """Refuse to bind a stream to a mesh whose topology is not the stream's template."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) != header.num_template_faces:
        raise TemplateMismatch(
            f"template mismatch: the stream was made for {header.num_template_faces} template faces, "
            f"the mesh has faces of shape {faces.shape}"
        )
    h = template_hash(faces)
    if h != header.template_hash:
        raise TemplateMismatch(
            f"template mismatch: the mesh's topology hash {h.hex()} differs from the stream's "
            f"{header.template_hash.hex()} (same face count, different faces)"
        )
    if header.coarse_faces is not None and len(header.coarse_faces) and header.coarse_faces.max() > faces.max():
        raise TemplateMismatch(
            f"template mismatch: the stream's coarse triangles name vertex {header.coarse_faces.max()}, "
            f"the mesh has {faces.max() + 1} vertices"
        )


def read_header(source) -> StreamInfo:
    """The header of a stream (path or bytes); raises if it is incomplete or invalid."""
    name = "<bytes>" if isinstance(source, (bytes, bytearray, memoryview)) else os.fspath(source)
    if isinstance(source, (bytes, bytearray, memoryview)):
        buf = memoryview(source).cast("B")
    else:
        with open(name, "rb") as fh:
            buf = fh.read(FIXED_SIZE)
            if len(buf) >= FIXED_SIZE:
                buf += fh.read(_fixed_size(buf) - FIXED_SIZE)
                H = _header_size_if_known(buf, name)
                if H is not None:
                    buf += fh.read(H - len(buf))
    _check_magic(buf, name)
    H = _header_size_if_known(buf, name)
    if H is None or len(buf) < H:
        raise StreamError(f"{name}: truncated inside the stream header ({len(buf)} bytes)")
    return _parse_header(buf, name)


# -- stream order -------------------------------------------------------------------------
ROOT_ORDERS = ("forest", "spatial", "importance", "both", "auto")


def root_keys(forest: Forest, how: str = "forest", importance=None, vertices=None):
    """Sort key (ascending) of each root inside its level, or None for the forest's order.

    forest: as the forest holds them (trained avatars: spread-out, core/avatar/coarse.py; older ones:
    template order). spatial: spread-out order of the roots' centroids on `vertices` (a rest
    pose). importance: descending importance. both: the spatial order's dyadic blocks (the
    first 1, 1, 2, 4, 8, ... roots: each block spread over the head) with every block sorted by
    descending importance. auto: spatial in level 0 (nothing renders below it: a prefix must
    not leave holes), importance in the later root levels (a whole head is already there:
    the most visible faces first); measured in docs/BENCHMARKS.md (issue 16)."""
    if how not in ROOT_ORDERS:
        raise ValueError(f"root order must be one of {ROOT_ORDERS}, got {how!r}")
    if how == "forest":
        return None
    R = forest.num_roots
    lv = forest.level[:R]
    if how in ("spatial", "both", "auto"):
        rank = np.arange(R, dtype=np.float64)
        if vertices is not None:
            from ..avatar.coarse import centroids, spread_order

            cen = centroids(vertices, forest.root_faces)
            for level in np.unique(lv):  # per root level
                ids = np.flatnonzero(lv == level)
                rank[ids[spread_order(cen[ids])]] = np.arange(len(ids))
        else:  # the forest's order within each level
            for level in np.unique(lv):
                ids = np.flatnonzero(lv == level)
                rank[ids] = np.arange(len(ids))
        if how == "spatial":
            return rank
        if how == "auto" and importance is None:
            return rank
    if importance is None:
        raise ValueError(f"root order {how!r} needs the faces' importance")
    imp = np.asarray(importance, np.float64)[:R]
    top = max(float(imp.max()), 1e-300) if R else 1.0
    if how == "importance":
        return -imp
    if how == "auto":  # level 0 by its spatial rank (all keys < 0), later levels by importance
        return np.where(lv == 0, rank - R, -imp)
    return np.floor(np.log2(rank + 1.0)) + 0.999 * (1.0 - np.clip(imp / top, 0.0, 1.0))


def stream_order(forest: Forest, importance=None, root_key=None) -> np.ndarray:
    """Permutation (new position -> old face): the roots level by level (coarse levels, then
    the template level), each by ascending `root_key` (default: the forest's order), then each
    further level by descending importance, ties by face index. Parents precede children
    since levels do."""
    N = forest.num_faces
    if importance is None:
        key = np.zeros(N)
    else:
        key = np.asarray(importance, np.float64).reshape(-1)
        if len(key) != N:
            raise ValueError(f"stream_order: importance has {len(key)} values for {N} faces")
        if not np.all(np.isfinite(key)):
            raise ValueError("stream_order: importance contains NaN or inf")
    R = forest.num_roots
    key = -key
    key[:R] = 0.0 if root_key is None else np.asarray(root_key, np.float64)[:R]
    idx = np.arange(N)
    return np.lexsort((idx, key, forest.level)).astype(np.int64)


# -- writer -------------------------------------------------------------------------------
def _quantize_records(
    av: Avatar, bary: np.ndarray, quant: np.ndarray, version: int = VERSION, root_ref=None
) -> np.ndarray:
    N = av.num_gaussians
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
    slot = np.maximum(av.forest.slot.astype(np.int64), 0).astype(np.uint64)
    rec["geo"] = (
        mu[:, 0]
        | (mu[:, 1] << np.uint64(12))
        | (mu[:, 2] << np.uint64(24))
        | (b0.astype(np.uint64) << np.uint64(36))
        | (b1.astype(np.uint64) << np.uint64(48))
        | (slot << np.uint64(60))
    )

    rc = codes(_unit_quaternions(av.d_rot), *q["rot"], 256).astype(np.uint32)
    rec["rot"] = rc[:, 0] | (rc[:, 1] << np.uint32(8)) | (rc[:, 2] << np.uint32(16)) | (rc[:, 3] << np.uint32(24))

    parent = np.where(av.forest.parent >= 0, av.forest.parent, QUANT_ROOT).astype(np.uint32)
    if version >= 3:  # roots name their row of the coarse + template table
        parent[: len(root_ref)] = root_ref
    rec["parent"] = np.stack([parent & 0xFF, (parent >> 8) & 0xFF, (parent >> 16) & 0xFF], 1).astype(np.uint8)
    rec["ls"] = codes(av.d_log_scale.astype(np.float64), *q["ls"], 256).astype(np.uint8)
    alpha = 1.0 / (1.0 + np.exp(-av.opacity_logit.astype(np.float64)))
    rec["opa"] = np.minimum(np.floor(alpha * 256.0), 255).astype(np.uint8)
    c = 0.5 + SH_C0 * av.f_dc.astype(np.float64)
    rec["col"] = codes(c, *q["c"], 256).astype(np.uint8)
    raw = rec.view(np.uint8).reshape(N, QUANT_RECORD)
    rec["crc"] = crc8_indexed(raw[:, : QUANT_RECORD - 1], 0) if version >= 3 else crc8(raw[:, : QUANT_RECORD - 1])
    return rec


def _lossless_records(av: Avatar, version: int = VERSION, root_ref=None) -> np.ndarray:
    N = av.num_gaussians
    rec = np.zeros(N, LOSSLESS_DTYPE)
    parent = np.where(av.forest.parent >= 0, av.forest.parent, LOSSLESS_ROOT).astype(np.uint32)
    if version >= 3:
        parent[: len(root_ref)] = root_ref
    rec["link"] = parent | (np.maximum(av.forest.slot, 0).astype(np.uint32) << np.uint32(30))
    rec["split_logits"] = av.forest.split_logits
    for name in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc"):
        rec[name] = getattr(av, name)
    if not np.all(np.isfinite(av.forest.split_logits)):
        raise ValueError("write_stream: split logits contain NaN or inf")
    raw = rec.view(np.uint8).reshape(N, LOSSLESS_RECORD)
    rec["crc"] = crc8_indexed(raw[:, : LOSSLESS_RECORD - 1], 0) if version >= 3 else crc8(raw[:, : LOSSLESS_RECORD - 1])
    return rec


def _unit_quaternions(d_rot) -> np.ndarray:
    """Rotations as coded (FORMAT.md 3.1): unit length, w >= 0 (q and -q are one rotation;
    this halves w's range), a zero quaternion read as the identity."""
    r = np.asarray(d_rot, np.float64)
    n = np.linalg.norm(r, axis=1, keepdims=True)
    r = np.where(n > 0, r / np.where(n > 0, n, 1.0), np.array([1.0, 0, 0, 0]))
    return np.where(r[:, :1] < 0, -r, r)


def _quant_table(av: Avatar) -> np.ndarray:
    c = 0.5 + SH_C0 * av.f_dc.astype(np.float64)
    c_lo = np.maximum(c.min(0), 0.0)
    c_hi = np.maximum(c.max(0), c_lo)
    r = _unit_quaternions(av.d_rot)
    lim = LOG_SCALE_LIMIT
    parts = [
        av.d_mu.min(0),
        av.d_mu.max(0),
        np.clip(av.d_log_scale.min(0), -lim, lim),
        np.clip(av.d_log_scale.max(0), -lim, lim),
        c_lo,
        c_hi,
        r.min(0),
        r.max(0),
    ]
    table = []
    for i, p in enumerate(parts):
        table.append(_f32_floor(p) if i % 2 == 0 else _f32_ceil(p))
    table = np.concatenate(table).astype(np.float32)
    table[6:12] = np.clip(table[6:12], -lim, lim)  # (outward rounding must not pass the limit)
    return table


def write_stream(
    path,
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
) -> StreamInfo:
    """Write `avatar` as a stream (atomically). Returns its header; `.order` maps stream index
    to the avatar's face index. Records carry the DC colour only: an avatar with higher SH
    bands is refused unless ``drop_sh`` (then the metadata says which degree was dropped).

    Roots (coarse levels, template level) go level by level in `root_order` (root_keys):
    default "auto" when rest-pose `vertices` are given, else the forest's order. The avatar's
    training settings (meta "config") stay out of the header (they are in the run folder):
    time to the first whole head counts.
    ``version=2`` writes the previous format (no coarse levels, roots in template order)."""
    forest = avatar.forest
    if avatar.sh_degree and not drop_sh:
        raise ValueError(
            f"write_stream: the avatar has SH degree {avatar.sh_degree}; stream records carry the "
            "DC colour only (docs/FORMAT.md). Pass drop_sh=True (export.py --drop-sh) to stream "
            "its view-independent colour, or export a PLY to keep every band"
        )
    N = forest.num_faces
    if not 1 <= int(records_per_block) <= 0xFFFF:
        raise ValueError(f"write_stream: records_per_block must be in [1, 65535], got {records_per_block}")
    limit = QUANT_ROOT if quantize else LOSSLESS_ROOT
    if N > limit:
        raise ValueError(f"write_stream: {N} Gaussians exceed this record type's limit of {limit}")
    if version not in (2, VERSION):
        raise ValueError(f"write_stream: can write versions 2 and {VERSION}, not {version}")
    C, K = forest.num_coarse, forest.num_coarse_levels
    if forest.num_roots != C + len(forest.template_faces):
        raise ValueError(
            f"write_stream: the avatar holds {forest.num_roots} of its {C + len(forest.template_faces)} "
            "roots (a prefix); streams start from every root"
        )
    if root_order is None:
        root_order = "auto" if vertices is not None else "forest"
    if version == 2:
        if K or not np.array_equal(forest.root_ref, np.arange(forest.num_roots)) or root_order != "forest":
            raise ValueError("write_stream: version 2 has no coarse levels and keeps roots in template order")
    order = stream_order(forest, importance, root_keys(forest, root_order, importance, vertices))
    f2 = forest.reorder(order)
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
    root_ref = row_of[f2.root_ref]
    av = Avatar(f2, *(getattr(avatar, n)[order] for n in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc")))

    meta = {k: v for k, v in dict(avatar.meta or {}).items() if k not in ("stream", "config")}
    if avatar.sh_degree:
        meta["sh_degree_dropped"] = avatar.sh_degree
    meta.update(metadata or {})
    try:
        meta_blob = json.dumps(meta, sort_keys=True, allow_nan=False).encode("utf-8") if meta else b""
    except (TypeError, ValueError) as exc:
        raise ValueError(f"write_stream: metadata must be JSON-serialisable: {exc}") from None
    tmpl = np.ascontiguousarray(forest.template_faces, "<i4")
    template_blob = zlib.compress(tmpl.tobytes(), 9) if embed_template else b""
    flags = (0 if quantize else FLAG_LOSSLESS) | (FLAG_TEMPLATE if embed_template else 0)
    level_counts = tuple(int(c) for c in f2.level_counts())
    if quantize:
        quant = _quant_table(av)
        recs = _quantize_records(av, f2.barycentrics(), quant, version, root_ref)
    else:
        quant = None
        recs = _lossless_records(av, version, root_ref)
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
    )
    header = _encode_header(info, template_blob, meta_blob, _encode_coarse(coarse_rows) if K else b"")
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
    with atomic_open(path) as fh:
        fh.write(data)
    info.order = order
    return info


def encode_stream(avatar: Avatar, importance=None, **kwargs) -> bytes:
    """The stream as bytes (writes through a temporary file so there is one writer)."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "s.pavs")
        write_stream(p, avatar, importance, **kwargs)
        with open(p, "rb") as fh:
            return fh.read()


# -- reader -------------------------------------------------------------------------------
class _Grow:
    """A reader-private growing array (first axis): amortised doubling capped at `limit`
    rows, starting at _FIRST_CAP rows; zero-initialised (calloc) when `fill` is 0."""

    def __init__(self, shape_tail, dtype, limit, fill=None):
        self.tail, self.dtype, self.fill, self.limit = tuple(shape_tail), dtype, fill, max(int(limit), 1)
        self.data = np.empty((0,) + self.tail, dtype)

    def reserve(self, n) -> np.ndarray:
        """data with at least n rows (existing rows kept)."""
        cap = len(self.data)
        if n <= cap:
            return self.data
        new = max(n, min(max(2 * cap, _FIRST_CAP), self.limit))
        if self.fill is None:
            arr = np.empty((new,) + self.tail, self.dtype)
        else:
            arr = np.zeros((new,) + self.tail, self.dtype)  # calloc: no pass over the memory
        arr[:cap] = self.data
        self.data = arr
        return arr


# Records per vectorised run in checking and decoding: large enough that numpy's per-call
# overhead vanishes, small enough that temporaries stay in cache and are reused by the C
# allocator instead of being page-faulted in afresh (which cost more than the arithmetic).
_RUN = 32768
# First allocation of the reader's growing arrays, in rows (records, or table entries): the
# whole stream at once when it is not huge (one allocation, no regrowth and copies while a
# stream arrives in small chunks); beyond, amortised doubling. Untouched capacity costs no
# memory on the usual virtual-memory systems.
_FIRST_CAP = 1 << 20

_COLUMNS = (  # name, row shape, dtype; widest first so every column stays aligned
    ("parent", (), np.int64),
    ("split_logits", (3,), np.float32),
    ("d_mu", (3,), np.float32),
    ("d_log_scale", (3,), np.float32),
    ("d_rot", (4,), np.float32),
    ("opacity_logit", (), np.float32),
    ("f_dc", (3,), np.float32),
    ("slot", (), np.int8),
)


def _carve(spec, n):
    """Arrays of n rows for each (name, row shape, dtype) of spec, carved from ONE allocation.

    One large block is reused by the C allocator from one decode to the next, whereas many
    medium-sized ones tend to be returned to the OS and page-faulted in again, which cost
    more than the decoding itself."""
    sizes = [n * int(np.prod(tail, dtype=np.int64)) * np.dtype(dt).itemsize for _, tail, dt in spec]
    buf = np.empty(sum(sizes), np.uint8)
    out, off = {}, 0
    for (name, tail, dt), size in zip(spec, sizes):
        out[name] = buf[off : off + size].view(dt).reshape((n,) + tuple(tail))
        off += size
    return out


class _Columns:
    """The reader's per-record outputs (parent, slot, decoded parameters) in one allocation,
    grown by amortised doubling up to `limit` rows. `hand_out()` gives the current arrays
    away (an Avatar keeps views of them and may edit them): the next `reserve()` then starts
    a fresh allocation with nothing valid, which the reader fills again from its verified
    bytes (never from the handed-out arrays)."""

    def __init__(self, limit):
        self.limit = max(int(limit), 1)
        self.cap = 0
        self.cols = _carve(_COLUMNS, 0)
        self.valid = {name: 0 for name, _, _ in _COLUMNS}  # rows holding data, per column
        self.shared = False

    def reserve(self, n) -> dict:
        if n <= self.cap and not self.shared:
            return self.cols
        new = self.cap if n <= self.cap else max(n, min(max(2 * self.cap, _FIRST_CAP), self.limit))
        cols = _carve(_COLUMNS, new)
        if self.shared:
            self.valid = dict.fromkeys(self.valid, 0)
        else:
            for name, arr in self.cols.items():
                k = self.valid[name]
                cols[name][:k] = arr[:k]
        self.cols, self.cap, self.shared = cols, new, False
        return cols

    def hand_out(self, name, n) -> np.ndarray:
        self.shared = True
        return self.cols[name][:n]


def _block_seeds(header_crc: int, n: int) -> np.ndarray:
    """zlib.crc32(u32(header_crc) ‖ u32(i)) for every block index i < n, vectorised: over
    messages of a fixed length the CRC is affine over GF(2), so the CRC of index i is the
    CRC of index 0 xor one constant per set bit of i."""
    pre = struct.pack("<I", header_crc)
    base = zlib.crc32(pre + bytes(4))
    i = np.arange(n, dtype=np.uint32)
    out = np.full(n, base, np.uint32)
    for k in range(max(n - 1, 0).bit_length()):  # per bit of the index
        d = np.uint32(zlib.crc32(pre + (1 << k).to_bytes(4, "little")) ^ base)
        out ^= ((i >> np.uint32(k)) & np.uint32(1)) * d
    return out


class StreamReader:
    """Incremental decoder: feed bytes as they arrive; every whole, verified record becomes a
    Gaussian. Work per feed is proportional to the new bytes (plus at most one block)."""

    def __init__(self, template_faces=None, *, source: str = "<stream>"):
        self.source = source
        self._given_template = None if template_faces is None else np.asarray(template_faces, np.int32)
        self._pending = bytearray()  # the header so far, then the bytes of the current incomplete block
        self.header: StreamInfo | None = None
        self._n = 0  # available records
        self._decoded = 0  # records decoded into parameter arrays
        self._block = 0  # index of the first block whose CRC-32 is not yet verified
        self.error: Exception | None = None
        self.bytes_received = 0
        self._lut_cache = None

    # -- public state --------------------------------------------------------------------
    @property
    def num_gaussians(self) -> int:
        return self._n

    @property
    def complete(self) -> bool:
        return self.header is not None and self._block >= self.header.num_blocks

    @property
    def template_faces(self):
        if self._given_template is not None:
            return self._given_template
        return None if self.header is None else self.header.template_faces

    # -- feeding --------------------------------------------------------------------------
    def feed(self, chunk) -> int:
        """Add bytes; returns how many Gaussians became available."""
        if self.error is not None:
            raise StreamError(f"{self.source}: the reader already failed: {self.error}")
        mv = memoryview(chunk).cast("B")
        if len(mv) == 0:
            return 0
        before = self._n
        self.bytes_received += len(mv)
        if self.complete:
            self._fail(
                StreamError(
                    f"{self.source}: {len(mv)} unexpected bytes after the end of the stream "
                    f"(offset {self.bytes_received - len(mv)})"
                )
            )
        try:
            if self.header is None:
                buf = mv
                if self._pending:  # (checked in place: no copy per call while the header trickles in)
                    self._pending += mv
                    buf = self._pending
                _check_magic(buf, self.source)
                H = _header_size_if_known(buf, self.source)
                if H is None or len(buf) < H:
                    if buf is mv:
                        self._pending = bytearray(mv)
                    return 0
                if buf is self._pending:
                    buf = bytes(buf)
                header = _parse_header(buf, self.source)
                self._start(header)
                self._pending = bytearray()
                mv = memoryview(buf)[header.header_size :]
            if len(mv):
                self._consume(mv)
        except ValueError as exc:
            self._fail(exc)
        return self._n - before

    def _fail(self, exc):
        self.error = exc
        raise exc

    def _block_error(self, bi, nbytes):
        h = self.header
        o = h.header_size + bi * h.block_bytes
        return StreamError(
            f"{self.source}: block {bi} (records {bi * h.records_per_block}.."
            f"{min(h.num_records, (bi + 1) * h.records_per_block) - 1}, bytes "
            f"{o}..{o + nbytes + 3}) fails its CRC-32: corrupted"
        )

    def _seeds(self, first, m) -> list:
        """CRC-32 state after u32(header_crc) ‖ u32(block index), for blocks first..first+m-1."""
        if self._seed_table is not None:
            return self._seed_table[first : first + m].tolist()
        return [zlib.crc32(bi.to_bytes(4, "little"), self._crc_seed) for bi in range(first, first + m)]

    def _block_crc(self, bi, data) -> int:
        return zlib.crc32(data, self._seeds(bi, 1)[0])

    def _consume(self, mv):
        """Verify what mv (the bytes after those already fed) completes: the pending block,
        whole blocks straight from mv (no copy of the chunk besides its records), the short
        last block, then the whole records of the new incomplete block by their CRC-8. All
        newly verified records then pass the structural checks in one batch."""
        h = self.header
        B, R, S, N = h.records_per_block, h.record_size, h.block_bytes, h.num_records
        nblocks = h.num_blocks
        a = self._n  # first record not yet available
        end = a  # records [a, end) are checksum-verified and copied into self._raw
        err = None
        raw = self._raw
        raw.reserve(min(N, self._block * B + (len(self._pending) + len(mv)) // R))  # once per feed
        pend = self._pending
        if pend:  # complete the pending block from the head of mv
            bi = self._block
            nrec = min(B, N - bi * B)
            need = nrec * R + 4 - len(pend)
            if len(mv) < need:
                pend += mv
                mv = mv[:0]
            else:
                pend += mv[:need]
                mv = mv[need:]
                blk = bytes(pend)
                pend.clear()
                if self._block_crc(bi, blk[: nrec * R]) != int.from_bytes(blk[nrec * R :], "little"):
                    err = self._block_error(bi, nrec * R)
                else:
                    i0 = bi * B
                    lo = max(end, i0)
                    dst = raw.reserve(i0 + nrec)
                    dst[lo : i0 + nrec] = np.frombuffer(blk, np.uint8, (i0 + nrec - lo) * R, (lo - i0) * R).reshape(
                        -1, R
                    )
                    end = i0 + nrec
                    self._block = bi + 1
        if err is None and not pend:
            # Whole full-size blocks straight from mv: one CRC-32 per block, one copy for all.
            bi = self._block
            full_left = nblocks - bi - (1 if N % B else 0)
            m = min(max(full_left, 0), len(mv) // S)
            if m:
                BR = B * R
                blocks = np.frombuffer(mv, np.uint8, m * S).reshape(m, S)
                stored = blocks[:, BR:].copy().view("<u4").ravel().tolist()
                crc32 = zlib.crc32
                crcs = [crc32(mv[o : o + BR], seed) for o, seed in zip(range(0, m * S, S), self._seeds(bi, m))]
                good = m
                if crcs != stored:
                    good = next(j for j in range(m) if crcs[j] != stored[j])
                    err = self._block_error(bi + good, BR)
                if good:
                    i0 = bi * B
                    dst = raw.reserve(i0 + good * B)
                    dst[i0 : i0 + good * B].reshape(good, B, R)[...] = blocks[:good, :BR].reshape(good, B, R)
                    end = i0 + good * B
                    self._block = bi + good
                del blocks
                mv = mv[m * S :]
            # The short last block, if it is complete.
            bi = self._block
            if err is None and bi == nblocks - 1 and N % B:
                nrec = N - bi * B
                size = nrec * R + 4
                if len(mv) >= size:
                    if self._block_crc(bi, mv[: nrec * R]) != int.from_bytes(mv[nrec * R : size], "little"):
                        err = self._block_error(bi, nrec * R)
                    else:
                        i0 = bi * B
                        dst = raw.reserve(N)
                        dst[i0:N] = np.frombuffer(mv, np.uint8, nrec * R).reshape(nrec, R)
                        end = N
                        self._block = nblocks
                        mv = mv[size:]
            if err is None:
                if self._block >= nblocks:
                    if len(mv):
                        err = StreamError(
                            f"{self.source}: {len(mv)} unexpected bytes after the end of the stream "
                            f"(offset {h.total_bytes})"
                        )
                else:
                    pend += mv
        if err is None and pend and self._block < nblocks:
            # Whole records of the incomplete block: each verified by its own CRC-8.
            bi = self._block
            i0 = bi * B
            hi = i0 + min(len(pend) // R, B, N - i0)
            lo = max(end, i0)
            if hi > lo:
                dst = raw.reserve(hi)
                rows = dst[lo:hi]
                rows[...] = np.frombuffer(bytes(pend[(lo - i0) * R : (hi - i0) * R]), np.uint8).reshape(-1, R)
                ok = (crc8_indexed(rows[:, :-1], lo) if h.version >= 3 else crc8(rows[:, :-1])) == rows[:, -1]
                if not ok.all():
                    bad = lo + int(np.argmin(ok))
                    err = StreamError(
                        f"{self.source}: record {bad} (offset {h.record_offset(bad)}, block "
                        f"{bad // B}) fails its CRC-8: corrupted"
                    )
                    hi = bad
                end = max(end, hi)
        if end > a:
            k, problem = self._check(a, end)
            self._n = a + k
            if problem is not None:
                raise StreamError(f"{self.source}: {problem} at offset {h.record_offset(a + k)}")
        if err is not None:
            raise err

    def _start(self, header: StreamInfo):
        if self._given_template is not None:
            check_template(header, self._given_template)
        self.header = header
        R = header.record_size
        N = header.num_records
        self._crc_seed = zlib.crc32(struct.pack("<I", header.header_crc))
        self._seed_table = _block_seeds(header.header_crc, header.num_blocks) if header.num_blocks <= 1 << 20 else None
        # Every decoded value is finite (so the Avatar need not scan for NaN/inf): lossless
        # floats are checked per record; quantised ones are affine in bounded codes.
        self._finite = header.lossless or bool(np.all(np.abs(header.quant) <= 1e30))
        self._raw = _Grow((R,), np.uint8, N)  # verified record bytes (decoding is lazy)
        self._child = _Grow((), np.int32, 3 * N, fill=0)  # 1 + record index per parent*3 + slot; N < 2^30
        self._level_starts = np.concatenate([[0], header.level_ends()]).astype(np.int64)
        self._starts_list = [int(x) for x in self._level_starts]
        self._cols = _Columns(N)
        # Root records: versions 1-2 the template faces in template order; version 3 every
        # coarse level and the template level, each root naming its row of the root table.
        self._nroots = header.num_roots if header.version >= 3 else header.num_template_faces
        self._root_ref = _Grow((), np.int64, self._nroots)
        self._root_claim = _Grow((), np.int32, self._nroots, fill=0)

    def _check(self, i0: int, i1: int):
        """_check_range over cache-sized runs of records (temporaries stay small and reused)."""
        self._reserve_cols(i1)
        self._child.reserve(3 * i1)
        for c0 in range(i0, i1, _RUN):
            c1 = min(i1, c0 + _RUN)
            k, problem = self._check_range(c0, c1)
            if problem is not None:
                return c0 - i0 + k, problem
        return i1 - i0, None

    def _check_range(self, i0: int, i1: int):
        """Structural rules of FORMAT.md section 3 for the checksum-verified records i0..i1-1
        (in self._raw), vectorised over the batch; stores their parent and slot and claims
        their (parent, slot). Returns (how many records from i0 pass, problem or None)."""
        h = self.header
        n = i1 - i0
        rows, rec, par, slt = self._structure(i0, i1, self._cols.cols)
        if h.lossless:
            bad = ~np.all(np.isfinite(rows[:, 4:72].copy().view("<f4")), axis=1)  # finite floats
            bad |= slt == 3  # two link bits: slot 3 is possible, and invalid
            root_val = LOSSLESS_ROOT
        else:
            bad = slt >= 3  # slot 3 or a reserved bit set (slt holds all four top bits here)
            s = np.right_shift(rec["b0"], np.uint16(4))
            s += rec["b1"] & np.uint16(0xFFF)
            bad |= s > np.uint16(4095)  # beta0 + beta1 <= 4095
            root_val = QUANT_ROOT
        nr = max(0, min(n, self._nroots - i0))  # records of this batch that must be roots
        starts = self._starts_list
        if nr and h.version < 3:
            bad[:nr] |= (par[:nr] != root_val) | (slt[:nr] != 0)
        elif nr:
            # A root names a row of the root table in its own level's row range (the table's
            # rows are grouped like the root records: coarse levels, then the template).
            bad[:nr] |= slt[:nr] != 0
            for lv in range(bisect.bisect_right(starts, i0) - 1, bisect.bisect_right(starts, i0 + nr - 1)):
                x, y = max(starts[lv], i0) - i0, min(starts[lv + 1], i0 + nr) - i0
                off = np.subtract(par[x:y], starts[lv])
                bad[x:y] |= off.view(np.uint64) >= np.uint64(starts[lv + 1] - starts[lv])
        # A non-root's parent lies in the previous level's index range (so before the child).
        l_first = bisect.bisect_right(starts, i0 + nr) - 1
        l_last = bisect.bisect_right(starts, i1 - 1) - 1
        for lv in range(max(l_first, 1, h.num_coarse_levels + 1), l_last + 1):  # per level this batch touches
            x, y = max(starts[lv], i0) - i0, min(starts[lv + 1], i1) - i0
            off = np.subtract(par[x:y], starts[lv - 1])
            bad[x:y] |= off.view(np.uint64) >= np.uint64(starts[lv] - starts[lv - 1])
        k, problem = n, None
        if bad.any():
            k = int(np.argmax(bad))
            problem = f"record {i0 + k} is structurally invalid (parent/slot/level/root marker/reserved bits/values)"
        # (parent, slot) must be unique: scatter the record indices, read them back.
        if k > nr:
            keys = par[nr:k] * 3
            keys += slt[nr:k]
            ids = np.arange(i0 + nr + 1, i0 + k + 1, dtype=np.int32)  # stored as index + 1 (0: free)
            child = self._child.reserve(3 * (i0 + k))
            old = child.take(keys)
            child[keys] = ids
            if old.max() > 0 or (child.take(keys) != ids).any():
                # The offender is a record whose key an earlier one (any batch) already holds.
                first = np.zeros(len(keys), bool)
                first[np.unique(keys, return_index=True)[1]] = True
                k = nr + int(np.argmax((old > 0) | ~first))
                problem = f"record {i0 + k} reuses the child slot of an earlier record"
                # The scatter above also wrote the refused record and those after it: put the
                # table back and claim only the kept records' slots, so the kept prefix's
                # forest keeps every child link (the duplicate overwrote its earlier twin's).
                child[keys] = old
                child[keys[: k - nr]] = ids[: k - nr]
        if h.version >= 3 and min(k, nr):
            # Each root row at most once: scatter, read back (as the child slots above).
            m = min(k, nr)
            refs = par[:m].copy()
            ids = np.arange(i0 + 1, i0 + m + 1, dtype=np.int32)
            claim = self._root_claim.reserve(self._nroots)
            old = claim.take(refs)
            claim[refs] = ids
            if old.max() > 0 or (claim.take(refs) != ids).any():
                first = np.zeros(m, bool)
                first[np.unique(refs, return_index=True)[1]] = True
                k = int(np.argmax((old > 0) | ~first))
                problem = f"record {i0 + k} names a root triangle an earlier record already holds"
            self._root_ref.reserve(i0 + m)[i0 : i0 + min(k, m)] = refs[: min(k, m)]
        if nr:
            par[:nr] = -1
            slt[:nr] = -1
        self._cols.valid["parent"] = self._cols.valid["slot"] = i0 + k
        return k, problem

    def _reserve_cols(self, n) -> dict:
        """Output columns for n records, owned by the reader. After a hand-out they are fresh:
        parent/slot of the available records are derived again from the verified bytes, and
        the parameters will be decoded again."""
        c = self._cols
        if n <= c.cap and not c.shared:
            return c.cols
        was_shared = c.shared
        cols = c.reserve(n)
        if was_shared:
            self._decoded = 0
            for c0 in range(0, self._n, _RUN):
                self._structure(c0, min(self._n, c0 + _RUN), cols)
            nr = min(self._n, self._nroots)
            cols["parent"][:nr] = -1
            cols["slot"][:nr] = -1
            c.valid["parent"] = c.valid["slot"] = self._n
        return cols

    def _structure(self, i0, i1, cols):
        """parent and slot columns of records i0..i1-1 from their bytes;
        roots are left as stored (the caller checks and marks them). Returns the rows, the
        quantised record view (None when lossless) and the two column slices."""
        rows = self._raw.data[i0:i1]
        par, slt = cols["parent"][i0:i1], cols["slot"][i0:i1]
        if self.header.lossless:
            link = rows[:, :4].copy().view("<u4")[:, 0]
            np.bitwise_and(link, np.uint32(LOSSLESS_ROOT), out=par)
            np.right_shift(link, np.uint32(30), out=slt, casting="unsafe")
            rec = None
        else:
            rec = rows.view(_QUANT_WORDS)[:, 0]
            np.bitwise_and(rec["p32"], np.uint32(QUANT_ROOT), out=par)
            np.right_shift(rec["top"], np.uint8(4), out=slt, casting="unsafe")
        return rows, rec, par, slt

    def _record_offset(self, i) -> int:
        return self.header.record_offset(int(i))

    # -- decoding -------------------------------------------------------------------------
    def _decode(self):
        """Decode the parameters of all available records (lazily: feed() only verifies),
        straight into the output columns; every operation runs over all new records."""
        b = self._n
        cols = self._reserve_cols(b)  # (may reset _decoded after a hand-out)
        a = self._decoded
        if b > a:
            raw = self._raw.data[a:b]
            out = {name: cols[name][a:b] for name in PARAM_NAMES + ("split_logits",)}
            if self.header.lossless:
                rec = raw.view(LOSSLESS_DTYPE)[:, 0]
                for name, dst in out.items():
                    dst[...] = rec[name]
            else:
                scratch = _decode_scratch(min(_RUN, b - a))
                for c0 in range(0, b - a, _RUN):  # cache-sized runs: small, reused temporaries
                    _decode_quantised(
                        raw[c0 : c0 + _RUN], {k: v[c0 : c0 + _RUN] for k, v in out.items()}, self._steps, scratch
                    )
        for name in PARAM_NAMES + ("split_logits",):
            self._cols.valid[name] = b
        self._decoded = b

    @property
    def _steps(self):
        if self._lut_cache is None:
            self._lut_cache = quant_steps(self.header.quant)
        return self._lut_cache

    def arrays(self, n=None) -> dict:
        """Decoded arrays of the first n available records (views; do not modify)."""
        self._decode()
        n = self._n if n is None else max(0, min(int(n), self._n))
        cols = self._reserve_cols(n)
        return {name: cols[name][:n] for name in ("split_logits",) + PARAM_NAMES + ("parent", "slot")}

    def avatar(self, n=None) -> Avatar | None:
        """An Avatar of the first n available Gaussians (all if None), faces in stream order;
        None when no record is available yet. The avatar owns its arrays: the reader hands its
        decoded columns over and copies them only if it has to write to them again."""
        if self.header is None or self._n == 0:
            return None
        n = self._n if n is None else max(0, min(int(n), self._n))
        if n == 0:
            return None
        tmpl = self.template_faces
        if tmpl is None:
            raise ValueError(
                f"{self.source}: the stream does not embed its template; pass template_faces "
                f"(a mesh with topology hash {self.header.template_hash_hex})"
            )
        self._decode()
        h = self.header
        c = self._cols
        forest = self._forest(tmpl, n)
        meta = dict(h.metadata)
        meta["stream"] = {
            "records": n,
            "total_records": h.num_records,
            "base_complete": n >= self._nroots,
            "head_complete": n >= h.head_records,
            "coarse_levels": h.num_coarse_levels,
            "lossless": h.lossless,
            "template_hash": h.template_hash_hex,
            "bytes": h.bytes_for_count(n),
            "total_bytes": h.total_bytes,
        }
        params = [c.hand_out(name, n) for name in PARAM_NAMES]
        if self._finite:
            # Verified record by record: no second validation pass (the format carries SH degree 0).
            return Avatar.from_verified(forest, dict(zip(PARAM_NAMES, params)), meta)
        return Avatar(forest, *params, meta=meta)

    def _forest(self, tmpl, n) -> Forest:
        """The forest of the first n records, from the structure _check verified."""
        h = self.header
        nroot = min(n, self._nroots)
        arr = _carve((("children", (3,), np.int64), ("root", (), np.int64), ("level", (), np.int8)), n)
        children, root, level = arr["children"], arr["root"], arr["level"]
        np.subtract(self._child.reserve(3 * n)[: 3 * n], 1, out=children.reshape(-1))
        if n < h.num_records:
            children[children >= n] = -1  # children that are not part of the prefix
        root[:nroot] = np.arange(nroot)
        parent = self._cols.hand_out("parent", n)
        starts = self._level_starts
        for lv in range(len(starts) - 1):  # per level
            x, y = int(starts[lv]), min(int(starts[lv + 1]), n)
            if x >= y:
                break
            level[x:y] = lv
            if x >= self._nroots:  # (root levels: each root is its own root)
                np.take(root, parent[x:y], out=root[x:y])
        if h.version >= 3:
            root_ref = self._root_ref.data[:nroot].copy()
        else:
            root_ref = np.arange(nroot, dtype=np.int64)
        K = h.num_coarse_levels
        coarse = h.coarse_faces if K else np.zeros((0, 3), np.int32)
        return Forest.from_verified(  # _check verified every rule Forest._derive enforces
            np.asarray(tmpl, np.int32),
            parent,
            self._cols.hand_out("slot", n),
            self._cols.hand_out("split_logits", n),
            children,
            level,
            root,
            coarse_faces=coarse,
            coarse_counts=tuple(h.level_counts[:K]),
            root_ref=root_ref,
        )


def _decode_scratch(n) -> dict:
    """Contiguous work rows for _decode_quantised over runs of up to n records (allocated once
    per decode: fresh large allocations would page-fault on every run)."""
    return {
        "f": np.empty((6, n), np.float32),
        "e": np.empty((4, n), np.float32),
        "t16": np.empty(n, np.uint16),
        "ix": np.empty((2, n), np.intp),
        "zero": np.zeros(n, np.float32),
    }


def _decode_quantised(raw, out, steps, scratch):
    """FORMAT.md 3.1 for records raw [n,23] into the float32 columns of `out`, in float32
    arithmetic as specified (products and sums separately rounded). Every operation is one
    whole-column pass (1-D, so numpy's inner loops run over all records, never over 3).
    Codes are first cast into a contiguous float32 row and the arithmetic runs there: numpy's
    mixed-type and strided loops are 2-3x slower, so each output column is written once, by
    the last operation."""
    rec = raw.view(_QUANT_WORDS)[:, 0]
    n = len(rec)
    mul, add, take = np.multiply, np.add, np.take
    m12 = np.uint16(0xFFF)
    f = scratch["f"][:, :n]
    t16 = scratch["t16"][:n]
    ix, ix2 = scratch["ix"][:, :n]
    a = f[0]
    # positions (12-bit affine codes)
    lo, step = steps["mu"]
    mu = out["d_mu"]
    for k, (op, field, arg) in enumerate(
        ((np.bitwise_and, "mx", m12), (np.right_shift, "my", np.uint16(4)), (np.bitwise_and, "mz", m12))
    ):
        a[...] = op(rec[field], arg, out=t16)
        mul(a, step[k], out=a)
        add(a, lo[k], out=mu[:, k])
    # split logits: beta0, beta1 and beta2 = 4095 - beta0 - beta1 through the log table
    # (The checks admitted only records with beta0 + beta1 <= 4095, so every index is in the
    # table and mode="wrap" returns what "clip" would; gathering into a contiguous row and
    # copying it into the strided column is faster than either mode gathering in place.)
    sl = out["split_logits"]
    g = f[4]
    np.right_shift(rec["b0"], np.uint16(4), out=ix)
    take(_BARY_LUT, ix, out=g, mode="wrap")
    sl[:, 0] = g
    ix2[...] = np.bitwise_and(rec["b1"], m12, out=t16)
    take(_BARY_LUT, ix2, out=g, mode="wrap")
    sl[:, 1] = g
    ix += ix2
    take(_BARY_LUT_REV, ix, out=g, mode="wrap")
    sl[:, 2] = g
    # log-scales, colours and (version 2) rotations w x y z: 8-bit affine codes
    affine8 = [("d_log_scale", "ls", "ls"), ("f_dc", "col", "fdc")]
    if "rot" in steps:
        affine8.append(("d_rot", "rq", "rot"))
    else:
        _decode_rotation_v1(rec, out["d_rot"], f, t16, scratch)
    for name, field, key in affine8:
        lo, step = steps[key]
        codes = rec[field]
        dst = out[name]
        for k in range(len(lo)):
            a[...] = codes[:, k]
            mul(a, step[k], out=a)
            add(a, lo[k], out=dst[:, k])
    # opacity (table)
    ix[...] = rec["opa"]
    take(_OPA_LUT, ix, out=out["opacity_logit"], mode="wrap")  # u8 codes: always in the table


def _decode_rotation_v1(rec, q, f, t16, scratch):
    """Version 1 rotations (FORMAT.md 7): the three smallest components (10 bit each), the
    largest from the unit norm, placed at the index the record names."""
    n = len(rec)
    f32 = np.float32
    mul, add = np.multiply, np.add
    m10 = np.uint16(0x3FF)
    v0, v1, v2, w, t, u = f
    for v, field, shift in ((v0, "r0", 0), (v1, "r1", 2), (v2, "r2", 4)):
        np.right_shift(rec[field], np.uint16(shift), out=t16)
        v[...] = np.bitwise_and(t16, m10, out=t16)
        mul(v, _ROT_STEP, out=v)
    f[:3] += _ROT_LO
    mul(v0, v0, out=w)
    mul(v1, v1, out=t)
    w += t
    mul(v2, v2, out=t)
    w += t
    np.subtract(f32(1), w, out=w)
    np.maximum(w, scratch["zero"][:n], out=w)  # (numpy 1.26 runs max(array, scalar) unvectorised: 5x slower)
    np.sqrt(w, out=w)
    # Place: slot `big` takes w, the others v0, v1, v2 in order. Selecting by multiplying with
    # 0/1 masks is exact here (x·1 = x, x·0 = ±0, x + ±0 = x; all values finite, none -0,
    # w >= 0) and several times faster than np.where.
    big = np.right_shift(rec["big"], np.uint8(6))
    e = scratch["e"][:, :n]
    for j in range(4):
        np.equal(big, np.uint8(j), out=e[j])
    e0, e1, e2, e3 = e
    mul(w, e0, out=t)  # big == 0 ? w : v0
    np.subtract(f32(1), e0, out=u)
    mul(v0, u, out=u)
    add(t, u, out=q[:, 0])
    mul(v0, e0, out=t)  # big == 0 ? v0 : big == 1 ? w : v1
    mul(w, e1, out=u)
    t += u
    add(e2, e3, out=u)
    mul(v1, u, out=u)
    add(t, u, out=q[:, 1])
    add(e0, e1, out=t)  # big <= 1 ? v1 : big == 2 ? w : v2
    mul(v1, t, out=t)
    mul(w, e2, out=u)
    t += u
    mul(v2, e3, out=u)
    add(t, u, out=q[:, 2])
    mul(w, e3, out=t)  # big == 3 ? w : v2
    np.subtract(f32(1), e3, out=u)
    mul(v2, u, out=u)
    add(t, u, out=q[:, 3])


def read_stream(source, *, percent=None, max_bytes=None, max_gaussians=None, template_faces=None) -> Avatar | None:
    """Decode a stream (path or bytes) to an Avatar whose faces are in stream order.

    A budget (percent of the stream's bytes, bytes, or Gaussians; the smallest wins) picks a
    prefix. A truncated source yields its whole verified records; None if there are none.
    """
    is_bytes = isinstance(source, (bytes, bytearray, memoryview))
    name = "<bytes>" if is_bytes else os.fspath(source)
    reader = StreamReader(template_faces, source=name)
    if is_bytes:
        data = memoryview(source).cast("B")
        fh = None
    else:
        fh = open(name, "rb")
    try:
        head = data[:FIXED_SIZE] if is_bytes else fh.read(FIXED_SIZE)
        _check_magic(head, name)
        if len(head) < FIXED_SIZE:
            return None
        if _fixed_size(head) > FIXED_SIZE:
            more = _fixed_size(head) - FIXED_SIZE
            head = bytes(head) + bytes(data[FIXED_SIZE : FIXED_SIZE + more] if is_bytes else fh.read(more))
        H = _header_size_if_known(head, name)
        if H is None:
            return None
        rest = data[len(head) : H] if is_bytes else fh.read(H - len(head))
        if len(head) + len(rest) < H:
            return None
        reader.feed(bytes(head) + bytes(rest))
        h = reader.header
        n = h.num_records
        if percent is not None:
            n = min(n, h.count_for_percent(percent))
        if max_bytes is not None:
            if max_bytes < 0:
                raise ValueError(f"read_stream: max_bytes must be >= 0, got {max_bytes}")
            n = min(n, h.count_for_bytes(max_bytes))
        if max_gaussians is not None:
            if max_gaussians < 0:
                raise ValueError(f"read_stream: max_gaussians must be >= 0, got {max_gaussians}")
            n = min(n, int(max_gaussians))
        # Read through the end of the block holding the last wanted record so the block CRC-32
        # (not only the CRC-8s) verifies it; a full read also catches trailing garbage.
        end = h.total_bytes if n == h.num_records else h.block_end_for_count(n)
        if is_bytes:
            body = data[H:end] if n < h.num_records else data[H:]
        else:
            body = fh.read(end - H) if n < h.num_records else fh.read()
        if len(body):
            reader.feed(body)
    finally:
        if fh is not None:
            fh.close()
    return reader.avatar(n)
