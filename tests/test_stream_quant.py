"""Robust quantisation (stream version 4, docs/FORMAT.md 3.2): outliers are carried exactly in
the header's exceptions table, the ranges hold the bulk, every value stays within the
documented bound, and prefixes, both readers and corrupted tables behave as the format says."""

import struct
import zlib

import numpy as np
import pytest

from progressive_avatars.core.avatar.avatar import Avatar, SH_C0
from progressive_avatars.core.stream.format import (
    LOG_SCALE_LIMIT,
    RANGE_LIMIT,
    StreamError,
    max_exceptions,
    quant_steps,
    read_header,
)
from progressive_avatars.core.stream.reader import StreamReader, read_stream
from progressive_avatars.core.stream.writer import write_stream
from tests.test_stream import PARAMS, assert_prefix, make_avatar


def base_avatar(seed=0):
    """A random forest with a trained avatar's proportions: small offsets, log-scales around
    -4, colours mostly inside [0, 1], rotations near the identity."""
    _, av, imp = make_avatar(seed, n_lat=6, n_lon=9, depth=3, frac=0.5)
    rng = np.random.default_rng(seed + 100)
    N = av.num_gaussians
    q = np.concatenate([np.ones((N, 1)), rng.normal(0, 0.15, (N, 3))], 1)
    av = Avatar(
        av.forest,
        rng.normal(0, 0.05, (N, 3)),
        rng.normal(-4.0, 0.5, (N, 3)),
        q,
        rng.normal(0, 2.0, N),
        rng.normal(0, 0.6, (N, 3)),
    )
    return av, imp


def copy(av):
    return Avatar(av.forest, *(getattr(av, n).copy() for n in PARAMS))


def roundtrip(tmp_path, av, imp, version=4, **kw):
    p = tmp_path / f"v{version}.pavs"
    info = write_stream(p, av, imp, version=version, **kw)
    data = p.read_bytes()
    return info, data, read_stream(data)


def errors(av, info, out):
    """Per-Gaussian quantisation errors (stream order): position (face scales), log-scale,
    rendered colour max(0.5 + SH_C0 f_dc, 0), rotation angle (radians)."""
    o = info.order
    ref = {n: getattr(av, n)[o].astype(np.float64) for n in PARAMS}
    dec = {n: getattr(out, n).astype(np.float64) for n in PARAMS}
    pos = np.linalg.norm(dec["d_mu"] - ref["d_mu"], axis=1)
    ls = np.abs(dec["d_log_scale"] - np.clip(ref["d_log_scale"], -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT))
    col = np.abs(np.maximum(0.5 + SH_C0 * dec["f_dc"], 0) - np.maximum(0.5 + SH_C0 * ref["f_dc"], 0))
    a = dec["d_rot"] / np.linalg.norm(dec["d_rot"], axis=1, keepdims=True)
    b = ref["d_rot"] / np.linalg.norm(ref["d_rot"], axis=1, keepdims=True)
    rot = 2 * np.arccos(np.clip(np.abs((a * b).sum(1)), 0, 1))
    return {"pos": pos, "ls": ls.max(1), "col": col.max(1), "rot": rot}


def assert_within_bound(av, info, out):
    """FORMAT.md 3.2: a component carried in the exceptions table decodes to its float32
    value exactly; every other one within half a step of its range (plus float32 rounding).
    Compared in stream order: exception indices are stream positions, and from version 5 the
    decoded avatar's rows (roots first) are not."""
    o = info.order
    at = out.forest.stream_order()  # the decoded row of each stream position
    idx, comp, val = info.exceptions if info.exceptions is not None else (np.zeros(0, int),) * 3
    esc = np.zeros((info.num_records, 13), bool)
    esc[idx, comp] = True
    steps = quant_steps(info.quant)
    c = 0.5 + SH_C0 * av.f_dc[o].astype(np.float64)
    cases = [
        ("d_mu", np.clip(av.d_mu[o], -RANGE_LIMIT, RANGE_LIMIT), steps["mu"][1], 0),
        ("d_log_scale", np.clip(av.d_log_scale[o], -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT), steps["ls"][1], 3),
        ("f_dc", (np.clip(c, 0, RANGE_LIMIT) - 0.5) / SH_C0, steps["fdc"][1], 6),
    ]
    for name, want, step, first in cases:
        got = getattr(out, name)[at].astype(np.float64)
        for k in range(3):
            e = esc[:, first + k]
            exact = getattr(av, name)[o][e, k].astype(np.float32)
            if name == "d_log_scale":
                exact = np.clip(exact, -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT)
            np.testing.assert_array_equal(getattr(out, name)[at][e, k], exact, err_msg=f"{name}[{k}] escaped")
            err = np.abs(got[~e, k] - want[~e, k])
            bound = step[k] / 2 + 1e-6 * (np.abs(want[~e, k]) + abs(float(step[k])) * 4096)
            assert np.all(err <= bound), (name, k, err.max(), step[k])


def injected(av, imp, edits):
    bad = copy(av)
    for name, where, value in edits:
        getattr(bad, name)[where] = value
    return bad


FIELD_OUTLIERS = {
    "position 1e3": [("d_mu", (17, 0), 1e3)],
    "colour 1e6": [("f_dc", (40, 1), 1e6)],
    "log-scale +25": [("d_log_scale", (63, 2), 25.0)],
    "log-scale -25": [("d_log_scale", (5, 0), -25.0)],
    "rotation 180 degrees": [("d_rot", 90, (0.0, 1.0, 0.0, 0.0))],
}
METRIC = {"position 1e3": "pos", "colour 1e6": "col", "log-scale +25": "ls", "log-scale -25": "ls"}


@pytest.mark.parametrize("case", list(FIELD_OUTLIERS))
def test_one_outlier_leaves_every_other_gaussian_as_accurate(tmp_path, case):
    av, imp = base_avatar()
    info0, _, out0 = roundtrip(tmp_path, av, imp)
    clean = errors(av, info0, out0)
    bad = injected(av, imp, FIELD_OUTLIERS[case])
    info, _, out = roundtrip(tmp_path, bad, imp)
    err = errors(bad, info, out)
    assert info.version == 4 and 1 <= info.num_exceptions <= max_exceptions(info.num_records)
    hit = np.isin(info.order, [w if isinstance(w, int) else w[0] for _, w, _ in FIELD_OUTLIERS[case]])
    for m in err:  # within 2x of the outlier-free figure, mean and worst, every metric
        assert err[m][~hit].mean() <= 2 * clean[m].mean() + 1e-7, (m, err[m][~hit].mean(), clean[m].mean())
        assert err[m][~hit].max() <= 2 * clean[m].max() + 1e-7, (m, err[m][~hit].max(), clean[m].max())
        # the outlier's own Gaussian: its escaped components exact, the others quantised as usual
        assert err[m][hit].max() <= 2 * clean[m].max() + 1e-7, (m, err[m][hit].max())
    assert_within_bound(bad, info, out)
    if case in METRIC:  # the same outlier under version 3's min..max ranges: every Gaussian pays
        info3, _, out3 = roundtrip(tmp_path, bad, imp, version=3)
        m = METRIC[case]
        assert errors(bad, info3, out3)[m][~hit].mean() > 4 * clean[m].mean()


def test_a_handful_at_once_and_more_than_the_cap(tmp_path):
    av, imp = base_avatar(1)
    info0, _, out0 = roundtrip(tmp_path, av, imp)
    clean = errors(av, info0, out0)
    edits = [e for v in FIELD_OUTLIERS.values() for e in v] + [("d_mu", (200, 2), -7e2), ("f_dc", (300, 0), -5e5)]
    bad = injected(av, imp, edits)
    info, _, out = roundtrip(tmp_path, bad, imp)
    err = errors(bad, info, out)
    rows = [w if isinstance(w, int) else w[0] for _, w, _ in edits]
    hit = np.isin(info.order, rows)
    for m in err:
        assert err[m][~hit].max() <= 2 * clean[m].max() + 1e-7, m
    assert_within_bound(bad, info, out)
    # More outliers than the cap: at most the cap are carried exactly (the farthest), the rest
    # set the range; every value still within the bound of its (wider) range.
    N = av.num_gaussians
    cap = max_exceptions(N)
    for count in (cap + 3, 5 * cap):
        many = copy(av)
        many.d_mu[:count, 0] = np.linspace(50, 500, count)
        info, _, out = roundtrip(tmp_path, many, imp)
        assert info.num_exceptions <= cap and (info.num_exceptions > 0 or count > 2 * cap)
        assert_within_bound(many, info, out)
        if info.num_exceptions:
            idx, comp, val = info.exceptions
            kept = np.setdiff1d(np.arange(N), info.order[idx])
            assert set(comp.tolist()) == {0} and val.min() > many.d_mu[kept, 0].max()  # the farthest escaped


def test_writer_never_emits_a_stream_its_reader_refuses(tmp_path):
    """Values at float32's limits and log-scales near overflow: both versions write, both read
    back finite, clamped to the documented limits (log-scale +-80, others +-1e30)."""
    av, imp = base_avatar(2)
    N = av.num_gaussians
    k = max_exceptions(N) + 5  # more than can escape: they set the range
    bad = copy(av)
    bad.d_mu[:k, 0] = 3e38
    bad.d_mu[k : 2 * k, 1] = -3e38
    bad.f_dc[:k, 2] = 3e38
    bad.d_log_scale[:k, 0] = 85.0
    bad.d_log_scale[k : 2 * k, 1] = -85.0
    for version in (3, 4):
        info, data, out = roundtrip(tmp_path, bad, imp, version=version)
        r = StreamReader()
        r.feed(data)
        for a in (out, r.avatar()):
            for n in PARAMS:
                assert np.all(np.isfinite(getattr(a, n))), (version, n)
            assert np.abs(a.d_log_scale).max() <= LOG_SCALE_LIMIT * (1 + 1e-6)
            assert np.abs(a.d_mu).max() <= RANGE_LIMIT * 1.001
        if version == 4:
            assert_within_bound(bad, info, out)


def _outlier_stream(tmp_path, records_per_block=8):
    av, imp = base_avatar(3)
    N = av.num_gaussians
    rng = np.random.default_rng(5)
    bad = copy(av)
    rows = rng.choice(N, 14, replace=False)
    for j, i in enumerate(rows):  # spread over every component family and the whole stream
        name, k, v = [("d_mu", j % 3, 1e3), ("f_dc", j % 3, 1e6), ("d_log_scale", j % 3, -25.0)][j % 3]
        getattr(bad, name)[i, k] = v
    bad.d_rot[rows[-1]] = (0.0, 0.0, 0.0, 1.0)
    info, data, full = roundtrip(tmp_path, bad, imp, records_per_block=records_per_block)
    return bad, info, data, full


def test_every_prefix_of_a_stream_with_exceptions_decodes_as_the_full_stream(tmp_path):
    bad, info, data, full = _outlier_stream(tmp_path)
    idx = info.exceptions[0]
    assert info.num_exceptions >= 13 and idx.min() < info.num_roots < idx.max()
    assert_within_bound(bad, info, full)
    for n in range(info.num_records + 1):  # a cut at every record boundary
        assert_prefix(read_stream(data[: info.bytes_for_count(n)]), full, n)
    for step in (1, 23, 61, 4096):  # the incremental reader, any feed size, equals read_stream
        r = StreamReader()
        for i in range(0, len(data), step):
            r.feed(data[i : i + step])
            if step > 1 and i // step % 7 == 3:  # decoding mid-stream, then going on
                assert_prefix(r.avatar(), full, r.num_gaussians)
        assert_prefix(r.avatar(), full, info.num_records)


def _exceptions_offset(info):
    return 64 + 4 * info.num_levels + 104


def _reseal(data, info, blob):
    """`data`'s header with its exceptions table replaced by `blob` (same size) and the header
    CRC-32 recomputed: what a buggy writer would make."""
    b = bytearray(data[: info.header_size])
    o = _exceptions_offset(info)
    b[o : o + len(blob)] = blob
    b[-4:] = struct.pack("<I", zlib.crc32(bytes(b[:-4])))
    return bytes(b)


def test_a_corrupted_exceptions_table_is_refused(tmp_path):
    _, info, data, _ = _outlier_stream(tmp_path)
    E, o = info.num_exceptions, _exceptions_offset(info)
    assert struct.unpack_from("<I", data, 60)[0] == E
    for pos in range(o, o + 9 * E):  # any byte changed: the header CRC-32 refuses it
        bad = bytearray(data)
        bad[pos] ^= 0x10
        with pytest.raises(StreamError, match="header checksum"):
            read_stream(bytes(bad))
        with pytest.raises(StreamError, match="header checksum"):
            StreamReader().feed(bytes(bad[: info.header_size + 50]))
    blob = bytearray(data[o : o + 9 * E])
    N = info.num_records
    forged = {
        "index beyond N": (0, struct.pack("<I", N)),
        "component 13": (4 * E, bytes([13])),
        "out of order": (0, struct.pack("<II", *struct.unpack_from("<II", blob, 0)[::-1])),
        "NaN": (5 * E, struct.pack("<f", float("nan"))),
        "log-scale 1e3": (
            5 * E + 4 * int(np.flatnonzero((info.exceptions[1] >= 3) & (info.exceptions[1] < 6))[0]),
            struct.pack("<f", 1e3),
        ),
    }
    for what, (at, raw) in forged.items():
        b = bytearray(blob)
        b[at : at + len(raw)] = raw
        with pytest.raises(StreamError, match="exceptions table"):
            read_header(_reseal(data, info, bytes(b)))
    # a count beyond the cap, or in a lossless stream: refused from the fixed part
    bad = bytearray(data)
    bad[60:64] = struct.pack("<I", max_exceptions(N) + 1)
    with pytest.raises(StreamError, match="exceptions"):
        read_stream(bytes(bad))


def test_version_4_header_ranges_beyond_the_limits_are_refused(tmp_path):
    _, info, data, _ = _outlier_stream(tmp_path)
    q = 64 + 4 * info.num_levels  # the quantisation table: mu lo[3] hi[3], ...
    b = bytearray(data[: info.header_size])
    b[q + 12 : q + 16] = struct.pack("<f", 3e38)  # mu hi x: lo + 4095 * step would overflow
    b[-4:] = struct.pack("<I", zlib.crc32(bytes(b[:-4])))
    with pytest.raises(StreamError, match="quantisation ranges"):
        read_header(bytes(b))
