"""The shipped default EPM against the committed code: same data, same config, same scores, same README.

If one of these fails, the asset and the code have drifted apart: regenerate the EPM with
``ofera mapping make-default`` and the README table with ``ofera mapping eval --markdown``.
"""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from ofera.assets import default_epm_path
from ofera.mapping.provenance import ProvenanceError, read_provenance, validation_l1

ROOT = Path(__file__).resolve().parents[1]
REGENERATE = "regenerate it with `ofera mapping make-default`"


@pytest.fixture(scope="module")
def shipped() -> dict:
    return read_provenance(default_epm_path())


def test_shipped_epm_records_how_it_was_made(shipped):
    from ofera.training.epm.model import DEFAULT_EPM_CONFIG, EPMConfig

    prov, train = shipped["provenance"], shipped["train"]
    assert prov["recipe"] == "ofera mapping make-default"
    assert prov["generator"] == "ofera.training.paired.make_benchmark"
    assert re.fullmatch(r"[0-9a-f]{16}", prov["generator_version"])
    assert re.fullmatch(r"[0-9a-f]{64}", prov["sample"]["sha256"])
    assert prov["threads"] == 1
    # The committed default config is the one the asset was trained with; no wall-clock cap.
    assert train["config"] == asdict(EPMConfig(**DEFAULT_EPM_CONFIG)), f"the default EPM config changed: {REGENERATE}"
    assert train["config"]["max_minutes"] == 0
    assert train["stopped"].startswith("early stop") or train["stopped"].startswith("max_epochs")
    assert train["epochs"] >= train["best_epoch"] + 1
    assert {"val_l1", "eval"} <= set(shipped["metrics"])


def test_shipped_epm_was_trained_on_what_the_committed_generator_makes(shipped):
    """Fast drift check: any change to what the generator makes (a rig constant, say) changes this sample."""
    from ofera.training.paired.benchmark import SAMPLE_STEP, sample_digest, validation_sample

    rec = shipped["provenance"]["sample"]
    assert rec["step"] == SAMPLE_STEP
    sample = validation_sample(frames=rec["frames"])
    assert (sample["subject"], sample["source"]) == (rec["subject"], rec["source"])
    assert sample_digest(sample) == rec["sha256"], (
        f"the committed paired-data generator no longer makes the data the shipped EPM was trained on: {REGENERATE}")


def test_epm_without_provenance_is_a_clear_error(tmp_path):
    pytest.importorskip("torch")
    from ofera.training.epm.export import export_onnx
    from ofera.training.epm.model import EPM

    path = export_onnx(EPM(hidden=16, blocks=1), tmp_path / "plain.onnx")
    with pytest.raises(ProvenanceError, match="no provenance metadata"):
        read_provenance(path)


@pytest.fixture(scope="module")
def evaluation():
    """The shipped EPM scored by `ofera mapping eval` on the cached benchmark of the committed generator."""
    from ofera.head import load_head
    from ofera.mapping.runtime import Mapper
    from ofera.training.epm.evaluate import default_matrix, evaluate, load_paired_data

    data = load_paired_data("synthetic", progress=False)
    head = load_head("default")
    mapper = Mapper.default()
    return data, mapper, evaluate(data, mapper, default_matrix(head), head)


def test_shipped_epm_scores_its_recorded_validation_metric(shipped, evaluation):
    data, mapper, _ = evaluation
    got = validation_l1(mapper, data)
    assert got == pytest.approx(shipped["metrics"]["val_l1"], abs=1e-4), f"validation L1 drifted: {REGENERATE}"


def test_shipped_epm_scores_its_recorded_evaluation(shipped, evaluation):
    rec, got = shipped["metrics"]["eval"], evaluation[2].as_json()
    for part in ("subjects", "holdout_source"):
        r, g = (rec, got) if part == "subjects" else (rec["holdout_source"], got["holdout_source"])
        assert g["test_subjects"] == r["test_subjects"] and g["sources"] == r["sources"]
        for method, row in r["methods"].items():
            for metric in ("param_rmse", "vertex_rmse_mm"):
                assert g["methods"][method][metric] == pytest.approx(row[metric], abs=1e-4), (part, method, metric)
        for key in ("without", "with"):
            assert g["bda"][key]["vertex_rmse_mm"] == pytest.approx(r["bda"][key]["vertex_rmse_mm"], abs=1e-4)


def _readme_block() -> str:
    text = (ROOT / "README.md").read_text()
    found = re.search(r"<!-- mapping-eval:begin -->\n(.*?)\n<!-- mapping-eval:end -->", text, re.S)
    assert found, "README.md lacks the mapping-eval table block"
    return found.group(1)


def test_readme_table_is_what_mapping_eval_prints(evaluation):
    from ofera.training.epm.evaluate import markdown_table

    block = _readme_block()
    table = "\n".join(line for line in block.splitlines() if line.startswith("|"))
    assert table == markdown_table(evaluation[2]), "README's table is stale: paste `ofera mapping eval --markdown`"


def test_epm_beats_ridge_by_the_margin_readme_claims(evaluation):
    claim = re.search(r"vertex RMSE is (\d+(?:\.\d+)?)% below ridge", _readme_block())
    assert claim, "README states no margin of the EPM over ridge"
    methods = evaluation[2].methods
    margin = 100.0 * (1.0 - methods["epm"]["vertex_rmse_mm"] / methods["ridge"]["vertex_rmse_mm"])
    assert margin >= float(claim.group(1)) - 0.05, f"EPM is {margin:.1f}% below ridge, README claims {claim.group(1)}%"
    assert margin >= 15.0  # the target of the mapping benchmark
    assert methods["epm"]["param_rmse"] < methods["ridge"]["param_rmse"]


def _train_val_l1(data: Path, out: Path) -> float:
    """Train in a fresh interpreter (`ofera epm train`), return its best validation L1."""
    res = subprocess.run([sys.executable, "-m", "ofera.cli.main", "epm", "train", str(data), "-o", str(out),
                          "--max-epochs", "6", "--patience", "6", "--quiet"],
                         capture_output=True, text=True, timeout=300, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    return float(re.search(r"best validation L1 ([0-9.]+)", res.stdout).group(1))


def test_epm_training_gives_the_same_model_in_two_fresh_processes(tmp_path):
    pytest.importorskip("torch")
    from ofera.training.paired import make_benchmark

    data = tmp_path / "tiny.npz"
    make_benchmark(tiny=True).save(data)
    a, b = (_train_val_l1(data, tmp_path / f"{k}.pt") for k in "ab")
    assert abs(a - b) <= 1e-3 and np.isfinite(a)
