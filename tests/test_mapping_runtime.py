"""Run-time Mapper: ONNX Runtime without torch, batch 1 and batched, BDA folded in."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from ofera.mapping.bda import BDA
from ofera.mapping.runtime import Mapper, MapperError


@pytest.fixture(scope="module")
def epm_onnx(tmp_path_factory):
    """A small exported EPM (torch), or the shipped default when torch is not installed."""
    try:
        import torch
        from ofera.training.epm.export import export_onnx
        from ofera.training.epm.model import EPM
    except ImportError:
        from ofera.assets import default_epm_path

        return default_epm_path(), None
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = EPM(hidden=64)
    path = export_onnx(model, tmp_path_factory.mktemp("epm") / "epm.onnx")
    return path, model


def _bda(seed: int = 0) -> BDA:
    rng = np.random.default_rng(seed)
    return BDA(np.eye(51) + rng.normal(0, 0.05, (51, 51)), rng.normal(0, 0.02, 51))


def test_map_and_map_batch_agree_with_torch(epm_onnx):
    path, model = epm_onnx
    rng = np.random.default_rng(1)
    x = rng.random((40, 51), dtype=np.float32)
    bda = _bda()
    mapper = Mapper.load(path, bda)
    batch = mapper.map_batch(x)
    assert batch.shape == (40, 68) and batch.dtype == np.float32
    for i in (0, 17, 39):
        one = mapper.map(x[i])
        assert one.shape == (68,) and one.dtype == np.float32
        np.testing.assert_allclose(one, batch[i], atol=1e-5)
    out = np.empty(68, np.float32)
    assert mapper.map(x[3], out=out) is out
    first = mapper.map(x[0])
    mapper.map(x[1])
    np.testing.assert_allclose(first, batch[0], atol=1e-5)  # results are not overwritten by the next call
    if model is not None:
        np.testing.assert_allclose(batch, model.predict(bda.apply(x)), atol=1e-5)
    ident = Mapper.load(path)
    np.testing.assert_allclose(ident.map_batch(x), ident.epm_only(x), atol=1e-6)  # x already in [0, 1]
    np.testing.assert_allclose(ident.map_batch(x * 3 - 1), ident.epm_only(np.clip(x * 3 - 1, 0, 1)), atol=1e-6)
    assert mapper.map_batch(x[:0]).shape == (0, 68)


def test_mapper_refuses_bad_input(epm_onnx, tmp_path):
    mapper = Mapper.load(epm_onnx[0])
    with pytest.raises(ValueError, match=r"\(51,\)"):
        mapper.map(np.zeros(52, np.float32))
    with pytest.raises(ValueError, match=r"\(B, 51\)"):
        mapper.map_batch(np.zeros((2, 50), np.float32))
    with pytest.raises(MapperError, match="no such EPM"):
        Mapper.load(tmp_path / "missing.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(MapperError, match="cannot load"):
        Mapper.load(tmp_path / "junk.onnx")


def test_single_threaded_session(epm_onnx):
    mapper = Mapper.load(epm_onnx[0])
    opts = mapper.session.get_session_options()
    assert opts.intra_op_num_threads == 1


def test_runtime_runs_without_torch(epm_onnx, tmp_path):
    path, _ = epm_onnx
    bda_path = _bda(2).save(tmp_path / "bda.npz")
    x = np.random.default_rng(3).random((5, 51), dtype=np.float32)
    expected = Mapper.load(path, bda_path).map_batch(x)
    np.save(tmp_path / "x.npy", x)
    code = textwrap.dedent(f"""
        import sys, json
        sys.modules["torch"] = None  # any `import torch` now raises ImportError
        import numpy as np
        from ofera.mapping.runtime import Mapper
        m = Mapper.load({str(path)!r}, {str(bda_path)!r})
        x = np.load({str(tmp_path / "x.npy")!r})
        y = m.map_batch(x)
        one = m.map(x[0])
        print(json.dumps({{"y": y.tolist(), "one": one.tolist(),
                          "torch": [k for k in sys.modules if k.startswith("torch") and sys.modules[k]]}}))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["torch"] == []
    np.testing.assert_allclose(np.array(got["y"]), expected, atol=1e-6)
    np.testing.assert_allclose(np.array(got["one"]), expected[0], atol=1e-5)
