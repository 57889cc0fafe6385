"""Evaluate mappers on held-out subjects: the paper's Table 1 (matrix, ridge, EPM) and the BDA ablation.

Metrics, over the TEST subjects of a paired data set (subject-disjoint from train and validation):

- ``param_rmse``: RMSE over the expression coefficients and the jaw 6D (56 values; eyes excluded, as
  the paper);
- ``vertex_rmse_mm``: RMSE of vertex positions in millimetres, meshes built from the predicted and
  the ground-truth FLAME values with each subject's own identity, over the face vertices (those that
  any expression, jaw or eye motion moves; the rigid scalp and neck would only dilute the average);
- ``regions``: the same vertex RMSE on the eyes, brows and mouth-and-jaw vertices;
- BDA ablation: the EPM on the simulated headset stream (Meta's OVR -> ARKit remapping of ``headset``),
  without and with a BDA fitted on the training subjects' pairs (headset arkit51, observed arkit51).

numpy + onnxruntime only: the EPM is evaluated through ``runtime.Mapper`` (the shipped ONNX by default).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..head import HeadModel, HeadSubject
from ..head.lbs import pose_feature, rigid_transforms
from .baselines import MatrixMapper, RidgeMapper, param_rmse
from .bda import BDA
from .flame_values import split_flame_values
from .layouts import to_arkit51
from .runtime import Mapper

METHODS = ("matrix", "ridge", "epm")
REGIONS = ("eyes", "brows", "mouth_jaw")


# ----- fast vertices (the reference is ofera.head.lbs; tests compare them) -------------------------


class FastVertices:
    """Batched float32 LBS for one head model (root and neck as given; ~10x faster than the reference).

    Blends the joints' 3x4 transforms per vertex with one matrix product, ``T = W @ A`` (B, V, 12),
    instead of the reference's (B, V, 4, 4) float64 einsum.
    """

    def __init__(self, model: HeadModel) -> None:
        self.model = model
        v = model.num_vertices
        self.exprdirs = np.ascontiguousarray(model.exprdirs.reshape(3 * v, -1).T, np.float32)  # (E, 3V)
        self.posedirs = np.ascontiguousarray(model.posedirs, np.float32)  # (36, 3V)
        self.weights = np.ascontiguousarray(model.weights, np.float32)  # (V, K)

    def __call__(self, subject: HeadSubject, expr: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """expr (B, n), rotations (B, K, 3, 3) -> vertices (B, V, 3) float32."""
        expr = np.atleast_2d(np.asarray(expr, np.float32))
        b, n = expr.shape
        v = self.model.num_vertices
        flat = subject.v_id.reshape(-1).astype(np.float32) + expr @ self.exprdirs[:n]
        flat += pose_feature(np.asarray(rotations, np.float64)).astype(np.float32) @ self.posedirs
        v_po = flat.reshape(b, v, 3)
        joints = subject.j_id[None] + np.einsum("kce,be->bkc", subject.j_expr[:, :, :n], expr.astype(np.float64))
        a = rigid_transforms(np.asarray(rotations, np.float64), joints, self.model.parents)
        k = a.shape[1]
        blend = np.matmul(self.weights[None], a[:, :, :3, :].reshape(b, k, 12).astype(np.float32))  # (B, V, 12)
        out = np.empty((b, v, 3), np.float32)
        for r in range(3):
            acc = blend[..., 4 * r + 3].copy()
            for c in range(3):
                acc += blend[..., 4 * r + c] * v_po[..., c]
            out[..., r] = acc
        return out


# ----- results -------------------------------------------------------------------------------------


@dataclass
class Evaluation:
    """What :func:`evaluate` measured; ``as_json()`` is the documented JSON layout."""

    methods: dict[str, dict] = field(default_factory=dict)
    bda: dict[str, dict] = field(default_factory=dict)
    test_subjects: list[int] = field(default_factory=list)
    per_vertex_mm: dict[str, np.ndarray] = field(default_factory=dict)  # method -> (V,) RMSE per vertex
    extras: dict = field(default_factory=dict)  # ridge alpha, frame counts, timings (printed, not in JSON)

    def as_json(self) -> dict:
        return {"methods": self.methods, "bda": self.bda, "test_subjects": self.test_subjects}


class _VertexErrors:
    """Accumulates squared vertex distances (per vertex) between predicted and true meshes."""

    def __init__(self, n_vertices: int) -> None:
        self.sq = np.zeros(n_vertices, np.float64)
        self.frames = 0

    def add(self, pred: np.ndarray, true: np.ndarray) -> None:
        d = pred - true
        self.sq += np.einsum("bvc,bvc->v", d, d, dtype=np.float64)
        self.frames += len(pred)

    def per_vertex_mm(self) -> np.ndarray:
        return np.sqrt(self.sq / max(self.frames, 1)) * 1000.0

    def rmse_mm(self, mask: np.ndarray) -> float:
        return float(np.sqrt(self.sq[mask].sum() / max(self.frames * int(mask.sum()), 1)) * 1000.0)


def face_regions(model: HeadModel) -> dict[str, np.ndarray]:
    """Vertex masks (V,) bool: ``face`` (vertices some expression, jaw or eye motion moves) and REGIONS."""
    from .paired import region_masks

    masks = {k: np.asarray(v, bool) for k, v in region_masks(model).items()}
    if "face" not in masks:
        moves = np.abs(model.exprdirs).max(axis=(1, 2)) > 1e-6
        moves |= model.weights[:, 2:].sum(axis=1) > 1e-6  # jaw and eyes
        masks["face"] = moves
    missing = [r for r in REGIONS if r not in masks]
    if missing:
        raise ValueError(f"region masks lack {missing}; have {sorted(masks)}")
    return masks


def evaluate(
    data,
    mapper: Mapper,
    matrix: MatrixMapper,
    model: HeadModel,
    max_test_frames: int = 0,
    progress: Callable[[str], None] | None = None,
) -> Evaluation:
    """Evaluate matrix, ridge (fitted here, alpha on validation) and the EPM (``mapper``) on TEST subjects.

    ``data`` is a ``PairedData``; ``mapper`` is used with its BDA replaced by identity / a fitted BDA
    for the ablation; ``max_test_frames`` > 0 subsamples test frames evenly (for quick runs).
    """
    say = progress or (lambda _msg: None)
    split = np.asarray(data.split).astype(str)
    train, val, test = (split == "train"), (split == "val"), (split == "test")
    if not test.any() or not train.any() or not val.any():
        raise ValueError("paired data needs train, val and test frames (split)")
    test_idx = np.flatnonzero(test)
    if max_test_frames and len(test_idx) > max_test_frames:
        test_idx = test_idx[np.linspace(0, len(test_idx) - 1, max_test_frames).astype(np.int64)]
    bs = np.asarray(data.bs, np.float32)
    flame = np.asarray(data.flame, np.float32)
    subject = np.asarray(data.subject, np.int64)

    say("fitting ridge (alpha on validation)")
    ridge = RidgeMapper.fit(bs[train], flame[train], bs[val], flame[val])
    epm = Mapper(mapper.session, BDA.identity(), mapper.source)
    x_test = bs[test_idx]
    preds = {"matrix": matrix.predict(x_test), "ridge": ridge.predict(x_test), "epm": epm.map_batch(x_test)}

    say("fitting BDA on the training subjects' headset stream")
    headset = to_arkit51("ovr63", np.asarray(data.headset, np.float32))
    bda = BDA.fit(headset[train], bs[train], device="simulated-headset")
    with_bda = Mapper(mapper.session, bda, mapper.source)
    preds["bda_without"] = epm.map_batch(headset[test_idx])
    preds["bda_with"] = with_bda.map_batch(headset[test_idx])

    masks = face_regions(model)
    errors = {k: _VertexErrors(model.num_vertices) for k in preds}
    fast = FastVertices(model)
    subjects = sorted(int(s) for s in np.unique(subject[test_idx]))
    for s in subjects:
        say(f"vertices of test subject {s}")
        rows = np.flatnonzero(subject[test_idx] == s)
        subj = HeadSubject.create(model, data.subject_shape(s) if hasattr(data, "subject_shape") else None)
        for i in range(0, len(rows), 256):
            chunk = rows[i:i + 256]
            true = fast(subj, *split_flame_values(flame[test_idx[chunk]]))
            for k, p in preds.items():
                errors[k].add(fast(subj, *split_flame_values(p[chunk])), true)

    result = Evaluation(test_subjects=subjects)
    for k in METHODS:
        result.methods[k] = {
            "param_rmse": param_rmse(preds[k], flame[test_idx]),
            "vertex_rmse_mm": errors[k].rmse_mm(masks["face"]),
            "regions": {r: errors[k].rmse_mm(masks[r]) for r in REGIONS},
        }
        result.per_vertex_mm[k] = errors[k].per_vertex_mm()
    result.bda = {
        "without": {"vertex_rmse_mm": errors["bda_without"].rmse_mm(masks["face"])},
        "with": {"vertex_rmse_mm": errors["bda_with"].rmse_mm(masks["face"])},
    }
    result.extras = {
        "ridge_alpha": ridge.alpha,
        "test_frames": len(test_idx),
        "face_vertices": int(masks["face"].sum()),
        "bda_param_rmse": {"without": param_rmse(preds["bda_without"], flame[test_idx]),
                           "with": param_rmse(preds["bda_with"], flame[test_idx])},
    }
    return result


# ----- presentation --------------------------------------------------------------------------------


def print_table(result: Evaluation, console=None) -> None:
    """The paper's Table 1 layout (rich), then the BDA ablation."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    table = Table(title=f"Mappers on held-out subjects {result.test_subjects} "
                        f"({result.extras.get('test_frames', '?')} frames)")
    table.add_column("method")
    table.add_column("param RMSE", justify="right")
    table.add_column("vertex RMSE (mm)", justify="right")
    for r in REGIONS:
        table.add_column(f"{r} (mm)", justify="right")
    best = {m: min(result.methods[k][m] for k in result.methods) for m in ("param_rmse", "vertex_rmse_mm")}
    for k, row in result.methods.items():
        cells = [f"{row[m]:.3f}" if row[m] != best[m] else f"[bold]{row[m]:.3f}[/]"
                 for m in ("param_rmse", "vertex_rmse_mm")]
        table.add_row(k, *cells, *(f"{row['regions'][r]:.3f}" for r in REGIONS))
    console.print(table)
    bda = Table(title="BDA ablation: EPM on the simulated headset stream (Meta's OVR -> ARKit mapping)")
    bda.add_column("")
    bda.add_column("vertex RMSE (mm)", justify="right")
    bda.add_row("without BDA", f"{result.bda['without']['vertex_rmse_mm']:.3f}")
    bda.add_row("with BDA", f"{result.bda['with']['vertex_rmse_mm']:.3f}")
    console.print(bda)


def draw_heatmaps(result: Evaluation, model: HeadModel, out: str | Path,
                  views: tuple[float, ...] = (0.0, 40.0)) -> Path:
    """Per-vertex RMSE (mm) of each method on the neutral head, side by side, one colour scale."""
    import tempfile

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import colormaps
    from matplotlib.colors import Normalize

    from ..head.render import render_mesh, vertex_colours

    methods = [k for k in METHODS if k in result.per_vertex_mm]
    vmax = max(float(np.percentile(result.per_vertex_mm[k], 99.5)) for k in methods) or 1.0
    norm, cmap = Normalize(0.0, vmax), colormaps["inferno"]
    base = vertex_colours(model)
    moving = face_regions(model)["face"]
    images = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in methods:
            col = base * 0.35 + 0.5  # washed-out label colours where nothing moves
            col[moving] = cmap(norm(result.per_vertex_mm[k][moving]))[:, :3]
            png = render_mesh(model.v_template, model.faces, col, Path(tmp) / f"{k}.png", views=views, size_px=360)
            images.append(plt.imread(png))
    fig, axes = plt.subplots(1, len(methods), figsize=(4.0 * len(methods) * len(views) / 2 + 0.8, 2.6), dpi=150)
    for ax, k, img in zip(np.atleast_1d(axes), methods, images):
        ax.imshow(img)
        ax.set_title(f"{k}: {result.methods[k]['vertex_rmse_mm']:.3f} mm", fontsize=9)
        ax.axis("off")
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes, fraction=0.02, pad=0.01,
                 label="per-vertex RMSE (mm)")
    fig.suptitle(f"Vertex error on held-out subjects {result.test_subjects}", fontsize=10)
    out = Path(out)
    fig.savefig(out, bbox_inches="tight")
    plt.close(fig)
    return out
