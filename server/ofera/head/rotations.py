"""Rotation conversions (numpy). Batched over leading axes.

Conventions:
- matrices act on column vectors: ``v' = R @ v``;
- quaternions are Hamilton, stored (w, x, y, z) inside the code (the wire uses x, y, z, w);
- 6D rotations follow pytorch3d (used by metrical-tracker and INSTA): the 6 numbers are the first two
  ROWS of R, so ``rot6d_to_matrix(matrix_to_rot6d(R)) == R`` and the identity is ``[1,0,0, 0,1,0]``.
  (Zhou et al.'s original code uses columns: its 6D of R is pytorch3d's 6D of R^T.)
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), _EPS)


def rot6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt; the rows of R are b1, b2, b3."""
    d6 = np.asarray(d6, dtype=np.result_type(d6, np.float32))
    a1, a2 = d6[..., 0:3], d6[..., 3:6]
    b1 = _normalize(a1)
    b2 = _normalize(a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1)
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-2)


def matrix_to_rot6d(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): the first two rows, flattened."""
    return r[..., :2, :].reshape(*r.shape[:-2], 6)


def axis_angle_to_matrix(aa: np.ndarray) -> np.ndarray:
    """(..., 3) axis * angle (radians) -> (..., 3, 3) by Rodrigues' formula."""
    aa = np.asarray(aa, dtype=np.float64)
    theta = np.linalg.norm(aa, axis=-1)[..., None, None]  # (..., 1, 1)
    k = aa / np.maximum(np.linalg.norm(aa, axis=-1, keepdims=True), _EPS)
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(kx)
    kmat = np.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], axis=-1).reshape(*aa.shape[:-1], 3, 3)
    eye = np.broadcast_to(np.eye(3), kmat.shape)
    return eye + np.sin(theta) * kmat + (1.0 - np.cos(theta)) * (kmat @ kmat)


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation -> (..., 4) unit quaternion (w, x, y, z) with w >= 0.

    Picks, per matrix, the best-conditioned of the four branches (largest of w, x, y, z), so it is
    accurate for every rotation including 180-degree turns.
    """
    r = np.asarray(r, dtype=np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    # 4 * q_i^2 for i = w, x, y, z
    sq = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1
    )
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s21, s02, s10 = r[..., 2, 1] + r[..., 1, 2], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 0] + r[..., 0, 1]
    # Each row: 4 * q_i * (w, x, y, z) for the branch i.
    cand = np.stack(
        [
            np.stack([sq[..., 0], d21, d02, d10], axis=-1),
            np.stack([d21, sq[..., 1], s10, s02], axis=-1),
            np.stack([d02, s10, sq[..., 2], s21], axis=-1),
            np.stack([d10, s02, s21, sq[..., 3]], axis=-1),
        ],
        axis=-2,
    )  # (..., 4, 4)
    best = np.argmax(sq, axis=-1)
    q = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternion (w, x, y, z), any norm -> (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _EPS)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def matrix_to_axis_angle(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3) axis * angle, angle in [0, pi]; via the quaternion (stable near 0 and pi)."""
    q = matrix_to_quaternion(r)
    vec = q[..., 1:]
    sin_half = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., :1])
    # angle / sin(angle/2) -> 2 as angle -> 0
    scale = np.where(sin_half > 1e-8, angle / np.maximum(sin_half, _EPS), 2.0)
    return vec * scale


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a (x) b of (..., 4) quaternions (w, x, y, z); rotation b first, then a."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """(..., 4) (w, x, y, z) -> (x, y, z, w), the wire order."""
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def euler_xy_to_matrix(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Eye-style rotation: yaw about +y then pitch about +x (radians) -> (..., 3, 3) = R_y(yaw) @ R_x(pitch)."""
    yaw, pitch = np.broadcast_arrays(np.asarray(yaw, np.float64), np.asarray(pitch, np.float64))
    ry = axis_angle_to_matrix(np.stack([np.zeros_like(yaw), yaw, np.zeros_like(yaw)], axis=-1))
    rx = axis_angle_to_matrix(np.stack([pitch, np.zeros_like(pitch), np.zeros_like(pitch)], axis=-1))
    return ry @ rx
