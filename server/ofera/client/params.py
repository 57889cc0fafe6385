"""Client-side deformation of a params session (PROTOCOL.md 13): the rig received at the handshake + each frame's
68 FLAME values -> the Gaussians, with the server's own reference code (`ofera.head.lbs`, `ofera.avatar.deform`).

    deformer = RigDeformer(client.conn.rig)
    position, rotation, scale = deformer.deform(frame.params)   # the rig's Gaussians, FLAME space
    deformer.apply(frame.params, gaussians, coords)             # into the client's state (rig.index rows)

The wire side (rig body, chunks, `ofera_protocol.rig.deform_rig`, the plain reference other clients port) lives in
the protocol package; this module rebuilds a head model and a binding from the rig, so that the Python client
deforms exactly as the server does (tests compare both with the server's float32 frames).
"""

from __future__ import annotations

import numpy as np
from ofera_protocol import GaussianState, to_coords
from ofera_protocol.rig import Rig

from ..avatar.binding import BarycentricBinding, TriangleBinding
from ..avatar.deform import Deformer, make_deformer
from ..head.lbs import HeadSubject, lbs
from ..head.model import FLAME_PARENTS, HeadModel
from ..mapping.flame_values import split_flame_values


def rig_head(rig: Rig) -> HeadSubject:
    """The rig's vertices as a head subject: template, expression basis, pose correctives (zero rows where the rig
    has none), skinning weights, and the rig's joints (J0, dJ/dpsi) instead of a joint regressor."""
    s, e = rig.vertices, rig.expr_dims
    exprdirs = np.ascontiguousarray(rig.expr_basis.astype(np.float64).transpose(0, 2, 1))  # (S, 3, E)
    posedirs = np.zeros((36, 3 * s))
    posedirs[rig.pose_rows.astype(np.int64)] = rig.pose_basis.astype(np.float64).transpose(1, 0, 2).reshape(-1, 3 * s)
    model = HeadModel(v_template=rig.template.astype(np.float64), shapedirs=np.zeros((s, 3, 0)), exprdirs=exprdirs,
                      posedirs=posedirs, j_regressor=np.zeros((5, s)), parents=FLAME_PARENTS.copy(),
                      weights=rig.weights.astype(np.float64), faces=rig.face.astype(np.int64), name="rig")
    return HeadSubject(model, model.v_template, rig.joints.astype(np.float64), rig.joints_expr.astype(np.float64),
                       np.ascontiguousarray(exprdirs.reshape(-1, e).T))


def rig_deformer(rig: Rig) -> Deformer:
    """The server's reference deformer for the rig's binding on the rig's faces."""
    face = rig.gaussian_face.astype(np.int64)
    rotation = rig.local_rotation.astype(np.float64)[:, [3, 0, 1, 2]]  # (x, y, z, w) -> (w, x, y, z)
    log_scale = np.log(rig.local_scale.astype(np.float64))
    if rig.binding == "triangle":
        binding = TriangleBinding(face, rig.local_position, rotation, log_scale)
    else:  # the rig's scale is relative to s_f already (canonical 1), its offset is k tanh(offset) (k 1)
        binding = BarycentricBinding(face, rig.bary, np.arctanh(rig.normal_offset.astype(np.float64)), rotation,
                                     log_scale, np.ones(rig.faces), normal_offset_scale=1.0)
    return make_deformer(binding, rig.face.astype(np.int64), rig.vertices)


class RigDeformer:
    """Deforms one rig's Gaussians from params frames (see the module docstring)."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.subject = rig_head(rig)
        self.deformer = rig_deformer(rig)
        self.index = rig.index.astype(np.int64)

    def deform(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """params (68,) float32 -> position (M, 3) m, rotation (M, 4) (x, y, z, w), scale (M, 3) m of the rig's
        Gaussians (session ids `rig.index`), float32, FLAME space."""
        expr, rotations = split_flame_values(np.asarray(params, np.float32).reshape(-1))
        verts = lbs(self.subject, expr[None, : self.rig.expr_dims], rotations[None])[0][0]
        state = self.deformer.deform(verts)
        return state.position, state.rotation, state.scale

    def apply(self, params: np.ndarray, gaussians: GaussianState, coords: str) -> None:
        """Write the deformed Gaussians into `gaussians` (the session's, from the avatar message) in `coords`."""
        position, rotation, scale = self.deform(params)
        position, rotation = to_coords(position, rotation, coords)
        gaussians.position[self.index] = position
        gaussians.rotation[self.index] = rotation
        gaussians.scale[self.index] = scale
