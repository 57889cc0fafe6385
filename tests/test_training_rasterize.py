"""The differentiable Gaussian rasteriser: gradients (gradcheck), a brute-force reference, memory chunking."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from ofera.avatar.camera import Camera  # noqa: E402
from ofera.training.rasterize import SUPPORT_ALPHA, project, quat_to_matrix, rasterize  # noqa: E402

torch.set_num_threads(1)


def scene(n: int, seed: int = 0, dtype=torch.float64, spread: float = 0.04, size: float = 0.012):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * spread
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * size + size / 3
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.6 + 0.3
    cols = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opac, cols


def reference(means, quats, scales, opac, cols, cam: Camera, bg, alpha_min):
    """Per-pixel loop in numpy: project (same EWA maths), sort, composite front to back; every Gaussian at every
    pixel, cut only by alpha_min (or, with alpha_min = 0, where alpha < SUPPORT_ALPHA)."""
    m, q, s, o, c = (t.detach().numpy() for t in (means, quats, scales, opac, cols))
    rot = quat_to_matrix(torch.as_tensor(q)).numpy()
    p = m @ cam.R.T + cam.t
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    img = np.zeros((cam.height, cam.width, 3))
    gs = []
    for i in np.argsort(p[:, 2]):
        x, y, z = p[i]
        jac = np.array([[fx / z, 0, -fx * x / z**2], [0, fy / z, -fy * y / z**2]])
        cov2 = jac @ cam.R @ (rot[i] @ np.diag(s[i] ** 2) @ rot[i].T) @ cam.R.T @ jac.T + 0.3 * np.eye(2)
        gs.append((np.array([fx * x / z + cx, fy * y / z + cy]), np.linalg.inv(cov2), o[i], c[i]))
    for py in range(cam.height):
        for px in range(cam.width):
            t, col = 1.0, np.zeros(3)
            for mu, inv, oi, ci in gs:
                d = np.array([px + 0.5, py + 0.5]) - mu
                a = min(0.99, oi * np.exp(-0.5 * d @ inv @ d))
                if a < (alpha_min or SUPPORT_ALPHA):
                    continue
                col += t * a * ci
                t *= 1 - a
            img[py, px] = col + t * bg
    return img


def test_gradcheck_tiny_scene():
    cam = Camera.look_at((0.02, -0.01, 0.25), (0, 0, 0), fov_x_deg=20, width=8, height=8)
    means, quats, scales, opac, cols = scene(4, seed=1)
    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, cols))

    def fn(*args):
        r = rasterize(*args, cam, background=0.3, alpha_min=0.0)
        return r.image, r.alpha

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_gradients_reach_every_attribute():
    cam = Camera.look_at((0.0, 0.0, 0.3), (0, 0, 0), fov_x_deg=25, width=16, height=16)
    inputs = tuple(t.clone().requires_grad_(True) for t in scene(6, seed=2))
    rasterize(*inputs, cam).image.square().sum().backward()
    for t in inputs:
        assert t.grad is not None and t.grad.abs().sum() > 0


@pytest.mark.parametrize("alpha_min", [0.0, 1 / 255])
def test_matches_bruteforce_reference(alpha_min):
    cam = Camera.look_at((0.05, 0.03, 0.3), (0, 0, 0), fov_x_deg=25, width=20, height=16)
    sc = scene(12, seed=3)
    ours = rasterize(*sc, cam, background=0.5, alpha_min=alpha_min).image.numpy()
    ref = reference(*sc, cam, 0.5, alpha_min)
    # alpha_min > 0: the same maths exactly; alpha_min = 0: splats end at a box around alpha = SUPPORT_ALPHA
    np.testing.assert_allclose(ours, ref, atol=1e-9 if alpha_min else 1e-4)


def test_chunking_does_not_change_the_image():
    cam = Camera.look_at((0.0, 0.0, 0.3), (0, 0, 0), fov_x_deg=25, width=24, height=24)
    sc = scene(40, seed=4, dtype=torch.float32)
    a = rasterize(*sc, cam).image
    b = rasterize(*sc, cam, max_elements=50).image
    torch.testing.assert_close(a, b, atol=1e-5, rtol=0)


def test_projection_of_centre_and_culling():
    cam = Camera.look_at((0.0, 0.0, 1.0), (0, 0, 0), fov_x_deg=40, width=32, height=32)
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])  # on axis; behind the camera
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    scales = torch.full((2, 3), 0.01)
    p = project(means, quats, scales, cam)
    torch.testing.assert_close(p.means2d[0], torch.tensor([16.0, 16.0]))
    assert p.radii[0] > 0 and p.radii[1] == 0
    # world +y (up) appears towards the top of the image (smaller row index)
    up = project(torch.tensor([[0.0, 0.1, 0.0]]), quats[:1], scales[:1], cam)
    assert up.means2d[0, 1] < 16


def test_camera_json_round_trip(tmp_path):
    from ofera.avatar.camera import load_cameras, save_cameras

    cams = [Camera.look_at((0.3, 0.1, 0.5), (0, 0, 0), width=40, height=30, name="a"),
            Camera.look_at((-0.3, 0.0, 0.5), (0, 0, 0), width=64, height=64, name="b")]
    save_cameras(cams, tmp_path / "cameras.json")
    back = load_cameras(tmp_path / "cameras.json")
    for c, d in zip(cams, back):
        assert (c.name, c.width, c.height) == (d.name, d.width, d.height)
        np.testing.assert_allclose(c.K, d.K)
        np.testing.assert_allclose(c.R, d.R)
        np.testing.assert_allclose(c.t, d.t)


def test_matches_avatar_preview_renderer():
    """Close agreement with the numpy preview renderer ``ofera.avatar.render`` (independent implementation)."""
    prev = pytest.importorskip("ofera.avatar.render")
    cam = Camera.look_at((0.03, 0.02, 0.3), (0, 0, 0), fov_x_deg=25, width=40, height=32)
    means, quats, scales, opac, cols = (t.numpy() for t in scene(60, seed=5))
    ours = rasterize(*(torch.as_tensor(a) for a in (means, quats, scales, opac, cols)), cam, background=1.0)
    xyzw = np.concatenate([quats[:, 1:], quats[:, :1]], 1) / np.linalg.norm(quats, axis=1, keepdims=True)
    proj = prev.project_gaussians(means, prev.covariance_3d(xyzw, scales), cam)
    theirs = prev.composite(proj, cols, opac, (1.0, 1.0, 1.0), (cam.width, cam.height))
    diff = np.abs(ours.image.numpy() - theirs)
    assert diff.mean() < 1e-3 and diff.max() < 0.02, (diff.mean(), diff.max())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat path needs CUDA (not run on CPU-only machines)")
def test_gsplat_agrees_on_cuda():
    pytest.importorskip("gsplat")
    from ofera.training.rasterize import rasterize_gsplat

    cam = Camera.look_at((0.03, 0.02, 0.3), (0, 0, 0), fov_x_deg=25, width=32, height=32)
    sc = [t.float().cuda() for t in scene(30, seed=6)]
    ours = rasterize(*sc, cam, background=0.0).image
    theirs = rasterize_gsplat(*sc, cam, background=0.0).image
    assert (ours - theirs).abs().mean() < 0.01
