"""Per-face frames of a triangle mesh (GaussianAvatars' ``compute_face_orientation``).

For face f with vertices v0, v1, v2 (in the mesh's winding order)::

    a0 = normalize(v1 - v0)
    a1 = normalize(cross(a0, v2 - v0))          # the face normal (outward for counter-clockwise faces)
    a2 = -normalize(cross(a1, a0)) = a0 x a1    # in the face plane
    R_f = [a0 | a1 | a2]                        # COLUMNS; orthonormal, det +1
    s_f = (|v1 - v0| + |a2 . (v2 - v0)|) / 2    # one isotropic scale, metres
    c_f = (v0 + v1 + v2) / 3                    # centroid
    n_f = cross(v1 - v0, v2 - v0)               # FATE's unnormalised normal (length = 2 * area)

Every function works on any float dtype and broadcasts over the face axis only.
"""

from __future__ import annotations

import numpy as np

_EPS2 = 1e-20  # clamp on squared lengths, as upstream (avoids division by zero on degenerate faces)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(np.maximum(np.sum(v * v, axis=-1, keepdims=True), _EPS2))


def face_corners(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corner positions v0, v1, v2, each (F, 3), of ``faces`` (F, 3) indexing ``vertices`` (V, 3)."""
    return vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]


def face_frames(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation R_f (F, 3, 3) with columns (a0, a1, a2), scale s_f (F,) metres, centroid c_f (F, 3)."""
    v0, v1, v2 = face_corners(vertices, faces)
    e1, e2 = v1 - v0, v2 - v0
    a0 = _normalize(e1)
    a1 = _normalize(np.cross(a0, e2))
    a2 = -_normalize(np.cross(a1, a0))
    rot = np.stack([a0, a1, a2], axis=-1)
    scale = (np.sqrt(np.maximum(np.sum(e1 * e1, axis=-1), _EPS2)) + np.abs(np.sum(a2 * e2, axis=-1))) / 2
    return rot, scale, (v0 + v1 + v2) / 3.0


def face_scales(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Only s_f (F,), e.g. FATE's ``face_scaling_canonical`` of a neutral mesh."""
    return face_frames(vertices, faces)[1]


def face_normals_unnormalised(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """n_f = cross(v1 - v0, v2 - v0) (F, 3): FATE's offset direction, length twice the face area (m^2)."""
    v0, v1, v2 = face_corners(vertices, faces)
    return np.cross(v1 - v0, v2 - v0)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas (F,) in m^2."""
    return 0.5 * np.linalg.norm(face_normals_unnormalised(vertices, faces), axis=-1)
