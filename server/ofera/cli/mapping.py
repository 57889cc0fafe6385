"""`ofera bda ...`, `ofera epm ...`, `ofera mapping ...`: fit BDA, train and export the EPM, evaluate mappers."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from .errors import CliError, user_errors

bda_app = typer.Typer(help="BDA (blendshape distribution alignment): fit and inspect.", no_args_is_help=True)
epm_app = typer.Typer(help="EPM (expression parameter mapper): train (torch) and export to ONNX.",
                      no_args_is_help=True)
mapping_app = typer.Typer(help="Mappers: evaluation against baselines, the default EPM.", no_args_is_help=True)

def _need_torch() -> None:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise CliError("this command needs torch: pip install 'ofera[train]'") from None


# ----- bda ------------------------------------------------------------------------------------------


def _read_arkit51(path: Path, layout: str = "auto", fps: float | None = None) -> np.ndarray:
    from ..sources.read import read_facelog

    return read_facelog(path, layout, fps).to_arkit51()


@bda_app.command("fit")
@user_errors()
def bda_fit(
    pairs: Annotated[list[Path], typer.Argument(help="A paired-data .npz (headset -> observed), or two face logs "
                                                     "HEADSET TARGET (CSV / .gesichter, same frame count).")],
    out: Annotated[Path, typer.Option("-o", "--out", help="BDA .npz to write.")],
    ridge: Annotated[float, typer.Option(help="Ridge weight pulling W towards the identity (0: plain least squares).")]
    = 0.0,
    split: Annotated[str, typer.Option(help="With a paired .npz: fit on this split ('train' or 'all').")] = "train",
    device: Annotated[str, typer.Option(help="Name of the headset profile stored in the file.")] = "",
    layout: Annotated[str, typer.Option("--layout", help="With two logs: the HEADSET log's layout, as for `ofera "
                                        "replay` ('auto', or e.g. ovr63 for a headerless Quest log).")] = "auto",
    target_layout: Annotated[str, typer.Option("--target-layout", help="With two logs: the TARGET log's layout "
                                               "('auto' or a layout name).")] = "auto",
    fps: Annotated[float | None, typer.Option("--fps", help="With two logs: the row rate of a log without time "
                                              "(Quest snapshot or headerless logs), as for `ofera replay`.")]
    = None,
) -> None:
    """Fit W (51x51) and b by least squares; prints the error before and after alignment."""
    from ..mapping.bda import BDA, BDAError
    from ..mapping.layouts import to_arkit51

    held = None
    if len(pairs) == 1 and pairs[0].suffix == ".npz":
        from ..training.epm.evaluate import load_paired_data

        data = load_paired_data(pairs[0])
        x = to_arkit51("ovr63", np.asarray(data.headset, np.float32))
        y = np.asarray(data.bs, np.float32)
        fit_rows = np.ones(len(x), bool) if split == "all" else data.split_mask(split)
        if not fit_rows.any():
            raise CliError(f"{pairs[0]}: no frames in split {split!r}")
        if split != "all" and (~fit_rows).any():
            held = (x[~fit_rows], y[~fit_rows])
        x, y = x[fit_rows], y[fit_rows]
    elif len(pairs) == 2:
        x, y = _read_arkit51(pairs[0], layout, fps), _read_arkit51(pairs[1], target_layout, fps)
        if len(x) != len(y):
            raise CliError(f"{pairs[0]} has {len(x)} frames, {pairs[1]} has {len(y)}: pairs must be frame-aligned")
    else:
        raise CliError("give one paired-data .npz, or two face logs: HEADSET TARGET")
    try:
        bda = BDA.fit(x, y, ridge=ridge, device=device)
    except BDAError as exc:
        raise CliError(str(exc)) from None
    bda.save(out)
    before, after = BDA.identity().error(x, y), bda.error(x, y)
    print(f"fitted on {len(x)} frames: RMSE {before['rmse']:.4f} -> {after['rmse']:.4f}, "
          f"MAE {before['mae']:.4f} -> {after['mae']:.4f}")
    if held is not None:
        hb, ha = BDA.identity().error(*held), bda.error(*held)
        print(f"held-out {len(held[0])} frames: RMSE {hb['rmse']:.4f} -> {ha['rmse']:.4f}, "
              f"MAE {hb['mae']:.4f} -> {ha['mae']:.4f}")
    print(f"wrote {out}")


@bda_app.command("info")
@user_errors()
def bda_info(path: Annotated[Path, typer.Argument(help="BDA .npz")]) -> None:
    """Device name and how far W, b are from the identity."""
    from ..mapping.bda import BDA

    bda = BDA.load(path)
    dev = np.abs(bda.W - np.eye(len(bda.names)))
    print(f"device: {bda.device or '-'}\nidentity: {bda.is_identity}\nmax |W - I|: {dev.max():.4f}\n"
          f"max |b|: {np.abs(bda.b).max():.4f}")


# ----- epm ------------------------------------------------------------------------------------------


@epm_app.command("train")
@user_errors()
def epm_train(
    data: Annotated[str, typer.Argument(help="Paired-data .npz, or 'synthetic' (the generated benchmark, cached).")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Checkpoint .pt to write.")],
    seed: Annotated[int, typer.Option(help="Random seed (training is deterministic for a seed).")] = 0,
    max_epochs: Annotated[int, typer.Option(help="Upper bound on epochs (early stopping usually ends sooner).")]
    = 200,
    max_minutes: Annotated[float, typer.Option(help="Wall-clock cap in minutes (0: none; a capped model depends on "
                                                    "the machine's speed).")] = 0.0,
    patience: Annotated[int, typer.Option(help="Epochs without validation improvement before stopping.")] = 15,
    hidden: Annotated[int, typer.Option(help="Width of the hidden layers.")] = 128,
    batch_size: Annotated[int, typer.Option(help="Frames per batch.")] = 512,
    lr: Annotated[float, typer.Option(help="Adam learning rate.")] = 1e-3,
    dropout: Annotated[float, typer.Option(help="Dropout inside the residual blocks.")] = 0.5,
    weight_decay: Annotated[float, typer.Option(help="Adam weight decay.")] = 1e-3,
    threads: Annotated[int, typer.Option(help="torch CPU threads (0: torch's default; 1 is reproducible).")] = 1,
    quiet: Annotated[bool, typer.Option(help="No progress bar.")] = False,
) -> None:
    """Train the EPM (L1, Adam, early stopping on the validation subjects, subject-wise sampling)."""
    _need_torch()
    from ..training.epm.evaluate import load_paired_data
    from ..training.epm.model import EPMConfig, train_on_paired

    if threads:
        import torch

        torch.set_num_threads(threads)
    paired = load_paired_data(data, progress=not quiet)
    cfg = EPMConfig(hidden=hidden, batch_size=batch_size, lr=lr, dropout=dropout, weight_decay=weight_decay,
                    max_epochs=max_epochs, patience=patience, max_minutes=max_minutes, seed=seed)
    result = train_on_paired(paired, cfg, out, progress=not quiet, source=str(data))
    print(f"{result.stopped}; best validation L1 {result.best_val:.4f} at epoch {result.best_epoch} "
          f"({result.seconds:.0f} s)")
    print(f"wrote {out}")


@epm_app.command("export")
@user_errors()
def epm_export(
    checkpoint: Annotated[Path, typer.Argument(help="EPM checkpoint .pt from `ofera epm train`.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="ONNX file to write.")],
) -> None:
    """Export to ONNX (BatchNorm in eval mode, dynamic batch) and check it against torch."""
    _need_torch()
    from ..training.epm.export import export_checkpoint

    path, diff = export_checkpoint(checkpoint, out)
    print(f"ONNX vs torch: max abs difference {diff:.3g}")
    if diff > 1e-4:
        raise CliError(f"{path}: ONNX output differs from torch by {diff:.3g} (> 1e-4); do not ship it")
    print(f"wrote {path}")


# ----- mapping --------------------------------------------------------------------------------------


@mapping_app.command("eval")
@user_errors()
def mapping_eval(
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the results as JSON here.")] = None,
    heatmap: Annotated[Path | None, typer.Option("--heatmap", help="PNG of per-vertex errors of the mappers.")]
    = None,
    data: Annotated[str, typer.Option("--data", help="Paired-data .npz, or 'synthetic' (generated, cached).")]
    = "synthetic",
    epm: Annotated[str, typer.Option("--epm", help="EPM ONNX file, or 'default' (the shipped one).")] = "default",
    matrix: Annotated[str, typer.Option("--matrix", help="A 51x103 matrix file (EMAGE layout), or 'default' "
                                                         "(built from per-shape correspondences).")] = "default",
    head: Annotated[str, typer.Option("--head", help="Head model of the data's FLAME values: 'default' (the "
                                                     "procedural head), a FLAME .pkl or an OFERA head .npz.")]
    = "default",
    max_test_frames: Annotated[int, typer.Option(help="Subsample test frames evenly (0: all).")] = 0,
    markdown: Annotated[bool, typer.Option("--markdown", help="Also print the table as Markdown (README's).")]
    = False,
) -> None:
    """Matrix vs ridge vs EPM on held-out subjects and on a held-out source, and the BDA ablation (Table 1)."""
    from rich.console import Console

    from ..head import HeadModelError
    from ..mapping.baselines import MatrixMapper
    from ..mapping.runtime import Mapper
    from ..training.epm.evaluate import (
        default_matrix,
        draw_heatmaps,
        evaluate,
        head_of,
        load_paired_data,
        markdown_table,
        print_table,
    )

    console = Console(stderr=True)
    paired = load_paired_data(data, progress=True)
    mapper = Mapper.default() if epm == "default" else Mapper.load(epm)
    try:
        model = head_of(paired, head)
    except HeadModelError as exc:
        raise CliError(str(exc)) from None
    mat = default_matrix(model) if matrix == "default" else MatrixMapper.load(matrix)
    with console.status("evaluating") as status:
        result = evaluate(paired, mapper, mat, model, max_test_frames=max_test_frames,
                          progress=lambda msg: status.update(msg))
    print_table(result, Console())
    if markdown:
        print(markdown_table(result))
    if json_out:
        json_out.write_text(json.dumps(result.as_json(), indent=2))
        print(f"wrote {json_out}")
    if heatmap:
        draw_heatmaps(result, model, heatmap)
        print(f"wrote {heatmap}")


@mapping_app.command("make-default")
@user_errors()
def make_default(
    out: Annotated[Path | None, typer.Option("-o", "--out", help="ONNX to write (default: the package's "
                                                                 "assets/epm_default.onnx).")] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    threads: Annotated[int, typer.Option(help="torch CPU threads (1, the default, is what the shipped EPM used).")]
    = 1,
    quiet: Annotated[bool, typer.Option(help="No progress bar.")] = False,
) -> None:
    """Regenerate the shipped EPM: train on the synthetic benchmark (epoch-capped), export, score, record provenance."""
    _need_torch()
    from ..assets import asset_path
    from ..training.epm.make_default import make_default_epm

    target = out or asset_path("epm_default.onnx")
    meta = make_default_epm(target, seed=seed, threads=threads, progress=not quiet)
    m = meta["metrics"]["eval"]["methods"]
    print(f"validation L1 {meta['metrics']['val_l1']:.4f}; vertex RMSE on held-out subjects: matrix "
          f"{m['matrix']['vertex_rmse_mm']:.3f}, ridge {m['ridge']['vertex_rmse_mm']:.3f}, EPM "
          f"{m['epm']['vertex_rmse_mm']:.3f} mm")
    print(f"wrote {target}")
