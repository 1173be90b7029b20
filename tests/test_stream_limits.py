"""Limits a hostile or broken stream must not get past (docs/FORMAT.md 2.1-2.3): counts that
would inflate gigabytes from a few bytes, a file far longer than its stream, a server sending
more than a budget asked for, an embedded template with negative indices, version 3 ranges
that decode beyond float32, more levels than int8 holds; and the JSON depth scan's memory.
Each builds small data and runs in well under a second."""

import copy
import math
import os
import re
import struct
import threading
import tracemalloc
import types
import warnings
import zlib
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from progressive_avatars.core.avatar.forest import Forest
from progressive_avatars.core.io import safe_io
from progressive_avatars.core.io.safe_io import json_depth
from progressive_avatars.core.stream import format as F
from progressive_avatars.core.stream import http as H
from progressive_avatars.core.stream import reader as stream_reader
from progressive_avatars.core.stream.format import StreamError, StreamInfo, read_header, template_hash
from progressive_avatars.core.stream.reader import read_stream
from progressive_avatars.core.stream.writer import build_stream, encode_stream, write_stream
from tests.test_stream import make_avatar
from progressive_avatars.core.stream.reader import StreamReader

# The documented caps (FORMAT.md 2.1, 2.3): template faces and coarse triangles, levels (int8).
MAX_ROOT_FACES = 1 << 24
MAX_LEVELS = 128


def _no_inflating(monkeypatch):
    """Make format.py's zlib refuse to inflate: a header the caps refuse never gets there."""

    def boom(*a, **k):
        raise AssertionError("inflated a table the header's counts should have refused")

    fake = types.SimpleNamespace(crc32=zlib.crc32, compress=zlib.compress, error=zlib.error, decompressobj=boom)
    monkeypatch.setattr(F, "zlib", fake)


def _lossless_header(N, F0, level_counts, *, template_blob=b"", coarse_blob=b"", K=0):
    flags = F.FLAG_LOSSLESS | (F.FLAG_TEMPLATE if template_blob else 0)
    info = StreamInfo(5, flags, 0, N, F0, F.LOSSLESS_RECORD, 256, tuple(level_counts), bytes(16), num_coarse_levels=K)
    return F._encode_header(info, template_blob, b"", coarse_blob)


def test_template_face_count_beyond_the_cap_is_refused_before_inflating(tmp_path, monkeypatch):
    _no_inflating(monkeypatch)
    blob = zlib.compress(bytes(12))
    p = tmp_path / "bomb.pavs"
    F0 = MAX_ROOT_FACES + 1
    p.write_bytes(_lossless_header(F0, F0, (F0,), template_blob=blob))  # header only: a legal prefix
    with pytest.raises(StreamError, match=re.escape(str(p)) + ".*template faces"):
        read_stream(p)
    # the cap itself is a legal count: it gets as far as inflating
    F0 = MAX_ROOT_FACES
    with pytest.raises(AssertionError, match="inflated"):
        read_header(_lossless_header(F0, F0, (F0,), template_blob=blob))
    assert F.MAX_ROOT_FACES == MAX_ROOT_FACES and F.MAX_LEVELS == MAX_LEVELS


def test_coarse_triangle_count_beyond_the_cap_is_refused_before_inflating(tmp_path, monkeypatch):
    _no_inflating(monkeypatch)
    C = MAX_ROOT_FACES + 1
    p = tmp_path / "coarse_bomb.pavs"
    p.write_bytes(_lossless_header(C + 1, 1, (C, 1), coarse_blob=zlib.compress(bytes(12)), K=1))
    with pytest.raises(StreamError, match=re.escape(str(p)) + ".*coarse triangles"):
        read_stream(p)


class _CountingFile:
    """A file whose reads must be bounded: read() of the rest would take all of a long file."""

    def __init__(self, fh, log):
        self.fh, self.log = fh, log

    def read(self, n=-1):
        assert n is not None and n >= 0, "read the whole rest of the file"
        got = self.fh.read(n)
        self.log.append(len(got))
        return got

    def close(self):
        self.fh.close()


def test_read_stream_reads_one_byte_past_the_stream_not_the_whole_file(tmp_path, monkeypatch):
    _, av, imp = make_avatar(0)
    p = tmp_path / "long.pavs"
    info = write_stream(p, av, imp)
    with open(p, "r+b") as fh:
        fh.truncate(info.total_bytes + (64 << 20))  # sparse: no disk, no memory unless read
    log = []
    monkeypatch.setattr(stream_reader, "open", lambda name, mode: _CountingFile(open(name, mode), log), raising=False)
    with pytest.raises(StreamError, match=re.escape(str(p)) + ": unexpected bytes after the end"):
        read_stream(p)
    assert sum(log) == info.total_bytes + 1
    # a budget reads its blocks only, and the exact stream reads through
    with open(p, "r+b") as fh:
        fh.truncate(info.total_bytes)
    log.clear()
    assert read_stream(p).num_gaussians == info.num_records and sum(log) == info.total_bytes
    log.clear()
    n = info.count_for_bytes(info.header_size + 200)
    assert read_stream(p, max_bytes=info.header_size + 200).num_gaussians == n
    assert sum(log) == info.block_end_for_count(n)


class _RoundingHandler(BaseHTTPRequestHandler):
    """Answers every range rounded up to 4 KiB blocks (as some CDNs do), with a consistent
    Content-Range naming the bytes it sends."""

    protocol_version = "HTTP/1.1"

    def log_message(self, *args):
        pass

    def do_GET(self):
        data = self.server.data
        m = re.match(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
        s = int(m.group(1))
        e = min(len(data) - 1, (s // 4096 + 1) * 4096 - 1)
        self.send_response(206)
        self.send_header("Content-Range", f"bytes {s}-{e}/{len(data)}")
        self.send_header("Content-Length", str(e - s + 1))
        self.send_header("ETag", '"x"')
        self.end_headers()
        try:
            self.wfile.write(data[s : e + 1])
        except OSError:  # the client hung up on the part it did not ask for
            pass


class _QuietServer(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):
        pass


@pytest.fixture
def rounding_server():
    _, av, imp = make_avatar(2, n_lat=6, n_lon=10)
    data = encode_stream(av, imp, records_per_block=16)
    srv = _QuietServer(("127.0.0.1", 0), _RoundingHandler)
    srv.data = data
    t = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    t.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}/a.pavs", data
    srv.shutdown()
    srv.server_close()
    t.join(5)


def test_overlong_range_responses_do_not_overrun_a_budget(rounding_server):
    url, data = rounding_server
    h = read_header(data)
    assert h.total_bytes > 4096  # several rounded blocks
    for kw, lim in ((dict(max_bytes=1000), 1000), (dict(percent=10), F.percent_bytes(10, h.total_bytes))):
        r = H.fetch_stream(url, chunk_size=256, timeout=5, **kw)
        assert r.status == H.BUDGET, r
        assert r.bytes_received == lim and r.num_gaussians == h.count_for_bytes(lim), (kw, r)
    r = H.fetch_stream(url, chunk_size=1000, timeout=5)
    assert r.status == H.COMPLETE and r.num_gaussians == h.num_records, r


def test_embedded_template_with_a_negative_index_is_refused_with_the_file_name(tmp_path):
    _, av, _ = make_avatar(1)
    data, info = build_stream(av, None, quantize=True, records_per_block=8)
    bad = av.forest.template_faces.copy()
    bad[0, 0] = -7
    forged = copy.copy(info)
    forged.template_hash = template_hash(bad)  # self-consistent: only the index is wrong
    p = tmp_path / "neg.pavs"
    p.write_bytes(F._encode_header(forged, zlib.compress(np.ascontiguousarray(bad, "<i4").tobytes()), b""))
    with pytest.raises(StreamError, match=re.escape(str(p)) + ".*negative vertex index"):
        read_stream(p)


def _v3_header_with(values: dict):
    _, av, imp = make_avatar(4)
    data, _ = build_stream(av, imp, version=3, records_per_block=8)
    info = read_header(data)
    forged = copy.copy(info)
    forged.quant = info.quant.copy()
    for i, v in values.items():
        forged.quant[i] = np.float32(v)
    blob = zlib.compress(np.ascontiguousarray(info.template_faces, "<i4").tobytes())
    return F._encode_header(forged, blob, b"")


def test_version_3_ranges_decoding_beyond_float32_are_refused_with_the_file_name(tmp_path):
    p = tmp_path / "v3.pavs"
    # quant order: mu lo[3] hi[3], ls lo hi, c lo hi, r lo hi; c_hi r, c_lo r (f_dc = c/C0), mu x's step
    for values in ({15: 3e38}, {12: -3e38}, {0: -3e38, 3: 3e38}):
        p.write_bytes(_v3_header_with(values))
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no numpy overflow warning on the way
            with pytest.raises(StreamError, match=re.escape(str(p)) + ".*quantisation ranges"):
                read_stream(p)
    # near float32's limit but decodable: still a valid version 3 header
    assert read_header(_v3_header_with({3: 3e38})).version == 3


def _chain_stream(version, L):
    """A lossless stream of one template face split L - 1 times down one slot: L levels."""
    tmpl = np.array([[0, 1, 2]], np.int32)
    rec = np.zeros(L, F.LOSSLESS_DTYPE)
    link = np.arange(-1, L - 1, dtype=np.int64)  # record i: parent i - 1, slot 0
    link[0] = (3 << 30) if version >= 5 else 0  # the root: row 0 (version 5: slot 3, the root flag)
    rec["link"] = link.astype(np.uint32)
    rec["d_log_scale"] = -3.0
    rec["d_rot"][:, 0] = 1.0
    rec["crc"] = F.crc8_indexed(rec.view(np.uint8).reshape(L, -1)[:, :-1], 0)
    info = StreamInfo(
        version, F.FLAG_LOSSLESS | F.FLAG_TEMPLATE, 0, L, 1, F.LOSSLESS_RECORD, 256, (1,) * L, template_hash(tmpl)
    )
    hdr = F._encode_header(info, zlib.compress(tmpl.tobytes()), b"")
    blk = rec.tobytes()
    return hdr + blk + struct.pack("<I", zlib.crc32(blk, zlib.crc32(struct.pack("<II", info.header_crc, 0))))


@pytest.mark.parametrize("version", [4, 5])
def test_more_levels_than_int8_holds_are_refused(tmp_path, version):
    p = tmp_path / "deep.pavs"
    p.write_bytes(_chain_stream(version, MAX_LEVELS + 1))
    with pytest.raises(StreamError, match=re.escape(str(p)) + f".*num_levels={MAX_LEVELS + 1}"):
        read_stream(p)
    a = read_stream(_chain_stream(version, MAX_LEVELS))  # levels 0..127: every one representable
    assert a.forest.level.min() == 0 and a.forest.level.max() == MAX_LEVELS - 1


def test_forest_split_refuses_the_level_int8_cannot_hold():
    f = Forest(np.array([[0, 1, 2]], np.int32))
    for _ in range(MAX_LEVELS - 1):
        f.split([f.num_faces - 1])
    assert f.max_level == MAX_LEVELS - 1 == np.iinfo(f.level.dtype).max
    with pytest.raises(ValueError, match=f"level {MAX_LEVELS - 1} do not split"):
        f.split([f.num_faces - 1])
    assert f.level.min() >= 0


def _json_depth_whole(data) -> int:
    """The scan before chunking (int64 over the whole text): the results to keep."""
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else bytes(data)
    raw = safe_io._JSON_STRING.sub(b'""', raw)
    b = np.frombuffer(raw, np.uint8)
    step = np.isin(b, (ord("["), ord("{"))).astype(np.int64) - np.isin(b, (ord("]"), ord("}")))
    return int(np.cumsum(step).max(initial=0))


def test_json_depth_keeps_its_results_in_small_chunks(monkeypatch):
    k = safe_io._DEPTH_CHUNK
    texts = [
        "",
        "0",
        "]]]",
        '{"a": [1, {"b": "[[[{"}], "c\\"[": 2}',
        '["\\\\", [[]]]',
        "[" * 70 + "]" * 70,
        "]]" + "[" * 5,
        b"[" * (k - 1) + b"[[" + b"]" * (k + 1),  # the deepest point just past a chunk boundary
        b"]" * (k + 3) + b"[" * 10,  # below zero first, across chunks
        b'"' + b"[" * (2 * k) + b'"' + b"[]",  # a string over several chunks
    ]
    for t in texts:
        assert json_depth(t) == _json_depth_whole(t), t[:40]
    monkeypatch.setattr(safe_io, "_DEPTH_CHUNK", 7)  # many boundaries in short texts
    rng = np.random.default_rng(0)
    for _ in range(50):
        t = rng.choice(np.frombuffer(b'[]{}"\\ 0,', np.uint8), int(rng.integers(0, 200))).tobytes()
        assert json_depth(t) == _json_depth_whole(t), t


def test_json_depth_memory_does_not_grow_with_the_text():
    text = b'{"k": "v", "a": [' + b"0," * (4 << 20) + b"0]}"  # 8 MiB
    tracemalloc.start()
    try:
        assert json_depth(text) == 2
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # The string-blanking regex builds its copy from pieces (2 bytes per byte at its peak), the
    # chunks take a few MiB; whole-text int64 arrays took over 24 bytes per byte.
    assert peak < 4 * len(text), peak / len(text)


def test_a_deep_chain_keeps_every_parent_first():
    """40 levels below the template (a chain of splits through the last child): the order
    inside a unit once used a base-4 number in int64, which overflowed from 33 levels and put a
    child before its parent (or raised OverflowError); the stream now writes and reads back."""
    from progressive_avatars.core.stream.order import interleaved_order

    f = Forest(np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    cur = [0]
    for _ in range(40):
        cur = f.split(cur)[:, 2]
    N = f.num_faces
    imp = np.zeros(N)
    leaf = f.children[:, 0] < 0
    imp[leaf & (f.slot == 0)], imp[leaf & (f.slot == 1)] = 1.0, 0.9
    imp[np.flatnonzero(f.level == f.level.max())] = 0.8
    imp[:2] = 1.0  # every child merges into its parent's unit: the path runs all 40 levels
    o = interleaved_order(f, imp)
    pos = np.empty(N, np.int64)
    pos[o] = np.arange(N)
    kids = np.flatnonzero(f.parent >= 0)
    assert sorted(o.tolist()) == list(range(N)) and np.all(pos[f.parent[kids]] < pos[kids])
    from progressive_avatars.core.avatar.avatar import Avatar

    data, _ = build_stream(Avatar.initial(f), imp)
    assert read_stream(data).num_gaussians == N


def test_zlib_tables_must_be_complete_and_fill_their_bytes(tmp_path):
    """FORMAT.md 2.2: the embedded template's and the coarse table's zlib streams end where
    their bytes end, Adler-32 included; a strict RFC 1950 reader (zlib.decompress) refuses
    junk after the end or a stream cut before its checksum, and so does ours."""
    _, av, imp = make_avatar(26, coarse=True)
    data, info = build_stream(av, imp, quantize=True, records_per_block=8)
    assert info.num_coarse_levels > 0
    tmpl = zlib.compress(np.ascontiguousarray(info.template_faces, "<i4").tobytes())
    coarse = F._encode_coarse(info.coarse_faces, getattr(info, "coarse_retire", None))
    read_header(F._encode_header(info, tmpl, b"", coarse))  # as written: accepted
    p = tmp_path / "z.pavs"
    for what, t, c in (
        ("embedded template: 2 bytes after", tmpl + b"\x00\x01", coarse),
        ("embedded template: its zlib stream is cut short", tmpl[:-4], coarse),
        ("coarse triangle table: 1 bytes after", tmpl, coarse + b"\x00"),
        ("coarse triangle table: its zlib stream is cut short", tmpl, coarse[:-2]),
    ):
        p.write_bytes(F._encode_header(info, t, b"", c))
        with pytest.raises(StreamError, match=re.escape(f"{p}: {what}")):
            read_stream(p)


R = 23


def _crc8(data: bytes) -> int:
    """CRC-8/SMBUS (FORMAT.md 5): poly 0x07, init 0, no reflection, xorout 0."""
    c = 0
    for byte in data:
        c ^= byte
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
    return c


assert _crc8(b"123456789") == 0xF4  # the check value FORMAT.md 5 gives


def _layout(data):
    """(version, header_size, N, B, level_counts) from the fixed header (FORMAT.md 2.1)."""
    version = struct.unpack_from("<H", data, 8)[0]
    hs, n = struct.unpack_from("<II", data, 12)
    b, levels = struct.unpack_from("<HH", data, 26)
    fixed = {3: 60, 4: 64, 5: 64}[version]
    counts = list(struct.unpack_from(f"<{levels}I", data, fixed))
    return version, hs, n, b, counts


def _offset(data, i):
    _, hs, _, b, _ = _layout(data)
    return hs + i * R + 4 * (i // b)


def patch(data, i, edit):
    """`data` with record i's bytes [0, 22) changed by edit(bytearray), its CRC-8 and its block's
    CRC-32 recomputed (FORMAT.md 4: CRC-32 of u32(header_crc) || u32(block) || record bytes)."""
    version, hs, n, b, _ = _layout(data)
    out = bytearray(data)
    blk = i // b
    start = hs + blk * (b * R + 4)
    nrec = min(b, n - blk * b)
    hcrc = out[hs - 4 : hs]

    def block_crc():
        return struct.pack(
            "<I", zlib.crc32(bytes(hcrc) + struct.pack("<I", blk) + bytes(out[start : start + nrec * R]))
        )

    assert block_crc() == out[start + nrec * R : start + nrec * R + 4]  # the helper agrees with the writer
    o = _offset(data, i)
    rec = bytearray(out[o : o + 22])
    edit(rec)
    out[o : o + 22] = rec
    out[o + 22] = _crc8((struct.pack("<I", i) if version >= 3 else b"") + bytes(rec))
    out[start + nrec * R : start + nrec * R + 4] = block_crc()
    return bytes(out)


def set_betas(b0, b1):
    def edit(rec):
        geo = int.from_bytes(rec[0:8], "little")
        geo &= ~((0xFFF << 36) | (0xFFF << 48))
        geo |= (b0 << 36) | (b1 << 48)
        rec[0:8] = geo.to_bytes(8, "little")

    return edit


@pytest.fixture(scope="module")
def plain():
    """A stream without coarse levels (K = 0), written as version 5 and version 4."""
    _, av, imp = make_avatar(11, n_lat=5, n_lon=7)
    return {v: encode_stream(av, imp, records_per_block=16, version=v) for v in (4, 5)}


@pytest.mark.parametrize("version", [4, 5])
def test_split_codes_summing_to_4096_are_refused(plain, version):
    """r2 (and its version 5 twin): beta0 + beta1 <= 4095 (FORMAT.md 3.1); 4096 leaves beta2 = -1."""
    data = plain[version]
    assert _layout(data)[0] == version
    i = _layout(data)[2] - 5  # a deep record near the end
    read_stream(data)  # untouched: fine
    for b0, b1 in ((4095, 1), (1, 4095), (2048, 2048)):
        with pytest.raises(StreamError, match=f"record {i} "):
            read_stream(patch(data, i, set_betas(b0, b1)))
    read_stream(patch(data, i, set_betas(4095, 0)))  # exactly 4095: accepted
    read_stream(patch(data, i, set_betas(2048, 2047)))


def test_a_parent_in_the_childs_own_level_is_refused_in_version_4(plain):
    """before version 5 a non-root's parent lies in the previous level's index range
    [starts[l-1], starts[l]) (FORMAT.md 3); the first record of the child's own level, index
    starts[l], is one past it."""
    data = plain[4]
    _, _, n, _, counts = _layout(data)
    assert len(counts) >= 3
    s2 = counts[0] + counts[1]  # first record of level 2
    j = s2 + 1

    def edit(rec):
        rec[12:15] = s2.to_bytes(3, "little")  # parent = s2 (keeps the slot)

    bad = patch(data, j, edit)
    with pytest.raises(StreamError, match=f"record {j} "):
        read_stream(bad)
    # A prefix ending just after it: not a shorter result, an error (FORMAT.md 4, rule 3).
    r = StreamReader()
    with pytest.raises(StreamError, match=f"record {j} "):
        r.feed(bad[: _offset(bad, j) + R])
    # The last record of the previous level, index s2 - 1, is a valid parent (a free slot of a
    # level-1 record: no other rule refuses it).
    used = set()
    for k in range(s2, s2 + counts[2]):
        o = _offset(data, k)
        used.add(
            (int.from_bytes(data[o + 12 : o + 15], "little"), (int.from_bytes(data[o : o + 8], "little") >> 60) & 3)
        )
    p, s = next((p, s) for p in range(s2 - 1, counts[0] - 1, -1) for s in range(3) if (p, s) not in used)
    assert p >= counts[0]

    def edit_ok(rec):
        rec[12:15] = p.to_bytes(3, "little")
        geo = int.from_bytes(rec[0:8], "little") & ~(3 << 60) | (s << 60)
        rec[0:8] = geo.to_bytes(8, "little")

    out = read_stream(patch(data, j, edit_ok))
    assert out.num_gaussians == n


f32 = np.float32


def _record_split(avatar, i):
    return avatar.forest.split_logits[avatar.forest.stream_order()[i]]


@pytest.mark.parametrize("version", [4, 5])
def test_split_code_zero_uses_the_2_pow_minus_20_floor(version):
    """a zero barycentric code decodes as f32(ln(2^-20 / 4095)) (FORMAT.md 3.1), about -22.18."""
    _, av, imp = make_avatar(11, n_lat=5, n_lon=7)
    data = encode_stream(av, imp, records_per_block=16, version=version)
    i = _layout(data)[2] - 3
    floor = f32(math.log(2.0**-20 / 4095.0))
    assert -22.19 < floor < -22.17
    out = read_stream(patch(data, i, set_betas(4095, 0)))  # beta = (4095, 0, 0)
    assert _record_split(out, i).tobytes() == np.array([0.0, floor, floor], f32).tobytes()
    out = read_stream(patch(data, i, set_betas(0, 1365)))  # beta = (0, 1365, 2730)
    want = [floor, f32(math.log(1365 / 4095)), f32(math.log(2730 / 4095))]
    assert _record_split(out, i).tobytes() == np.array(want, f32).tobytes()


V1 = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests", "data", "stream_v1.pavs")


def _v1_offset(data, i):
    hs, _ = struct.unpack_from("<II", data, 12)
    b = struct.unpack_from("<H", data, 26)[0]
    return hs + i * 23 + 4 * (i // b)


def _v1_patch(data, i, rot):
    """Version 1 (FORMAT.md 7; the CRC-8 covers the record's own bytes): record i's u32 rot set."""

    hs, n = struct.unpack_from("<II", data, 12)
    b = struct.unpack_from("<H", data, 26)[0]
    out = bytearray(data)
    o = _v1_offset(data, i)
    out[o + 8 : o + 12] = struct.pack("<I", rot)
    out[o + 22] = _crc8(bytes(out[o : o + 22]))
    blk = i // b
    start = hs + blk * (b * 23 + 4)
    nrec = min(b, n - blk * b)
    end = start + nrec * 23
    old = zlib.crc32(bytes(data[hs - 4 : hs]) + struct.pack("<I", blk) + bytes(data[start:end]))
    assert struct.pack("<I", old) == data[end : end + 4]  # the block CRC rule holds for version 1 too
    out[end : end + 4] = struct.pack(
        "<I", zlib.crc32(bytes(out[hs - 4 : hs]) + struct.pack("<I", blk) + bytes(out[start:end]))
    )
    return bytes(out)


def _v1_component(code):
    lo32, step32 = f32(-1 / math.sqrt(2.0)), f32(math.sqrt(2.0) / 1023.0)
    return f32(lo32 + f32(f32(code) * step32))


@pytest.mark.parametrize("m", [0, 1, 2, 3])
def test_version_1_rotation_whose_three_smallest_overflow_the_unit_norm(m):
    """three components coded 1023 (each +1/sqrt(2)): 1 - (v0^2 + v1^2 + v2^2) < 0, and the
    largest is sqrt(max(., 0)) = 0 (FORMAT.md 7), never NaN."""
    data = open(V1, "rb").read()
    assert struct.unpack_from("<H", data, 8)[0] == 1
    i = 300
    v = _v1_component(1023)
    s = f32(f32(f32(v * v) + f32(v * v)) + f32(v * v))
    assert f32(f32(1) - s) < 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a sqrt of a negative number warns: none may happen
        out = read_stream(_v1_patch(data, i, 1023 | 1023 << 10 | 1023 << 20 | m << 30))
    q = out.d_rot[out.forest.stream_order()[i]]
    want = [v, v, v]
    want.insert(m, f32(0))
    assert q.tobytes() == np.array(want, f32).tobytes()


@pytest.mark.parametrize("m", [0, 1, 2, 3])
def test_version_1_largest_index_is_the_top_two_bits(m):
    """bits 30-31 of rot name the largest component; bit 29 (the top bit of the third code)
    is not part of it. Codes (0, 511, 1023): v = -1/sqrt(2) + q*sqrt(2)/1023."""
    data = open(V1, "rb").read()
    i = 301
    codes = (0, 511, 1023)
    out = read_stream(_v1_patch(data, i, codes[0] | codes[1] << 10 | codes[2] << 20 | m << 30))
    q = out.d_rot[out.forest.stream_order()[i]]
    v = [_v1_component(c) for c in codes]
    s = f32(f32(f32(v[0] * v[0]) + f32(v[1] * v[1])) + f32(v[2] * v[2]))
    w = np.sqrt(max(f32(f32(1) - s), f32(0)))
    want = v[:]
    want.insert(m, w)
    assert q.tobytes() == np.array(want, f32).tobytes()
