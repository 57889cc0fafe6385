"""The paper's baselines for the EPM: a fixed matrix mapping and ridge regression (numpy only).

Matrix mapping: ``v = x @ M + m0`` with M (51, 103) in EMAGE's layout, 51 ARKit weights -> 100 FLAME
expression coefficients and 3 jaw axis-angle values (radians). Any such matrix loads (a user's EMAGE
matrix); the project builds its own from per-shape correspondences, without fitting to paired frames
(see :func:`correspondence_matrix`). FLAME values are then ``[expr[:50], 6D(jaw), 6D(I), 6D(I)]``:
a fixed matrix knows nothing of gaze, so the eyes stay straight.

Ridge regression: ``y = x @ A + c`` for all 68 FLAME values, in closed form, alpha chosen from a grid
by parameter RMSE (expression + jaw) on the validation subjects.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import OferaError
from ..head.rotations import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_rot6d, rot6d_to_matrix

N_IN = 51
N_OUT = 68
N_EXPR = 50
EMAGE_EXPR = 100
EMAGE_WIDTH = EMAGE_EXPR + 3
IDENTITY_6D = np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], np.float32)
PARAM_DIMS = slice(0, N_EXPR + 6)
"""Expression and jaw 6D: the values the parameter RMSE is taken over (eyes excluded, as the paper)."""


class BaselineError(OferaError, ValueError):
    """A baseline matrix or fit input is invalid; the message says what and what to do."""


def param_rmse(pred: np.ndarray, target: np.ndarray) -> float:
    """RMSE over expression and jaw 6D (the first 56 FLAME values), eyes excluded."""
    d = np.asarray(pred, np.float64)[:, PARAM_DIMS] - np.asarray(target, np.float64)[:, PARAM_DIMS]
    return float(np.sqrt(np.mean(d * d)))


def flame_values_from_emage(v: np.ndarray) -> np.ndarray:
    """(T, 103) [expr 100, jaw axis-angle 3] -> (T, 68) FLAME values (expr cut to 50, eyes identity)."""
    v = np.asarray(v, np.float64)
    out = np.empty((len(v), N_OUT), np.float32)
    out[:, :N_EXPR] = v[:, :N_EXPR]
    out[:, N_EXPR:N_EXPR + 6] = matrix_to_rot6d(axis_angle_to_matrix(v[:, EMAGE_EXPR:EMAGE_WIDTH]))
    out[:, N_EXPR + 6:N_EXPR + 12] = IDENTITY_6D
    out[:, N_EXPR + 12:] = IDENTITY_6D
    return out


def emage_from_flame_values(y: np.ndarray) -> np.ndarray:
    """(T, 68) FLAME values -> (T, 103) [expr padded to 100 with zeros, jaw axis-angle]."""
    y = np.asarray(y, np.float64)
    out = np.zeros((len(y), EMAGE_WIDTH))
    out[:, :N_EXPR] = y[:, :N_EXPR]
    out[:, EMAGE_EXPR:] = matrix_to_axis_angle(rot6d_to_matrix(y[:, N_EXPR:N_EXPR + 6]))
    return out


@dataclass(frozen=True)
class MatrixMapper:
    """Fixed linear map in EMAGE's layout: ``v (T, 103) = x (T, 51) @ matrix + offset``."""

    matrix: np.ndarray  # (51, 103)
    offset: np.ndarray | None = None  # (103,); None: zeros (a neutral face maps to zeros)
    name: str = "matrix"

    def __post_init__(self) -> None:
        m = np.asarray(self.matrix, np.float64)
        if m.shape == (EMAGE_WIDTH, N_IN):
            m = m.T
        if m.shape != (N_IN, EMAGE_WIDTH):
            raise BaselineError(f"a mapping matrix must be ({N_IN}, {EMAGE_WIDTH}) (ARKit -> 100 expr + 3 jaw "
                                f"axis-angle) or its transpose, got {m.shape}")
        object.__setattr__(self, "matrix", m)
        off = np.zeros(EMAGE_WIDTH) if self.offset is None else np.asarray(self.offset, np.float64).reshape(-1)
        if off.shape != (EMAGE_WIDTH,):
            raise BaselineError(f"matrix offset must hold {EMAGE_WIDTH} values, got {off.shape}")
        object.__setattr__(self, "offset", off)

    def predict(self, x: np.ndarray) -> np.ndarray:
        """(T, 51) arkit51 -> (T, 68) FLAME values."""
        return flame_values_from_emage(np.asarray(x, np.float64) @ self.matrix + self.offset)

    __call__ = predict

    def save(self, path: str | Path) -> Path:
        """``.npy`` (the bare 51 x 103 matrix) or ``.npz`` (matrix and offset)."""
        path = Path(path)
        if path.suffix == ".npy":
            np.save(path, self.matrix)
        else:
            with open(path, "wb") as fh:
                np.savez(fh, matrix=self.matrix, offset=self.offset)
        return path

    @classmethod
    def load(cls, path: str | Path) -> MatrixMapper:
        """A 51 x 103 matrix from ``.npy``, ``.npz`` (key ``matrix``, optional ``offset``) or text/CSV."""
        path = Path(path)
        if not path.is_file():
            raise BaselineError(f"{path}: no such matrix file")
        try:
            if path.suffix == ".npy":
                return cls(np.load(path, allow_pickle=False), name=path.stem)
            if path.suffix == ".npz":
                with np.load(path, allow_pickle=False) as z:
                    key = "matrix" if "matrix" in z.files else z.files[0]
                    return cls(z[key], z["offset"] if "offset" in z.files else None, name=path.stem)
            return cls(np.loadtxt(path, delimiter="," if path.suffix == ".csv" else None, ndmin=2), name=path.stem)
        except (OSError, ValueError) as exc:
            if isinstance(exc, BaselineError):
                raise
            raise BaselineError(f"{path}: cannot read a mapping matrix: {exc}") from exc


def correspondence_matrix(
    shape_values: Callable[[int], np.ndarray] | np.ndarray,
    neutral: np.ndarray | None = None,
) -> MatrixMapper:
    """The project's own matrix from per-shape correspondences (no paired frames involved).

    ``shape_values``: (51, 68) FLAME values of the head fitted to each ARKit shape alone at weight 1
    (or a callable i -> (68,)); ``neutral``: the FLAME values of the neutral face (default: zero
    expression, identity rotations). Row i of the matrix is shape i's values minus the neutral's, in
    EMAGE's layout (jaw as axis-angle), so ``x @ M`` adds the shapes' displacements linearly.
    """
    if callable(shape_values):
        rows = np.stack([np.asarray(shape_values(i), np.float64) for i in range(N_IN)])
    else:
        rows = np.asarray(shape_values, np.float64)
    if rows.shape != (N_IN, N_OUT):
        raise BaselineError(f"per-shape FLAME values must be ({N_IN}, {N_OUT}), got {rows.shape}")
    base = np.zeros(N_OUT) if neutral is None else np.asarray(neutral, np.float64)
    if neutral is None:
        base[N_EXPR:] = np.tile(IDENTITY_6D, 3)
    m = emage_from_flame_values(rows) - emage_from_flame_values(base[None])
    return MatrixMapper(m, emage_from_flame_values(base[None])[0], name="correspondence")


@dataclass(frozen=True)
class RidgeMapper:
    """Ridge regression ``y = x @ A + c`` (A (51, 68)); ``alpha`` the chosen penalty."""

    A: np.ndarray
    c: np.ndarray
    alpha: float
    scores: tuple[tuple[float, float], ...] = ()  # (alpha, validation parameter RMSE) tried

    def predict(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, np.float64) @ self.A + self.c).astype(np.float32)

    __call__ = predict

    @staticmethod
    def solve(x: np.ndarray, y: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
        """Closed form on centred data: ``A = (Xc'Xc + alpha I)^-1 Xc'Yc``, ``c = my - mx A``."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        mx, my = x.mean(axis=0), y.mean(axis=0)
        xc = x - mx
        gram = xc.T @ xc
        a = np.linalg.solve(gram + max(alpha, 1e-10 * np.trace(gram) / len(gram)) * np.eye(len(gram)),
                            xc.T @ (y - my))
        return a, my - mx @ a

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray, x_val: np.ndarray, y_val: np.ndarray,
            alphas: Sequence[float] | None = None) -> RidgeMapper:
        """Fit on (x, y) for each alpha, keep the one with the lowest validation parameter RMSE."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if x.ndim != 2 or x.shape[1] != N_IN or y.shape != (len(x), N_OUT) or len(x) < 2:
            raise BaselineError(f"ridge needs x (T, {N_IN}) and y (T, {N_OUT}) with T >= 2, got {x.shape}, {y.shape}")
        if len(x_val) == 0:
            raise BaselineError("ridge needs validation frames to choose alpha")
        alphas = list(alphas) if alphas is not None else list(np.logspace(-4, 4, 17) * len(x) / 1000.0)
        scores, best = [], None
        for alpha in alphas:
            a, c = cls.solve(x, y, alpha)
            score = param_rmse(np.asarray(x_val) @ a + c, y_val)
            scores.append((float(alpha), score))
            if best is None or score < best[0]:
                best = (score, alpha, a, c)
        assert best is not None
        return cls(best[2], best[3], float(best[1]), tuple(scores))
