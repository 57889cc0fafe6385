"""The default avatar, generated once and cached on disk.

Location: ``$OFERA_CACHE`` or ``~/.cache/ofera/``, file ``avatar-default-<key>.npz`` where ``key`` hashes the
generator's version and the source of everything that shapes it (the procedural head and avatar modules,
the binding maths), so a code change makes a new file. A missing or unreadable file is regenerated; files
are written atomically (temporary file, then rename), so concurrent processes never see a partial one.
Writing a new file removes the files of earlier versions.
"""

from __future__ import annotations

import hashlib
import sys
from functools import lru_cache
from pathlib import Path

from ..assets import cache_dir
from .errors import AvatarError
from .io import FORMAT_VERSION, load_avatar_npz, save_avatar
from .model import GaussianAvatar
from .procedural import make_default_avatar


def default_avatar_key() -> str:
    """16 hex digits over the generator version, the file format version and the generating sources."""
    from ..head import procedural as head_procedural
    from . import binding, frames, procedural, sh

    h = hashlib.sha256(f"gen{procedural.GENERATOR_VERSION}/fmt{FORMAT_VERSION}/seed{procedural.SEED}".encode())
    for module in (head_procedural, procedural, binding, frames, sh):
        h.update(Path(module.__file__).read_bytes())
    return h.hexdigest()[:16]


def default_avatar_path() -> Path:
    return cache_dir(create=False) / f"avatar-default-{default_avatar_key()}.npz"


@lru_cache(maxsize=4)
def _cached(path: Path) -> GaussianAvatar:
    if path.is_file():
        try:
            return load_avatar_npz(path)
        except AvatarError as exc:
            print(f"warning: regenerating the default avatar ({exc})", file=sys.stderr)
    avatar = make_default_avatar()
    try:
        save_avatar(avatar, path)
    except OSError as exc:  # a read-only cache is not fatal
        print(f"warning: cannot cache the default avatar at {path}: {exc}", file=sys.stderr)
        return avatar
    for old in path.parent.glob("avatar-default-*.npz"):  # files of earlier generator versions
        if old != path:
            old.unlink(missing_ok=True)
    return avatar


def default_avatar() -> GaussianAvatar:
    """The procedural default avatar (from the cache, else generated and cached)."""
    return _cached(default_avatar_path())
