"""Import real paired data: a per-frame blendshape CSV aligned with a FLAME tracker's output.

The blendshape CSV (what a camera estimator such as MediaPipe's FaceLandmarker wrote for each video
frame): one row per frame, columns by name: the 51 ARKit names in any order and any spelling that
``layouts.normalize_name`` matches (MediaPipe's ``_neutral`` and ARKit's ``tongueOut`` are accepted
and ignored), an optional frame column (``frame``, ``frame_index``, ``frame_number``, ``frame_id``;
without one, row i is frame i), other columns (time stamps) ignored, ``#`` comment lines skipped.

Tracker outputs, matched to the CSV by frame index:

- metrical-tracker (MICA): a folder of per-frame ``<id>.frame`` files (``torch.save`` of a dict; read
  with ``torch.load(weights_only=True)``, numpy arrays allowed): ``flame.exp`` (1, 100),
  ``flame.shape`` (1, 300), ``flame.jaw`` (1, 6) 6D, ``flame.eyes`` (1, 12) left 6D then right 6D;
- VHAP / GaussianAvatars / NeRSemble ``flame_param.npz`` (axis-angle): ``expr`` (T, 100),
  ``jaw_pose`` (T, 3), ``eyes_pose`` (T, 6) left then right, ``shape`` (300,); row i is frame i;
- INSTA: ``flame/exp/<id>.txt`` (100 values each), and where present ``flame/jaw/<id>.txt`` and
  ``flame/eyes/<id>.txt`` (6D: 6 / 12 values, or axis-angle: 3 / 6 values); without them the jaw and
  eyes are identity (the meta says so).

Expression is truncated to the first 50 coefficients; rotations become 6D in the pytorch3d rows
convention (``ofera.mapping.flame_values``). Every mismatch (a frame the other side lacks, a different
number of frames, a missing file or key, a wrong shape) raises :class:`PairedDataError` saying which.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ofera.head.rotations import axis_angle_to_matrix, rot6d_to_matrix
from ofera.mapping.flame_values import N_EXPR, join_flame_values
from ofera.mapping.layouts import ARKIT51_NAMES, normalize_name
from ofera.training.paired.data import SPLITS, PairedData, PairedDataError

FRAME_COLUMNS = ("frame", "frame_index", "frame_number", "frame_id")
_ARKIT_KEYS = {normalize_name(n): i for i, n in enumerate(ARKIT51_NAMES)}
_IGNORED_SHAPES = {normalize_name("_neutral"), normalize_name("tongueOut")}


# ----- the blendshape CSV ------------------------------------------------------------------------------


def read_blendshape_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Frame ids (N,) int64 and arkit51 weights (N, 51) float32 from a per-frame blendshape CSV."""
    path = Path(path)
    if not path.is_file():
        raise PairedDataError(f"{path}: no such blendshape CSV")
    with open(path, newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.reader(line for line in fh if line.strip() and not line.lstrip().startswith("#"))]
    if not rows:
        raise PairedDataError(f"{path}: empty CSV (expected a header with the 51 ARKit names)")
    header, body = rows[0], rows[1:]
    keys = [normalize_name(h) for h in header]
    column = {}
    for i, key in enumerate(keys):
        if key in _ARKIT_KEYS:
            if key in column:
                raise PairedDataError(f"{path}: column {header[i]!r} appears twice")
            column[key] = i
    missing = [n for n in ARKIT51_NAMES if normalize_name(n) not in column]
    if missing:
        shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
        raise PairedDataError(f"{path}: missing blendshape columns {shown} (need the 51 ARKit names, "
                              "MediaPipe or ARKit spelling)")
    frame_col = next((keys.index(c) for c in FRAME_COLUMNS if c in keys), None)
    order = [column[normalize_name(n)] for n in ARKIT51_NAMES]
    weights = np.empty((len(body), 51), np.float32)
    ids = np.arange(len(body), dtype=np.int64)
    for r, row in enumerate(body):
        if len(row) != len(header):
            raise PairedDataError(f"{path}: data row {r + 1} has {len(row)} fields, the header {len(header)}")
        try:
            weights[r] = [float(row[i]) for i in order]
            if frame_col is not None:
                ids[r] = int(float(row[frame_col]))
        except ValueError as exc:
            raise PairedDataError(f"{path}: data row {r + 1}: {exc}") from None
    if not np.all(np.isfinite(weights)):
        raise PairedDataError(f"{path}: blendshape values must be finite numbers")
    if len(np.unique(ids)) != len(ids):
        raise PairedDataError(f"{path}: frame ids repeat (each frame once)")
    return ids, weights


def _align(csv_ids: np.ndarray, tracker_ids: np.ndarray, what: str, csv_path: Path) -> np.ndarray:
    """Row of the tracker output for each CSV frame; every CSV frame must have one and vice versa."""
    lookup = {int(t): i for i, t in enumerate(tracker_ids)}
    lacking = [int(i) for i in csv_ids if int(i) not in lookup]
    extra = sorted(set(lookup) - {int(i) for i in csv_ids})
    if lacking or extra:
        parts = []
        if lacking:
            parts.append(f"{len(lacking)} CSV frames have no {what} (first: {lacking[:5]})")
        if extra:
            parts.append(f"{len(extra)} {what} frames are not in the CSV (first: {extra[:5]})")
        raise PairedDataError(f"{csv_path}: misaligned with {what}: CSV {len(csv_ids)} frames, {what} "
                              f"{len(tracker_ids)} frames; " + "; ".join(parts))
    return np.array([lookup[int(i)] for i in csv_ids], dtype=np.int64)


def _rotations(values: np.ndarray, joints: int, what: str) -> list[np.ndarray]:
    """(T, joints * 6) 6D or (T, joints * 3) axis-angle -> list of (T, 3, 3)."""
    t, n = values.shape
    if n == 6 * joints:
        return [rot6d_to_matrix(values[:, 6 * k:6 * k + 6].astype(np.float64)) for k in range(joints)]
    if n == 3 * joints:
        return [axis_angle_to_matrix(values[:, 3 * k:3 * k + 3].astype(np.float64)) for k in range(joints)]
    raise PairedDataError(f"{what}: {n} values per frame, expected {6 * joints} (6D) or {3 * joints} (axis-angle)")


def _flame(expr: np.ndarray, jaw: np.ndarray, eyes: np.ndarray, where: str) -> np.ndarray:
    expr = np.asarray(expr, np.float64)
    if expr.ndim != 2:
        raise PairedDataError(f"{where}: expression must be (T, n), got {expr.shape}")
    if expr.shape[1] < N_EXPR:
        expr = np.pad(expr, ((0, 0), (0, N_EXPR - expr.shape[1])))
    (jaw_r,) = _rotations(np.asarray(jaw).reshape(len(expr), -1), 1, f"{where} jaw")
    left, right = _rotations(np.asarray(eyes).reshape(len(expr), -1), 2, f"{where} eyes")
    return join_flame_values(expr[:, :N_EXPR], jaw_r, left, right)


def _paired(csv_path: Path, bs: np.ndarray, ids: np.ndarray, flame: np.ndarray, shape: np.ndarray | None,
            fps: float, subject: int, source: int, split: str, meta: dict) -> PairedData:
    if split not in SPLITS:
        raise PairedDataError(f"unknown split {split!r}; splits: {', '.join(SPLITS)}")
    n = len(bs)
    shape_rows = None
    if shape is not None:
        shape_rows = np.zeros((subject + 1, np.asarray(shape).size), np.float32)
        shape_rows[subject] = np.asarray(shape, np.float32).reshape(-1)
    return PairedData(bs=bs, flame=flame, subject=np.full(n, subject), source=np.full(n, source),
                      split=np.full(n, SPLITS.index(split)), frame=ids, fps=fps, shape=shape_rows,
                      meta={"blendshapes": str(csv_path), **meta})


def _frame_ids(paths: Sequence[Path], what: str) -> np.ndarray:
    ids = []
    for p in paths:
        m = re.search(r"(\d+)$", p.stem)
        if m is None:
            raise PairedDataError(f"{p}: {what} file name has no frame number")
        ids.append(int(m.group(1)))
    if len(set(ids)) != len(ids):
        raise PairedDataError(f"{what}: two files have the same frame number")
    return np.array(ids, dtype=np.int64)


# ----- metrical-tracker ----------------------------------------------------------------------------------


def _torch_load(path: Path) -> dict:
    try:
        import torch
    except ImportError:
        raise PairedDataError("reading metrical-tracker .frame files needs torch (pip install 'ofera[train]')") \
            from None
    from numpy._core.multiarray import _reconstruct  # how numpy arrays pickle

    allowed = [_reconstruct, (_reconstruct, "numpy.core.multiarray._reconstruct"), np.ndarray, np.dtype]
    allowed += [getattr(np.dtypes, n) for n in dir(np.dtypes) if n.endswith("DType")]
    try:
        with torch.serialization.safe_globals(allowed):
            data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for a bad or unsafe file
        raise PairedDataError(f"{path}: cannot read as a metrical-tracker frame (torch.load, weights only): "
                              f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if not isinstance(data, dict) or not isinstance(data.get("flame"), dict):
        raise PairedDataError(f"{path}: not a metrical-tracker frame (no 'flame' dict)")
    return data["flame"]


def _array(value) -> np.ndarray:
    if hasattr(value, "detach"):  # a torch tensor
        value = value.detach().cpu().numpy()
    return np.asarray(value, np.float64)


def _pick(flame: dict, names: tuple[str, ...], path: Path) -> np.ndarray:
    for name in names:
        if name in flame:
            return _array(flame[name]).reshape(-1)
    raise PairedDataError(f"{path}: flame has no {' or '.join(repr(n) for n in names)} "
                          f"(keys: {', '.join(sorted(flame))})")


def import_metrical_tracker(csv_path: str | Path, frames_dir: str | Path, fps: float = 30.0, subject: int = 0,
                            source: int = 0, split: str = "train") -> PairedData:
    """Blendshape CSV + a metrical-tracker folder of ``<id>.frame`` files -> :class:`PairedData`."""
    csv_path, frames_dir = Path(csv_path), Path(frames_dir)
    if not frames_dir.is_dir():
        raise PairedDataError(f"{frames_dir}: no such folder (metrical-tracker's per-frame .frame files)")
    files = sorted(frames_dir.glob("*.frame"))
    if not files:
        raise PairedDataError(f"{frames_dir}: no .frame files")
    ids, bs = read_blendshape_csv(csv_path)
    rows = _align(ids, _frame_ids(files, "metrical-tracker"), "metrical-tracker", csv_path)
    exprs, jaws, eyes, shape = [], [], [], None
    for r in rows:
        flame = _torch_load(files[r])
        exprs.append(_pick(flame, ("exp", "expr"), files[r]))
        jaws.append(_pick(flame, ("jaw", "jaw_pose"), files[r]))
        eyes.append(_pick(flame, ("eyes", "eyes_pose"), files[r]))
        if shape is None and "shape" in flame:
            shape = _array(flame["shape"]).reshape(-1)
    for what, values in (("exp", exprs), ("jaw", jaws), ("eyes", eyes)):
        if len({v.size for v in values}) > 1:
            raise PairedDataError(f"{frames_dir}: flame.{what} has different sizes in different frames")
    flame_values = _flame(np.stack(exprs), np.stack(jaws), np.stack(eyes), str(frames_dir))
    return _paired(csv_path, bs, ids, flame_values, shape, fps, subject, source, split,
                   {"importer": "metrical-tracker", "tracker": str(frames_dir)})


# ----- VHAP / GaussianAvatars ----------------------------------------------------------------------------


def import_vhap(csv_path: str | Path, npz_path: str | Path, fps: float = 30.0, subject: int = 0, source: int = 0,
                split: str = "train") -> PairedData:
    """Blendshape CSV + a VHAP/GaussianAvatars ``flame_param.npz`` (row i = frame i) -> :class:`PairedData`."""
    csv_path, npz_path = Path(csv_path), Path(npz_path)
    if not npz_path.is_file():
        raise PairedDataError(f"{npz_path}: no such file (VHAP/GaussianAvatars flame_param.npz)")
    try:
        with np.load(npz_path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise PairedDataError(f"{npz_path}: cannot read as npz: {exc}") from None
    missing = [k for k in ("expr", "jaw_pose", "eyes_pose") if k not in arrays]
    if missing:
        raise PairedDataError(f"{npz_path}: missing arrays {missing} (has: {', '.join(sorted(arrays))})")
    t = len(arrays["expr"])
    for key in ("jaw_pose", "eyes_pose"):
        if len(arrays[key]) != t:
            raise PairedDataError(f"{npz_path}: {key} has {len(arrays[key])} frames, expr {t}")
    ids, bs = read_blendshape_csv(csv_path)
    rows = _align(ids, np.arange(t), "flame_param.npz", csv_path)
    flame = _flame(arrays["expr"][rows], arrays["jaw_pose"][rows], arrays["eyes_pose"][rows], str(npz_path))
    return _paired(csv_path, bs, ids, flame, arrays.get("shape"), fps, subject, source, split,
                   {"importer": "vhap", "tracker": str(npz_path)})


# ----- INSTA -------------------------------------------------------------------------------------------


def _read_txt(path: Path) -> np.ndarray:
    try:
        return np.loadtxt(path, dtype=np.float64, ndmin=1).reshape(-1)
    except ValueError as exc:
        raise PairedDataError(f"{path}: not a list of numbers: {exc}") from None


def import_insta(csv_path: str | Path, root: str | Path, fps: float = 30.0, subject: int = 0, source: int = 0,
                 split: str = "train") -> PairedData:
    """Blendshape CSV + an INSTA data folder (``flame/exp/<id>.txt``) -> :class:`PairedData`."""
    csv_path, root = Path(csv_path), Path(root)
    exp_dir = root / "flame" / "exp"
    if not exp_dir.is_dir():
        raise PairedDataError(f"{root}: no flame/exp folder (INSTA's per-frame expression .txt files)")
    files = sorted(exp_dir.glob("*.txt"))
    if not files:
        raise PairedDataError(f"{exp_dir}: no .txt files")
    ids, bs = read_blendshape_csv(csv_path)
    frame_ids = _frame_ids(files, "INSTA exp")
    rows = _align(ids, frame_ids, "INSTA flame/exp", csv_path)
    exprs = [_read_txt(files[r]) for r in rows]
    if len({e.size for e in exprs}) > 1:
        raise PairedDataError(f"{exp_dir}: expression files hold different numbers of values")
    rotations, notes = {}, {}
    for part, joints in (("jaw", 1), ("eyes", 2)):
        folder = root / "flame" / part
        if folder.is_dir():
            paths = [folder / f.name for f in (files[r] for r in rows)]
            absent = [p.name for p in paths if not p.is_file()]
            if absent:
                raise PairedDataError(f"{folder}: missing {len(absent)} frames (first: {absent[:5]})")
            rotations[part] = np.stack([_read_txt(p) for p in paths])
        else:
            rotations[part] = np.tile(np.array([1.0, 0, 0, 0, 1.0, 0]), (len(rows), joints))
            notes[part] = f"identity (no flame/{part} folder)"
    flame = _flame(np.stack(exprs), rotations["jaw"], rotations["eyes"], str(root))
    return _paired(csv_path, bs, ids, flame, None, fps, subject, source, split,
                   {"importer": "insta", "tracker": str(root), **{f"{k}_rotation": v for k, v in notes.items()}})
