"""Turn expected failures into one clear line and a non-zero exit, never a traceback."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import TypeVar

import typer

from ..errors import OferaError

F = TypeVar("F", bound=Callable)


class CliError(OferaError):
    """A user-facing failure: the message says what was wrong and what to do."""


def user_errors(*types: type[BaseException]) -> Callable[[F], F]:
    """Decorate a command so that ``OferaError`` (``CliError`` included), ``ValueError``, ``FileNotFoundError``
    and the given exception types print ``error: ...``."""
    caught = (OferaError, FileNotFoundError, ValueError, *types)  # OferaError: CliError and every input error

    def wrap(fn: F) -> F:
        @functools.wraps(fn)
        def inner(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except caught as exc:
                print(f"error: {exc}", file=sys.stderr)
                raise typer.Exit(2) from None

        return inner  # type: ignore[return-value]

    return wrap
