"""Resolve an avatar name to a :class:`GaussianAvatar`: the one place that knows what ``"default"`` means.

``"default"`` is the procedural avatar (generated once, cached: :mod:`.cache`); a ``.npz`` is the project's own
file (:mod:`.io`); a ``.zip`` is a LAM export, imported once and then read from the cache (:mod:`.lam`).
"""

from __future__ import annotations

from pathlib import Path

from .cache import default_avatar
from .errors import AvatarError
from .io import load_avatar_npz
from .lam import import_lam_cached
from .model import GaussianAvatar


def load_avatar(source: str | Path) -> GaussianAvatar:
    """``"default"`` (the procedural avatar, cached on disk), an OFERA avatar ``.npz`` or a LAM export ``.zip``
    (imported once, then read from the cache: :func:`ofera.avatar.lam.import_lam_cached`)."""
    if str(source) == "default":
        return default_avatar()
    path = Path(source)
    if not path.is_file():
        raise AvatarError(f"{path}: no such file (give 'default' or an OFERA avatar .npz)")
    if path.suffix.lower() == ".zip":
        return import_lam_cached(path)
    if path.suffix != ".npz":
        raise AvatarError(
            f"{path}: unknown avatar format {path.suffix!r}: expected an OFERA avatar .npz or a LAM .zip "
            "(convert GaussianAvatars / FATE outputs with `ofera avatar import`)"
        )
    return load_avatar_npz(path)
