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
import time
from dataclasses import dataclass, field
from urllib.parse import urljoin, urlsplit

from .format import StreamReader

COMPLETE = "complete"  # the whole stream arrived and verified
BUDGET = "budget"  # stopped at the requested budget (everything inside it verified)
STALLED = "stalled"  # no byte for `timeout` seconds
CUT = "connection_cut"  # the server closed or reset the connection mid-body
HTTP_ERROR = "http_error"  # a non-success HTTP status (or a malformed response)
UNREACHABLE = "unreachable"  # could not connect at all
CORRUPT = "corrupt"  # the bytes failed verification (checksum or structure)
CANCELLED = "cancelled"  # the callback asked to stop

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

    @property
    def ok(self) -> bool:
        return self.status in (COMPLETE, BUDGET)

    @property
    def num_gaussians(self) -> int:
        return self.reader.num_gaussians

    @property
    def bytes_received(self) -> int:
        return self.reader.bytes_received

    def avatar(self):
        return self.reader.avatar()

    def __str__(self):
        return (f"{self.status}: {self.num_gaussians} Gaussians verified from {self.bytes_received} bytes of "
                f"{self.url} ({self.requests} requests{', ranges' if self.used_ranges else ''}) {self.message}").strip()


def fetch_stream(url: str, *, reader: StreamReader | None = None, template_faces=None, chunk_size: int = 1 << 20,
                 read_size: int = 1 << 16, timeout: float = 10.0, on_chunk=None, max_bytes: int | None = None,
                 percent: float | None = None, headers: dict | None = None, max_redirects: int = 5) -> FetchResult:
    """Download `url` progressively into a StreamReader (a new one, or `reader` to resume).

    on_chunk(reader, new_gaussians) runs after each piece (every `read_size` bytes at most);
    returning False stops the download ("cancelled"). `timeout` is the longest wait for any
    byte. max_bytes / percent (of the stream's size, FORMAT.md section 6) stop early ("budget").
    """
    if chunk_size < 1 or read_size < 1:
        raise ValueError("fetch_stream: chunk_size and read_size must be positive")
    reader = reader if reader is not None else StreamReader(template_faces, source=url)
    res = FetchResult(UNREACHABLE, reader, url)
    t0 = time.monotonic()
    conn = None
    redirects = 0
    use_ranges = True

    def limit() -> int | None:
        """Bytes wanted in total (None: unknown until the header arrives)."""
        lim = None
        h = reader.header
        if h is not None:
            lim = h.total_bytes
            if percent is not None:
                lim = min(lim, math.floor(float(percent) / 100.0 * h.total_bytes))
        if max_bytes is not None:
            lim = max_bytes if lim is None else min(lim, max_bytes)
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
        new = reader.feed(data)
        if on_chunk is not None and on_chunk(reader, new) is False:
            res.status, res.message = CANCELLED, "stopped by the callback"
            return False
        return True

    target = url
    try:
        while True:
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
            path = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
            start = reader.bytes_received
            hdrs = {"Accept-Encoding": "identity", **(headers or {})}
            lim = limit()
            if use_ranges:
                end = start + chunk_size - 1
                if lim is not None:
                    end = min(end, lim - 1)
                hdrs["Range"] = f"bytes={start}-{end}"
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
                    res.status, res.message = HTTP_ERROR, f"unexpected Content-Range {resp.getheader('Content-Range')!r}"
                    break
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
                        return _done(res, conn, t0)
                if got < want:
                    res.status, res.message = CUT, f"range response ended after {got} of {want} bytes"
                    break
                resp.read()  # nothing left; marks the response done so the connection is reusable
                if resp.will_close:
                    conn.close()
                    conn = None
                continue
            if resp.status == 200:
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
                    lim = limit()
                    n = read_size if lim is None else max(1, min(read_size, lim - reader.bytes_received))
                    piece = resp.read1(n)
                    if not piece:
                        break
                    if not feed(piece):
                        return _done(res, conn, t0)
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
    except ValueError as exc:  # the reader refused the bytes
        res.status, res.message = CORRUPT, str(exc)
    except OSError as exc:
        res.status, res.message = CUT, f"{type(exc).__name__}: {exc}"
    return _done(res, conn, t0)


def _done(res: FetchResult, conn, t0: float) -> FetchResult:
    if conn is not None:
        conn.close()
    res.seconds = time.monotonic() - t0
    return res
