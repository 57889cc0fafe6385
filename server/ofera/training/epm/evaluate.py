"""Evaluate mappers on held-out subjects: the paper's Table 1 (matrix, ridge, EPM) and the BDA ablation.

Metrics, over the TEST subjects of a paired data set (subject-disjoint from train and validation):

- ``param_rmse``: RMSE over the expression coefficients and the jaw 6D (56 values; eyes excluded, as
  the paper);
- ``vertex_rmse_mm``: RMSE of vertex positions in millimetres, meshes built from the predicted and
  the ground-truth FLAME values with each subject's own identity, over the face vertices (those that
  any expression, jaw or eye motion moves; the rigid scalp and neck would only dilute the average);
- ``regions``: the same vertex RMSE on the eyes, brows and mouth-and-jaw vertices;
- BDA ablation: the EPM on the simulated headset stream (Meta's OVR -> ARKit remapping of ``headset``),
  without and with a BDA of that headset (every source has its own) fitted on other subjects' pairs
  (headset arkit51, observed arkit51): the source's training subjects, or for a held-out source, its
  other subjects (a user calibrating a new headset on a few people).

Two test splits: held-out subjects of the training sources, and a held-out source (estimator, headset
and recording style never seen in training or validation).

numpy + onnxruntime only: the EPM is evaluated through ``runtime.Mapper`` (the shipped ONNX by default).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...head import HeadModel, HeadSubject
from ...head.lbs import pose_feature, rigid_transforms
from ...mapping.baselines import MatrixMapper, RidgeMapper, correspondence_matrix, param_rmse
from ...mapping.bda import BDA
from ...mapping.flame_values import split_flame_values
from ...mapping.layouts import to_arkit51
from ...mapping.runtime import Mapper
from ..paired import REGIONS, PairedData, PairedDataError, make_benchmark, region_masks
from ..paired._threads import single_blas_thread

METHODS = ("matrix", "ridge", "epm")


# ----- fast vertices (the reference is ofera.head.lbs; tests compare them) -------------------------


class FastVertices:
    """Batched float32 LBS on some vertices of one head model (the reference is
    ``paired.vertices_from_flame`` / ``ofera.head.lbs``; a test compares them).

    Blends the joints' 3x4 transforms per vertex with one matrix product, ``T = W @ A`` (B, n, 12),
    instead of (B, n, 3, 3) float64 einsums: about 10x faster, which keeps evaluation in minutes.
    """

    def __init__(self, model: HeadModel, vertex_ids: np.ndarray | None = None) -> None:
        self.model = model
        ids = np.arange(model.num_vertices) if vertex_ids is None else np.asarray(vertex_ids, np.int64)
        self.ids = ids
        n = len(ids)
        self.exprdirs = np.ascontiguousarray(model.exprdirs[ids].reshape(3 * n, -1).T, np.float32)  # (E, 3n)
        posedirs = model.posedirs.reshape(-1, model.num_vertices, 3)[:, ids]
        self.posedirs = np.ascontiguousarray(posedirs.reshape(len(posedirs), 3 * n), np.float32)  # (36, 3n)
        self.weights = np.ascontiguousarray(model.weights[ids], np.float32)  # (n, K)

    def __call__(self, subject: HeadSubject, expr: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """expr (B, e), rotations (B, K, 3, 3) -> vertices (B, n, 3) float32."""
        expr = np.atleast_2d(np.asarray(expr, np.float32))
        b, e = expr.shape
        n = len(self.ids)
        rotations = np.asarray(rotations, np.float64)
        flat = subject.v_id[self.ids].reshape(-1).astype(np.float32) + expr @ self.exprdirs[:e]
        flat += pose_feature(rotations).astype(np.float32) @ self.posedirs
        v_po = flat.reshape(b, n, 3)  # shaped and pose-corrected, before skinning
        joints = subject.j_id[None] + np.einsum("kce,be->bkc", subject.j_expr[:, :, :e], expr.astype(np.float64))
        a = rigid_transforms(rotations, joints, self.model.parents)
        k = a.shape[1]
        blend = np.matmul(self.weights[None], a[:, :, :3, :].reshape(b, k, 12).astype(np.float32))  # (B, n, 12)
        out = np.empty((b, n, 3), np.float32)
        for r in range(3):
            acc = blend[..., 4 * r + 3].copy()
            for c in range(3):
                acc += blend[..., 4 * r + c] * v_po[..., c]
            out[..., r] = acc
        return out


# ----- results -------------------------------------------------------------------------------------


@dataclass
class Split:
    """The scores of the mappers on one set of test frames (see :func:`evaluate`)."""

    test_subjects: list[int] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)
    frames: int = 0
    methods: dict[str, dict] = field(default_factory=dict)
    bda: dict[str, dict] = field(default_factory=dict)
    per_vertex_mm: dict[str, np.ndarray] = field(default_factory=dict)  # method -> (V,) RMSE per vertex

    def as_json(self) -> dict:
        return {"methods": self.methods, "bda": self.bda, "test_subjects": self.test_subjects,
                "sources": self.sources, "frames": self.frames}


@dataclass
class Evaluation:
    """What :func:`evaluate` measured; ``as_json()`` is the documented JSON layout.

    ``subjects``: test subjects of the training sources (their estimators and headsets were seen in
    training); ``source``: the held-out source(s), never seen (None when the data has none).
    """

    subjects: Split
    source: Split | None = None
    extras: dict = field(default_factory=dict)  # ridge alpha, frame counts (printed, not in JSON)

    @property
    def methods(self) -> dict[str, dict]:
        return self.subjects.methods

    @property
    def per_vertex_mm(self) -> dict[str, np.ndarray]:
        return self.subjects.per_vertex_mm

    @property
    def test_subjects(self) -> list[int]:
        return self.subjects.test_subjects

    def as_json(self) -> dict:
        out = self.subjects.as_json()
        out["holdout_source"] = None if self.source is None else self.source.as_json()
        return out


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
    """Vertex masks (V,) bool from ``paired.region_masks``: ``face`` and the REGIONS."""
    masks = {k: np.asarray(v, bool) for k, v in region_masks(model).items()}
    missing = [r for r in ("face", *REGIONS) if r not in masks]
    if missing:
        raise ValueError(f"region masks lack {missing}; have {sorted(masks)}")
    return masks


# ----- inputs: paired data (cached benchmark), head, the correspondence matrix ----------------------


def generator_version() -> str:
    """Key of the synthetic benchmark's generator: a hash of the code that generates it.

    Any change to the paired-data package (``ofera.training.paired``), the procedural head and its LBS, the
    layouts (the server's and the protocol's names) or the FLAME values makes a new key, so a stale cached
    benchmark is never used.
    """
    import hashlib
    import importlib

    from .. import paired

    files = sorted(Path(paired.__file__).parent.glob("*.py"))  # ofera/training/paired/
    files += [Path(importlib.import_module(m).__file__ or "") for m in (
        "ofera.head.io", "ofera.head.lbs", "ofera.head.model", "ofera.head.procedural", "ofera.head.rotations",
        "ofera.mapping.layouts", "ofera_protocol.layouts", "ofera.mapping.flame_values")]
    digest = hashlib.sha256()
    for f in files:
        digest.update(f.name.encode())
        digest.update(f.read_bytes())
    return digest.hexdigest()[:16]


def load_paired_data(source: str | Path, progress: bool = True, cache: bool = True) -> PairedData:
    """A paired-data ``.npz``, or ``synthetic``: the benchmark, generated once and cached under
    ``~/.cache/ofera/paired/`` (``$OFERA_CACHE``) keyed by :func:`generator_version`."""
    if str(source) != "synthetic":
        return PairedData.load(source)
    from ...assets import cache_dir

    path = cache_dir("paired") / f"benchmark-{generator_version()}.npz"
    if cache and path.is_file():
        try:
            return PairedData.load(path)
        except PairedDataError:
            path.unlink(missing_ok=True)  # a broken cache file: regenerate
    data = make_benchmark(progress=progress or None)
    if cache:
        tmp = path.with_suffix(".tmp")
        data.save(tmp)
        tmp.replace(path)
    return data


def head_of(data: PairedData, head: str | Path = "default") -> HeadModel:
    """The head model the paired data's FLAME values belong to (``default``: the procedural head)."""
    from ...head import load_head

    model = load_head(head)
    made_on = (data.meta or {}).get("head")
    if made_on and made_on != model.name:
        raise ValueError(f"the paired data was made on head {made_on!r}, not {model.name!r}: pass --head")
    return model


def default_matrix(model: HeadModel) -> MatrixMapper:
    """The project's own fixed matrix, from per-shape correspondences, without paired frames.

    For each ARKit shape alone at weight 1, the synthetic rig (as designed: neutral style, mean
    identity) makes a mesh and the tracker-style fitter finds the head's FLAME values for it; the
    matrix rows are those values minus the neutral face's, in EMAGE's layout (see ``baselines``).
    """
    from ..paired.fit import FlameFitter, fit_vertices
    from ..paired.rig import Rig, RigStyle

    ids = fit_vertices(model)
    rig = Rig(model, RigStyle.neutral(model.shape_dims), ids)
    fitted = FlameFitter(model, None, ids).fit(rig.mesh(np.vstack([np.zeros(51), np.eye(51)]))).flame
    return correspondence_matrix(fitted[1:], fitted[0])


def evaluate(
    data: PairedData,
    mapper: Mapper,
    matrix: MatrixMapper,
    model: HeadModel,
    max_test_frames: int = 0,
    progress: Callable[[str], None] | None = None,
    heatmap_frames: int = 600,
) -> Evaluation:
    """Evaluate matrix, ridge (fitted here, alpha on validation) and the EPM (``mapper``) on TEST subjects.

    Two splits: test subjects of the sources that have training subjects, and the subjects of held-out
    sources (sources with no training or validation frames). ``mapper``'s session is used with an
    identity BDA for the three mappers, then, for the ablation on the headset stream, with identity and
    with a BDA of the subject's headset (each source has its own) fitted on other subjects wearing it.
    ``max_test_frames`` > 0 subsamples each split's test frames evenly (quick runs).
    """
    say = progress or (lambda _msg: None)
    train, val, test = (data.split_mask(k) for k in ("train", "val", "test"))
    if not test.any() or not train.any() or not val.any():
        raise ValueError("paired data needs train, val and test frames (split)")
    if data.headset is None:
        raise ValueError("paired data has no headset stream: the BDA ablation needs one")
    seen = np.isin(data.source, np.unique(data.source[train | val]))
    say("fitting ridge (alpha on validation)")
    ridge = RidgeMapper.fit(data.bs[train], data.flame[train], data.bs[val], data.flame[val])
    headset = to_arkit51("ovr63", data.headset)
    mappers = {"matrix": matrix.predict, "ridge": ridge.predict,
               "epm": Mapper(mapper.session, BDA.identity(), mapper.source).map_batch}

    def with_bda(s: int) -> Callable:
        """The EPM behind a BDA for subject ``s``'s headset, fitted on other subjects wearing it: the source's
        training subjects, or (a held-out source has none) the source's other subjects."""
        same = data.source == data.source[data.subject == s][0]
        rows = same & train if (same & train).any() else same & (data.subject != s)
        if not rows.any():
            raise ValueError(f"cannot fit a BDA for the headset of test subject {s}: no other subject wears it "
                             "(a held-out source needs at least two subjects)")
        bda = BDA.fit(headset[rows], data.bs[rows], device=f"headset of source {int(data.source[same][0])}")
        return Mapper(mapper.session, bda, mapper.source).map_batch

    def split(rows: np.ndarray) -> Split:
        idx = np.flatnonzero(rows)
        if max_test_frames and len(idx) > max_test_frames:
            idx = idx[np.linspace(0, len(idx) - 1, max_test_frames).astype(np.int64)]
        return _score(data, idx, mappers, with_bda, headset, model, say, heatmap_frames)

    subjects = split(test & seen)
    source = split(test & ~seen) if (test & ~seen).any() else None
    extras = {"ridge_alpha": ridge.alpha, "test_frames": subjects.frames,
              "face_vertices": int(face_regions(model)["face"].sum())}
    return Evaluation(subjects, source, extras)


def _score(data: PairedData, test_idx: np.ndarray, mappers: dict[str, Callable],
           with_bda: Callable[[int], Callable], headset: np.ndarray, model: HeadModel, say: Callable[[str], None],
           heatmap_frames: int) -> Split:
    """Vertex and parameter errors of every mapper (and the BDA ablation) on the frames ``test_idx``."""
    flame, subject = data.flame, data.subject.astype(np.int64)
    x_test = data.bs[test_idx]
    preds = {k: f(x_test) for k, f in mappers.items()}
    preds["bda_without"] = mappers["epm"](headset[test_idx])
    preds["bda_with"] = np.empty_like(preds["bda_without"])
    for s in np.unique(subject[test_idx]):
        rows = subject[test_idx] == s
        preds["bda_with"][rows] = with_bda(int(s))(headset[test_idx[rows]])

    masks = face_regions(model)
    ids = np.flatnonzero(masks["face"])
    local = {k: masks[k][ids] for k in ("face", *REGIONS)}
    errors = {k: _VertexErrors(len(ids)) for k in preds}
    fast = FastVertices(model, ids)
    # The heatmaps show every vertex; a subsample of the test frames is enough for a picture.
    whole = {k: _VertexErrors(model.num_vertices) for k in METHODS}
    fast_all = FastVertices(model)
    every = max(1, len(test_idx) // heatmap_frames) if heatmap_frames else 0
    subjects = sorted(int(s) for s in np.unique(subject[test_idx]))
    with single_blas_thread():
        for s in subjects:
            say(f"meshes of test subject {s}")
            rows = np.flatnonzero(subject[test_idx] == s)
            subj = HeadSubject.create(model, None if data.shape is None else data.shape[s])
            for i in range(0, len(rows), 256):
                chunk = rows[i:i + 256]
                true = fast(subj, *split_flame_values(flame[test_idx[chunk]]))
                for k, p in preds.items():
                    errors[k].add(fast(subj, *split_flame_values(p[chunk])), true)
            if every:
                pick = rows[::every]
                true = fast_all(subj, *split_flame_values(flame[test_idx[pick]]))
                for k in METHODS:
                    whole[k].add(fast_all(subj, *split_flame_values(preds[k][pick])), true)

    names = data.source_names
    sources = sorted({names[int(i)] if int(i) < len(names) else str(int(i)) for i in np.unique(data.source[test_idx])})
    out = Split(test_subjects=subjects, sources=sources, frames=len(test_idx))
    for k in METHODS:
        out.methods[k] = {
            "param_rmse": param_rmse(preds[k], flame[test_idx]),
            "vertex_rmse_mm": errors[k].rmse_mm(local["face"]),
            "regions": {r: errors[k].rmse_mm(local[r]) for r in REGIONS},
        }
        if every:
            out.per_vertex_mm[k] = whole[k].per_vertex_mm()
    for key in ("without", "with"):
        out.bda[key] = {"vertex_rmse_mm": errors[f"bda_{key}"].rmse_mm(local["face"]),
                        "param_rmse": param_rmse(preds[f"bda_{key}"], flame[test_idx])}
    return out


# ----- presentation --------------------------------------------------------------------------------


def print_table(result: Evaluation, console=None) -> None:
    """The paper's Table 1 layout (rich) for each split, then the BDA ablation."""
    from rich.console import Console

    console = console or Console()
    for title, part in (("held-out subjects", result.subjects), ("held-out source", result.source)):
        if part is None:
            continue
        console.print(_methods_table(part, f"Mappers on {title} {part.test_subjects} of {', '.join(part.sources)} "
                                           f"({part.frames} frames); regions: vertex RMSE in mm"))
        console.print(_bda_table(part, f"BDA ablation on {title}: EPM on the headset stream (Meta's OVR -> ARKit)"))


def _methods_table(part: Split, title: str):
    from rich.table import Table

    table = Table(title=title)
    table.add_column("method")
    table.add_column("param RMSE", justify="right")
    table.add_column("vertex mm", justify="right")
    for r in REGIONS:
        table.add_column(r.replace("_and_", "+"), justify="right")
    best = {m: min(part.methods[k][m] for k in part.methods) for m in ("param_rmse", "vertex_rmse_mm")}
    for k, row in part.methods.items():
        cells = [f"{row[m]:.3f}" if row[m] != best[m] else f"[bold]{row[m]:.3f}[/]"
                 for m in ("param_rmse", "vertex_rmse_mm")]
        table.add_row(k, *cells, *(f"{row['regions'][r]:.3f}" for r in REGIONS))
    return table


def _bda_table(part: Split, title: str):
    from rich.table import Table

    bda = Table(title=title)
    bda.add_column("")
    bda.add_column("vertex mm", justify="right")
    bda.add_column("param RMSE", justify="right")
    for key in ("without", "with"):
        bda.add_row(f"{key} BDA", f"{part.bda[key]['vertex_rmse_mm']:.3f}", f"{part.bda[key]['param_rmse']:.3f}")
    return bda


def markdown_table(result: Evaluation) -> str:
    """The README's table: both splits, every method, the BDA ablation (what ``ofera mapping eval`` prints)."""
    head = "| split | method | param RMSE | vertex RMSE mm | " + " | ".join(r.replace("_and_", "+") for r in REGIONS)
    lines = [head + " |", "|" + "---|" * (4 + len(REGIONS))]
    for name, part in (("held-out subjects", result.subjects), ("held-out source", result.source)):
        if part is None:
            continue
        for k, row in part.methods.items():
            regions = " | ".join(f"{row['regions'][r]:.3f}" for r in REGIONS)
            lines.append(f"| {name} | {k} | {row['param_rmse']:.3f} | {row['vertex_rmse_mm']:.3f} | {regions} |")
        for key in ("without", "with"):
            b = part.bda[key]
            lines.append(f"| {name} | EPM on headset, {key} BDA | {b['param_rmse']:.3f} | {b['vertex_rmse_mm']:.3f} |"
                         + " |" * len(REGIONS))
    return "\n".join(lines)


def draw_heatmaps(result: Evaluation, model: HeadModel, out: str | Path,
                  views: tuple[float, ...] = (0.0, 40.0)) -> Path:
    """Per-vertex RMSE (mm) of each method on the neutral head, side by side, one colour scale."""
    import tempfile

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import colormaps
    from matplotlib.colors import Normalize

    from ...head.render import render_mesh

    methods = [k for k in METHODS if k in result.per_vertex_mm]
    if not methods:
        raise ValueError("no per-vertex errors to draw (evaluate with heatmap_frames > 0)")
    vmax = max(float(np.percentile(result.per_vertex_mm[k], 99.5)) for k in methods) or 1.0
    norm, cmap = Normalize(0.0, vmax), colormaps["YlOrRd"]
    images = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in methods:
            col = cmap(norm(result.per_vertex_mm[k]))[:, :3]
            png = render_mesh(model.v_template, model.faces, col, Path(tmp) / f"{k}.png", views=views, size_px=360)
            images.append(plt.imread(png))
    fig, axes = plt.subplots(1, len(methods), figsize=(4.0 * len(methods) * len(views) / 2 + 0.8, 2.6), dpi=150)
    for ax, k, img in zip(np.atleast_1d(axes), methods, images):
        ax.imshow(img)
        ax.set_title(f"{k}: {result.methods[k]['vertex_rmse_mm']:.3f} mm", fontsize=9)
        ax.axis("off")
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes, fraction=0.02, pad=0.01,
                 label="per-vertex RMSE (mm)")
    fig.suptitle(f"Per-vertex RMSE on held-out subjects {result.test_subjects} (neutral head; value: face RMSE)",
                 fontsize=10)
    out = Path(out)
    fig.savefig(out, bbox_inches="tight")
    plt.close(fig)
    return out
