"""Rooms across two `ofera serve` processes joined by a real redis-server (PROTOCOL.md 12.5), as a user runs them:
a publisher on server a and a watcher on server b meet (f32 frames bit for bit the offline pipeline's), and when
server a's process dies (SIGKILL: no goodbye) its member leaves the watcher's room within 3 s."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from ofera.client import connect, watch
from ofera.streaming import offline_pipeline
from ofera_protocol import Frame, Join, Leave
from redis_support import RedisServer, free_port, running_redis
from test_server_support import SMALL, avatars_dir, run, settings

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
try:
    from _common import wait_healthz  # the one definition, shared with the benchmarks' server processes
finally:
    sys.path.remove(str(Path(__file__).resolve().parents[1] / "benchmarks"))

pytestmark = pytest.mark.timeout(300)
ROOM = "two-processes"


class ServeProcess:
    """`ofera serve` in its own process (the console script's entry point), serving the tests' small avatar."""

    def __init__(self, redis_url: str) -> None:
        self.port = free_port()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from ofera.cli.main import app; app()", "serve", "--port", str(self.port),
             "--avatars", str(avatars_dir()), "--default-avatar", SMALL, "--redis", redis_url,
             "--log-level", "warning"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/v1/stream"

    def wait_ready(self, timeout: float = 180.0) -> ServeProcess:
        if wait_healthz(self.proc, self.port, timeout):
            return self
        if self.proc.poll() is not None:
            raise RuntimeError(f"ofera serve exited {self.proc.returncode}: {self.proc.stdout.read().decode()}")
        raise RuntimeError("ofera serve did not answer /healthz in time")

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    with running_redis() as server:
        yield server


def test_a_room_spans_two_serve_processes_and_a_dead_server_takes_its_member_out(redis_server) -> None:
    a, b = ServeProcess(redis_server.url), ServeProcess(redis_server.url)
    try:
        a.wait_ready()
        b.wait_ready()
        w8 = np.random.default_rng(7).uniform(0, 1, 52).astype(np.float32)
        state, _ = offline_pipeline(SMALL, "arkit52", w8, settings=settings())

        async def main() -> float:
            publisher = await connect(a.url, avatar=SMALL, room=ROOM, encoding="f32")
            watcher = await watch(b.url, ROOM, encoding="f32")
            try:
                frame: Frame | None = None
                deadline = time.monotonic() + 30
                while frame is None and time.monotonic() < deadline:  # publish until a frame crosses the servers
                    await publisher.send_bs(w8)
                    try:
                        msg = await watcher.recv(timeout=0.5)
                    except asyncio.TimeoutError:
                        continue
                    if isinstance(msg, Frame) and msg.member == publisher.member:
                        frame = msg
                assert frame is not None, "no frame of the publisher on server a reached the watcher on server b"
                assert any(isinstance(j, Join) and j.member == publisher.member for j in watcher.joins)
                assert frame.position.tobytes() == state.position.tobytes()
                assert frame.rotation.tobytes() == state.rotation.tobytes()
                assert frame.scale.tobytes() == state.scale.tobytes()
                publisher.ws.transport.abort()  # its server is about to die: nothing left to close
                t0 = time.monotonic()
                a.kill()
                while not any(isinstance(lv, Leave) and lv.member == publisher.member for lv in watcher.leaves):
                    try:
                        await watcher.recv(timeout=max(0.1, t0 + 6 - time.monotonic()))
                    except asyncio.TimeoutError:
                        break
                    if time.monotonic() - t0 > 6:
                        break
                took = time.monotonic() - t0
                reasons = [lv.reason for lv in watcher.leaves if lv.member == publisher.member]
                assert reasons == ["server_lost"], reasons
                return took
            finally:
                await watcher.close()

        took = run(main())
        assert took < 3.0, f"the dead server's member left after {took:.2f} s"
    finally:
        a.kill()
        b.kill()
