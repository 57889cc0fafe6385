"""How a shipped EPM was made, read back from its ONNX metadata, and the scores that check it (numpy + onnxruntime).

``ofera mapping make-default`` writes these metadata keys (JSON values) next to the export's own
(``ofera_model``, ``input_names``, ``output_layout``):

    provenance  {"recipe", "generator", "generator_version", "sample": {"subject", "source", "frames",
                 "step", "sha256"}, "torch", "threads"}
    train       {"config": EPMConfig as a dict, "best_epoch", "epochs", "stopped", "train_frames",
                 "val_frames", "train_subjects"}
    metrics     {"val_l1": the ONNX model's validation L1 (:func:`validation_l1`),
                 "eval": ``Evaluation.as_json()`` of ``ofera mapping eval`` at export}

``generator_version`` hashes the generator's source files (any edit changes it, formatting too);
``sample.sha256`` hashes a small regenerated sample of its output, so it changes only when what the
generator makes changes. Tests compare both the sample and the scores with the committed code's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import OferaError
from .runtime import Mapper

PROVENANCE_KEYS = ("provenance", "train", "metrics")


class ProvenanceError(OferaError, ValueError):
    """An EPM file without (or with unreadable) provenance metadata."""


def read_provenance(path: str | Path) -> dict[str, dict]:
    """The EPM's provenance metadata -> {"provenance": ..., "train": ..., "metrics": ...}."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    meta = sess.get_modelmeta().custom_metadata_map
    missing = [k for k in PROVENANCE_KEYS if k not in meta]
    if missing:
        raise ProvenanceError(f"{path}: no provenance metadata {missing}; regenerate it with "
                              "`ofera mapping make-default`")
    try:
        return {k: json.loads(meta[k]) for k in PROVENANCE_KEYS}
    except json.JSONDecodeError as exc:
        raise ProvenanceError(f"{path}: provenance metadata is not JSON: {exc}") from None


def output_std(y_train: np.ndarray) -> np.ndarray:
    """(68,) float32 per-output scale of the L1 loss: the training targets' std, floored at 1e-3 (as the EPM's)."""
    return np.maximum(np.asarray(y_train, np.float32).astype(np.float64).std(axis=0), 1e-3).astype(np.float32)


def validation_l1(mapper: Mapper, data) -> float:
    """The EPM's mean L1 on standardised outputs over a ``PairedData``'s validation frames (the training
    objective, on the model as exported: no BDA, no clamping)."""
    train, val = data.split_mask("train"), data.split_mask("val")
    scale = output_std(data.flame[train]).astype(np.float64)
    pred = mapper.epm_only(np.asarray(data.bs[val], np.float32)).astype(np.float64)
    return float(np.mean(np.abs(pred - data.flame[val]) / scale))
