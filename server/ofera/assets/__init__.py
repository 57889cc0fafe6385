"""Default assets shipped with the package, and where cached generated assets live.

Shipped: ``epm_default.onnx``, the default EPM trained on the synthetic paired benchmark of the
procedural head. Regenerate it with ``ofera mapping make-default`` (same as ``ofera epm train synthetic
-o epm.pt && ofera epm export epm.pt -o server/ofera/assets/epm_default.onnx``). The default BDA is
the identity (``ofera.mapping.bda.BDA.identity()``), built in code: no file.
"""

from __future__ import annotations

import os
from pathlib import Path

ASSETS_DIR = Path(__file__).resolve().parent
EPM_DEFAULT = "epm_default.onnx"


def asset_path(name: str) -> Path:
    """Path of a shipped asset file (it may not exist in a source tree that has not generated it yet)."""
    return ASSETS_DIR / name


def default_epm_path() -> Path:
    """The shipped default EPM (ONNX); a clear error when it is missing."""
    path = asset_path(EPM_DEFAULT)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the default EPM is missing; regenerate it with `ofera mapping make-default`")
    return path


def cache_dir(*parts: str, create: bool = True) -> Path:
    """``$OFERA_CACHE`` or ``~/.cache/ofera`` (plus ``parts``), created on demand (``create``)."""
    root = Path(os.environ.get("OFERA_CACHE") or Path.home() / ".cache" / "ofera")
    path = root.joinpath(*parts)
    if create:
        path.mkdir(parents=True, exist_ok=True)
    return path
