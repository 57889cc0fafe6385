"""Entry point of the `ofera` command."""

from __future__ import annotations

import typer

from . import avatar, head, replay
from . import mapping as mapping_cmd
from . import serve as serve_cmd
from .train import mia_app

# rich_markup_mode None: help texts are shown as written ("[env OFERA_PORT; default 8000]" is not rich markup).
app = typer.Typer(help="OFERA server: blendshape-driven Gaussian head avatars.", no_args_is_help=True,
                  pretty_exceptions_enable=False, rich_markup_mode=None)
app.add_typer(head.app, name="head")
app.add_typer(avatar.app, name="avatar")
app.add_typer(mapping_cmd.bda_app, name="bda")
app.add_typer(mapping_cmd.epm_app, name="epm")
app.add_typer(mapping_cmd.mapping_app, name="mapping")
app.command("serve")(serve_cmd.serve)
app.add_typer(replay.replay_app, name="replay")
app.add_typer(replay.ingest_app, name="ingest")
app.add_typer(mia_app, name="mia")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
