"""BDA, Blendshape Distribution Alignment: an affine map ``y = clamp(W x + b, 0, 1)`` on arkit51.

A headset's blendshapes, after Meta's coarse OVR -> ARKit remapping, do not follow the distribution the
mapper was trained on (the iPhone / MediaPipe-style ARKit weights). BDA corrects that with one linear
map fitted by least squares on paired frames (headset arkit51, target arkit51), so that one EPM serves
every headset. W is (51, 51), b is (51,); frames are rows, so a batch maps as ``X @ W.T + b``.

numpy only (the run time imports this without torch). Files are ``.npz`` without pickles, holding the
layout names so that a BDA fitted on another order is refused instead of silently scrambling shapes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import OferaError
from .layouts import ARKIT51_NAMES, normalize_name

FORMAT = "ofera-bda"
FORMAT_VERSION = 1


class BDAError(OferaError, ValueError):
    """A BDA file or array set is invalid; the message says what and what to do."""


@dataclass(frozen=True)
class BDA:
    """An alignment ``clamp(x @ W.T + b, 0, 1)``; W (51, 51) float32, b (51,) float32."""

    W: np.ndarray
    b: np.ndarray
    names: tuple[str, ...] = ARKIT51_NAMES
    device: str = ""

    def __post_init__(self) -> None:
        w = np.ascontiguousarray(self.W, dtype=np.float32)
        b = np.ascontiguousarray(self.b, dtype=np.float32).reshape(-1)
        n = len(self.names)
        if w.shape != (n, n) or b.shape != (n,):
            raise BDAError(f"BDA W {w.shape} and b {b.shape} do not fit {n} names (expected ({n}, {n}) and ({n},))")
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(b))):
            raise BDAError("BDA W or b holds NaN or infinite values")
        w.setflags(write=False)
        b.setflags(write=False)
        object.__setattr__(self, "W", w)
        object.__setattr__(self, "b", b)
        object.__setattr__(self, "names", tuple(str(s) for s in self.names))

    # ----- construction ----------------------------------------------------------------------------

    @classmethod
    def identity(cls, names: Sequence[str] = ARKIT51_NAMES) -> BDA:
        """The default: no alignment (apply only clamps to [0, 1])."""
        n = len(names)
        return cls(np.eye(n, dtype=np.float32), np.zeros(n, np.float32), tuple(names), device="identity")

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray, ridge: float = 0.0, names: Sequence[str] = ARKIT51_NAMES,
            device: str = "") -> BDA:
        """Least-squares W, b with ``y ~ x @ W.T + b`` from paired frames x, y (T, 51).

        ``ridge`` >= 0 adds ``ridge * ||W - I||^2`` (shrinks towards the identity, never the bias), which
        keeps shapes that barely move in the data (zero columns of x) mapped to themselves.
        """
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        n = len(names)
        if x.ndim != 2 or x.shape != y.shape or x.shape[1] != n:
            raise BDAError(f"BDA fit needs x and y of the same shape (T, {n}), got {x.shape} and {y.shape}")
        if len(x) < 2:
            raise BDAError(f"BDA fit needs at least 2 paired frames, got {len(x)}")
        if ridge < 0:
            raise BDAError(f"ridge must be >= 0, got {ridge}")
        # Centre, then solve (Xc' Xc + r I) D = Xc' (Yc - Xc) for D = W' - I: the ridge pulls W to I.
        mx, my = x.mean(axis=0), y.mean(axis=0)
        xc, yc = x - mx, y - my
        gram = xc.T @ xc
        rhs = xc.T @ (yc - xc)
        scale = max(float(np.trace(gram)) / n, 1e-12)
        reg = ridge + 1e-10 * scale  # a tiny floor keeps rank-deficient data solvable (min-norm-like)
        d = np.linalg.solve(gram + reg * np.eye(n), rhs)
        w = (d + np.eye(n)).T
        b = my - mx @ w.T
        return cls(w, b, tuple(names), device=device)

    # ----- use -------------------------------------------------------------------------------------

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.W, np.eye(len(self.names), dtype=np.float32)) and not np.any(self.b))

    def apply(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(..., 51) -> (..., 51) float32 ``clamp(x @ W.T + b, 0, 1)``."""
        x = np.asarray(x, np.float32)
        if x.shape[-1] != len(self.names):
            raise BDAError(f"BDA expects (..., {len(self.names)}) weights, got {x.shape}")
        res = np.matmul(x, self.W.T, out=out)
        res += self.b
        np.maximum(res, np.float32(0.0), out=res)
        return np.minimum(res, np.float32(1.0), out=res)

    __call__ = apply

    def error(self, x: np.ndarray, y: np.ndarray) -> dict[str, float]:
        """RMSE and mean absolute error of ``apply(x)`` against y."""
        d = self.apply(x).astype(np.float64) - np.asarray(y, np.float64)
        return {"rmse": float(np.sqrt(np.mean(d * d))), "mae": float(np.mean(np.abs(d)))}

    # ----- files -----------------------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write an ``.npz`` (no pickles): W, b, the layout names, format and version."""
        path = Path(path)
        with open(path, "wb") as fh:
            np.savez(
                fh,
                format=np.array(FORMAT),
                format_version=np.array(FORMAT_VERSION),
                W=self.W,
                b=self.b,
                names=np.array(self.names),
                device=np.array(self.device),
            )
        return path

    @classmethod
    def load(cls, path: str | Path, names: Sequence[str] = ARKIT51_NAMES) -> BDA:
        """Read a file written by :meth:`save`; refuse one whose names are not ``names`` (arkit51)."""
        path = Path(path)
        if not path.is_file():
            raise BDAError(f"{path}: no such BDA file (fit one with `ofera bda fit PAIRS -o {path.name}`)")
        try:
            with np.load(path, allow_pickle=False) as z:
                if "format" not in z.files or str(z["format"]) != FORMAT:
                    raise BDAError(f"{path}: not a BDA file (no format = {FORMAT!r}); fit one with `ofera bda fit`")
                version = int(z["format_version"])
                if version > FORMAT_VERSION:
                    raise BDAError(f"{path}: BDA format version {version} is newer than {FORMAT_VERSION}")
                missing = [k for k in ("W", "b", "names") if k not in z.files]
                if missing:
                    raise BDAError(f"{path}: missing arrays {missing}")
                stored = tuple(str(s) for s in z["names"])
                w, b = z["W"], z["b"]
                device = str(z["device"]) if "device" in z.files else ""
        except (OSError, ValueError, KeyError) as exc:
            if isinstance(exc, BDAError):
                raise
            raise BDAError(f"{path}: cannot read BDA file: {exc}") from exc
        check_names(stored, names, what=str(path))
        return cls(w, b, tuple(names), device=device)


def check_names(stored: Sequence[str], expected: Sequence[str], what: str = "BDA") -> None:
    """Raise BDAError naming the first differences when ``stored`` is not ``expected`` (up to spelling)."""
    got = [normalize_name(s) for s in stored]
    want = [normalize_name(s) for s in expected]
    if got == want:
        return
    if len(got) != len(want):
        raise BDAError(f"{what}: holds {len(got)} blendshape names, expected {len(want)} (arkit51 order); "
                       "refit the BDA on arkit51 pairs")
    diffs = [f"#{i}: {s!r} (expected {e!r})" for i, (s, e, g, w) in
             enumerate(zip(stored, expected, got, want)) if g != w]
    raise BDAError(f"{what}: blendshape names differ from arkit51 at {len(diffs)} positions: "
                   f"{'; '.join(diffs[:4])}{' ...' if len(diffs) > 4 else ''}; refit the BDA on arkit51 pairs")


def load_bda(source: str | Path | BDA | None) -> BDA:
    """``None`` or ``"identity"`` -> identity; a BDA is returned as is; otherwise a path to an ``.npz``."""
    if source is None or (isinstance(source, str) and source in ("identity", "none", "")):
        return BDA.identity()
    if isinstance(source, BDA):
        return source
    return BDA.load(source)
