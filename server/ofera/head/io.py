"""Load a head model from ``default``, a FLAME pickle or the project's ``.npz``."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from .flame_pickle import load_flame_pickle
from .model import HeadModel, HeadModelError
from .procedural import make_procedural_head


@lru_cache(maxsize=1)
def default_head() -> HeadModel:
    """The built-in procedural head (generated on first use, then kept in memory)."""
    return make_procedural_head()


def load_head(source: str | Path) -> HeadModel:
    """``default``, a FLAME 2020/2023 ``.pkl`` (safe unpickler), or an OFERA head ``.npz``."""
    if str(source) == "default":
        return default_head()
    path = Path(source)
    if not path.is_file():
        raise HeadModelError(f"{path}: no such file (give 'default', a FLAME .pkl or an OFERA head .npz)")
    if path.suffix == ".pkl":
        return load_flame_pickle(path)
    if path.suffix == ".npz":
        return HeadModel.load_npz(path)
    raise HeadModelError(f"{path}: unknown head format {path.suffix!r} (expected .pkl or .npz)")
