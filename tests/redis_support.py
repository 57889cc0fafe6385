"""A real redis-server for the rooms-across-servers tests: started on a free port, killed and restarted on the same
port. Without the redis-server binary the tests skip (and fail when CI is set: .ci/run installs it)."""

from __future__ import annotations

import contextlib
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator

from conftest import skip_or_fail

REDIS_SERVER = "redis-server"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ping(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5) as s:
            s.sendall(b"PING\r\n")
            return s.recv(16).startswith(b"+PONG")
    except OSError:
        return False


class RedisServer:
    """One redis-server process without persistence (`--save '' --appendonly no`): a restart starts empty."""

    def __init__(self, port: int | None = None) -> None:
        self.port = port or free_port()
        self.dir = tempfile.mkdtemp(prefix="ofera-redis-")
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self, timeout: float = 10.0) -> RedisServer:
        assert self.proc is None, "already running"
        self.proc = subprocess.Popen(
            [REDIS_SERVER, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--dir", self.dir, "--protected-mode", "no"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout
        while not _ping(self.port):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.kill()
                raise RuntimeError(f"redis-server did not start on port {self.port}")
            time.sleep(0.02)
        return self

    def kill(self) -> None:
        """SIGKILL (no goodbye to clients: what a crash looks like) and wait for the process."""
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            self.proc = None

    def restart(self) -> RedisServer:
        self.kill()
        return self.start()

    def close(self) -> None:
        self.kill()
        shutil.rmtree(self.dir, ignore_errors=True)


def redis_missing() -> str | None:
    return None if shutil.which(REDIS_SERVER) else f"{REDIS_SERVER} is missing (apt-get install redis-server)"


def require_redis() -> None:
    """Skip without redis-server; fail instead when CI is set."""
    missing = redis_missing()
    if missing:
        skip_or_fail(missing, "Redis test")


@contextlib.contextmanager
def running_redis() -> Iterator[RedisServer]:
    """A fresh redis-server (skips or fails first without the binary: `require_redis`), killed on exit."""
    require_redis()
    server = RedisServer().start()
    try:
        yield server
    finally:
        server.close()
