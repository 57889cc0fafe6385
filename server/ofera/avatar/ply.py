"""Standard 3D Gaussian Splatting PLY files (graphdeco-inria/gaussian-splatting layout), via plyfile.

One ``vertex`` element, binary little-endian, float32 properties in this order::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3(K-1)-1)  opacity  scale_0..2  rot_0..3  [extra...]

Stored raw: ``opacity`` is a logit (apply sigmoid), ``scale_*`` are logs (apply exp), ``rot_*`` is an
unnormalised quaternion (w, x, y, z). ``f_rest`` is channel-major: all red coefficients, then green, then blue.
Exports always write degree 3 (45 ``f_rest``, zeros above the avatar's degree) so every viewer reads them.
GaussianAvatars adds ``binding_0`` (the parent face, as a float) and stores LOCAL attributes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import AvatarError
from .sh import sh_count, sh_degree
from .state import GaussianState

MAX_PLY_BYTES = 2 * 1024**3


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p))


def checked_file(path: str | Path, max_bytes: int) -> Path:
    """``path`` if it is a file of at most ``max_bytes`` (an importer's input), else an :class:`AvatarError`."""
    path = Path(path)
    if not path.is_file():
        raise AvatarError(f"{path}: no such file")
    size = path.stat().st_size
    if size > max_bytes:
        raise AvatarError(f"{path}: {size / 1e9:.1f} GB is larger than the {max_bytes / 1e9:.1f} GB limit")
    return path


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def gaussian_ply_arrays(
    position: np.ndarray,
    rotation_wxyz: np.ndarray,
    log_scale: np.ndarray,
    opacity_logit: np.ndarray,
    sh: np.ndarray,
    degree: int = 3,
    extra: dict[str, np.ndarray] | None = None,
) -> np.ndarray:
    """The structured (N,) array of a 3DGS PLY vertex element; SH padded/truncated to ``degree``."""
    n = position.shape[0]
    k = sh_count(degree)
    coeffs = np.zeros((n, k, 3), np.float32)
    kk = min(k, sh.shape[1])
    coeffs[:, :kk] = sh[:, :kk]
    rest = coeffs[:, 1:].transpose(0, 2, 1).reshape(n, -1)  # channel-major
    columns = (
        [("x", position[:, 0]), ("y", position[:, 1]), ("z", position[:, 2])]
        + [(f"n{c}", np.zeros(n)) for c in "xyz"]
        + [(f"f_dc_{i}", coeffs[:, 0, i]) for i in range(3)]
        + [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
        + [("opacity", opacity_logit)]
        + [(f"scale_{i}", log_scale[:, i]) for i in range(3)]
        + [(f"rot_{i}", rotation_wxyz[:, i]) for i in range(4)]
        + list((extra or {}).items())
    )
    out = np.empty(n, dtype=[(name, "<f4") for name, _ in columns])
    for name, col in columns:
        out[name] = col
    return out


def write_ply(path: str | Path, vertex: np.ndarray) -> Path:
    """Write a structured vertex array as a binary little-endian PLY."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<").write(str(path))
    return path


def export_state_ply(path: str | Path, state: GaussianState, opacity: np.ndarray, sh: np.ndarray) -> Path:
    """World-space Gaussians of one frame -> standard 3DGS PLY (degree 3, LE float32)."""
    vertex = gaussian_ply_arrays(
        state.position,
        state.rotation_wxyz(),
        np.log(np.maximum(state.scale.astype(np.float64), 1e-12)),
        _logit(opacity),
        sh,
    )
    return write_ply(path, vertex)


def read_gaussian_ply(path: str | Path, max_bytes: int = MAX_PLY_BYTES) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY into raw arrays: ``position`` (N,3), ``rotation`` (N,4) (w,x,y,z) raw, ``log_scale`` (N,3),
    ``opacity_logit`` (N,), ``sh`` (N,K,3), and every other property by name (e.g. ``binding_0``)."""
    from plyfile import PlyData

    path = checked_file(path, max_bytes)
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"].data
    except Exception as exc:  # plyfile raises many types on malformed input
        raise AvatarError(f"{path}: not a readable PLY ({type(exc).__name__}: {exc})") from None
    names = set(vertex.dtype.names or ())
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", *(f"scale_{i}" for i in range(3)),
            *(f"rot_{i}" for i in range(4))]
    missing = [k for k in need if k not in names]
    if missing:
        raise AvatarError(f"{path}: not a 3D Gaussian PLY, missing properties {missing}")
    n = len(vertex)
    n_rest = sum(1 for k in names if k.startswith("f_rest_"))
    try:
        k = sh_count(sh_degree(1 + n_rest // 3)) if n_rest % 3 == 0 else -1
    except ValueError:
        k = -1
    if k < 0:
        raise AvatarError(f"{path}: {n_rest} f_rest properties, expected 0, 9, 24 or 45")

    def col(name: str) -> np.ndarray:
        return np.asarray(vertex[name], np.float64)

    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = np.stack([col(f"f_dc_{i}") for i in range(3)], axis=1)
    if n_rest:
        rest = np.stack([col(f"f_rest_{i}") for i in range(n_rest)], axis=1)
        sh[:, 1:] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    out = {
        "position": np.stack([col(c) for c in "xyz"], axis=1),
        "rotation": np.stack([col(f"rot_{i}") for i in range(4)], axis=1),
        "log_scale": np.stack([col(f"scale_{i}") for i in range(3)], axis=1),
        "opacity_logit": col("opacity"),
        "sh": sh,
    }
    known = set(need) | {f"f_rest_{i}" for i in range(n_rest)} | {"nx", "ny", "nz"}
    out |= {k: col(k) for k in vertex.dtype.names if k not in known}
    for key in ("position", "rotation", "log_scale", "opacity_logit", "sh"):
        if not np.all(np.isfinite(out[key])):
            raise AvatarError(f"{path}: {key} holds NaN or infinite values")
    return out
