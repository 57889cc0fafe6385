"""Coordinate conventions. `flame`: right-handed, y up, face looks +z, metres (the server's space).
`unity`: Unity's left-handed space, reached from FLAME by mirroring x.

Mirroring x maps position (x, y, z) -> (-x, y, z), quaternion (x, y, z, w) -> (x, -y, -z, w)
(the rotation M R M with M = diag(-1, 1, 1)), leaves scale unchanged, and negates the spherical
harmonics coefficients whose basis function is odd in x (3DGS order: 3, 4, 7, 10, 13, 15).
The map is its own inverse.
"""

from __future__ import annotations

import numpy as np

from .constants import COORDS

SH_ODD_IN_X: tuple[int, ...] = (3, 4, 7, 10, 13, 15)
"""Indices (3DGS / graphdeco order) of real SH basis functions that change sign when x is mirrored."""

_POS_SIGN = np.array([-1.0, 1.0, 1.0], dtype=np.float32)
_ROT_SIGN = np.array([1.0, -1.0, -1.0, 1.0], dtype=np.float32)


def mirror_x_position(position: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3): (x, y, z) -> (-x, y, z). Returns a new float32 array."""
    return np.asarray(position, dtype=np.float32) * _POS_SIGN


def mirror_x_rotation(rotation: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w) -> (x, -y, -z, w). Returns a new float32 array."""
    return np.asarray(rotation, dtype=np.float32) * _ROT_SIGN


def mirror_x_sh(sh: np.ndarray) -> np.ndarray:
    """(N, K, 3) SH coefficients -> the same with x-odd basis functions negated (new float32 array)."""
    out = np.array(sh, dtype=np.float32, copy=True)
    odd = [k for k in SH_ODD_IN_X if k < out.shape[1]]
    out[:, odd, :] *= -1.0
    return out


def to_coords(position: np.ndarray, rotation: np.ndarray, coords: str) -> tuple[np.ndarray, np.ndarray]:
    """FLAME-space (N, 3) positions and (N, 4) quaternions expressed in `coords` ('flame': unchanged)."""
    if coords == "flame":
        return position, rotation
    if coords == "unity":
        return mirror_x_position(position), mirror_x_rotation(rotation)
    raise ValueError(f"unknown coords {coords!r}; expected one of {COORDS}")
