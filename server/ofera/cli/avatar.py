"""`ofera avatar ...`: inspect, export, render and import Gaussian avatars."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from ..avatar import AvatarError, load_avatar
from ..head import HeadModelError
from .errors import CliError, user_errors
from .expression import ExpressionArgs, ExprOpt, EyesOpt, JawOpt
from .summary import print_summary

app = typer.Typer(help="Gaussian avatars: the built-in default, OFERA .npz, GaussianAvatars / FATE / LAM imports.",
                  no_args_is_help=True)

SourceArg = Annotated[str, typer.Argument(help="'default', an OFERA avatar .npz or a LAM .zip")]


class ImportKind(str, Enum):
    gaussianavatars = "gaussianavatars"
    fate = "fate"
    lam = "lam"


def _state(avatar, expr: list[str] | None, jaw: float, eyes: str | None):
    names: tuple[str, ...] = ()
    if getattr(avatar, "expression", "flame68") == "arkit51":
        from ..mapping.layouts import ARKIT51_NAMES

        if jaw or eyes:
            raise CliError("an ARKit-driven avatar has no jaw or eye joints: use --expr jawOpen=1, "
                           "--expr eyeLookInLeft=0.5, ...")
        names = ARKIT51_NAMES
    args = ExpressionArgs.parse(avatar.head, expr, jaw, eyes, names)
    return avatar.deformer().deform(args.vertices(avatar.head))


@app.command()
@user_errors(AvatarError, HeadModelError)
def info(
    source: SourceArg,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Gaussian count, SH degree, binding type, movable Gaussians and the head they bind to."""
    print_summary(load_avatar(source).info(), as_json)


@app.command()
@user_errors(AvatarError, HeadModelError)
def export(
    source: SourceArg,
    out: Annotated[Path, typer.Option("-o", "--out", help="3DGS .ply to write.")],
    expr: ExprOpt = None,
    jaw: JawOpt = 0.0,
    eyes: EyesOpt = None,
) -> None:
    """Write the avatar with an expression as a standard world-space 3DGS PLY (any splat viewer opens it)."""
    from ..avatar.ply import export_state_ply

    avatar = load_avatar(source)
    export_state_ply(out, _state(avatar, expr, jaw, eyes), avatar.opacity, avatar.sh)
    print(f"wrote {out} ({avatar.count} Gaussians)")


@app.command()
@user_errors(AvatarError, HeadModelError)
def render(
    source: SourceArg,
    out: Annotated[Path, typer.Option("-o", "--out", help="PNG to write.")],
    expr: ExprOpt = None,
    jaw: JawOpt = 0.0,
    eyes: EyesOpt = None,
    size: Annotated[int, typer.Option("--size", min=16, max=2048, help="Image width and height, px.")] = 512,
    yaw: Annotated[float, typer.Option("--yaw", help="Camera orbit about the vertical, degrees.")] = 0.0,
) -> None:
    """A CPU splat render (perspective, looking at the face) of the avatar with the given expression."""
    from ..avatar.render import face_camera, render_state, save_png

    avatar = load_avatar(source)
    camera = face_camera(avatar.head.v_template, avatar.head.vertex_labels, size=size, yaw_deg=yaw)
    save_png(render_state(_state(avatar, expr, jaw, eyes), avatar.opacity, avatar.sh, camera), out)
    print(f"wrote {out}")


@app.command("import")
@user_errors(AvatarError, HeadModelError)
def import_(
    kind: Annotated[ImportKind, typer.Argument(help="gaussianavatars, fate or lam")],
    sources: Annotated[list[Path], typer.Argument(help="gaussianavatars: the folder, or point_cloud.ply and "
                                                       "flame_param.npz; fate: the checkpoint; lam: the export .zip")],
    out: Annotated[Path, typer.Option("-o", "--out", help="OFERA avatar .npz to write.")],
    head: Annotated[str | None, typer.Option("--head", help="gaussianavatars / fate: the FLAME file the avatar was "
                                                            "made with (.pkl or .npz); lam: not needed.")] = None,
    n_expr: Annotated[int | None, typer.Option("--n-expr", help="FATE: expression components (default: "
                                                                "from the checkpoint's size)")] = None,
    target_order: Annotated[str | None, typer.Option("--target-order", help="lam, only for a skin.glb without morph "
                                                     "target names: 'arkit' (Apple's order) or 'sorted' "
                                                     "(alphabetical)")] = None,
    colour: Annotated[str, typer.Option("--colour", help="lam: how offset.ply's f_dc is read: 'rgb' (LAM's plain "
                                        "colour), 'sh' (3DGS DC coefficients) or 'auto' (rgb when every value "
                                        "lies in 0..1; the notes say which)")] = "auto",
) -> None:
    """Convert a GaussianAvatars or FATE avatar (bound to the given FLAME head) or a LAM export (ARKit morph
    head, no FLAME needed) into the project's .npz."""
    from ..avatar import import_fate, import_gaussianavatars, save_avatar
    from ..head import load_head

    if kind is ImportKind.lam:
        from ..avatar.lam import load_lam

        if len(sources) != 1:
            raise AvatarError(f"lam takes one .zip, got {len(sources)} paths")
        result = load_lam(sources[0], name=out.name.split(".", 1)[0], target_order=target_order, colour=colour)
        for note in result.notes:
            print(f"  {note}")
        avatar = result.avatar
        save_avatar(avatar, out)
        print(f"wrote {out} ({avatar.count} Gaussians, vertex binding, SH degree {avatar.sh_degree}, driven by "
              f"{avatar.head.expr_dims} ARKit morph targets: expression {avatar.expression})")
        return
    if head is None:
        raise CliError(f"{kind.value} needs --head: the FLAME file the avatar was made with (.pkl or .npz)")
    model = load_head(head)
    if kind is ImportKind.gaussianavatars:
        avatar = import_gaussianavatars(sources, model)
    else:
        if len(sources) != 1:
            raise AvatarError(f"fate takes one checkpoint file, got {len(sources)} paths")
        avatar = import_fate(sources[0], model, n_expr=n_expr)
    save_avatar(avatar, out)
    print(f"wrote {out} ({avatar.count} Gaussians, {avatar.binding_type} binding, head {avatar.head.name}: "
          f"{avatar.head.num_vertices} vertices, {avatar.head.num_faces} faces)")


def _register_extensions() -> None:
    """Commands other parts add to ``ofera avatar`` (``train`` lives with the trainer, ``ofera.cli.train``)."""
    try:
        from .train import register
    except ImportError:  # pragma: no cover - a distribution without the training part
        return
    register(app)


_register_extensions()
