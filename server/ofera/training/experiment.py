"""The MiA experiment: does training the avatar on the mapper's FLAME values help when the mapper drives it?

1. A synthetic multi-view capture (``synthetic.make_scene``): a rig subject's blendshapes, the rig's meshes
   (the "real face"), the tracker's FLAME fit of those meshes, and ground-truth images.
2. Two avatars from the same degraded start, same objective, same steps and seed:
   - without MiA: trained on the tracker's FLAME values (the usual pipeline);
   - with MiA: trained on EPM(blendshapes) of the same training frames.
3. Both are driven by EPM(blendshapes) on held-out frames (what the server does at run time) and compared with
   the ground-truth images: PSNR and SSIM, plus a PNG grid (GT / without MiA / with MiA).

Hyperparameters are chosen on validation frames (between the training and the test frames in time), never on
the test frames: each arm keeps the training step with the best validation PSNR (checked every ``val_every``
steps), and ``tune=True`` also picks, per arm, the learning-rate scale and views per step of ``TUNE_GRID`` with
the best validation PSNR. Each pipeline validates the way it would be run: without MiA on renders driven by the
tracker's values (the usual pipeline has no mapper), with MiA on renders driven by the EPM. The test frames are
rendered only for the chosen avatars. ``epm_selected`` reports a second protocol for comparison: both arms
validated on EPM-driven renders (the baseline then gets mapper-aware early stopping, half of MiA's idea).
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields, replace
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
    val_frames: int = 16  # hyperparameters (steps, learning rates, views) are chosen on these, never on test
    iterations: int = 2000
    val_every: int = 100  # steps between validation checks; each arm keeps its best step on validation
    lr_scale: float = 1.0  # multiplies every learning rate of TrainConfig
    per_face: int = 1
    seed: int = 0
    background: float = 1.0
    correct_basis: bool = True
    grid_frames: int = 4
    views_per_step: int = 1


FULL = ExperimentConfig()
QUICK = ExperimentConfig(size=64, cameras=3, train_frames=48, test_frames=16, val_frames=8, iterations=700)
TUNE_GRID: dict[str, tuple] = {"lr_scale": (0.5, 1.0, 2.0), "views_per_step": (1, 0)}
"""What ``tune=True`` searches, per arm, on the validation frames (views_per_step 0: every camera)."""
_LRS = tuple(f.name for f in fields(TrainConfig) if f.name.startswith("lr_"))


# ----- the mapper --------------------------------------------------------------------------------------------


class RidgeMapper:
    """Stand-in EPM when no ONNX EPM is available: ridge regression from [w, w^2, 1] to FLAME values on the
    training split of a small paired benchmark (like the EPM it never saw the test subject)."""

    def __init__(self, subjects_per_source: int = 4, frames: int = 600, ridge: float = 1e-3, seed: int = 0) -> None:
        from .paired.benchmark import make_benchmark

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


def _train_arm(start: TrainableAvatar, cap, flame: np.ndarray, tcfg: TrainConfig, val_every: int,
               scorers: dict[str, Callable[[TrainableAvatar], float]], train_idx: np.ndarray) -> dict[str, dict]:
    """Train a copy of ``start``, scoring it on validation every ``val_every`` steps with each scorer; returns, per
    scorer, {"avatar" (at its best step), "best_step", "val_psnr", "val_curve" [(step, score)]}."""
    av = TrainableAvatar.from_attributes(start.head_model, start.attributes())
    trainer = Trainer(av, cap, flame, tcfg, train_idx=train_idx)
    best = {k: {"val_psnr": -np.inf, "best_step": 0, "attrs": av.attributes(), "val_curve": []} for k in scorers}
    every = max(1, val_every)
    while trainer.iteration < tcfg.iterations:
        trainer.run(iterations=min(tcfg.iterations, trainer.iteration + every), progress=False)
        for k, score_of in scorers.items():
            score = score_of(av)
            best[k]["val_curve"].append((trainer.iteration, round(score, 3)))
            if score > best[k]["val_psnr"]:
                best[k] |= {"val_psnr": score, "best_step": trainer.iteration, "attrs": av.attributes()}
    return {k: {"avatar": TrainableAvatar.from_attributes(start.head_model, b.pop("attrs")), **b}
            for k, b in best.items()}


def run_experiment(cfg: ExperimentConfig, epm: str | None = None, grid: str | Path | None = None,
                   log: Callable[[str], None] = print,
                   train_overrides: dict | None = None, mapper=None, tune: bool = False) -> dict:
    """Run the experiment; returns the result dict (see module docstring; JSON-ready)."""
    from ..head import default_head
    from .synthetic import capture_cameras, degraded_copy, make_scene

    torch.manual_seed(cfg.seed)
    t_start = time.perf_counter()
    head = default_head()
    cams = capture_cameras(cfg.cameras, cfg.size)
    log(f"scene: {cfg.cameras} cameras at {cfg.size} px, {cfg.train_frames} training + {cfg.val_frames} validation "
        f"+ {cfg.test_frames} held-out frames of a rig subject")
    scene = make_scene(head, cfg.train_frames, cfg.test_frames, cams, seed=cfg.seed, per_face=cfg.per_face,
                       background=cfg.background, n_val=cfg.val_frames)
    cap = scene.capture
    if mapper is None:
        mapper, mapper_name = load_mapper(head, epm)
    else:
        mapper_name = type(mapper).__name__
    log(f"mapper: {mapper_name}")
    y_epm = np.asarray(mapper.map_batch(cap.blendshapes), np.float32)
    y_trk = cap.tracker
    train_idx, val_idx, test_idx = cap.indices("train"), cap.indices("val"), cap.indices("test")
    if len(val_idx) == 0:
        raise ValueError("the experiment needs validation frames (val_frames > 0) to choose its hyperparameters")
    gt_test = np.stack([[cap.image(c.name, i) for c in cams] for i in test_idx])  # (T, C, H, W, 3)
    gt_val = np.stack([[cap.image(c.name, i) for c in cams] for i in val_idx])
    # Pixels that expressions change, per camera: "psnr_moving" measures only those.
    masks = np.stack([np.std(np.stack([cap.image(c.name, i) for i in range(cap.num_frames)]), 0).max(-1) > 1e-3
                      for c in cams])

    def metrics(pred: np.ndarray) -> dict[str, float]:
        base = image_metrics(pred, gt_test)
        diff = (pred - gt_test) ** 2  # (T, C, H, W, 3)
        sel = np.broadcast_to(masks[None, :, :, :, None], diff.shape)
        per = [10 * np.log10(1.0 / max(float(diff[t][sel[t]].mean()), 1e-12)) for t in range(len(diff))]
        return base | {"psnr_moving": float(np.mean(per))}

    def val_psnr(y: np.ndarray) -> Callable[[TrainableAvatar], float]:
        return lambda av: image_metrics(render_frames(av, y[val_idx], cams, cfg.background), gt_val)["psnr"]

    start = degraded_copy(scene.gt_avatar, seed=cfg.seed + 1, correct_basis=cfg.correct_basis)
    base_cfg = TrainConfig(iterations=cfg.iterations, seed=cfg.seed, background=cfg.background,
                           correct_basis=cfg.correct_basis, checkpoint_every=0, views_per_step=cfg.views_per_step)
    if train_overrides:
        base_cfg = replace(base_cfg, **train_overrides)
    grid_points = [dict(zip(TUNE_GRID, v)) for v in itertools.product(*TUNE_GRID.values())] if tune else \
        [{"lr_scale": cfg.lr_scale, "views_per_step": base_cfg.views_per_step}]
    results: dict = {"psnr": {}, "ssim": {}, "psnr_moving": {}, "val_psnr": {},
                     "epm_selected": {"psnr": {}, "ssim": {}, "val_psnr": {}, "chosen": {}}}
    renders: dict[str, np.ndarray] = {}
    extra: dict = {}
    keys = ("lr_scale", "views_per_step", "best_step", "val_psnr")
    for name, flame in (("without_mia", y_trk), ("mia", y_epm)):
        log(f"training {name.replace('_', ' ')} ({'tracker FLAME fit' if name == 'without_mia' else 'EPM(bs)'}"
            f" values), {cfg.iterations} steps x {len(grid_points)} setting(s)")
        # "own": validated on renders driven by the values it trains on; "epm": on EPM-driven renders.
        scorers = {"own": val_psnr(flame)} if name == "mia" else {"own": val_psnr(y_trk), "epm": val_psnr(y_epm)}
        tried = []
        t0 = time.perf_counter()
        for point in grid_points:
            tcfg = replace(base_cfg, views_per_step=point["views_per_step"],
                           **{k: getattr(base_cfg, k) * point["lr_scale"] for k in _LRS})
            arm = _train_arm(start, cap, flame, tcfg, cfg.val_every, scorers, train_idx)
            arm.setdefault("epm", arm["own"])
            tried.append({k: {**point, **v} for k, v in arm.items()})
            log(f"  {name} {point}: best validation PSNR {arm['own']['val_psnr']:.2f} dB at step "
                f"{arm['own']['best_step']}")
        secs = time.perf_counter() - t0
        chosen = max((t["own"] for t in tried), key=lambda t: t["val_psnr"])
        av = chosen["avatar"]
        pred = render_frames(av, y_epm[test_idx], cams, cfg.background)
        renders[name] = pred
        m = metrics(pred)
        for k in ("psnr", "ssim", "psnr_moving"):
            results[k][name] = m[k]
        results["val_psnr"][name] = chosen["val_psnr"]
        alt = max((t["epm"] for t in tried), key=lambda t: t["val_psnr"])
        m_alt = m if alt is chosen else metrics(render_frames(alt["avatar"], y_epm[test_idx], cams, cfg.background))
        sel = results["epm_selected"]
        sel["psnr"][name], sel["ssim"][name], sel["val_psnr"][name] = m_alt["psnr"], m_alt["ssim"], alt["val_psnr"]
        sel["chosen"][name] = {k: alt[k] for k in keys}
        # The same avatar driven by the tracker's values (for the MiA avatar: values it never trained on).
        trk = metrics(render_frames(av, y_trk[test_idx], cams, cfg.background))
        extra[name] = {
            "train_seconds": round(secs, 1),
            "chosen": {k: chosen[k] for k in keys},
            "tried": [{c: {k: t[c][k] for k in (*keys, "val_curve")} for c in t} for t in tried],
            "epm_driven": m,
            "tracker_driven": trk,
        }
        log(f"  {name}: held-out PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} (EPM-driven; chosen on validation: "
            f"{extra[name]['chosen']}); with EPM-driven validation {m_alt['psnr']:.2f} dB; {secs:.0f} s")
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
    results["config"] = asdict(cfg) | {"mapper": mapper_name, "train": asdict(base_cfg), "tune": tune,
                                       "tune_grid": TUNE_GRID if tune else None}
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
