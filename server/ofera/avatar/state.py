"""The per-frame output of an avatar: world-space Gaussian positions, rotations and scales."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class GaussianState:
    """World-space Gaussians of one frame (the Avatar contract's output).

    position (N, 3) float32 metres; rotation (N, 4) float32 unit quaternion in the WIRE order
    (x, y, z, w); scale (N, 3) float32 linear standard deviations in metres along the rotated axes.
    """

    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray

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
