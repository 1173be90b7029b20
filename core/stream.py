"""The progressive avatar stream: importance order, writer, reader (numpy only: runs in Blender).

The byte layout is specified once, in docs/FORMAT.md; this module implements it. In short:
a checksummed header, then fixed-size records (one Gaussian per forest face) in stream order
(level 0 in template order, then each level by descending importance), grouped in blocks
that end with a CRC-32, each record also ending with a CRC-8 so that every whole record of a
truncated stream can be verified.

Decoding is vectorised: records are viewed with a structured dtype (np.frombuffer) and
decoded with lookup tables; the only Python loops run per block (CRC-32) or per byte
column of a record (CRC-8 of an incomplete block), never per record.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

from .avatar import SH_C0, Avatar
from .forest import Forest

MAGIC = b"PAVS\r\n\x1a\n"
VERSION = 1
FLAG_LOSSLESS = 1
FLAG_TEMPLATE = 2
KNOWN_FLAGS = FLAG_LOSSLESS | FLAG_TEMPLATE
FIXED_HEADER = struct.Struct("<8sHHIIIHHHH16sII")
FIXED_SIZE = FIXED_HEADER.size  # 56
QUANT_TABLE_SIZE = 18 * 4
MAX_HEADER = 256 << 20
DEFAULT_BLOCK = 256
QUANT_RECORD = 23
LOSSLESS_RECORD = 73
QUANT_ROOT = 0xFFFFFF
LOSSLESS_ROOT = 0x3FFFFFFF

QUANT_DTYPE = np.dtype({
    "names": ["geo", "rot", "parent", "ls", "opa", "col", "crc"],
    "formats": ["<u8", "<u4", ("u1", 3), ("u1", 3), "u1", ("u1", 3), "u1"],
    "offsets": [0, 8, 12, 15, 18, 19, 22],
    "itemsize": QUANT_RECORD,
})
# The same record seen as aligned-width words for fast decoding: the halves of `geo`, and the
# u24 parent read as a u32 whose top byte (the first log-scale code) is masked off.
_QUANT_VIEW = np.dtype({
    "names": ["g_lo", "g_hi", "rot", "p32", "ls", "opa", "col"],
    "formats": ["<u4", "<u4", "<u4", "<u4", ("u1", 3), "u1", ("u1", 3)],
    "offsets": [0, 4, 8, 12, 15, 18, 19],
    "itemsize": QUANT_RECORD,
})
LOSSLESS_DTYPE = np.dtype({
    "names": ["link", "split_logits", "d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc", "crc"],
    "formats": ["<u4", ("<f4", 3), ("<f4", 3), ("<f4", 3), ("<f4", 4), "<f4", ("<f4", 3), "u1"],
    "offsets": [0, 4, 16, 28, 40, 56, 60, 72],
    "itemsize": LOSSLESS_RECORD,
})
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
_ROT_STEP = np.float32(2.0 * _SQRT1_2 / 1023.0)
_ROT_LO = np.float32(-_SQRT1_2)
_OPA_ALPHA = (np.arange(256) + 0.5) / 256.0
_OPA_LUT = np.log(_OPA_ALPHA / (1.0 - _OPA_ALPHA)).astype(np.float32)
_BARY_LUT = np.log(np.maximum(np.arange(4096, dtype=np.float64), 2.0 ** -20) / 4095.0).astype(np.float32)
_ROT_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], np.intp)


def quant_steps(quant) -> dict:
    """Per-field (lo, step) float32 pairs of FORMAT.md 3.1 from the header's 18 floats."""
    q = np.asarray(quant, np.float64).reshape(3, 2, 3)
    lo, hi = q[:, 0], q[:, 1]
    return {
        "mu": (lo[0].astype(np.float32), ((hi[0] - lo[0]) / 4095.0).astype(np.float32)),
        "ls": (lo[1].astype(np.float32), ((hi[1] - lo[1]) / 255.0).astype(np.float32)),
        "fdc": (((lo[2] - 0.5) / SH_C0).astype(np.float32), ((hi[2] - lo[2]) / (255.0 * SH_C0)).astype(np.float32)),
    }


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
        """Bytes needed for the whole base level (every template face)."""
        return self.bytes_for_count(self.num_template_faces)

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
            "version": self.version, "lossless": self.lossless, "records": self.num_records,
            "template_faces": self.num_template_faces, "levels": list(self.level_counts),
            "record_size": self.record_size, "records_per_block": self.records_per_block,
            "header_bytes": self.header_size, "total_bytes": self.total_bytes,
            "bytes_per_gaussian": self.bytes_per_gaussian, "base_bytes": self.base_bytes,
            "template_hash": self.template_hash_hex, "template_embedded": self.template_embedded,
        }


StreamHeader = StreamInfo


def _encode_header(info: StreamInfo, template_blob: bytes, meta_blob: bytes) -> bytes:
    L = len(info.level_counts)
    parts = [
        None,  # fixed part, filled once the size is known
        np.asarray(info.level_counts, "<u4").tobytes(),
        b"" if info.lossless else np.asarray(info.quant, "<f4").tobytes(),
        template_blob,
        meta_blob,
    ]
    size = FIXED_SIZE + 4 * L + len(parts[2]) + len(template_blob) + len(meta_blob) + 4
    parts[0] = FIXED_HEADER.pack(MAGIC, VERSION, info.flags, size, info.num_records, info.num_template_faces,
                                 info.record_size, info.records_per_block, L, 0, info.template_hash,
                                 len(meta_blob), len(template_blob))
    body = b"".join(parts)
    crc = zlib.crc32(body)
    info.header_size = size
    info.header_crc = crc
    return body + struct.pack("<I", crc)


def _check_magic(buf, source: str) -> None:
    k = min(len(buf), len(MAGIC))
    if bytes(buf[:k]) != MAGIC[:k]:
        raise ValueError(f"{source}: not a ProgressiveAvatars stream (bad magic at offset 0: {bytes(buf[:k])!r})")


def _parse_fixed(buf, source: str):
    _check_magic(buf, source)
    (magic, version, flags, hsize, N, F0, R, B, L, reserved, thash, M, T) = FIXED_HEADER.unpack_from(buf, 0)
    if version != VERSION:
        raise ValueError(f"{source}: stream format version {version} is not supported (this reader: {VERSION})")
    if flags & ~KNOWN_FLAGS:
        raise ValueError(f"{source}: unknown header flags 0x{flags:04x} at offset 10")
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
    expect = FIXED_SIZE + 4 * L + (0 if lossless else QUANT_TABLE_SIZE) + T + M + 4
    if hsize != expect or hsize > MAX_HEADER:
        problems.append(f"header size {hsize} (fields imply {expect}, limit {MAX_HEADER})")
    if problems:
        raise ValueError(f"{source}: invalid stream header: " + "; ".join(problems))
    return dict(version=version, flags=flags, header_size=hsize, num_records=N, num_template_faces=F0,
                record_size=R, records_per_block=B, num_levels=L, template_hash=thash, M=M, T=T)


def _parse_header(buf, source: str) -> StreamInfo:
    """Parse and verify a complete header (buf holds at least header_size bytes)."""
    f = _parse_fixed(buf, source)
    H = f["header_size"]
    stored = struct.unpack_from("<I", buf, H - 4)[0]
    actual = zlib.crc32(bytes(buf[: H - 4]))
    if stored != actual:
        raise ValueError(f"{source}: header checksum mismatch (stored 0x{stored:08x}, computed 0x{actual:08x}, "
                         f"header bytes 0..{H - 1}): the header is corrupted")
    pos = FIXED_SIZE
    L = f["num_levels"]
    counts = np.frombuffer(bytes(buf[pos: pos + 4 * L]), "<u4").astype(np.int64)
    pos += 4 * L
    if counts[0] != f["num_template_faces"] or counts.sum() != f["num_records"] or np.any(counts < 1):
        raise ValueError(f"{source}: level counts {counts.tolist()} disagree with N={f['num_records']}, "
                         f"F0={f['num_template_faces']}")
    quant = None
    if not f["flags"] & FLAG_LOSSLESS:
        quant = np.frombuffer(bytes(buf[pos: pos + QUANT_TABLE_SIZE]), "<f4").astype(np.float32)
        pos += QUANT_TABLE_SIZE
        lo, hi = quant.reshape(3, 2, 3)[:, 0], quant.reshape(3, 2, 3)[:, 1]
        if not np.all(np.isfinite(quant)) or np.any(lo > hi):
            raise ValueError(f"{source}: invalid quantisation ranges in the header: {quant.tolist()}")
    template = None
    if f["T"]:
        blob = bytes(buf[pos: pos + f["T"]])
        pos += f["T"]
        want = 12 * f["num_template_faces"]
        try:
            d = zlib.decompressobj()
            raw = d.decompress(blob, want + 1)  # bounded: a hostile blob cannot inflate past the template
        except zlib.error as exc:
            raise ValueError(f"{source}: embedded template does not decompress: {exc}") from None
        if len(raw) != want:
            raise ValueError(f"{source}: embedded template holds {len(raw)} bytes, expected {want}")
        template = np.frombuffer(raw, "<i4").reshape(-1, 3).astype(np.int32)
        if template_hash(template) != f["template_hash"]:
            raise ValueError(f"{source}: embedded template does not match the header's template hash")
    meta = {}
    if f["M"]:
        try:
            meta = json.loads(bytes(buf[pos: pos + f["M"]]).decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{source}: metadata is not valid UTF-8 JSON: {exc}") from None
        if not isinstance(meta, dict):
            raise ValueError(f"{source}: metadata must be a JSON object")
    return StreamInfo(f["version"], f["flags"], H, f["num_records"], f["num_template_faces"], f["record_size"],
                      f["records_per_block"], tuple(int(c) for c in counts), f["template_hash"], quant, meta,
                      template, stored)


def check_template(header: StreamInfo, faces) -> None:
    """Refuse to bind a stream to a mesh whose topology is not the stream's template."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) != header.num_template_faces:
        raise ValueError(f"template mismatch: the stream was made for {header.num_template_faces} template faces, "
                         f"the mesh has faces of shape {faces.shape}")
    h = template_hash(faces)
    if h != header.template_hash:
        raise ValueError(f"template mismatch: the mesh's topology hash {h.hex()} differs from the stream's "
                         f"{header.template_hash.hex()} (same face count, different faces)")


def read_header(source) -> StreamInfo:
    """The header of a stream (path or bytes); raises if it is incomplete or invalid."""
    name = "<bytes>" if isinstance(source, (bytes, bytearray, memoryview)) else os.fspath(source)
    if isinstance(source, (bytes, bytearray, memoryview)):
        buf = memoryview(source).cast("B")
    else:
        with open(name, "rb") as fh:
            buf = fh.read(FIXED_SIZE)
            if len(buf) >= FIXED_SIZE:
                buf += fh.read(_parse_fixed(buf, name)["header_size"] - FIXED_SIZE)
    _check_magic(buf, name)
    if len(buf) < FIXED_SIZE or len(buf) < _parse_fixed(buf, name)["header_size"]:
        raise ValueError(f"{name}: truncated inside the stream header ({len(buf)} bytes)")
    return _parse_header(buf, name)


# -- stream order -------------------------------------------------------------------------
def stream_order(forest: Forest, importance=None) -> np.ndarray:
    """Permutation (new position -> old face): roots in template order, then each level by
    descending importance, ties by face index. Parents precede children since levels do."""
    N = forest.num_faces
    if importance is None:
        key = np.zeros(N)
    else:
        key = np.asarray(importance, np.float64).reshape(-1)
        if len(key) != N:
            raise ValueError(f"stream_order: importance has {len(key)} values for {N} faces")
        if not np.all(np.isfinite(key)):
            raise ValueError("stream_order: importance contains NaN or inf")
    key = np.where(forest.level == 0, 0.0, -key)  # roots keep template order whatever their importance
    idx = np.arange(N)
    return np.lexsort((idx, key, forest.level)).astype(np.int64)


# -- writer -------------------------------------------------------------------------------
def _quantize_records(av: Avatar, bary: np.ndarray, quant: np.ndarray) -> np.ndarray:
    N = av.num_gaussians
    rec = np.zeros(N, QUANT_DTYPE)
    q = quant.astype(np.float64).reshape(3, 2, 3)

    def codes(x, lo, hi, levels):
        span = hi - lo
        safe = np.where(span > 0, span, 1.0)
        c = np.rint((np.clip(x, lo, hi) - lo) / safe * (levels - 1))
        return np.where(span > 0, c, 0).astype(np.uint64)

    mu = codes(av.d_mu.astype(np.float64), q[0, 0], q[0, 1], 4096)
    b0 = np.rint(bary[:, 0] * 4095).astype(np.int64)
    b1 = np.minimum(np.rint(bary[:, 1] * 4095).astype(np.int64), 4095 - b0)
    slot = np.maximum(av.forest.slot.astype(np.int64), 0).astype(np.uint64)
    rec["geo"] = (mu[:, 0] | (mu[:, 1] << np.uint64(12)) | (mu[:, 2] << np.uint64(24))
                  | (b0.astype(np.uint64) << np.uint64(36)) | (b1.astype(np.uint64) << np.uint64(48))
                  | (slot << np.uint64(60)))

    r = av.d_rot.astype(np.float64)
    n = np.linalg.norm(r, axis=1, keepdims=True)
    r = np.where(n > 0, r / np.where(n > 0, n, 1.0), np.array([1.0, 0, 0, 0]))
    m = np.argmax(np.abs(r), axis=1)
    r = np.where(np.take_along_axis(r, m[:, None], 1) < 0, -r, r)
    v = np.take_along_axis(r, _ROT_OTHERS[m], 1)
    rc = np.clip(np.rint((v / _SQRT1_2 + 1.0) * 1023.0 / 2.0), 0, 1023).astype(np.uint32)
    rec["rot"] = rc[:, 0] | (rc[:, 1] << np.uint32(10)) | (rc[:, 2] << np.uint32(20)) | (m.astype(np.uint32) << np.uint32(30))

    parent = np.where(av.forest.parent >= 0, av.forest.parent, QUANT_ROOT).astype(np.uint32)
    rec["parent"] = np.stack([parent & 0xFF, (parent >> 8) & 0xFF, (parent >> 16) & 0xFF], 1).astype(np.uint8)
    rec["ls"] = codes(av.d_log_scale.astype(np.float64), q[1, 0], q[1, 1], 256).astype(np.uint8)
    alpha = 1.0 / (1.0 + np.exp(-av.opacity_logit.astype(np.float64)))
    rec["opa"] = np.minimum(np.floor(alpha * 256.0), 255).astype(np.uint8)
    c = 0.5 + SH_C0 * av.f_dc.astype(np.float64)
    rec["col"] = codes(c, q[2, 0], q[2, 1], 256).astype(np.uint8)
    raw = rec.view(np.uint8).reshape(N, QUANT_RECORD)
    rec["crc"] = crc8(raw[:, :QUANT_RECORD - 1])
    return rec


def _lossless_records(av: Avatar) -> np.ndarray:
    N = av.num_gaussians
    rec = np.zeros(N, LOSSLESS_DTYPE)
    parent = np.where(av.forest.parent >= 0, av.forest.parent, LOSSLESS_ROOT).astype(np.uint32)
    rec["link"] = parent | (np.maximum(av.forest.slot, 0).astype(np.uint32) << np.uint32(30))
    rec["split_logits"] = av.forest.split_logits
    for name in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc"):
        rec[name] = getattr(av, name)
    if not np.all(np.isfinite(av.forest.split_logits)):
        raise ValueError("write_stream: split logits contain NaN or inf")
    raw = rec.view(np.uint8).reshape(N, LOSSLESS_RECORD)
    rec["crc"] = crc8(raw[:, :LOSSLESS_RECORD - 1])
    return rec


def _quant_table(av: Avatar) -> np.ndarray:
    c = 0.5 + SH_C0 * av.f_dc.astype(np.float64)
    c_lo = np.maximum(c.min(0), 0.0)
    c_hi = np.maximum(c.max(0), c_lo)
    parts = [av.d_mu.min(0), av.d_mu.max(0), av.d_log_scale.min(0), av.d_log_scale.max(0), c_lo, c_hi]
    table = []
    for i, p in enumerate(parts):
        table.append(_f32_floor(p) if i % 2 == 0 else _f32_ceil(p))
    return np.concatenate(table).astype(np.float32)


def write_stream(path, avatar: Avatar, importance=None, *, quantize: bool = True, metadata=None,
                 embed_template: bool = True, records_per_block: int = DEFAULT_BLOCK) -> StreamInfo:
    """Write `avatar` as a stream (atomically). Returns its header; `.order` maps stream index
    to the avatar's face index."""
    forest = avatar.forest
    N, F0 = forest.num_faces, forest.num_roots
    if not 1 <= int(records_per_block) <= 0xFFFF:
        raise ValueError(f"write_stream: records_per_block must be in [1, 65535], got {records_per_block}")
    limit = QUANT_ROOT if quantize else LOSSLESS_ROOT
    if N > limit:
        raise ValueError(f"write_stream: {N} Gaussians exceed this record type's limit of {limit}")
    order = stream_order(forest, importance)
    f2 = forest.reorder(order)
    av = Avatar(f2, *(getattr(avatar, n)[order] for n in ("d_mu", "d_log_scale", "d_rot", "opacity_logit", "f_dc")))

    meta = {k: v for k, v in dict(avatar.meta or {}).items() if k != "stream"}
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
        recs = _quantize_records(av, f2.barycentrics(), quant)
    else:
        quant = None
        recs = _lossless_records(av)
    R = recs.dtype.itemsize
    info = StreamInfo(VERSION, flags, 0, N, F0, R, int(records_per_block), level_counts, template_hash(tmpl),
                      quant, meta, tmpl.astype(np.int32) if embed_template else None)
    header = _encode_header(info, template_blob, meta_blob)
    raw = recs.tobytes()
    B = info.records_per_block
    prefix = struct.pack("<I", info.header_crc)
    parts = [header]
    for bi in range(info.num_blocks):  # per block, not per record
        block = raw[bi * B * R: min(N, (bi + 1) * B) * R]
        crc = zlib.crc32(block, zlib.crc32(prefix + struct.pack("<I", bi)))
        parts.append(block)
        parts.append(struct.pack("<I", crc))
    data = b"".join(parts)
    assert len(data) == info.total_bytes
    path = os.fspath(path)
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
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
    """A growing array with amortised doubling (first axis)."""

    def __init__(self, shape_tail, dtype, fill=None):
        self.tail, self.dtype, self.fill = tuple(shape_tail), dtype, fill
        self.data = np.empty((0,) + self.tail, dtype)

    def reserve(self, n, limit=None):
        cap = len(self.data)
        if n <= cap:
            return
        new = max(n, 2 * cap, 1024)
        if limit is not None:
            new = max(n, min(new, limit))
        arr = np.empty((new,) + self.tail, self.dtype) if self.fill is None else np.full((new,) + self.tail, self.fill, self.dtype)
        arr[:cap] = self.data
        self.data = arr


class StreamReader:
    """Incremental decoder: feed bytes as they arrive; every whole, verified record becomes a
    Gaussian. Work per feed is proportional to the new bytes (plus at most one block)."""

    def __init__(self, template_faces=None, *, source: str = "<stream>"):
        self.source = source
        self._given_template = None if template_faces is None else np.asarray(template_faces, np.int32)
        self._pending = bytearray()  # bytes from the start of the current incomplete block (or header)
        self._offset = 0  # stream offset of _pending[0]
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
            raise ValueError(f"{self.source}: the reader already failed: {self.error}")
        mv = memoryview(chunk).cast("B")
        if len(mv) == 0:
            return 0
        before = self._n
        self.bytes_received += len(mv)
        if self.complete:
            self._fail(ValueError(f"{self.source}: {len(mv)} unexpected bytes after the end of the stream "
                                  f"(offset {self.bytes_received - len(mv)})"))
        try:
            if self._pending:
                self._pending += mv
                if self.header is None and len(self._pending) < self._header_need():
                    return 0
                # A copy, so that no view of the bytearray outlives this call (exceptions keep
                # frames alive); the pending part is at most one block plus this chunk.
                used = self._process(bytes(self._pending))
                del self._pending[:used]
            else:
                used = self._process(mv)
                self._pending = bytearray(mv[used:])
            self._offset += used
        except ValueError as exc:
            self._fail(exc)
        return self._n - before

    def _header_need(self) -> int:
        """Bytes the header phase needs before parsing is worth trying (checks the magic)."""
        _check_magic(self._pending, self.source)
        if len(self._pending) < FIXED_SIZE:
            return FIXED_SIZE
        return _parse_fixed(self._pending, self.source)["header_size"]

    def _fail(self, exc):
        self.error = exc
        raise exc

    def _process(self, buf) -> int:
        """Consume what can be verified from buf (stream offset self._offset); returns bytes
        consumed up to the end of the last complete block (the incomplete block stays pending)."""
        pos = 0
        if self.header is None:
            _check_magic(buf, self.source)
            if len(buf) < FIXED_SIZE:
                return 0
            H = _parse_fixed(buf, self.source)["header_size"]
            if len(buf) < H:
                return 0
            self._start(_parse_header(buf, self.source))
            pos = H
        h = self.header
        B, R = h.records_per_block, h.record_size
        S = h.block_bytes
        nblocks = h.num_blocks
        # Whole blocks: verify each CRC-32 (loop per block), then take their records in one go.
        first = self._block
        full_left = nblocks - first - (1 if h.num_records % B else 0)  # full-size blocks not yet verified
        m = min(max(full_left, 0), (len(buf) - pos) // S)
        if m:
            self._verify_blocks(buf, pos, first, m, S, B * R)
            arr = np.frombuffer(buf, np.uint8, m * S, pos).reshape(m, S)[:, : B * R]
            self._accept(arr.reshape(m * B, R), first * B, verified=True)
            del arr
            pos += m * S
            self._block = first + m
        # The short last block, if complete.
        if self._block == nblocks - 1 and h.num_records % B:
            nrec = h.num_records - self._block * B
            size = nrec * R + 4
            if len(buf) - pos >= size:
                self._verify_blocks(buf, pos, self._block, 1, size, nrec * R)
                arr = np.frombuffer(buf, np.uint8, nrec * R, pos).reshape(nrec, R)
                self._accept(arr, self._block * B, verified=True)
                del arr
                pos += size
                self._block += 1
        if self._block >= nblocks:
            if len(buf) > pos:
                raise ValueError(f"{self.source}: {len(buf) - pos} unexpected bytes after the end of the stream "
                                 f"(offset {self._offset + pos})")
            return pos
        # Records of the incomplete block: each verified by its own CRC-8.
        nrec = min(B, h.num_records - self._block * B)
        whole = min((len(buf) - pos) // R, nrec)
        start = self._block * B
        if start + whole > self._n:
            skip = self._n - start
            arr = np.frombuffer(buf, np.uint8, (whole - skip) * R, pos + skip * R).reshape(whole - skip, R)
            self._accept(arr, self._n, verified=False)
            del arr
        return pos

    def _verify_blocks(self, buf, pos, first, m, stride, nbytes):
        h = self.header
        prefix = struct.pack("<I", h.header_crc)
        trailers = np.frombuffer(buf, np.uint8, m * stride, pos).reshape(m, stride)[:, nbytes:nbytes + 4]
        stored = np.ascontiguousarray(trailers).view("<u4").ravel()
        del trailers
        for j in range(m):  # per block (B records each)
            o = pos + j * stride
            crc = zlib.crc32(buf[o: o + nbytes], zlib.crc32(prefix + struct.pack("<I", first + j)))
            if crc != stored[j]:
                bi = first + j
                raise ValueError(f"{self.source}: block {bi} (records {bi * h.records_per_block}.."
                                 f"{min(h.num_records, (bi + 1) * h.records_per_block) - 1}, bytes "
                                 f"{self._offset + o}..{self._offset + o + nbytes + 3}) fails its CRC-32: corrupted")

    def _start(self, header: StreamInfo):
        if self._given_template is not None:
            check_template(header, self._given_template)
        self.header = header
        R = header.record_size
        N = header.num_records
        self._raw = _Grow((R,), np.uint8)
        self._parent = _Grow((), np.int64)
        self._slot = _Grow((), np.int8)
        self._child = _Grow((), np.int32, fill=-1)  # record index per (parent, slot); N < 2^30
        self._level_starts = np.concatenate([[0], header.level_ends()]).astype(np.int64)
        self._limit = N
        self._params = {
            "split_logits": _Grow((3,), np.float32), "d_mu": _Grow((3,), np.float32),
            "d_log_scale": _Grow((3,), np.float32), "d_rot": _Grow((4,), np.float32),
            "opacity_logit": _Grow((), np.float32), "f_dc": _Grow((3,), np.float32),
        }

    def _record_offset(self, i) -> int:
        return self.header.record_offset(int(i))

    def _accept(self, rows: np.ndarray, i0: int, verified: bool):
        """Structural checks and storage for records i0.. (rows [n,R] uint8, checksum pending
        unless `verified`). Records before i0 + len(rows) that were already accepted are skipped."""
        h = self.header
        skip = max(0, self._n - i0)
        rows = rows[skip:]
        i0 += skip
        n = len(rows)
        if n == 0:
            return
        bad_at = n
        if not verified:
            ok = crc8(rows[:, :-1]) == rows[:, -1]
            if not ok.all():
                bad_at = int(np.argmin(ok))
        rows = rows[:bad_at]
        k = len(rows)
        idx = np.arange(i0, i0 + k, dtype=np.int64)
        problem = None
        if k:
            if h.lossless:
                rec = rows.view(LOSSLESS_DTYPE)[:, 0] if rows.flags.c_contiguous else np.ascontiguousarray(rows).view(LOSSLESS_DTYPE)[:, 0]
                link = rec["link"].astype(np.int64)
                parent = link & LOSSLESS_ROOT
                slot = (link >> 30).astype(np.int8)
                root_mark = parent == LOSSLESS_ROOT
                floats = np.ascontiguousarray(rows[:, 4:72]).view("<f4")
                finite = np.all(np.isfinite(floats), axis=1)
                extra_bad = ~finite
            else:
                rec = (rows if rows.flags.c_contiguous else np.ascontiguousarray(rows)).view(_QUANT_VIEW)[:, 0]
                parent = (rec["p32"] & np.uint32(0xFFFFFF)).astype(np.int64)
                g_hi = rec["g_hi"]
                slot = ((g_hi >> np.uint32(28)) & np.uint32(3)).astype(np.int8)
                extra_bad = ((g_hi >> np.uint32(30)) != 0) | (
                    ((g_hi >> np.uint32(4)) & np.uint32(4095)) + ((g_hi >> np.uint32(16)) & np.uint32(4095)) > 4095)
                root_mark = parent == QUANT_ROOT
            # Roots come first; a non-root's parent must lie in the previous level's index range
            # (which also puts it before the child). Loop over the levels this batch touches.
            starts = self._level_starts
            nr = max(0, min(k, h.num_template_faces - i0))
            bad = extra_bad | (slot == 3)
            bad[:nr] |= ~root_mark[:nr] | (slot[:nr] != 0)
            l_first = int(np.searchsorted(starts, i0 + nr, side="right")) - 1
            l_last = int(np.searchsorted(starts, i0 + k - 1, side="right")) - 1
            for lv in range(max(l_first, 1), l_last + 1):
                a, b = max(int(starts[lv]), i0) - i0, min(int(starts[lv + 1]), i0 + k) - i0
                pp = parent[a:b]
                bad[a:b] |= (pp < starts[lv - 1]) | (pp >= starts[lv])
            if bad.any():
                k = int(np.argmax(bad))
                problem = f"record {i0 + k} is structurally invalid (parent/slot/level/root marker/reserved bits/values)"
            # (parent, slot) must be unique: scatter the record indices, read them back.
            if k > nr:
                keys = parent[nr:k] * 3 + slot[nr:k]
                ids = idx[nr:k]
                self._child.reserve(int(keys.max()) + 1)
                taken = self._child.data[keys] >= 0
                self._child.data[keys] = ids
                dup = taken | (self._child.data[keys] != ids)
                if dup.any():
                    k = nr + int(np.argmax(dup))
                    problem = f"record {i0 + k} reuses the child slot of an earlier record"
            if k:
                end = i0 + k
                for g, vals in ((self._raw, rows[:k]), (self._parent, np.where(root_mark[:k], -1, parent[:k])),
                                (self._slot, np.where(root_mark[:k], -1, slot[:k]))):
                    g.reserve(end, self._limit)
                    g.data[i0:end] = vals
                self._n = end
        if problem is not None:
            raise ValueError(f"{self.source}: {problem} at offset {self._record_offset(i0 + k)}")
        if bad_at < n:
            i = i0 + bad_at
            raise ValueError(f"{self.source}: record {i} (offset {self._record_offset(i)}, block "
                             f"{i // h.records_per_block}) fails its CRC-8: corrupted")

    # -- decoding -------------------------------------------------------------------------
    def _decode(self):
        """Decode parameters of records not yet decoded (lazily: feed() only verifies).
        Writes straight into the output columns; every operation runs over all new records."""
        a, b = self._decoded, self._n
        if b <= a:
            return
        h = self.header
        for g in self._params.values():
            g.reserve(b, self._limit)
        P = {name: g.data[a:b] for name, g in self._params.items()}
        raw = self._raw.data[a:b]
        if h.lossless:
            rec = raw.view(LOSSLESS_DTYPE)[:, 0]
            for name, dst in P.items():
                dst[...] = rec[name]
            self._decoded = b
            return
        st = self._steps
        # Transpose the fields once into contiguous rows: every later operation then runs on
        # aligned, unit-stride data (several times faster than on 23-byte-strided fields).
        g_lo, g_hi, rot = np.ascontiguousarray(raw[:, :12]).view("<u4").T.copy()
        tail = raw[:, 15:22].T.copy()  # log-scale codes, opacity code, colour codes
        m12 = np.uint32(4095)
        f32 = np.float32
        lo, step = st["mu"]
        mu = P["d_mu"]
        mu[:, 0] = (g_lo & m12).astype(f32) * step[0] + lo[0]
        mu[:, 1] = ((g_lo >> np.uint32(12)) & m12).astype(f32) * step[1] + lo[1]
        mu[:, 2] = (((g_lo >> np.uint32(24)) | (g_hi << np.uint32(8))) & m12).astype(f32) * step[2] + lo[2]
        b0 = ((g_hi >> np.uint32(4)) & m12).astype(np.int32)
        b1 = ((g_hi >> np.uint32(16)) & m12).astype(np.int32)
        sl = P["split_logits"]
        sl[:, 0] = _BARY_LUT[b0]
        sl[:, 1] = _BARY_LUT[b1]
        sl[:, 2] = _BARY_LUT[4095 - b0 - b1]
        v0 = (rot & np.uint32(1023)).astype(f32) * _ROT_STEP + _ROT_LO
        v1 = ((rot >> np.uint32(10)) & np.uint32(1023)).astype(f32) * _ROT_STEP + _ROT_LO
        v2 = ((rot >> np.uint32(20)) & np.uint32(1023)).astype(f32) * _ROT_STEP + _ROT_LO
        big = (rot >> np.uint32(30)).astype(np.int8)
        w = np.sqrt(np.maximum(f32(1) - (v0 * v0 + v1 * v1 + v2 * v2), f32(0)))
        q = P["d_rot"]
        # Slot j holds the largest if big == j, else v_{j-1} when big < j, else v_j.
        q[:, 0] = np.where(big == 0, w, v0)
        q[:, 1] = np.where(big == 1, w, np.where(big < 1, v0, v1))
        q[:, 2] = np.where(big == 2, w, np.where(big < 2, v1, v2))
        q[:, 3] = np.where(big == 3, w, v2)
        lo, step = st["ls"]
        out = P["d_log_scale"]
        for k in range(3):  # over the three axes
            out[:, k] = tail[k].astype(f32) * step[k] + lo[k]
        P["opacity_logit"][...] = _OPA_LUT[tail[3]]
        lo, step = st["fdc"]
        out = P["f_dc"]
        for k in range(3):
            out[:, k] = tail[4 + k].astype(f32) * step[k] + lo[k]
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
        out = {name: g.data[:n] for name, g in self._params.items()}
        out["parent"] = self._parent.data[:n]
        out["slot"] = self._slot.data[:n]
        return out

    def avatar(self, n=None) -> Avatar | None:
        """An Avatar of the first n available Gaussians (all if None), faces in stream order;
        None when no record is available yet."""
        if self.header is None or self._n == 0:
            return None
        n = self._n if n is None else max(0, min(int(n), self._n))
        if n == 0:
            return None
        tmpl = self.template_faces
        if tmpl is None:
            raise ValueError(f"{self.source}: the stream does not embed its template; pass template_faces "
                             f"(a mesh with topology hash {self.header.template_hash_hex})")
        a = self.arrays(n)
        h = self.header
        F0 = h.num_template_faces
        forest = Forest(tmpl[: min(n, F0)], a["parent"], a["slot"], a["split_logits"])
        meta = dict(h.metadata)
        meta["stream"] = {"records": n, "total_records": h.num_records, "base_complete": n >= F0,
                          "lossless": h.lossless, "template_hash": h.template_hash_hex,
                          "bytes": h.bytes_for_count(n), "total_bytes": h.total_bytes}
        return Avatar(forest, a["d_mu"].copy(), a["d_log_scale"].copy(), a["d_rot"].copy(),
                      a["opacity_logit"].copy(), a["f_dc"].copy(), meta=meta)


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
        H = _parse_fixed(head, name)["header_size"]
        rest = data[FIXED_SIZE:H] if is_bytes else fh.read(H - FIXED_SIZE)
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
