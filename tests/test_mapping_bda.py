"""BDA: least-squares recovery, clamping, files with layout names."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.mapping.bda import BDA, BDAError, load_bda
from ofera.mapping.layouts import ARKIT51_NAMES


def _known(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    w = np.eye(51) * rng.uniform(0.6, 1.2, 51) + rng.normal(0.0, 0.05, (51, 51))
    return w, rng.normal(0.0, 0.03, 51)


def test_fit_recovers_known_w_and_b():
    rng = np.random.default_rng(0)
    w, b = _known(rng)
    x = rng.random((3000, 51))
    y = x @ w.T + b  # unclamped affine targets: least squares must recover W, b exactly
    bda = BDA.fit(x, y)
    np.testing.assert_allclose(bda.W, w, atol=1e-4)
    np.testing.assert_allclose(bda.b, b, atol=1e-4)


def test_fit_with_noise_and_ridge_is_close():
    rng = np.random.default_rng(1)
    w, b = _known(rng)
    x = rng.random((5000, 51))
    y = x @ w.T + b + rng.normal(0, 0.01, (5000, 51))
    bda = BDA.fit(x, y, ridge=1.0)
    assert np.abs(bda.W - w).max() < 0.02
    assert np.abs(bda.b - b).max() < 0.02
    assert bda.error(x, np.clip(y, 0, 1))["rmse"] < BDA.identity().error(x, np.clip(y, 0, 1))["rmse"]


def test_ridge_keeps_unobserved_shapes_identity():
    rng = np.random.default_rng(2)
    x = rng.random((500, 51))
    x[:, 7] = 0.0  # a shape that never moves
    bda = BDA.fit(x, x * 0.9, ridge=1e-3)
    assert bda.W[7, 7] == pytest.approx(1.0, abs=1e-6)


def test_apply_clamps_and_keeps_shape():
    bda = BDA(np.eye(51) * 2.0, np.full(51, -0.5))
    x = np.linspace(0, 1, 51, dtype=np.float32)
    y = bda.apply(x)
    assert y.shape == (51,) and y.dtype == np.float32
    assert y.min() == 0.0 and y.max() == 1.0
    assert bda.apply(np.tile(x, (4, 3, 1))).shape == (4, 3, 51)
    ident = BDA.identity()
    assert ident.is_identity
    np.testing.assert_array_equal(ident.apply(np.array([[-0.2] * 51, [1.5] * 51])), [[0.0] * 51, [1.0] * 51])


def test_save_load_roundtrip_and_refuses_other_names(tmp_path):
    rng = np.random.default_rng(3)
    w, b = _known(rng)
    path = BDA(w, b, device="quest-pro").save(tmp_path / "bda.npz")
    back = BDA.load(path)
    np.testing.assert_array_equal(back.W, np.float32(w))
    assert back.device == "quest-pro" and back.names == ARKIT51_NAMES
    assert load_bda(None).is_identity and load_bda("identity").is_identity

    names = list(ARKIT51_NAMES)
    names[3], names[4] = names[4], names[3]
    BDA(w, b, tuple(names)).save(tmp_path / "swapped.npz")
    with pytest.raises(BDAError, match="differ from arkit51 at 2 positions"):
        BDA.load(tmp_path / "swapped.npz")
    BDA.identity(ARKIT51_NAMES[:50]).save(tmp_path / "short.npz")
    with pytest.raises(BDAError, match="50 blendshape names"):
        BDA.load(tmp_path / "short.npz")
    np.savez(tmp_path / "other.npz", W=w)
    with pytest.raises(BDAError, match="not a BDA file"):
        BDA.load(tmp_path / "other.npz")
    with pytest.raises(BDAError, match="no such BDA file"):
        BDA.load(tmp_path / "missing.npz")


def test_bad_shapes_are_refused():
    with pytest.raises(BDAError):
        BDA(np.eye(50), np.zeros(50))
    with pytest.raises(BDAError):
        BDA.fit(np.zeros((10, 51)), np.zeros((9, 51)))


def test_cli_fit_on_paired_npz_reports_errors(tmp_path):
    from ofera.cli.main import app
    from ofera.mapping.flame_values import neutral_flame_values
    from ofera.mapping.layouts import to_arkit51
    from ofera.training.paired import PairedData
    from typer.testing import CliRunner

    rng = np.random.default_rng(4)
    t = 600
    headset = rng.random((t, 63)).astype(np.float32) * 0.5
    w, b = _known(rng)
    bs = np.clip(to_arkit51("ovr63", headset) @ w.T * 0.8 + b, 0, 1)
    data = PairedData(bs=bs, flame=neutral_flame_values(t), subject=np.repeat(np.arange(6), 100),
                      source=np.zeros(t), split=np.repeat([0, 0, 0, 0, 1, 2], 100), frame=np.tile(np.arange(100), 6),
                      headset=headset)
    data.save(tmp_path / "pairs.npz")
    res = CliRunner().invoke(app, ["bda", "fit", str(tmp_path / "pairs.npz"), "-o", str(tmp_path / "bda.npz")])
    assert res.exit_code == 0, res.output
    assert "RMSE" in res.output and "held-out 200 frames" in res.output
    bda = BDA.load(tmp_path / "bda.npz")
    held = bda.error(to_arkit51("ovr63", headset[400:]), bs[400:])
    assert held["rmse"] < 0.5 * BDA.identity().error(to_arkit51("ovr63", headset[400:]), bs[400:])["rmse"]
    res = CliRunner().invoke(app, ["bda", "fit", str(tmp_path / "nothing.npz"), "-o", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "error:" in res.output
