"""Training: capture layout round trip, losses, binding vs the avatar reference, optimisation, checkpoints, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from ofera.training.data import Capture, CaptureError, read_capture, write_capture  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def tiny(head):
    """A tiny synthetic capture: 2 cameras of 24 px, 3 frames, 300 Gaussians on the nose/mouth region."""
    from ofera.training.synthetic import capture_cameras, degraded_copy, ground_truth_avatar, render_on_meshes

    v, f = head.v_template, head.faces
    c = v[f].mean(axis=1)
    faces = np.flatnonzero((c[:, 2] > 0.06) & (np.abs(c[:, 0]) < 0.03) & (c[:, 1] > -0.05) & (c[:, 1] < 0.0))[:300]
    gt = ground_truth_avatar(head, None, faces=faces)
    cams = capture_cameras(2, 24, distance=0.3, fov_deg=20)
    rng = np.random.default_rng(0)
    flame = np.zeros((3, 68), np.float32)
    flame[:, :10] = rng.normal(0, 1.0, (3, 10))
    flame[:, 50:68] = np.tile([1, 0, 0, 0, 1, 0], 3)
    with torch.no_grad():
        meshes = gt.vertices(torch.as_tensor(flame)).numpy()
    images = render_on_meshes(gt, meshes, cams)
    bs = rng.uniform(0, 1, (3, 51)).astype(np.float32)
    cap = Capture(cams, images, bs, ["a", "b", "c"], tracker=flame, split={"train": ["a", "b"], "test": ["c"]})
    return cap, gt, degraded_copy(gt, seed=3)


@pytest.mark.parametrize("fmt", ["png", "npz"])
def test_capture_round_trip(tmp_path, tiny, fmt):
    cap = tiny[0]
    write_capture(cap, tmp_path / "cap", image_format=fmt)
    back = read_capture(tmp_path / "cap")
    assert back.frames == cap.frames and back.split == cap.split
    assert [c.name for c in back.cameras] == [c.name for c in cap.cameras]
    np.testing.assert_allclose(back.blendshapes, cap.blendshapes, atol=1e-5)
    np.testing.assert_array_equal(back.tracker, cap.tracker)
    for c in cap.cameras:
        np.testing.assert_array_equal(back.images[c.name], cap.images[c.name])
        np.testing.assert_allclose(back.cameras[0].K, cap.cameras[0].K)


def test_capture_errors_say_what_is_wrong(tmp_path, tiny):
    root = write_capture(tiny[0], tmp_path / "cap", image_format="png")
    (root / "frames" / "cam1" / "b.png").unlink()
    with pytest.raises(CaptureError, match="b.png"):
        read_capture(root)
    (root / "blendshapes.csv").write_text("time,eyeBlinkLeft\n0,1\n")
    with pytest.raises(CaptureError, match="'frame'"):
        read_capture(root)
    with pytest.raises(CaptureError, match="no such folder"):
        read_capture(tmp_path / "missing")


def test_blendshapes_csv_accepts_other_layouts(tmp_path, tiny):
    from ofera.mapping.layouts import ARKIT52_NAMES

    root = write_capture(tiny[0], tmp_path / "cap", image_format="npz")
    names = list(reversed(ARKIT52_NAMES))  # any order, tongueOut extra
    rows = [",".join(["frame", *names])]
    for f, w in zip(tiny[0].frames, tiny[0].blendshapes):
        full = dict(zip(ARKIT52_NAMES, [*w.tolist(), 0.5]))
        rows.append(",".join([f, *(str(full[n]) for n in names)]))
    (root / "blendshapes.csv").write_text("\n".join(rows) + "\n")
    np.testing.assert_allclose(read_capture(root).blendshapes, tiny[0].blendshapes, atol=1e-6)


def test_ssim_properties():
    from ofera.training.losses import ssim

    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 32, 32, 3, generator=g, dtype=torch.float64)
    assert abs(float(ssim(x, x)) - 1.0) < 1e-12
    noisy = (x + 0.1 * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    assert 0.0 < float(ssim(x, noisy)) < 0.95
    assert float(ssim(x, noisy)) == pytest.approx(float(ssim(noisy, x)))
    # Constant images: luminance term only, (2 m1 m2 + C1) / (m1^2 + m2^2 + C1)
    a, b = torch.full((1, 16, 16, 1), 0.2, dtype=torch.float64), torch.full((1, 16, 16, 1), 0.4, dtype=torch.float64)
    c1 = 0.01**2
    assert float(ssim(a, b)) == pytest.approx((2 * 0.08 + c1) / (0.04 + 0.16 + c1))
    xs = x.clone().requires_grad_(True)
    (1 - ssim(xs, noisy)).backward()
    assert xs.grad.abs().sum() > 0


def test_laplacian_of_a_rigid_shift_is_zero(head):
    from ofera.training.losses import laplacian_loss, uniform_laplacian

    lap = uniform_laplacian(head.faces, head.num_vertices)
    v = torch.as_tensor(head.v_template, dtype=torch.float32)
    assert float(laplacian_loss(lap, v + torch.tensor([0.01, -0.02, 0.03]), v)) < 1e-12
    bumpy = v + 0.001 * torch.randn(v.shape, generator=torch.Generator().manual_seed(0))
    assert float(laplacian_loss(lap, bumpy, v)) > 1e-8


def test_perceptual_loads_user_weights(tmp_path):
    from ofera.training.losses import VGGPerceptual

    torch.manual_seed(0)
    state = VGGPerceptual({k: v for k, v in _random_vgg_state().items()}).state_dict()
    state |= {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate((64, 128, 256, 512, 512))}
    torch.save(state, tmp_path / "lpips.pth")
    p = VGGPerceptual.load(tmp_path / "lpips.pth")
    x = torch.rand(1, 32, 32, 3)
    assert float(p(x, x)) == 0.0 and float(p(x, x.flip(1))) > 0
    torch.save({"something": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="VGG16"):
        VGGPerceptual.load(tmp_path / "bad.pth")


def _random_vgg_state() -> dict:
    from ofera.training.losses import _VGG16_CFG

    out, c_in, i = {}, 3, 0
    for v in _VGG16_CFG:
        if v == "M":
            i += 1
            continue
        out[f"features.{i}.weight"] = torch.randn(v, c_in, 3, 3) * 0.05
        out[f"features.{i}.bias"] = torch.zeros(v)
        c_in, i = v, i + 2
    return out


def test_split_flame_values_matches_mapping(head):
    from ofera.mapping.flame_values import split_flame_values
    from ofera.training.model import split_flame_values as split_torch

    y = np.random.default_rng(0).normal(size=(4, 68)).astype(np.float32)
    e, r = split_flame_values(y)
    et, rt = split_torch(torch.as_tensor(y))
    np.testing.assert_allclose(et.numpy(), e)
    np.testing.assert_allclose(rt.numpy(), r, atol=1e-6)


def test_corrected_head_equals_torch_head_and_binding_matches_avatar_reference(head, tiny):
    from ofera.head.lbs_torch import TorchHead
    from ofera.training.model import CorrectedHead

    g = torch.Generator().manual_seed(1)
    expr = torch.randn(2, 50, generator=g, dtype=torch.float64)
    rot = torch.eye(3, dtype=torch.float64).expand(2, 5, 3, 3).clone()
    ch = CorrectedHead(head, dtype=torch.float64)
    torch.testing.assert_close(ch(expr, rot), TorchHead(head, dtype=torch.float64)(expr, rot))
    # Gaussians of the trainable avatar == the avatar package's numpy reference deformation.
    pytest.importorskip("ofera.avatar.deform")
    from ofera.training.convert import to_gaussian_avatar

    av = tiny[2]
    with torch.no_grad():
        verts = av.vertices(torch.as_tensor(tiny[0].tracker[:1]))[0]
        ours = av.gaussians(verts)
    ref = to_gaussian_avatar(av).deformer().deform(verts.double().numpy())
    np.testing.assert_allclose(ours["means"].numpy(), ref.position, atol=1e-6)
    np.testing.assert_allclose(ours["scales"].numpy(), ref.scale, rtol=1e-4)
    q = ours["quats"].numpy()
    q_ref = ref.rotation_wxyz()
    assert np.all(np.abs(np.abs(np.sum(q * q_ref, axis=1)) - 1) < 1e-5)


def test_export_round_trip_through_the_avatar_format(tmp_path, tiny):
    from ofera.avatar import load_avatar, save_avatar
    from ofera.training.convert import from_gaussian_avatar, to_gaussian_avatar

    av = tiny[2]
    with torch.no_grad():
        av.head.delta_exprdirs.normal_(0, 1e-4)
    exported = to_gaussian_avatar(av)
    # the correction stays on the vertices the basis moves: the server's static Gaussians stay static
    from ofera.avatar.movable import movable_gaussians

    np.testing.assert_array_equal(exported.movable, movable_gaussians(av.head_model, exported.binding.face))
    path = save_avatar(exported, tmp_path / "a.npz")
    back = from_gaussian_avatar(load_avatar(path), correct_basis=False)
    y = torch.as_tensor(tiny[0].tracker[:1])
    with torch.no_grad():
        a, b = av.gaussians(av.vertices(y)[0]), back.gaussians(back.vertices(y)[0])
    for k in ("means", "scales", "opacities", "colours"):
        torch.testing.assert_close(a[k], b[k], atol=2e-6, rtol=1e-4)


def test_a_few_steps_reduce_the_loss_and_checkpoints_resume(tmp_path, tiny):
    from ofera.training.model import TrainableAvatar
    from ofera.training.trainer import TrainConfig, Trainer, load_checkpoint

    cap, _, start = tiny
    cfg = TrainConfig(iterations=12, seed=0, checkpoint_every=0)

    def fresh():
        return TrainableAvatar.from_attributes(start.head_model, start.attributes())

    tr = Trainer(fresh(), cap, cap.tracker, cfg)
    frames = tr.train_idx.tolist()
    before = sum(float(tr.loss(f, [0, 1])[0].detach()) for f in frames)
    tr.run(iterations=6, checkpoint=tmp_path / "ck.pt", progress=False)
    tr.run(iterations=12, progress=False)
    after = sum(float(tr.loss(f, [0, 1])[0].detach()) for f in frames)
    assert after < 0.9 * before
    # Resume from step 6 and finish: the same parameters as the uninterrupted run.
    state = load_checkpoint(tmp_path / "ck.pt")
    assert state["iteration"] == 6
    tr2 = Trainer(fresh(), cap, cap.tracker, cfg)
    tr2.load_state_dict(state)
    tr2.run(iterations=12, progress=False)
    for k in ("local_xyz", "sh_dc"):
        torch.testing.assert_close(getattr(tr2.avatar, k), getattr(tr.avatar, k), atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(tr2.avatar.head.delta_exprdirs, tr.avatar.head.delta_exprdirs, atol=1e-8, rtol=1e-4)


def test_cli_train_and_resume(tmp_path, tiny):
    import typer
    from ofera.cli.train import register
    from typer.testing import CliRunner

    app = typer.Typer()
    register(app)

    @app.command("noop")
    def noop() -> None:  # a second command keeps typer from collapsing the group
        pass

    cap = tiny[0]
    root = write_capture(cap, tmp_path / "cap", image_format="npz")
    out = tmp_path / "out"
    runner = CliRunner()
    args = ["train", str(root), "-o", str(out), "--mode", "tracker", "--iterations", "2", "--checkpoint-every", "1"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert (out / "checkpoint.pt").is_file() and (out / "preview.png").is_file()
    assert len(json.loads((out / "history.json").read_text())) == 2
    res = runner.invoke(app, [*args[:-4], "--iterations", "3", "--resume"])
    assert res.exit_code == 0, res.output
    assert "resuming at step 2" in res.output
    assert len(json.loads((out / "history.json").read_text())) == 3
    res = runner.invoke(app, ["train", str(tmp_path / "nowhere"), "-o", str(out)])
    assert res.exit_code == 2 and "no such folder" in res.output


def test_mia_experiment_smoke(tmp_path):
    """The experiment end to end on a tiny configuration (numbers meaningless; keys, files, CLI JSON)."""
    from ofera.training.experiment import ExperimentConfig, run_experiment, write_json

    cfg = ExperimentConfig(size=20, cameras=2, train_frames=3, test_frames=2, val_frames=2, iterations=2, val_every=1,
                           grid_frames=2)
    calls = {}

    class Mapper:  # a stand-in for the EPM (keeps the test fast)
        def map_batch(self, w):
            calls["n"] = len(w)
            y = np.zeros((len(w), 68), np.float32)
            y[:, :50] = 0.3 * w[:, :50]
            y[:, 50:] = np.tile([1, 0, 0, 0, 1, 0], 3)
            return y

    res = run_experiment(cfg, grid=tmp_path / "grid.png", log=lambda s: None, mapper=Mapper())
    assert calls["n"] == 7
    for part in (res, res["epm_selected"]):
        for key in ("psnr", "ssim", "val_psnr"):
            assert set(part[key]) == {"mia", "without_mia"}
            assert all(np.isfinite(v) for v in part[key].values())
    for arm in ("mia", "without_mia"):  # the step kept is one of the validation checks (every step here)
        assert res["extra"][arm]["chosen"]["best_step"] in (1, 2)
    assert res["epm_selected"]["chosen"]["mia"] == res["extra"]["mia"]["chosen"]  # MiA validates EPM-driven anyway
    assert (tmp_path / "grid.png").stat().st_size > 1000
    out = write_json(res, tmp_path / "r.json")
    assert json.loads(out.read_text())["psnr"] == res["psnr"]
