"""FLAME pickles (safe, chumpy-free), the project's .npz, and the `ofera head` CLI."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import types

import numpy as np
import pytest
import scipy.sparse as sp
from ofera.head import HeadModelError, load_head
from ofera.head.flame_pickle import UnsafePickleError


def _chumpy_class():
    """A class pickled as `chumpy.ch.Ch`, the way FLAME 2020 stores some arrays."""
    mod = types.ModuleType("chumpy.ch")

    class Ch:
        pass

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    mod.Ch = Ch
    return mod, Ch


def write_flame_pickle(path, n_expr=100, rng=None):
    """FLAME's key set and shapes, chumpy objects under `chumpy.ch`, old numpy/scipy names, protocol 2."""
    rng = rng or np.random.default_rng(0)
    v, f = 5023, 9976
    mod, ch = _chumpy_class()
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = types.ModuleType("chumpy"), mod
    try:
        def chumpy(arr):
            obj = ch()
            obj.__dict__.update({"x": arr, "_dirty_vars": set()})
            return obj

        jreg = np.zeros((5, v))
        for k in range(5):
            jreg[k, rng.choice(v, 8, replace=False)] = 1 / 8
        weights = rng.random((v, 5))
        data = {
            "v_template": chumpy(rng.normal(size=(v, 3)) * 0.05),
            "f": rng.integers(0, v, size=(f, 3)).astype(np.uint32),
            "shapedirs": chumpy((rng.normal(size=(v, 3, 300 + n_expr)) * 1e-3).astype(np.float32)),
            "posedirs": rng.normal(size=(v, 3, 36)) * 1e-3,
            "J_regressor": sp.csc_matrix(jreg),
            "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
            "weights": chumpy(weights / weights.sum(1, keepdims=True)),
            "bs_style": "lbs",
            "bs_type": "lrotmin",
        }
        raw = pickle.dumps(data, protocol=2)
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]
    renames = ((b"numpy._core.multiarray", b"numpy.core.multiarray"), (b"scipy.sparse._csc", b"scipy.sparse.csc"))
    for new, old in renames:
        raw = raw.replace(new, old)
    assert b"chumpy.ch" in raw and b"numpy.core.multiarray" in raw and b"scipy.sparse.csc" in raw
    path.write_bytes(raw)
    return data


@pytest.fixture(scope="module")
def flame_pkl(tmp_path_factory):
    path = tmp_path_factory.mktemp("flame") / "generic_model.pkl"
    write_flame_pickle(path)
    return path


def test_flame_pickle_loads_without_chumpy(flame_pkl):
    assert "chumpy" not in sys.modules
    model = load_head(flame_pkl)
    assert (model.num_vertices, model.num_faces, model.shape_dims, model.expr_dims) == (5023, 9976, 300, 100)
    assert model.parents.tolist() == [-1, 0, 1, 1, 1]
    assert model.posedirs.shape == (36, 3 * 5023)
    np.testing.assert_allclose(model.j_regressor.sum(1), 1.0)


def test_posedirs_reshape_matches_flame(flame_pkl):
    from ofera.head.flame_pickle import read_flame_pickle

    raw = read_flame_pickle(flame_pkl)
    model = load_head(flame_pkl)
    feat = np.random.default_rng(3).normal(size=36)
    ref = np.einsum("vcp,p->vc", raw["posedirs"], feat)  # FLAME: posedirs (V, 3, 36) . feat
    np.testing.assert_allclose((feat @ model.posedirs).reshape(-1, 3), ref, atol=1e-12)


class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_pickle_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "pwned"
    bad = tmp_path / "evil.pkl"
    bad.write_bytes(pickle.dumps({"v_template": _Evil(marker)}, protocol=2))
    with pytest.raises(UnsafePickleError, match="refused"):
        load_head(bad)
    assert not marker.exists()
    res = subprocess.run([sys.executable, "-m", "ofera.cli.main", "head", "info", str(bad), "--json"],
                         capture_output=True, text=True)
    assert res.returncode != 0 and "refused" in res.stderr and "Traceback" not in res.stderr
    assert not marker.exists()


def test_garbage_and_wrong_files_give_clear_errors(tmp_path):
    junk = tmp_path / "junk.pkl"
    junk.write_bytes(b"\x80\x02not a pickle at all")
    with pytest.raises(HeadModelError, match="junk.pkl"):
        load_head(junk)
    with pytest.raises(HeadModelError, match="unknown head format"):
        (tmp_path / "x.obj").write_text("v 0 0 0")
        load_head(tmp_path / "x.obj")
    notflame = tmp_path / "dict.pkl"
    notflame.write_bytes(pickle.dumps({"a": np.zeros(3)}, protocol=2))
    with pytest.raises(HeadModelError, match="missing keys"):
        load_head(notflame)


def test_npz_round_trip(head, tmp_path):
    path = tmp_path / "head.npz"
    head.save(path)
    back = load_head(path)
    for key in ("v_template", "exprdirs", "shapedirs", "posedirs", "weights", "j_regressor"):
        np.testing.assert_allclose(getattr(back, key), getattr(head, key), atol=1e-6)
    np.testing.assert_array_equal(back.faces, head.faces)
    assert back.vertex_labels.keys() == head.vertex_labels.keys()
    np.testing.assert_allclose(back.landmarks["nose_tip"], head.landmarks["nose_tip"], atol=1e-7)


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "ofera.cli.main", *args], capture_output=True, text=True)


def test_cli_info_default_and_flame(flame_pkl):
    res = run_cli("head", "info", "default", "--json")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert info["joints"] == 5 and info["expr_dims"] >= 50
    assert {"vertices", "faces", "shape_dims", "expr_dims", "joints"} <= info.keys()
    flame = json.loads(run_cli("head", "info", str(flame_pkl), "--json").stdout)
    assert (flame["vertices"], flame["faces"]) == (5023, 9976)


def test_cli_render_and_errors(tmp_path):
    out = tmp_path / "h.png"
    res = run_cli("head", "render", "default", "--expr", "0=2", "--jaw", "15", "--eyes", "10,-5", "-o", str(out))
    assert res.returncode == 0, res.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    bad = run_cli("head", "render", "default", "--expr", "zz", "-o", str(out))
    assert bad.returncode == 2 and bad.stderr.startswith("error: --expr") and "Traceback" not in bad.stderr
