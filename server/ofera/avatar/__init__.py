"""Gaussian head avatars bound to the head mesh: bindings, deformation, formats, importers, preview renderer.

Public API::

    load_avatar("default" | path) -> GaussianAvatar     # .count .sh_degree .opacity .sh .head .movable
    avatar.deformer().deform(vertices (V, 3)) -> GaussianState(position, rotation xyzw, scale)
    avatar.neutral() -> GaussianState
    save_avatar(avatar, path)                            # the project's .npz (FORMAT.md)
    import_gaussianavatars([folder] | [ply, npz], head)  # GaussianAvatars point_cloud.ply + flame_param.npz
    import_fate(checkpoint, head)                        # FATE torch checkpoint
    import_lam(zip)                                      # LAM export: skin.glb + offset.ply (ARKit morph head)
    export_state_ply(path, state, opacity, sh)           # standard world-space 3DGS PLY
    ofera.avatar.camera: Camera (OpenCV pinhole; cameras.json); ofera.avatar.render: project_gaussians, composite,
    render_state, face_camera
"""

from .binding import BarycentricBinding, TriangleBinding, VertexBinding
from .catalog import load_avatar
from .deform import BarycentricDeformer, Deformer, TriangleDeformer, VertexDeformer
from .errors import AvatarError
from .fate import import_fate
from .gaussianavatars import import_gaussianavatars
from .io import save_avatar
from .lam import import_lam
from .model import GaussianAvatar
from .ply import export_state_ply
from .state import GaussianState

__all__ = [
    "AvatarError",
    "BarycentricBinding",
    "BarycentricDeformer",
    "Deformer",
    "GaussianAvatar",
    "GaussianState",
    "TriangleBinding",
    "TriangleDeformer",
    "VertexBinding",
    "VertexDeformer",
    "export_state_ply",
    "import_fate",
    "import_gaussianavatars",
    "import_lam",
    "load_avatar",
    "save_avatar",
]
