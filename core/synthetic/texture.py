"""The synthetic head's appearance: a procedural albedo of the canonical point (skin, hair
strands, eyes, lips, collar, marks), per-face detail, and the paper-scale head's albedo.
Reporting tier (numpy).
"""

from __future__ import annotations

import numpy as np

from .fields import _edge, _fbm, _hash01, _mix, _sd_ellipsoid, _smoothstep, _value_noise
from .surface import (
    _BUTTON_Y,
    _buttons,
    _ear_coords,
    EYE_CENTERS,
    EYE_HALF_OPENING,
    EYE_HALF_WIDTH,
    _hairline_mask,
    MOUTH_Y,
    NECK_AXIS_Z,
    _strands,
)

SKIN = np.array([0.86, 0.66, 0.55])
BLUSH = np.array([0.86, 0.50, 0.46])
HAIR = np.array([0.23, 0.15, 0.10])
LIP = np.array([0.72, 0.33, 0.35])
MOUTH_INSIDE = np.array([0.16, 0.04, 0.05])
SCLERA = np.array([0.94, 0.92, 0.89])
IRIS = np.array([0.22, 0.44, 0.52])
PUPIL = np.array([0.03, 0.03, 0.04])
SHIRT = np.array([0.10, 0.16, 0.38])
WHITE = np.array([0.96, 0.96, 0.95])
INK = np.array([0.05, 0.05, 0.06])


def albedo(points) -> np.ndarray:
    """Procedural reflectance [N,3] in [0,1] at canonical surface points [N,3] (metres)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    n = len(p)

    # smooth skin: low-frequency mottling, warmer cheeks, lighter forehead
    col = np.tile(SKIN, (n, 1)) * (0.92 + 0.14 * _fbm(p * 22.0, 2, 1))[:, None]
    col += (0.035 * _smoothstep(0.0, 0.09, y))[:, None] * np.array([1.0, 0.95, 0.8])
    col *= (1.0 - 0.10 * _smoothstep(-0.12, -0.2, y))[:, None]  # neck a shade darker
    for sx in (1.0, -1.0):
        g = np.exp(-((x - sx * 0.046) ** 2 + (y + 0.022) ** 2) / (2 * 0.019**2)) * _smoothstep(0.02, 0.06, z)
        col = _mix(col, BLUSH, 0.45 * g)
    front = z > 0.04

    # stubble: crisp dark dots on chin, jaw and upper lip (3D cell dots cut by the surface)
    beard = (
        _smoothstep(-0.036, -0.046, y)
        * _smoothstep(-0.128, -0.112, y)
        * _smoothstep(-0.02, 0.02, z)
        * (1.0 - _smoothstep(0.055, 0.07, ax) * _smoothstep(-0.07, -0.06, y))
    )
    sel = np.nonzero(beard > 0.01)[0]
    if len(sel):
        cell = 0.0024
        q = p[sel] / cell
        ci = np.floor(q).astype(np.int64)
        jitter = np.stack([_hash01(ci[:, 0], ci[:, 1], ci[:, 2], 31 + k) for k in range(3)], 1)
        d = np.linalg.norm(q - ci - 0.25 - 0.5 * jitter, axis=1)
        present = _hash01(ci[:, 0], ci[:, 1], ci[:, 2], 37) < 0.75
        dots = _edge(d - 0.36, 0.06) * present
        col[sel] *= (1.0 - 0.55 * dots * beard[sel])[:, None]
        col[sel] *= (1.0 - 0.12 * beard[sel])[:, None]  # shadow of the shaved beard area

    # lips with a crisp outline and a dark mouth interior along the contact line
    sel = np.nonzero(front & (np.abs(y - MOUTH_Y) < 0.014) & (ax < 0.03))[0]
    if len(sel):
        xs, dy = x[sel], y[sel] - MOUTH_Y
        u = np.clip(1.0 - (xs / 0.025) ** 2, 0.0, 1.0)
        upper_h = 0.0082 * np.sqrt(u) - 0.0016 * np.exp(-(xs**2) / (2 * 0.0035**2)) * np.sqrt(u)
        lower_h = 0.0098 * np.sqrt(np.clip(1.0 - (xs / 0.0235) ** 2, 0.0, 1.0))
        inside = np.where(dy >= 0, dy - upper_h, -dy - lower_h)
        lip = _edge(inside, 0.00025)
        creases = 0.93 + 0.07 * np.sin(xs / 0.0009)
        lipcol = LIP * creases[:, None]
        c = _mix(col[sel], 0.8 * LIP, _edge(np.abs(inside) - 0.0003, 0.0002))  # lip line
        c = _mix(c, lipcol, lip)
        gap = _edge(np.abs(dy) - 0.0018, 0.0002) * _edge(ax[sel] - 0.021, 0.0008)
        c = _mix(c, MOUTH_INSIDE, gap)
        col[sel] = c

    # nostrils
    for sx in (1.0, -1.0):
        d = _sd_ellipsoid(p, (sx * 0.0085, -0.037, 0.095), (0.0045, 0.0035, 0.0055))
        col = _mix(col, np.array([0.30, 0.14, 0.12]), _edge(d, 0.0004))

    # eyes: almond opening with sclera, iris with radial streaks, pupil, highlight, lashes
    for ex, ey in EYE_CENTERS:
        sel = np.nonzero(front & (np.abs(x - ex) < 0.022) & (np.abs(y - ey) < 0.016))[0]
        if not len(sel):
            continue
        dx, dy = x[sel] - ex, y[sel] - ey
        u = np.clip(1.0 - (dx / EYE_HALF_WIDTH) ** 2, 0.0, 1.0)
        half = EYE_HALF_OPENING * u**0.75
        lid_up = dy - half
        opening = np.maximum(lid_up, -dy - 0.85 * half)
        r = np.hypot(dx, dy)
        ang = np.arctan2(dy, dx)
        streak = _value_noise(np.stack([ang * 9.0, r / 0.0012, np.zeros_like(r)], 1), 41 + int(ex > 0))
        iris = IRIS[None, :] * (0.6 + 0.8 * streak)[:, None]
        iris = _mix(iris, 0.35 * IRIS, _smoothstep(0.0042, 0.0056, r))  # limbal ring
        eye = np.tile(SCLERA, (len(sel), 1)) * (1.0 - 0.15 * (1.0 - u))[:, None]
        eye = _mix(eye, iris, _edge(r - 0.0056, 0.0002))
        eye = _mix(eye, PUPIL, _edge(r - 0.0023, 0.0002))
        eye = _mix(eye, WHITE, _edge(np.hypot(dx - 0.0016, dy - 0.0017) - 0.0008, 0.0002))
        c = _mix(col[sel], eye, _edge(opening, 0.00025))
        lash = _edge(np.abs(lid_up - 0.0005) - 0.0006, 0.0002) * _edge(np.abs(dx) - EYE_HALF_WIDTH - 0.0015, 0.0004)
        c = _mix(c, INK, lash)
        col[sel] = c

    # eyebrows: arched bands of short dark strokes
    for ex, ey in EYE_CENTERS:
        sel = np.nonzero(front & (np.abs(x - ex) < 0.026) & (y > ey + 0.008) & (y < ey + 0.032))[0]
        if not len(sel):
            continue
        s = (x[sel] - ex) * np.sign(ex)  # along the brow, toward the temple
        centre = ey + 0.0185 + 0.005 * (1.0 - (s / 0.02) ** 2) - 0.002 * (s > 0.01) * (s - 0.01) / 0.01
        thick = 0.0034 * (1.0 - 0.55 * _smoothstep(-0.015, 0.022, s))
        band = _edge(np.abs(y[sel] - centre) - thick, 0.0004) * _edge(np.abs(s) - 0.022, 0.002)
        strokes = _value_noise(
            np.stack([(s + 0.4 * (y[sel] - centre)) / 0.0007, (y[sel] - centre) / 0.004, np.zeros_like(s)], 1), 53
        )
        browcol = HAIR[None, :] * (0.6 + 0.7 * strokes)[:, None]
        col[sel] = _mix(col[sel], browcol, band * (0.75 + 0.25 * strokes))

    # hair: strands running down from the crown, an irregular hairline, skin on the ears
    hc = p - np.array([0.0, 0.015, -0.012])
    phi = np.arctan2(hc[:, 0], hc[:, 2])
    aphi = np.degrees(np.abs(phi))
    hairline = np.interp(
        aphi, [0, 35, 62, 80, 88, 96, 112, 140, 180], [0.074, 0.068, 0.05, 0.03, -0.012, 0.034, 0.03, -0.04, -0.072]
    )
    sel = np.nonzero(y > hairline - 0.01)[0]
    if len(sel):
        ps, phs = p[sel], phi[sel]
        theta = np.arccos(np.clip(hc[sel, 1] / np.maximum(np.linalg.norm(hc[sel], axis=1), 1e-9), -1, 1))
        jag = 0.006 * (_value_noise(np.stack([phs * 40.0, ps[:, 1] * 0.0, np.zeros(len(sel))], 1), 61) - 0.5)
        hairmask = _edge(hairline[sel] + jag - ps[:, 1], 0.0008)
        for sx in (1.0, -1.0):  # ears stay skin
            hairmask *= 1.0 - _edge(_sd_ellipsoid(ps, (sx * 0.079, 0.004, -0.010), (0.013, 0.031, 0.021)), 0.001)
        arc = phs * 0.09 * np.sin(np.clip(theta, 0.3, np.pi))  # metres across the strands
        along = theta * 0.1
        q1 = np.stack([arc / 0.0021, along / 0.018, np.zeros(len(sel))], 1)
        q2 = np.stack([arc / 0.0055, along / 0.03, np.ones(len(sel)) * 7.0], 1)
        strands = 0.55 * _value_noise(q1, 71) + 0.45 * _value_noise(q2, 73)
        shine = np.exp(-(((theta - 0.75) / 0.18) ** 2))  # a soft sheen band across the top
        haircol = HAIR[None, :] * (0.35 + 1.3 * strands)[:, None] + (0.10 * shine * strands)[:, None]
        col[sel] = _mix(col[sel], haircol, hairmask)

    # neck: a choker band with text-like marks above a striped shirt collar
    nphi = np.arctan2(x, z - NECK_AXIS_Z)
    sel = np.nonzero(y < -0.183)[0]
    if len(sel):
        ys, ph = y[sel], nphi[sel]
        c = col[sel]
        arc = ph * 0.052
        band = _edge(np.abs(ys + 0.1915) - 0.0068, 0.0002)
        c = _mix(c, WHITE, band)
        # glyphs: 3 columns x 5 rows of bits per character, a blank column between characters
        gx = np.floor(arc / 0.0011).astype(np.int64)
        gy = np.floor((ys + 0.1955) / 0.0011).astype(np.int64)
        char = np.floor_divide(gx, 4)
        colk = gx - 4 * char
        bit = _hash01(char, colk, gy, 83) < 0.55
        word_gap = _hash01(char, 0, 0, 89) < 0.18
        ink = bit & (colk < 3) & (gy >= 0) & (gy < 5) & ~word_gap & (np.abs(ph) < 2.2)
        c = _mix(c, INK, ink * band)
        shirt = _edge(ys + 0.206, 0.0003)
        stripes = np.floor(arc / 0.0042).astype(np.int64) % 2 == 0
        shirtcol = np.where(stripes[:, None], SHIRT[None, :], WHITE[None, :])
        piping = _edge(np.abs(ys + 0.2075) - 0.0012, 0.0002)
        shirtcol = _mix(shirtcol, INK, piping)
        col[sel] = _mix(c, shirtcol, shirt)

    return np.clip(col, 0.0, 1.0)


def face_detail(vertices, faces, order: int = 6, albedo_fn=None) -> np.ndarray:
    """Per-face appearance detail: the variance of the albedo over a barycentric grid.

    float32 [F]; summed over RGB. Smooth skin scores near zero; hair, eyes, lips, stubble
    and the collar score high.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    i, j = np.meshgrid(np.arange(order), np.arange(order), indexing="ij")
    keep = i + j < order
    b1 = (i[keep] + 1.0 / 3.0) / order
    b2 = (j[keep] + 1.0 / 3.0) / order
    bary = np.stack([1.0 - b1 - b2, b1, b2], 1)  # [S,3], inside every face
    tri = v[f]  # [F,3,3]
    pts = np.einsum("sk,fkd->fsd", bary, tri).reshape(-1, 3)
    col = (albedo if albedo_fn is None else albedo_fn)(pts).reshape(len(f), len(bary), 3)
    return col.var(axis=1).sum(axis=1).astype(np.float32)


TEETH = np.array([0.93, 0.90, 0.82])
TONGUE = np.array([0.62, 0.26, 0.28])
BUTTON = np.array([0.90, 0.88, 0.80])


def paper_albedo(points) -> np.ndarray:
    """The default albedo plus detail at the paper's pixel size, mostly where a FLAME-like
    template is coarse: fine hair strands with dark gaps and sheen, fine stubble, ear folds,
    a woven shirt with buttons and a seam, teeth and a tongue in the mouth."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    col = albedo(p)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    sel, hair, theta, phi = _hairline_mask(p)
    if len(sel):
        fine = _strands(p[sel], theta, phi, 0.0006, 0.012, 111)
        gaps = _smoothstep(0.25, 0.08, _strands(p[sel], theta, phi, 0.0009, 0.03, 113))
        mult = (0.55 + 0.9 * fine) * (1.0 - 0.6 * gaps)
        sheen = 0.12 * np.exp(-(((theta - 0.8) / 0.12) ** 2)) * fine
        c = col[sel] * mult[:, None] + sheen[:, None]
        col[sel] = _mix(col[sel], c, hair)
    # fine stubble between the coarse dots
    beard = (
        _smoothstep(-0.036, -0.046, y)
        * _smoothstep(-0.128, -0.112, y)
        * _smoothstep(-0.02, 0.02, z)
        * (1.0 - _smoothstep(0.055, 0.07, ax) * _smoothstep(-0.07, -0.06, y))
    )
    sel = np.nonzero(beard > 0.01)[0]
    if len(sel):
        q = p[sel] / 0.0011
        ci = np.floor(q).astype(np.int64)
        jitter = np.stack([_hash01(ci[:, 0], ci[:, 1], ci[:, 2], 131 + k) for k in range(3)], 1)
        dd = np.linalg.norm(q - ci - 0.25 - 0.5 * jitter, axis=1)
        dots = _edge(dd - 0.3, 0.08) * (_hash01(ci[:, 0], ci[:, 1], ci[:, 2], 137) < 0.6)
        col[sel] *= (1.0 - 0.45 * dots * beard[sel])[:, None]
    # ear folds: shadowed creases along the ridges of paper_displacement
    near_ear = np.nonzero((ax > 0.06) & (np.abs(y - 0.004) < 0.032) & (np.abs(z + 0.010) < 0.022))[0]
    for sx in (1.0, -1.0):
        r, w = _ear_coords(p[near_ear], sx)
        keep = np.nonzero(w > 0.01)[0]
        sel = near_ear[keep]
        r, w = r[keep], w[keep]
        if len(sel):
            rs = r
            crease = (
                np.exp(-(((rs - 0.66) / 0.035) ** 2))
                + np.exp(-(((rs - 0.93) / 0.03) ** 2))
                + 0.8 * (1.0 - _smoothstep(0.25, 0.36, rs))
            )
            col[sel] *= (1.0 - 0.45 * np.clip(crease, 0, 1) * w)[:, None]
    # shirt: a fine weave, a placket seam and buttons with four holes
    sel = np.nonzero(y < -0.205)[0]
    if len(sel):
        ps = p[sel]
        ys = ps[:, 1]
        arc = np.arctan2(ps[:, 0], ps[:, 2] - NECK_AXIS_Z) * 0.052
        shirt = _edge(ys + 0.206, 0.0003)
        weave = 0.5 + 0.5 * np.sign(np.sin(arc / 0.00045 * np.pi)) * np.sign(np.sin(ys / 0.00045 * np.pi))
        c = col[sel] * (0.8 + 0.3 * weave)[:, None]
        seam = _edge(np.abs(ps[:, 0] - 0.006) - 0.00035, 0.0001) * (ys < -0.212) * (ps[:, 2] > 0.0)
        c = _mix(c, INK, 0.8 * seam)
        bd, front = _buttons(ps)
        button = _edge(bd - 0.0036, 0.0002) * front
        holes = np.zeros(len(ps))
        for by in _BUTTON_Y:
            for hx, hy in ((-0.0009, -0.0009), (0.0009, -0.0009), (-0.0009, 0.0009), (0.0009, 0.0009)):
                holes = np.maximum(holes, _edge(np.hypot(ps[:, 0] - hx, ys - by - hy) - 0.00045, 0.0001))
        rim = _edge(np.abs(bd - 0.003) - 0.0003, 0.0001)
        bcol = _mix(_mix(np.tile(BUTTON, (len(ps), 1)), 0.6 * BUTTON, rim), INK, holes)
        c = _mix(c, bcol, button)
        col[sel] = _mix(col[sel], c, shirt)
    # mouth interior: upper and lower teeth with gaps, the tongue behind
    sel = np.nonzero((z > 0.04) & (np.abs(y - MOUTH_Y) < 0.004) & (ax < 0.025))[0]
    if len(sel):
        xs, dy = x[sel], y[sel] - MOUTH_Y
        gap = _edge(np.abs(dy) - 0.0018, 0.0002) * _edge(ax[sel] - 0.021, 0.0008)
        tooth = np.abs(((xs + 0.0021) / 0.0042) % 1.0 - 0.5) < 0.42
        teeth = _edge(np.abs(dy) - 0.0011, 0.00015) * _edge(np.abs(dy) - 0.0004, -0.00015) * tooth
        inside = _mix(np.tile(MOUTH_INSIDE, (len(sel), 1)), TONGUE, _edge(np.abs(dy) - 0.0006, 0.0002))
        inside = _mix(inside, TEETH, teeth * (ax[sel] < 0.016))
        col[sel] = _mix(col[sel], inside, gap)
    return np.clip(col, 0.0, 1.0)
