"""Import a GaussianAvatars (ShenhanQian/GaussianAvatars) avatar: ``point_cloud.ply`` + ``flame_param.npz``.

``point_cloud.ply`` is a 3DGS PLY with an extra float property ``binding_0`` (the parent face); its x, y, z,
scale and rot are LOCAL (triangle-space) values. ``flame_param.npz`` holds the tracked FLAME parameters
(``shape`` (300,), ``static_offset`` (1, V, 3), per-frame expr/poses that this importer ignores).

The avatar binds to FLAME with GaussianAvatars' teeth (5143 vertices, 10144 faces): given a FLAME-topology
head (5023 vertices, 9976 faces) the importer adds the teeth (:mod:`.teeth`), then bakes the identity into
the template as upstream does (``v_template + shapedirs . shape + static_offset``). Any other head is used
as it is, and refused when the avatar binds to faces it lacks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..head.model import HeadModel
from .binding import TriangleBinding, normalize_quaternions
from .errors import AvatarError
from .model import GaussianAvatar
from .ply import read_gaussian_ply, sigmoid
from .teeth import FLAME_FACES, FLAME_VERTICES, add_teeth

PLY_NAME, PARAM_NAME = "point_cloud.ply", "flame_param.npz"


def resolve_sources(sources: Sequence[str | Path]) -> tuple[Path, Path]:
    """A folder holding both files, or the two files in any order -> (ply, npz)."""
    paths = [Path(s) for s in sources]
    if len(paths) == 1 and paths[0].is_dir():
        paths = [paths[0] / PLY_NAME, paths[0] / PARAM_NAME]
    ply = [p for p in paths if p.suffix == ".ply"]
    npz = [p for p in paths if p.suffix == ".npz"]
    if len(paths) != 2 or len(ply) != 1 or len(npz) != 1:
        got = [str(p) for p in paths]
        raise AvatarError(f"give a GaussianAvatars folder or its {PLY_NAME} and {PARAM_NAME}, got {got}")
    for p in (ply[0], npz[0]):
        if not p.is_file():
            raise AvatarError(f"{p}: no such file")
    return ply[0], npz[0]


def read_flame_param(path: Path) -> dict[str, np.ndarray]:
    """The arrays of ``flame_param.npz`` (no pickles)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError) as exc:
        raise AvatarError(f"{path}: cannot read FLAME parameters ({type(exc).__name__}: {exc})") from None


def personalise(head: HeadModel, params: dict[str, np.ndarray], needed_faces: int) -> HeadModel:
    """Teeth (for a FLAME head), then ``shape`` and ``static_offset`` baked into ``v_template``."""
    if head.num_vertices == FLAME_VERTICES and head.num_faces == FLAME_FACES:
        head = add_teeth(head)
    if needed_faces > head.num_faces:
        raise AvatarError(
            f"the avatar binds to face {needed_faces - 1} but head {head.name!r} has {head.num_faces} faces "
            f"(GaussianAvatars binds to FLAME with teeth: give a FLAME head, {FLAME_VERTICES} vertices)"
        )
    v = head.v_template.copy()
    if "shape" in params:
        shape = np.asarray(params["shape"], np.float64).reshape(-1)[: head.shape_dims]
        v += head.shapedirs[:, :, : shape.size] @ shape
    if "static_offset" in params:
        off = np.asarray(params["static_offset"], np.float64)
        off = off.reshape(-1, 3)
        if off.shape[0] > v.shape[0]:
            raise AvatarError(f"static_offset has {off.shape[0]} vertices, the head has {v.shape[0]}")
        v[: off.shape[0]] += off
    return replace(head, v_template=v)


def import_gaussianavatars(sources: Sequence[str | Path], head: HeadModel, name: str | None = None) -> GaussianAvatar:
    """Read a GaussianAvatars output (folder or the two files) bound to ``head`` (a FLAME head)."""
    ply_path, param_path = resolve_sources(sources)
    raw = read_gaussian_ply(ply_path)
    if "binding_0" not in raw:
        raise AvatarError(f"{ply_path}: no 'binding_0' property: not a GaussianAvatars point cloud")
    binding = raw["binding_0"]
    if np.any(binding < 0) or np.any(binding != np.round(binding)):
        raise AvatarError(f"{ply_path}: binding_0 holds values that are not face indices")
    face = binding.astype(np.int64)
    params = read_flame_param(param_path)
    bound = personalise(head, params, int(face.max()) + 1 if face.size else 0)
    return GaussianAvatar(
        head=bound,
        binding=TriangleBinding(
            face=face,
            position=raw["position"].astype(np.float32),
            rotation=normalize_quaternions(raw["rotation"]).astype(np.float32),
            log_scale=raw["log_scale"].astype(np.float32),
        ),
        opacity=sigmoid(raw["opacity_logit"]).astype(np.float32),
        sh=raw["sh"],
        name=name or ply_path.parent.name or "gaussianavatars",
    )
