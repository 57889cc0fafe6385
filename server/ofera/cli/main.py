"""Entry point of the `ofera` command."""

from __future__ import annotations

import typer

from . import head, replay
from . import serve as serve_cmd

app = typer.Typer(help="OFERA server: blendshape-driven Gaussian head avatars.", no_args_is_help=True,
                  pretty_exceptions_enable=False)
app.add_typer(head.app, name="head")
app.command("serve")(serve_cmd.serve)
app.command("replay")(replay.replay)
app.add_typer(replay.ingest_app, name="ingest")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
