"""CPU preview renderer for Gaussian avatars (numpy): 3DGS projection (EWA) and front-to-back compositing.

The maths is split into small array functions that a torch version can mirror one for one:

- :func:`covariance_3d`: Sigma = R S S^T R^T from (x, y, z, w) quaternions and linear scales;
- :func:`project_gaussians`: camera-space means, the EWA Jacobian J of the perspective map at each mean,
  Sigma_2D = J W Sigma W^T J^T + 0.3 I (the 0.3 px dilation of 3DGS), its inverse (the conic), depth and a
  3-sigma pixel radius;
- :func:`composite`: depth-sorted, front-to-back alpha blending,
  ``C = sum_i c_i a_i prod_{j<i} (1 - a_j)`` with ``a_i = min(0.99, o_i exp(-0.5 d^T Sigma_2D^-1 d))``,
  splats below 1/255 skipped, as in 3DGS.

Camera (:class:`.camera.Camera`): OpenCV (x right, y down, z forward), pixel (i, j) covers [i, i+1) x [j, j+1), its
centre at (i + 0.5, j + 0.5). Colours: SH evaluated for the camera-to-Gaussian direction (degree 0 .. the avatar's).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..head.rotations import quaternion_to_matrix
from .camera import Camera
from .sh import eval_sh
from .state import GaussianState

ALPHA_MIN, ALPHA_MAX, T_MIN = 1.0 / 255.0, 0.99, 1e-4
DILATION_PX = 0.3


@dataclass(frozen=True)
class Projected:
    """Screen-space Gaussians: mean (N, 2) px, cov (N, 2, 2) px^2, conic (N, 3) = (a, b, c) of the inverse
    [[a, b], [b, c]], depth (N,) metres along the view axis, radius (N,) px, visible (N,) bool."""

    mean: np.ndarray
    cov: np.ndarray
    conic: np.ndarray
    depth: np.ndarray
    radius: np.ndarray
    visible: np.ndarray


def covariance_3d(rotation_xyzw: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(N, 3, 3) world covariance from unit quaternions (N, 4) (x, y, z, w) and linear scales (N, 3) metres."""
    q = np.asarray(rotation_xyzw, np.float64)
    m = quaternion_to_matrix(np.concatenate([q[:, 3:], q[:, :3]], axis=1)) * np.asarray(scale, np.float64)[:, None, :]
    return m @ m.transpose(0, 2, 1)


def project_gaussians(
    position: np.ndarray,
    cov3d: np.ndarray,
    camera: Camera,
    near: float = 0.01,
    dilation: float = DILATION_PX,
) -> Projected:
    """EWA splatting projection of Gaussians with means (N, 3) and covariances (N, 3, 3), world space."""
    w = camera.R
    t = np.asarray(position, np.float64) @ w.T + camera.t  # camera space (N, 3)
    z = t[:, 2]
    zs = np.where(z > near, z, 1.0)
    # 3DGS clamps the tangent of the Jacobian's point to 1.3 x the half field of view (stability off-screen).
    lim_x = 1.3 * (camera.width / 2) / camera.fx
    lim_y = 1.3 * (camera.height / 2) / camera.fy
    tx = np.clip(t[:, 0] / zs, -lim_x, lim_x) * zs
    ty = np.clip(t[:, 1] / zs, -lim_y, lim_y) * zs
    jac = np.zeros((len(t), 2, 3))
    jac[:, 0, 0] = camera.fx / zs
    jac[:, 0, 2] = -camera.fx * tx / zs**2
    jac[:, 1, 1] = camera.fy / zs
    jac[:, 1, 2] = -camera.fy * ty / zs**2
    m = jac @ w  # (N, 2, 3)
    cov = m @ cov3d @ m.transpose(0, 2, 1) + dilation * np.eye(2)
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    conic = np.stack([c, -b, a], axis=1) / np.where(det > 0, det, 1.0)[:, None]
    mid = (a + c) / 2
    lam = mid + np.sqrt(np.maximum(mid * mid - det, 0.1))
    radius = np.ceil(3.0 * np.sqrt(lam))
    mean = np.stack([camera.fx * t[:, 0] / zs + camera.cx, camera.fy * t[:, 1] / zs + camera.cy], axis=1)
    visible = (
        (z > near) & (det > 0)
        & (mean[:, 0] + radius > 0) & (mean[:, 0] - radius < camera.width)
        & (mean[:, 1] + radius > 0) & (mean[:, 1] - radius < camera.height)
    )
    return Projected(mean, cov, conic, z, radius, visible)


def _pairs(
    mean: np.ndarray, cov: np.ndarray, conic: np.ndarray, k2: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (splat, pixel) pair whose pixel centre lies inside the splat's ellipse ``d^T conic d <= k2``.

    Rows first (the ellipse's vertical extent is ``sqrt(k2 * cov_yy)``), then the exact x-span on each row.
    Returns splat ids (P,), pixel x (P,), pixel y (P,), clipped to the image.
    """
    mx, my = mean[:, 0], mean[:, 1]
    ext_y = np.sqrt(k2 * cov[:, 1, 1])
    y0 = np.clip(np.ceil(my - 0.5 - ext_y), 0, height).astype(np.int64)
    y1 = np.clip(np.floor(my - 0.5 + ext_y), -1, height - 1).astype(np.int64)
    rows = np.maximum(y1 - y0 + 1, 0)
    rid = np.repeat(np.arange(len(mean)), rows)
    py = y0[rid] + np.arange(rows.sum()) - np.repeat(np.cumsum(rows) - rows, rows)
    a, b, c = conic[rid, 0], conic[rid, 1], conic[rid, 2]
    dy = py + 0.5 - my[rid]
    centre = mx[rid] - b * dy / a
    half = np.sqrt(np.maximum(b * b * dy * dy - a * (c * dy * dy - k2[rid]), 0.0)) / a
    x0 = np.clip(np.ceil(centre - half - 0.5), 0, width).astype(np.int64)
    x1 = np.clip(np.floor(centre + half - 0.5), -1, width - 1).astype(np.int64)
    cols = np.maximum(x1 - x0 + 1, 0)
    pid = np.repeat(np.arange(len(rid)), cols)
    px = x0[pid] + np.arange(cols.sum()) - np.repeat(np.cumsum(cols) - cols, cols)
    return rid[pid], px, py[pid]


def composite(
    proj: Projected,
    colour: np.ndarray,
    opacity: np.ndarray,
    background: np.ndarray = (1.0, 1.0, 1.0),
    size: tuple[int, int] = (512, 512),
    chunk: int = 16384,
) -> np.ndarray:
    """Front-to-back alpha compositing of projected Gaussians -> image (H, W, 3) float in 0..1.

    colour (N, 3) and opacity (N,) linear; size = (width, height) px. Each splat covers the pixels where its
    alpha reaches 1/255 (an ellipse, :func:`_pairs`). Splats are taken in depth order in chunks; inside a
    chunk the (splat, pixel) pairs are grouped by pixel with a stable sort (keeping depth order), and the
    transmittance before each pair is an exclusive cumulative product within its pixel times the pixel's
    transmittance carried from earlier chunks, so the result equals sequential blending. Pixels whose
    transmittance fell below 1e-4 stop accumulating (as in 3DGS).
    """
    width, height = size
    opacity = np.asarray(opacity, np.float64)
    idx = np.flatnonzero(proj.visible & (opacity * ALPHA_MAX >= ALPHA_MIN))
    idx = idx[np.argsort(proj.depth[idx], kind="stable")]
    trans = np.ones(width * height)
    accum = np.zeros((width * height, 3))
    colour = np.asarray(colour, np.float64)
    k2_all = 2.0 * np.log(np.maximum(opacity, ALPHA_MIN) / ALPHA_MIN)  # alpha >= 1/255 inside d^T Q d <= k2
    for start in range(0, len(idx), chunk):
        ids = idx[start : start + chunk]
        mean, conic, op, col = proj.mean[ids], proj.conic[ids], opacity[ids], colour[ids]
        sid, px, py = _pairs(mean, proj.cov[ids], conic, k2_all[ids], width, height)
        dx = px + 0.5 - mean[sid, 0]
        dy = py + 0.5 - mean[sid, 1]
        power = -0.5 * (conic[sid, 0] * dx * dx + conic[sid, 2] * dy * dy) - conic[sid, 1] * dx * dy
        alpha = np.minimum(ALPHA_MAX, op[sid] * np.exp(np.minimum(power, 0.0)))
        keep = alpha >= ALPHA_MIN
        pix, alpha, sid = (py * width + px)[keep], alpha[keep], sid[keep]
        order = np.argsort(pix, kind="stable")
        pix, alpha, sid = pix[order], alpha[order], sid[order]
        log_keep = np.log1p(-alpha)
        csum = np.cumsum(log_keep)
        first = np.flatnonzero(np.r_[True, pix[1:] != pix[:-1]])
        seg = np.repeat(np.arange(len(first)), np.diff(np.r_[first, len(pix)]))
        before = csum - log_keep - (csum[first] - log_keep[first])[seg]  # log transmittance inside the chunk
        t_before = trans[pix] * np.exp(before)
        weight = np.where(t_before >= T_MIN, alpha * t_before, 0.0)
        for ch in range(3):
            accum[:, ch] += np.bincount(pix, weight * col[sid, ch], width * height)
        trans *= np.exp(np.bincount(pix, log_keep, width * height))
    image = accum + trans[:, None] * np.asarray(background, np.float64)[None]
    return image.reshape(height, width, 3)


def render_state(
    state: GaussianState,
    opacity: np.ndarray,
    sh: np.ndarray,
    camera: Camera,
    background: np.ndarray = (1.0, 1.0, 1.0),
    sh_degree: int | None = None,
) -> np.ndarray:
    """Image (H, W, 3) float of world-space Gaussians with SH colour for this camera."""
    proj = project_gaussians(state.position, covariance_3d(state.rotation, state.scale), camera)
    dirs = state.position.astype(np.float64) - camera.centre
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    colour = eval_sh(sh.astype(np.float64), dirs, sh_degree)
    return composite(proj, colour, opacity, background, (camera.width, camera.height))


def face_camera(
    vertices: np.ndarray,
    labels: dict[str, np.ndarray] | None = None,
    size: int = 512,
    yaw_deg: float = 0.0,
    fov_y_deg: float = 20.0,
) -> Camera:
    """A camera looking at the face of a head (vertices (V, 3), FLAME axes: y up, face towards +z).

    Frames the head without the neck (``neck`` label when present), orbiting ``yaw_deg`` about the vertical.
    """
    pts = vertices
    if labels and "neck" in labels and (~labels["neck"]).sum() > 3:
        pts = vertices[~labels["neck"]]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    target = (lo + hi) / 2
    half = 0.56 * max(hi[1] - lo[1], hi[0] - lo[0])
    dist = half / np.tan(np.radians(fov_y_deg) / 2) + (hi[2] - target[2])
    a = np.radians(yaw_deg)
    eye = target + dist * np.array([np.sin(a), 0.0, np.cos(a)])
    return Camera.look_at(eye, target, fov_y_deg=fov_y_deg, width=size, height=size)


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an (H, W, 3) float image in 0..1 as PNG."""
    import matplotlib.image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    matplotlib.image.imsave(str(path), np.clip(image, 0.0, 1.0))
    return path
