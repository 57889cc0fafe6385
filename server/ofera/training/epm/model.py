"""EPM, Expression Parameter Mapper: an MLP from 51 ARKit blendshapes to 68 FLAME values (torch).

Architecture (the paper's)::

    x (B, 51) -> FC 51->H, BN, ReLU
              -> 4 x residual block: h + ReLU(BN(FC(Dropout(ReLU(BN(FC(h)))))))
              -> FC H->68 -> y * y_std + y_mean       (output scale fixed from the training targets)

FLAME values are ``[expr(50), jaw 6D, left-eye 6D, right-eye 6D]`` (see ``flame_values``). Training:
L1 loss, Adam, validation-based early stopping (the best validation state is kept), and subject-wise
sampling: each batch draws subjects uniformly over all merged sources, then a frame of each drawn
subject, so a long recording does not outweigh a short one. Deterministic for a given seed.

Training and export need torch (``pip install ofera[train]``); the server runs the exported ONNX with
``runtime.Mapper`` and never imports this module.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ...errors import OferaError
from ...mapping.layouts import ARKIT51_NAMES

N_IN = 51
N_OUT = 68
CHECKPOINT_FORMAT = "ofera-epm"
CHECKPOINT_VERSION = 1


class EPMError(OferaError, ValueError):
    """An invalid checkpoint or training input; the message says what and what to do."""


@dataclass
class EPMConfig:
    """Model and training settings (all saved in the checkpoint)."""

    hidden: int = 128
    blocks: int = 4
    dropout: float = 0.5  # strong: across subjects the net overfits quickly (chosen on validation L1)
    batch_size: int = 512
    lr: float = 1e-3
    weight_decay: float = 1e-3
    max_epochs: int = 200
    steps_per_epoch: int = 0  # 0: ceil(train frames / batch size)
    patience: int = 15  # epochs without validation improvement before stopping
    lr_patience: int = 5  # epochs without improvement before the learning rate is halved
    min_lr: float = 1e-5
    max_minutes: float = 0.0  # wall-clock cap (0: none); never for a shipped model: it stops at another epoch
    # on a slower or loaded machine
    seed: int = 0
    loss_weights: list[float] = field(default_factory=list)  # per output (68) L1 weights; empty: all 1
    # Input augmentation (0: off), per frame and shape: x' = clip(x * exp(N(0, gain)) + N(0, bias) + N(0, noise)).
    # It simulates other estimators and subjects, so the net cannot key on one training subject's offsets.
    aug_gain: float = 0.0
    aug_bias: float = 0.0
    aug_noise: float = 0.0


class ResidualBlock(nn.Module):
    """h + ReLU(BN(FC(Dropout(ReLU(BN(FC(h)))))))."""

    def __init__(self, width: int, dropout: float) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Linear(width, width),
            nn.BatchNorm1d(width),
            nn.ReLU(),
            nn.Dropout(dropout),
            nn.Linear(width, width),
            nn.BatchNorm1d(width),
            nn.ReLU(),
        )

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return h + self.body(h)


class EPM(nn.Module):
    """The Expression Parameter Mapper; ``forward(x (B, 51)) -> (B, 68)`` FLAME values."""

    def __init__(self, hidden: int = 128, blocks: int = 4, dropout: float = 0.1) -> None:
        super().__init__()
        self.stem = nn.Sequential(nn.Linear(N_IN, hidden), nn.BatchNorm1d(hidden), nn.ReLU())
        self.blocks = nn.Sequential(*(ResidualBlock(hidden, dropout) for _ in range(blocks)))
        self.head = nn.Linear(hidden, N_OUT)
        self.register_buffer("y_mean", torch.zeros(N_OUT))
        self.register_buffer("y_std", torch.ones(N_OUT))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.blocks(self.stem(x))) * self.y_std + self.y_mean

    def set_output_scale(self, y: np.ndarray) -> None:
        """Fix the output de-normalisation from training targets (T, 68) (std floored for constants)."""
        y = np.asarray(y, np.float64)
        self.y_mean.copy_(torch.as_tensor(y.mean(axis=0), dtype=torch.float32))
        self.y_std.copy_(torch.as_tensor(np.maximum(y.std(axis=0), 1e-3), dtype=torch.float32))

    @torch.no_grad()
    def predict(self, x: np.ndarray, batch: int = 8192) -> np.ndarray:
        """(T, 51) -> (T, 68) float32 in eval mode (the model's mode is restored afterwards)."""
        was = self.training
        self.eval()
        x = np.asarray(x, np.float32)
        out = np.concatenate([self(torch.from_numpy(x[i:i + batch])).numpy() for i in range(0, len(x), batch)]) \
            if len(x) else np.zeros((0, N_OUT), np.float32)
        self.train(was)
        return out


# ----- training ------------------------------------------------------------------------------------


class SubjectSampler:
    """Batches of frame indices: subjects (groups) uniformly with replacement, then a frame of each."""

    def __init__(self, groups: np.ndarray, rng: np.random.Generator) -> None:
        groups = np.asarray(groups)
        if groups.ndim != 1 or len(groups) == 0:
            raise EPMError("subject-wise sampling needs a non-empty (T,) array of subject keys")
        self.order = np.argsort(groups, kind="stable")
        _, self.starts, self.counts = np.unique(groups[self.order], return_index=True, return_counts=True)
        self.rng = rng

    @property
    def num_groups(self) -> int:
        return len(self.counts)

    def batch(self, size: int) -> np.ndarray:
        g = self.rng.integers(0, self.num_groups, size=size)
        offset = np.floor(self.rng.random(size) * self.counts[g]).astype(np.int64)
        return self.order[self.starts[g] + offset]


def subject_keys(subject: np.ndarray, source: np.ndarray | None = None) -> np.ndarray:
    """One int64 key per (source, subject) pair, so subjects of merged sources never collide."""
    subject = np.asarray(subject, np.int64)
    if source is None:
        return subject
    source = np.asarray(source, np.int64)
    return source * (int(subject.max(initial=0)) + 1) + subject


@dataclass
class TrainResult:
    model: EPM
    config: EPMConfig
    history: list[dict] = field(default_factory=list)
    best_epoch: int = -1
    best_val: float = math.inf
    seconds: float = 0.0
    stopped: str = ""


def _seed_everything(seed: int) -> None:
    torch.manual_seed(seed)  # numpy draws go through the Generator given to the sampler


def train_epm(
    x_train: np.ndarray,
    y_train: np.ndarray,
    groups: np.ndarray,
    x_val: np.ndarray,
    y_val: np.ndarray,
    config: EPMConfig | None = None,
    progress: bool | Callable[[dict], None] = True,
) -> TrainResult:
    """Train an EPM; returns the model at its best validation L1 (eval mode) and the history.

    x (T, 51) in [0, 1], y (T, 68) FLAME values; ``groups`` (T_train,) subject keys for subject-wise
    sampling (see :func:`subject_keys`). ``progress``: True shows a rich progress bar, a callable gets
    each epoch's record, False is silent.
    """
    cfg = config or EPMConfig()
    x_train, y_train = np.asarray(x_train, np.float32), np.asarray(y_train, np.float32)
    x_val, y_val = np.asarray(x_val, np.float32), np.asarray(y_val, np.float32)
    for name, x, y in (("train", x_train, y_train), ("val", x_val, y_val)):
        if x.ndim != 2 or x.shape[1] != N_IN or y.shape != (len(x), N_OUT):
            raise EPMError(f"{name} data: expected x (T, {N_IN}) and y (T, {N_OUT}), got {x.shape} and {y.shape}")
        if len(x) == 0:
            raise EPMError(f"{name} data is empty: give the paired data a {name} split")
    if len(groups) != len(x_train):
        raise EPMError(f"groups has {len(groups)} entries for {len(x_train)} training frames")

    _seed_everything(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    sampler = SubjectSampler(groups, rng)
    model = EPM(cfg.hidden, cfg.blocks, cfg.dropout)
    model.set_output_scale(y_train)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=cfg.lr_patience, min_lr=cfg.min_lr)
    w = torch.ones(N_OUT) if not cfg.loss_weights else torch.as_tensor(cfg.loss_weights, dtype=torch.float32)
    if w.shape != (N_OUT,):
        raise EPMError(f"loss_weights must hold {N_OUT} values, got {tuple(w.shape)}")
    inv_std = 1.0 / model.y_std  # L1 on standardised outputs: every FLAME value counts alike
    xt, yt = torch.from_numpy(x_train), torch.from_numpy(y_train)
    xv, yv = torch.from_numpy(x_val), torch.from_numpy(y_val)
    steps = cfg.steps_per_epoch or max(1, math.ceil(len(x_train) / cfg.batch_size))
    augment = bool(cfg.aug_gain or cfg.aug_bias or cfg.aug_noise)

    def val_loss() -> float:
        model.eval()
        with torch.no_grad():
            total = 0.0
            for i in range(0, len(xv), 8192):
                d = (model(xv[i:i + 8192]) - yv[i:i + 8192]).abs() * inv_std * w
                total += float(d.sum())
        model.train()
        return total / (len(xv) * float(w.sum()))

    result = TrainResult(model, cfg)
    best_state = {k: v.clone() for k, v in model.state_dict().items()}
    bar = _Progress(progress, cfg.max_epochs)
    start = time.perf_counter()
    since_best = 0
    model.train()
    try:
        for epoch in range(cfg.max_epochs):
            running = 0.0
            for _ in range(steps):
                idx = torch.from_numpy(sampler.batch(cfg.batch_size))
                xb = xt[idx]
                if augment:
                    xb = _augment(xb, cfg)
                pred = model(xb)
                loss = ((pred - yt[idx]).abs() * inv_std * w).sum(dim=1).mean() / float(w.sum())
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                running += float(loss.detach())
            val = val_loss()
            sched.step(val)
            record = {"epoch": epoch, "train_l1": running / steps, "val_l1": val, "lr": opt.param_groups[0]["lr"]}
            result.history.append(record)
            if val < result.best_val - 1e-6:
                result.best_val, result.best_epoch, since_best = val, epoch, 0
                best_state = {k: v.clone() for k, v in model.state_dict().items()}
            else:
                since_best += 1
            bar.update(record, result.best_val)
            elapsed = time.perf_counter() - start
            if since_best >= cfg.patience:
                result.stopped = f"early stop: no validation improvement for {cfg.patience} epochs"
                break
            if cfg.max_minutes and elapsed > cfg.max_minutes * 60:
                result.stopped = f"time cap of {cfg.max_minutes} min reached"
                break
        else:
            result.stopped = f"max_epochs={cfg.max_epochs} reached"
    finally:
        bar.close()
    model.load_state_dict(best_state)
    model.eval()
    result.seconds = time.perf_counter() - start
    return result


def _augment(x: torch.Tensor, cfg: EPMConfig) -> torch.Tensor:
    """Random per-frame, per-shape gain, bias and noise on a batch of inputs (torch's seeded RNG)."""
    out = x * torch.exp(torch.randn_like(x) * cfg.aug_gain) if cfg.aug_gain else x.clone()
    if cfg.aug_bias:
        out += torch.randn_like(x) * cfg.aug_bias
    if cfg.aug_noise:
        out += torch.randn_like(x) * cfg.aug_noise
    return out.clamp_(0.0, 1.0)


class _Progress:
    """A rich progress bar over epochs (or a callback, or nothing)."""

    def __init__(self, progress: bool | Callable[[dict], None], total: int) -> None:
        self.callback = progress if callable(progress) else None
        self.bar = None
        if progress is True:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self.bar = Progress(TextColumn("[bold]EPM[/] epoch {task.completed}/{task.total}"), BarColumn(),
                                TextColumn("{task.description}"), TimeElapsedColumn(), transient=False)
            self.task = self.bar.add_task("", total=total)
            self.bar.start()

    def update(self, record: dict, best: float) -> None:
        if self.callback:
            self.callback(record)
        if self.bar is not None:
            self.bar.update(self.task, advance=1, description=(
                f"train L1 {record['train_l1']:.4f}  val L1 {record['val_l1']:.4f}  best {best:.4f}  "
                f"lr {record['lr']:.1e}"))

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


# ----- checkpoints ---------------------------------------------------------------------------------


def save_checkpoint(path: str | Path, model: EPM, config: EPMConfig, history: list[dict] | None = None,
                    meta: dict | None = None) -> Path:
    """Write a ``.pt`` holding only tensors and plain values (loadable with ``weights_only=True``)."""
    path = Path(path)
    torch.save({
        "format": CHECKPOINT_FORMAT,
        "format_version": CHECKPOINT_VERSION,
        "config": asdict(config),
        "state_dict": model.state_dict(),
        "input_names": list(ARKIT51_NAMES),
        "history": history or [],
        "meta": meta or {},
    }, path)
    return path


def load_checkpoint(path: str | Path) -> tuple[EPM, EPMConfig, dict]:
    """Read a checkpoint written by :func:`save_checkpoint` -> (model in eval mode, config, the raw dict)."""
    path = Path(path)
    if not path.is_file():
        raise EPMError(f"{path}: no such EPM checkpoint (train one with `ofera epm train DATA -o {path.name}`)")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's problem to fix
        raise EPMError(f"{path}: cannot read EPM checkpoint: {exc}") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise EPMError(f"{path}: not an OFERA EPM checkpoint (format {CHECKPOINT_FORMAT!r})")
    if int(ckpt.get("format_version", 0)) > CHECKPOINT_VERSION:
        raise EPMError(f"{path}: checkpoint version {ckpt['format_version']} is newer than {CHECKPOINT_VERSION}")
    if list(ckpt.get("input_names", [])) != list(ARKIT51_NAMES):
        raise EPMError(f"{path}: the EPM's input names are not arkit51")
    known = EPMConfig.__dataclass_fields__
    config = EPMConfig(**{k: v for k, v in ckpt["config"].items() if k in known})
    model = EPM(config.hidden, config.blocks, config.dropout)
    model.load_state_dict(ckpt["state_dict"])
    model.eval()
    return model, config, ckpt


# ----- paired data ---------------------------------------------------------------------------------

DEFAULT_EPM_CONFIG: dict = {}
"""Overrides of :class:`EPMConfig` for the shipped default EPM (``ofera mapping make-default``): none. It is
capped by ``max_epochs`` and early stopping only (no wall clock), and ``ofera epm train synthetic``'s
defaults are the same, so either command trains the same model on one thread."""


def train_on_paired(data, config: EPMConfig | None = None, out: str | Path | None = None,
                    progress: bool | Callable[[dict], None] = True, source: str = "") -> TrainResult:
    """Train on a ``PairedData``'s train split (subject-wise over (source, subject)), stop on its val split.

    Writes the checkpoint to ``out`` when given (with the data's description in ``meta``).
    """
    train, val = data.split_mask("train"), data.split_mask("val")
    if not train.any() or not val.any():
        raise EPMError(f"paired data needs train and val frames (subject-disjoint); it has {int(train.sum())} "
                       f"train and {int(val.sum())} val frames")
    x, y = np.asarray(data.bs, np.float32), np.asarray(data.flame, np.float32)
    keys = subject_keys(data.subject, data.source)
    cfg = config or EPMConfig(**DEFAULT_EPM_CONFIG)
    result = train_epm(x[train], y[train], keys[train], x[val], y[val], cfg, progress)
    if out is not None:
        meta = {
            "data": source,
            "train_frames": int(train.sum()),
            "val_frames": int(val.sum()),
            "train_subjects": int(len(np.unique(keys[train]))),
            "best_epoch": result.best_epoch,
            "best_val_l1": result.best_val,
            "seconds": round(result.seconds, 1),
        }
        save_checkpoint(out, result.model, cfg, result.history, meta)
    return result
