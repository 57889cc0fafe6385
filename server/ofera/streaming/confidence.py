"""Hold a face region's last confident expression while the tracker's confidence in it is low.

`bs.conf` (PROTOCOL.md 4.2) carries Meta's two face confidences, [lower face, upper face] in [0, 1].
Regions follow Meta's definition (OpenXR XrFaceConfidence2FB): the upper face is everything above the
upper lip, eyes and eyebrows; the lower face everything below the eyes, mouth and chin; cheeks and nose
belong to both. In arkit51 terms (after the layout adapter, so every layout is treated alike):

- upper: the 14 `eye*` and the 5 `brow*` shapes;
- lower: the 4 `jaw*` and the 23 `mouth*` shapes;
- both:  `cheekPuff`, `cheekSquintLeft/Right`, `noseSneerLeft/Right` (held while either region is low).

A region whose confidence is below the threshold gets the values it had in the last sample where it was
confident (neutral 0 before the first one); a region at or above the threshold passes through and refreshes
that memory. The comparison is in float32, the wire's precision, so that `conf` equal to the threshold
(e.g. 0.7 sent as float32 0.69999999) counts as at the threshold.
"""

from __future__ import annotations

import numpy as np

from ..mapping.layouts import ARKIT51_NAMES

_PREFIXES_UPPER = ("eye", "brow")
_PREFIXES_LOWER = ("jaw", "mouth")
_PREFIXES_BOTH = ("cheek", "nose")


def _mask(prefixes: tuple[str, ...]) -> np.ndarray:
    return np.array([n.startswith(prefixes) for n in ARKIT51_NAMES], dtype=bool)


UPPER_FACE = _mask(_PREFIXES_UPPER)
"""(51,) bool: arkit51 shapes of the upper face only (eyes, brows)."""
LOWER_FACE = _mask(_PREFIXES_LOWER)
"""(51,) bool: arkit51 shapes of the lower face only (jaw, mouth)."""
BOTH_REGIONS = _mask(_PREFIXES_BOTH)
"""(51,) bool: arkit51 shapes in both regions (cheeks, nose)."""

DEFAULT_THRESHOLD = 0.5
"""Confidence below which a region is held (the server's `confidence_threshold` default)."""


class RegionHold:
    """Per-session memory of the last confident arkit51 values of each region.

    Call the instance (``region_hold(x, conf)``, i.e. ``__call__``): it edits `x` (51,) float32 in place and
    returns it; `conf` (2,) [lower, upper] in [0, 1], or None (full confidence). `threshold` 0 passes
    everything through. `held` counts the samples in which some region was held.
    """

    def __init__(self, threshold: float = DEFAULT_THRESHOLD) -> None:
        if not 0.0 <= threshold <= 1.0:
            raise ValueError(f"confidence threshold must be in [0, 1], got {threshold}")
        self.threshold = float(threshold)
        self._threshold32 = np.float32(threshold)
        self.last = np.zeros(len(ARKIT51_NAMES), np.float32)
        self.held = 0

    def __call__(self, x: np.ndarray, conf: np.ndarray | None) -> np.ndarray:
        """Hold the regions of `x` whose confidence in `conf` is below the threshold (see the class)."""
        if conf is None or self.threshold <= 0.0:
            self.last[:] = x
            return x
        c = np.asarray(conf, np.float32)
        low_lower = bool(c[0] < self._threshold32)
        low_upper = bool(c[1] < self._threshold32)
        if not (low_lower or low_upper):
            self.last[:] = x
            return x
        stale = BOTH_REGIONS.copy()
        if low_lower:
            stale |= LOWER_FACE
        if low_upper:
            stale |= UPPER_FACE
        x[stale] = self.last[stale]
        self.last[~stale] = x[~stale]
        self.held += 1
        return x
