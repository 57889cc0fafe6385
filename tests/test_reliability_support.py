"""Helpers of tests/test_reliability_*.py and benchmarks/{stalled_client,soak,storm}.py.

- `avatars_dir()`: the small test avatar (tests/test_server_support.py) plus an EPM next to it when the
  shipped default is absent (a stand-in with the paper's shape, benchmarks/_common.py), so that these tests
  run in a source tree that has not generated `epm_default.onnx` yet.
- `rel_server()`: one in-process server (background thread) for the reliability tests, with small avatar
  chunks (so a reset can land in the middle of the avatar transfer) and a short keepalive.
- `rel_server_process()`: the same server in a subprocess of its own, for what must be measured on the server
  alone (its RSS, `rss_mb(server.pid)`) while the clients stay in the test process.
- `RawWebSocket`, `hello`, `bs`, `cycle` (connection faults): re-exported from benchmarks/_raw.py, where the
  benchmarks find them too.
- `loop_call(server, fn)` (run a function on the server's event loop: asyncio task counts).

Run as a script, this module is that subprocess: ``python tests/test_reliability_support.py '<settings json>'``
prints the port, serves until its stdin closes.
"""

from __future__ import annotations

import asyncio
import atexit
import functools
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from test_server_support import SMALL, SMALL_COUNT, _tempdir, devices_dir, make_small_avatar, settings

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
try:
    from _common import rss_mb  # noqa: F401 - re-exported: the one definition, shared with the benchmarks
    from _raw import (  # noqa: F401 - re-exported as well: the raw client and the connection faults
        KINDS,
        OP_BINARY,
        OP_CLOSE,
        OP_TEXT,
        RawWebSocket,
        bs,
        cycle,
        hello,
        pack,
        unpack,
        ws_frame,
    )
finally:
    sys.path.remove(str(ROOT / "benchmarks"))
FRAME_F32_BYTES = SMALL_COUNT * 40
"""Positions, rotations and scales of the small avatar in float32 (PROTOCOL.md section 6: 40 B a Gaussian):
what one computed frame's state holds, the least a session that computed a frame and leaked would keep."""
PING_INTERVAL = 3.0
"""Keepalive ping interval and timeout (seconds) of the reliability server: a client that neither reads nor
answers pings is dropped after 3 to 6 s instead of uvicorn's 20 to 40 s."""


def ensure_epm(directory: Path, avatar_id: str) -> None:
    """Put an EPM `<avatar_id>.onnx` in `directory` if the package's default EPM has not been generated."""
    from ofera.assets import EPM_DEFAULT, asset_path

    if asset_path(EPM_DEFAULT).is_file() or (directory / f"{avatar_id}.onnx").is_file():
        return
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from _common import epm
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    path, _ = epm()
    shutil.copy(path, directory / f"{avatar_id}.onnx")


@functools.cache
def avatars_dir() -> Path:
    d = _tempdir("ofera-rel-avatars-")
    make_small_avatar(d / f"{SMALL}.npz")
    ensure_epm(d, SMALL)
    return d


def rel_settings(**overrides: Any):
    base = dict(avatars=avatars_dir(), devices=devices_dir(), avatar_chunk_bytes=32 * 1024, max_sessions=32)
    base.update(overrides)
    return settings(**base)


def _server_thread(s):
    """A started ServerThread with settings `s` and a PING_INTERVAL keepalive."""
    from ofera.streaming.server import ServerThread

    server = ServerThread(s)
    server.server.config.ws_ping_interval = PING_INTERVAL
    server.server.config.ws_ping_timeout = PING_INTERVAL
    return server.start()


def start_server(**overrides: Any):
    """A ServerThread with `rel_settings(**overrides)` and a PING_INTERVAL keepalive (stopped at exit)."""
    server = _server_thread(rel_settings(**overrides))
    atexit.register(server.stop)
    return server


@dataclass
class ServerProcess:
    """A reliability server in a subprocess: `url`, `port`, `http_url` like a ServerThread, and its `pid`."""

    proc: subprocess.Popen
    port: int
    log: Any = None
    """The server's stdout and stderr (a temporary file)."""

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/v1/stream"

    @property
    def http_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()  # the server's cue to stop
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@functools.cache
def rel_server_process() -> ServerProcess:
    """`rel_server()`'s settings and keepalive, served by a subprocess (stopped at exit)."""
    s = rel_settings()
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), s.model_dump_json()],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, text=True)
    line = proc.stdout.readline()
    if not line.strip().isdigit():
        proc.kill()
        proc.wait()
        log.seek(0)
        raise RuntimeError(f"the reliability server process did not start: {line!r}\n{log.read().decode()[-4000:]}")
    server = ServerProcess(proc, int(line), log)
    atexit.register(server.stop)
    return server


@functools.cache
def rel_server():
    """The reliability tests' server: open, 32 sessions, 32 KiB avatar chunks, PING_INTERVAL keepalive."""
    return start_server()


# ----------------------------------------------------------------------------- a streaming session


async def recv_msg(ws, timeout: float = 15.0) -> dict:
    return unpack(await asyncio.wait_for(ws.recv(), timeout))


async def open_streaming(url: str, **hello_fields) -> tuple:
    """A `websockets` session past its handshake (hello, welcome, every avatar chunk): (ws, welcome)."""
    from websockets.asyncio.client import connect

    ws = await connect(url, compression=None, max_size=None)
    await ws.send(hello(**hello_fields))
    welcome = await recv_msg(ws)
    assert welcome["type"] == "welcome", welcome
    while True:
        m = await recv_msg(ws)
        assert m["type"] == "avatar", m
        if m["chunk"] == m["chunks"] - 1:
            return ws, welcome


# ----------------------------------------------------------------------------- server introspection


def health(server) -> dict:
    return httpx.get(f"{server.http_url}/healthz", timeout=10).json()


def loop_call(server, fn, timeout: float = 10.0) -> Any:
    """`fn()` run on the server's event loop (its thread), e.g. `lambda: len(asyncio.all_tasks())`."""
    loop = server.server.servers[0].get_loop()

    async def call() -> Any:
        return fn()

    return asyncio.run_coroutine_threadsafe(call(), loop).result(timeout)


def task_count(server) -> int:
    return loop_call(server, lambda: len(asyncio.all_tasks()))


def wait_until(predicate, timeout: float = 15.0, every: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(every)
    return bool(predicate())


def wait_idle_process(server: ServerProcess, timeout: float = 15.0) -> bool:
    """Until a server process reports no session (/healthz)."""
    return wait_until(lambda: health(server)["sessions"] == 0, timeout)


def wait_idle(server, timeout: float = 15.0) -> bool:
    """Until the server has no session (hub) and no open connection (uvicorn)."""
    hub = server.app.state.hub
    return wait_until(lambda: hub.active == 0 and not hub.sessions and not server.server.connections(), timeout)


if __name__ == "__main__":  # the server of rel_server_process(): print the port, serve until stdin closes
    from ofera.streaming import Settings

    _server = _server_thread(Settings(**json.loads(sys.argv[1])))
    print(_server.port, flush=True)
    sys.stdin.read()
    _server.stop()
