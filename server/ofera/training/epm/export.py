"""Export a trained EPM to ONNX (TorchScript exporter, ``dynamo=False``) and check it against torch.

The graph has one input ``blendshapes`` (B, 51) float32 in arkit51 order and one output ``flame``
(B, 68) float32, with a dynamic batch axis. BatchNorm and Dropout are taken in eval mode: each
BatchNorm is folded into the Linear before it and the output scale into the last Linear (the same
function, half the graph nodes: ONNX Runtime does not fuse Gemm + BatchNormalization itself). The
model's metadata holds the input names and the output layout so the run time can check what it loads.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ...mapping.layouts import ARKIT51_NAMES
from .model import EPM, N_IN, N_OUT, load_checkpoint

INPUT_NAME = "blendshapes"
OUTPUT_NAME = "flame"
OPSET = 17
OUTPUT_LAYOUT = "expr50,jaw6d,left_eye6d,right_eye6d"


def _fold(linear: nn.Linear, bn: nn.BatchNorm1d | None = None, scale: torch.Tensor | None = None,
          shift: torch.Tensor | None = None) -> nn.Linear:
    """A Linear equal to ``bn(linear(x))`` in eval mode, or to ``linear(x) * scale + shift``."""
    w, b = linear.weight.detach().double(), linear.bias.detach().double()
    if bn is not None:
        scale = bn.weight.detach().double() / torch.sqrt(bn.running_var.double() + bn.eps)
        shift = bn.bias.detach().double() - bn.running_mean.double() * scale
    assert scale is not None and shift is not None
    out = nn.Linear(linear.in_features, linear.out_features)
    with torch.no_grad():
        out.weight.copy_((w * scale.double()[:, None]).float())
        out.bias.copy_((b * scale.double() + shift.double()).float())
    return out


class _FoldedBlock(nn.Module):
    def __init__(self, block: nn.Module) -> None:
        super().__init__()
        fc1, bn1, _, _, fc2, bn2, _ = block.body
        self.body = nn.Sequential(_fold(fc1, bn1), nn.ReLU(), _fold(fc2, bn2), nn.ReLU())

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return h + self.body(h)


def fold_batchnorm(model: EPM) -> nn.Module:
    """The inference-only twin of ``model`` (eval mode) with BatchNorm and output scale folded in."""
    model.eval()
    stem_fc, stem_bn, _ = model.stem
    return nn.Sequential(
        _fold(stem_fc, stem_bn),
        nn.ReLU(),
        *(_FoldedBlock(b) for b in model.blocks),
        _fold(model.head, scale=model.y_std, shift=model.y_mean),
    ).eval()


def export_onnx(model: EPM, path: str | Path, metadata: dict[str, str] | None = None) -> Path:
    """Write ``model`` (in eval mode, BatchNorm folded) as ONNX with a dynamic batch axis."""
    import onnx

    path = Path(path)
    folded = fold_batchnorm(model)
    dummy = torch.rand(2, N_IN)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter is deprecated, not gone
        torch.onnx.export(
            folded,
            (dummy,),
            str(path),
            input_names=[INPUT_NAME],
            output_names=[OUTPUT_NAME],
            dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
            opset_version=OPSET,
            do_constant_folding=True,
            dynamo=False,
        )
    proto = onnx.load(str(path))
    meta = {
        "ofera_model": "epm",
        "input_names": json.dumps(list(ARKIT51_NAMES)),
        "output_layout": OUTPUT_LAYOUT,
        **(metadata or {}),
    }
    for k, v in meta.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = k, str(v)
    proto.producer_name = "ofera"
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))
    return path


def check_onnx(model: EPM, path: str | Path, frames: int = 512, seed: int = 0) -> float:
    """Max abs difference between ONNX Runtime and torch on random inputs (batch ``frames`` and 1)."""
    import onnxruntime as ort

    rng = np.random.default_rng(seed)
    x = rng.random((frames, N_IN), dtype=np.float32)
    x[: frames // 4] *= rng.random((frames // 4, 1), dtype=np.float32) < 0.5  # some sparse frames
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    ref = model.predict(x)
    got = sess.run([OUTPUT_NAME], {INPUT_NAME: x})[0]
    one = sess.run([OUTPUT_NAME], {INPUT_NAME: x[:1]})[0]
    if got.shape != (frames, N_OUT) or one.shape != (1, N_OUT):
        raise RuntimeError(f"ONNX output shapes {got.shape}, {one.shape}; expected ({frames}, {N_OUT}), (1, {N_OUT})")
    return float(max(np.abs(got - ref).max(), np.abs(one - ref[:1]).max()))


def export_checkpoint(checkpoint: str | Path, out: str | Path) -> tuple[Path, float]:
    """Checkpoint ``.pt`` -> ONNX file; returns the path and the ONNX-vs-torch max abs difference."""
    model, config, ckpt = load_checkpoint(checkpoint)
    meta = {"epm_config": json.dumps({"hidden": config.hidden, "blocks": config.blocks})}
    for k, v in (ckpt.get("meta") or {}).items():
        meta[f"train_{k}"] = json.dumps(v) if not isinstance(v, str) else v
    path = export_onnx(model, out, meta)
    return path, check_onnx(model, path)
