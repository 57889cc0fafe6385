"""Expression options shared by `head render`, `avatar render` and `avatar export`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
import typer

from ..head.model import HeadModel
from ..head.rotations import euler_xy_to_matrix
from .errors import CliError

# The options of every command that poses a head: `head render`, `avatar render`, `avatar export`.
ExprOpt = Annotated[list[str] | None, typer.Option("--expr", help="Expression coefficient INDEX=VALUE (repeatable); "
                                                  "ARKit-driven (LAM) avatars also take NAME=VALUE, e.g. jawOpen=1.")]
JawOpt = Annotated[float, typer.Option("--jaw", help="Jaw opening in degrees.")]
EyesOpt = Annotated[str | None, typer.Option("--eyes", help="Gaze YAW,PITCH in degrees.")]


@dataclass(frozen=True)
class ExpressionArgs:
    """Parsed ``--expr I=V``, ``--jaw DEG``, ``--eyes YAW,PITCH`` (degrees)."""

    expr: np.ndarray  # (E,)
    jaw: np.ndarray  # (3, 3)
    eyes: np.ndarray  # (3, 3), both eyes

    @classmethod
    def parse(cls, model: HeadModel, expr: list[str] | None, jaw: float, eyes: str | None,
              names: tuple[str, ...] = ()) -> ExpressionArgs:
        """``names``: the expression directions' names (an ARKit morph head), accepted as NAME=VALUE."""
        values = np.zeros(model.expr_dims)
        lookup = {n.lower(): i for i, n in enumerate(names)}
        for item in expr or []:
            try:
                i, v = item.split("=")
                idx = lookup[i.strip().lower()] if i.strip().lower() in lookup else int(i)
                val = float(v)
            except ValueError:
                hint = f" or NAME=VALUE ({', '.join(names[:3])}, ...)" if names else ""
                raise CliError(f"--expr {item!r}: expected INDEX=VALUE{hint}, e.g. --expr 0=2.0") from None
            if not 0 <= idx < model.expr_dims:
                raise CliError(f"--expr {item!r}: index must be 0..{model.expr_dims - 1}")
            values[idx] = val
        yaw = pitch = 0.0
        if eyes:
            try:
                yaw, pitch = (float(t) for t in eyes.split(","))
            except ValueError:
                raise CliError(f"--eyes {eyes!r}: expected YAW,PITCH in degrees, e.g. --eyes 15,-5") from None
        jaw_m = euler_xy_to_matrix(0.0, np.radians(jaw))
        eye_m = euler_xy_to_matrix(np.radians(yaw), np.radians(pitch))
        return cls(values, jaw_m, eye_m)

    def vertices(self, model: HeadModel) -> np.ndarray:
        """Deformed vertices (V, 3) of ``model`` for these options."""
        from ..head.lbs import forward

        return forward(model, self.expr[None], jaw=self.jaw, left_eye=self.eyes, right_eye=self.eyes)[0]
