"""An avatar's rig for expression streaming (PROTOCOL.md 13): what a params-session client needs to deform the
avatar's movable Gaussians exactly as the server does, built from the server's own deformation data.

    rig = build_rig(avatar, subject, rows, ids)   # rows: avatar Gaussians, ids: their session ids

The rig holds, for the vertices of the faces those Gaussians are bound to: the subject's template (identity baked
in), the first 50 expression directions, the pose correctives of the jaw and the eyes (neck rows are left out: the
neck is the identity in FLAME values, the client owns head pose), the skinning weights; the joints and their motion
per expression coefficient (J = J_regressor (T + E psi) = J0 + dJ psi); and each Gaussian's binding.
"""

from __future__ import annotations

import numpy as np
from ofera_protocol.rig import Rig

from ..errors import OferaError
from ..head.lbs import HeadSubject
from .binding import BarycentricBinding, TriangleBinding, normalize_quaternions
from .model import GaussianAvatar

RIG_EXPR = 50
"""Expression components a rig carries: the 50 of FLAME values."""
NECK_ROWS = 9
"""Pose-feature entries 0..8 belong to the neck, always the identity in FLAME values (zero coefficients)."""


class RigError(OferaError, ValueError):
    """The avatar cannot be streamed as a rig (the message says why)."""


def build_rig(avatar: GaussianAvatar, subject: HeadSubject, rows: np.ndarray, ids: np.ndarray, count: int) -> Rig:
    """The rig of avatar Gaussians `rows` (M,) int, known to the client as session ids `ids` (M,) ascending, in a
    session of `count` Gaussians. FLAME space; f16 arrays as PROTOCOL.md 13.3 says."""
    if avatar.expression != "flame68":
        raise RigError(f"params needs a FLAME-driven avatar (expression flame68); {avatar.name!r} is driven by "
                       f"{avatar.expression} weights: ask for f32, f16 or q13")
    binding = avatar.binding
    if not isinstance(binding, (TriangleBinding, BarycentricBinding)):
        raise RigError(f"params needs triangle or barycentric Gaussians; {avatar.name!r} is {binding.kind}-bound")
    head = avatar.head
    rows = np.asarray(rows, np.int64)
    used_faces, gaussian_face = np.unique(np.asarray(binding.face, np.int64)[rows], return_inverse=True)
    vids, face = np.unique(np.asarray(head.faces, np.int64)[used_faces], return_inverse=True)
    e = min(RIG_EXPR, head.expr_dims)
    pose = np.asarray(head.posedirs, np.float64).reshape(-1, head.num_vertices, 3)[:, vids]  # (36, S, 3)
    used = np.abs(pose).reshape(pose.shape[0], -1).max(axis=1, initial=0.0) > 0
    used[:NECK_ROWS] = False
    pose_rows = np.flatnonzero(used)
    quat = normalize_quaternions(binding.rotation[rows])[:, [1, 2, 3, 0]]  # (w, x, y, z) -> (x, y, z, w)
    log_scale = binding.log_scale[rows].astype(np.float64)
    extra: dict[str, np.ndarray] = {}
    if isinstance(binding, TriangleBinding):
        extra["local_position"] = binding.position[rows].astype(np.float32)
        local_scale = np.exp(log_scale)
        kind = "triangle"
    else:
        extra["bary"] = binding.bary[rows].astype(np.float32)
        extra["normal_offset"] = (binding.normal_offset_scale * np.tanh(binding.offset[rows].astype(np.float64))
                                  ).astype(np.float32)
        canonical = binding.face_scale_canonical.astype(np.float64)[np.asarray(binding.face, np.int64)[rows]]
        local_scale = np.exp(log_scale) / canonical[:, None]
        kind = "barycentric"
    return Rig(
        binding=kind, count=int(count), index=np.asarray(ids, np.uint32),
        joints=subject.j_id.astype(np.float32), joints_expr=np.ascontiguousarray(subject.j_expr[:, :, :e], np.float32),
        template=subject.v_id[vids].astype(np.float32),
        expr_basis=np.ascontiguousarray(np.asarray(head.exprdirs)[vids, :, :e].transpose(0, 2, 1), np.float32),
        pose_rows=pose_rows.astype(np.uint8),
        pose_basis=np.ascontiguousarray(pose[pose_rows].transpose(1, 0, 2), np.float16),
        weights=np.asarray(head.weights, np.float32)[vids], face=face.reshape(-1, 3).astype(np.uint32),
        gaussian_face=gaussian_face.reshape(-1).astype(np.uint32), local_rotation=quat.astype(np.float16),
        local_scale=local_scale.astype(np.float16), **extra)
