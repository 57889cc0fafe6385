"""A client that stops reading (never calls recv, small TCP receive buffer): the server keeps at most one
pending frame for it (write buffer bounded, newer frames replace older ones), another session's latency
does not suffer, and once the client also stops answering keepalive pings it is dropped (session closed,
its tasks gone); with the server in its own process, its RSS stays bounded meanwhile. The measured version
(server in a subprocess, p99 and RSS over time) is benchmarks/stalled_client.py.
"""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np
from test_reliability_support import (
    FRAME_F32_BYTES,
    PING_INTERVAL,
    RawWebSocket,
    bs,
    health,
    hello,
    rel_server,
    rel_server_process,
    rss_mb,
    task_count,
    unpack,
    wait_idle,
    wait_idle_process,
    wait_until,
)
from test_server_support import run
from websockets.asyncio.client import connect

RATE = 72.0


async def measure(url: str, seconds: float, stalled: RawWebSocket | None = None) -> list[float]:
    """Round trips (ms) of a session sending bs at RATE Hz; `stalled` is fed bs at the same rate."""
    async with connect(url, compression=None, max_size=None) as ws:
        await ws.send(hello())
        while True:
            m = unpack(await ws.recv())
            if m["type"] == "avatar" and m["chunk"] == m["chunks"] - 1:
                break
        rtts: list[float] = []

        async def reader() -> None:
            while True:
                m = unpack(await ws.recv())
                if m["type"] == "frame":
                    rtts.append((time.monotonic_ns() // 1000 - m["t"]) / 1000)

        task = asyncio.create_task(reader())
        loop = asyncio.get_running_loop()
        t0, i = loop.time(), 0
        while loop.time() - t0 < seconds:
            await ws.send(bs(i, value=(i % 50) / 50))
            if stalled is not None:
                try:
                    stalled.sock.send(stalled_frame(i))
                except (BlockingIOError, OSError):
                    pass
            i += 1
            await asyncio.sleep(max(0.0, t0 + i / RATE - loop.time()))
        await asyncio.sleep(0.2)
        task.cancel()
        return rtts


def stalled_frame(i: int) -> bytes:
    from test_reliability_support import ws_frame

    return ws_frame(bs(i, value=(i % 50) / 50))


def viewer_of(server, before: set[str], timeout: float = 10.0):
    """The session that is not in `before`, once its source and viewer exist: the server makes them just after
    sending the avatar's last chunk, so a client that has read the avatar can look before they do (CI once did)."""
    hub = server.app.state.hub
    deadline = time.monotonic() + timeout
    while True:
        new = [s for sid, s in list(hub.sessions.items()) if sid not in before]
        if new and new[0].source is not None and new[0].viewer is not None or time.monotonic() > deadline:
            return new[0] if new else None
        time.sleep(0.01)


def test_stalled_client_is_bounded_and_does_not_slow_others() -> None:
    server = rel_server()
    assert wait_idle(server)
    tasks0 = task_count(server)

    alone = run(measure(server.url, 2.0))

    hub = server.app.state.hub
    before = set(hub.sessions)
    stalled = RawWebSocket(server, rcvbuf=4096)
    stalled.handshake()  # reads the welcome and the avatar, then never reads again
    stalled.sock.setblocking(False)
    session = viewer_of(server, before)
    assert session is not None
    source, viewer = session.source, session.viewer  # (the session lets go of them when it ends)
    beside = run(measure(server.url, 2.5, stalled))

    # At most one pending frame: newer work replaced older (bs before computing or frames before sending),
    # the socket's buffer holds about one frame, and the stalled client's pipeline has stopped computing.
    assert source is not None and viewer is not None and session.id in hub.sessions
    assert source.skipped + viewer.skipped > 0, "nothing was dropped for the stalled client"
    frame_bytes = 40 * 2000 + 1024
    conns = server.server.connections()
    buffered = max(c.transport.get_write_buffer_size() for c in conns) if conns else 0
    assert buffered <= 2 * frame_bytes + 65536, f"{buffered} bytes buffered for the stalled client"
    computed = source.computed
    for i in range(36):  # half a second more of bs: at most one more frame computed for it
        try:
            stalled.sock.send(stalled_frame(10_000 + i))
        except OSError:
            pass
        time.sleep(1 / RATE)
    time.sleep(0.2)
    assert source.computed - computed <= 1, (computed, source.computed)

    p99_alone, p99_beside = np.percentile(alone, 99), np.percentile(beside, 99)
    assert len(beside) > 0.8 * RATE * 2.5, len(beside)
    # Loose in CI (a shared 2-core machine, server and clients in one process): the 2x target is measured by
    # benchmarks/stalled_client.py with the server in its own process.
    assert p99_beside <= max(3 * p99_alone, p99_alone + 30), (p99_alone, p99_beside)

    # It does not answer keepalive pings either: dropped after about 2 x PING_INTERVAL, nothing left behind.
    assert wait_until(lambda: session.id not in hub.sessions, 6 * PING_INTERVAL + 5), \
        "the stalled session was never closed"
    assert wait_idle(server)
    assert wait_until(lambda: task_count(server) <= tasks0, 5), (task_count(server), tasks0)
    try:
        stalled.sock.close()
    except OSError:
        pass


def test_stalled_client_does_not_grow_the_server_process() -> None:
    """Server in its own process: a client that stopped reading is fed bs at RATE for 3 s. The server keeps at
    most one pending frame for it (and computes none while one is unsent), so its RSS grows by less than half
    of what buffering a frame (the small avatar's float32 state) for every bs would."""
    server = rel_server_process()

    async def warm_up() -> None:  # first-use allocations of a session, before the baseline
        await measure(server.url, 0.3)

    run(warm_up())
    assert wait_idle_process(server)
    rss0 = rss_mb(server.pid)
    stalled = RawWebSocket(server, rcvbuf=4096)
    stalled.handshake()  # reads the welcome and the avatar, then never reads again
    stalled.sock.setblocking(False)
    seconds, t0, i = 3.0, time.monotonic(), 0
    while time.monotonic() - t0 < seconds:
        try:
            stalled.sock.send(stalled_frame(i))
        except OSError:
            pass
        i += 1
        time.sleep(max(0.0, t0 + i / RATE - time.monotonic()))
    growth = rss_mb(server.pid) - rss0
    assert health(server)["sessions"] == 1, "the stalled session ended before it was measured"
    stalled.abort()
    bound = 0.5 * i * FRAME_F32_BYTES / 2**20
    print(f"server RSS growth {growth:.2f} MB, bound {bound:.1f} MB")
    assert growth < bound, f"the server's RSS grew {growth:.1f} MB beside a stalled client (bound {bound:.1f} MB)"
    assert wait_idle_process(server)


def test_stalled_before_reading_the_avatar() -> None:
    """Stalls right after hello, with the avatar still to send: dropped by the keepalive as well."""
    server = rel_server()
    assert wait_idle(server)
    hub = server.app.state.hub
    c = RawWebSocket(server, rcvbuf=2048)
    c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
    c.send(hello())
    assert wait_until(lambda: hub.active == 1, 5)
    assert wait_until(lambda: hub.active == 0, 6 * PING_INTERVAL + 5), "the stalled session was never closed"
    c.sock.close()
    assert wait_idle(server)


def test_stalled_client_that_gets_a_fatal_error_is_let_go() -> None:
    """A stalled client whose session ends (here: it sends a text frame) cannot keep the connection, and
    the frame buffered for it, alive by never reading the close frame."""
    from ofera.streaming.server import StreamingWebSocketProtocol

    server = rel_server()
    assert wait_idle(server)
    old = getattr(StreamingWebSocketProtocol, "close_timeout_s", None)
    StreamingWebSocketProtocol.close_timeout_s = 1.0
    try:
        c = RawWebSocket(server, rcvbuf=4096)
        c.handshake()
        c.sock.setblocking(False)
        for i in range(72):  # one second of bs, never reading the frames
            try:
                c.sock.send(stalled_frame(i))
            except OSError:
                pass
            time.sleep(1 / RATE)
        c.sock.setblocking(True)
        from test_reliability_support import OP_TEXT

        c.send(b"not binary", OP_TEXT)
        assert wait_idle(server, 6 * PING_INTERVAL + 5), "the connection was never let go"
        c.sock.close()
    finally:
        if old is None:
            del StreamingWebSocketProtocol.close_timeout_s
        else:
            StreamingWebSocketProtocol.close_timeout_s = old
