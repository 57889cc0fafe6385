"""Helpers shared by tests/test_server_*.py and tests/test_client_*.py: real servers on free ports.

Servers run in background threads (uvicorn on 127.0.0.1, port 0) and are started once per test process
(functools.cache), serving a small avatar so that tests stay fast on a shared 2-core machine.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import dataclasses
import functools
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
from ofera.streaming import Settings
from ofera.streaming.server import ServerThread

SMALL = "small"
"""Avatar id of the small test avatar (also what `default` resolves to on the test servers)."""
SMALL_COUNT = 2000
TOKEN = "s3cret-token"
DEVICE = "testset"


def make_small_avatar(path: Path) -> None:
    """The built-in procedural avatar subsampled to SMALL_COUNT Gaussians, written as an avatar .npz."""
    from ofera.avatar import load_avatar, save_avatar

    full = load_avatar("default")
    keep = np.sort(np.random.default_rng(7).choice(full.count, size=min(SMALL_COUNT, full.count), replace=False))
    b = full.binding
    per_gaussian = {f.name: getattr(b, f.name)[keep] for f in dataclasses.fields(b)
                    if f.name != "face_scale_canonical" and isinstance(getattr(b, f.name), np.ndarray)}
    small = dataclasses.replace(full, binding=dataclasses.replace(b, **per_gaussian), opacity=full.opacity[keep],
                                sh=full.sh[keep], name=SMALL)
    save_avatar(small, path)


def make_device_bda(path: Path) -> None:
    """A non-identity BDA profile (so a device session computes something different)."""
    from ofera.mapping.bda import BDA

    rng = np.random.default_rng(3)
    w = np.eye(51, dtype=np.float32) * 0.8 + rng.normal(0, 0.02, (51, 51)).astype(np.float32)
    BDA(w, np.full(51, 0.05, np.float32), device=DEVICE).save(path)


def _tempdir(prefix: str) -> Path:
    d = Path(tempfile.mkdtemp(prefix=prefix))
    atexit.register(shutil.rmtree, d, True)
    return d


@contextlib.contextmanager
def private_cache(prefix: str) -> Iterator[Path]:
    """A temporary folder `root` holding an empty `root/avatars`, with $OFERA_CACHE at `root/cache` until the end of
    the block; then $OFERA_CACHE is as it was and `root` is removed."""
    root = Path(tempfile.mkdtemp(prefix=prefix))
    old = os.environ.get("OFERA_CACHE")
    os.environ["OFERA_CACHE"] = str(root / "cache")
    (root / "avatars").mkdir()
    try:
        yield root
    finally:
        if old is None:
            os.environ.pop("OFERA_CACHE", None)
        else:
            os.environ["OFERA_CACHE"] = old
        shutil.rmtree(root, ignore_errors=True)


@functools.cache
def avatars_dir() -> Path:
    d = _tempdir("ofera-avatars-")
    make_small_avatar(d / f"{SMALL}.npz")
    (d / "broken.npz").write_bytes(b"this is not an avatar")  # loading it fails: `internal`
    return d


@functools.cache
def devices_dir() -> Path:
    d = _tempdir("ofera-devices-")
    make_device_bda(d / f"{DEVICE}.npz")
    return d


def settings(**overrides) -> Settings:
    base = dict(host="127.0.0.1", port=0, avatars=avatars_dir(), devices=devices_dir(), default_avatar=SMALL,
                log_level="warning", compute_threads=2, hello_timeout=5.0)
    base.update(overrides)
    return Settings(**base)


def _start(s: Settings) -> ServerThread:
    server = ServerThread(s).start()
    atexit.register(server.stop)
    return server


@functools.cache
def main_server() -> ServerThread:
    """Open server: no token, generous limits."""
    return _start(settings())


@functools.cache
def strict_server() -> ServerThread:
    """Token required, one session at most, 5 bs/s with bursts of 3, 1 KiB messages, 1 s to say hello."""
    return _start(settings(token=TOKEN, max_sessions=1, bs_rate=5.0, bs_burst=3.0, max_message_bytes=1024,
                           hello_timeout=1.0))


def run(coro):
    """Run a coroutine to completion (tests are plain functions; no asyncio plugin needed)."""
    return asyncio.run(coro)


def metric(server: ServerThread, name: str, labels: str = "") -> float:
    """A sample value from /metrics (0 if absent), e.g. metric(s, "ofera_frames_skipped_total", 'stage="bs"')."""
    text = httpx.get(f"{server.http_url}/metrics", timeout=10).text
    key = f"{name}{{{labels}}}" if labels else name
    for line in text.splitlines():
        if line.startswith(key + " "):
            return float(line.split()[-1])
    return 0.0
