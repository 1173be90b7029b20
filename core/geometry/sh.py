"""Real spherical harmonics up to degree 3 for view-dependent colour (numpy or torch).

The 3DGS convention: colour = max(0.5 + C0·f_dc + Σ_k Y_k(d)·f_rest[k], 0) with d the unit
direction from the camera centre to the Gaussian, in world space, and the basis functions in
the order 3DGS (and its PLY files) use. The same code runs on numpy arrays and torch tensors:
only indexing, arithmetic and ``stack`` are used.
"""

from __future__ import annotations

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_DEGREE = 3


def num_rest(degree: int) -> int:
    """Coefficients per colour channel beyond the DC term: 0, 3, 8 or 15."""
    if not 0 <= int(degree) <= MAX_DEGREE:
        raise ValueError(f"SH degree must be 0..{MAX_DEGREE}, got {degree}")
    return (int(degree) + 1) ** 2 - 1


def degree_of(n_rest: int) -> int:
    for d in range(MAX_DEGREE + 1):
        if num_rest(d) == n_rest:
            return d
    raise ValueError(f"{n_rest} SH coefficients per channel is not a whole degree (0, 3, 8 or 15)")


def rest_basis(dirs, degree: int, stack):
    """Basis values [N, num_rest(degree)] (DC excluded) at unit directions dirs [N,3].
    ``stack`` is np.stack or torch.stack."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = []
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return stack(out, 1) if out else dirs[:, :0]


def sh_rgb(f_dc, f_rest, dirs, stack, degree: int | None = None):
    """RGB [N,3] (before clamping) from f_dc [N,3], f_rest [N,K,3] and unit dirs [N,3], using the
    first num_rest(degree) coefficients (all when degree is None)."""
    k = f_rest.shape[1] if degree is None else min(num_rest(degree), f_rest.shape[1])
    rgb = 0.5 + SH_C0 * f_dc
    if k == 0:
        return rgb
    basis = rest_basis(dirs, degree_of(k), stack)  # [N,k]
    return rgb + (basis[:, :, None] * f_rest[:, :k, :]).sum(1)
