"""Evaluation on a tiny generated benchmark: JSON layout, metrics, heatmap, cache, fast vertices."""

from __future__ import annotations

import json

import numpy as np
import pytest
from ofera.mapping.flame_values import neutral_flame_values
from ofera.mapping.runtime import Mapper
from ofera.training.epm import evaluate as ev
from ofera.training.paired import make_benchmark, region_masks, vertices_from_flame


@pytest.fixture(scope="module")
def tiny():
    return make_benchmark(tiny=True)


@pytest.fixture(scope="module")
def epm_path(tmp_path_factory):
    try:
        import torch
        from ofera.training.epm.export import export_onnx
        from ofera.training.epm.model import EPM
    except ImportError:
        from ofera.assets import default_epm_path

        return default_epm_path()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    return export_onnx(EPM(hidden=32), tmp_path_factory.mktemp("epm") / "epm.onnx")


def test_fast_vertices_match_reference(head):
    rng = np.random.default_rng(0)
    flame = neutral_flame_values(6, dtype=np.float64)
    flame[:, :50] = rng.normal(0, 1.0, (6, 50))
    flame[:, 50:] += rng.normal(0, 0.15, (6, 18))  # jaw and eyes, not orthonormal on purpose
    shape = rng.normal(0, 1.0, head.shape_dims)
    ids = np.flatnonzero(region_masks(head)["face"])
    ref = vertices_from_flame(head, flame, shape, ids, dtype=np.float64)
    from ofera.head import HeadSubject
    from ofera.mapping.flame_values import split_flame_values

    got = ev.FastVertices(head, ids)(HeadSubject.create(head, shape), *split_flame_values(flame))
    assert np.abs(got - ref).max() < 2e-6  # metres (float32)


def test_evaluate_tiny_benchmark(tiny, epm_path, head, tmp_path):
    matrix = ev.default_matrix(head)
    assert matrix.matrix.shape == (51, 103)
    result = ev.evaluate(tiny, Mapper.load(epm_path), matrix, head)
    out = result.as_json()
    assert set(out) == {"methods", "bda", "test_subjects", "sources", "frames", "holdout_source"}
    held = out["holdout_source"]
    for part in (out, held):
        assert set(part["methods"]) == {"matrix", "ridge", "epm"}
        for row in part["methods"].values():
            assert set(row) == {"param_rmse", "vertex_rmse_mm", "regions"}
            assert set(row["regions"]) == {"eyes", "brows", "mouth_and_jaw"}
            assert np.isfinite([row["param_rmse"], row["vertex_rmse_mm"], *row["regions"].values()]).all()
            assert row["vertex_rmse_mm"] > 0
        assert set(part["bda"]) == {"without", "with"}
        assert set(part["bda"]["with"]) == {"vertex_rmse_mm", "param_rmse"}
    # The two splits: test subjects of the training sources, and every subject of the held-out source.
    test = tiny.split_mask("test")
    holdout = np.isin(tiny.source, [tiny.source_names.index(n) for n in tiny.meta["holdout_sources"]])
    assert held["sources"] == ["handheld"] and "handheld" not in out["sources"]
    assert out["test_subjects"] == sorted(set(tiny.subject[test & ~holdout].tolist()))
    assert held["test_subjects"] == sorted(set(tiny.subject[holdout].tolist()))
    assert out["frames"] == int((test & ~holdout).sum()) and held["frames"] == int(holdout.sum())
    assert not (holdout & ~test).any()  # nothing of the held-out source is trained or validated on
    json.dumps(out)  # plain JSON types
    table = ev.markdown_table(result)
    assert table.count("| held-out subjects |") == 5 and table.count("| held-out source |") == 5
    # The matrix knows nothing of the data; ridge is fitted on it: on these frames ridge must do better.
    assert out["methods"]["ridge"]["param_rmse"] < out["methods"]["matrix"]["param_rmse"]
    png = ev.draw_heatmaps(result, head, tmp_path / "heat.png")
    assert png.stat().st_size > 10_000
    ev.print_table(result)


def test_synthetic_data_is_cached_by_generator_version(tiny, tmp_path, monkeypatch):
    monkeypatch.setenv("OFERA_CACHE", str(tmp_path))
    calls = []
    monkeypatch.setattr(ev, "make_benchmark", lambda **kw: calls.append(kw) or tiny)
    a = ev.load_paired_data("synthetic", progress=False)
    b = ev.load_paired_data("synthetic", progress=False)
    assert len(calls) == 1 and len(a) == len(b) == len(tiny)
    assert (tmp_path / "paired" / f"benchmark-{ev.generator_version()}.npz").is_file()
    np.testing.assert_array_equal(b.flame, tiny.flame)


def test_cli_train_export_eval_on_tiny_data(tiny, tmp_path):
    pytest.importorskip("torch")
    from ofera.cli.main import app
    from typer.testing import CliRunner

    data = tmp_path / "tiny.npz"
    tiny.save(data)
    run = CliRunner().invoke
    res = run(app, ["epm", "train", str(data), "-o", str(tmp_path / "epm.pt"), "--max-epochs", "3", "--quiet"])
    assert res.exit_code == 0, res.output
    res = run(app, ["epm", "export", str(tmp_path / "epm.pt"), "-o", str(tmp_path / "epm.onnx")])
    assert res.exit_code == 0, res.output
    assert "max abs difference" in res.output
    res = run(app, ["mapping", "eval", "--data", str(data), "--epm", str(tmp_path / "epm.onnx"),
                    "--json", str(tmp_path / "out.json"), "--heatmap", str(tmp_path / "heat.png")])
    assert res.exit_code == 0, res.output
    out = json.loads((tmp_path / "out.json").read_text())
    assert {"methods", "bda", "test_subjects", "holdout_source"} <= set(out) and (tmp_path / "heat.png").is_file()
    res = run(app, ["mapping", "eval", "--data", str(tmp_path / "missing.npz")])
    assert res.exit_code == 2 and "error:" in res.output
