"""Deformation: deformed head vertices (V, 3) -> world-space Gaussians (:class:`GaussianState`).

This is the straightforward numpy REFERENCE implementation (float64 inside, float32 out). Everything that
does not change per frame is precomputed in the constructor: the faces actually used, each Gaussian's
index into them, normalised local rotations, linear local scales, tanh of FATE offsets. Faster deformers
must match :meth:`Deformer.deform` (tests compare against it).
"""

from __future__ import annotations

import numpy as np

from ..head.rotations import matrix_to_quaternion, quaternion_multiply, wxyz_to_xyzw
from .binding import BarycentricBinding, Binding, TriangleBinding, VertexBinding, normalize_quaternions
from .frames import face_frames, face_normals_unnormalised
from .state import GaussianState


class Deformer:
    """Base: holds the used faces; subclasses implement :meth:`deform` for one binding type."""

    def __init__(self, face: np.ndarray, faces: np.ndarray, num_vertices: int) -> None:
        self.num_vertices = num_vertices
        self.used_faces, self.gather = np.unique(np.asarray(face, np.int64), return_inverse=True)
        self.face_vertex_ids = np.asarray(faces, np.int64)[self.used_faces]  # (U, 3)

    def _check(self, vertices: np.ndarray) -> np.ndarray:
        vertices = np.asarray(vertices, np.float64)
        if vertices.shape != (self.num_vertices, 3):
            raise ValueError(f"vertices have shape {vertices.shape}, the head has ({self.num_vertices}, 3)")
        return vertices

    def deform(self, vertices: np.ndarray) -> GaussianState:
        raise NotImplementedError

    @staticmethod
    def _state(position: np.ndarray, rotation_wxyz: np.ndarray, scale: np.ndarray) -> GaussianState:
        rot = wxyz_to_xyzw(normalize_quaternions(rotation_wxyz))
        return GaussianState(position.astype(np.float32), rot.astype(np.float32), scale.astype(np.float32))


class TriangleDeformer(Deformer):
    """GaussianAvatars: ``R_f @ p * s_f + c_f``, ``quat(R_f) (x) q``, ``exp(log s) * s_f``."""

    def __init__(self, binding: TriangleBinding, faces: np.ndarray, num_vertices: int) -> None:
        super().__init__(binding.face, faces, num_vertices)
        self.local_position = binding.position.astype(np.float64)
        self.local_rotation = normalize_quaternions(binding.rotation)
        self.local_scale = np.exp(binding.log_scale.astype(np.float64))

    def deform(self, vertices: np.ndarray) -> GaussianState:
        vertices = self._check(vertices)
        rot_f, s_f, c_f = face_frames(vertices, self.face_vertex_ids)  # (U, 3, 3), (U,), (U, 3)
        q_f = matrix_to_quaternion(rot_f)  # (U, 4)
        g = self.gather
        position = np.einsum("nij,nj->ni", rot_f[g], self.local_position) * s_f[g, None] + c_f[g]
        rotation = quaternion_multiply(q_f[g], self.local_rotation)
        return self._state(position, rotation, self.local_scale * s_f[g, None])


class BarycentricDeformer(Deformer):
    """FATE: barycentric point + ``n_f * k * tanh(offset)``, ``quat(R_f) (x) q``, scale by ``s_f / s_f_canonical``."""

    def __init__(self, binding: BarycentricBinding, faces: np.ndarray, num_vertices: int) -> None:
        super().__init__(binding.face, faces, num_vertices)
        self.bary = binding.bary.astype(np.float64)
        self.shift = binding.normal_offset_scale * np.tanh(binding.offset.astype(np.float64))  # (N,)
        self.local_rotation = normalize_quaternions(binding.rotation)
        self.log_scale = binding.log_scale.astype(np.float64)
        self.log_canonical = np.log(binding.face_scale_canonical.astype(np.float64))[self.used_faces]  # (U,)

    def deform(self, vertices: np.ndarray) -> GaussianState:
        vertices = self._check(vertices)
        rot_f, s_f, _ = face_frames(vertices, self.face_vertex_ids)
        n_f = face_normals_unnormalised(vertices, self.face_vertex_ids)
        q_f = matrix_to_quaternion(rot_f)
        g = self.gather
        corners = vertices[self.face_vertex_ids[g]]  # (N, 3, 3)
        position = np.einsum("nk,nkc->nc", self.bary, corners) + n_f[g] * self.shift[:, None]
        rotation = quaternion_multiply(q_f[g], self.local_rotation)
        scale = np.exp(self.log_scale + (np.log(s_f) - self.log_canonical)[g, None])
        return self._state(position, rotation, scale)


class VertexDeformer(Deformer):
    """LAM: ``v[vertex] + offset``; rotation and scale fixed (see :class:`.binding.VertexBinding`)."""

    def __init__(self, binding: VertexBinding, faces: np.ndarray, num_vertices: int) -> None:
        self.num_vertices = num_vertices
        self.vertex = np.asarray(binding.vertex, np.int64)
        self.offset = binding.offset.astype(np.float64)
        rotation = wxyz_to_xyzw(normalize_quaternions(binding.rotation)).astype(np.float32)
        scale = np.exp(binding.log_scale.astype(np.float64)).astype(np.float32)
        rotation.flags.writeable = False
        scale.flags.writeable = False
        self._rotation, self._scale = rotation, scale  # shared by every state (read-only)

    def deform(self, vertices: np.ndarray) -> GaussianState:
        vertices = self._check(vertices)
        position = (vertices[self.vertex] + self.offset).astype(np.float32)
        return GaussianState(position, self._rotation, self._scale)


def make_deformer(binding: Binding, faces: np.ndarray, num_vertices: int) -> Deformer:
    """The reference deformer for ``binding`` on a mesh with ``faces`` (F, 3) and ``num_vertices``."""
    if isinstance(binding, TriangleBinding):
        return TriangleDeformer(binding, faces, num_vertices)
    if isinstance(binding, BarycentricBinding):
        return BarycentricDeformer(binding, faces, num_vertices)
    if isinstance(binding, VertexBinding):
        return VertexDeformer(binding, faces, num_vertices)
    raise TypeError(f"unknown binding {type(binding).__name__}")
