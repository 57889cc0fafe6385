"""Which parts of the head move with the face (expressions, jaw, eyes) and which only follow the head pose.

A vertex is movable when any of these is non-negligible (above ``tol``):
- its expression basis rows ``exprdirs[v]`` (metres per unit coefficient);
- its skinning weight on the jaw or an eye (joints 2, 3, 4);
- its pose correctives for those joints (``posedirs`` rows 9..35, metres per unit of (R - I)).
A Gaussian is movable when any vertex of its face is. With the head pose owned by the client (root and
neck identity), the non-movable Gaussians are the same in every frame: a streamer sends them once.
"""

from __future__ import annotations

import numpy as np

from ..head.model import HeadModel

FACE_JOINTS = (2, 3, 4)  # jaw, left eye, right eye
MOVABLE_TOLERANCE_M = 1e-7  # 0.1 micrometre per unit coefficient: far below anything visible


def movable_vertices(head: HeadModel, tol: float = MOVABLE_TOLERANCE_M) -> np.ndarray:
    """(V,) bool: vertices moved by expressions, the jaw/eye joints or their pose correctives."""
    v = head.num_vertices
    expr = np.abs(head.exprdirs).reshape(v, -1).max(axis=1, initial=0.0) > tol
    joints = head.weights[:, list(FACE_JOINTS)].max(axis=1) > 1e-6
    rows = np.concatenate([np.arange(9 * (j - 1), 9 * j) for j in FACE_JOINTS])
    pose = np.abs(head.posedirs[rows]).reshape(len(rows), v, 3).max(axis=(0, 2)) > tol
    return expr | joints | pose


def movable_gaussians(head: HeadModel, face: np.ndarray, tol: float = MOVABLE_TOLERANCE_M) -> np.ndarray:
    """(N,) bool for Gaussians bound to faces ``face`` (N,): any vertex of the face is movable."""
    moving_face = movable_vertices(head, tol)[head.faces].any(axis=1)
    return moving_face[np.asarray(face, np.int64)]
