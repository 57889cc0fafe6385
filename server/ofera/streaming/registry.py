"""Which avatars and device BDA profiles a server offers, loaded once each on first use.

Avatars directory: every entry (file or folder) is an avatar whose id is its name up to the first dot
(`anna.ply` -> `anna`), except `<id>.onnx` (that avatar's EPM) and `<id>.bda.npz` (its BDA), which sit
next to it. `default` is the built-in avatar with the shipped EPM unless the directory has its own.
Devices directory: `<device>.npz` BDA files; hello's `device` picks one.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

from ..mapping.bda import BDA
from ..mapping.runtime import Mapper
from .config import Settings
from .pipeline import AvatarAssets

DEFAULT = "default"


@dataclass(frozen=True)
class AvatarSource:
    id: str
    path: Path | None  # None: the built-in default
    epm: Path | None
    bda: Path | None


def _stem(p: Path) -> str:
    return p.name.split(".", 1)[0]


def scan_avatars(directory: Path | None) -> dict[str, AvatarSource]:
    found: dict[str, AvatarSource] = {DEFAULT: AvatarSource(DEFAULT, None, None, None)}
    if directory is None:
        return found
    if not directory.is_dir():
        raise FileNotFoundError(f"avatars directory {directory} does not exist (give a directory of avatar "
                                "files, or leave --avatars out to serve the built-in default)")
    entries = sorted(p for p in directory.iterdir() if not p.name.startswith("."))
    for p in entries:
        if p.name.endswith((".onnx", ".bda.npz")) or p.name.lower().startswith("readme"):
            continue
        aid = _stem(p)
        epm, bda = directory / f"{aid}.onnx", directory / f"{aid}.bda.npz"
        found[aid] = AvatarSource(aid, p, epm if epm.is_file() else None, bda if bda.is_file() else None)
    if DEFAULT not in found or found[DEFAULT].path is None:  # a lone default.onnx / default.bda.npz applies
        epm, bda = directory / f"{DEFAULT}.onnx", directory / f"{DEFAULT}.bda.npz"
        found[DEFAULT] = AvatarSource(DEFAULT, None, epm if epm.is_file() else None, bda if bda.is_file() else None)
    return found


def scan_devices(directory: Path | None) -> dict[str, Path]:
    if directory is None:
        return {}
    if not directory.is_dir():
        raise FileNotFoundError(f"devices directory {directory} does not exist (give a directory of "
                                "<device>.npz BDA profiles)")
    return {_stem(p): p for p in sorted(directory.glob("*.npz")) if not p.name.startswith(".")}


class AvatarRegistry:
    """Resolves avatar ids and device names; loads each avatar (with its EPM and BDA) once, thread-safely."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.sources = scan_avatars(settings.avatars)
        self.devices = scan_devices(settings.devices)
        if settings.default_avatar not in self.sources:
            raise ValueError(f"default avatar {settings.default_avatar!r} is not in {settings.avatars} "
                             f"(available: {', '.join(self.sources)})")
        self._loaded: dict[str, AvatarAssets] = {}
        self._bdas: dict[str, BDA] = {}
        self._lock = threading.Lock()
        self._locks: dict[str, threading.Lock] = {}

    def resolve(self, avatar_id: str) -> str | None:
        """The id a hello's `avatar` names (`default` -> settings.default_avatar), or None if unknown."""
        aid = self.settings.default_avatar if avatar_id == DEFAULT else avatar_id
        return aid if aid in self.sources else None

    def loaded(self, avatar_id: str) -> AvatarAssets | None:
        return self._loaded.get(avatar_id)

    def get(self, avatar_id: str) -> AvatarAssets:
        """Load (first call) and return an avatar's assets. KeyError for an unknown id."""
        aid = self.resolve(avatar_id)
        if aid is None:
            raise KeyError(f"unknown avatar {avatar_id!r}; available: {', '.join(self.sources)}")
        assets = self._loaded.get(aid)
        if assets is not None:
            return assets
        with self._lock:
            lock = self._locks.setdefault(aid, threading.Lock())
        with lock:
            if aid not in self._loaded:
                self._loaded[aid] = self._load(self.sources[aid])
            return self._loaded[aid]

    def _load(self, src: AvatarSource) -> AvatarAssets:
        from ..avatar import load_avatar

        avatar = load_avatar(DEFAULT if src.path is None else src.path)
        mapper = Mapper.load(src.epm) if src.epm is not None else Mapper.default()
        bda = BDA.load(src.bda) if src.bda is not None else None
        return AvatarAssets.create(src.id, avatar, mapper, bda, fast=self.settings.fast)

    def device_bda(self, device: str) -> BDA | None:
        """The BDA profile named `device`, or None if the server has none by that name."""
        path = self.devices.get(device)
        if path is None:
            return None
        with self._lock:
            if device not in self._bdas:
                self._bdas[device] = BDA.load(path)
            return self._bdas[device]

    def describe(self) -> list[dict]:
        out = []
        for aid, src in self.sources.items():
            a = self._loaded.get(aid)
            out.append({"id": aid, "source": "built-in" if src.path is None else src.path.name,
                        "epm": src.epm.name if src.epm else "default", "bda": src.bda.name if src.bda else "identity",
                        "loaded": a is not None, "count": a.count if a else None,
                        "sh_degree": a.sh_degree if a else None})
        return out


_REGISTRIES: dict[tuple, AvatarRegistry] = {}
_REGISTRIES_LOCK = threading.Lock()


def registry_for(settings: Settings | None = None) -> AvatarRegistry:
    """A process-wide registry per (avatars, devices, default_avatar, fast): servers and offline runs share
    loads."""
    settings = settings or Settings()
    key = (str(settings.avatars), str(settings.devices), settings.default_avatar, settings.fast)
    with _REGISTRIES_LOCK:
        reg = _REGISTRIES.get(key)
        if reg is None:
            reg = _REGISTRIES[key] = AvatarRegistry(settings)
        return reg
