"""How Gaussians are attached to the head mesh: the bindings (triangle, barycentric, vertex) and their attributes.

Triangle-local (GaussianAvatars). Each Gaussian has a parent face and attributes in that face's frame
(R_f, s_f, c_f from :mod:`.frames`)::

    position = R_f @ local_position * s_f + c_f
    rotation = quat(R_f) (x) normalize(local_rotation)          # Hamilton, (w, x, y, z)
    scale    = exp(local_log_scale) * s_f

Barycentric with normal offset (FATE). Each Gaussian has a face, barycentric coordinates and one offset
scalar; its scale is relative to the face's scale in the canonical mesh the avatar was trained on::

    position = sum_k bary_k v_k + n_f * normal_offset_scale * tanh(offset)   # n_f = cross(v1 - v0, v2 - v0)
    rotation = quat(R_f) (x) normalize(local_rotation)
    scale    = exp(local_log_scale + log(s_f / face_scale_canonical[f]))

Vertex offset (LAM). Each Gaussian has a parent vertex and a fixed offset from it; its rotation and scale
do not follow the surface (LAM's renderer and training keep them as predicted for the neutral head)::

    position = v[vertex] + offset
    rotation = normalize(rotation)                                # (w, x, y, z), fixed
    scale    = exp(log_scale)                                     # fixed

Arrays are kept as loaded (float32 for attributes, int64 for faces); deformers compute in float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..head.rotations import matrix_to_quaternion, quaternion_multiply
from .errors import AvatarError
from .frames import face_frames


def _check(name: str, arr: np.ndarray, shape: tuple) -> None:
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        raise AvatarError(f"{name} has shape {arr.shape}, expected {shape} (None = any)")
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise AvatarError(f"{name} holds NaN or infinite values")


def quaternion_conjugate(q: np.ndarray) -> np.ndarray:
    """(..., 4) (w, x, y, z) -> conjugate (the inverse rotation for unit quaternions)."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def normalize_quaternions(q: np.ndarray) -> np.ndarray:
    """(..., 4) -> unit quaternions (zero quaternions become the identity)."""
    q = np.asarray(q, np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    ident = np.zeros_like(q)
    ident[..., 0] = 1.0
    return np.where(n > 1e-12, q / np.maximum(n, 1e-12), ident)


@dataclass(frozen=True, eq=False)
class TriangleBinding:
    """GaussianAvatars' binding. face (N,) int; position (N, 3) in face units; rotation (N, 4) (w, x, y, z);
    log_scale (N, 3) natural log of the scale in face units."""

    kind: ClassVar[str] = "triangle"
    face: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    log_scale: np.ndarray

    def __post_init__(self) -> None:
        n = self.face.shape[0]
        _check("binding face", self.face, (n,))
        _check("local position", self.position, (n, 3))
        _check("local rotation", self.rotation, (n, 4))
        _check("local log scale", self.log_scale, (n, 3))

    @property
    def count(self) -> int:
        return int(self.face.shape[0])

    @classmethod
    def from_world(
        cls,
        face: np.ndarray,
        position: np.ndarray,
        rotation: np.ndarray,
        scale: np.ndarray,
        vertices: np.ndarray,
        faces: np.ndarray,
    ) -> TriangleBinding:
        """Bind world-space Gaussians to ``face`` (N,) of the mesh (``vertices`` (V, 3), ``faces`` (F, 3)).

        position (N, 3) m, rotation (N, 4) (w, x, y, z), scale (N, 3) m. Deforming the result with the same
        vertices gives these attributes back (the neutral pose reproduces the canonical attributes).
        """
        face = np.asarray(face, np.int64)
        rot_f, s_f, c_f = face_frames(np.asarray(vertices, np.float64), np.asarray(faces)[face])
        local_pos = np.einsum("nji,nj->ni", rot_f, np.asarray(position, np.float64) - c_f) / s_f[:, None]
        q_f = matrix_to_quaternion(rot_f)
        local_rot = quaternion_multiply(quaternion_conjugate(q_f), normalize_quaternions(rotation))
        local_log_scale = np.log(np.asarray(scale, np.float64) / s_f[:, None])
        return cls(face, local_pos.astype(np.float32), local_rot.astype(np.float32), local_log_scale.astype(np.float32))


@dataclass(frozen=True, eq=False)
class BarycentricBinding:
    """FATE's binding. face (N,) int; bary (N, 3); offset (N,) raw (tanh applied at run time); rotation (N, 4)
    (w, x, y, z); log_scale (N, 3); face_scale_canonical (F,) s_f of every face of the canonical mesh."""

    kind: ClassVar[str] = "barycentric"
    face: np.ndarray
    bary: np.ndarray
    offset: np.ndarray
    rotation: np.ndarray
    log_scale: np.ndarray
    face_scale_canonical: np.ndarray
    normal_offset_scale: float = 0.05

    def __post_init__(self) -> None:
        n = self.face.shape[0]
        _check("binding face", self.face, (n,))
        _check("barycentric coordinates", self.bary, (n, 3))
        _check("normal offset", self.offset, (n,))
        _check("local rotation", self.rotation, (n, 4))
        _check("local log scale", self.log_scale, (n, 3))
        _check("face_scale_canonical", self.face_scale_canonical, (None,))
        if np.any(self.face_scale_canonical <= 0):
            raise AvatarError("face_scale_canonical must be positive")

    @property
    def count(self) -> int:
        return int(self.face.shape[0])


@dataclass(frozen=True, eq=False)
class VertexBinding:
    """LAM's binding. vertex (N,) int parent vertex; offset (N, 3) metres from it; rotation (N, 4) (w, x, y, z)
    and log_scale (N, 3) in the avatar's frame, the same in every frame (they do not follow the surface)."""

    kind: ClassVar[str] = "vertex"
    vertex: np.ndarray
    offset: np.ndarray
    rotation: np.ndarray
    log_scale: np.ndarray

    def __post_init__(self) -> None:
        n = self.vertex.shape[0]
        _check("binding vertex", self.vertex, (n,))
        _check("vertex offset", self.offset, (n, 3))
        _check("rotation", self.rotation, (n, 4))
        _check("log scale", self.log_scale, (n, 3))

    @property
    def count(self) -> int:
        return int(self.vertex.shape[0])


Binding = TriangleBinding | BarycentricBinding | VertexBinding
