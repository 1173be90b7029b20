"""The incremental stream reader: feed bytes as they arrive, every whole verified record
becomes a Gaussian; read_stream decodes a file or bytes through it (numpy only: runs in Blender).

Decoding is vectorised: records are viewed with a structured dtype and every field is decoded
by whole-array operations over all new records; the only Python loops run per block (CRC-32)
or per level, never per record.
"""

from __future__ import annotations

import bisect
import os
import struct
import zlib

import numpy as np

from ..avatar.avatar import LOG_SCALE_MAX, Avatar, PARAM_NAMES
from ..avatar.forest import Forest
from .decode import _decode_quantised, _decode_scratch
from .format import (
    FIXED_SIZE,
    LOSSLESS_DTYPE,
    LOSSLESS_ROOT,
    LOSSLESS_ROOT_SLOT,
    QUANT_ROOT,
    StreamError,
    StreamInfo,
    _QUANT_WORDS,
    _check_magic,
    _fixed_size,
    _header_size_if_known,
    _parse_header,
    check_template,
    crc8,
    crc8_indexed,
    quant_steps,
)


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


def _claim(table: np.ndarray, keys: np.ndarray, ids: np.ndarray):
    """Claim each key (a parent's child slot, a root row) for a record, stored as its index + 1
    (0: free): scatter, read back. Returns None when every key was free and distinct, else the
    position in `keys` of the first record whose key an earlier one (this batch or any before)
    holds; then only the records before it keep their claims, so the kept prefix's forest keeps
    every link (a duplicate would have overwritten its earlier twin's)."""
    old = table.take(keys)
    table[keys] = ids
    if old.max() == 0 and (table.take(keys) == ids).all():
        return None
    first = np.zeros(len(keys), bool)
    first[np.unique(keys, return_index=True)[1]] = True
    j = int(np.argmax((old > 0) | ~first))
    table[keys] = old
    table[keys[:j]] = ids[:j]
    return j


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


def _lossless_values_bad(rows: np.ndarray):
    """(bad, big) per lossless record of rows [n, 73]: bad where a float is not finite or a
    log-scale component is at or above LOG_SCALE_MAX (its scale exp(.) would be infinite in
    float32: the Avatar constructor's own limit, which the reader's trusted Avatar.from_verified
    relies on the records having passed); big where the latter holds."""
    f = rows[:, 4:72].copy().view("<f4")  # split_logits, d_mu, d_log_scale, d_rot, opacity, f_dc
    big = np.any(f[:, 6:9] >= LOG_SCALE_MAX, axis=1)  # (float32 against the same bound as Avatar)
    return ~np.all(np.isfinite(f), axis=1) | big, big


def _invalid_record(rows, big, i0: int, k: int) -> str:
    """The problem of record i0 + k, the first of its batch that breaks a rule of FORMAT.md 3."""
    if big is not None and big[k]:
        ls = rows[k, 28:40].copy().view("<f4")
        return (
            f"record {i0 + k} is invalid: its log-scale {float(ls.max()):g} is at or above "
            f"{LOG_SCALE_MAX:.2f} (its scale would be infinite)"
        )
    return f"record {i0 + k} is structurally invalid (parent/slot/level/root marker/reserved bits/values)"


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
        # The last records a downloader could not tie to the file the header came from (set by
        # core/stream/http.py's fetch_stream, FetchResult.unconfirmed): a resume re-checks them.
        self.unconfirmed = 0
        self._lut_cache = None

    # -- public state --------------------------------------------------------------------
    @property
    def num_gaussians(self) -> int:
        return self._n

    @property
    def complete(self) -> bool:
        return self.header is not None and self._block >= self.header.num_blocks

    @property
    def pending_bytes(self) -> bytes:
        """The bytes received after the last boundary the reader verified: the header so far while
        it is incomplete, then the current block's (its records may have passed their CRC-8s, the
        block's CRC-32 has not). A downloader compares them with the source's bytes to tell a
        replaced file from damaged bytes (core/stream/http.py)."""
        return bytes(self._pending)

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
        # Every decoded value is finite and every log-scale below LOG_SCALE_MAX (so the Avatar
        # need not scan for them): lossless floats are checked per record; quantised ones are
        # affine in bounded codes (log-scale ranges within +-80, checked with the header).
        self._finite = header.lossless or bool(np.all(np.abs(header.quant) <= 1e30))
        self._raw = _Grow((R,), np.uint8, N)  # verified record bytes (decoding is lazy)
        self._child = _Grow((), np.int32, 3 * N, fill=0)  # 1 + record index per parent*3 + slot; N < 2^30
        self._level_starts = np.concatenate([[0], header.level_ends()]).astype(np.int64)
        self._starts_list = [int(x) for x in self._level_starts]
        self._cols = _Columns(N)
        # Records that must be roots, by position: versions 1-2 the template faces in template
        # order; versions 3-4 every coarse level and the template level, version 5 the coarse
        # levels (the template level without them); from version 3 each root names its row of
        # the root table. Version 5 roots after those carry a root flag.
        self._nroots = header.lead_records
        self._v5 = header.version >= 5
        self._root_ref = _Grow((), np.int64, N if self._v5 else self._nroots)  # by stream position
        self._root_claim = _Grow((), np.int32, header.num_roots, fill=0)
        if self._v5:
            self._isroot = _Grow((), np.bool_, N, fill=0)
            self._lev = _Grow((), np.int16, N)
            self._level_received = np.zeros(header.num_levels, np.int64)

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
        if self._v5:
            return self._check_range_v5(i0, i1)
        n = i1 - i0
        rows, rec, par, slt = self._structure(i0, i1, self._cols.cols)
        if h.lossless:
            bad, big = _lossless_values_bad(rows)
            bad |= slt == 3  # two link bits: slot 3 is possible, and invalid
            root_val = LOSSLESS_ROOT
        else:
            bad = slt >= 3  # slot 3 or a reserved bit set (slt holds all four top bits here)
            big = None
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
            self._check_lead_rows(i0, nr, par, bad)
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
            problem = _invalid_record(rows, big, i0, k)
        # (parent, slot) must be unique: scatter the record indices, read them back.
        if k > nr:
            keys = par[nr:k] * 3
            keys += slt[nr:k]
            ids = np.arange(i0 + nr + 1, i0 + k + 1, dtype=np.int32)  # stored as index + 1 (0: free)
            j = _claim(self._child.reserve(3 * (i0 + k)), keys, ids)
            if j is not None:
                k = nr + j
                problem = f"record {i0 + k} reuses the child slot of an earlier record"
        if h.version >= 3 and min(k, nr):
            m = min(k, nr)  # each root row at most once
            refs = par[:m].copy()
            j = _claim(self._root_claim.reserve(self._nroots), refs, np.arange(i0 + 1, i0 + m + 1, dtype=np.int32))
            if j is not None:
                k = j
                problem = f"record {i0 + k} names a root triangle an earlier record already holds"
            self._root_ref.reserve(i0 + m)[i0 : i0 + min(k, m)] = refs[: min(k, m)]
        if nr:
            par[:nr] = -1
            slt[:nr] = -1
        self._cols.valid["parent"] = self._cols.valid["slot"] = i0 + k
        return k, problem

    def _check_lead_rows(self, i0, nr, par, bad, lev=None) -> None:
        """The batch's first nr records (from i0) lie in the lead, roots by position: each names a
        row of its own level's range of the root table (rows are grouped like the lead's records).
        Marks those that do not in `bad`; stores each record's level in `lev` when given."""
        starts = self._starts_list
        for lv in range(bisect.bisect_right(starts, i0) - 1, bisect.bisect_right(starts, i0 + nr - 1)):
            x, y = max(starts[lv], i0) - i0, min(starts[lv + 1], i0 + nr) - i0
            off = np.subtract(par[x:y], starts[lv])
            bad[x:y] |= off.view(np.uint64) >= np.uint64(starts[lv + 1] - starts[lv])
            if lev is not None:
                lev[i0 + x : i0 + y] = lv

    def _check_range_v5(self, i0: int, i1: int):
        """Version 5 structure (FORMAT.md 3): the lead records (coarse levels) by position as in
        version 4; after them each record is a root (its flag set, a template row) or names
        its parent's stream index p < i, a parent below the coarse levels, its level within
        the header's levels and their counts. Stores parent (stream index), slot, root flag
        and level per record; claims (parent, slot) and root rows as version 4 does."""
        h = self.header
        n = i1 - i0
        rows, rec, par, slt = self._structure(i0, i1, self._cols.cols)
        K, L = h.num_coarse_levels, h.num_levels
        starts = self._starts_list
        idx = np.arange(i0, i1, dtype=np.int64)
        big = None
        if h.lossless:
            bad, big = _lossless_values_bad(rows)
            root = slt == LOSSLESS_ROOT_SLOT
        else:
            root = (slt & 4) != 0
            bad = slt >= 8  # geo bit 63 is reserved
            bad |= root & ((slt & 3) != 0)  # a root's slot is 0
            bad |= slt == 3  # slot 3 does not exist
            b = np.right_shift(rec["b0"], np.uint16(4))
            b += rec["b1"] & np.uint16(0xFFF)
            bad |= b > np.uint16(4095)
        np.bitwise_and(slt, 3, out=slt)
        slt[root] = 0
        lev = self._lev.reserve(i1)
        nr = max(0, min(n, self._nroots - i0))  # lead records in this batch: roots by position
        bad[:nr] |= ~root[:nr]
        if nr:
            self._check_lead_rows(i0, nr, par, bad, lev)
        late = root.copy()
        late[:nr] = False  # roots after the lead: template faces (rows of level K)
        if K:
            off = np.subtract(par, starts[K])
            bad |= late & (off.view(np.uint64) >= np.uint64(starts[K + 1] - starts[K]))
            lev[i0:i1][late] = K
        else:
            bad |= late  # without coarse levels the lead holds every root
        bad |= ~root & (par >= idx)  # a parent precedes its child
        k = int(np.argmax(bad)) if bad.any() else n
        # Levels of the non-roots before the first bad record: a parent's level plus one
        # (those whose parent is in this batch settle in one more pass per level they span).
        nz = np.flatnonzero(~root[:k])
        if len(nz):
            p = par[nz]
            own = lev[i0:i1]
            own[nz] = np.minimum(lev[p] + 1, L)  # final where the parent came in an earlier batch
            inner = np.flatnonzero(p >= i0)
            q, at = p[inner], nz[inner]
            for _ in range(L):
                new = np.minimum(lev[q] + 1, L)
                if np.array_equal(new, own[at]):
                    break
                own[at] = new
            wrong = (lev[p] < K) | (own[nz] >= L)  # coarse faces have no children; levels < L
            if wrong.any():
                k = int(nz[np.argmax(wrong)])
        # Each level holds at most the header's count of records.
        got = lev[i0 : i0 + k]
        full = np.asarray(h.level_counts) - self._level_received  # records each level can still take
        for lv in np.flatnonzero(np.bincount(got, minlength=L)[:L] > full):  # (rarely any)
            k = min(k, int(np.flatnonzero(got == lv)[full[lv]]))
        problem = None
        if k < n:
            problem = _invalid_record(rows, big, i0, k)
        # (parent, slot) unique among non-roots; root rows unique among roots.
        nz = np.flatnonzero(~root[:k])
        if len(nz):
            keys = par[nz] * 3
            keys += slt[nz]
            j = _claim(self._child.reserve(3 * (i0 + k)), keys, (idx[nz] + 1).astype(np.int32))
            if j is not None:
                k = int(nz[j])
                problem = f"record {i0 + k} reuses the child slot of an earlier record"
        rz = np.flatnonzero(root[:k])
        if len(rz):
            refs = par[rz].copy()
            j = _claim(self._root_claim.reserve(h.num_roots), refs, (idx[rz] + 1).astype(np.int32))
            if j is not None:
                k = int(rz[j])
                problem = f"record {i0 + k} names a root triangle an earlier record already holds"
                rz = rz[:j]
            self._root_ref.reserve(i1)[i0 + rz] = refs[: len(rz)]
        self._isroot.reserve(i1)[i0 : i0 + k] = root[:k]
        self._level_received += np.bincount(lev[i0 : i0 + k], minlength=L)[:L]
        par[root] = -1
        slt[root] = -1
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
            self._decode_rows(self._raw.data[a:b], {name: cols[name][a:b] for name in PARAM_NAMES + ("split_logits",)})
            if self.header.exceptions is not None:
                _apply_exceptions(cols, self.header.exceptions, a, b)
        for name in PARAM_NAMES + ("split_logits",):
            self._cols.valid[name] = b
        self._decoded = b

    def _decode_rows(self, raw, out: dict) -> None:
        """Record bytes raw [n,R] into the float32 columns of `out` (exceptions not applied)."""
        if self.header.lossless:
            rec = raw.view(LOSSLESS_DTYPE)[:, 0]
            for name, dst in out.items():
                dst[...] = rec[name]
            return
        n = len(raw)
        scratch = _decode_scratch(min(_RUN, n))
        for c0 in range(0, n, _RUN):  # cache-sized runs: small, reused temporaries
            _decode_quantised(raw[c0 : c0 + _RUN], {k: v[c0 : c0 + _RUN] for k, v in out.items()}, self._steps, scratch)

    @property
    def _steps(self):
        if self._lut_cache is None:
            self._lut_cache = quant_steps(self.header.quant)
        return self._lut_cache

    def arrays(self, n=None) -> dict | None:
        """Decoded arrays of the first n available records (all if None), in stream order
        (views; do not modify). None exactly when ``avatar(n)`` is None: before the header has
        arrived, or while no record is available (or n is 0)."""
        if self.header is None or self._n == 0:
            return None
        n = self._n if n is None else max(0, min(int(n), self._n))
        if n == 0:
            return None
        self._decode()
        cols = self._reserve_cols(n)
        return {name: cols[name][:n] for name in ("split_logits",) + PARAM_NAMES + ("parent", "slot")}

    def avatar(self, n=None) -> Avatar | None:
        """An Avatar of the first n available Gaussians (all if None), its faces the roots in
        stream order, then the others in stream order (just stream order before version 5);
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
        if not self._v5:
            self._decode()
        h = self.header
        c = self._cols
        if self._v5:
            forest, params = self._forest_v5(tmpl, n)
        else:
            forest = self._forest(tmpl, n)
            params = None
        meta = dict(h.metadata)
        meta["stream"] = {
            "records": n,
            "total_records": h.num_records,
            "base_complete": forest.num_roots == h.num_roots,
            "head_complete": n >= h.head_records,
            "coarse_levels": h.num_coarse_levels,
            "lossless": h.lossless,
            "template_hash": h.template_hash_hex,
            "bytes": h.bytes_for_count(n),
            "total_bytes": h.total_bytes,
        }
        if params is None:
            params = [c.hand_out(name, n) for name in PARAM_NAMES]
        if self._finite:
            # Verified record by record: no second validation pass (the format carries SH degree 0).
            return Avatar.from_verified(forest, dict(zip(PARAM_NAMES, params)), meta)
        return Avatar(forest, *params, meta=meta)

    def _forest_v5(self, tmpl, n):
        """(forest, parameter arrays) of the first n records of a version 5 stream: the roots in
        stream order, then the other records in stream order (parents still precede children);
        the forest's root_rank keeps where each root arrived. The verified record bytes are
        gathered into that order once (one row copy each) and decoded there, so the parameters
        need no second permutation."""
        h = self.header
        cols = self._cols.cols
        is_root = self._isroot.data[:n]
        rpos = np.flatnonzero(is_root)
        r = len(rpos)
        dec = np.empty(n, np.int64)  # face -> stream position
        dec[:r] = rpos
        dec[r:] = np.flatnonzero(~is_root)
        pos = np.empty(n, np.int64)
        pos[dec] = np.arange(n)  # stream position -> face
        parent = np.full(n, -1, np.int64)
        np.take(pos, cols["parent"][dec[r:]], out=parent[r:])
        slot = np.full(n, -1, np.int8)
        slot[r:] = cols["slot"][dec[r:]]
        level = self._lev.data[dec].astype(np.int8)
        root = np.arange(n, dtype=np.int64)
        root[r:] = parent[r:]
        for _ in range(max(int(h.num_levels - h.num_coarse_levels - 1), 0).bit_length()):  # pointer jumping
            np.take(root, root, out=root)
        children = np.full((n, 3), -1, np.int64)
        keys = parent[r:] * 3
        keys += slot[r:]
        children.reshape(-1)[keys] = np.arange(r, n)  # (parent, slot) pairs verified unique
        R = h.record_size
        raw = np.take(self._raw.data[:n].view(np.dtype((np.void, R))).ravel(), dec).view(np.uint8).reshape(n, R)
        out = _carve(tuple((name, tail, dt) for name, tail, dt in _COLUMNS if name not in ("parent", "slot")), n)
        self._decode_rows(raw, out)
        if h.exceptions is not None:
            idx, comp, val = h.exceptions
            held = idx < n
            _apply_exceptions(out, (pos[idx[held]], comp[held], val[held]), 0, n, sorted_idx=False)
        K = h.num_coarse_levels
        forest = Forest.from_verified(
            np.asarray(tmpl, np.int32),
            parent,
            slot,
            out["split_logits"],
            children,
            level,
            root,
            coarse_faces=h.coarse_faces if K else np.zeros((0, 3), np.int32),
            coarse_counts=tuple(h.level_counts[:K]),
            root_ref=self._root_ref.data[rpos].copy(),
            root_rank=rpos,
            stand_ins=h.coarse_retire is not None,
            retire=h.coarse_retire,
            backdrop=h.backdrop,
        )
        return forest, [out[name] for name in PARAM_NAMES]

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
            stand_ins=h.coarse_retire is not None,
            retire=h.coarse_retire,
            backdrop=h.backdrop,
        )


def _apply_exceptions(cols, exceptions, a: int, b: int, sorted_idx: bool = True) -> None:
    """Version 4 (FORMAT.md 3.2): the exceptions of records a..b-1 replace their decoded
    components with the exact values (vectorised per parameter, never per record). With
    ``sorted_idx`` False the indices are rows of `cols` already (any order, all kept)."""
    idx, comp, val = exceptions
    if sorted_idx:
        i, j = np.searchsorted(idx, [a, b])
        if i == j:
            return
        idx, comp, val = idx[i:j], comp[i:j], val[i:j]
    for name, first, width in (("d_mu", 0, 3), ("d_log_scale", 3, 3), ("f_dc", 6, 3), ("d_rot", 9, 4)):
        sel = (comp >= first) & (comp < first + width)
        if sel.any():
            cols[name][idx[sel], comp[sel] - first] = val[sel]


def read_stream(source, *, percent=None, max_bytes=None, max_gaussians=None, template_faces=None) -> Avatar | None:
    """Decode a stream (path or bytes) to an Avatar (faces: the roots in stream order, then the
    others in stream order; ``avatar.forest.stream_ids(n)`` are the first n records' faces).

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
            # One byte past the stream tells that trailing bytes exist: a file far longer than
            # its stream is never read whole.
            body = fh.read(end - H + (n == h.num_records))
        if not is_bytes and len(body) > end - H:
            reader.feed(body[: end - H])  # (a corrupt record is the first thing to report)
            raise StreamError(f"{name}: unexpected bytes after the end of the stream (offset {h.total_bytes})")
        if len(body):
            reader.feed(body)
    finally:
        if fh is not None:
            fh.close()
    return reader.avatar(n)
