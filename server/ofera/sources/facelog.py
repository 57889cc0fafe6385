"""The common in-memory face log every reader returns, and the error readers raise."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ofera.mapping.layouts import Layout, to_arkit51

from ..errors import OferaError

DATA_SOURCES: tuple[str, ...] = ("visual", "audio")
"""Meta v2 data source codes: `FaceLog.data_source` holds indices into this tuple."""


class SourceFormatError(OferaError, ValueError):
    """A malformed input; the message names the file, the line or frame, and the problem."""

    def __init__(
        self, problem: str, path: str | Path | None = None, line: int | None = None, frame: int | None = None
    ) -> None:
        where = [str(path)] if path is not None else []
        if line is not None:
            where.append(f"line {line}")
        if frame is not None:
            where.append(f"frame {frame}")
        super().__init__(f"{', '.join(where)}: {problem}" if where else problem)
        self.path, self.line, self.frame, self.problem = path, line, frame, problem


@dataclass
class FaceLog:
    """A recorded blendshape stream.

    times: (T,) float64 seconds, non-decreasing, relative to the first frame (readers start at 0).
    weights: (T, K) float32 in `layout` order (Live Link's last nine values are radians).
    confidence: optional (T, C) float32; the face-log CSV carries C = 2 (lower face, upper face).
    data_source: optional (T,) uint8 indices into `DATA_SOURCES` (0 visual, 1 audio).
    source: human-readable description of where the frames came from.
    metadata: free-form key/value pairs (e.g. from `# key: value` comment lines, device id).
    """

    times: np.ndarray
    weights: np.ndarray
    layout: Layout
    confidence: np.ndarray | None = None
    data_source: np.ndarray | None = None
    source: str = ""
    metadata: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.times = np.asarray(self.times, dtype=np.float64)
        self.weights = np.asarray(self.weights, dtype=np.float32)
        t = len(self.times)
        if self.times.ndim != 1 or self.weights.shape != (t, self.layout.length):
            raise ValueError(
                f"times {self.times.shape} and weights {self.weights.shape} do not fit "
                f"T frames of layout {self.layout.name!r} (K={self.layout.length})"
            )
        if t and not np.all(np.diff(self.times) >= 0):
            raise ValueError("times must be non-decreasing")
        if self.confidence is not None:
            self.confidence = np.asarray(self.confidence, dtype=np.float32)
            if self.confidence.ndim != 2 or len(self.confidence) != t:
                raise ValueError(f"confidence must be (T={t}, C), got {self.confidence.shape}")
        if self.data_source is not None:
            self.data_source = np.asarray(self.data_source, dtype=np.uint8)
            if self.data_source.shape != (t,) or np.any(self.data_source >= len(DATA_SOURCES)):
                raise ValueError(f"data_source must be (T={t},) codes < {len(DATA_SOURCES)}")

    def __len__(self) -> int:
        return len(self.times)

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return float(self.times[-1] - self.times[0]) if len(self) else 0.0

    def to_arkit51(self) -> np.ndarray:
        """(T, 51) float32 arkit51 weights, clamped to [0, 1]."""
        return to_arkit51(self.layout, self.weights)
