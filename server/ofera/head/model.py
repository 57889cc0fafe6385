"""The head model object: a FLAME-structured linear blend skinning model.

Shapes (V vertices, F faces, S identity and E expression components, K = 5 joints):

    v_template   (V, 3)      metres, neutral mean head
    shapedirs    (V, 3, S)   identity basis, metres per unit coefficient
    exprdirs     (V, 3, E)   expression basis, metres per unit coefficient
    posedirs     (36, 3V)    pose correctives: rows are the 4 non-root joints x 9 entries of (R - I)
    j_regressor  (K, V)      joint locations as weighted sums of vertices
    parents      (K,)        kinematic tree; -1 for the root
    weights      (V, K)      skinning weights, rows sum to 1
    faces        (F, 3)      triangle vertex indices, counter-clockwise seen from outside

Joints, in order: 0 root, 1 neck, 2 jaw, 3 left eye, 4 right eye (FLAME's order).
Axes are FLAME's: right-handed, y up, the face looks along +z.

``landmarks`` and ``vertex_labels`` are optional semantic extras (a procedural head has them; a FLAME
file does not): named points (3,) and named boolean vertex masks (V,).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import OferaError

JOINT_NAMES = ("root", "neck", "jaw", "left_eye", "right_eye")
FLAME_PARENTS = np.array([-1, 0, 1, 1, 1], dtype=np.int64)
FORMAT_VERSION = 1


class HeadModelError(OferaError, ValueError):
    """A head model file or array set is invalid; the message says what and where."""


@dataclass(frozen=True)
class HeadModel:
    v_template: np.ndarray
    shapedirs: np.ndarray
    exprdirs: np.ndarray
    posedirs: np.ndarray
    j_regressor: np.ndarray
    parents: np.ndarray
    weights: np.ndarray
    faces: np.ndarray
    name: str = "head"
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    vertex_labels: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        v = self.v_template.shape[0]
        k = self.parents.shape[0]
        expected = {
            "v_template": (self.v_template, (v, 3)),
            "shapedirs": (self.shapedirs, (v, 3, None)),
            "exprdirs": (self.exprdirs, (v, 3, None)),
            "posedirs": (self.posedirs, ((k - 1) * 9, 3 * v)),
            "j_regressor": (self.j_regressor, (k, v)),
            "weights": (self.weights, (v, k)),
            "faces": (self.faces, (None, 3)),
        }
        for key, (arr, shape) in expected.items():
            if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
                raise HeadModelError(f"{self.name}: {key} has shape {arr.shape}, expected {shape} (None = any)")
        if k != len(JOINT_NAMES):
            raise HeadModelError(f"{self.name}: {k} joints, expected {len(JOINT_NAMES)} ({', '.join(JOINT_NAMES)})")
        if self.parents[0] != -1 or np.any(self.parents[1:] < 0) or np.any(self.parents[1:] >= np.arange(1, k)):
            raise HeadModelError(f"{self.name}: parents {self.parents.tolist()} is not a tree rooted at joint 0")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= v):
            raise HeadModelError(f"{self.name}: faces index vertices outside 0..{v - 1}")
        for key, mask in self.vertex_labels.items():
            if mask.shape != (v,):
                raise HeadModelError(f"{self.name}: vertex label {key!r} has shape {mask.shape}, expected ({v},)")

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def shape_dims(self) -> int:
        return int(self.shapedirs.shape[2])

    @property
    def expr_dims(self) -> int:
        return int(self.exprdirs.shape[2])

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    def info(self) -> dict:
        """Summary for `ofera head info`."""
        lo, hi = self.v_template.min(axis=0), self.v_template.max(axis=0)
        return {
            "name": self.name,
            "vertices": self.num_vertices,
            "faces": self.num_faces,
            "shape_dims": self.shape_dims,
            "expr_dims": self.expr_dims,
            "joints": self.num_joints,
            "joint_names": list(JOINT_NAMES),
            "parents": self.parents.tolist(),
            "extent_m": (hi - lo).round(4).tolist(),
        }

    # ----- the project's own .npz format -----------------------------------------------------------

    def arrays(self) -> dict[str, np.ndarray]:
        """The model's arrays as the head format stores them (float32 bases, int64 parents, int32 faces,
        ``landmark/<name>``, ``label/<name>``); the avatar format embeds the same under ``head/``."""
        arrays = {
            "name": np.array(self.name),
            "v_template": self.v_template.astype(np.float32),
            "shapedirs": self.shapedirs.astype(np.float32),
            "exprdirs": self.exprdirs.astype(np.float32),
            "posedirs": self.posedirs.astype(np.float32),
            "j_regressor": self.j_regressor.astype(np.float32),
            "parents": self.parents.astype(np.int64),
            "weights": self.weights.astype(np.float32),
            "faces": self.faces.astype(np.int32),
        }
        arrays |= {f"landmark/{k}": np.asarray(v, np.float32) for k, v in self.landmarks.items()}
        arrays |= {f"label/{k}": np.asarray(v, bool) for k, v in self.vertex_labels.items()}
        return arrays

    def save(self, path: str | Path) -> None:
        """Write the project's head format: one uncompressed .npz, no pickles."""
        arrays = {"format": np.array("ofera-head"), "format_version": np.array(FORMAT_VERSION)} | self.arrays()
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)

    @classmethod
    def load_npz(cls, path: str | Path) -> HeadModel:
        """Read a file written by :meth:`save` (``allow_pickle=False``: nothing in it can run code)."""
        try:
            with np.load(path, allow_pickle=False) as z:
                if "format" not in z.files or str(z["format"]) != "ofera-head":
                    raise HeadModelError(f"{path}: not an OFERA head file (no 'format' = 'ofera-head')")
                version = int(z["format_version"])
                if version > FORMAT_VERSION:
                    raise HeadModelError(f"{path}: head format version {version} is newer than {FORMAT_VERSION}")
                req = ["v_template", "shapedirs", "exprdirs", "posedirs", "j_regressor", "parents", "weights", "faces"]
                missing = [k for k in req if k not in z.files]
                if missing:
                    raise HeadModelError(f"{path}: missing arrays {missing}")
                return cls(
                    **{k: z[k] for k in req},
                    name=str(z["name"]),
                    landmarks={k[9:]: z[k] for k in z.files if k.startswith("landmark/")},
                    vertex_labels={k[6:]: z[k] for k in z.files if k.startswith("label/")},
                )
        except (OSError, ValueError, KeyError) as exc:
            if isinstance(exc, HeadModelError):
                raise
            raise HeadModelError(f"{path}: cannot read head model: {exc}") from exc
