"""Real spherical harmonics as 3DGS uses them (degrees 0..3), colour <-> DC conversions.

Coefficients are stored (N, (d+1)^2, 3): index 0 is DC, then degree 1 (3), degree 2 (5), degree 3 (7),
each row an RGB triple. ``colour = sum_k sh[:, k] * Y_k(dir) + 0.5``, clamped at 0, with ``dir`` the unit
vector from the camera centre to the Gaussian (3DGS's convention).
"""

from __future__ import annotations

import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_count(degree: int) -> int:
    """Coefficients per channel for ``degree``: 1, 4, 9 or 16."""
    return (degree + 1) ** 2


def sh_degree(count: int) -> int:
    """Inverse of :func:`sh_count`; raises ValueError for counts that are not a square of 1..4."""
    d = int(round(np.sqrt(count))) - 1
    if d < 0 or d > 3 or (d + 1) ** 2 != count:
        raise ValueError(f"{count} SH coefficients per channel: expected 1, 4, 9 or 16")
    return d


def rgb_to_dc(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) colour in 0..1 -> DC coefficient."""
    return (np.asarray(rgb) - 0.5) / C0


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """Basis values (N, (degree+1)^2) for unit directions (N, 3)."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [np.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return np.stack(out, axis=-1)


def eval_sh(sh: np.ndarray, dirs: np.ndarray, degree: int | None = None) -> np.ndarray:
    """RGB (N, 3) >= 0 of coefficients (N, K, 3) seen along unit directions (N, 3), up to ``degree``."""
    d = sh_degree(sh.shape[1]) if degree is None else min(degree, sh_degree(sh.shape[1]))
    basis = sh_basis(dirs, d)  # (N, K')
    return np.maximum(np.einsum("nk,nkc->nc", basis, sh[:, : basis.shape[1]]) + 0.5, 0.0)
