"""HTTP faults (core/stream/http.py) against an in-process loopback server (127.0.0.1 only):
a file replaced mid-download, percent budgets before the header, a dripping server, nested
JSON metadata. Every test is bounded to a few seconds."""

import hashlib
import re
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from progressive_avatars.core.stream import http as H
from progressive_avatars.core.stream.format import FIXED_SIZE_MAX, read_header
from progressive_avatars.core.stream.reader import StreamReader, read_stream
from progressive_avatars.core.stream.writer import encode_stream
from progressive_avatars.core.avatar.avatar import Avatar
from tests.test_stream import assert_prefix, make_avatar


class FaultHandler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, *args):
        pass

    def do_GET(self):
        srv = self.server
        srv.requests += 1
        if srv.swap_after is not None and srv.requests > srv.swap_after:
            srv.data, srv.etag = srv.new_data, srv.new_etag
        data, etag = srv.data, srv.etag
        if srv.drip_headers:
            for ch in b"HTTP/1.1 200 OK\r\n":
                self.wfile.write(bytes([ch]))
                self.wfile.flush()
                time.sleep(srv.drip)
            return
        rng = self.headers.get("Range")
        if_range = self.headers.get("If-Range")
        srv.log.append((rng, if_range))
        start, end, partial = 0, len(data) - 1, False
        validator = etag if srv.send_etag else _lastmod(etag)
        if rng and srv.ranges and (if_range is None or if_range == validator):
            m = re.match(r"bytes=(\d+)-(\d*)", rng)
            start = int(m.group(1))
            end = min(int(m.group(2)) if m.group(2) else len(data) - 1, len(data) - 1)
            partial = True
        self.send_response(206 if partial else 200)
        if partial:
            self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
        if srv.send_etag:
            self.send_header("ETag", etag)
        else:  # Last-Modified only: an HTTP date that differs between the two versions
            self.send_header("Last-Modified", _lastmod(etag))
        self.send_header("Content-Length", str(end - start + 1))
        self.end_headers()
        body = data[start : end + 1]
        if srv.drip:
            for i in range(len(body)):
                try:
                    self.wfile.write(body[i : i + 1])
                    self.wfile.flush()
                except OSError:
                    return
                time.sleep(srv.drip)
        else:
            self.wfile.write(body)


def _lastmod(etag):
    second = int(etag.strip('"')[:4], 16) % 60
    return f"Mon, 23 Nov 2026 04:00:{second:02d} GMT"


def _etag(data):
    return '"' + hashlib.sha1(data).hexdigest()[:16] + '"'


class _QuietServer(ThreadingHTTPServer):
    def handle_error(self, request, client_address):
        pass  # the client hanging up on a dripping response is the point of some tests


class FaultServer:
    def __init__(
        self, data, *, new_data=None, swap_after=None, ranges=True, send_etag=True, drip=0.0, drip_headers=False
    ):
        self.httpd = _QuietServer(("127.0.0.1", 0), FaultHandler)
        self.httpd.daemon_threads = True
        h = self.httpd
        h.data, h.etag, h.new_data = data, _etag(data), new_data
        h.new_etag = _etag(new_data) if new_data is not None else None
        h.swap_after, h.ranges, h.send_etag, h.drip, h.drip_headers = swap_after, ranges, send_etag, drip, drip_headers
        h.requests, h.log = 0, []
        self.thread = threading.Thread(target=h.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{h.server_address[1]}/s.pavs"

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(5)


@pytest.fixture
def serve():
    servers = []

    def start(*a, **k):
        s = FaultServer(*a, **k)
        servers.append(s)
        return s

    yield start
    for s in servers:
        s.close()


@pytest.fixture(scope="module")
def two_streams():
    _, av, imp = make_avatar(11, n_lat=6, n_lon=10, depth=3)
    # The replacement: same forest and size, other colours (a re-export after more training).
    av2 = Avatar(av.forest, av.d_mu, av.d_log_scale, av.d_rot, av.opacity_logit, av.f_dc + 0.5, meta=av.meta)
    a = encode_stream(av, imp, records_per_block=16)
    b = encode_stream(av2, imp, records_per_block=16)
    return a, b, read_stream(a)


@pytest.mark.parametrize("ranges", [True, False], ids=["if-range", "server-ignores-range"])
def test_file_replaced_mid_download_is_detected_not_stitched(two_streams, serve, ranges):
    a, b, full_a = two_streams
    assert len(a) == len(b)  # same size: only the validator can tell them apart
    srv = serve(a, new_data=b, swap_after=2 if ranges else 1, ranges=ranges)
    res = H.fetch_stream(
        srv.url,
        chunk_size=1500,
        read_size=1500 if ranges else 400,
        timeout=2,
        percent=90 if ranges else None,
        on_chunk=(None if ranges else lambda r, n: r.bytes_received < 1200),
    )
    if ranges:
        assert res.status == H.CHANGED and not res.ok, str(res)
        assert "changed mid-download" in res.message and "discard" in res.message
        assert srv.httpd.log[1][1] == _etag(a)  # the second range request carried If-Range
        assert_prefix(res.avatar(), full_a, res.num_gaussians)  # only old-file records, never a mix
        assert res.num_gaussians > 0 and res.keepable_gaussians == 0  # the add-on keeps none of them
        # Resuming with the same reader and the old validator is refused the same way.
        res2 = H.fetch_stream(srv.url, reader=res.reader, validator=res.validator, timeout=2)
        assert res2.status == H.CHANGED, str(res2)
    else:
        # Without range support the client restarts a plain GET and sees the new ETag at once.
        res2 = H.fetch_stream(srv.url, reader=res.reader, validator=res.validator, timeout=2)
        assert res.status == H.CANCELLED and res2.status == H.CHANGED, (str(res), str(res2))


def test_last_modified_used_without_etag(two_streams, serve):
    a, b, full_a = two_streams
    assert _lastmod(_etag(a)) != _lastmod(_etag(b))
    srv = serve(a, new_data=b, swap_after=1, send_etag=False)
    res = H.fetch_stream(srv.url, chunk_size=1500, timeout=2)
    assert res.status == H.CHANGED, str(res)
    assert res.validator == _lastmod(_etag(a)) and srv.httpd.log[1][1] == res.validator  # sent as If-Range
    assert_prefix(res.avatar(), full_a, res.num_gaussians)


@pytest.mark.parametrize("percent", [0, 1, 10, 50, 99])
def test_percent_budget_exact_before_header(two_streams, serve, percent):
    a, _, full = two_streams
    info = read_header(a)
    assert len(a) < (1 << 20)  # under the default first request size: was downloaded whole
    srv = serve(a)
    res = H.fetch_stream(srv.url, timeout=2, percent=percent)
    want = max(FIXED_SIZE_MAX if percent else 0, min(len(a), int(percent / 100 * len(a))))  # the fixed part first
    assert res.status == H.BUDGET, str(res)
    assert res.bytes_received == want, (res.bytes_received, want)
    n = info.count_for_percent(percent)
    assert res.num_gaussians == n
    if n:
        assert_prefix(res.avatar(), full, n)
    # Without Range support the same budget holds (the plain GET is read only that far).
    srv2 = serve(a, ranges=False)
    res2 = H.fetch_stream(srv2.url, timeout=2, percent=percent)
    assert res2.status == H.BUDGET and res2.num_gaussians == n


def test_deadline_and_min_rate_stop_a_dripping_server(two_streams, serve):
    a, _, full = two_streams
    srv = serve(a, drip=0.05)  # 20 bytes/s: every byte inside the 2 s socket timeout
    t = time.monotonic()
    res = H.fetch_stream(srv.url, timeout=2, deadline=1.0, min_rate=None)
    assert time.monotonic() - t < 3.0
    assert res.status == H.DEADLINE and "deadline" in res.message, str(res)
    assert 0 < res.bytes_received < len(a)
    assert_prefix(res.avatar(), full, res.num_gaussians)
    t = time.monotonic()
    res = H.fetch_stream(srv.url, timeout=2, min_rate=200, rate_window=0.6)
    assert time.monotonic() - t < 3.0
    assert res.status == H.TOO_SLOW and "minimum rate" in res.message, str(res)
    # Response headers dripped byte by byte are bounded too.
    srv2 = serve(a, drip=0.1, drip_headers=True)
    t = time.monotonic()
    res = H.fetch_stream(srv2.url, timeout=2, deadline=0.8)
    assert time.monotonic() - t < 3.0 and res.status == H.DEADLINE, str(res)
    with pytest.raises(ValueError, match="deadline"):
        H.fetch_stream(srv.url, deadline=-1)


def test_nested_json_metadata_reported_as_corrupt(serve):
    _, av, imp = make_avatar(3, n_lat=3, n_lon=4, depth=1)
    nested = {}
    for _ in range(200):
        nested = {"n": nested}
    data = encode_stream(av, imp, metadata={"deep": nested})
    srv = serve(data)
    res = H.fetch_stream(srv.url, timeout=2)
    assert res.status == H.CORRUPT and "JSON nested" in res.message, str(res)


# -- scripted servers: each test says how the server answers --------------------------------------


class ScriptHandler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, *args):
        pass

    def do_GET(self):
        self.server.requests += 1
        self.server.script(self)


def _send(h, status, body=b"", headers=()):
    h.send_response(status)
    for k, v in headers:
        h.send_header(k, v)
    h.send_header("Content-Length", str(len(body)))
    h.end_headers()
    h.wfile.write(body)


def _static(data, ranges=True):
    """An honest static server for `data`: 206 for a range, 416 past the end, 200 without ranges."""

    def script(h):
        m = re.match(r"bytes=(\d+)-(\d*)", h.headers.get("Range") or "")
        if not (m and ranges):
            return _send(h, 200, data)
        start = int(m.group(1))
        if start >= len(data):
            return _send(h, 416, headers=[("Content-Range", f"bytes */{len(data)}")])
        end = min(int(m.group(2)) if m.group(2) else len(data) - 1, len(data) - 1)
        _send(h, 206, data[start : end + 1], [("Content-Range", f"bytes {start}-{end}/{len(data)}")])

    return script


@pytest.fixture
def scripted():
    servers = []

    def start(script):
        httpd = _QuietServer(("127.0.0.1", 0), ScriptHandler)
        httpd.daemon_threads = True
        httpd.script, httpd.requests = script, 0
        threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
        servers.append(httpd)
        return httpd, f"http://127.0.0.1:{httpd.server_address[1]}/s.pavs"

    yield start
    for httpd in servers:
        httpd.shutdown()
        httpd.server_close()


@pytest.mark.parametrize(
    "location",
    ["http://:81/s.pavs", "http://127.0.0.1:99999/s.pavs", "http://127.0.0.1:port/s.pavs", "http://[::1/s.pavs"],
)
def test_redirect_to_an_unusable_url_is_an_http_error_naming_it(scripted, location):
    """A Location without a host or with a bad port was a raw TypeError/AttributeError out of
    http.client, or 'refused' (the reader's status for bytes it cannot use)."""
    _, url = scripted(lambda h: _send(h, 302, headers=[("Location", location)]))
    res = H.fetch_stream(url, timeout=2)
    assert res.status == H.HTTP_ERROR and res.http_status == 302, str(res)
    assert "redirected to a bad URL" in res.message and location in res.message, res.message


@pytest.mark.parametrize("url", ["http:///s.pavs", "http://:81/s.pavs", "http://127.0.0.1:99999/s.pavs"])
def test_caller_url_without_host_or_with_bad_port_is_an_http_error(url):
    res = H.fetch_stream(url, timeout=2)
    assert res.status == H.HTTP_ERROR and res.requests == 0, str(res)
    assert f"bad URL {url!r}" in res.message, res.message


@pytest.mark.parametrize("bad", ["backwards", "past-the-end"])
def test_unusable_content_range_fails_at_once(two_streams, scripted, bad):
    """A 206 whose Content-Range ends before it starts made the client re-request the same range
    thousands of times a second (only a deadline or min_rate ended it); one ending past the file's
    size was read as a cut connection."""
    a = two_streams[0]

    def script(h):
        start = int(re.match(r"bytes=(\d+)-", h.headers["Range"]).group(1))
        if start == 0:  # the first chunk is honest
            return _send(h, 206, a[:64], [("Content-Range", f"bytes 0-63/{len(a)}")])
        last = start - 1 if bad == "backwards" else len(a) + 10
        _send(h, 206, b"", [("Content-Range", f"bytes {start}-{last}/{len(a)}")])

    httpd, url = scripted(script)
    t = time.monotonic()
    res = H.fetch_stream(url, chunk_size=64, timeout=2, min_rate=None, deadline=3)
    assert time.monotonic() - t < 2, str(res)
    assert res.status == H.HTTP_ERROR and "unexpected Content-Range" in res.message, str(res)
    assert res.requests == httpd.requests == 2 and res.bytes_received == 64


@pytest.mark.parametrize("ranges", [True, False], ids=["ranges", "server-ignores-range"])
@pytest.mark.parametrize("k", [30, 60, 400])  # inside the fixed header part, after it, deep in the header
def test_percent_budget_holds_when_resuming_inside_the_header(two_streams, scripted, ranges, k):
    """A reader that stopped inside the stream header, resumed with a percent budget, fetched the
    whole stream ('complete'): the budget logic ran only for a fresh reader."""
    a, _, full = two_streams
    info = read_header(a)
    assert FIXED_SIZE_MAX < 400 < info.header_size
    _, url = scripted(_static(a, ranges))
    fresh = H.fetch_stream(url, timeout=2, percent=10)
    assert fresh.status == H.BUDGET and fresh.num_gaussians == info.count_for_percent(10), str(fresh)
    reader = StreamReader(source=url)
    reader.feed(a[:k])
    assert reader.header is None
    res = H.fetch_stream(url, reader=reader, timeout=2, percent=10)
    assert res.status == H.BUDGET, str(res)
    assert (res.bytes_received, res.num_gaussians) == (fresh.bytes_received, fresh.num_gaussians)
    assert_prefix(res.avatar(), full, res.num_gaussians)


def test_caller_errors_propagate_and_bad_arguments_raise_up_front(two_streams, scripted):
    """The catch-all `except ValueError -> refused` also swallowed the caller's own bugs and bad
    arguments; 'refused' is for the reader's verdict on the bytes only."""
    a, _, full = two_streams
    httpd, url = scripted(_static(a))

    def buggy(reader, new):
        int("not a number")

    with pytest.raises(ValueError, match="not a number"):
        H.fetch_stream(url, timeout=2, on_chunk=buggy)

    def full_disk(reader, new):
        raise OSError(28, "No space left on device")  # not the connection's fault: not 'connection_cut'

    with pytest.raises(OSError, match="No space left"):
        H.fetch_stream(url, timeout=2, on_chunk=full_disk)

    class Tee(StreamReader):  # a caller's reader that writes what it is fed (the add-on's kind)
        def feed(self, chunk):
            raise OSError(5, "write failed")

    with pytest.raises(OSError, match="write failed"):
        H.fetch_stream(url, reader=Tee(source=url), timeout=2)
    served = httpd.requests
    bad = [
        ({"timeout": 0}, "timeout"),
        ({"timeout": -1}, "timeout"),
        ({"timeout": float("nan")}, "timeout"),
        ({"max_bytes": -5}, "max_bytes"),
        ({"max_bytes": 1.5}, "max_bytes"),
        ({"percent": 101}, "percent"),
        ({"percent": float("nan")}, "percent"),
        ({"percent": "abc"}, "percent"),
        ({"chunk_size": 0}, "chunk_size"),
        ({"chunk_size": 1.5}, "chunk_size"),
        ({"read_size": -1}, "read_size"),
        ({"max_redirects": -1}, "max_redirects"),
        ({"headers": {"X-Bad": "a\r\nInjected: 1"}}, "header"),
        ({"validator": '"\u20ac"'}, "If-Range"),
    ]
    for kw, name in bad:
        with pytest.raises(ValueError, match=f"fetch_stream: .*{name}"):
            H.fetch_stream(url, timeout=kw.pop("timeout", 2), **kw)
    assert httpd.requests == served  # refused before any request
    # The reader's own refusal of valid bytes is still 'refused'.
    other = full.forest.template_faces[::-1].copy()
    res = H.fetch_stream(url, template_faces=other, timeout=2)
    assert res.status == H.REFUSED and "template mismatch" in res.message, str(res)


@pytest.mark.parametrize("ranges", [True, False], ids=["ranges", "server-ignores-range"])
def test_file_shorter_than_its_header_is_truncated_not_a_bare_416(two_streams, scripted, ranges):
    """A server file shorter than its header announces (an interrupted upload) ended in
    "HTTP 416 Requested Range Not Satisfiable: ", naming neither the truncation nor the sizes."""
    a, _, full = two_streams
    info = read_header(a)
    k = len(a) * 2 // 3
    httpd, url = scripted(_static(a[:k], ranges))
    res = H.fetch_stream(url, chunk_size=4000, timeout=2)
    assert res.status == H.TRUNCATED and not res.ok, str(res)
    assert f"holds only {k} of the {len(a)} bytes the stream's header announces" in res.message, res.message
    assert res.bytes_received == k and res.num_gaussians == info.count_for_bytes(k)
    assert res.keepable_gaussians == res.num_gaussians  # the verified prefix is kept
    assert_prefix(res.avatar(), full, res.num_gaussians)
    assert httpd.requests == (-(-k // 4000) if ranges else 1)  # Content-Range's size: no request for a 416
    if ranges:
        # Resuming against a file shorter still: a Content-Range gives its size (the header-CRC
        # check that opens a resume without a strong ETag gets it; else the 416 would).
        _, url2 = scripted(_static(a[: k // 2]))
        res2 = H.fetch_stream(url2, reader=res.reader, timeout=2)
        assert res2.status == H.TRUNCATED and res2.http_status in (206, 416), str(res2)
        assert f"holds only {k // 2} of the {len(a)} bytes" in res2.message, res2.message


@pytest.mark.parametrize("ranges", [True, False], ids=["ranges", "server-ignores-range"])
def test_resume_without_a_strong_etag_notices_a_replaced_file(two_streams, scripted, ranges):
    """A server with no validator (or a Last-Modified of one-second resolution): a file replaced
    between two fetches passed each record's own CRC-8, and the resumed avatar mixed the new
    file's records, decoded with the old header, into the old ones. The resume re-reads the
    header's CRC first."""
    a, b, full_a = two_streams
    _, url_a = scripted(_static(a, ranges))
    first = H.fetch_stream(url_a, percent=40, timeout=2)
    assert first.status == H.BUDGET and first.validator is None
    held = first.num_gaussians
    _, url_b = scripted(_static(b, ranges))
    res = H.fetch_stream(url_b, reader=first.reader, timeout=2)
    assert res.status == H.CHANGED and "header CRC differs" in res.message, str(res)
    assert res.num_gaussians == held
    assert_prefix(res.avatar(), full_a, held)  # nothing of the other file went in
    _, url_a2 = scripted(_static(a, ranges))  # the same file again: resumes to the end
    again = H.fetch_stream(url_a2, reader=res.reader, timeout=2)
    assert again.status == H.COMPLETE, str(again)
    assert_prefix(again.avatar(), full_a, full_a.num_gaussians)


def test_an_encoded_body_is_named_not_called_corrupt(two_streams, scripted):
    """A server (or CDN) that gzips the body although identity was asked for: an http_error
    naming the encoding, not a 'corrupt' stream."""
    import gzip

    a, _, _ = two_streams
    _, url = scripted(lambda h: _send(h, 200, gzip.compress(a), [("Content-Encoding", "gzip")]))
    res = H.fetch_stream(url, timeout=2)
    assert res.status == H.HTTP_ERROR and "gzip-encoded" in res.message and url in res.message, str(res)


def test_a_resume_that_re_reads_its_prefix_is_not_too_slow(two_streams, scripted):
    """Against a server that ignores Range a resume downloads the held prefix again; those
    bytes are progress for the minimum rate (they counted for nothing, and a resume whose
    prefix took longer than rate_window to re-read failed every time)."""
    a, _, full = two_streams

    def trickle(h):  # the whole file, ignoring Range, 1 KB every 20 ms
        h.send_response(200)
        h.send_header("Content-Length", str(len(a)))
        h.end_headers()
        try:
            for i in range(0, len(a), 1024):
                h.wfile.write(a[i : i + 1024])
                h.wfile.flush()
                time.sleep(0.02)
        except OSError:
            pass

    reader = StreamReader(source="test")
    reader.feed(a[: len(a) * 3 // 4])
    _, url = scripted(trickle)
    res = H.fetch_stream(url, reader=reader, timeout=2, min_rate=1024, rate_window=0.2)
    assert res.status == H.COMPLETE, str(res)
    assert_prefix(res.avatar(), full, full.num_gaussians)


def test_the_deadline_holds_while_connecting():
    """A listener whose backlog is full never completes a connection: the deadline (not the
    per-read timeout, six times longer) ends the fetch."""
    import socket

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(0)
    port = srv.getsockname()[1]
    fillers = []
    try:
        for _ in range(8):  # fill the backlog: later connections wait for a SYN-ACK that never comes
            c = socket.socket()
            c.setblocking(False)
            c.connect_ex(("127.0.0.1", port))
            fillers.append(c)
        time.sleep(0.1)
        t = time.monotonic()
        res = H.fetch_stream(f"http://127.0.0.1:{port}/s.pavs", timeout=6, deadline=0.5)
        took = time.monotonic() - t
    finally:
        for c in fillers:
            c.close()
        srv.close()
    assert took < 2.5, (took, str(res))
    assert res.status in (H.DEADLINE, H.UNREACHABLE, H.STALLED), str(res)


@pytest.mark.parametrize("status", [503, 302])
def test_an_error_or_redirect_whose_body_stalls_says_its_status(scripted, status):
    """The status line arrived, the body never did: an http_error naming the status (it was
    'stalled', which hid the 503 or the redirect behind a timeout)."""

    def script(h):
        h.send_response(status)
        if status == 302:
            h.send_header("Location", "/elsewhere.pavs")
        h.send_header("Content-Length", "100")
        h.end_headers()
        h.wfile.flush()
        time.sleep(1.5)

    _, url = scripted(script)
    res = H.fetch_stream(url, timeout=0.5)
    assert res.status == H.HTTP_ERROR and f"HTTP {status}" in res.message and "stalled" in res.message, str(res)


RPB = 16  # records per block of the test stream
R = 23  # quantised record size (FORMAT.md 3.1)


@pytest.fixture(scope="module")
def streams():
    """Two same-size streams of one forest (the second with other colours: a re-export)."""
    _, av, imp = make_avatar(11, n_lat=6, n_lon=10, depth=3)
    other = Avatar(av.forest, av.d_mu, av.d_log_scale, av.d_rot, av.opacity_logit, av.f_dc + 0.5, meta=av.meta)
    a = encode_stream(av, imp, records_per_block=RPB)
    b = encode_stream(other, imp, records_per_block=RPB)
    assert len(a) == len(b)
    return a, b, read_stream(a)


def _fields(data):
    """header_size, num_records, records_per_block straight from the fixed header (FORMAT.md 2.1)."""
    return (
        int.from_bytes(data[12:16], "little"),
        int.from_bytes(data[16:20], "little"),
        int.from_bytes(data[26:28], "little"),
    )


def _count(data, k):
    """FORMAT.md 6, count_for_bytes(k), written out from the document."""
    hs, n, b = _fields(data)
    if k < hs:
        return 0
    u, s = k - hs, b * R + 4
    return min(n, (u // s) * b + min((u % s) // R, b))


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, *args):
        pass

    def do_GET(self):
        srv = self.server
        srv.count += 1
        srv.ranges.append(self.headers.get("Range"))
        srv.answer(self, srv.count)


class _Quiet(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):
        pass


@pytest.fixture
def server():
    made = []

    def start(answer):
        httpd = _Quiet(("127.0.0.1", 0), _Handler)
        httpd.answer, httpd.count, httpd.ranges = answer, 0, []
        threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
        made.append(httpd)
        return httpd, f"http://127.0.0.1:{httpd.server_address[1]}/s.pavs"

    yield start
    for httpd in made:
        httpd.shutdown()
        httpd.server_close()


def _reply(h, status, body=b"", headers=(), length=None):
    h.send_response(status)
    for k, v in headers:
        h.send_header(k, v)
    h.send_header("Content-Length", str(len(body) if length is None else length))
    h.end_headers()
    h.wfile.write(body)


def _asked(h, size):
    m = re.match(r"bytes=(\d+)-(\d*)", h.headers.get("Range") or "")
    assert m, "every request of these tests is a range request"
    first = int(m.group(1))
    last = min(int(m.group(2)) if m.group(2) else size - 1, size - 1)
    return first, last


def _honest(data, headers=()):
    def answer(h, n):
        if not data or _asked(h, len(data))[0] >= len(data):
            return _reply(h, 416, headers=[("Content-Range", f"bytes */{len(data)}"), *headers])
        s, e = _asked(h, len(data))
        _reply(h, 206, data[s : e + 1], [("Content-Range", f"bytes {s}-{e}/{len(data)}"), *headers])

    return answer


# -- Content-Range validation ----------------------------------------------------------------------


def test_a_range_starting_elsewhere_than_asked_is_refused(streams, server):
    """a 206 whose Content-Range starts 10 bytes after the requested start (its body the
    file's bytes from there) must not be fed as if it started where asked."""
    a = streams[0]

    def answer(h, n):
        s, e = _asked(h, len(a))
        if n > 1:
            s, e = s + 10, min(e + 10, len(a) - 1)
        _reply(h, 206, a[s : e + 1], [("Content-Range", f"bytes {s}-{e}/{len(a)}")])

    httpd, url = server(answer)
    res = H.fetch_stream(url, chunk_size=1000, timeout=2, min_rate=None)
    assert res.status == H.HTTP_ERROR and "unexpected Content-Range" in res.message, str(res)
    assert res.requests == 2 and res.bytes_received == 1000


def test_a_range_ending_at_the_size_is_past_the_end(streams, server):
    """the last byte of a file of `size` bytes is size - 1: `bytes s-size/size` is invalid."""
    a = streams[0]

    def answer(h, n):
        s, e = _asked(h, len(a))
        if n == 1:
            return _reply(h, 206, a[s : e + 1], [("Content-Range", f"bytes {s}-{e}/{len(a)}")])
        _reply(h, 206, a[s:] + b"\0", [("Content-Range", f"bytes {s}-{len(a)}/{len(a)}")])

    _, url = server(answer)
    res = H.fetch_stream(url, chunk_size=1000, timeout=2, min_rate=None)
    assert res.status == H.HTTP_ERROR and "unexpected Content-Range" in res.message, str(res)
    assert res.requests == 2 and res.bytes_received == 1000


def test_a_range_body_one_byte_short_is_a_cut(streams, server):
    """a 206 body that ends one byte before its Content-Range says is a cut connection."""
    a = streams[0]

    def answer(h, n):
        s, e = _asked(h, len(a))
        body = a[s:e]  # one byte short of s..e, and the Content-Length says so
        _reply(h, 206, body, [("Content-Range", f"bytes {s}-{e}/{len(a)}")])
        h.close_connection = True

    httpd, url = server(answer)
    res = H.fetch_stream(url, chunk_size=1000, timeout=2, min_rate=None)
    assert res.status == H.CUT and "ended after 999 of 1000 bytes" in res.message, str(res)
    assert res.requests == httpd.count == 1 and res.bytes_received == 999


def test_more_than_asked_is_not_fed_past_the_budget(streams, server):
    """a server rounding every range up to 4 KiB blocks (some CDNs do): a byte budget holds."""
    a, _, full = streams

    def answer(h, n):
        s, _ = _asked(h, len(a))
        e = min((s // 4096 + 1) * 4096, len(a)) - 1
        _reply(h, 206, a[s : e + 1], [("Content-Range", f"bytes {s}-{e}/{len(a)}")])

    _, url = server(answer)
    res = H.fetch_stream(url, chunk_size=700, read_size=256, timeout=2, max_bytes=1500, min_rate=None)
    assert res.status == H.BUDGET and res.bytes_received == 1500, str(res)
    n = _count(a, 1500)
    assert n == 2 * RPB + (1500 - 530 - 2 * (RPB * R + 4)) // R == 41  # header 530 B, two whole blocks, 9 more
    assert res.num_gaussians == n
    assert_prefix(res.avatar(), full, n)


# -- sizes and 416 ---------------------------------------------------------------------------------


def test_an_empty_file_is_truncated_not_an_http_error(server):
    """an honest server's 416 for an empty file (Content-Range `bytes */0`) at the first
    request: the file ends inside the stream's header."""
    httpd, url = server(_honest(b""))
    res = H.fetch_stream(url, timeout=2, min_rate=None)
    assert res.status == H.TRUNCATED, str(res)
    assert "ends after 0 bytes, inside the stream's header" in res.message, res.message
    assert res.http_status == 416 and res.requests == 1 and res.bytes_received == 0


def test_a_file_replaced_by_one_of_another_size_is_changed(streams, server):
    """without ETag or Last-Modified, the Content-Range size is the one sign of a replaced
    file; a file that grew 16 bytes after the first request must not be stitched on."""
    a, _, full = streams
    grown = a + bytes(16)

    def answer(h, n):
        _honest(a if n == 1 else grown)(h, n)

    _, url = server(answer)
    res = H.fetch_stream(url, chunk_size=4000, timeout=2, min_rate=None)
    assert res.status == H.CHANGED, str(res)
    assert f"size {len(a)} -> {len(a) + 16}" in res.message, res.message
    assert res.bytes_received == 4000 and res.keepable_gaussians == 0


# -- redirects -------------------------------------------------------------------------------------


def test_max_redirects_allows_exactly_that_many(streams, server):
    """two redirects are fine with max_redirects=2 and one too many with max_redirects=1."""
    a, _, full = streams

    def answer(h, n):
        if h.path == "/s.pavs":
            return _reply(h, 302, headers=[("Location", "/hop.pavs")])
        if h.path == "/hop.pavs":
            return _reply(h, 302, headers=[("Location", "/real.pavs")])
        _honest(a)(h, n)

    _, url = server(answer)
    res = H.fetch_stream(url, timeout=2, max_redirects=2, min_rate=None)
    assert res.status == H.COMPLETE, str(res)
    assert_prefix(res.avatar(), full, full.num_gaussians)
    res = H.fetch_stream(url, timeout=2, max_redirects=1, min_rate=None)
    assert res.status == H.HTTP_ERROR and "too many redirects" in res.message, str(res)
    res = H.fetch_stream(url.replace("/s.pavs", "/real.pavs"), timeout=2, max_redirects=0, min_rate=None)
    assert res.status == H.COMPLETE, str(res)


# -- validators --------------------------------------------------------------------------------------


def test_resume_with_a_last_modified_validator_rechecks_the_header(streams, server):
    """Last-Modified has one-second resolution, so a file replaced within the same second
    keeps it and If-Range still matches: a resume with it must re-read the header CRC."""
    a, b, full_a = streams
    stamp = "Mon, 23 Nov 2026 04:00:07 GMT"

    def serving(data):
        def answer(h, n):
            if h.headers.get("If-Range") not in (None, stamp):
                return _reply(h, 200, data, [("Last-Modified", stamp)])
            _honest(data, headers=[("Last-Modified", stamp)])(h, n)

        return answer

    _, url_a = server(serving(a))
    first = H.fetch_stream(url_a, percent=40, timeout=2, min_rate=None)
    assert first.status == H.BUDGET and first.validator == stamp, str(first)
    held = first.num_gaussians
    _, url_b = server(serving(b))
    res = H.fetch_stream(url_b, reader=first.reader, validator=first.validator, timeout=2, min_rate=None)
    assert res.status == H.CHANGED and "header CRC differs" in res.message, str(res)
    assert res.num_gaussians == held
    assert_prefix(res.avatar(), full_a, held)


# -- percent budget before the header --------------------------------------------------------------


def test_percent_budget_takes_two_requests(streams, server):
    """the fixed part gives the stream's size (FORMAT.md 6: H + N*R + 4*ceil(N/B), the last,
    partial block has its CRC too): the second request then ends exactly at the budget."""
    a, _, full = streams
    hs, n, b = _fields(a)
    assert n % b and hs + n * R + 4 * (-(-n // b)) == len(a)  # a partial last block
    httpd, url = server(_honest(a))
    res = H.fetch_stream(url, timeout=2, percent=99, min_rate=None)
    want = 99 * len(a) // 100
    assert res.status == H.BUDGET and res.bytes_received == want, str(res)
    assert res.requests == 2 and httpd.ranges == ["bytes=0-63", f"bytes=64-{want - 1}"], httpd.ranges


# -- minimum rate ----------------------------------------------------------------------------------


def test_min_rate_is_bytes_per_second_not_per_window(streams, server):
    """about 20 KB/s against min_rate=6000 bytes/s over 0.25 s windows is fast enough (each
    window brings ~5 KB, above 6000 * 0.25 = 1500 bytes; per window, not per second, it would be too slow)."""
    a, _, full = streams

    def answer(h, n):
        s, e = _asked(h, len(a))
        body = a[s : e + 1]
        h.send_response(206)
        h.send_header("Content-Range", f"bytes {s}-{e}/{len(a)}")
        h.send_header("Content-Length", str(len(body)))
        h.end_headers()
        try:
            for i in range(0, len(body), 1000):
                h.wfile.write(body[i : i + 1000])
                h.wfile.flush()
                time.sleep(0.05)
        except OSError:
            pass

    _, url = server(answer)
    res = H.fetch_stream(url, chunk_size=1 << 20, timeout=2, min_rate=6000, rate_window=0.25)
    assert res.status == H.COMPLETE, str(res)
    assert_prefix(res.avatar(), full, full.num_gaussians)


# -- a same-size replacement within the Last-Modified second ---------------------------------------
# Python's http.server (and others) send Last-Modified only: a file replaced by one of the same
# size within the same second keeps both the validator and the size, so If-Range cannot tell.

STAMP = "Mon, 23 Nov 2026 04:00:07 GMT"
H0, S0 = 530, RPB * R + 4  # the test stream's header size and block size (with its CRC)


@pytest.fixture(scope="module")
def same_header(streams):
    """A third same-size stream whose header is byte-identical to streams' first (other opacities:
    they are coded without a range in the header, FORMAT.md 3.1), its records different."""
    _, av, imp = make_avatar(11, n_lat=6, n_lon=10, depth=3)
    other = Avatar(av.forest, av.d_mu, av.d_log_scale, av.d_rot, -av.opacity_logit, av.f_dc, meta=av.meta)
    c = encode_stream(other, imp, records_per_block=RPB)
    a = streams[0]
    assert _fields(a)[0] == H0 and len(c) == len(a) and c[:H0] == a[:H0] and c[H0 + 2 * S0 :] != a[H0 + 2 * S0 :]
    return c


def _replaced(old, new, after, cut=None):
    """Last-Modified only, always the same: `old` for the first `after` requests, `new` from then on.
    cut: the request whose body stops after that many bytes (the connection then closes)."""

    def answer(h, n):
        data = old if n <= after else new
        if cut is not None and n == cut[0]:
            s, e = _asked(h, len(data))
            _reply(
                h,
                206,
                data[s : s + cut[1]],
                [("Content-Range", f"bytes {s}-{e}/{len(data)}"), ("Last-Modified", STAMP)],
                length=e - s + 1,
            )
            h.close_connection = True
            return
        _honest(data, headers=[("Last-Modified", STAMP)])(h, n)

    return answer


def test_replaced_mid_download_other_header_is_changed_not_corrupt(streams, server):
    """The new file's first bytes complete a block begun with the old file's: its CRC-32 (seeded
    with the old header's CRC) fails. That is a replacement, not damaged bytes."""
    a, b, full_a = streams
    _, url = server(_replaced(a, b, after=1))
    res = H.fetch_stream(url, chunk_size=1500, timeout=2, min_rate=None)
    assert res.status == H.CHANGED, str(res)
    assert url in res.message and "discard" in res.message, res.message
    assert res.keepable_gaussians == 0


@pytest.mark.parametrize("end", ["budget", "cut"])
def test_replaced_between_responses_before_a_block_completes_is_changed(streams, server, end):
    """The old file's bytes end at a block boundary; the new file's records of the next block each
    pass their own CRC-8 and no block CRC-32 follows (a budget, a cut): they were kept, decoded
    with the old header's ranges, a silently mixed avatar."""
    a, b, full_a = streams
    first = H0 + 2 * S0  # two whole blocks: request 2 starts block 2
    _, url = server(_replaced(a, b, after=1, cut=(2, 10 * R) if end == "cut" else None))
    kw = {"max_bytes": first + 10 * R} if end == "budget" else {}
    res = H.fetch_stream(url, chunk_size=first, timeout=2, min_rate=None, **kw)
    assert res.status == H.CHANGED, str(res)
    assert res.keepable_gaussians == 0


def test_replaced_mid_download_same_header_is_changed(streams, same_header, server):
    """A byte-identical header: the block the replacement fell into mixes both files' bytes and
    fails its CRC-32; re-reading the header cannot tell, the block's bytes on the server can."""
    a, _, full_a = streams
    _, url = server(_replaced(a, same_header, after=1))
    res = H.fetch_stream(url, chunk_size=1500, timeout=2, min_rate=None)
    assert res.status == H.CHANGED, str(res)
    assert res.keepable_gaussians == 0


def test_replaced_same_header_inside_the_last_block_is_changed(streams, same_header, server):
    """A byte-identical header and the replacement between two records of the last, incomplete
    block: each record passes its CRC-8, no block CRC-32 covers them."""
    a, _, full_a = streams
    first = H0 + 2 * S0 + 5 * R
    _, url = server(_replaced(a, same_header, after=1))
    res = H.fetch_stream(url, chunk_size=first, max_bytes=first + 5 * R, timeout=2, min_rate=None)
    assert res.status == H.CHANGED, str(res)


def test_replaced_same_header_at_a_block_boundary_is_undetectable(streams, same_header, server):
    """The documented limit: a byte-identical header and the replacement exactly between two
    blocks. Every block verifies against the header; nothing received differs from the server's
    file in the block being received. Only a strong ETag rules this out."""
    a, _, full_a = streams
    first = H0 + 2 * S0
    _, url = server(_replaced(a, same_header, after=1))
    res = H.fetch_stream(url, chunk_size=first, max_bytes=first + 10 * R, timeout=2, min_rate=None)
    assert res.status == H.BUDGET, str(res)
    full_c = read_stream(same_header)
    assert_prefix(res.reader.avatar(2 * RPB), full_a, 2 * RPB)  # the old file's blocks 0-1
    np.testing.assert_array_equal(res.avatar().opacity_logit[2 * RPB :], full_c.opacity_logit[2 * RPB : 2 * RPB + 10])


@pytest.mark.parametrize("budget", [True, False], ids=["budget", "to-the-end"])
def test_resume_into_a_same_header_replacement_is_changed(streams, same_header, server, budget):
    """A reader stopped inside a block, resumed against a replacement with a byte-identical header:
    the header CRC check passes, and the new records either complete the old block (its CRC-32
    fails: 'corrupt') or each pass their CRC-8 inside it (a silently mixed avatar)."""
    a, _, full_a = streams
    held = H0 + 2 * S0 + 5 * R
    _, url_a = server(_replaced(a, a, after=1))
    first = H.fetch_stream(url_a, max_bytes=held, timeout=2, min_rate=None)
    assert first.status == H.BUDGET and first.validator == STAMP, str(first)
    _, url_c = server(_replaced(same_header, same_header, after=1))
    kw = {"max_bytes": held + 5 * R} if budget else {}
    res = H.fetch_stream(url_c, reader=first.reader, validator=first.validator, timeout=2, min_rate=None, **kw)
    assert res.status == H.CHANGED, str(res)
    assert res.keepable_gaussians == 0
    assert "same size and validator, so If-Range could not tell" in res.message, res.message


def test_replaced_inside_the_header_is_changed(streams, server):
    """Requests smaller than the header: its first bytes from the old file, the rest from the new
    one. The assembled header fails its CRC-32: the header bytes on the server tell why."""
    a, b, _ = streams
    _, url = server(_replaced(a, b, after=1))
    res = H.fetch_stream(url, chunk_size=300, timeout=2, min_rate=None)
    assert res.status == H.CHANGED, str(res)


def test_records_the_end_check_cannot_tie_are_not_kept(streams, server):
    """The last response brought records of a block it did not complete, and re-reading the
    server's bytes fails (503 from the third request on): they are not kept. With the server
    answering, two small re-reads tie them; with a strong ETag none is needed."""
    a, _, full_a = streams
    first = H0 + 2 * S0
    kw = {"chunk_size": first, "max_bytes": first + 10 * R, "timeout": 2, "min_rate": None}

    def busy(h, n):
        if n > 2:
            return _reply(h, 503, b"busy")
        _honest(a, headers=[("Last-Modified", STAMP)])(h, n)

    _, url = server(busy)
    res = H.fetch_stream(url, **kw)
    assert res.status == H.BUDGET and res.num_gaussians == 2 * RPB + 10, str(res)
    assert res.keepable_gaussians == 2 * RPB and res.unconfirmed == 10
    assert "10 Gaussians" in res.message and url in res.message and "not kept" in res.message, res.message
    _, url = server(_honest(a, headers=[("Last-Modified", STAMP)]))
    res = H.fetch_stream(url, **kw)
    assert res.status == H.BUDGET and res.keepable_gaussians == 2 * RPB + 10 and res.requests == 4, str(res)
    assert_prefix(res.avatar(), full_a, 2 * RPB + 10)
    _, url = server(_honest(a, headers=[("ETag", '"v1"')]))
    res = H.fetch_stream(url, **kw)
    assert res.status == H.BUDGET and res.keepable_gaussians == 2 * RPB + 10 and res.requests == 2, str(res)


def test_corruption_across_responses_stays_corrupt(streams, server):
    """A damaged byte in a later response, no strong ETag: the re-reads find the server's file as
    received, so it is 'corrupt' (the verified prefix kept), not 'changed'."""
    a, _, full_a = streams
    bad = bytearray(a)
    bad[H0 + 3 * S0 + 5] ^= 0x55  # block 3
    _, url = server(_honest(bytes(bad), headers=[("Last-Modified", STAMP)]))
    res = H.fetch_stream(url, chunk_size=1500, timeout=2, min_rate=None)
    assert res.status == H.CORRUPT and "block 3" in res.message, str(res)
    assert res.keepable_gaussians == res.num_gaussians == 3 * RPB
    assert_prefix(res.avatar(), full_a, 3 * RPB)


def test_resume_check_reads_a_header_crc_split_between_pieces(streams, server):
    """A resume against a server that ignores Range re-reads the held prefix; the header CRC's 4
    bytes fell across two pieces of it and were compared in neither: the replaced file's records
    went on to be decoded with the old header."""
    a, b, full_a = streams

    def whole(data):
        return lambda h, n: _reply(h, 200, data, [("Last-Modified", STAMP)])

    _, url_a = server(whole(a))
    first = H.fetch_stream(url_a, percent=40, timeout=2, min_rate=None)
    assert first.status == H.BUDGET and first.validator == STAMP, str(first)
    _, url_b = server(whole(b))
    res = H.fetch_stream(url_b, reader=first.reader, validator=first.validator, read_size=H0 - 2, timeout=2)
    assert res.status == H.CHANGED and "header CRC differs" in res.message, str(res)
    # A server sending the whole file is no If-Range that could not tell; the change may have come
    # before this fetch or during it.
    assert "ignores ranges and sent it again" in res.message and "If-Range" not in res.message, res.message
    assert "since the earlier fetch or during this one" in res.message, res.message
    assert_prefix(res.avatar(), full_a, first.num_gaussians)


def test_the_end_check_keeps_to_the_deadline(streams, server):
    """The re-reads at the end are part of the download: a server dripping their response headers
    (each byte well inside the socket timeout) is stopped by the deadline like any other request,
    and the records they were to tie are not kept."""
    a, _, full_a = streams
    first = H0 + 2 * S0

    def answer(h, n):
        if n <= 2:
            return _honest(a, headers=[("Last-Modified", STAMP)])(h, n)
        for ch in b"HTTP/1.1 206 Partial Content\r\nX-Filler: " + b"x" * 200:
            try:
                h.wfile.write(bytes([ch]))
                h.wfile.flush()
            except OSError:
                return
            time.sleep(0.05)

    _, url = server(answer)
    t = time.monotonic()
    res = H.fetch_stream(url, chunk_size=first, max_bytes=first + 10 * R, timeout=2, deadline=1.0, min_rate=None)
    took = time.monotonic() - t
    assert took < 2.0, (took, str(res))
    assert res.status == H.BUDGET and res.keepable_gaussians == 2 * RPB and res.unconfirmed == 10, str(res)


def test_an_end_check_redirected_to_a_bad_host_is_a_status_not_an_exception(streams, server):
    """Records left untied, then a redirect to a host name IDNA cannot encode: the transfer ends
    as an http_error naming it, and the end check's own request to that host must not raise."""
    a, _, full_a = streams
    bad = "http://" + "a" * 64 + ".example/s.pavs"

    def answer(h, n):
        # 100-byte requests: the 6th completes the header (at 530), the 7th only brings records
        if n <= 7:
            return _honest(a, headers=[("Last-Modified", STAMP)])(h, n)
        _reply(h, 302, headers=[("Location", bad)])

    _, url = server(answer)
    res = H.fetch_stream(url, chunk_size=100, timeout=2, min_rate=None)
    assert res.status == H.HTTP_ERROR and bad in res.message, str(res)
    assert res.keepable_gaussians == res.num_gaussians - res.unconfirmed < res.num_gaussians, str(res)


@pytest.mark.parametrize("more", [0, 3], ids=["no-byte", "three-records"])
def test_a_resume_keeps_the_records_the_earlier_end_check_could_not_tie_unconfirmed(streams, server, more):
    """An earlier fetch left 10 records untied (its re-reads failed: 503). A resume that brings no
    byte, or 3 more records of the same block, while the server's re-reads still fail must not
    report those 10 keepable: neither this fetch nor the earlier one tied them to the header."""
    a, _, full_a = streams
    first = H0 + 2 * S0

    def busy(h, n):
        if n > 2:
            return _reply(h, 503, b"busy")
        _honest(a, headers=[("Last-Modified", STAMP)])(h, n)

    _, url = server(busy)
    res = H.fetch_stream(url, chunk_size=first, max_bytes=first + 10 * R, timeout=2, min_rate=None)
    assert res.status == H.BUDGET and res.keepable_gaussians == 2 * RPB and res.unconfirmed == 10, str(res)
    # the resume: its header CRC check and `more` records answered, the re-reads not
    _, url2 = server(lambda h, n: busy(h, n) if (n <= 1 or (more and n == 2)) else _reply(h, 503, b"busy"))
    kw = {"max_bytes": first + (10 + more) * R, "chunk_size": more * R} if more else {}
    res2 = H.fetch_stream(url2, reader=res.reader, validator=res.validator, timeout=2, min_rate=None, **kw)
    assert res2.status == (H.BUDGET if more else H.HTTP_ERROR), str(res2)
    assert res2.num_gaussians == 2 * RPB + 10 + more, str(res2)
    assert res2.keepable_gaussians == 2 * RPB and res2.unconfirmed == 10 + more, str(res2)
