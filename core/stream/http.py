"""Progressive download of a stream over HTTP(S) (standard library only: runs in Blender).

Any static server or CDN will do: the client asks for byte ranges (one request per chunk, so a
receiver can stop at any budget and a dropped connection costs one chunk), and falls back to
reading a plain GET incrementally when the server ignores Range. Every piece goes through a
StreamReader, so what has been received is verified as it arrives and survives a stall, a cut
connection or an HTTP error: the result says what happened and keeps the verified Gaussians.

Failures of the transfer come back as a status; mistakes of the caller do not: bad arguments
raise ValueError before any request, and an exception raised by the caller's on_chunk (or by a
caller's StreamReader subclass, other than the reader's own verdict on the bytes) propagates
unchanged.
"""

from __future__ import annotations

import http.client
import math
import numbers
import operator
import re
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from urllib.parse import urljoin, urlsplit

from .format import FIXED_SIZE, FIXED_SIZE_MAX, StreamError, _fixed_size, _parse_fixed, percent_bytes
from .reader import StreamReader

COMPLETE = "complete"  # the whole stream arrived and verified
BUDGET = "budget"  # stopped at the requested budget (everything inside it verified)
STALLED = "stalled"  # no byte for `timeout` seconds
CUT = "connection_cut"  # the server closed or reset the connection mid-body
HTTP_ERROR = "http_error"  # a non-success HTTP status (or a malformed response)
UNREACHABLE = "unreachable"  # could not connect at all
CORRUPT = "corrupt"  # the bytes failed verification (checksum or structure)
REFUSED = "refused"  # valid bytes the reader cannot use here (e.g. a stream made for another template)
CANCELLED = "cancelled"  # the callback asked to stop
CHANGED = "changed"  # the file on the server was replaced mid-download: discard what arrived
DEADLINE = "deadline"  # the total `deadline` passed
TOO_SLOW = "too_slow"  # fewer than `min_rate` bytes/s over a `rate_window`
# The file on the server is shorter than its stream header announces (an interrupted upload): its
# verified prefix is kept, but resuming cannot help until the file is replaced.
TRUNCATED = "truncated"

_CONTENT_RANGE = re.compile(r"bytes\s+(\d+)-(\d+)/(\d+|\*)")
_UNSATISFIED_RANGE = re.compile(r"bytes\s+\*/(\d+)")  # a 416's Content-Range: the file's size


class _CallerError(Exception):
    """Carries an exception raised by the caller's code (on_chunk, a StreamReader subclass) past
    fetch_stream's handlers, which classify failures of the transfer, not the caller's bugs."""

    def __init__(self, error):
        super().__init__(error)
        self.error = error


def _split_url(url):
    """(parts, None) for a usable http(s) URL, else (None, why not): http.client would raise
    on a missing host or a bad port instead of failing the request."""
    try:
        parts = urlsplit(url)
        parts.port  # raises ValueError for a port out of range or not a number
    except ValueError as exc:
        return None, str(exc)
    if parts.scheme not in ("http", "https"):
        return None, f"unsupported URL scheme {parts.scheme!r}"
    if not parts.hostname:
        return None, "no host"
    return parts, None


def _request_path(parts) -> str:
    return (parts.path or "/") + (f"?{parts.query}" if parts.query else "")


def _check_args(timeout, chunk_size, read_size, max_bytes, percent, max_redirects, headers, validator):
    """Raise ValueError for arguments no download can honour (they would otherwise fail deep in
    http.client or socket and come back as a misleading status, or be silently ignored)."""

    def integer(name, v, low):
        try:
            n = operator.index(v)
        except TypeError:
            raise ValueError(f"fetch_stream: {name} must be an integer, got {v!r}") from None
        if n < low:
            raise ValueError(f"fetch_stream: {name} must be >= {low}, got {v!r}")

    integer("chunk_size", chunk_size, 1)
    integer("read_size", read_size, 1)
    integer("max_redirects", max_redirects, 0)
    if max_bytes is not None:
        integer("max_bytes", max_bytes, 0)
    if timeout is not None and not (
        isinstance(timeout, numbers.Real) and not isinstance(timeout, bool) and math.isfinite(timeout) and timeout > 0
    ):
        raise ValueError(f"fetch_stream: timeout must be a positive number of seconds, got {timeout!r}")
    if percent is not None:
        try:
            ok = 0.0 <= float(percent) <= 100.0  # False for NaN
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"fetch_stream: percent must be a number in [0, 100], got {percent!r}")
    sent = {**(headers or {}), **({} if validator is None else {"If-Range": validator})}
    if sent:
        # http.client itself checks each header (no connection is made: putrequest and putheader
        # only build the request), so a bad one fails here, not as a status mid-download.
        probe = http.client.HTTPConnection("localhost")
        probe.putrequest("GET", "/", skip_host=True, skip_accept_encoding=True)
        for k, v in sent.items():
            try:
                probe.putheader(k, v)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"fetch_stream: bad header {k!r}: {exc}") from None


@dataclass
class FetchResult:
    status: str
    reader: StreamReader
    url: str
    http_status: int | None = None
    used_ranges: bool | None = None  # None: undecided (no successful response yet)
    requests: int = 0
    seconds: float = 0.0
    message: str = ""
    events: list = field(default_factory=list)
    # The server's validator for the file (strong ETag, else Last-Modified): pass it back as
    # `validator=` when resuming with the same reader so a replaced file is detected.
    validator: str | None = None
    # Verified Gaussians at the end that could not be tied to the file the header came from (no
    # strong ETag, no block CRC-32 over them, and re-reading the server's bytes failed): not kept.
    # The reader remembers them (reader.unconfirmed): a resume with it checks them again.
    unconfirmed: int = 0

    @property
    def ok(self) -> bool:
        return self.status in (COMPLETE, BUDGET)

    @property
    def num_gaussians(self) -> int:
        return self.reader.num_gaussians

    @property
    def bytes_received(self) -> int:
        return self.reader.bytes_received

    @property
    def keepable_gaussians(self) -> int:
        """The verified Gaussians a caller may keep: none when the file changed on the server
        mid-download (what arrived is a prefix of the old file, not of the one at the URL now),
        and not the `unconfirmed` ones at the end."""
        return 0 if self.status == CHANGED else self.reader.num_gaussians - self.unconfirmed

    def avatar(self):
        return self.reader.avatar()

    def __str__(self):
        return (
            f"{self.status}: {self.num_gaussians} Gaussians verified from {self.bytes_received} bytes of "
            f"{self.url} ({self.requests} requests{', ranges' if self.used_ranges else ''}) {self.message}"
        ).strip()


class _Watchdog:
    """Enforces the total deadline and the minimum rate from a helper thread: per-socket
    timeouts cannot, since a server dripping a byte every few tenths of a second (even inside
    the response headers) never trips them. On a violation it shuts the socket down, which
    wakes the blocked read; the fetch loop then reports the reason."""

    def __init__(self, received, deadline, min_rate, rate_window):
        # received(): bytes read from the network so far, re-read ones included (a resume from a
        # server that ignores Range re-downloads the held prefix: that is progress too)
        self.received, self.deadline, self.min_rate, self.window = received, deadline, min_rate, rate_window
        self.reason = None
        self.message = ""
        self.conn = None
        self._stop = threading.Event()
        self._thread = None
        self.t_start = time.monotonic()
        if deadline is not None or min_rate is not None:
            self._thread = threading.Thread(target=self._run, name="fetch_stream-watchdog", daemon=True)
            self._thread.start()

    def _run(self):
        t0 = time.monotonic()
        w0, b0 = t0, self.received()
        while not self._stop.wait(0.05):
            now = time.monotonic()
            if self.reason:
                pass
            elif self.deadline is not None and now - t0 >= self.deadline:
                self.reason, self.message = DEADLINE, f"total deadline of {self.deadline} s passed"
            elif self.min_rate is not None and now - w0 >= self.window:
                got = self.received() - b0
                if got < self.min_rate * (now - w0):
                    self.reason = TOO_SLOW
                    self.message = (
                        f"{got} bytes in {now - w0:.1f} s, under the minimum rate of {self.min_rate:g} bytes/s"
                    )
                w0, b0 = now, self.received()
            if self.reason:
                # Until stopped: a socket still connecting (none yet) is shut down once it exists.
                sock = getattr(self.conn, "sock", None)
                if sock is not None:
                    try:
                        sock.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass

    def remaining(self, timeout: float) -> float:
        """The longest a blocking step may wait: `timeout`, or less when the deadline is nearer."""
        if self.deadline is None:
            return timeout
        return max(0.001, min(timeout, self.deadline - (time.monotonic() - self.t_start)))

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)


def _strong(validator: str | None) -> bool:
    """A strong ETag (quoted, not W/): the one validator that names the file's exact bytes."""
    return bool(validator) and validator.startswith('"')


def _validator(resp) -> str | None:
    """A strong ETag, else Last-Modified: what If-Range may carry (RFC 9110 13.1.5)."""
    etag = resp.getheader("ETag")
    if etag and not etag.startswith("W/"):
        return etag
    return resp.getheader("Last-Modified")


def fetch_stream(
    url: str,
    *,
    reader: StreamReader | None = None,
    template_faces=None,
    chunk_size: int = 1 << 20,
    read_size: int = 1 << 16,
    timeout: float = 10.0,
    on_chunk=None,
    max_bytes: int | None = None,
    percent: float | None = None,
    headers: dict | None = None,
    max_redirects: int = 5,
    deadline: float | None = None,
    min_rate: float | None = 1024.0,
    rate_window: float = 10.0,
    validator: str | None = None,
) -> FetchResult:
    """Download `url` progressively into a StreamReader (a new one, or `reader` to resume).

    on_chunk(reader, new_gaussians) runs after each piece (every `read_size` bytes at most);
    returning False stops the download ("cancelled"); an exception it raises propagates.
    `timeout` is the longest wait for any byte; `deadline` (seconds, None: none) bounds the
    whole download and `min_rate` (bytes/s, None: none) the pace over each `rate_window`
    seconds, response headers included ("deadline", "too_slow"). max_bytes / percent (of the
    stream's size, FORMAT.md section 6) stop early ("budget"); a percent budget is exact from
    the first request (the fixed header part is fetched alone first, again by a resumed reader
    that lacks its header rather than overshoot). Range requests carry If-Range with the file's
    ETag or Last-Modified (`validator` to resume an earlier fetch): if the file changes on the
    server the result is "changed" and the bytes received belong to the old file: discard them.
    Without a strong ETag (none, or a Last-Modified, which has one-second resolution) a file
    replaced by one of the same size within that second passes If-Range and the size check, so
    the server's bytes are compared with what this fetch holds: a resumed reader first re-reads
    the 4 bytes of the header's CRC-32; a verification failure whose bytes came in more than
    one response, and an end (budget, cancel, cut, ...) leaving verified records that neither
    the header nor a block CRC-32 in their own response tied to the header's file, re-read the
    header's CRC and the bytes received since the last verified block. Any difference is
    "changed"; a re-read that fails leaves those records out of keepable_gaussians
    (`unconfirmed`). Undetectable: a replacement whose header is byte-identical, falling exactly
    between two blocks received (every block verifies against the header, and the incomplete
    one holds only the new file's bytes): the avatar mixes the two files' records. Only a strong
    ETag rules it out. A body sent with a Content-Encoding other than identity is an "http_error"
    naming it. The minimum rate counts every byte read, a held prefix re-read included.
    A file on the server shorter than its header announces ends "truncated" (its verified
    prefix kept; resuming cannot help). A URL, or a redirect's, without a host, with a bad port
    or a scheme other than http(s) is an "http_error" naming it. Bad arguments raise ValueError
    before any request.
    """
    _check_args(timeout, chunk_size, read_size, max_bytes, percent, max_redirects, headers, validator)
    for name, v in (("deadline", deadline), ("min_rate", min_rate), ("rate_window", rate_window)):
        if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"fetch_stream: {name} must be a positive number of seconds or bytes/s, got {v!r}")
    pct = None if percent is None else float(percent)
    reader = reader if reader is not None else StreamReader(template_faces, source=url)
    res = FetchResult(UNREACHABLE, reader, url, validator=validator)
    t0 = time.monotonic()
    conn = None
    redirects = 0
    use_ranges = True
    total_seen = None  # the file size a Content-Range reported first
    # The fixed header part (bytes from offset 0), kept while the stream's size is unknown. A
    # fresh download collects it from what it feeds; a resumed reader's earlier bytes are not
    # ours to read, so with a percent budget they are requested again (see need_head).
    head = bytearray()
    fixed_total = [None]  # stream size implied by the fixed part (before the whole header)
    wire = [0]  # body bytes read from the network, re-read ones included (the watchdog's rate)
    # A resumed reader's records were decoded with its header: without a strong ETag (none, or a
    # Last-Modified of one-second resolution) a file replaced since would pass each record's own
    # CRC-8, so the first request re-reads the header's CRC-32 and compares it.
    h0 = reader.header
    verify = h0 is not None and reader.bytes_received >= h0.header_size and not _strong(validator)
    crc_at = h0.header_size - 4 if verify else 0
    resumed = reader.bytes_received > 0
    # What the server's bytes are compared with (see replaced): the header's CRC, and the bytes
    # received since the last block boundary the reader verified (`tail`, at stream offset
    # tail_at[0]; a resumed reader's own included), whose records no block CRC-32 has tied yet.
    tail = bytearray(reader.pending_bytes)
    tail_at = [reader.bytes_received - len(tail)]
    # One response is one version of the file: the records of a response that completed the
    # header or a block are tied to the header's file (`sure`: how many records are); those of
    # one that did neither are re-checked at the end (settle). A resumed reader's last records
    # that an earlier fetch could not tie (reader.unconfirmed) are not tied yet either.
    sure = [reader.num_gaussians - getattr(reader, "unconfirmed", 0)]
    resp_from = [0]  # reader.bytes_received when the current response began
    tied = [False]  # the current response completed the header or a block, or re-read the header CRC
    bad_url = "bad URL"  # how an unusable target is named: the caller's URL, or a redirect's

    def limit() -> int | None:
        """Bytes wanted in total (None: unknown until the header arrives)."""
        lim = 0 if pct == 0.0 else None
        h = reader.header
        total = h.total_bytes if h is not None else fixed_total[0]
        if total is not None:
            lim = total if lim is None else lim
            if pct is not None:
                lim = min(lim, percent_bytes(pct, total))  # what count_for_percent means
        if max_bytes is not None:
            lim = max_bytes if lim is None else min(lim, max_bytes)
        return lim

    def need_head() -> bool:
        """A percent budget needs the stream's size before the bytes it would overshoot: the
        fixed header part comes first, alone (re-fetched when a resumed reader lacks it)."""
        return pct is not None and reader.header is None and fixed_total[0] is None

    def request_cap() -> int | None:
        """Where the next request must end: the budget, or with a percent budget and no
        header yet, the fixed header part (its fields give the stream's size)."""
        lim = limit()
        if need_head():
            lim = FIXED_SIZE_MAX if lim is None else min(lim, FIXED_SIZE_MAX)
        return lim

    def finished() -> str | None:
        if reader.complete:
            return COMPLETE
        lim = limit()
        if lim is not None and reader.bytes_received >= lim:
            return BUDGET
        return None

    def take_head(data, at):
        """Keep the fixed-part bytes among `data` (stream offset `at`) until its fields are known."""
        n = len(head)
        if fixed_total[0] is not None or not (at <= n < min(at + len(data), FIXED_SIZE_MAX)):
            return
        head.extend(bytes(data[n - at : FIXED_SIZE_MAX - at]))
        # The fixed part is 56 bytes up to version 2, 60 in version 3, 64 from version 4 (its version
        # field, inside the first 56, says which).
        if len(head) >= FIXED_SIZE and len(head) >= _fixed_size(head):
            f = _parse_fixed(head, url)
            fixed_total[0] = (
                f["header_size"]
                + f["num_records"] * f["record_size"]
                + 4 * -(-f["num_records"] // f["records_per_block"])
            )

    def replaced(data, at, whole=False) -> bool:
        """Set CHANGED when `data`, the server's bytes at stream offset `at`, differ from those
        held there: the header CRC the reader decoded its records with, or `tail`. (Compared
        byte by byte where they overlap: a piece may hold part of either.) `whole`: `data` comes
        from a 200 answer, the server sending the file from its start (it ignores ranges)."""
        h = reader.header
        held = [] if h is None else [(h.header_size - 4, struct.pack("<I", h.header_crc), "header CRC differs")]
        held.append((tail_at[0], tail, "bytes {}..{} differ from those received"))
        for lo, ref, what in held:
            a, b = max(lo, at), min(lo + len(ref), at + len(data))
            if a < b and bytes(data[a - at : b - at]) != ref[a - lo : b - lo]:
                same = f"same size{' and validator' if res.validator else ''}"
                why = (
                    f"{same}; the server ignores ranges and sent it again"
                    if whole
                    else f"{same}, so If-Range could not tell"
                )
                res.status = CHANGED
                res.message = (
                    f"the file at {target} changed "
                    f"{'since the earlier fetch or during this one' if resumed else 'mid-download'} "
                    f"(its {what.format(a, b - 1)}; {why}); the {reader.bytes_received} bytes received are not "
                    "all the file's now there: discard them"
                )
                return True
        return False

    def reread(lo, size) -> bytes | None:
        """The server's `size` bytes at stream offset `lo` now: one range request without
        If-Range, on a new connection. None when no usable answer came; a changed validator or
        file size sets CHANGED (and gives None)."""
        parts, problem = _split_url(target)
        if problem or dog.reason:  # a deadline passed or the server is too slow: no more requests
            return None
        cls = http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection
        c = cls(parts.hostname, parts.port, timeout=dog.remaining(timeout))
        dog.conn = c  # the deadline and the minimum rate hold for it too (a dripping answer)
        hdrs = {"Accept-Encoding": "identity", **(headers or {}), "Range": f"bytes={lo}-{lo + size - 1}"}
        try:
            c.request("GET", _request_path(parts), headers=hdrs)
            res.requests += 1
            resp = c.getresponse()
            m = _CONTENT_RANGE.match(resp.getheader("Content-Range") or "")
            if resp.status != 206 or not m or int(m.group(1)) != lo or int(m.group(2)) < lo + size - 1:
                return None
            if (resp.getheader("Content-Encoding") or "identity").strip().lower() != "identity":
                return None
            if changed(resp, "validator") or (m.group(3) != "*" and resized(int(m.group(3)))):
                return None
            got = resp.read(size)
            wire[0] += len(got)
            return got if len(got) == size else None
        except (OSError, http.client.HTTPException, ValueError):  # ValueError: a host IDNA cannot encode
            return None
        finally:
            c.close()

    def settle():
        """Run before a result is returned (see the docstring): re-read the header CRC and `tail`
        when the end leaves received bytes untied to one file."""
        n = reader.num_gaussians
        if _strong(res.validator) or res.status in (COMPLETE, CHANGED, REFUSED):
            return
        if n <= sure[0] and not (res.status == CORRUPT and resp_from[0] > 0):
            return  # (a failure inside the one response that brought every byte is corruption)
        was = res.message if res.status == CORRUPT else ""
        h = reader.header
        for lo, size in ([(h.header_size - 4, 4)] if h is not None else []) + [(tail_at[0], len(tail))]:
            if size == 0:
                continue
            got = reread(lo, size)
            if got is None or replaced(got, lo):
                break
        else:
            sure[0] = n  # the server holds what arrived: a corrupt file stays "corrupt"
            return
        if res.status == CHANGED:
            if was:
                res.message += f" (what arrived failed verification: {was})"
            return
        res.unconfirmed = n - sure[0]
        if res.unconfirmed:
            why = f"re-reading it failed: {dog.message}" if dog.reason else "re-reading it failed"
            note = (
                f"{res.unconfirmed} Gaussians at the end, in no block verified in their response, could "
                f"not be checked against the file at {target} (no strong ETag; {why}): not kept"
            )
            res.message = f"{res.message}; {note}" if res.message else note

    def feed(data, at) -> bool:
        """Take the bytes at stream offset `at`: note the fixed part, feed the reader what it
        lacks (bytes it holds were only re-read for the fixed part), call back. False: stop
        (cancelled by the callback, or refused by the reader; res says which)."""
        wire[0] += len(data)
        take_head(data, at)
        skip = reader.bytes_received - at
        if skip >= len(data):
            return True
        if skip > 0:
            data = data[skip:]
        tail.extend(data)
        try:
            new = reader.feed(data)
        except StreamError:
            raise  # failed verification: "corrupt"
        except ValueError as exc:  # valid bytes the reader refuses (template mismatch, ...)
            res.status, res.message = REFUSED, str(exc)
            return False
        except Exception as exc:  # a caller's StreamReader subclass failing (e.g. its own file)
            raise _CallerError(exc) from None
        h = reader.header
        if h is not None:
            H, S = h.header_size, h.block_bytes
            blocks = (reader.bytes_received - H) // S  # whole blocks received (each verified)
            tied[0] = tied[0] or resp_from[0] < H or blocks > (resp_from[0] - H) // S
            if tied[0]:
                sure[0] = reader.num_gaussians
            cut = min(H + blocks * S, reader.bytes_received)
            if cut > tail_at[0]:
                del tail[: cut - tail_at[0]]
                tail_at[0] = cut
        if on_chunk is not None:
            try:
                go = on_chunk(reader, new)
            except Exception as exc:  # the caller's bug: theirs to see, not a transfer status
                raise _CallerError(exc) from None
            if go is False:
                res.status, res.message = CANCELLED, "stopped by the callback"
                return False
        return True

    def changed(resp, what) -> bool:
        """Set CHANGED when this response's validator differs from the first one's."""
        v = _validator(resp)
        if res.validator is None:
            res.validator = v
            return False
        if v is not None and v != res.validator:
            res.status = CHANGED
            res.message = (
                f"the file on the server changed mid-download ({what}: {res.validator} -> {v}); "
                f"the {reader.bytes_received} bytes received belong to the old file: discard them"
            )
            return True
        return False

    def resized(size) -> bool:
        """Set CHANGED when a response reports another file size than the first one did."""
        if total_seen is not None and size != total_seen:
            res.status = CHANGED
            res.message = (
                f"the file on the server changed mid-download (size {total_seen} -> {size}); the "
                f"{reader.bytes_received} bytes received belong to the old file: discard them"
            )
            return True
        return False

    def truncated(size):
        """The server's whole file (`size` bytes) arrived and the stream is not complete."""
        h = reader.header
        announced = h.total_bytes if h is not None else fixed_total[0]
        res.status = TRUNCATED
        if announced is None:
            res.message = f"the server's file ends after {size} bytes, inside the stream's header: truncated"
        else:
            res.message = (
                f"the server's file holds only {size} of the {announced} bytes the stream's header "
                "announces (truncated on the server, e.g. an interrupted upload); the verified prefix is kept"
            )

    dog = _Watchdog(lambda: wire[0], deadline, min_rate, rate_window)
    stalled_body = None  # set while the body of a redirect or an error response is read
    target = url
    caller_error = None
    try:
        while True:
            if dog.reason:
                break
            done = finished()
            if done:
                res.status = done
                break
            parts, problem = _split_url(target)
            if problem:
                res.status, res.message = HTTP_ERROR, f"{bad_url} {target!r}: {problem}"
                break
            path = _request_path(parts)
            start = crc_at if verify else len(head) if need_head() else reader.bytes_received
            if use_ranges and total_seen is not None and start >= total_seen:
                # Content-Range gave the file's size and every byte of it arrived: asking for
                # more only gets a 416.
                truncated(total_seen)
                break
            progress = (len(head), reader.bytes_received)
            hdrs = {"Accept-Encoding": "identity", **(headers or {})}
            lim = request_cap()
            if use_ranges:
                end = start + chunk_size - 1
                if lim is not None:
                    end = min(end, lim - 1)
                if verify:
                    end = crc_at + 3
                hdrs["Range"] = f"bytes={start}-{end}"
                if res.validator is not None:
                    hdrs["If-Range"] = res.validator
            try:
                if conn is None:
                    cls = http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection
                    conn = cls(parts.hostname, parts.port, timeout=timeout)
                    dog.conn = conn
                    # Connecting waits no longer than the deadline leaves (the watchdog has no
                    # socket to shut down until it exists); reads then wait up to `timeout`.
                    conn.timeout = dog.remaining(timeout)
                    conn.connect()
                    conn.timeout = timeout  # (a reconnect http.client makes by itself waits as long)
                    conn.sock.settimeout(timeout)
                    if dog.reason:
                        break
                conn.request("GET", path, headers=hdrs)
            except (http.client.InvalidURL, UnicodeError) as exc:
                # Characters http.client will not send (or a host name IDNA cannot encode).
                res.status, res.message = HTTP_ERROR, f"{bad_url} {target!r}: {exc}"
                break
            except OSError as exc:
                if res.requests == 0:
                    res.status, res.message = UNREACHABLE, f"cannot connect: {exc}"
                else:
                    res.status, res.message = CUT, f"connection lost: {exc}"
                break
            res.requests += 1
            resp = conn.getresponse()
            res.http_status = resp.status
            if resp.status in (301, 302, 303, 307, 308):
                loc = resp.getheader("Location")
                stalled_body = f"HTTP {resp.status} from {target}"
                resp.read(1 << 16)  # a redirect's body is short; a stalled one ends as an http_error
                stalled_body = None
                redirects += 1
                if not loc or redirects > max_redirects:
                    res.status, res.message = HTTP_ERROR, f"HTTP {resp.status}: bad or too many redirects"
                    break
                bad_url = f"HTTP {resp.status} redirected to a bad URL"
                try:
                    target = urljoin(target, loc)
                except ValueError as exc:  # e.g. an unclosed IPv6 bracket
                    res.status, res.message = HTTP_ERROR, f"{bad_url} {loc!r}: {exc}"
                    break
                conn.close()
                conn = None
                continue
            encoding = (resp.getheader("Content-Encoding") or "identity").strip().lower()
            if resp.status in (200, 206) and encoding != "identity":
                # Asked for identity; a gzip body fed as stream bytes would read as corruption.
                resp.close()
                res.status = HTTP_ERROR
                res.message = (
                    f"HTTP {resp.status} from {target}: the body is {encoding}-encoded (identity was asked for)"
                )
                break
            if resp.status == 416 and reader.complete:
                res.status = COMPLETE
                break
            if resp.status == 416:
                m = _UNSATISFIED_RANGE.match(resp.getheader("Content-Range") or "")
                if m and int(m.group(1)) <= start:
                    if changed(resp, "validator") or resized(int(m.group(1))):
                        break
                    truncated(int(m.group(1)))
                    break
            if resp.status == 206:
                cr = resp.getheader("Content-Range")
                m = _CONTENT_RANGE.match(cr or "")
                first, last = (int(m.group(1)), int(m.group(2))) if m else (None, None)
                size = int(m.group(3)) if m and m.group(3) != "*" else None
                # A range that does not start where asked, ends before it starts (which would
                # be re-requested forever) or past the file's end cannot be used.
                if not m or first != start or last < first or (size is not None and last >= size):
                    res.status, res.message = HTTP_ERROR, f"unexpected Content-Range {cr!r}"
                    break
                if changed(resp, "validator"):
                    break
                if size is not None:
                    if resized(size):
                        break
                    total_seen = size
                res.used_ranges = True
                resp_from[0], tied[0] = reader.bytes_received, False
                # A server may send more than asked (a CDN rounding ranges up to its blocks):
                # only the requested bytes are fed, so a budget holds; the rest stays unread.
                want = min(last, end) - start + 1
                got = 0
                while got < want:
                    # read1: whatever arrived (one recv), so a stall loses nothing already received
                    piece = resp.read1(min(read_size, want - got))
                    if not piece:
                        break
                    if replaced(piece, start + got):  # held bytes re-read: the resume check, the fixed part
                        return _done(res, conn, t0, dog, settle)
                    if not feed(piece, start + got):
                        return _done(res, conn, t0, dog, settle)
                    got += len(piece)
                if got < want:
                    res.status, res.message = CUT, f"range response ended after {got} of {want} bytes"
                    break
                if verify:  # the header CRC matched: go on from where the reader is
                    verify = False
                elif (len(head), reader.bytes_received) == progress:
                    # Cannot happen with the checks above; a guard against a hot loop of requests.
                    res.status, res.message = HTTP_ERROR, f"no progress from Content-Range {cr!r}"
                    break
                if last > end:  # the unread rest of an overlong range: drop the connection, not read it
                    conn.close()
                    conn = None
                    continue
                resp.read()  # nothing left; marks the response done so the connection is reusable
                if resp.will_close:
                    conn.close()
                    conn = None
                continue
            if resp.status == 200:
                # Either the server ignores Range, or (If-Range) the file changed: a 200 to a
                # conditional range request after bytes arrived with another validator.
                if reader.bytes_received == 0:
                    res.validator = res.validator or _validator(resp)
                elif changed(resp, "If-Range answered with the whole file"):
                    break
                # The server ignored Range: the body starts at byte 0. Skip what we have (noting
                # the fixed part) and read the rest incrementally on this one response.
                res.used_ranges = False
                use_ranges = False
                resp_from[0], tied[0] = reader.bytes_received, False
                pos = 0
                while pos < reader.bytes_received:
                    dropped = resp.read1(min(read_size, reader.bytes_received - pos))  # counted as it arrives
                    if not dropped:
                        break
                    wire[0] += len(dropped)
                    if replaced(dropped, pos, whole=True):
                        return _done(res, conn, t0, dog, settle)
                    take_head(dropped, pos)
                    pos += len(dropped)
                # the held header CRC and tail compared equal: this response is of the header's file
                tied[0] = reader.header is not None and pos >= reader.bytes_received
                verify = False
                while pos >= reader.bytes_received:
                    if finished():
                        break
                    lim = request_cap()
                    n = read_size if lim is None else max(1, min(read_size, lim - reader.bytes_received))
                    piece = resp.read1(n)
                    if not piece:
                        break
                    if not feed(piece, pos):
                        return _done(res, conn, t0, dog, settle)
                    pos += len(piece)
                done = finished()
                if done:
                    res.status = done
                elif resp.length == 0 or (resp.chunked and resp.isclosed()):
                    truncated(pos)  # the whole body (Content-Length, or the last chunk) arrived: the file is short
                else:
                    res.status, res.message = CUT, f"response body ended after {pos} bytes"
                break
            stalled_body = f"HTTP {resp.status} {resp.reason} from {target}"
            body = resp.read1(2048).decode("utf-8", "replace")  # what arrived
            res.status, res.message = HTTP_ERROR, f"{stalled_body}: {body[:200]}"
            break
    except _CallerError as exc:
        caller_error = exc.error
    except (socket.timeout, TimeoutError):
        if stalled_body:  # the status line said what went wrong; its body never came
            res.status, res.message = HTTP_ERROR, f"{stalled_body} (its body stalled for {timeout} s)"
        else:
            res.status, res.message = STALLED, f"no data for {timeout} s"
    except (http.client.IncompleteRead, http.client.RemoteDisconnected, ConnectionError) as exc:
        res.status, res.message = CUT, f"{type(exc).__name__}: {exc}"
    except http.client.HTTPException as exc:
        res.status, res.message = HTTP_ERROR, f"malformed response: {type(exc).__name__}: {exc}"
    except StreamError as exc:  # the bytes failed verification
        res.status, res.message = CORRUPT, str(exc)
    except OSError as exc:
        res.status, res.message = CUT, f"{type(exc).__name__}: {exc}"
    if caller_error is not None:
        _done(res, conn, t0, dog)  # stop the watchdog, close the connection
        # Raised here, outside the handler, so what the caller sees is their exception with
        # its own traceback, nothing of fetch_stream's chained onto it.
        raise caller_error
    return _done(res, conn, t0, dog, settle)


def _done(res: FetchResult, conn, t0: float, dog: _Watchdog, settle=None) -> FetchResult:
    if dog.reason and res.status not in (COMPLETE, BUDGET, CANCELLED, CHANGED, TRUNCATED):
        res.status, res.message = dog.reason, dog.message  # what woke the read, not the cut it caused
    if conn is not None:
        conn.close()
    if settle is not None:
        # After the connection is closed and the status is known; its requests are the
        # download's too, so the watchdog (deadline, minimum rate) still runs.
        settle()
        res.reader.unconfirmed = res.unconfirmed  # for a resume with this reader (see sure)
    dog.stop()
    res.seconds = time.monotonic() - t0
    return res
