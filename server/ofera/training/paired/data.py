"""``PairedData``: blendshapes paired with FLAME values, frame by frame (the EPM's training data).

One ``.npz`` file, no pickles (``allow_pickle=False``). Arrays, T frames:

    bs           (T, 51) float32   observed arkit51 weights (camera-style estimates)
    flame        (T, 68) float32   ground-truth FLAME values [expr 50, jaw 6D, left eye 6D, right eye 6D]
    subject      (T,)    int32     subject id (row of ``shape``)
    source       (T,)    int32     capture set id (name in ``source_names``)
    split        (T,)    int8      0 train, 1 val, 2 test (``SPLITS``), subject-disjoint
    frame        (T,)    int32     frame index within the subject's sequence
    fps          scalar
    headset      (T, 63) float32   simulated OVR63 headset weights, optional (for BDA)
    rig_weights  (T, 51) float32   the clean true weights, optional (synthetic data only)
    fit_rms      (T,)    float32   metres, RMS of the FLAME fit to the frame's mesh, optional
    shape        (n_subjects, S) float32   identity coefficients per subject, optional
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ofera.mapping.flame_values import FLAME_VALUES

from ...errors import OferaError

SPLITS: tuple[str, ...] = ("train", "val", "test")
FORMAT = "ofera-paired"
FORMAT_VERSION = 1


class PairedDataError(OferaError, ValueError):
    """Paired data that is inconsistent, or a file that cannot be read; the message says what."""


_REQUIRED = ("bs", "flame", "subject", "source", "split", "frame")
_OPTIONAL = ("headset", "rig_weights", "fit_rms", "shape")
_DTYPES = {"bs": np.float32, "flame": np.float32, "subject": np.int32, "source": np.int32, "split": np.int8,
           "frame": np.int32, "headset": np.float32, "rig_weights": np.float32, "fit_rms": np.float32,
           "shape": np.float32}
_WIDTH = {"bs": 51, "flame": FLAME_VALUES, "headset": 63, "rig_weights": 51}


@dataclass
class PairedData:
    bs: np.ndarray
    flame: np.ndarray
    subject: np.ndarray
    source: np.ndarray
    split: np.ndarray
    frame: np.ndarray
    fps: float = 30.0
    headset: np.ndarray | None = None
    rig_weights: np.ndarray | None = None
    fit_rms: np.ndarray | None = None
    shape: np.ndarray | None = None
    source_names: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for key in _REQUIRED + _OPTIONAL:
            value = getattr(self, key)
            if value is not None:
                setattr(self, key, np.ascontiguousarray(value, dtype=_DTYPES[key]))
        t = len(self.bs)
        for key in _REQUIRED + _OPTIONAL[:-1]:
            value = getattr(self, key)
            if value is None:
                continue
            want = (t, _WIDTH[key]) if key in _WIDTH else (t,)
            if value.shape != want:
                raise PairedDataError(f"paired data: {key} has shape {value.shape}, expected {want}")
        if t and (self.split.min() < 0 or self.split.max() >= len(SPLITS)):
            raise PairedDataError(f"paired data: split codes must be 0..{len(SPLITS) - 1} ({', '.join(SPLITS)})")
        if self.shape is not None:
            if self.shape.ndim != 2:
                raise PairedDataError(f"paired data: shape must be (n_subjects, S), got {self.shape.shape}")
            if t and self.subject.max() >= len(self.shape):
                raise PairedDataError(f"paired data: subject id {self.subject.max()} has no row in shape "
                                      f"({len(self.shape)} rows)")
        self.fps = float(self.fps)
        self.source_names = tuple(str(s) for s in self.source_names)
        if t and self.source_names and self.source.max() >= len(self.source_names):
            raise PairedDataError(f"paired data: source id {self.source.max()} has no name ({self.source_names})")

    # --- views ---------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.bs)

    @property
    def split_names(self) -> np.ndarray:
        """(T,) str: the split of each frame by name."""
        return np.asarray(SPLITS)[self.split]

    def split_mask(self, name: str) -> np.ndarray:
        if name not in SPLITS:
            raise PairedDataError(f"unknown split {name!r}; splits: {', '.join(SPLITS)}")
        return self.split == SPLITS.index(name)

    def select(self, mask: np.ndarray) -> PairedData:
        """Frames where ``mask`` (bool (T,) or indices) holds; ``shape`` rows are kept (ids stay valid)."""
        per_frame = {k: getattr(self, k)[mask] for k in _REQUIRED + _OPTIONAL[:-1] if getattr(self, k) is not None}
        return replace(self, **per_frame)

    def subset(self, split: str) -> PairedData:
        """The frames of one split (``train``, ``val`` or ``test``)."""
        return self.select(self.split_mask(split))

    @property
    def subjects(self) -> np.ndarray:
        return np.unique(self.subject)

    def summary(self) -> dict:
        out = {"frames": len(self), "fps": self.fps, "subjects": int(len(self.subjects)),
               "sources": list(self.source_names) or sorted(set(self.source.tolist()))}
        for name in SPLITS:
            m = self.split_mask(name)
            out[name] = {"frames": int(m.sum()), "subjects": sorted(set(self.subject[m].tolist()))}
        if self.fit_rms is not None and len(self):
            out["fit_rms_mm"] = {"mean": float(self.fit_rms.mean() * 1e3), "p95": float(np.percentile(self.fit_rms,
                                                                                                      95) * 1e3)}
        return out

    # --- file -------------------------------------------------------------------------------------

    def save(self, path: str | Path) -> None:
        """Write one uncompressed ``.npz`` (no object arrays, so it loads without pickle)."""
        arrays = {"format": np.array(FORMAT), "format_version": np.array(FORMAT_VERSION), "fps": np.array(self.fps),
                  "split_names": np.array(SPLITS), "source_names": np.array(self.source_names, dtype=str),
                  "meta": np.array(json.dumps(self.meta))}
        for key in _REQUIRED + _OPTIONAL:
            value = getattr(self, key)
            if value is not None:
                arrays[key] = value
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> PairedData:
        path = Path(path)
        if not path.is_file():
            raise PairedDataError(f"{path}: no such paired-data file")
        try:
            with np.load(path, allow_pickle=False) as z:
                if "format" not in z.files or str(z["format"]) != FORMAT:
                    raise PairedDataError(f"{path}: not an OFERA paired-data file (no 'format' = '{FORMAT}')")
                if int(z["format_version"]) > FORMAT_VERSION:
                    raise PairedDataError(f"{path}: paired-data version {int(z['format_version'])} is newer than "
                                          f"{FORMAT_VERSION}; update ofera")
                missing = [k for k in _REQUIRED if k not in z.files]
                if missing:
                    raise PairedDataError(f"{path}: missing arrays {missing}")
                if "split_names" in z.files and tuple(z["split_names"].tolist()) != SPLITS:
                    raise PairedDataError(f"{path}: split names {z['split_names'].tolist()} are not {SPLITS}")
                kwargs = {k: z[k] for k in _REQUIRED + _OPTIONAL if k in z.files}
                return cls(**kwargs, fps=float(z["fps"]), source_names=tuple(z["source_names"].tolist()),
                           meta=json.loads(str(z["meta"])) if "meta" in z.files else {})
        except PairedDataError:
            raise
        except (OSError, ValueError, KeyError) as exc:
            raise PairedDataError(f"{path}: cannot read paired data: {exc}") from exc


def concat(parts: Sequence[PairedData]) -> PairedData:
    """Concatenate paired data with the same fps; subject ids and shapes are offset to stay distinct."""
    if not parts:
        raise PairedDataError("nothing to concatenate")
    fps = {p.fps for p in parts}
    if len(fps) > 1:
        raise PairedDataError(f"cannot concatenate paired data of different frame rates {sorted(fps)}")
    out: dict = {}
    offset, shapes = 0, []
    subjects = []
    for p in parts:
        subjects.append(p.subject + offset)
        n = (int(p.subject.max()) + 1) if len(p) else 0
        if p.shape is not None:
            n = max(n, len(p.shape))
            shapes.append(p.shape)
        offset += n
    out["subject"] = np.concatenate(subjects)
    for key in _REQUIRED + _OPTIONAL[:-1]:
        if key == "subject":
            continue
        values = [getattr(p, key) for p in parts]
        if all(v is not None for v in values):
            out[key] = np.concatenate(values)
        elif key not in _REQUIRED:
            out[key] = None
    if shapes and len(shapes) == len(parts):
        width = max(s.shape[1] for s in shapes)
        out["shape"] = np.concatenate([np.pad(s, ((0, 0), (0, width - s.shape[1]))) for s in shapes])
    names = [p.source_names for p in parts]
    return PairedData(**out, fps=fps.pop(), source_names=names[0] if all(n == names[0] for n in names) else (),
                      meta={"concatenated": len(parts)})


__all__ = ["SPLITS", "PairedData", "PairedDataError", "concat"]
