"""The CPU preview renderer (projection, compositing) and the `ofera avatar` command."""

from __future__ import annotations

import json

import numpy as np
import pytest
from ofera.avatar.camera import Camera
from ofera.avatar.render import composite, covariance_3d, face_camera, project_gaussians, render_state
from ofera.avatar.state import GaussianState
from ofera.cli.main import app
from plyfile import PlyData
from test_avatar_formats import default_avatar  # noqa: F401  (session fixture)
from test_avatar_importers import flame, write_fate_checkpoint, write_gaussianavatars  # noqa: F401
from typer.testing import CliRunner


def test_projection_of_an_isotropic_gaussian():
    cam = Camera.look_at([0, 0, 1.0], [0, 0, 0], fov_y_deg=30, width=100, height=80)
    cov = covariance_3d(np.array([[0, 0, 0, 1.0]]), np.array([[0.01, 0.01, 0.01]]))
    p = project_gaussians(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]]), np.repeat(cov, 2, 0), cam)
    assert np.allclose(p.mean[0], [50, 40]) and np.isclose(p.depth[0], 1.0)
    sigma_px = cam.fx * 0.01 / 1.0
    assert np.allclose(p.cov[0], np.eye(2) * (sigma_px**2 + 0.3))
    assert np.allclose(p.conic[0], [1 / (sigma_px**2 + 0.3), 0, 1 / (sigma_px**2 + 0.3)])
    assert p.visible.tolist() == [True, False]  # the second is behind the camera
    # image x grows to the right (+x world), y downwards (+y world is up)
    q = project_gaussians(np.array([[0.1, 0.1, 0.0]]), cov, cam)
    assert q.mean[0, 0] > 50 and q.mean[0, 1] < 40


def test_composite_equals_sequential_blending():
    rng = np.random.default_rng(0)
    n, w, h = 60, 24, 20
    cam = Camera.look_at([0, 0, 1.0], [0, 0, 0], fov_y_deg=40, width=w, height=h)
    pos = rng.normal(scale=0.08, size=(n, 3))
    rot = rng.normal(size=(n, 4))
    rot /= np.linalg.norm(rot, axis=1, keepdims=True)
    cov = covariance_3d(rot, rng.uniform(0.005, 0.05, (n, 3)))
    p = project_gaussians(pos, cov, cam)
    colour, opacity = rng.random((n, 3)), rng.uniform(0.2, 1.0, n)
    image = composite(p, colour, opacity, (0.1, 0.2, 0.3), (w, h), chunk=7)
    ref = np.zeros((h, w, 3))
    for y in range(h):
        for x in range(w):
            t, c = 1.0, np.zeros(3)
            for i in np.argsort(p.depth, kind="stable"):
                if not p.visible[i] or t < 1e-4:
                    continue
                d = np.array([x + 0.5, y + 0.5]) - p.mean[i]
                a, b, cc = p.conic[i]
                alpha = min(0.99, opacity[i] * np.exp(-0.5 * (a * d[0] ** 2 + cc * d[1] ** 2) - b * d[0] * d[1]))
                if alpha < 1 / 255:
                    continue
                c += colour[i] * alpha * t
                t *= 1 - alpha
            ref[y, x] = c + t * np.array([0.1, 0.2, 0.3])
    assert np.allclose(image, ref, atol=1e-9)


def test_render_default_avatar_is_not_blank(default_avatar):  # noqa: F811
    a = default_avatar
    cam = face_camera(a.head.v_template, a.head.vertex_labels, size=96)
    image = render_state(a.neutral(), a.opacity, a.sh, cam)
    assert image.shape == (96, 96, 3) and np.all(np.isfinite(image))
    covered = np.abs(image - 1.0).max(axis=2) > 0.05
    assert 0.3 < covered.mean() < 0.95 and covered[48, 48]  # the face fills the middle, background around
    centre = image[30:70, 25:71]
    assert centre.std() > 0.05 and centre[..., 0].mean() > centre[..., 2].mean()  # features on warm skin


def test_empty_state_renders_the_background():
    """An empty state renders the background."""
    state = GaussianState(np.zeros((0, 3), np.float32), np.zeros((0, 4), np.float32), np.zeros((0, 3), np.float32))
    cam = Camera.look_at([0, 0, 1.0], [0, 0, 0], width=8, height=8)
    assert np.allclose(render_state(state, np.zeros(0), np.zeros((0, 1, 3)), cam, background=(0, 0, 0)), 0)


@pytest.fixture(scope="module")
def runner():
    return CliRunner()


def test_cli_info_export_render(default_avatar, runner, tmp_path):  # noqa: F811
    res = runner.invoke(app, ["avatar", "info", "default", "--json"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.stdout)
    assert info["count"] >= 100_000 and info["sh_degree"] == 3 and info["binding"] == "triangle"
    assert 0 < info["movable"] < info["count"]
    res = runner.invoke(app, ["avatar", "export", "default", "-o", str(tmp_path / "x.ply"), "--jaw", "15",
                              "--expr", "0=1.5", "--eyes", "10,-5"])
    assert res.exit_code == 0, res.output
    ply = PlyData.read(str(tmp_path / "x.ply"))
    assert ply.byte_order == "<" and ply["vertex"].count == info["count"]
    res = runner.invoke(app, ["avatar", "render", "default", "-o", str(tmp_path / "x.png"), "--size", "64",
                              "--jaw", "20"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "x.png").read_bytes()[:4] == b"\x89PNG"


def test_cli_errors_are_one_line(runner, tmp_path):
    for args in (["avatar", "info", str(tmp_path / "none.npz")],
                 ["avatar", "export", "default", "-o", str(tmp_path / "y.ply"), "--expr", "nonsense"]):
        res = runner.invoke(app, args)
        assert res.exit_code == 2 and res.output.startswith("error: ") and res.output.count("\n") == 1, res.output


def test_cli_import_both_formats(runner, tmp_path, flame):  # noqa: F811
    rng = np.random.default_rng(1)
    flame_path, raw = flame
    write_gaussianavatars(tmp_path / "ga", rng, n=300)
    res = runner.invoke(app, ["avatar", "import", "gaussianavatars", str(tmp_path / "ga"), "--head",
                              str(flame_path), "-o", str(tmp_path / "ga.npz")])
    assert res.exit_code == 0, res.output
    assert "5143 vertices, 10144 faces" in res.output
    write_fate_checkpoint(tmp_path / "f.pth", raw, rng, n=200)
    res = runner.invoke(app, ["avatar", "import", "fate", str(tmp_path / "f.pth"), "--head",
                              str(flame_path), "-o", str(tmp_path / "f.npz")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["avatar", "info", str(tmp_path / "f.npz"), "--json"])
    assert json.loads(res.stdout)["binding"] == "barycentric" and json.loads(res.stdout)["count"] == 200
    res = runner.invoke(app, ["avatar", "import", "fate", str(tmp_path / "f.pth"), "--head", "default", "-o",
                              str(tmp_path / "g.npz")])
    assert res.exit_code == 2 and res.output.startswith("error: ")
