"""Decoding quantised records into float32 parameters (FORMAT.md 3.1), vectorised over
records (numpy only: runs in Blender)."""

from __future__ import annotations

import math

import numpy as np

from .format import _QUANT_WORDS


# -- decoding constants (FORMAT.md 3.1: float32 arithmetic, bit-exact in any IEEE-754 reader) --
_SQRT1_2 = 1.0 / math.sqrt(2.0)
_ROT_STEP = np.float32(2.0 * _SQRT1_2 / 1023.0)  # version 1 rotations
_ROT_LO = np.float32(-_SQRT1_2)
_OPA_ALPHA = (np.arange(256) + 0.5) / 256.0
_OPA_LUT = np.log(_OPA_ALPHA / (1.0 - _OPA_ALPHA)).astype(np.float32)
_BARY_LUT = np.log(np.maximum(np.arange(4096, dtype=np.float64), 2.0**-20) / 4095.0).astype(np.float32)
_BARY_LUT_REV = np.ascontiguousarray(_BARY_LUT[::-1])  # [s] = _BARY_LUT[4095 - s]


def _decode_scratch(n) -> dict:
    """Contiguous work rows for _decode_quantised over runs of up to n records (allocated once
    per decode: fresh large allocations would page-fault on every run)."""
    return {
        "f": np.empty((6, n), np.float32),
        "e": np.empty((4, n), np.float32),
        "t16": np.empty(n, np.uint16),
        "ix": np.empty((2, n), np.intp),
        "zero": np.zeros(n, np.float32),
    }


def _decode_quantised(raw, out, steps, scratch):
    """FORMAT.md 3.1 for records raw [n,23] into the float32 columns of `out`, in float32
    arithmetic as specified (products and sums separately rounded). Every operation is one
    whole-column pass (1-D, so numpy's inner loops run over all records, never over 3).
    Codes are first cast into a contiguous float32 row and the arithmetic runs there: numpy's
    mixed-type and strided loops are 2-3x slower, so each output column is written once, by
    the last operation."""
    rec = raw.view(_QUANT_WORDS)[:, 0]
    n = len(rec)
    mul, add, take = np.multiply, np.add, np.take
    m12 = np.uint16(0xFFF)
    f = scratch["f"][:, :n]
    t16 = scratch["t16"][:n]
    ix, ix2 = scratch["ix"][:, :n]
    a = f[0]
    # positions (12-bit affine codes)
    lo, step = steps["mu"]
    mu = out["d_mu"]
    for k, (op, field, arg) in enumerate(
        ((np.bitwise_and, "mx", m12), (np.right_shift, "my", np.uint16(4)), (np.bitwise_and, "mz", m12))
    ):
        a[...] = op(rec[field], arg, out=t16)
        mul(a, step[k], out=a)
        add(a, lo[k], out=mu[:, k])
    # split logits: beta0, beta1 and beta2 = 4095 - beta0 - beta1 through the log table
    # (The checks admitted only records with beta0 + beta1 <= 4095, so every index is in the
    # table and mode="wrap" returns what "clip" would; gathering into a contiguous row and
    # copying it into the strided column is faster than either mode gathering in place.)
    sl = out["split_logits"]
    g = f[4]
    np.right_shift(rec["b0"], np.uint16(4), out=ix)
    take(_BARY_LUT, ix, out=g, mode="wrap")
    sl[:, 0] = g
    ix2[...] = np.bitwise_and(rec["b1"], m12, out=t16)
    take(_BARY_LUT, ix2, out=g, mode="wrap")
    sl[:, 1] = g
    ix += ix2
    take(_BARY_LUT_REV, ix, out=g, mode="wrap")
    sl[:, 2] = g
    # log-scales, colours and (version 2) rotations w x y z: 8-bit affine codes
    affine8 = [("d_log_scale", "ls", "ls"), ("f_dc", "col", "fdc")]
    if "rot" in steps:
        affine8.append(("d_rot", "rq", "rot"))
    else:
        _decode_rotation_v1(rec, out["d_rot"], f, t16, scratch)
    for name, field, key in affine8:
        lo, step = steps[key]
        codes = rec[field]
        dst = out[name]
        for k in range(len(lo)):
            a[...] = codes[:, k]
            mul(a, step[k], out=a)
            add(a, lo[k], out=dst[:, k])
    # opacity (table)
    ix[...] = rec["opa"]
    take(_OPA_LUT, ix, out=out["opacity_logit"], mode="wrap")  # u8 codes: always in the table


def _decode_rotation_v1(rec, q, f, t16, scratch):
    """Version 1 rotations (FORMAT.md 7): the three smallest components (10 bit each), the
    largest from the unit norm, placed at the index the record names."""
    n = len(rec)
    f32 = np.float32
    mul, add = np.multiply, np.add
    m10 = np.uint16(0x3FF)
    v0, v1, v2, w, t, u = f
    for v, field, shift in ((v0, "r0", 0), (v1, "r1", 2), (v2, "r2", 4)):
        np.right_shift(rec[field], np.uint16(shift), out=t16)
        v[...] = np.bitwise_and(t16, m10, out=t16)
        mul(v, _ROT_STEP, out=v)
    f[:3] += _ROT_LO
    mul(v0, v0, out=w)
    mul(v1, v1, out=t)
    w += t
    mul(v2, v2, out=t)
    w += t
    np.subtract(f32(1), w, out=w)
    np.maximum(w, scratch["zero"][:n], out=w)  # (numpy 1.26 runs max(array, scalar) unvectorised: 5x slower)
    np.sqrt(w, out=w)
    # Place: slot `big` takes w, the others v0, v1, v2 in order. Selecting by multiplying with
    # 0/1 masks is exact here (x·1 = x, x·0 = ±0, x + ±0 = x; all values finite, none -0,
    # w >= 0) and several times faster than np.where.
    big = np.right_shift(rec["big"], np.uint8(6))
    e = scratch["e"][:, :n]
    for j in range(4):
        np.equal(big, np.uint8(j), out=e[j])
    e0, e1, e2, e3 = e
    mul(w, e0, out=t)  # big == 0 ? w : v0
    np.subtract(f32(1), e0, out=u)
    mul(v0, u, out=u)
    add(t, u, out=q[:, 0])
    mul(v0, e0, out=t)  # big == 0 ? v0 : big == 1 ? w : v1
    mul(w, e1, out=u)
    t += u
    add(e2, e3, out=u)
    mul(v1, u, out=u)
    add(t, u, out=q[:, 1])
    add(e0, e1, out=t)  # big <= 1 ? v1 : big == 2 ? w : v2
    mul(v1, t, out=t)
    mul(w, e2, out=u)
    t += u
    mul(v2, e3, out=u)
    add(t, u, out=q[:, 2])
    mul(w, e3, out=t)  # big == 3 ? w : v2
    np.subtract(f32(1), e3, out=u)
    mul(v2, u, out=u)
    add(t, u, out=q[:, 3])
