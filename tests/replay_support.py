"""Helpers of the replay, ingest and confidence tests: a small avatar, a server that serves it, and `ofera ingest`
run against it with UDP datagrams (`run_ingest_cli`).

    with small_server(tmp_path) as server:      # ServerThread on a free 127.0.0.1 port
        ... replay / ingest against server.url ...

A small avatar (2,000 Gaussians by default instead of the default's ~100k) keeps tests fast on a
shared CPU; it is bound to the default procedural head, so the server's default EPM drives it.
"""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

SMALL_AVATAR_ID = "small"


def write_small_avatar(path: str | Path, count: int = 2000, seed: int = 0) -> Path:
    """Write an avatar `.npz` of `count` Gaussians on random faces of the default head."""
    from ofera.avatar import GaussianAvatar, TriangleBinding, save_avatar
    from ofera.head import default_head

    head = default_head()
    rng = np.random.default_rng(seed)
    binding = TriangleBinding(
        face=rng.integers(0, head.num_faces, count).astype(np.int64),
        position=rng.normal(0.0, 0.2, (count, 3)).astype(np.float32),
        rotation=np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (count, 1)),
        log_scale=np.full((count, 3), -1.0, np.float32),
    )
    avatar = GaussianAvatar(head, binding, np.full(count, 0.8, np.float32),
                            rng.uniform(-0.5, 0.5, (count, 1, 3)).astype(np.float32), name=SMALL_AVATAR_ID)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_avatar(avatar, path)
    return path


def small_avatar_dir(directory: str | Path, count: int = 2000) -> Path:
    """`directory` holding `small.npz` (written once), for `ofera serve --avatars DIR --default-avatar small`."""
    directory = Path(directory)
    target = directory / f"{SMALL_AVATAR_ID}.npz"
    if not target.is_file():
        write_small_avatar(target, count)
    return directory


def serve_args(directory: str | Path, count: int = 2000) -> list[str]:
    """`ofera serve` arguments that serve the small avatar as the default."""
    return ["--avatars", str(small_avatar_dir(directory, count)), "--default-avatar", SMALL_AVATAR_ID]


@contextlib.contextmanager
def small_server(directory: str | Path, count: int = 2000, **settings: object) -> Iterator:
    """A `ServerThread` on a free 127.0.0.1 port whose default avatar is the small one."""
    from ofera.streaming.config import Settings
    from ofera.streaming.server import ServerThread

    options: dict[str, object] = {"host": "127.0.0.1", "port": 0, "log_level": "warning",
                                  "avatars": small_avatar_dir(directory, count), "default_avatar": SMALL_AVATAR_ID}
    options.update(settings)
    with ServerThread(Settings(**options)) as server:
        yield server


def run_ingest_cli(kind: str, url: str, json_path: Path, datagram: Callable[[int], bytes], junk: bytes
                   ) -> tuple[int, str, dict]:
    """`ofera ingest KIND --seconds 2` on a free UDP port, fed ~1.5 s of `datagram(i)` at 60 Hz with `junk` every
    tenth: (exit status, its output, its --json summary)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-c", "from ofera.cli.main import main; main()", "ingest", kind, "--listen",
         f"127.0.0.1:{port}", "--url", url, "--seconds", "2", "--status-every", "0.5", "--json", str(json_path)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        first = proc.stdout.readline()  # printed once the session is open and the port listens
        assert " on udp 127.0.0.1" in first, first + proc.stdout.read()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            t_end = time.monotonic() + 1.5
            i = 0
            while time.monotonic() < t_end and proc.poll() is None:
                s.sendto(datagram(i), ("127.0.0.1", port))
                if i % 10 == 0:
                    s.sendto(junk, ("127.0.0.1", port))
                i += 1
                time.sleep(1 / 60)
        output, _ = proc.communicate(timeout=30)
        output = first + output
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, output, json.loads(json_path.read_text()) if json_path.is_file() else {}
