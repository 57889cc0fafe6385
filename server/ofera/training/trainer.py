"""Avatar training: the paper's objective on the mesh deformed by given FLAME values (mapper or tracker).

    L = w_l1 |I - I*|_1 + (w_perceptual P(I, I*)  if perceptual weights are given,  else  w_ssim (1 - SSIM(I, I*)))
        + w_laplacian |L (dE psi)|^2 + w_basis |dE|^2        (the expression-basis correction stays smooth and small;
                                                            dE psi is the correction of the mesh before skinning, in mm)
        + w_flame |dy|^2                                     (per-frame refinement dy of the FLAME values, if enabled)
        + w_scale max(0, s_local - 0.6) + w_xyz max(0, |x_local| - 1)   (GaussianAvatars' Gaussian regularisers)

MiA (mapper-integrated avatar) is this objective with the FLAME values y = EPM(BDA(blendshapes)) of the training
video's own blendshapes; the baseline is the same objective with a tracker's values.

Checkpoints are ``torch.save`` of a plain dict (tensors, numbers, strings, lists): load with ``weights_only=True``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch

from .data import Capture
from .losses import VGGPerceptual, laplacian_loss, position_regulariser, scale_regulariser, ssim, uniform_laplacian
from .model import TrainableAvatar
from .rasterize import rasterize

CHECKPOINT_FORMAT = "ofera-avatar-train"
CHECKPOINT_VERSION = 1
MM = 1e3  # regularisers measure displacements in millimetres


@dataclass
class TrainConfig:
    iterations: int = 3000
    views_per_step: int = 0  # 0: every camera of the sampled frame
    lr_xyz: float = 5e-3  # local (face-size) units
    lr_scale: float = 1e-2
    lr_rot: float = 2e-3
    lr_opacity: float = 5e-2
    lr_colour: float = 2e-2  # SH DC units
    lr_basis: float = 2e-5  # metres per expression unit
    lr_flame: float = 1e-3
    w_l1: float = 0.8
    w_ssim: float = 0.2
    w_perceptual: float = 0.1
    w_laplacian: float = 0.5
    w_basis: float = 1e-3
    w_flame: float = 1.0
    w_scale: float = 1.0
    w_xyz: float = 0.01
    correct_basis: bool = True
    refine_flame: bool = False
    background: float = 1.0
    seed: int = 0
    checkpoint_every: int = 500

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


class Trainer:
    """Optimises a :class:`TrainableAvatar` on the frames ``train_idx`` of a capture with FLAME values ``flame``."""

    def __init__(self, avatar: TrainableAvatar, capture: Capture, flame: np.ndarray, config: TrainConfig,
                 train_idx: np.ndarray | None = None, perceptual: VGGPerceptual | None = None) -> None:
        if flame.shape != (capture.num_frames, 68):
            raise ValueError(f"FLAME values {flame.shape}, expected ({capture.num_frames}, 68): one row per frame")
        if config.correct_basis and avatar.head.delta_exprdirs is None:
            raise ValueError("correct_basis needs an avatar built with correct_basis=True")
        self.avatar, self.capture, self.config = avatar, capture, config
        self.train_idx = capture.indices("train") if train_idx is None else np.asarray(train_idx, np.int64)
        if len(self.train_idx) == 0:
            raise ValueError("no training frames")
        self.flame = torch.as_tensor(flame, dtype=torch.float32)
        self.perceptual = perceptual
        self.iteration = 0
        self.history: list[dict] = []
        self.generator = torch.Generator().manual_seed(config.seed)
        self.flame_offsets = torch.nn.Parameter(torch.zeros(capture.num_frames, 68)) if config.refine_flame else None
        self.lap = uniform_laplacian(avatar.head_model.faces, avatar.head_model.num_vertices)
        self.images = {c.name: torch.as_tensor(capture.images[c.name]) for c in capture.cameras}
        c = config
        groups = [
            {"params": [avatar.local_xyz], "lr": c.lr_xyz, "name": "xyz"},
            {"params": [avatar.local_log_scale], "lr": c.lr_scale, "name": "scale"},
            {"params": [avatar.local_rot], "lr": c.lr_rot, "name": "rot"},
            {"params": [avatar.opacity_logit], "lr": c.lr_opacity, "name": "opacity"},
            {"params": [avatar.sh_dc], "lr": c.lr_colour, "name": "colour"},
        ]
        if c.correct_basis:
            groups.append({"params": [avatar.head.delta_exprdirs], "lr": c.lr_basis, "name": "basis"})
        if self.flame_offsets is not None:
            groups.append({"params": [self.flame_offsets], "lr": c.lr_flame, "name": "flame"})
        self.optimizer = torch.optim.Adam(groups, eps=1e-15)

    def target(self, cam: str, frame: int) -> torch.Tensor:
        img = self.images[cam][frame]
        return img.float() / 255.0 if img.dtype == torch.uint8 else img.float()

    def frame_values(self, frames: torch.Tensor) -> torch.Tensor:
        y = self.flame[frames]
        return y if self.flame_offsets is None else y + self.flame_offsets[frames]

    def loss(self, frame: int, cams: list[int]) -> tuple[torch.Tensor, dict[str, float]]:
        """The objective for one frame seen by cameras ``cams``; returns (loss, parts)."""
        c, av = self.config, self.avatar
        fr = torch.tensor([frame])
        y = self.frame_values(fr)
        verts = av.vertices(y)[0]
        g = av.gaussians(verts)
        renders, targets = [], []
        for k in cams:
            cam = self.capture.cameras[k]
            r = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], g["colours"], cam,
                          background=c.background, with_depth=False)
            renders.append(r.image)
            targets.append(self.target(cam.name, frame))
        parts: dict[str, torch.Tensor] = {}
        l1 = sum((r - t).abs().mean() for r, t in zip(renders, targets)) / len(cams)
        parts["l1"] = l1
        total = c.w_l1 * l1
        if self.perceptual is not None:
            p = sum(self.perceptual(r[None], t[None]) for r, t in zip(renders, targets)) / len(cams)
            parts["perceptual"] = p
            total = total + c.w_perceptual * p
        else:
            s = sum(ssim(r, t) for r, t in zip(renders, targets)) / len(cams)
            parts["ssim"] = s
            total = total + c.w_ssim * (1.0 - s)
        if c.correct_basis:
            d_e = av.head.correction()
            disp = torch.einsum("vce,e->vc", d_e[:, :, :50], y[0, :50]) * MM
            parts["laplacian"] = laplacian_loss(self.lap, disp)
            parts["basis"] = (d_e * MM).square().mean()
            total = total + c.w_laplacian * parts["laplacian"] + c.w_basis * parts["basis"]
        if self.flame_offsets is not None:
            parts["flame"] = self.flame_offsets[fr].square().mean()
            total = total + c.w_flame * parts["flame"]
        parts["scale"] = scale_regulariser(av.local_log_scale)
        parts["xyz"] = position_regulariser(av.local_xyz)
        total = total + c.w_scale * parts["scale"] + c.w_xyz * parts["xyz"]
        return total, {k: float(v.detach()) for k, v in parts.items()}

    def step(self) -> dict[str, float]:
        c = self.config
        frame = int(self.train_idx[torch.randint(len(self.train_idx), (1,), generator=self.generator)])
        n_cam = len(self.capture.cameras)
        if c.views_per_step and c.views_per_step < n_cam:
            cams = torch.randperm(n_cam, generator=self.generator)[: c.views_per_step].tolist()
        else:
            cams = list(range(n_cam))
        self.optimizer.zero_grad(set_to_none=True)
        total, parts = self.loss(frame, cams)
        total.backward()
        self.optimizer.step()
        self.iteration += 1
        rec = {"iteration": self.iteration, "loss": float(total.detach()), **parts}
        self.history.append(rec)
        return rec

    # ----- checkpoints -------------------------------------------------------------------------------------

    def state_dict(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "iteration": self.iteration,
            "config": asdict(self.config),
            "avatar": self.avatar.attributes(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "flame_offsets": None if self.flame_offsets is None else self.flame_offsets.detach().clone(),
            "history": self.history,
        }

    def load_state_dict(self, state: dict) -> None:
        fresh = TrainableAvatar.from_attributes(self.avatar.head_model, state["avatar"])
        with torch.no_grad():
            for k in TrainableAvatar.PARAMS:
                getattr(self.avatar, k).data = getattr(fresh, k).data
            if fresh.head.delta_exprdirs is not None and self.avatar.head.delta_exprdirs is not None:
                self.avatar.head.delta_exprdirs.data = fresh.head.delta_exprdirs.data
            if self.flame_offsets is not None and state.get("flame_offsets") is not None:
                self.flame_offsets.data = state["flame_offsets"].clone()
        self.avatar.binding = fresh.binding
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        self.iteration = int(state["iteration"])
        self.history = list(state.get("history", []))

    def save(self, path: str | Path, extra: dict | None = None) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        torch.save(self.state_dict() | (extra or {}), tmp)
        tmp.replace(path)  # a crash never leaves half a checkpoint
        return path

    # ----- the loop ----------------------------------------------------------------------------------------

    def run(self, iterations: int | None = None, checkpoint: str | Path | None = None, progress: bool = True,
            callback: Callable[[dict], None] | None = None, extra: dict | None = None) -> list[dict]:
        """Train up to ``iterations`` (default config.iterations) total steps, saving to ``checkpoint``."""
        total = self.config.iterations if iterations is None else iterations
        bar = None
        if progress:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            bar = Progress(TextColumn("training"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                           TextColumn("{task.fields[info]}"))
            bar.start()
            task = bar.add_task("train", total=total, completed=self.iteration, info="")
        try:
            t0 = time.perf_counter()
            while self.iteration < total:
                rec = self.step()
                if not math.isfinite(rec["loss"]):
                    raise FloatingPointError(f"loss became {rec['loss']} at iteration {self.iteration}; "
                                             "lower the learning rates")
                if callback:
                    callback(rec)
                if bar is not None:
                    bar.update(task, completed=self.iteration,
                               info=f"loss {rec['loss']:.4f}  l1 {rec['l1']:.4f}")
                every = self.config.checkpoint_every
                if checkpoint is not None and every and self.iteration % every == 0:
                    self.save(checkpoint, extra)
            self.seconds = time.perf_counter() - t0
        finally:
            if bar is not None:
                bar.stop()
        if checkpoint is not None:
            self.save(checkpoint, extra)
        return self.history


def load_checkpoint(path: str | Path) -> dict:
    """Read a training checkpoint (``weights_only=True``: the file cannot run code)."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same message
        raise ValueError(f"{path}: not a readable training checkpoint ({exc})") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not an OFERA avatar training checkpoint")
    if int(state.get("version", 0)) > CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {state['version']} is newer than {CHECKPOINT_VERSION}")
    return state


def render_frames(avatar: TrainableAvatar, flame: np.ndarray, cameras, background: float = 1.0,
                  corrected: bool = True) -> np.ndarray:
    """Images (T, C, H, W, 3) float32 of the avatar driven by FLAME values (T, 68), no gradients."""
    out = []
    with torch.no_grad():
        for y in torch.as_tensor(flame, dtype=torch.float32):
            g = avatar.gaussians(avatar.vertices(y[None], corrected=corrected)[0])
            out.append([rasterize(g["means"], g["quats"], g["scales"], g["opacities"], g["colours"], cam,
                                  background=background).image.clamp(0, 1).numpy() for cam in cameras])
    return np.asarray(out, np.float32)

