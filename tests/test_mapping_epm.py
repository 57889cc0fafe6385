"""EPM: architecture, subject-wise sampling, deterministic training, checkpoints, ONNX export vs torch."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from ofera.training.epm.export import check_onnx, export_checkpoint, export_onnx, fold_batchnorm  # noqa: E402
from ofera.training.epm.model import (  # noqa: E402
    EPM,
    EPMConfig,
    SubjectSampler,
    load_checkpoint,
    save_checkpoint,
    subject_keys,
    train_epm,
)


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _toy(n: int = 1200, seed: int = 0):
    rng = np.random.default_rng(seed)
    x = rng.random((n, 51), dtype=np.float32)
    a = rng.normal(size=(51, 68)).astype(np.float32) * 0.3
    y = np.tanh(x @ a).astype(np.float32)
    groups = np.repeat(np.arange(6), n // 6)
    return x, y, groups


def test_architecture():
    model = EPM()
    linears = [m for m in model.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(51, 128)] + [(128, 128)] * 8 + [(128, 68)]
    assert sum(isinstance(m, torch.nn.BatchNorm1d) for m in model.modules()) == 9
    assert sum(isinstance(m, torch.nn.Dropout) for m in model.modules()) == 4
    model.eval()
    assert model(torch.rand(3, 51)).shape == (3, 68)


def test_subject_sampler_is_uniform_over_subjects():
    groups = np.concatenate([np.zeros(1000, int), np.ones(10, int), np.full(100, 2)])
    sampler = SubjectSampler(groups, np.random.default_rng(0))
    drawn = groups[sampler.batch(30000)]
    share = np.bincount(drawn) / len(drawn)
    np.testing.assert_allclose(share, 1 / 3, atol=0.02)
    keys = subject_keys(np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1]))
    assert len(np.unique(keys)) == 4


def test_training_is_deterministic_and_learns():
    x, y, g = _toy()
    cfg = EPMConfig(max_epochs=4, batch_size=64, seed=3)
    a = train_epm(x[:1000], y[:1000], g[:1000], x[1000:], y[1000:], cfg, progress=False)
    b = train_epm(x[:1000], y[:1000], g[:1000], x[1000:], y[1000:], cfg, progress=False)
    assert [h["val_l1"] for h in a.history] == [h["val_l1"] for h in b.history]
    assert a.history[-1]["train_l1"] < a.history[0]["train_l1"]
    for p, q in zip(a.model.state_dict().values(), b.model.state_dict().values()):
        assert torch.equal(p, q)
    assert not a.model.training


def test_early_stopping_keeps_best_state():
    x, y, g = _toy()
    records = []
    cfg = EPMConfig(max_epochs=50, batch_size=64, patience=2, lr=0.05, steps_per_epoch=5)
    res = train_epm(x[:1000], y[:1000], g[:1000], x[1000:], y[1000:], cfg, progress=records.append)
    assert len(records) == len(res.history) <= 50
    assert res.best_val == min(h["val_l1"] for h in res.history)
    pred = res.model.predict(x[1000:])
    std = res.model.y_std.numpy()
    assert np.mean(np.abs(pred - y[1000:]) / std) == pytest.approx(res.best_val, rel=1e-4)


def test_checkpoint_roundtrip_and_onnx_matches_torch(tmp_path):
    x, y, g = _toy()
    res = train_epm(x, y, g, x[:200], y[:200], EPMConfig(max_epochs=2, batch_size=64), progress=False)
    ckpt = save_checkpoint(tmp_path / "epm.pt", res.model, res.config, res.history, {"data": "toy"})
    model, cfg, raw = load_checkpoint(ckpt)
    assert raw["meta"]["data"] == "toy" and cfg.batch_size == 64
    np.testing.assert_array_equal(model.predict(x[:10]), res.model.predict(x[:10]))

    folded = fold_batchnorm(model)
    with torch.no_grad():
        ref = model(torch.from_numpy(x[:50])).numpy()
        np.testing.assert_allclose(folded(torch.from_numpy(x[:50])).numpy(), ref, atol=1e-5)

    path, diff = export_checkpoint(ckpt, tmp_path / "epm.onnx")
    assert diff < 1e-5
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert sess.get_inputs()[0].shape[0] == "batch"  # dynamic batch axis
    for batch in (1, 7, 300):
        got = sess.run(None, {"blendshapes": x[:batch]})[0]
        np.testing.assert_allclose(got, model.predict(x[:batch]), atol=1e-5)
    meta = sess.get_modelmeta().custom_metadata_map
    assert meta["ofera_model"] == "epm" and "eyeBlinkLeft" in meta["input_names"]


def test_export_of_untrained_model_in_eval_mode(tmp_path):
    model = EPM(hidden=32, blocks=4)
    model.train()
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.running_mean.uniform_(-1, 1)
                m.running_var.uniform_(0.5, 2)
    path = export_onnx(model, tmp_path / "m.onnx")
    assert not model.training
    assert check_onnx(model, path) < 1e-5


def test_bad_inputs():
    x, y, g = _toy()
    from ofera.training.epm.model import EPMError

    with pytest.raises(EPMError, match="expected x"):
        train_epm(x[:, :50], y, g, x, y, progress=False)
    with pytest.raises(EPMError, match="empty"):
        train_epm(x, y, g, x[:0], y[:0], progress=False)
