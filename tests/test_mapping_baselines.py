"""Baselines: fixed matrix mapping (EMAGE layout), correspondence matrix, ridge with alpha on validation."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.head.rotations import axis_angle_to_matrix, matrix_to_rot6d
from ofera.mapping.baselines import (
    BaselineError,
    MatrixMapper,
    RidgeMapper,
    correspondence_matrix,
    emage_from_flame_values,
    flame_values_from_emage,
    param_rmse,
)
from ofera.mapping.flame_values import neutral_flame_values


def test_matrix_mapper_shapes_and_layout(tmp_path):
    rng = np.random.default_rng(0)
    m = rng.normal(0, 0.1, (51, 103))
    mapper = MatrixMapper(m)
    x = rng.random((7, 51))
    y = mapper.predict(x)
    assert y.shape == (7, 68) and y.dtype == np.float32
    v = x @ m
    np.testing.assert_allclose(y[:, :50], v[:, :50], atol=1e-5)
    np.testing.assert_allclose(y[:, 50:56], matrix_to_rot6d(axis_angle_to_matrix(v[:, 100:103])), atol=1e-5)
    np.testing.assert_allclose(y[:, 56:], np.tile([1, 0, 0, 0, 1, 0], (7, 2)), atol=0)
    np.testing.assert_allclose(MatrixMapper(m.T).predict(x), y)  # (103, 51) is accepted too
    for name in ("m.npy", "m.npz"):
        np.testing.assert_allclose(MatrixMapper.load(mapper.save(tmp_path / name)).predict(x), y)
    np.savetxt(tmp_path / "m.csv", m, delimiter=",")
    np.testing.assert_allclose(MatrixMapper.load(tmp_path / "m.csv").predict(x), y, atol=1e-5)
    with pytest.raises(BaselineError, match="51, 103"):
        MatrixMapper(np.zeros((51, 68)))


def test_emage_roundtrip():
    rng = np.random.default_rng(1)
    aa = rng.normal(0, 0.2, (5, 3))
    v = np.concatenate([rng.normal(size=(5, 50)), np.zeros((5, 50)), aa], axis=1)
    np.testing.assert_allclose(emage_from_flame_values(flame_values_from_emage(v)), v, atol=1e-6)


def test_correspondence_matrix_adds_displacements():
    rng = np.random.default_rng(2)
    per_shape = neutral_flame_values(51, dtype=np.float64)
    per_shape[:, :50] = rng.normal(size=(51, 50))
    per_shape[17, 50:56] = matrix_to_rot6d(axis_angle_to_matrix(np.array([0.3, 0, 0])))  # jawOpen
    mapper = correspondence_matrix(per_shape)
    assert mapper.matrix.shape == (51, 103)
    onehot = np.eye(51)
    np.testing.assert_allclose(mapper.predict(onehot), per_shape, atol=1e-5)
    np.testing.assert_allclose(mapper.predict(np.zeros((1, 51))), neutral_flame_values(1), atol=1e-6)


def test_ridge_recovers_linear_map_and_picks_alpha():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(51, 68))
    c = rng.normal(size=68)
    x, xv = rng.random((2000, 51)), rng.random((500, 51))
    y, yv = x @ a + c + rng.normal(0, 0.01, (2000, 68)), xv @ a + c
    ridge = RidgeMapper.fit(x, y, xv, yv)
    assert ridge.A.shape == (51, 68) and ridge.c.shape == (68,)
    assert param_rmse(ridge.predict(xv), yv) < 0.01
    assert ridge.alpha == min(ridge.scores, key=lambda s: s[1])[0]
    # Heavy noise on few frames: a larger alpha wins on validation.
    y_noisy = x[:60] @ a + c + rng.normal(0, 3.0, (60, 68))
    noisy = RidgeMapper.fit(x[:60], y_noisy, xv, yv)
    assert noisy.alpha > ridge.alpha


def test_param_rmse_excludes_eyes():
    y = neutral_flame_values(4)
    p = y.copy()
    p[:, 56:] += 1.0  # eyes only
    assert param_rmse(p, y) == 0.0
    p[:, 0] += 56 ** 0.5
    assert param_rmse(p, y) == pytest.approx(1.0)
