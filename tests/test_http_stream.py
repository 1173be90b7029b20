"""Progressive HTTP download (core/stream/http.py) against real local servers."""

import re
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from progressive_avatars.core.stream import http as H
from progressive_avatars.core.stream.format import StreamError, TemplateMismatch, read_header
from progressive_avatars.core.stream.reader import read_stream
from progressive_avatars.core.stream.writer import encode_stream
from tests.test_stream import assert_prefix, make_avatar


class Handler(BaseHTTPRequestHandler):
    # set per server: data, mode ("range" | "norange"), stall_at, cut_at, status, release, log
    def log_message(self, *args):
        pass

    def do_GET(self):
        srv = self.server
        srv.log.append(self.headers.get("Range"))
        if srv.status != 200:
            self.send_error(srv.status, "nope")
            return
        if self.path == "/moved":
            self.send_response(302)
            self.send_header("Location", "/s.pavs")
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        data = srv.data
        start, end = 0, len(data) - 1
        rng = self.headers.get("Range")
        partial = False
        if rng and srv.mode == "range":
            m = re.match(r"bytes=(\d+)-(\d*)", rng)
            start = int(m.group(1))
            end = min(int(m.group(2)) if m.group(2) else len(data) - 1, len(data) - 1)
            if start >= len(data):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(data)}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            partial = True
        self.send_response(206 if partial else 200)
        if partial:
            self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
        self.send_header("Content-Length", str(end - start + 1))
        self.send_header("Accept-Ranges", "bytes" if srv.mode == "range" else "none")
        self.end_headers()
        body = data[start : end + 1]
        for at, action in ((srv.stall_at, "stall"), (srv.cut_at, "cut")):
            if at is not None and start <= at <= end:
                self.wfile.write(body[: at - start])
                self.wfile.flush()
                if action == "stall":
                    srv.release.wait(5)  # bounded: the test releases it on teardown
                else:
                    import socket

                    self.connection.shutdown(socket.SHUT_RDWR)
                    self.close_connection = True
                return
        self.wfile.write(body)


class Server:
    def __init__(self, data, mode="range", stall_at=None, cut_at=None, status=200, http11=False):
        Handler.protocol_version = "HTTP/1.1" if http11 else "HTTP/1.0"
        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.httpd.block_on_close = False
        self.httpd.data, self.httpd.mode, self.httpd.status = data, mode, status
        self.httpd.stall_at, self.httpd.cut_at = stall_at, cut_at
        self.httpd.release = threading.Event()
        self.httpd.log = []
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/s.pavs"

    def close(self):
        self.httpd.release.set()
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(5)


@pytest.fixture(scope="module")
def stream():
    _, av, imp = make_avatar(11, n_lat=6, n_lon=10, depth=3)
    data = encode_stream(av, imp, records_per_block=16)
    return data, read_stream(data), read_header(data)


@pytest.fixture
def serve():
    servers = []

    def start(*a, **k):
        s = Server(*a, **k)
        servers.append(s)
        return s

    yield start
    for s in servers:
        s.close()


@pytest.mark.parametrize("http11", [False, True])
def test_range_download_complete_with_callbacks(stream, serve, http11):
    data, full, info = stream
    srv = serve(data, http11=http11)
    seen = []
    res = H.fetch_stream(
        srv.url,
        chunk_size=1000,
        read_size=300,
        timeout=2,
        on_chunk=lambda r, new: seen.append((r.bytes_received, r.num_gaussians, new)),
    )
    assert res.status == H.COMPLETE and res.ok, str(res)
    assert res.used_ranges and res.requests == -(-len(data) // 1000)
    assert all(g == (info.count_for_bytes(b) if b >= info.header_size else 0) for b, g, _ in seen)
    assert sum(n for _, _, n in seen) == info.num_records
    assert_prefix(res.avatar(), full, info.num_records)
    assert srv.httpd.log[0] == "bytes=0-999"


def test_server_ignoring_range_falls_back_to_plain_get(stream, serve):
    data, full, info = stream
    srv = serve(data, mode="norange")
    calls = []
    res = H.fetch_stream(srv.url, chunk_size=1000, read_size=512, timeout=2, on_chunk=lambda r, n: calls.append(n))
    assert res.status == H.COMPLETE and res.used_ranges is False and res.requests == 1, str(res)
    assert len(calls) >= -(-len(data) // 512) and sum(calls) == info.num_records
    assert_prefix(res.avatar(), full, info.num_records)


@pytest.mark.parametrize("mode", ["range", "norange"])
def test_stall_keeps_what_was_verified(stream, serve, mode):
    data, full, info = stream
    at = info.header_size + 50 * 23 + 7
    srv = serve(data, mode=mode, stall_at=at)
    t = time.monotonic()
    res = H.fetch_stream(srv.url, chunk_size=4096, read_size=256, timeout=0.4)
    assert time.monotonic() - t < 3
    assert res.status == H.STALLED, str(res)
    assert res.bytes_received == at
    assert res.num_gaussians == info.count_for_bytes(at)
    assert_prefix(res.avatar(), full, info.count_for_bytes(at))


@pytest.mark.parametrize("mode", ["range", "norange"])
def test_connection_cut_keeps_what_was_verified(stream, serve, mode):
    data, full, info = stream
    at = info.header_size + 77 * 23 + 3
    srv = serve(data, mode=mode, cut_at=at)
    res = H.fetch_stream(srv.url, chunk_size=4096, read_size=256, timeout=2)
    assert res.status == H.CUT, str(res)
    assert res.bytes_received == at
    assert_prefix(res.avatar(), full, info.count_for_bytes(at))
    # resume from where it stopped, on a healthy server
    srv2 = serve(data)
    res2 = H.fetch_stream(srv2.url, reader=res.reader, chunk_size=4096, timeout=2)
    assert res2.status == H.COMPLETE, str(res2)
    # resumed without a strong ETag: the header's CRC is read again first (a file replaced since
    # would pass each record's own check), then the rest from where the reader stopped
    assert srv2.httpd.log[:2] == [f"bytes={info.header_size - 4}-{info.header_size - 1}", f"bytes={at}-{at + 4095}"]
    assert_prefix(res2.avatar(), full, info.num_records)


def test_http_errors_and_unreachable(stream, serve):
    data, _, _ = stream
    srv = serve(data, status=404)
    res = H.fetch_stream(srv.url, timeout=2)
    assert res.status == H.HTTP_ERROR and res.http_status == 404 and res.num_gaussians == 0
    srv_dead = serve(data)
    dead_url = srv_dead.url
    srv_dead.close()
    res = H.fetch_stream(dead_url, timeout=1)
    assert res.status in (H.UNREACHABLE, H.CUT) and res.num_gaussians == 0


def test_redirect_budget_and_cancel(stream, serve):
    data, full, info = stream
    srv = serve(data)
    moved = srv.url.replace("/s.pavs", "/moved")
    res = H.fetch_stream(moved, chunk_size=2048, timeout=2, percent=40)
    assert res.status == H.BUDGET, str(res)
    n = info.count_for_percent(40)
    assert res.num_gaussians == n
    assert_prefix(res.avatar(), full, n)
    res = H.fetch_stream(srv.url, chunk_size=700, timeout=2, max_bytes=1500)
    assert res.status == H.BUDGET and res.bytes_received == 1500
    res = H.fetch_stream(
        srv.url, chunk_size=700, read_size=100, timeout=2, on_chunk=lambda r, new: r.bytes_received < 1000
    )
    assert res.status == H.CANCELLED and res.bytes_received == 1000


def test_corruption_is_reported_not_hidden(stream, serve):
    data, full, info = stream
    bad = bytearray(data)
    o = info.record_offset(100) + 5
    bad[o] ^= 0x55
    srv = serve(bytes(bad))
    res = H.fetch_stream(srv.url, chunk_size=1 << 16, read_size=256, timeout=2)
    assert res.status == H.CORRUPT and ("record 100" in res.message or "block 6" in res.message), str(res)
    assert res.num_gaussians <= 100
    assert_prefix(res.avatar(), full, res.num_gaussians)


def test_only_verification_failures_are_corrupt(stream, serve):
    """A flipped byte is a StreamError ("corrupt"); a valid stream bound to another template is
    refused as such ("refused"), not reported as damaged bytes."""
    data, full, info = stream
    bad = bytearray(data)
    bad[info.record_offset(3) + 2] ^= 0x21
    with pytest.raises(StreamError):
        read_stream(bytes(bad), template_faces=full.forest.template_faces)
    other = full.forest.template_faces[::-1].copy()
    with pytest.raises(TemplateMismatch):
        read_stream(data, template_faces=other)
    res = H.fetch_stream(serve(data).url, template_faces=other, timeout=2)
    assert res.status == H.REFUSED and "template mismatch" in res.message, str(res)


def test_cuts_inside_every_level_of_a_coarse_stream(serve):
    """A stream with coarse levels, cut (connection closed) at 1, 3, 10 and 50 % of its bytes and
    inside every level: each download keeps exactly the whole verified records, and they bind
    to the whole template (a cut inside a root level is a spread-out subset of its roots)."""
    verts, av, imp = make_avatar(31, n_lat=10, n_lon=14, depth=3, coarse=True)
    data = encode_stream(av, imp, records_per_block=16, embed_template=False)
    full = read_stream(data, template_faces=av.forest.template_faces)
    info = read_header(data)
    ends = info.level_ends()
    cuts = {int(p / 100 * len(data)) for p in (1, 3, 10, 50)}
    cuts |= {info.bytes_for_count(int(e) - max(1, int(c) // 2)) + 5 for e, c in zip(ends, info.level_counts)}
    for at in sorted(c for c in cuts if info.header_size < c < len(data)):
        srv = serve(data, cut_at=at)
        res = H.fetch_stream(
            srv.url, template_faces=av.forest.template_faces, chunk_size=4096, read_size=256, timeout=2
        )
        assert res.status == H.CUT, str(res)
        n = info.count_for_bytes(at)
        assert res.num_gaussians == n
        a = res.avatar()
        assert_prefix(a, full, n)
        if a is not None:
            np.testing.assert_array_equal(a.forest.template_faces, av.forest.template_faces)
            g = a.gaussians(verts)
            assert all(np.all(np.isfinite(v)) for v in g.values())
