"""The asyncio client library (`ofera.client`) against a real server."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import numpy as np
import pytest
from ofera.client import LatencyStats, ServerError, connect, now_us, stream_url
from ofera_protocol import (
    AvatarChunk,
    ClientConnection,
    ClientState,
    ConnectionUsageError,
    ErrorMessage,
    Frame,
    FrameHeader,
    Join,
    Leave,
    Pong,
    ProtocolError,
    Welcome,
)
from test_server_support import SMALL, main_server, run

VECTORS = Path(__file__).resolve().parents[1] / "protocol" / "vectors"


def test_stream_url_forms() -> None:
    assert stream_url("127.0.0.1:8000") == "ws://127.0.0.1:8000/v1/stream"
    assert stream_url("ws://h:1") == "ws://h:1/v1/stream"
    assert stream_url("http://h:1/") == "ws://h:1/v1/stream"
    assert stream_url("https://h/v1/stream") == "wss://h/v1/stream"
    assert stream_url("ws://h:1/custom/path") == "ws://h:1/custom/path"


def test_latency_stats() -> None:
    s = LatencyStats()
    assert s.p50 is None and s.summary()["n"] == 0
    for us in range(1000, 101_000, 1000):  # 1..100 ms
        s.add(us)
    assert s.p50 == pytest.approx(50.5) and s.p99 == pytest.approx(99.01)
    summary = s.summary()
    assert summary["n"] == 100 and summary["max_ms"] == 100.0


def test_connect_stream_and_close() -> None:
    server = main_server()

    async def main() -> None:
        c = await connect(server.url, layout="arkit51", avatar=SMALL)
        assert c.welcome.layout == "arkit51" and c.avatar.count == c.count > 0
        assert c.avatar.sh.shape == (c.count, (c.welcome.avatar.sh_degree + 1) ** 2, 3)
        w = np.full(51, 0.25, np.float32)
        seqs = [await c.send_bs(w) for _ in range(3)]
        assert seqs == [0, 1, 2]
        got = []
        async for frame in c.frames(timeout=30):
            assert isinstance(frame, Frame) and frame.position.dtype == np.float32
            got.append(frame.seq)
            if frame.seq == 2:
                break
        assert got == sorted(got) and got[-1] == 2
        assert await c.send_bs(w, seq=10, t=5) == 10
        f = await c.recv_frame(timeout=30)
        assert (f.seq, f.t) == (10, 5)
        assert c.latency.p50 is not None and c.latency.p99 is not None and len(c.latency) == len(got) + 1
        await c.ping()
        assert isinstance(await c.recv(timeout=10), Pong) and len(c.pongs) == 1
        await c.send_raw(b"\xc1")  # a non-fatal error is kept, the next frame returned
        await c.send_bs(w)
        f = await c.recv_frame(timeout=30)
        assert f.seq == 11 and [e.code for e in c.errors] == ["malformed"]
        await c.close()
        await c.close()  # idempotent

    run(main())


def test_refused_handshake_raises_server_error() -> None:
    async def main() -> None:
        with pytest.raises(ServerError) as e:
            await connect(main_server().url, avatar="nobody")
        assert e.value.code == "unknown_avatar" and e.value.fatal and e.value.close_code == 4012

    run(main())


def test_fatal_error_while_streaming_raises() -> None:
    async def main() -> None:
        async with await connect(main_server().url) as c:
            await c.send_raw("text is not allowed")
            msg = await c.recv(timeout=10)
            assert isinstance(msg, ErrorMessage) and msg.fatal and msg.code == "text_frame"
            with pytest.raises(ServerError) as e:
                await c.recv_frame(timeout=10)
            assert e.value.close_code == 1003

    run(main())


def test_context_manager_sends_bye() -> None:
    async def main() -> None:
        async with await connect(main_server().url) as c:
            await c.send_bs(np.zeros(52, np.float32))
            await c.recv_frame(timeout=30)
        await asyncio.wait_for(c.ws.wait_closed(), 10)
        assert c.ws.close_code == 1000

    run(main())


def test_header_only_frames_keep_latency_and_counts() -> None:
    server = main_server()

    async def main() -> None:
        c = await connect(server.url, layout="arkit51", avatar=SMALL, header_only=True)
        assert c.header_only and c.gaussians is None and c.avatar.count == c.count > 0
        w = np.full(51, 0.25, np.float32)
        await c.send_bs(w, seq=4, t=now_us())
        head = await c.recv_frame(timeout=30)
        assert isinstance(head, FrameHeader) and head.seq == 4 and head.n == c.count and head.member is None
        assert head.size == c.last_bytes > 12 * c.count and "total" in head.timing
        assert c.frames_received == 1 and len(c.latency) == 1
        await c.ping()
        assert isinstance(await c.recv(timeout=10), Pong)  # other messages: decoded as usual
        await c.close()

    run(main())


@pytest.mark.parametrize("kwargs, what", [({"track": True}, "track=True"), ({"delta": True, "encoding": "f16"},
                                          "delta=True"), ({"encoding": "params"}, 'encoding="params"')])
def test_header_only_refuses_what_needs_arrays(kwargs, what) -> None:
    with pytest.raises(ConnectionUsageError, match=f"header_only=True .*{re.escape(what)} needs them"):
        run(connect("ws://127.0.0.1:9/v1/stream", header_only=True, **kwargs))  # refused before connecting


def _vector(name: str) -> bytes:
    return (VECTORS / f"{name}.msgpack").read_bytes()


def test_receive_header_follows_the_room_state_machine() -> None:
    """Golden vectors of a q13 room: a member's frame before its avatar is not_ready, after it a FrameHeader that
    counts in `members`; welcome, join, avatar and leave go through the state machine as with `receive`."""
    conn = ClientConnection(track_gaussians=False)
    conn.hello("arkit52", encoding="q13", room="lab-1")
    assert isinstance(conn.receive_header(_vector("welcome_room")), Welcome)
    with pytest.raises(ProtocolError, match="before its join") as e:
        conn.receive_header(_vector("frame_q13_member"))
    assert e.value.code == "not_ready" and not e.value.fatal
    assert isinstance(conn.receive_header(_vector("join")), Join)
    assert isinstance(conn.receive_header(_vector("avatar_member")), AvatarChunk)
    member = "m-03c8e1aa42f6"
    assert conn.members[member].ready and conn.members[member].frames == 0
    for _ in range(2):
        head = conn.receive_header(_vector("frame_q13_member"))
        assert isinstance(head, FrameHeader) and head.member == member and head.seq == 42
    assert conn.members[member].frames == 2
    assert isinstance(conn.receive_header(_vector("leave")), Leave) and member not in conn.members
    with pytest.raises(ProtocolError, match="before its join"):
        conn.receive_header(_vector("frame_q13_member"))


def test_receive_header_checks_v1_state_and_refuses_what_needs_arrays() -> None:
    conn = ClientConnection(track_gaussians=False)
    conn.hello("arkit52")
    with pytest.raises(ProtocolError, match="before welcome") as e:  # fatal before the stream, as in `receive`
        conn.receive_header(_vector("frame_f32"))
    assert e.value.fatal and conn.state is ClientState.CLOSED
    for kwargs in ({"encoding": "f16", "delta": True}, {"encoding": "params"}):
        c = ClientConnection(track_gaussians=False)
        c.hello("arkit52", **kwargs)
        with pytest.raises(ConnectionUsageError, match="receive_header"):
            c.receive_header(_vector("frame_f32"))
    with pytest.raises(ConnectionUsageError, match="track_gaussians"):
        ClientConnection().receive_header(_vector("frame_f32"))
