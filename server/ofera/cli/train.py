"""`ofera avatar train` (added to the avatar app by :func:`register`) and `ofera mia experiment` (``mia_app``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from .errors import CliError, user_errors

mia_app = typer.Typer(help="MiA (mapper-integrated avatar): the with/without-MiA experiment.", no_args_is_help=True)


def _need_torch() -> None:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise CliError("this command needs torch: pip install 'ofera[train]'") from None


def train(
    capture: Annotated[Path, typer.Argument(help="Capture folder (layout: server/ofera/training/LAYOUT.md).")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output folder: checkpoint.pt, avatar.npz, history.json, "
                                                          "preview.png.")],
    mode: Annotated[str, typer.Option(help="'mia': FLAME values = EPM(BDA(blendshapes)); 'tracker': tracker.npz "
                                           "(the baseline without MiA).")] = "mia",
    epm: Annotated[str, typer.Option(help="EPM ONNX for --mode mia ('default': the shipped one).")] = "default",
    bda: Annotated[Path | None, typer.Option(help="BDA .npz applied before the EPM (default: identity).")] = None,
    head: Annotated[str, typer.Option(help="Head model: 'default', a FLAME .pkl or an OFERA head .npz.")] = "default",
    init: Annotated[str, typer.Option(help="'mesh' (fresh Gaussians on the head's faces) or an OFERA avatar .npz "
                                           "whose Gaussians start the training.")] = "mesh",
    per_face: Annotated[int, typer.Option(help="With --init mesh: Gaussians per face.")] = 1,
    iterations: Annotated[int, typer.Option(help="Optimisation steps (total, also when resuming).")] = 3000,
    views_per_step: Annotated[int, typer.Option(help="Cameras per step (0: all cameras of the frame).")] = 0,
    perceptual: Annotated[Path | None, typer.Option(help="VGG16 (torchvision state_dict) or LPIPS weights .pth: "
                                                         "adds the perceptual term instead of SSIM.")] = None,
    w_ssim: Annotated[float, typer.Option(help="Weight of 1 - SSIM (without --perceptual).")] = 0.2,
    w_perceptual: Annotated[float, typer.Option(help="Weight of the perceptual term.")] = 0.1,
    w_laplacian: Annotated[float, typer.Option(help="Weight of the Laplacian smoothness of the basis correction.")]
    = 0.5,
    w_basis: Annotated[float, typer.Option(help="Weight of the L2 size of the basis correction (mm^2).")] = 1e-3,
    w_flame: Annotated[float, typer.Option(help="Weight of the FLAME-value refinement penalty.")] = 1.0,
    w_scale: Annotated[float, typer.Option(help="Weight of the Gaussian scale regulariser.")] = 1.0,
    correct_basis: Annotated[bool, typer.Option(help="Learn per-avatar corrections of the expression basis.")]
    = True,
    refine_flame: Annotated[bool, typer.Option(help="Learn per-frame offsets of the FLAME values (regularised).")]
    = False,
    background: Annotated[float, typer.Option(help="Background grey level 0..1 (images with alpha are composited "
                                                   "over it).")] = 1.0,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    resume: Annotated[bool, typer.Option("--resume", help="Continue from OUT/checkpoint.pt.")] = False,
    checkpoint_every: Annotated[int, typer.Option(help="Save a checkpoint every N steps.")] = 500,
    threads: Annotated[int, typer.Option(help="torch CPU threads (0: torch's default).")] = 1,
) -> None:
    """Train a Gaussian avatar on a multi-view capture (with the mapper in the loop for --mode mia)."""
    _need_torch()
    import numpy as np
    import torch

    from ..head import HeadModelError, load_head
    from ..training.data import CaptureError, read_capture
    from ..training.trainer import TrainConfig, Trainer, load_checkpoint

    if threads:
        torch.set_num_threads(threads)
    if mode not in ("mia", "tracker"):
        raise CliError(f"--mode {mode!r}: use 'mia' or 'tracker'")
    try:
        cap = read_capture(capture, background=background)
        model = load_head(head)
    except (CaptureError, HeadModelError) as exc:
        raise CliError(str(exc)) from None
    shape = None
    if mode == "tracker":
        if cap.tracker is None:
            raise CliError(f"{capture}: --mode tracker needs tracker.npz (per-frame 68 FLAME values)")
        flame = cap.tracker
    else:
        from ..mapping.runtime import Mapper, MapperError

        try:
            mapper = Mapper.default(bda) if epm == "default" else Mapper.load(epm, bda)
        except (MapperError, FileNotFoundError) as exc:
            raise CliError(str(exc)) from None
        flame = mapper.map_batch(cap.blendshapes)
    shape_file = capture / "tracker.npz"
    if shape_file.is_file():
        with np.load(shape_file, allow_pickle=False) as z:
            shape = z["shape"] if "shape" in z.files else None

    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoint.pt"
    config = TrainConfig(iterations=iterations, views_per_step=views_per_step, w_ssim=w_ssim,
                         w_perceptual=w_perceptual, w_laplacian=w_laplacian, w_basis=w_basis, w_flame=w_flame,
                         w_scale=w_scale, correct_basis=correct_basis, refine_flame=refine_flame,
                         background=background, seed=seed, checkpoint_every=checkpoint_every)
    state = None
    if resume:
        if not ckpt.is_file():
            raise CliError(f"{ckpt}: nothing to resume (train without --resume first)")
        state = load_checkpoint(ckpt)
        if state.get("mode", mode) != mode:
            raise CliError(f"{ckpt} was trained with --mode {state['mode']}; resume with the same mode")
        config = TrainConfig.from_dict(state["config"] | {"iterations": iterations})
    avatar = _initial_avatar(model, init, per_face, config.correct_basis, seed, shape, state)
    perc = None
    if perceptual is not None:
        from ..training.losses import VGGPerceptual

        perc = VGGPerceptual.load(perceptual)
    trainer = Trainer(avatar, cap, np.asarray(flame, np.float32), config, perceptual=perc)
    if state is not None:
        trainer.load_state_dict(state)
        print(f"resuming at step {trainer.iteration} of {iterations}")
    extra = {"mode": mode, "head": head, "capture": str(capture)}
    trainer.run(checkpoint=ckpt, extra=extra)
    _write_outputs(trainer, out, flame)
    print(f"wrote {ckpt}, {out / 'avatar.npz'}, {out / 'history.json'}, {out / 'preview.png'}")


def _initial_avatar(model, init: str, per_face: int, correct_basis: bool, seed: int, shape, state):
    from ..training.model import TrainableAvatar

    if state is not None:
        return TrainableAvatar.from_attributes(model, state["avatar"])
    if init == "mesh":
        from ..head.render import vertex_colours

        col = vertex_colours(model)[model.faces].mean(axis=1)
        return TrainableAvatar.init_on_mesh(model, None, col, per_face=per_face, seed=seed,
                                            correct_basis=correct_basis, shape=shape)
    from ..avatar import AvatarError, load_avatar
    from ..training.convert import from_gaussian_avatar

    try:
        return from_gaussian_avatar(load_avatar(init), correct_basis=correct_basis)
    except AvatarError as exc:
        raise CliError(str(exc)) from None


def _write_outputs(trainer, out: Path, flame) -> None:
    import numpy as np

    from ..training.convert import to_gaussian_avatar
    from ..training.experiment import save_grid
    from ..training.trainer import render_frames

    (out / "history.json").write_text(json.dumps(trainer.history))
    try:
        from ..avatar import save_avatar

        save_avatar(to_gaussian_avatar(trainer.avatar, name=out.name or "trained"), out / "avatar.npz")
    except ImportError:  # pragma: no cover - the avatar package is part of the distribution
        pass
    cap = trainer.capture
    i = int(trainer.train_idx[0])
    pred = render_frames(trainer.avatar, np.asarray(flame)[i : i + 1], cap.cameras, trainer.config.background)[0]
    gt = np.stack([cap.image(c.name, i) for c in cap.cameras])
    save_grid(out / "preview.png", {"capture": gt, "avatar": pred}, title=f"frame {cap.frames[i]}")


def register(avatar_app: typer.Typer) -> None:
    """Add ``train`` to the ``ofera avatar`` app (called by ``ofera.cli.avatar``)."""
    avatar_app.command("train")(user_errors()(train))


@mia_app.command("experiment")
@user_errors()
def experiment(
    quick: Annotated[bool, typer.Option("--quick", help="Small and short (64 px, 3 cameras, 700 steps).")] = False,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the results as JSON here.")] = None,
    grid: Annotated[Path | None, typer.Option("--grid", help="Write a PNG grid GT / without / with MiA here.")]
    = None,
    epm: Annotated[str, typer.Option(help="EPM ONNX driving the avatars ('default': the shipped one, or a ridge "
                                          "stand-in when it is missing).")] = "default",
    iterations: Annotated[int | None, typer.Option(help="Override the number of training steps.")] = None,
    seed: Annotated[int, typer.Option(help="Subject and training seed.")] = 0,
    threads: Annotated[int, typer.Option(help="torch CPU threads (1 is fastest for these small tensors, and "
                                               "reproducible).")] = 1,
    tune: Annotated[bool, typer.Option("--tune", help="Also choose learning-rate scale and views per step per arm "
                                                      "on the validation frames (6 trainings per arm).")] = False,
) -> None:
    """Train one avatar without MiA (tracker values) and one with MiA (EPM values) on a synthetic capture, drive
    both with the EPM on held-out frames, and compare PSNR / SSIM against the ground truth. Hyperparameters
    (the step kept, and with --tune the learning rates and views) are chosen on validation frames."""
    _need_torch()
    from dataclasses import replace

    import torch

    from ..training.experiment import FULL, QUICK, run_experiment, write_json

    torch.set_num_threads(max(1, threads))
    cfg = QUICK if quick else FULL
    cfg = replace(cfg, seed=seed, **({"iterations": iterations} if iterations else {}))
    res = run_experiment(cfg, epm=None if epm == "default" else epm, grid=grid, tune=tune)
    summary = {k: res[k] for k in ("psnr", "ssim", "val_psnr")}
    print(json.dumps(summary, indent=1))
    if json_out is not None:
        write_json(res, json_out)
        print(f"wrote {json_out}")
    if grid is not None:
        print(f"wrote {grid}")
