"""The avatar object: Gaussians bound to a (personalised) head model.

Contract (docs/ARCHITECTURE.md): ``count``, ``sh_degree``, ``opacity (N,) float32`` linear in 0..1,
``sh (N, (d+1)^2, 3) float32``, ``head: HeadModel`` (the identity is baked into its ``v_template``: drive it
with ``HeadSubject.create(avatar.head)`` and no shape), ``movable (N,) bool``, ``deformer()`` and
``neutral()``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..head.model import HeadModel
from .binding import Binding
from .deform import Deformer, make_deformer
from .errors import AvatarError
from .movable import movable_gaussians, movable_vertices
from .sh import sh_degree
from .state import GaussianState

EXPRESSION_SPACES = ("flame68", "arkit51")
"""What drives an avatar: ``flame68`` = the EPM's 68 FLAME values (50 expression + jaw and eye 6D rotations),
``arkit51`` = the BDA-aligned ARKit weights themselves (a head whose 51 expression directions are ARKit morph
targets, in the ``arkit51`` order; the EPM is skipped)."""


@dataclass(frozen=True, eq=False)
class GaussianAvatar:
    head: HeadModel
    binding: Binding
    opacity: np.ndarray  # (N,) float32, linear
    sh: np.ndarray  # (N, (d+1)^2, 3) float32
    name: str = "avatar"
    expression: str = "flame68"  # the expression space: "flame68" (EPM output) or "arkit51" (morph-target head)

    def __post_init__(self) -> None:
        n = self.binding.count
        if self.opacity.shape != (n,):
            raise AvatarError(f"{self.name}: opacity has shape {self.opacity.shape}, expected ({n},)")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise AvatarError(f"{self.name}: sh has shape {self.sh.shape}, expected ({n}, (d+1)^2, 3)")
        try:
            sh_degree(self.sh.shape[1])
        except ValueError as exc:
            raise AvatarError(f"{self.name}: {exc}") from None
        if not (np.all(np.isfinite(self.opacity)) and np.all(np.isfinite(self.sh))):
            raise AvatarError(f"{self.name}: opacity or SH hold NaN or infinite values")
        if self.expression not in EXPRESSION_SPACES:
            raise AvatarError(f"{self.name}: unknown expression space {self.expression!r} "
                              f"(expected one of {', '.join(EXPRESSION_SPACES)})")
        if self.expression == "arkit51" and self.head.expr_dims != 51:
            raise AvatarError(f"{self.name}: an arkit51 avatar needs a head with 51 expression directions (the ARKit "
                              f"morph targets), {self.head.name!r} has {self.head.expr_dims}")
        vertex = getattr(self.binding, "vertex", None)
        if vertex is not None:
            if n and (vertex.min() < 0 or vertex.max() >= self.head.num_vertices):
                raise AvatarError(f"{self.name}: Gaussians bind to vertex {int(vertex.max())} but head "
                                  f"{self.head.name!r} has only {self.head.num_vertices} vertices")
            return
        face = self.binding.face
        if n and (face.min() < 0 or face.max() >= self.head.num_faces):
            raise AvatarError(
                f"{self.name}: Gaussians bind to face {int(face.max())} but head {self.head.name!r} has only "
                f"{self.head.num_faces} faces (give the head the avatar was made for)"
            )
        canonical = getattr(self.binding, "face_scale_canonical", None)
        if canonical is not None and canonical.shape != (self.head.num_faces,):
            raise AvatarError(
                f"{self.name}: face_scale_canonical has {canonical.shape[0]} faces, the head has {self.head.num_faces}"
            )

    @property
    def count(self) -> int:
        return self.binding.count

    @property
    def sh_degree(self) -> int:
        return sh_degree(self.sh.shape[1])

    @property
    def binding_type(self) -> str:
        """``"triangle"`` (GaussianAvatars), ``"barycentric"`` (FATE) or ``"vertex"`` (LAM)."""
        return self.binding.kind

    @cached_property
    def movable(self) -> np.ndarray:
        """(N,) bool: Gaussians on faces (vertex binding: vertices) that expressions, the jaw or the eyes move
        (see :mod:`.movable`)."""
        vertex = getattr(self.binding, "vertex", None)
        if vertex is not None:
            return movable_vertices(self.head)[np.asarray(vertex, np.int64)]
        return movable_gaussians(self.head, self.binding.face)

    def deformer(self) -> Deformer:
        """The reference deformer: ``deform(vertices (V, 3)) -> GaussianState``."""
        return make_deformer(self.binding, self.head.faces, self.head.num_vertices)

    def neutral(self) -> GaussianState:
        """Gaussians on the neutral head (zero expression, identity pose: the head's ``v_template``)."""
        return self.deformer().deform(self.head.v_template)

    def info(self) -> dict:
        """Summary for ``ofera avatar info``."""
        state = self.neutral()
        lo, hi = state.position.min(axis=0), state.position.max(axis=0)
        return {
            "name": self.name,
            "count": self.count,
            "sh_degree": self.sh_degree,
            "binding": self.binding_type,
            "expression": self.expression,
            "movable": int(self.movable.sum()),
            **({"vertices_used": int(np.unique(self.binding.vertex).size)} if self.binding_type == "vertex"
               else {"faces_used": int(np.unique(self.binding.face).size)}),
            "head": {"name": self.head.name, "vertices": self.head.num_vertices, "faces": self.head.num_faces,
                     "expr_dims": self.head.expr_dims},
            "extent_m": [round(float(e), 4) for e in hi - lo],
            "opacity_mean": round(float(self.opacity.mean()), 4) if self.count else 0.0,
        }
