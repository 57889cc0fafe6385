"""FLAME values: the 68-float layout and its conversion (split/join)."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.head.rotations import axis_angle_to_matrix, matrix_to_rot6d
from ofera.mapping.flame_values import (
    FLAME_VALUES,
    JAW,
    LEFT_EYE,
    RIGHT_EYE,
    join_flame_values,
    neutral_flame_values,
    split_flame_values,
)


def _rotations(rng, n):
    return axis_angle_to_matrix(rng.normal(0.0, 0.4, (n, 3)))


def test_layout_and_round_trip():
    rng = np.random.default_rng(0)
    expr = rng.normal(size=(7, 50))
    jaw, left, right = (_rotations(rng, 7) for _ in range(3))
    y = join_flame_values(expr, jaw, left, right)
    assert y.shape == (7, FLAME_VALUES) == (7, 68)
    np.testing.assert_array_equal(y[:, :50], expr)
    np.testing.assert_allclose(y[:, JAW], matrix_to_rot6d(jaw))  # pytorch3d rows convention
    np.testing.assert_allclose(y[:, LEFT_EYE], matrix_to_rot6d(left))
    np.testing.assert_allclose(y[:, RIGHT_EYE], matrix_to_rot6d(right))
    e2, rot = split_flame_values(y)
    assert rot.shape == (7, 5, 3, 3)
    np.testing.assert_allclose(e2, expr)
    np.testing.assert_allclose(rot[:, 0], np.broadcast_to(np.eye(3), (7, 3, 3)))  # root identity
    np.testing.assert_allclose(rot[:, 1], np.broadcast_to(np.eye(3), (7, 3, 3)))  # neck identity
    for k, r in ((2, jaw), (3, left), (4, right)):
        np.testing.assert_allclose(rot[:, k], r, atol=1e-12)


def test_neutral_is_identity():
    y = neutral_flame_values(3)
    expr, rot = split_flame_values(y)
    assert y.dtype == np.float32 and expr.dtype == np.float32 and rot.dtype == np.float32
    np.testing.assert_array_equal(expr, 0)
    np.testing.assert_allclose(rot, np.broadcast_to(np.eye(3), (3, 5, 3, 3)))


def test_split_orthonormalises_raw_network_output():
    rng = np.random.default_rng(1)
    y = neutral_flame_values(5, dtype=np.float64) + rng.normal(0, 0.1, (5, 68))
    _, rot = split_flame_values(y)
    eye = np.broadcast_to(np.eye(3), (5, 5, 3, 3))
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


def test_shorter_expression_is_padded_and_errors_are_clear():
    r = np.eye(3)
    y = join_flame_values(np.ones(10), r, r, r)
    assert y.shape == (68,) and y[:10].sum() == 10 and y[10:50].sum() == 0
    with pytest.raises(ValueError, match="68"):
        split_flame_values(np.zeros((2, 67)))
    with pytest.raises(ValueError, match="truncate"):
        join_flame_values(np.zeros(100), r, r, r)
    with pytest.raises(ValueError, match="jaw"):
        join_flame_values(np.zeros(50), np.zeros(6), r, r)
