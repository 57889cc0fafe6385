"""The MiA experiment: does training the avatar on the mapper's FLAME values help when the mapper drives it?

1. A synthetic multi-view capture (``synthetic.make_scene``): a rig subject's blendshapes, the rig's meshes
   (the "real face"), the tracker's FLAME fit of those meshes, and ground-truth images.
2. Two avatars from the same degraded start, same objective, same steps and seed:
   - without MiA: trained on the tracker's FLAME values (the usual pipeline);
   - with MiA: trained on EPM(blendshapes) of the same training frames.
3. Both are driven by EPM(blendshapes) on held-out frames (what the server does at run time) and compared with
   the ground-truth images: PSNR and SSIM, plus a PNG grid (GT / without MiA / with MiA).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from .losses import psnr, ssim
from .model import TrainableAvatar
from .trainer import TrainConfig, Trainer, render_frames


@dataclass
class ExperimentConfig:
    size: int = 96
    cameras: int = 4
    train_frames: int = 120
    test_frames: int = 32
    iterations: int = 2000
    per_face: int = 1
    seed: int = 0
    background: float = 1.0
    correct_basis: bool = True
    grid_frames: int = 4
    views_per_step: int = 1


FULL = ExperimentConfig()
QUICK = ExperimentConfig(size=64, cameras=3, train_frames=48, test_frames=16, iterations=700)


# ----- the mapper --------------------------------------------------------------------------------------------


class RidgeMapper:
    """Stand-in EPM when no ONNX EPM is available: ridge regression from [w, w^2, 1] to FLAME values on the
    training split of a small paired benchmark (like the EPM it never saw the test subject)."""

    def __init__(self, subjects_per_source: int = 4, frames: int = 600, ridge: float = 1e-3, seed: int = 0) -> None:
        from ..mapping.paired.benchmark import make_benchmark

        data = make_benchmark(frames_per_subject=frames, subjects_per_source=subjects_per_source, seed=seed)
        train = data.subset("train")
        x, y = self._features(np.asarray(train.bs, np.float64)), np.asarray(train.flame, np.float64)
        self.coef = np.linalg.solve(x.T @ x + ridge * len(x) * np.eye(x.shape[1]), x.T @ y)

    @staticmethod
    def _features(w: np.ndarray) -> np.ndarray:
        return np.concatenate([w, w**2, np.ones((len(w), 1))], axis=1)

    def map_batch(self, w: np.ndarray) -> np.ndarray:
        return (self._features(np.asarray(w, np.float64)) @ self.coef).astype(np.float32)


def load_mapper(head, epm: str | None, bda: str | None = None):
    """(mapper with ``map_batch``, description). ``epm`` None: the shipped EPM, else the ridge stand-in."""
    try:
        from ..mapping.runtime import Mapper

        if epm is not None and epm != "default":
            return Mapper.load(epm, bda), f"EPM {epm}"
        return Mapper.default(bda), "default EPM (ofera/assets/epm_default.onnx)"
    except FileNotFoundError:
        if epm not in (None, "default"):
            raise
        return RidgeMapper(), "ridge stand-in mapper (no default EPM ONNX found)"


# ----- metrics and pictures ----------------------------------------------------------------------------------


def image_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Mean per-image PSNR (dB) and SSIM over images (..., H, W, 3) in [0, 1]; with ``mask`` (H, W) also the
    PSNR over the masked pixels (the parts of the face that expressions move)."""
    p = torch.as_tensor(pred, dtype=torch.float64).reshape(-1, *pred.shape[-3:])
    g = torch.as_tensor(gt, dtype=torch.float64).reshape(-1, *gt.shape[-3:])
    out = {
        "psnr": float(np.mean([float(psnr(a, b)) for a, b in zip(p, g)])),
        "ssim": float(ssim(p, g, reduce=False).mean()),
    }
    if mask is not None:
        m = torch.as_tensor(mask, dtype=torch.bool)
        out["psnr_moving"] = float(np.mean([float(psnr(a[m], b[m])) for a, b in zip(p, g)]))
    return out


def save_grid(path: str | Path, columns: dict[str, np.ndarray], title: str = "") -> Path:
    """A PNG with one column per entry (images (R, H, W, 3) in [0, 1]) and one row per image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(columns)
    rows = len(next(iter(columns.values())))
    h, w = next(iter(columns.values())).shape[1:3]
    fig, axes = plt.subplots(rows, len(names), figsize=(1.9 * len(names), 1.9 * rows * h / w + 0.4), squeeze=False)
    for j, name in enumerate(names):
        for i in range(rows):
            ax = axes[i, j]
            ax.imshow(np.clip(columns[name][i], 0, 1), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(name, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ----- the experiment ----------------------------------------------------------------------------------------


def run_experiment(cfg: ExperimentConfig, epm: str | None = None, grid: str | Path | None = None,
                   progress: bool = True, log: Callable[[str], None] = print,
                   train_overrides: dict | None = None, mapper=None) -> dict:
    """Run the experiment; returns the result dict (see module docstring; JSON-ready)."""
    from ..head import default_head
    from .synthetic import capture_cameras, degraded_copy, make_scene

    torch.manual_seed(cfg.seed)
    t_start = time.perf_counter()
    head = default_head()
    cams = capture_cameras(cfg.cameras, cfg.size)
    log(f"scene: {cfg.cameras} cameras at {cfg.size} px, {cfg.train_frames} training + {cfg.test_frames} held-out "
        "frames of a rig subject")
    scene = make_scene(head, cfg.train_frames, cfg.test_frames, cams, seed=cfg.seed, per_face=cfg.per_face,
                       background=cfg.background)
    cap = scene.capture
    if mapper is None:
        mapper, mapper_name = load_mapper(head, epm)
    else:
        mapper_name = type(mapper).__name__
    log(f"mapper: {mapper_name}")
    y_epm = np.asarray(mapper.map_batch(cap.blendshapes), np.float32)
    y_trk = cap.tracker
    train_idx, test_idx = cap.indices("train"), cap.indices("test")
    gt_test = np.stack([[cap.image(c.name, i) for c in cams] for i in test_idx])  # (T, C, H, W, 3)
    # Pixels that expressions change, per camera: "psnr_moving" measures only those.
    masks = np.stack([np.std(np.stack([cap.image(c.name, i) for i in range(cap.num_frames)]), 0).max(-1) > 1e-3
                      for c in cams])

    def metrics(pred: np.ndarray) -> dict[str, float]:
        base = image_metrics(pred, gt_test)
        diff = (pred - gt_test) ** 2  # (T, C, H, W, 3)
        sel = np.broadcast_to(masks[None, :, :, :, None], diff.shape)
        per = [10 * np.log10(1.0 / max(float(diff[t][sel[t]].mean()), 1e-12)) for t in range(len(diff))]
        return base | {"psnr_moving": float(np.mean(per))}

    start = degraded_copy(scene.gt_avatar, seed=cfg.seed + 1, correct_basis=cfg.correct_basis)
    tcfg = TrainConfig(iterations=cfg.iterations, seed=cfg.seed, background=cfg.background,
                       correct_basis=cfg.correct_basis, checkpoint_every=0, views_per_step=cfg.views_per_step)
    if train_overrides:
        tcfg = replace(tcfg, **train_overrides)
    results: dict = {"psnr": {}, "ssim": {}, "psnr_moving": {}}
    renders: dict[str, np.ndarray] = {}
    extra: dict = {}
    for name, flame in (("without_mia", y_trk), ("mia", y_epm)):
        log(f"training {name.replace('_', ' ')} ({'tracker FLAME fit' if name == 'without_mia' else 'EPM(bs)'}"
            f" values), {cfg.iterations} steps")
        av = TrainableAvatar.from_attributes(head, start.attributes())
        trainer = Trainer(av, cap, flame, tcfg, train_idx=train_idx)
        t0 = time.perf_counter()
        hist = trainer.run(progress=progress)
        secs = time.perf_counter() - t0
        pred = render_frames(av, y_epm[test_idx], cams, cfg.background)
        renders[name] = pred
        m = metrics(pred)
        for k in results:
            results[k][name] = m[k]
        # The same avatar driven by the tracker's values (for the MiA avatar: values it never trained on).
        trk = metrics(render_frames(av, y_trk[test_idx], cams, cfg.background))
        extra[name] = {
            "train_seconds": round(secs, 1),
            "final_l1": float(np.mean([h["l1"] for h in hist[-50:]])),
            "epm_driven": m,
            "tracker_driven": trk,
        }
        log(f"  {name}: held-out PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} (EPM-driven); "
            f"{secs:.0f} s")
    # Reference points: the ground-truth avatar on the FLAME mesh of the tracker's values / of the EPM's values.
    gt_av = TrainableAvatar.from_attributes(head, scene.gt_avatar.attributes())
    extra["reference"] = {
        "gt_avatar_tracker_driven": metrics(render_frames(gt_av, y_trk[test_idx], cams, cfg.background)),
        "gt_avatar_epm_driven": metrics(render_frames(gt_av, y_epm[test_idx], cams, cfg.background)),
        "start_epm_driven": metrics(render_frames(start, y_epm[test_idx], cams, cfg.background)),
    }
    err = np.abs(y_epm - y_trk)
    extra["mapper_vs_tracker"] = {"expr_mae": float(err[:, :50].mean()), "rot6d_mae": float(err[:, 50:].mean())}
    results["extra"] = extra
    results["config"] = asdict(cfg) | {"mapper": mapper_name, "train": asdict(tcfg)}
    results["fit_rms_mm"] = float(scene.fit_rms.mean() * 1e3)
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    if grid is not None:
        k = min(cfg.grid_frames, len(test_idx))
        pick = np.linspace(0, len(test_idx) - 1, k).round().astype(int)
        cols = {"ground truth": gt_test[pick, 0], "without MiA": renders["without_mia"][pick, 0],
                "with MiA": renders["mia"][pick, 0],
                "|err| without x4": np.clip(4 * np.abs(renders["without_mia"][pick, 0] - gt_test[pick, 0]), 0, 1),
                "|err| with x4": np.clip(4 * np.abs(renders["mia"][pick, 0] - gt_test[pick, 0]), 0, 1)}
        title = (f"held-out frames, EPM-driven: PSNR without {results['psnr']['without_mia']:.2f} / with "
                 f"{results['psnr']['mia']:.2f} dB")
        results["grid"] = str(save_grid(grid, cols, title))
    return results


def write_json(results: dict, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1))
    return path
