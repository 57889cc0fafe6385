"""Client-side deformation of a params session (PROTOCOL.md 13): the rig received at the handshake + each frame's
68 FLAME values -> the Gaussians. By default the fast path (`rig_fast.FastRig`: numba, 1.5-2 ms for the built-in
avatar's rig); `reference=True` uses the protocol's reference (`ofera_protocol.rig.deform_rig`, float64 numpy, the
code the browser and C# clients port). A client library imports nothing of the server (tests/test_architecture.py).

    deformer = RigDeformer(client.conn.rig)
    position, rotation, scale = deformer.deform(frame.params)   # the rig's Gaussians, FLAME space
    deformer.apply(frame.params, gaussians, coords)             # into the client's state (rig.index rows)

tests/test_params_rig.py checks the reference against the server's own float32 frames, tests/test_params_fast.py
the fast path against the reference.
"""

from __future__ import annotations

import numpy as np
from ofera_protocol import GaussianState, to_coords
from ofera_protocol.fast_encodings import coord_signs
from ofera_protocol.rig import Rig, deform_rig

from .rig_fast import FastRig


class RigDeformer:
    """Deforms one rig's Gaussians from params frames (see the module docstring); not thread-safe (the fast path
    keeps scratch arrays)."""

    def __init__(self, rig: Rig, reference: bool = False) -> None:
        self.rig = rig
        self.index = rig.index.astype(np.int64)
        self.fast = None if reference else FastRig(rig)

    def deform(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """params (68,) float32 -> position (M, 3) m, rotation (M, 4) (x, y, z, w), scale (M, 3) m of the rig's
        Gaussians (session ids `rig.index`), float32, FLAME space."""
        params = np.asarray(params, np.float32).reshape(-1)
        return deform_rig(self.rig, params) if self.fast is None else self.fast.deform(params)

    def apply(self, params: np.ndarray, gaussians: GaussianState, coords: str) -> None:
        """Write the deformed Gaussians into `gaussians` (the session's, from the avatar message) in `coords` (the
        fast path writes them in place, no intermediate arrays)."""
        if self.fast is not None:
            psign, rsign = coord_signs(coords)
            self.fast.apply(params, gaussians.position, gaussians.rotation, gaussians.scale, psign, rsign)
            return
        position, rotation, scale = self.deform(params)
        position, rotation = to_coords(position, rotation, coords)
        gaussians.position[self.index] = position
        gaussians.rotation[self.index] = rotation
        gaussians.scale[self.index] = scale
