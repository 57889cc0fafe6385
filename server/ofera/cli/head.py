"""`ofera head ...`: inspect and render head models."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..head import HeadModelError, load_head
from .errors import user_errors
from .expression import ExpressionArgs, ExprOpt, EyesOpt, JawOpt
from .summary import print_summary

app = typer.Typer(help="Head models: the built-in procedural head, FLAME files, OFERA .npz.", no_args_is_help=True)



@app.command()
@user_errors(HeadModelError)
def info(
    source: Annotated[str, typer.Argument(help="'default', a FLAME .pkl or an OFERA head .npz")],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Vertices, faces, basis sizes and joints of a head model."""
    print_summary(load_head(source).info(), as_json)


@app.command()
@user_errors(HeadModelError)
def render(
    source: Annotated[str, typer.Argument(help="'default', a FLAME .pkl or an OFERA head .npz")],
    out: Annotated[Path, typer.Option("-o", "--out", help="PNG to write.")],
    expr: ExprOpt = None,
    jaw: JawOpt = 0.0,
    eyes: EyesOpt = None,
) -> None:
    """A shaded picture of the head (front and three-quarter views) with the given expression."""
    from ..head.render import render_head

    model = load_head(source)
    args = ExpressionArgs.parse(model, expr, jaw, eyes)
    render_head(model, args.vertices(model), out)
    print(f"wrote {out}")


@app.command()
@user_errors(HeadModelError)
def convert(
    source: Annotated[str, typer.Argument(help="'default', a FLAME .pkl or an OFERA head .npz")],
    out: Annotated[Path, typer.Option("-o", "--out", help="OFERA head .npz to write.")],
) -> None:
    """Save any head model in the project's own .npz format (no pickle)."""
    load_head(source).save(out)
    print(f"wrote {out}")
