"""The project's own avatar file: one ``.npz`` (numpy zip, no pickles; read with ``allow_pickle=False``).

Format ``ofera-avatar``, version 1. N Gaussians, K = (d+1)^2 SH coefficients, F faces of the head::

    format                    str   "ofera-avatar"
    format_version            int   1 (readers refuse newer versions)
    name                      str
    binding                   str   "triangle" (GaussianAvatars), "barycentric" (FATE) or "vertex" (LAM)
    expression                str   optional: "flame68" (default: driven by the EPM) or "arkit51" (ARKit morph head)
    opacity                   (N,)        float32  linear, 0..1 (NOT a logit)
    sh                        (N, K, 3)   float32  SH coefficients, [:, 0] is DC; colour = C0 * dc + 0.5
    gaussian/face             (N,)        int32    parent face index into head/faces (not for "vertex")
    gaussian/rotation         (N, 4)      float32  local rotation (w, x, y, z), normalised on use
    gaussian/log_scale        (N, 3)      float32  natural log of the local scale
  binding = "vertex" (rotation and scale are in the avatar's frame and fixed):
    gaussian/vertex           (N,)        int32    parent vertex index into head/v_template
    gaussian/vertex_offset    (N, 3)      float32  offset from the vertex, metres
  binding = "triangle":
    gaussian/position         (N, 3)      float32  local position in face units
  binding = "barycentric":
    gaussian/bary             (N, 3)      float32  barycentric coordinates in the face
    gaussian/offset           (N,)        float32  raw normal offset (tanh applied at run time)
    face_scale_canonical      (F,)        float32  s_f of each face of the canonical mesh
    normal_offset_scale       ()          float32  FATE's shell length (0.05)
  the head model the Gaussians bind to (HeadModel.save's arrays, prefixed "head/"), identity baked in:
    head/name, head/v_template (V,3), head/shapedirs (V,3,S), head/exprdirs (V,3,E), head/posedirs (36,3V),
    head/j_regressor (5,V), head/parents (5,), head/weights (V,5), head/faces (F,3) int32,
    head/landmark/<name> (3,), head/label/<name> (V,) bool

The deformation each binding defines is written in :mod:`ofera.avatar.binding`. ``FORMAT.md`` next to this
module says the same for people who do not read Python.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from ..head.model import HeadModel, HeadModelError
from .binding import BarycentricBinding, TriangleBinding, VertexBinding
from .errors import AvatarError
from .model import GaussianAvatar

FORMAT = "ofera-avatar"
FORMAT_VERSION = 1
_HEAD_ARRAYS = ("v_template", "shapedirs", "exprdirs", "posedirs", "j_regressor", "parents", "weights", "faces")


def head_arrays(head: HeadModel, prefix: str = "head/") -> dict[str, np.ndarray]:
    """The head's arrays in :meth:`HeadModel.save`'s layout and dtypes (:meth:`HeadModel.arrays`), keys prefixed."""
    return {prefix + k: v for k, v in head.arrays().items()}


def head_from_arrays(z, prefix: str = "head/") -> HeadModel:
    """Inverse of :func:`head_arrays` on an open npz (or dict); float arrays come back float64."""
    missing = [k for k in _HEAD_ARRAYS if prefix + k not in z]
    if missing:
        raise AvatarError(f"missing head arrays {[prefix + k for k in missing]}")
    arrays = {k: np.asarray(z[prefix + k]) for k in _HEAD_ARRAYS}
    arrays = {k: a.astype(np.float64) if a.dtype.kind == "f" else a.astype(np.int64) for k, a in arrays.items()}
    lm, lab = prefix + "landmark/", prefix + "label/"
    keys = list(z.keys()) if isinstance(z, dict) else z.files
    return HeadModel(
        **arrays,
        name=str(z[prefix + "name"]) if prefix + "name" in keys else "head",
        landmarks={k[len(lm):]: np.asarray(z[k], np.float64) for k in keys if k.startswith(lm)},
        vertex_labels={k[len(lab):]: np.asarray(z[k], bool) for k in keys if k.startswith(lab)},
    )


def avatar_arrays(avatar: GaussianAvatar) -> dict[str, np.ndarray]:
    """Everything :func:`save_avatar` writes, as a dict of arrays."""
    b = avatar.binding
    arrays = {
        "format": np.array(FORMAT),
        "format_version": np.array(FORMAT_VERSION),
        "name": np.array(avatar.name),
        "binding": np.array(b.kind),
        "expression": np.array(avatar.expression),
        "opacity": avatar.opacity.astype(np.float32),
        "sh": avatar.sh.astype(np.float32),
        "gaussian/rotation": b.rotation.astype(np.float32),
        "gaussian/log_scale": b.log_scale.astype(np.float32),
    }
    if isinstance(b, VertexBinding):
        arrays["gaussian/vertex"] = b.vertex.astype(np.int32)
        arrays["gaussian/vertex_offset"] = b.offset.astype(np.float32)
        return arrays | head_arrays(avatar.head)
    arrays["gaussian/face"] = b.face.astype(np.int32)
    if isinstance(b, TriangleBinding):
        arrays["gaussian/position"] = b.position.astype(np.float32)
    else:
        arrays["gaussian/bary"] = b.bary.astype(np.float32)
        arrays["gaussian/offset"] = b.offset.astype(np.float32)
        arrays["face_scale_canonical"] = b.face_scale_canonical.astype(np.float32)
        arrays["normal_offset_scale"] = np.array(b.normal_offset_scale, np.float32)
    return arrays | head_arrays(avatar.head)


def save_avatar(avatar: GaussianAvatar, path: str | Path) -> Path:
    """Write ``path`` atomically (a temporary file in the same folder, then rename). Uncompressed npz."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **avatar_arrays(avatar))
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _binding_from(z, kind: str):
    common = {
        "rotation": z["gaussian/rotation"].astype(np.float32),
        "log_scale": z["gaussian/log_scale"].astype(np.float32),
    }
    if kind == VertexBinding.kind:
        return VertexBinding(vertex=z["gaussian/vertex"].astype(np.int64),
                             offset=z["gaussian/vertex_offset"].astype(np.float32), **common)
    common["face"] = z["gaussian/face"].astype(np.int64)
    if kind == TriangleBinding.kind:
        return TriangleBinding(position=z["gaussian/position"].astype(np.float32), **common)
    if kind == BarycentricBinding.kind:
        return BarycentricBinding(
            bary=z["gaussian/bary"].astype(np.float32),
            offset=z["gaussian/offset"].astype(np.float32),
            face_scale_canonical=z["face_scale_canonical"].astype(np.float32),
            normal_offset_scale=float(z["normal_offset_scale"]),
            **common,
        )
    raise AvatarError(f"unknown binding type {kind!r} (expected 'triangle', 'barycentric' or 'vertex')")


def load_avatar_npz(path: str | Path) -> GaussianAvatar:
    """Read a file written by :func:`save_avatar`; every failure is an :class:`AvatarError` naming the file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if "format" not in z.files or str(z["format"]) != FORMAT:
                raise AvatarError(f"not an OFERA avatar file (no 'format' = '{FORMAT}')")
            version = int(z["format_version"])
            if version > FORMAT_VERSION:
                raise AvatarError(f"avatar format version {version} is newer than this reader ({FORMAT_VERSION})")
            return GaussianAvatar(
                head=head_from_arrays(z),
                binding=_binding_from(z, str(z["binding"])),
                opacity=z["opacity"].astype(np.float32),
                sh=z["sh"].astype(np.float32),
                name=str(z["name"]),
                expression=str(z["expression"]) if "expression" in z.files else "flame68",
            )
    except AvatarError as exc:
        raise AvatarError(f"{path}: {exc}") from None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, HeadModelError) as exc:
        raise AvatarError(f"{path}: cannot read avatar ({type(exc).__name__}: {exc})") from None
