"""The progressive avatar stream's format (numpy only: runs in Blender): constants, record
layouts, checksums, the header (StreamInfo, encode, parse and verify) and template checks.

The byte layout is specified once, in docs/FORMAT.md; this package implements it. In short:
a checksummed header, then fixed-size records (one Gaussian per forest face) in stream order
(level 0 in template order, then each level by descending importance), grouped in blocks
that end with a CRC-32, each record also ending with a CRC-8 so that every whole record of a
truncated stream can be verified. The writer is in writer.py, the stream order in order.py,
the incremental reader in reader.py and the quantised records' decoding in decode.py.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import zlib
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from ..avatar.avatar import SH_C0
from ..io.safe_io import loads_json


class StreamError(ValueError):
    """The bytes are not a valid stream: the header, a record or a block failed verification
    (what an HTTP download reports as "corrupt")."""


class TemplateMismatch(ValueError):
    """A valid stream made for another template than the mesh it is bound to."""


MAGIC = b"PAVS\r\n\x1a\n"
VERSION = 5  # what the writer writes
# what the reader reads (1: smallest-three rotations, 2: no coarse levels, 3: no exceptions table,
# 4: every root before any other record; FORMAT.md 7)
READ_VERSIONS = (1, 2, 3, 4, 5)
FLAG_LOSSLESS = 1
FLAG_TEMPLATE = 2
FLAG_STAND_INS = 4  # the coarse faces are stand-ins; the coarse table adds their retire positions (FORMAT.md 2.4)
FLAG_BACKDROP = 8  # with bit 2: a retired stand-in stays, composited behind every other Gaussian (FORMAT.md 2.4)
KNOWN_FLAGS = FLAG_LOSSLESS | FLAG_TEMPLATE | FLAG_STAND_INS | FLAG_BACKDROP
FIXED_HEADER = struct.Struct("<8sHHIIIHHHH16sII")
FIXED_SIZE = FIXED_HEADER.size  # 56: versions 1 and 2; version 3 adds u32 coarse_length
FIXED_SIZE_V3 = FIXED_SIZE + 4
FIXED_SIZE_V4 = FIXED_SIZE_V3 + 4  # version 4 adds u32 num_exceptions
FIXED_SIZE_MAX = FIXED_SIZE_V4
QUANT_TABLE_SIZE = {1: 18 * 4, 2: 26 * 4, 3: 26 * 4, 4: 26 * 4, 5: 26 * 4}  # by version
# |log-scale| bound of header ranges: exp() of more overflows float32 (88.7) in a renderer; the
# writer clamps to it, readers refuse a header beyond it (FORMAT.md 3.1).
LOG_SCALE_LIMIT = 80.0
# |value| bound of version 4 header ranges and exception values for positions and colours: the
# affine decode (lo + code * step in float32) then stays far from float32 overflow (FORMAT.md 3.2).
RANGE_LIMIT = 1e30
# Version 4 exceptions table (FORMAT.md 3.2): per entry u32 record index, u8 component, f32 value.
EXCEPTION_SIZE = 9
# The 13 components an exception can carry, in table order: d_mu x y z, d_log_scale x y z,
# f_dc r g b, d_rot w x y z (the unit quaternion with w >= 0 the record codes).
EXCEPTION_COMPONENTS = tuple(
    (name, k) for name, w in (("d_mu", 3), ("d_log_scale", 3), ("f_dc", 3), ("d_rot", 4)) for k in range(w)
)


def max_exceptions(num_records: int) -> int:
    """Most exception entries a version 4 stream of num_records records may carry."""
    return max(16, int(num_records) // 1000)


MAX_HEADER = 256 << 20
# Most template faces (F0) and most coarse triangles (C) a header may claim, refused before the
# embedded template or coarse table is inflated: a few kilobytes of zlib can claim gigabytes.
# FLAME has ~10k faces; 2^24 faces is a 192 MiB template (FORMAT.md 2.1, 2.3).
MAX_ROOT_FACES = 1 << 24
# Most levels: Forest.level is int8, so levels 0..127 (FORMAT.md 2.1).
MAX_LEVELS = 128
DEFAULT_BLOCK = 256
QUANT_RECORD = 23
LOSSLESS_RECORD = 73
QUANT_ROOT = 0xFFFFFF
LOSSLESS_ROOT = 0x3FFFFFFF
# Version 5 root marker (FORMAT.md 3): quantised records set geo bit 62; lossless records
# carry slot value 3.
QUANT_ROOT_BIT = 62
LOSSLESS_ROOT_SLOT = 3

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


_CODE_MAX = {"mu": 4095, "ls": 255, "fdc": 255, "rot": 255}


def _decodes_finite(quant) -> bool:
    """Whether every code of every range decodes (FORMAT.md 3.1, float32) to a finite value.
    Steps are >= 0 (lo <= hi), so the decode is monotone in the code and its extremes are codes
    0 and max. Version 4 bounds every range far below overflow; a version 3 range near
    float32's limits (c_hi = 3e38: f_dc = c/C0) would decode to infinity after every record
    had verified, in an Avatar that cannot name the file."""
    with np.errstate(over="ignore", invalid="ignore"):
        for key, (lo, step) in quant_steps(quant).items():
            if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(lo + np.float32(_CODE_MAX[key]) * step))):
                return False
    return True


def percent_bytes(p, total) -> int:
    """⌊p/100 · total⌋ exactly (FORMAT.md 6) for the float ``p`` as given: in floating point,
    29 % of 47,200 bytes came out 13,687.999... and floored one byte (and so one record) short."""
    return int(Fraction(float(p)) * int(total) // 100)


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
    # flag bit 2: per coarse row, the stream index at which that stand-in makes way (it renders
    # in a prefix of n records while n <= retire; FORMAT.md 2.4)
    coarse_retire: np.ndarray | None = field(default=None, repr=False, compare=False)
    # version 4: (record index int64 [E], component uint8 [E], value float32 [E]), sorted by
    # (index, component); values replace the decoded component exactly (FORMAT.md 3.2)
    exceptions: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def num_exceptions(self) -> int:
        return 0 if self.exceptions is None else len(self.exceptions[0])

    @property
    def num_roots(self) -> int:
        """Root records: every coarse level and the template level (records 0..num_roots-1
        before version 5)."""
        return int(sum(self.level_counts[: self.num_coarse_levels + 1]))

    @property
    def lead_records(self) -> int:
        """Records that open the stream level by level, every one a root: version 5 the
        coarse levels (the template level when there are none), after which roots and other
        records may mix; versions 3-4 every root; versions 1-2 the template level."""
        if self.version >= 5:
            return int(sum(self.level_counts[: max(self.num_coarse_levels, 1)]))
        if self.version >= 3:
            return self.num_roots
        return int(self.num_template_faces)

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
    def backdrop(self) -> bool:
        return bool(self.flags & FLAG_BACKDROP)

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
        """Bytes of the base level's records (every template face, and the coarse levels); from
        version 5 the template faces may be spread over the stream, so this is their size,
        not the prefix that holds them."""
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
        return self.count_for_bytes(percent_bytes(p, self.total_bytes))

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
        """Level of each stream index of a level-by-level stream (version 5: of the lead's
        records only; the others' levels come from their parents)."""
        cum = np.cumsum(self.level_counts)
        return np.searchsorted(cum, np.asarray(index), side="right").astype(np.int8)

    def level_ends(self) -> np.ndarray:
        """Cumulative level counts: where each level ends in a level-by-level stream (version 5:
        in the lead; each level's root-table rows in every version)."""
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
            "exceptions": self.num_exceptions,
        }


StreamHeader = StreamInfo


def _encode_exceptions(exceptions) -> bytes:
    """FORMAT.md 3.2: the E record indices (u32), then the E components (u8), then the E values (f32)."""
    idx, comp, val = exceptions
    return np.asarray(idx, "<u4").tobytes() + np.asarray(comp, "u1").tobytes() + np.asarray(val, "<f4").tobytes()


def _encode_header(info: StreamInfo, template_blob: bytes, meta_blob: bytes, coarse_blob: bytes = b"") -> bytes:
    L = len(info.level_counts)
    v3 = info.version >= 3
    v4 = info.version >= 4
    E = info.num_exceptions
    parts = [
        None,  # fixed part, filled once the size is known
        np.asarray(info.level_counts, "<u4").tobytes(),
        b"" if info.lossless else np.asarray(info.quant, "<f4").tobytes(),
        _encode_exceptions(info.exceptions) if E else b"",
        coarse_blob,
        template_blob,
        meta_blob,
    ]
    assert v4 or not E
    fixed = FIXED_SIZE_V4 if v4 else FIXED_SIZE_V3 if v3 else FIXED_SIZE
    size = fixed + sum(len(p) for p in parts[1:]) + 4
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
    if v4:
        parts[0] += struct.pack("<I", E)
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
    """Bytes of the fixed header part (the version is at offset 8: 56 before version 3, 60 in
    version 3, 64 from version 4)."""
    if len(buf) >= 10:
        version = struct.unpack_from("<H", buf, 8)[0]
        if version >= 4:
            return FIXED_SIZE_V4
        if version == 3:
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
    K, CL, E = 0, 0, 0  # version 3: coarse levels (offset 30, reserved before) and coarse table bytes
    if version >= 3 and version in READ_VERSIONS:
        K, reserved = reserved, 0
        CL = struct.unpack_from("<I", buf, FIXED_SIZE)[0]
    if version >= 4 and version in READ_VERSIONS:  # version 4: exceptions table entries
        E = struct.unpack_from("<I", buf, FIXED_SIZE_V3)[0]
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
    if F0 > MAX_ROOT_FACES:
        problems.append(f"{F0} template faces (at most {MAX_ROOT_FACES})")
    if not lossless and N > QUANT_ROOT:
        problems.append(f"N={N} exceeds the quantised record's 24-bit parent index")
    if lossless and N > LOSSLESS_ROOT:
        problems.append(f"N={N} exceeds the lossless record's 30-bit parent index")
    if B < 1 or L < 1 or L > MAX_LEVELS or reserved != 0:
        problems.append(f"records_per_block={B}, num_levels={L} (at most {MAX_LEVELS}), reserved={reserved}")
    if bool(T) != bool(flags & FLAG_TEMPLATE):
        problems.append(f"template length {T} disagrees with flag bit 1")
    if K >= L or bool(K) != bool(CL):
        problems.append(f"coarse levels {K} with {L} levels and a coarse table of {CL} bytes")
    if flags & FLAG_STAND_INS and not K:
        problems.append("flag bit 2 (coarse stand-ins) without coarse levels")
    if flags & FLAG_BACKDROP and not flags & FLAG_STAND_INS:
        problems.append("flag bit 3 (stand-ins stay as a backdrop) without flag bit 2 (coarse stand-ins)")
    if E and (lossless or E > max_exceptions(N)):
        problems.append(f"{E} exceptions (at most {max_exceptions(N)} for N={N}, none in a lossless stream)")
    fixed = FIXED_SIZE_V4 if version >= 4 else FIXED_SIZE_V3 if version == 3 else FIXED_SIZE
    expect = fixed + 4 * L + (0 if lossless else QUANT_TABLE_SIZE[version]) + EXCEPTION_SIZE * E + CL + T + M + 4
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
        E=E,
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
            or (f["version"] >= 4 and np.any(np.abs(quant) > RANGE_LIMIT))
            or not _decodes_finite(quant)
        ):
            raise StreamError(
                f"{source}: invalid quantisation ranges in the header (lo > hi, not finite, a "
                f"log-scale beyond +-{LOG_SCALE_LIMIT:g}, from version 4 a value beyond +-{RANGE_LIMIT:g}, "
                f"or a range whose codes decode beyond float32): {quant.tolist()}"
            )
    exceptions = None
    if f["E"]:
        exceptions = _parse_exceptions(bytes(buf[pos : pos + EXCEPTION_SIZE * f["E"]]), f["num_records"], source)
        pos += EXCEPTION_SIZE * f["E"]
    coarse, retire = None, None
    if K:
        if counts[:K].sum() > MAX_ROOT_FACES:
            raise StreamError(
                f"{source}: {int(counts[:K].sum())} coarse triangles (at most {MAX_ROOT_FACES}); refused before inflating"
            )
        stand_ins = bool(f["flags"] & FLAG_STAND_INS)
        coarse, retire = _decode_coarse(bytes(buf[pos : pos + f["CL"]]), int(counts[:K].sum()), source, stand_ins)
        pos += f["CL"]
        lead = int(counts[:K].sum())
        if retire is not None and len(retire) and (retire.min() < lead or retire.max() >= f["num_records"]):
            raise StreamError(
                f"{source}: coarse stand-in retire positions must lie in [{lead}, {f['num_records']}) "
                f"(after the coarse levels, within the stream), got {retire.min()}..{retire.max()}"
            )
    template = None
    if f["T"]:
        blob = bytes(buf[pos : pos + f["T"]])
        pos += f["T"]
        raw = _inflate_exact(blob, 12 * f["num_template_faces"], f"{source}: embedded template")
        template = np.frombuffer(raw, "<i4").reshape(-1, 3).astype(np.int32)
        if template_hash(template) != f["template_hash"]:
            raise StreamError(f"{source}: embedded template does not match the header's template hash")
        if template.min() < 0:
            raise StreamError(f"{source}: embedded template holds a negative vertex index ({template.min()})")
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
        coarse_retire=retire,
        exceptions=exceptions,
    )


def _parse_exceptions(blob: bytes, N: int, source: str):
    """The version 4 exceptions table (FORMAT.md 3.2), checked: record indices below N,
    components below 13, (index, component) strictly increasing, values finite and within the
    limits the writer keeps (log-scales +-LOG_SCALE_LIMIT, the rest +-RANGE_LIMIT)."""
    E = len(blob) // EXCEPTION_SIZE
    idx = np.frombuffer(blob, "<u4", E).astype(np.int64)
    comp = np.frombuffer(blob, "u1", E, 4 * E).copy()
    val = np.frombuffer(blob, "<f4", E, 5 * E).astype(np.float32)
    key = idx * len(EXCEPTION_COMPONENTS) + comp
    is_ls = (comp >= 3) & (comp < 6)
    limit = np.where(is_ls, LOG_SCALE_LIMIT, RANGE_LIMIT)
    problems = []
    if np.any(idx >= N) or np.any(comp >= len(EXCEPTION_COMPONENTS)):
        problems.append("a record index or component out of range")
    if np.any(np.diff(key) <= 0):
        problems.append("entries not in strictly increasing (record, component) order")
    if not np.all(np.isfinite(val)) or np.any(np.abs(val.astype(np.float64)) > limit):
        problems.append(f"a value not finite or beyond its limit (log-scale {LOG_SCALE_LIMIT:g}, else {RANGE_LIMIT:g})")
    if problems:
        raise StreamError(f"{source}: invalid exceptions table in the header: " + "; ".join(problems))
    return idx, comp, val


def _encode_coarse(tris, retire=None) -> bytes:
    """FORMAT.md 2.3: zlib of int32 LE columns (a[i] - a[i-1], b - a, c - a) of the [C,3]
    coarse table (a[-1] = 0), and with stand-ins a fourth column, each row's retire position.
    Rows sorted by their first vertex make small numbers."""
    t = np.asarray(tris, np.int64).reshape(-1, 3)
    a = t[:, 0]
    cols = [np.diff(a, prepend=0), t[:, 1] - a, t[:, 2] - a]
    if retire is not None:
        cols.append(np.asarray(retire, np.int64).reshape(-1))
    return zlib.compress(np.concatenate(cols).astype("<i4").tobytes(), 9)


def _inflate_exact(blob: bytes, want: int, what: str, counted: str = "") -> bytes:
    """The ``want`` bytes a zlib stream (RFC 1950) holds, refused unless the stream is complete
    (its Adler-32 present and right) and fills ``blob`` exactly (FORMAT.md 2.2). Bounded: a
    hostile blob cannot inflate past ``want`` + 1 bytes."""
    d = zlib.decompressobj()
    try:
        raw = d.decompress(blob, want + 1)
    except zlib.error as exc:
        raise StreamError(f"{what} does not decompress: {exc}") from None
    if len(raw) != want:
        raise StreamError(f"{what} holds {len(raw)} bytes, expected {want}{counted}")
    if not d.eof:
        raise StreamError(f"{what}: its zlib stream is cut short (no end or Adler-32 checksum)")
    if d.unused_data:
        raise StreamError(f"{what}: {len(d.unused_data)} bytes after the end of its zlib stream")
    return raw


def _decode_coarse(blob: bytes, C: int, source: str, stand_ins: bool = False):
    """(triangles [C,3] int32, retire positions [C] int64 with stand-ins else None)."""
    raw = _inflate_exact(blob, (16 if stand_ins else 12) * C, f"{source}: coarse triangle table", f" ({C} triangles)")
    cols = np.frombuffer(raw, "<i4").astype(np.int64).reshape(-1, C)
    a = np.cumsum(cols[0])
    t = np.stack([a, a + cols[1], a + cols[2]], axis=1)
    if C and (t.min() < 0 or t.max() > 0x7FFFFFFF):
        raise StreamError(f"{source}: coarse triangle table holds invalid vertex indices")
    return t.astype(np.int32), (cols[3].copy() if stand_ins else None)


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
