"""The synthetic head's rig (jaw, blink, smile/pucker, head rotation and translation) and the ten
sequences it drives, the last of which mixes expressions no training sequence shows.
Reporting tier (numpy).
"""

from __future__ import annotations

import numpy as np

from .fields import _rotation_xyz, _smoothstep
from .surface import EYE_CENTERS, EYE_HALF_OPENING, EYE_HALF_WIDTH, MOUTH_HALF_WIDTH, MOUTH_Y

JAW_PIVOT = np.array([0.0, -0.025, -0.02])
NECK_PIVOT = np.array([0.0, -0.12, -0.012])


RIG_KEYS = ("jaw", "blink", "smile", "rotation", "translation")


def neutral_params() -> dict:
    return {"jaw": 0.0, "blink": 0.0, "smile": 0.0, "rotation": (0.0, 0.0, 0.0), "translation": (0.0, 0.0, 0.0)}


def pose_head(template_vertices, params) -> np.ndarray:
    """The rig: canonical vertices [V,3] + params -> posed vertices float32 [V,3].

    params (missing keys = neutral):
      jaw          0..1, opens the mouth (lower face rotates up to 12 degrees about the jaw axis)
      blink        0..1 (or a pair (left, right)), upper lids close over the eyes
      smile        -1..1, mouth corners out and up (> 0) or pucker in and forward (< 0)
      rotation     (yaw, pitch, roll) degrees; pitch > 0 looks down; the neck blends to
                   the unrotated collar
      translation  (3,) metres, moves everything
    All weights are smooth functions of the canonical position, so nearby vertices move
    alike (no tearing) whatever the tessellation.
    """
    P = np.asarray(template_vertices, np.float64)
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    out = P.copy()
    jaw = float(params.get("jaw", 0.0))
    blink = params.get("blink", 0.0)
    blink = (float(blink), float(blink)) if np.ndim(blink) == 0 else tuple(float(b) for b in blink)
    smile = float(params.get("smile", 0.0))
    yaw, pitch, roll = (np.radians(float(a)) for a in params.get("rotation", (0.0, 0.0, 0.0)))
    translation = np.asarray(params.get("translation", (0.0, 0.0, 0.0)), np.float64).reshape(3)

    front = _smoothstep(0.0, 0.05, z)
    ax = np.abs(x)

    # Smile / pucker act on the mouth region before the jaw, so the lips follow the jaw.
    if smile > 0:
        for sx in (1.0, -1.0):
            g = np.exp(-((x - sx * MOUTH_HALF_WIDTH) ** 2 + (y - MOUTH_Y) ** 2) / (2 * 0.013**2)) * front
            out[:, 0] += sx * 0.0065 * smile * g
            out[:, 1] += 0.0055 * smile * g
            out[:, 2] -= 0.002 * smile * g
            cheek = np.exp(-((x - sx * 0.042) ** 2 + (y + 0.03) ** 2) / (2 * 0.016**2)) * front
            out[:, 1] += 0.003 * smile * cheek
            out[:, 2] += 0.003 * smile * cheek
    elif smile < 0:
        pucker = -smile
        g = np.exp(-(x**2 / (2 * 0.022**2) + (y - MOUTH_Y) ** 2 / (2 * 0.013**2))) * front
        out[:, 0] -= 0.32 * pucker * x * g
        out[:, 2] += 0.008 * pucker * g

    # Blink: skin between the lower lid and the brow slides down, squeezing the eye
    # opening toward the lower lid (the texture is glued to the surface, so the iris
    # vanishes into a thin line, as under a closing lid).
    for (ex, ey), amount in zip(EYE_CENTERS, blink):
        if amount == 0.0:
            continue
        v = y - ey
        low, up = -EYE_HALF_OPENING, EYE_HALF_OPENING + 0.0008
        # smooth in v (no kinks a coarse triangle could not follow), ~0 at the lower lid,
        # full at the upper lid, back to 0 below the brow
        shift = (
            0.92
            * amount
            * (up - low)
            * _smoothstep(low - 0.002, up, v)
            * (1.0 - _smoothstep(up + 0.001, up + 0.009, v))
        )
        window = 1.0 - _smoothstep(0.9, 1.45, np.abs(x - ex) / EYE_HALF_WIDTH)
        out[:, 1] -= shift * window * _smoothstep(0.04, 0.065, z)

    # Jaw: the lower face rotates about a left-right axis. The weight is a sharp step at
    # the lip contact line between the mouth corners (the lips part there) and a soft one
    # over the cheeks; it fades toward the back and down the throat.
    if jaw != 0.0:
        width = 0.0016 + 0.014 * _smoothstep(MOUTH_HALF_WIDTH - 0.006, MOUTH_HALF_WIDTH + 0.018, ax)
        below = 1.0 / (1.0 + np.exp(-(MOUTH_Y - y) / width))
        w = below * _smoothstep(-0.05, 0.03, z) * _smoothstep(-0.175, -0.115, y)
        angle = np.radians(12.0) * jaw
        c, s = np.cos(angle), np.sin(angle)
        R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        rel = out - JAW_PIVOT
        out = out + w[:, None] * (rel @ R.T + JAW_PIVOT - out)

    # Head rotation about the neck, blended to zero at the collar.
    if yaw or pitch or roll:
        R = _rotation_xyz(yaw, pitch, roll)
        w = _smoothstep(-0.205, -0.11, y)
        rel = out - NECK_PIVOT
        out = out + w[:, None] * (rel @ R.T + NECK_PIVOT - out)

    out = out + translation
    return out.astype(np.float32)


# Expression mixes of the training sequences. Each entry: parameter -> (amplitude, cycles
# over the sequence). One-sided parameters (jaw, blink) swing 0..amplitude, signed ones
# -amplitude..amplitude. The novel mix of the test sequence combines motions no single
# training sequence combines, with its own amplitudes.
_TRAIN_MIXES = (
    {"jaw": (1.0, 1), "pitch": (6.0, 1)},
    {"smile": (1.0, 1), "blink": (1.0, 2)},
    {"smile": (-1.0, 1), "yaw": (24.0, 1)},
    {"blink": (1.0, 1), "pitch": (15.0, 1), "ty": (0.01, 1)},
    {"jaw": (0.7, 2), "smile": (0.8, 1), "roll": (10.0, 1)},
    {"yaw": (25.0, 1), "tx": (0.02, 1), "blink": (0.6, 2)},
    {"smile": (-0.9, 2), "jaw": (0.4, 1), "pitch": (-10.0, 1)},
    {"blink": (1.0, 3), "smile": (0.6, 1), "tz": (0.02, 1), "yaw": (-12.0, 1)},
    {"jaw": (0.5, 1), "smile": (0.5, 2), "yaw": (10.0, 1), "pitch": (6.0, 2), "roll": (-6.0, 1)},
)
_TEST_MIX = {
    "jaw": (0.85, 1),
    "smile": (-0.8, 1),
    "blink": (0.9, 2),
    "yaw": (-20.0, 1),
    "roll": (12.0, 1),
    "pitch": (-8.0, 2),
    "tx": (-0.015, 1),
    "ty": (0.01, 1),
}
_ONE_SIDED = ("jaw", "blink")
_MIX_NAMES = (
    "jaw",
    "smile-blink",
    "pucker-yaw",
    "blink-nod",
    "talk-roll",
    "turn",
    "pucker-talk",
    "blink-smile-dolly",
    "mixed",
)


def sequence_params(sequence: int, frame: int, frames: int, sequences: int = 10, seed: int = 0) -> dict:
    """Rig parameters of one frame; the last sequence is the novel-expression test mix."""
    is_test = sequence == sequences - 1
    mix = _TEST_MIX if is_test else _TRAIN_MIXES[sequence % len(_TRAIN_MIXES)]
    rng = np.random.default_rng([int(seed), int(sequence)])
    t = frame / max(frames, 1)
    vals = {}
    for key in sorted(mix):
        amp, cycles = mix[key]
        phase = rng.uniform(0, 2 * np.pi)
        if key in _ONE_SIDED:
            vals[key] = amp * (0.5 - 0.5 * np.cos(2 * np.pi * cycles * t + phase))
        else:
            vals[key] = amp * np.sin(2 * np.pi * cycles * t + phase)
    p = neutral_params()
    p["jaw"] = float(np.clip(vals.get("jaw", 0.0), 0.0, 1.0))
    p["blink"] = float(np.clip(vals.get("blink", 0.0), 0.0, 1.0))
    p["smile"] = float(np.clip(vals.get("smile", 0.0), -1.0, 1.0))
    p["rotation"] = (float(vals.get("yaw", 0.0)), float(vals.get("pitch", 0.0)), float(vals.get("roll", 0.0)))
    p["translation"] = (float(vals.get("tx", 0.0)), float(vals.get("ty", 0.0)), float(vals.get("tz", 0.0)))
    return p


def sequence_name(sequence: int, sequences: int = 10) -> str:
    if sequence == sequences - 1:
        return f"EXP-{sequence}-novel"
    return f"EXP-{sequence}-{_MIX_NAMES[sequence % len(_MIX_NAMES)]}"
