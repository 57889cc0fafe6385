"""The recipe of the shipped default EPM (``ofera mapping make-default``): train, export, score, record.

1. the synthetic paired benchmark of the committed generator (cached, keyed by ``generator_version``);
2. ``train_on_paired`` with ``DEFAULT_EPM_CONFIG`` on one torch thread: capped by epochs and early
   stopping, never by wall clock, so every machine stops at the same epoch;
3. ONNX export (checked against torch), then the ONNX file itself is scored: its validation L1 and
   ``ofera mapping eval`` on both test splits;
4. everything is written into the ONNX metadata (``provenance``), with a hash of a regenerated sample.

Needs torch (``ofera[train]``).
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

DEFAULT_RECIPE = "ofera mapping make-default"


def make_default_epm(out: str | Path, seed: int = 0, threads: int = 1, progress: bool = True,
                     log: Callable[[str], None] = print) -> dict:
    """Regenerate the default EPM into ``out``; returns the metadata it wrote (see ``provenance``)."""
    import onnx
    import torch

    from ...head import load_head
    from ...mapping.provenance import validation_l1
    from ...mapping.runtime import Mapper
    from ..paired.benchmark import SAMPLE_STEP, sample_digest, validation_sample
    from .evaluate import default_matrix, evaluate, generator_version, load_paired_data
    from .export import export_checkpoint
    from .model import DEFAULT_EPM_CONFIG, EPMConfig, train_on_paired

    if threads:
        torch.set_num_threads(threads)
    paired = load_paired_data("synthetic", progress=progress)
    cfg = EPMConfig(**{**DEFAULT_EPM_CONFIG, "seed": seed})
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = Path(tmp) / "epm.pt"
        result = train_on_paired(paired, cfg, ckpt, progress=progress, source="synthetic")
        log(f"{result.stopped}; best validation L1 {result.best_val:.4f} at epoch {result.best_epoch}")
        path, diff = export_checkpoint(ckpt, out)
    log(f"ONNX vs torch: max abs difference {diff:.3g}")
    if diff > 1e-4:
        raise RuntimeError(f"{path}: ONNX output differs from torch by {diff:.3g} (> 1e-4)")

    mapper = Mapper.load(path)
    head = load_head("default")
    scores = evaluate(paired, mapper, default_matrix(head), head)
    sample = validation_sample(seed)
    train = paired.split_mask("train")
    meta = {
        "provenance": {
            "recipe": DEFAULT_RECIPE if seed == 0 else f"{DEFAULT_RECIPE} --seed {seed}",
            "generator": paired.meta.get("generator", ""),
            "generator_version": generator_version(),
            "sample": {"subject": sample["subject"], "source": sample["source"], "frames": sample["frames"],
                       "step": SAMPLE_STEP, "sha256": sample_digest(sample)},
            "torch": torch.__version__,
            "threads": threads,
        },
        "train": {
            "config": asdict(cfg),
            "best_epoch": result.best_epoch,
            "epochs": len(result.history),
            "stopped": result.stopped,
            "train_frames": int(train.sum()),
            "val_frames": int(paired.split_mask("val").sum()),
            "train_subjects": int(len(np.unique(paired.subject[train]))),
        },
        "metrics": {"val_l1": validation_l1(mapper, paired), "eval": scores.as_json()},
    }
    proto = onnx.load(str(path))
    keep = [p for p in proto.metadata_props if not p.key.startswith("train_") and p.key not in meta]
    del proto.metadata_props[:]
    proto.metadata_props.extend(keep)
    for k, v in meta.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = k, json.dumps(v, sort_keys=True)
    onnx.save(proto, str(path))
    return meta
