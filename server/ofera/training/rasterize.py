"""A differentiable 3D Gaussian rasteriser in plain PyTorch (CPU or any device), for training.

The maths is 3D Gaussian splatting's (Kerbl et al. 2023):

    p_cam  = R p + t                                  world -> camera (OpenCV axes: x right, y down, z forward)
    (u, v) = (fx x / z + cx, fy y / z + cy)           pixel coordinates; pixel (i, j) has its centre at (i+.5, j+.5)
    J      = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]   (x/z, y/z clamped to 1.3 x the half field of view)
    Sigma  = R_q S S^T R_q^T                          3D covariance from the unit quaternion q and the scales s
    Sigma' = J R Sigma R^T J^T + 0.3 I                EWA splatting, plus 3DGS's 0.3 px^2 low-pass
    alpha  = min(0.99, o exp(-1/2 d^T Sigma'^-1 d))   d = pixel centre - (u, v); alpha < alpha_min counts as 0
    C      = sum_i c_i alpha_i T_i + T_end bg,   T_i = prod_{j<i} (1 - alpha_j), sorted near to far

Unlike the CUDA rasteriser it has no early stop at T < 1e-4 (what lies behind contributes under 1e-4).
Evaluation is per pixel: every Gaussian contributes (pixel, Gaussian) pairs for the pixel centres inside the
bounding box of the ellipse where its alpha can reach ``alpha_min`` (so the threshold, not a box, decides
what is drawn, as in 3DGS); pairs are sorted by pixel and, within a pixel, by depth; transmittance is a
segmented cumulative sum of log(1 - alpha). Pairs are processed in chunks of whole pixels (``max_elements``
pairs at most), which bounds memory. Everything that carries gradients is ordinary autograd; only the pair
lists and the sort are built without gradients (they are piecewise constant), so gradients reach positions,
rotations, scales, opacities and colours.

Quaternions are (w, x, y, z) and need not be normalised; scales are linear (metres); opacities linear in
[0, 1]; colours are any number of channels (RGB usually).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..avatar.camera import Camera

LOW_PASS = 0.3  # px^2 added to every 2D covariance (3DGS)
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
SUPPORT_ALPHA = 1e-5  # with alpha_min = 0: splats are cut where their alpha falls below this


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) (w, x, y, z), any norm -> (..., 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities (N rows)."""

    means2d: torch.Tensor  # (N, 2) pixels
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c): d^T [[a, b], [b, c]] d
    depths: torch.Tensor  # (N,) camera z
    radii: torch.Tensor  # (N,) int, 3-sigma radius in pixels; 0 = culled
    cov2d: torch.Tensor  # (N, 2, 2)


def project(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, camera: Camera,
            near: float = 0.01, low_pass: float = LOW_PASS) -> Projected:
    """Project 3D Gaussians (means (N,3), quats (N,4) wxyz, scales (N,3)) to 2D through ``camera``."""
    dt, dev = means.dtype, means.device
    rot = torch.as_tensor(camera.R, dtype=dt, device=dev)
    k = torch.as_tensor(camera.K, dtype=dt, device=dev)
    p = means @ rot.T + torch.as_tensor(camera.t, dtype=dt, device=dev)
    x, y, z = p.unbind(-1)
    zs = z.clamp_min(near)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    # 3DGS clamps the Jacobian's x/z, y/z to 1.3 x the half field of view (off-screen splats stay sane).
    lim_x, lim_y = 1.3 * 0.5 * camera.width / fx, 1.3 * 0.5 * camera.height / fy
    tx = torch.maximum(torch.minimum(x / zs, lim_x), -lim_x)
    ty = torch.maximum(torch.minimum(y / zs, lim_y), -lim_y)
    zero = torch.zeros_like(zs)
    jac = torch.stack([fx / zs, zero, -fx * tx / zs, zero, fy / zs, -fy * ty / zs], -1).reshape(-1, 2, 3)
    m = quat_to_matrix(quats) * scales[:, None, :]  # R_q S
    t_mat = jac @ rot @ m  # (N, 2, 3)
    cov = t_mat @ t_mat.transpose(1, 2) + low_pass * torch.eye(2, dtype=dt, device=dev)
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], -1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lam)).to(torch.int64)
        ok = (z > near) & (det > 0)
        ok &= (means2d[:, 0] + radii > 0) & (means2d[:, 0] - radii < camera.width)
        ok &= (means2d[:, 1] + radii > 0) & (means2d[:, 1] - radii < camera.height)
        radii = torch.where(ok, radii, torch.zeros_like(radii))
    return Projected(means2d, conics, z, radii, cov)


@dataclass
class Render:
    image: torch.Tensor  # (H, W, C)
    alpha: torch.Tensor  # (H, W) accumulated opacity, 1 - T_end
    depth: torch.Tensor  # (H, W) alpha-weighted depth (not normalised by alpha)


def _pairs(proj: Projected, opacities: torch.Tensor, width: int, height: int,
           support_alpha: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(pixel id, Gaussian id) for every pixel centre where a Gaussian's alpha reaches ``support_alpha``, sorted
    by pixel, then by depth (near first) within a pixel. No gradients (integer bookkeeping): candidates are the
    pixels in the bounding box of the ellipse o exp(-d^T Sigma^-1 d / 2) >= support_alpha, then tested."""
    dev = proj.means2d.device
    with torch.no_grad():
        order = torch.argsort(proj.depths)
        g = order[proj.radii[order] > 0]  # visible, near to far
        c2 = proj.means2d[g]
        o = opacities[g].clamp(0, ALPHA_MAX)
        k2 = 2.0 * torch.log((o / support_alpha).clamp_min(1.0))  # Mahalanobis^2 of the threshold
        ext = torch.sqrt(k2[:, None] * torch.stack([proj.cov2d[g, 0, 0], proj.cov2d[g, 1, 1]], -1))
        lo = torch.ceil(c2 - ext - 0.5).clamp_min(0).long()  # first pixel whose centre (i + .5) is inside
        hi = torch.floor(c2 + ext - 0.5).long()
        hi = torch.minimum(hi, torch.tensor([width - 1, height - 1], device=dev))
        size = (hi - lo + 1).clamp_min(0)
        count = size[:, 0] * size[:, 1]
        keep = count > 0
        g, lo, size, count, c2, k2 = g[keep], lo[keep], size[keep], count[keep], c2[keep], k2[keep]
        j = torch.repeat_interleave(torch.arange(len(g), device=dev), count)  # box of each candidate
        box = torch.cat([lo.to(c2.dtype), size[:, :1].to(c2.dtype), (torch.cumsum(count, 0) - count)[:, None].to(
            c2.dtype), c2, k2[:, None], proj.conics[g]], 1)[j]  # one gather: lo x y, row, first, centre, k2, conic
        k = torch.arange(len(j), device=dev, dtype=c2.dtype) - box[:, 3]  # index inside the box
        ky = torch.div(k, box[:, 2], rounding_mode="floor")
        px = box[:, 0] + (k - ky * box[:, 2])
        py = box[:, 1] + ky
        dx = px + 0.5 - box[:, 4]
        dy = py + 0.5 - box[:, 5]
        maha = box[:, 7] * dx * dx + box[:, 9] * dy * dy + 2 * box[:, 8] * dx * dy
        inside = maha <= box[:, 6] * (1 + 1e-6)  # alpha >= support_alpha (up to rounding)
        pid = (py * width + px)[inside].to(torch.int32)
        gid = g[j[inside]]
        pid, perm = torch.sort(pid, stable=True)  # stable: keeps near-to-far inside each pixel
        return pid.long(), gid[perm]


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colours: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | float | None = None,
    alpha_min: float = ALPHA_MIN,
    max_elements: int = 4_000_000,
    near: float = 0.01,
    with_depth: bool = True,
) -> Render:
    """Render Gaussians (N rows; see the module docstring for conventions) into ``camera``'s image.

    Work is one (pixel, Gaussian) pair per pixel centre where the Gaussian's alpha reaches ``alpha_min`` (so
    nothing is cut that 3DGS would draw); pairs are processed in chunks of whole pixels of at most
    ``max_elements`` pairs (bounds memory). Transmittance is a segmented cumulative sum of log(1 - alpha) per
    pixel, done in float64 so long pixel lists lose no precision. ``with_depth`` False skips the depth map.
    """
    dt, dev = means.dtype, means.device
    ch = colours.shape[1]
    w, h = camera.width, camera.height
    proj = project(means, quats, scales, camera, near=near)
    bg = torch.zeros(ch, dtype=dt, device=dev) if background is None else torch.as_tensor(
        background, dtype=dt, device=dev).expand(ch)
    opac = opacities.reshape(-1)
    pid_all, gid_all = _pairs(proj, opac.detach(), w, h, alpha_min if alpha_min > 0 else SUPPORT_ALPHA)
    # One gather per pair for everything the pair needs (the backward pass is then one scatter).
    feats = [proj.means2d, proj.conics, opac[:, None], colours]
    if with_depth:
        feats.append(proj.depths[:, None])
    packed = torch.cat(feats, 1)  # (N, 6 + C [+ 1])
    out = torch.zeros(h * w, packed.shape[1] - 6, dtype=dt, device=dev)  # colour [, depth] per pixel
    log_t_end = torch.zeros(h * w, dtype=torch.float64, device=dev)
    bounds = [0]  # chunk boundaries at pixel changes: no pixel's list is split
    while bounds[-1] < len(pid_all):
        stop = min(bounds[-1] + max_elements, len(pid_all))
        if stop < len(pid_all):
            last = pid_all[stop - 1]
            stop = int(torch.searchsorted(pid_all, last, right=False))
            if stop <= bounds[-1]:  # one pixel longer than max_elements: take it whole
                stop = int(torch.searchsorted(pid_all, last, right=True))
        bounds.append(stop)
    for s0, s1 in zip(bounds[:-1], bounds[1:]):
        pid, gid = pid_all[s0:s1], gid_all[s0:s1]
        f = packed[gid]
        mx, my, ca, cb, cc, o = f[:, :6].unbind(1)  # unbind: one backward op, not one per column
        px = (pid % w).to(dt) + 0.5
        py = torch.div(pid, w, rounding_mode="floor").to(dt) + 0.5
        dx, dy = px - mx, py - my
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        alpha = (o * torch.exp(power.clamp_max(0.0))).clamp_max(ALPHA_MAX)
        if alpha_min > 0:
            alpha = torch.where(alpha < alpha_min, torch.zeros_like(alpha), alpha)
        log1m = torch.log1p(-alpha.double())
        excl = torch.cumsum(log1m, 0) - log1m  # exclusive, over the whole chunk
        with torch.no_grad():
            new_px = torch.ones_like(pid, dtype=torch.bool)
            new_px[1:] = pid[1:] != pid[:-1]
            seg_first = torch.cummax(torch.where(new_px, torch.arange(len(pid), device=dev), 0), 0).values
        weight = alpha * torch.exp(excl - excl[seg_first]).to(dt)  # alpha_i T_i
        out = out.index_add(0, pid, weight[:, None] * f[:, 6:])
        log_t_end = log_t_end.index_add(0, pid, log1m)
    t_end = torch.exp(log_t_end).to(dt)
    image = out[:, :ch] + t_end[:, None] * bg
    depth = out[:, ch] if with_depth else torch.zeros(h * w, dtype=dt, device=dev)
    return Render(image.reshape(h, w, ch), (1.0 - t_end).reshape(h, w), depth.reshape(h, w))


def rasterize_gsplat(means, quats, scales, opacities, colours, camera: Camera, background=None) -> Render:
    """The same render through gsplat's CUDA kernels (optional: ``pip install gsplat``, needs a CUDA GPU; not
    exercised on CPU-only machines). Depth is not produced (zeros)."""
    try:
        from gsplat import rasterization
    except ImportError as exc:  # pragma: no cover - optional dependency
        raise RuntimeError("gsplat is not installed: pip install gsplat (needs CUDA), or use rasterize()") from exc
    dt, dev = means.dtype, means.device
    view = torch.eye(4, dtype=dt, device=dev)
    view[:3, :3] = torch.as_tensor(camera.R, dtype=dt, device=dev)
    view[:3, 3] = torch.as_tensor(camera.t, dtype=dt, device=dev)
    k = torch.as_tensor(camera.K, dtype=dt, device=dev)
    ch = colours.shape[1]
    bg = None if background is None else torch.as_tensor(background, dtype=dt, device=dev).expand(1, ch)
    img, alpha, _ = rasterization(means, quats / quats.norm(dim=-1, keepdim=True), scales, opacities.reshape(-1),
                                  colours, view[None], k[None], camera.width, camera.height, eps2d=LOW_PASS,
                                  render_mode="RGB", backgrounds=bg)
    return Render(img[0], alpha[0, ..., 0], torch.zeros_like(alpha[0, ..., 0]))
