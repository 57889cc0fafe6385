"""`ofera avatar ...`: inspect, export, render and import Gaussian avatars."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from ..avatar import AvatarError, load_avatar
from ..head import HeadModelError
from .errors import user_errors
from .expression import ExpressionArgs, ExprOpt, EyesOpt, JawOpt
from .summary import print_summary

app = typer.Typer(help="Gaussian avatars: the built-in default, OFERA .npz, GaussianAvatars / FATE imports.",
                  no_args_is_help=True)

SourceArg = Annotated[str, typer.Argument(help="'default' or an OFERA avatar .npz")]


class ImportKind(str, Enum):
    gaussianavatars = "gaussianavatars"
    fate = "fate"


def _state(avatar, expr: list[str] | None, jaw: float, eyes: str | None):
    args = ExpressionArgs.parse(avatar.head, expr, jaw, eyes)
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
    kind: Annotated[ImportKind, typer.Argument(help="gaussianavatars or fate")],
    sources: Annotated[list[Path], typer.Argument(help="gaussianavatars: the folder, or point_cloud.ply and "
                                                       "flame_param.npz; fate: the checkpoint")],
    head: Annotated[str, typer.Option("--head", help="The FLAME file the avatar was made with (.pkl or .npz).")],
    out: Annotated[Path, typer.Option("-o", "--out", help="OFERA avatar .npz to write.")],
    n_expr: Annotated[int | None, typer.Option("--n-expr", help="FATE: expression components (default: "
                                                                "from the checkpoint's size)")] = None,
) -> None:
    """Convert a GaussianAvatars or FATE avatar into the project's .npz (bound to the given FLAME head)."""
    from ..avatar import import_fate, import_gaussianavatars, save_avatar
    from ..head import load_head

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
