"""The per-frame output of an avatar: world-space Gaussian positions, rotations and scales."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ofera_protocol.fast_encodings import VaryingRows


@dataclass(frozen=True, eq=False)
class GaussianState:
    """World-space Gaussians of one frame (the Avatar contract's output).

    position (N, 3) float32 metres; rotation (N, 4) float32 unit quaternion in the WIRE order
    (x, y, z, w); scale (N, 3) float32 linear standard deviations in metres along the rotated axes.
    varying: None, or the rows that may differ between the states that carry the same object (outside them they
    hold the same values; the fast path's states: the Gaussians it deforms), so an encoder can re-encode only those.
    """

    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    varying: VaryingRows | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        n = self.position.shape[0]
        for name, arr, width in (("position", self.position, 3), ("rotation", self.rotation, 4),
                                 ("scale", self.scale, 3)):
            if arr.shape != (n, width):
                raise ValueError(f"GaussianState.{name} has shape {arr.shape}, expected ({n}, {width})")

    @property
    def count(self) -> int:
        return int(self.position.shape[0])

    def rotation_wxyz(self) -> np.ndarray:
        """(N, 4) the same quaternions in the code's (w, x, y, z) order."""
        return np.concatenate([self.rotation[:, 3:], self.rotation[:, :3]], axis=1)
