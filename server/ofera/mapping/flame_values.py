"""FLAME values: the EPM's 68-float output, and the one way every part converts it.

Layout (``FLAME_VALUES = 68``)::

    [ expr (50) | jaw 6D (6) | left-eye 6D (6) | right-eye 6D (6) ]

6D rotations follow the pytorch3d rows convention (``ofera.head.rotations``: the first two ROWS of the
matrix; identity = ``[1,0,0, 0,1,0]``). Root and neck are not part of the values: the client owns head
pose, so :func:`split_flame_values` returns them as identity.
"""

from __future__ import annotations

import numpy as np

from ofera.head.rotations import matrix_to_rot6d, rot6d_to_matrix

N_EXPR = 50
FLAME_VALUES = N_EXPR + 18
EXPR = slice(0, N_EXPR)
JAW = slice(N_EXPR, N_EXPR + 6)
LEFT_EYE = slice(N_EXPR + 6, N_EXPR + 12)
RIGHT_EYE = slice(N_EXPR + 12, N_EXPR + 18)
IDENTITY_6D = np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], dtype=np.float32)


def _check(y: np.ndarray) -> np.ndarray:
    y = np.asarray(y)
    if y.shape[-1:] != (FLAME_VALUES,):
        raise ValueError(f"FLAME values must have {FLAME_VALUES} values on the last axis, got shape {y.shape}")
    return y


def split_flame_values(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 68) -> expr (..., 50) and rotations (..., 5, 3, 3) in joint order (root, neck, jaw, eyes).

    Root and neck are identity. Rotations are re-orthonormalised from the 6D values (Gram-Schmidt), so
    a network's raw output is always a valid rotation. Float dtype follows the input (float32 stays).
    """
    y = _check(y)
    dtype = np.result_type(y.dtype, np.float32)
    y = y.astype(dtype, copy=False)
    eye = np.broadcast_to(np.eye(3, dtype=dtype), (*y.shape[:-1], 3, 3))
    rotations = np.stack(
        [eye, eye, rot6d_to_matrix(y[..., JAW]), rot6d_to_matrix(y[..., LEFT_EYE]), rot6d_to_matrix(y[..., RIGHT_EYE])],
        axis=-3,
    )
    return y[..., EXPR].copy(), rotations.astype(dtype, copy=False)


def join_flame_values(expr: np.ndarray, jaw: np.ndarray, left_eye: np.ndarray, right_eye: np.ndarray) -> np.ndarray:
    """expr (..., n <= 50; zero-padded to 50) and rotation matrices (..., 3, 3) -> (..., 68).

    Float dtype follows the inputs (at least float32).
    """
    expr = np.asarray(expr)
    if expr.shape[-1] > N_EXPR:
        raise ValueError(f"{expr.shape[-1]} expression values; FLAME values hold {N_EXPR} (truncate first)")
    mats = [np.asarray(r) for r in (jaw, left_eye, right_eye)]
    for name, r in zip(("jaw", "left_eye", "right_eye"), mats):
        if r.shape[-2:] != (3, 3):
            raise ValueError(f"{name} must be rotation matrices (..., 3, 3), got shape {r.shape}")
    dtype = np.result_type(expr.dtype, *(m.dtype for m in mats), np.float32)
    lead = np.broadcast_shapes(expr.shape[:-1], *(m.shape[:-2] for m in mats))
    out = np.zeros((*lead, FLAME_VALUES), dtype=dtype)
    out[..., : expr.shape[-1]] = expr
    out[..., JAW] = matrix_to_rot6d(np.broadcast_to(mats[0], (*lead, 3, 3)))
    out[..., LEFT_EYE] = matrix_to_rot6d(np.broadcast_to(mats[1], (*lead, 3, 3)))
    out[..., RIGHT_EYE] = matrix_to_rot6d(np.broadcast_to(mats[2], (*lead, 3, 3)))
    return out


def neutral_flame_values(*lead: int, dtype: np.dtype | type = np.float32) -> np.ndarray:
    """Neutral FLAME values (zero expression, identity rotations) of shape (*lead, 68)."""
    out = np.zeros((*lead, FLAME_VALUES), dtype=dtype)
    for sl in (JAW, LEFT_EYE, RIGHT_EYE):
        out[..., sl] = IDENTITY_6D
    return out
