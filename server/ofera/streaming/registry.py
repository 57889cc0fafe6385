"""Which avatars and device BDA profiles a server offers, loaded once each on first use.

Avatars directory: every entry (file or folder) is an avatar whose id is its name up to the first dot
(`anna.ply` -> `anna`), except `<id>.onnx` (that avatar's EPM) and `<id>.bda.npz` (its BDA), which sit
next to it. `default` is the built-in avatar with the shipped EPM unless the directory has its own.
A `.zip` (a LAM export) is imported on first use and cached by content (`ofera.avatar.lam.import_lam_cached`);
`Settings.avatar_zip` adds one more zip, which is then the default avatar unless `default_avatar` is set.
ARKit-driven avatars (LAM) load no EPM.
Devices directory: `<device>.npz` BDA files; hello's `device` picks one.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..avatar.state import GaussianState
from ..mapping.bda import BDA
from ..mapping.runtime import Mapper
from .config import Settings
from .pipeline import KERNEL_THREADS, AvatarAssets, Pipeline

DEFAULT = "default"


@dataclass(frozen=True)
class AvatarSource:
    id: str
    path: Path | None  # None: the built-in default
    epm: Path | None
    bda: Path | None


def _stem(p: Path) -> str:
    return p.name.split(".", 1)[0]


def scan_avatars(directory: Path | None, avatar_zip: Path | None = None) -> dict[str, AvatarSource]:
    found: dict[str, AvatarSource] = {DEFAULT: AvatarSource(DEFAULT, None, None, None)}
    if avatar_zip is not None:
        if not avatar_zip.is_file():
            raise FileNotFoundError(f"avatar zip {avatar_zip} does not exist (give a LAM export .zip)")
        found[_stem(avatar_zip)] = AvatarSource(_stem(avatar_zip), avatar_zip, None, None)
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
        if avatar_zip is not None and aid == _stem(avatar_zip):
            continue  # the --avatar-zip one wins
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
        self.sources = scan_avatars(settings.avatars, settings.avatar_zip)
        self.devices = scan_devices(settings.devices)
        self.default_id = self.default_id_for(settings)
        if self.default_id not in self.sources:
            raise ValueError(f"default avatar {self.default_id!r} is not in {settings.avatars} "
                             f"(available: {', '.join(self.sources)})")
        self._loaded: dict[str, AvatarAssets] = {}
        self._bdas: dict[str, BDA] = {}
        self._lock = threading.Lock()
        self._locks: dict[str, threading.Lock] = {}

    @staticmethod
    def default_id_for(settings: Settings) -> str:
        """The id `default` means: `settings.default_avatar` when set, else the `--avatar-zip` avatar's (its name up
        to the first dot) when one is given, else `default`."""
        if settings.avatar_zip is not None and "default_avatar" not in settings.model_fields_set:
            return _stem(settings.avatar_zip)
        return settings.default_avatar

    def resolve(self, avatar_id: str) -> str | None:
        """The id a hello's `avatar` names (`default` -> the default avatar's id), or None if unknown."""
        aid = self.default_id if avatar_id == DEFAULT else avatar_id
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

        avatar = load_avatar(DEFAULT if src.path is None else src.path)  # a LAM .zip: imported once, cached
        if getattr(avatar, "expression", "flame68") == "arkit51":
            mapper = None  # driven by the aligned ARKit weights themselves
        else:
            mapper = Mapper.load(src.epm) if src.epm is not None else Mapper.default()
        bda = BDA.load(src.bda) if src.bda is not None else None
        return AvatarAssets.create(src.id, avatar, mapper, bda, fast=self.settings.fast,
                                   parallel=KERNEL_THREADS[self.settings.kernel_threads])

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
            # ARKit-driven avatars (LAM: a loaded arkit51 avatar, or a zip) load no EPM, whatever sits beside them
            arkit = (a.expression == "arkit51") if a else (src.path is not None and src.path.suffix.lower() == ".zip")
            epm = "none" if arkit else src.epm.name if src.epm else "default"
            out.append({"id": aid, "source": "built-in" if src.path is None else src.path.name,
                        "epm": epm, "bda": src.bda.name if src.bda else "identity",
                        "loaded": a is not None, "count": a.count if a else None,
                        "sh_degree": a.sh_degree if a else None, "expression": a.expression if a else None})
        return out


_REGISTRIES: dict[tuple, AvatarRegistry] = {}
_REGISTRIES_LOCK = threading.Lock()


def registry_for(settings: Settings | None = None) -> AvatarRegistry:
    """A process-wide registry per (avatars, devices, default_avatar, fast): servers and offline runs share
    loads."""
    settings = settings or Settings()
    key = (str(settings.avatars), str(settings.avatar_zip), str(settings.devices), settings.default_avatar,
           settings.fast)
    with _REGISTRIES_LOCK:
        reg = _REGISTRIES.get(key)
        if reg is None:
            reg = _REGISTRIES[key] = AvatarRegistry(settings)
        return reg


def offline_pipeline(avatar_id: str, layout: str, weights: np.ndarray, *, settings: Settings | None = None,
                     device: str | None = None) -> tuple[GaussianState, dict[str, int]]:
    """The server's computation for one frame, without a server: same registry, same Pipeline.

    `settings` selects the avatars / devices directories like the server's; None uses the defaults
    (environment included).
    """
    reg = registry_for(settings)
    assets = reg.get(avatar_id)
    bda = reg.device_bda(device) if device else None
    return Pipeline(assets, layout, bda).run(np.asarray(weights, np.float32))
