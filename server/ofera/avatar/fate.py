"""Import a FATE (zjwfufu/FateAvatar) checkpoint: a torch file whose ``model`` entry is the state_dict.

Read with ``torch.load(path, weights_only=True, map_location="cpu")`` (no code runs), after a size check.
Used entries (N Gaussians, V = 5023, F = 9976, S + E identity + expression components)::

    _offset (N, 1)  _features_dc (N, 1, 3)  _features_rest (N, K-1, 3)  _scaling (N, 3) log
    _rotation (N, 4) (w, x, y, z)  _opacity (N, 1) logit  face_index (N,)  bary_coords (N, 3)
    delta_shapedirs (V, 3, S + E)  delta_posedirs (36, 3V)  delta_vertex (V, 3)  face_scaling_canonical (F, 1)
    flame.v_template (V, 3) (optional: FATE stores the subject's shaped template there)  faces (F, 3) (optional)

FATE's FLAME concatenates S identity and E expression columns (100 + 50 or 300 + 100); it drives the
expression columns with zeros for identity, so the avatar's personalised head is::

    v_template = flame.v_template (else the head's) + delta_vertex
    exprdirs   = head.exprdirs[:, :, :E] + delta_shapedirs[:, :, S:]
    shapedirs  = head.shapedirs[:, :, :S] + delta_shapedirs[:, :, :S]   (identity is already in v_template)
    posedirs   = head.posedirs + delta_posedirs
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ..head.model import HeadModel
from .binding import BarycentricBinding, normalize_quaternions
from .errors import AvatarError
from .model import GaussianAvatar
from .ply import checked_file, sigmoid

MAX_CHECKPOINT_BYTES = 4 * 1024**3
REQUIRED = ("_offset", "_features_dc", "_features_rest", "_scaling", "_rotation", "_opacity", "face_index",
            "bary_coords", "delta_shapedirs", "delta_posedirs", "delta_vertex", "face_scaling_canonical")
EXPR_BY_TOTAL = {150: 50, 200: 100, 350: 50, 400: 100}  # FATE's (n_shape, n_exp) configurations


def read_checkpoint(path: str | Path, max_bytes: int = MAX_CHECKPOINT_BYTES) -> dict[str, np.ndarray]:
    """The checkpoint's model state as numpy arrays (float64 / int64)."""
    path = checked_file(path, max_bytes)
    try:
        import torch
    except ImportError:
        raise AvatarError("importing a FATE checkpoint needs torch (pip install 'ofera[train]')") from None
    try:
        ckpt = torch.load(str(path), weights_only=True, map_location="cpu")
    except Exception as exc:  # torch raises many types (UnpicklingError, RuntimeError, ...)
        raise AvatarError(f"{path}: not a loadable torch checkpoint ({type(exc).__name__}: {exc})") from None
    state = ckpt.get("model", ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(state, dict):
        raise AvatarError(f"{path}: expected a dict with a 'model' state_dict")
    missing = [k for k in REQUIRED if k not in state]
    if missing:
        raise AvatarError(f"{path}: not a FATE checkpoint, missing {missing}")
    out = {}
    for k, t in state.items():
        if isinstance(t, torch.Tensor):
            a = t.detach().cpu().numpy()
            out[k] = a.astype(np.float64) if a.dtype.kind == "f" else a.astype(np.int64)
    return out


def personal_head(head: HeadModel, s: dict[str, np.ndarray], n_expr: int | None, source: str) -> HeadModel:
    """The head with FATE's personalised template, expression basis and pose correctives."""
    v = head.num_vertices
    d_shape, d_pose, d_vert = s["delta_shapedirs"], s["delta_posedirs"], s["delta_vertex"]
    if d_vert.shape != (v, 3) or d_shape.ndim != 3 or d_shape.shape[:2] != (v, 3):
        raise AvatarError(f"{source}: deltas are for {d_vert.shape[0]} vertices, head {head.name!r} has {v}")
    if d_pose.shape != head.posedirs.shape:
        raise AvatarError(f"{source}: delta_posedirs has shape {d_pose.shape}, expected {head.posedirs.shape}")
    total = d_shape.shape[2]
    n_expr = n_expr if n_expr is not None else EXPR_BY_TOTAL.get(total)
    if n_expr is None or not 0 < n_expr <= total:
        raise AvatarError(f"{source}: {total} blendshape columns: give the number of expression components (n_expr)")
    n_shape = total - n_expr
    if n_expr > head.expr_dims or n_shape > head.shape_dims:
        raise AvatarError(f"{source}: needs {n_shape} identity + {n_expr} expression components, head "
                          f"{head.name!r} has {head.shape_dims} + {head.expr_dims}")
    template = s.get("flame.v_template")
    template = template if template is not None and template.shape == (v, 3) else head.v_template
    if "faces" in s and (s["faces"].shape != head.faces.shape or np.any(s["faces"] != head.faces)):
        raise AvatarError(f"{source}: the checkpoint's faces differ from head {head.name!r}'s: give its FLAME file")
    return replace(
        head,
        v_template=template + d_vert,
        shapedirs=head.shapedirs[:, :, :n_shape] + d_shape[:, :, :n_shape],
        exprdirs=head.exprdirs[:, :, :n_expr] + d_shape[:, :, n_shape:],
        posedirs=head.posedirs + d_pose,
        name=f"{head.name}+fate",
    )


def import_fate(
    path: str | Path, head: HeadModel, n_expr: int | None = None, name: str | None = None
) -> GaussianAvatar:
    """Read a FATE checkpoint bound to ``head`` (the FLAME 2020 model it was trained with)."""
    s = read_checkpoint(path)
    n = s["_offset"].shape[0]
    face = s["face_index"].reshape(-1)
    canonical = s["face_scaling_canonical"].reshape(-1)
    if face.shape != (n,):
        raise AvatarError(f"{path}: face_index has {face.size} entries for {n} Gaussians")
    if canonical.shape != (head.num_faces,):
        raise AvatarError(f"{path}: the avatar binds to a mesh of {canonical.size} faces, head {head.name!r} has "
                          f"{head.num_faces}: give the FLAME file it was trained with")
    dc, rest = s["_features_dc"].reshape(n, -1, 3), s["_features_rest"].reshape(n, -1, 3)
    return GaussianAvatar(
        head=personal_head(head, s, n_expr, str(path)),
        binding=BarycentricBinding(
            face=face,
            bary=s["bary_coords"].reshape(n, 3).astype(np.float32),
            offset=s["_offset"].reshape(n).astype(np.float32),
            rotation=normalize_quaternions(s["_rotation"].reshape(n, 4)).astype(np.float32),
            log_scale=s["_scaling"].reshape(n, 3).astype(np.float32),
            face_scale_canonical=canonical.astype(np.float32),
        ),
        opacity=sigmoid(s["_opacity"].reshape(n)).astype(np.float32),
        sh=np.concatenate([dc, rest], axis=1).astype(np.float32),
        name=name or Path(path).stem,
    )
