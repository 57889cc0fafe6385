"""Helpers of tests/test_reliability_*.py and benchmarks/{stalled_client,soak,storm}.py.

- `avatars_dir()`: the small test avatar (tests/test_server_support.py) plus an EPM next to it when the
  shipped default is absent (a stand-in with the paper's shape, benchmarks/_common.py), so that these tests
  run in a source tree that has not generated `epm_default.onnx` yet.
- `rel_server()`: one in-process server (background thread) for the reliability tests, with small avatar
  chunks (so a reset can land in the middle of the avatar transfer) and a short keepalive.
- `rel_server_process()`: the same server in a subprocess of its own, for what must be measured on the server
  alone (its RSS, `rss_mb(server.pid)`) while the clients stay in the test process.
- `RawWebSocket`: a WebSocket client on a plain socket (handshake and masked frames written by hand) for
  what a library will not do: never read, send any bytes as a frame, reset the TCP connection.
- `loop_call(server, fn)` (run a function on the server's event loop: asyncio task counts).

Run as a script, this module is that subprocess: ``python tests/test_reliability_support.py '<settings json>'``
prints the port, serves until its stdin closes.
"""

from __future__ import annotations

import asyncio
import atexit
import base64
import functools
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import msgpack
import numpy as np
from test_server_support import SMALL, SMALL_COUNT, _tempdir, devices_dir, make_small_avatar, settings

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
try:
    from _common import rss_mb  # noqa: F401 - re-exported: the one definition, shared with the benchmarks
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


# ----------------------------------------------------------------------------- messages


def pack(obj: object) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def unpack(data: bytes) -> Any:
    return msgpack.unpackb(data, raw=False)


def hello(**fields: Any) -> bytes:
    base = {"type": "hello", "protocol": 1, "layout": "arkit52", "avatar": "default", "encoding": "f32"}
    base.update(fields)
    return pack({k: v for k, v in base.items() if v is not None})


def bs(seq: int = 0, n: int = 52, value: float = 0.2, w: np.ndarray | None = None, t: int | None = None) -> bytes:
    w = np.full(n, value, "<f4") if w is None else np.asarray(w, "<f4")
    return pack({"type": "bs", "seq": seq, "t": time.monotonic_ns() // 1000 if t is None else t, "w": w.tobytes()})


# ----------------------------------------------------------------------------- a WebSocket on a plain socket

OP_TEXT, OP_BINARY, OP_CLOSE = 0x1, 0x2, 0x8


def ws_frame(payload: bytes, opcode: int = OP_BINARY, fin: bool = True) -> bytes:
    """A masked client frame (RFC 6455 section 5.2)."""
    head = bytes([(0x80 if fin else 0) | opcode])
    n = len(payload)
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 1 << 16:
        head += bytes([0x80 | 126]) + struct.pack("!H", n)
    else:
        head += bytes([0x80 | 127]) + struct.pack("!Q", n)
    mask = os.urandom(4)
    body = (np.frombuffer(payload, np.uint8) ^ np.resize(np.frombuffer(mask, np.uint8), n)).tobytes()
    return head + mask + body


class RawWebSocket:
    """Blocking client on a plain socket. `rcvbuf` shrinks the kernel receive buffer (set before connect so
    that the TCP window stays small); `origin` adds an Origin header."""

    def __init__(self, server, rcvbuf: int | None = None, origin: str | None = None, timeout: float = 10.0,
                 path: str = "/v1/stream") -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(timeout)
        self.sock.connect(("127.0.0.1", server.port))
        key = base64.b64encode(os.urandom(16)).decode()
        lines = [f"GET {path} HTTP/1.1", f"Host: 127.0.0.1:{server.port}", "Upgrade: websocket",
                 "Connection: Upgrade", f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13"]
        if origin is not None:
            lines.append(f"Origin: {origin}")
        self.sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        self.buf = bytearray()
        while b"\r\n\r\n" not in self.buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                break
            self.buf += chunk
        head, _, rest = bytes(self.buf).partition(b"\r\n\r\n")
        self.buf = bytearray(rest)
        self.status = int(head.split(b" ", 2)[1]) if head.startswith(b"HTTP/") else 0

    def send(self, payload: bytes, opcode: int = OP_BINARY) -> None:
        self.sock.sendall(ws_frame(payload, opcode))

    def send_raw(self, data: bytes) -> None:
        self.sock.sendall(data)

    def _read(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.sock.recv(1 << 20)
            if not chunk:
                raise ConnectionError("connection closed")
            self.buf += chunk  # a bytearray: amortised appends
        out = bytes(self.buf[:n])
        del self.buf[:n]
        return out

    def recv(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next server frame (control frames included; no fragmentation)."""
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack("!H", self._read(2))[0]
        elif n == 127:
            n = struct.unpack("!Q", self._read(8))[0]
        return b0 & 0x0F, self._read(n)

    def recv_msg(self) -> dict:
        """The next binary message, unpacked (skips pings); ConnectionError on close, with its code."""
        while True:
            op, payload = self.recv()
            if op == OP_BINARY:
                return unpack(payload)
            if op == OP_CLOSE:
                code = struct.unpack("!H", payload[:2])[0] if len(payload) >= 2 else None
                raise ConnectionError(f"closed {code}", code, payload[2:].decode(errors="replace"))

    def handshake(self, **hello_fields: Any) -> dict:
        """hello -> welcome -> every avatar chunk; returns the welcome."""
        self.send(hello(**hello_fields))
        welcome = self.recv_msg()
        assert welcome["type"] == "welcome", welcome
        while True:
            m = self.recv_msg()
            assert m["type"] == "avatar", m["type"]
            if m["chunk"] == m["chunks"] - 1:
                return welcome

    def abort(self) -> None:
        """Reset the TCP connection (SO_LINGER 0: RST, no FIN, no WebSocket close)."""
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.sock.close()

    def vanish(self) -> None:
        """Close the socket without a WebSocket close frame (FIN only)."""
        self.sock.close()

    def close(self) -> None:
        try:
            self.send(struct.pack("!H", 1000), OP_CLOSE)
        except OSError:
            pass
        self.sock.close()


if __name__ == "__main__":  # the server of rel_server_process(): print the port, serve until stdin closes
    from ofera.streaming import Settings

    _server = _server_thread(Settings(**json.loads(sys.argv[1])))
    print(_server.port, flush=True)
    sys.stdin.read()
    _server.stop()
