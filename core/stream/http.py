"""Progressive download of a stream over HTTP(S) (standard library only: runs in Blender).

Any static server or CDN will do: the client asks for byte ranges (one request per chunk, so a
receiver can stop at any budget and a dropped connection costs one chunk), and falls back to
reading a plain GET incrementally when the server ignores Range. Every piece goes through a
StreamReader, so what has been received is verified as it arrives and survives a stall, a cut
connection or an HTTP error: the result says what happened and keeps the verified Gaussians.
"""

from __future__ import annotations

import http.client
import math
import re
import socket
import threading
import time
from dataclasses import dataclass, field
from urllib.parse import urljoin, urlsplit

from .format import FIXED_SIZE, FIXED_SIZE_MAX, StreamError, _fixed_size, _parse_fixed
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

_CONTENT_RANGE = re.compile(r"bytes\s+(\d+)-(\d+)/(\d+|\*)")


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
        mid-download (what arrived is a prefix of the old file, not of the one at the URL now)."""
        return 0 if self.status == CHANGED else self.reader.num_gaussians

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

    def __init__(self, reader, deadline, min_rate, rate_window):
        self.reader, self.deadline, self.min_rate, self.window = reader, deadline, min_rate, rate_window
        self.reason = None
        self.message = ""
        self.conn = None
        self._stop = threading.Event()
        self._thread = None
        if deadline is not None or min_rate is not None:
            self._thread = threading.Thread(target=self._run, name="fetch_stream-watchdog", daemon=True)
            self._thread.start()

    def _run(self):
        t0 = time.monotonic()
        w0, b0 = t0, self.reader.bytes_received
        while not self._stop.wait(0.05):
            now = time.monotonic()
            if self.deadline is not None and now - t0 >= self.deadline:
                self.reason, self.message = DEADLINE, f"total deadline of {self.deadline} s passed"
            elif self.min_rate is not None and now - w0 >= self.window:
                got = self.reader.bytes_received - b0
                if got < self.min_rate * (now - w0):
                    self.reason = TOO_SLOW
                    self.message = (
                        f"{got} bytes in {now - w0:.1f} s, under the minimum rate of {self.min_rate:g} bytes/s"
                    )
                w0, b0 = now, self.reader.bytes_received
            if self.reason:
                conn = self.conn
                sock = getattr(conn, "sock", None)
                if sock is not None:
                    try:
                        sock.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
                return

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)


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
    returning False stops the download ("cancelled"). `timeout` is the longest wait for any
    byte; `deadline` (seconds, None: none) bounds the whole download and `min_rate` (bytes/s,
    None: none) the pace over each `rate_window` seconds, response headers included
    ("deadline", "too_slow"). max_bytes / percent (of the stream's size, FORMAT.md section 6)
    stop early ("budget"); a percent budget is exact from the first request (the fixed header
    part is fetched alone first). Range requests carry If-Range with the file's ETag or
    Last-Modified (`validator` to resume an earlier fetch): if the file changes on the server
    the result is "changed" and the bytes received belong to the old file: discard them.
    """
    if chunk_size < 1 or read_size < 1:
        raise ValueError("fetch_stream: chunk_size and read_size must be positive")
    for name, v in (("deadline", deadline), ("min_rate", min_rate), ("rate_window", rate_window)):
        if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"fetch_stream: {name} must be a positive number of seconds or bytes/s, got {v!r}")
    if percent is not None and not (0.0 <= float(percent) <= 100.0):
        raise ValueError(f"fetch_stream: percent must be in [0, 100], got {percent}")
    reader = reader if reader is not None else StreamReader(template_faces, source=url)
    res = FetchResult(UNREACHABLE, reader, url, validator=validator)
    t0 = time.monotonic()
    conn = None
    redirects = 0
    use_ranges = True
    total_seen = None  # the file size a Content-Range reported first
    head = bytearray()  # the fixed header part, kept while the full header is incomplete
    fixed_total = [None]  # stream size implied by the fixed part (before the whole header)
    fresh = reader.bytes_received == 0

    def limit() -> int | None:
        """Bytes wanted in total (None: unknown until the header arrives)."""
        lim = 0 if percent is not None and float(percent) == 0.0 else None
        h = reader.header
        total = h.total_bytes if h is not None else fixed_total[0]
        if total is not None:
            lim = total if lim is None else lim
            if percent is not None:
                lim = min(lim, math.floor(float(percent) / 100.0 * total))
        if max_bytes is not None:
            lim = max_bytes if lim is None else min(lim, max_bytes)
        return lim

    def request_cap() -> int | None:
        """Where the next request must end: the budget, or with a percent budget and no
        header yet, the fixed header part (its fields give the stream's size)."""
        lim = limit()
        if percent is not None and reader.header is None and fixed_total[0] is None and fresh:
            lim = FIXED_SIZE_MAX if lim is None else min(lim, FIXED_SIZE_MAX)
        return lim

    def finished() -> str | None:
        if reader.complete:
            return COMPLETE
        lim = limit()
        if lim is not None and reader.bytes_received >= lim:
            return BUDGET
        return None

    def feed(data) -> bool:
        """Feed, call back; False when the caller cancelled."""
        if fresh and fixed_total[0] is None and len(head) < FIXED_SIZE_MAX:
            head.extend(bytes(data[: FIXED_SIZE_MAX - len(head)]))
            # The fixed part is 56 bytes up to version 2, 60 in version 3, 64 from version 4 (its version
            # field, inside the first 56, says which).
            if len(head) >= FIXED_SIZE and len(head) >= _fixed_size(head):
                f = _parse_fixed(head, url)
                fixed_total[0] = (
                    f["header_size"]
                    + f["num_records"] * f["record_size"]
                    + 4 * -(-f["num_records"] // f["records_per_block"])
                )
        new = reader.feed(data)
        if on_chunk is not None and on_chunk(reader, new) is False:
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

    dog = _Watchdog(reader, deadline, min_rate, rate_window)
    target = url
    try:
        while True:
            if dog.reason:
                break
            done = finished()
            if done:
                res.status = done
                break
            parts = urlsplit(target)
            if parts.scheme not in ("http", "https"):
                res.status, res.message = HTTP_ERROR, f"unsupported URL scheme {parts.scheme!r}"
                break
            if conn is None:
                cls = http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection
                conn = cls(parts.hostname, parts.port, timeout=timeout)
                dog.conn = conn
            path = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
            start = reader.bytes_received
            hdrs = {"Accept-Encoding": "identity", **(headers or {})}
            lim = request_cap()
            if use_ranges:
                end = start + chunk_size - 1
                if lim is not None:
                    end = min(end, lim - 1)
                hdrs["Range"] = f"bytes={start}-{end}"
                if res.validator is not None:
                    hdrs["If-Range"] = res.validator
            try:
                conn.request("GET", path, headers=hdrs)
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
                resp.read()
                redirects += 1
                if not loc or redirects > max_redirects:
                    res.status, res.message = HTTP_ERROR, f"HTTP {resp.status}: bad or too many redirects"
                    break
                target = urljoin(target, loc)
                conn.close()
                conn = None
                continue
            if resp.status == 416 and reader.complete:
                res.status = COMPLETE
                break
            if resp.status == 206:
                m = _CONTENT_RANGE.match(resp.getheader("Content-Range") or "")
                if not m or int(m.group(1)) != start:
                    res.status, res.message = (
                        HTTP_ERROR,
                        f"unexpected Content-Range {resp.getheader('Content-Range')!r}",
                    )
                    break
                if changed(resp, "validator"):
                    break
                if m.group(3) != "*":
                    if total_seen is not None and int(m.group(3)) != total_seen:
                        res.status = CHANGED
                        res.message = (
                            f"the file on the server changed mid-download (size {total_seen} -> "
                            f"{m.group(3)}); the {reader.bytes_received} bytes received belong to the "
                            "old file: discard them"
                        )
                        break
                    total_seen = int(m.group(3))
                res.used_ranges = True
                want = int(m.group(2)) - start + 1
                got = 0
                while got < want:
                    # read1: whatever arrived (one recv), so a stall loses nothing already received
                    piece = resp.read1(min(read_size, want - got))
                    if not piece:
                        break
                    got += len(piece)
                    if not feed(piece):
                        return _done(res, conn, t0, dog)
                if got < want:
                    res.status, res.message = CUT, f"range response ended after {got} of {want} bytes"
                    break
                resp.read()  # nothing left; marks the response done so the connection is reusable
                if resp.will_close:
                    conn.close()
                    conn = None
                continue
            if resp.status == 200:
                # Either the server ignores Range, or (If-Range) the file changed: a 200 to a
                # conditional range request after bytes arrived with another validator.
                if start == 0:
                    res.validator = res.validator or _validator(resp)
                elif changed(resp, "If-Range answered with the whole file"):
                    break
                # The server ignored Range: the body starts at byte 0. Skip what we have and
                # read the rest incrementally on this one response.
                res.used_ranges = False
                use_ranges = False
                skip = start
                while skip > 0:
                    dropped = resp.read(min(read_size, skip))
                    if not dropped:
                        break
                    skip -= len(dropped)
                while True:
                    if finished():
                        break
                    lim = request_cap()
                    n = read_size if lim is None else max(1, min(read_size, lim - reader.bytes_received))
                    piece = resp.read1(n)
                    if not piece:
                        break
                    if not feed(piece):
                        return _done(res, conn, t0, dog)
                done = finished()
                if done:
                    res.status = done
                else:
                    res.status, res.message = CUT, f"response body ended after {reader.bytes_received} bytes"
                break
            body = resp.read(2048).decode("utf-8", "replace")
            res.status, res.message = HTTP_ERROR, f"HTTP {resp.status} {resp.reason}: {body[:200]}"
            break
    except (socket.timeout, TimeoutError):
        res.status, res.message = STALLED, f"no data for {timeout} s"
    except (http.client.IncompleteRead, http.client.RemoteDisconnected, ConnectionError) as exc:
        res.status, res.message = CUT, f"{type(exc).__name__}: {exc}"
    except http.client.HTTPException as exc:
        res.status, res.message = HTTP_ERROR, f"malformed response: {type(exc).__name__}: {exc}"
    except StreamError as exc:  # the bytes failed verification
        res.status, res.message = CORRUPT, str(exc)
    except ValueError as exc:  # verified bytes the reader refuses (template mismatch, ...)
        res.status, res.message = REFUSED, str(exc)
    except OSError as exc:
        res.status, res.message = CUT, f"{type(exc).__name__}: {exc}"
    return _done(res, conn, t0, dog)


def _done(res: FetchResult, conn, t0: float, dog: _Watchdog) -> FetchResult:
    dog.stop()
    if dog.reason and res.status not in (COMPLETE, BUDGET, CANCELLED, CHANGED):
        res.status, res.message = dog.reason, dog.message  # what woke the read, not the cut it caused
    if conn is not None:
        conn.close()
    res.seconds = time.monotonic() - t0
    return res
