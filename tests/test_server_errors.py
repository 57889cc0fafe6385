"""Every error code the server can emit, on a real socket, with its fatality and close code.

Messages are built with raw msgpack so that they can be wrong in every way the codec refuses.
"""

from __future__ import annotations

import asyncio
import time

import httpx
import msgpack
import numpy as np
import pytest
from test_server_support import TOKEN, main_server, metric, run, strict_server
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed


def pack(obj: object) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def hello(**fields) -> bytes:
    base = {"type": "hello", "protocol": 1, "layout": "arkit52", "avatar": "default", "encoding": "f32"}
    base.update(fields)
    return pack({k: v for k, v in base.items() if v is not None})


def bs(seq: int = 0, n: int = 52, value: float = 0.2) -> bytes:
    return pack({"type": "bs", "seq": seq, "t": 123, "w": np.full(n, value, "<f4").tobytes()})


async def recv_msg(ws) -> dict:
    return msgpack.unpackb(await asyncio.wait_for(ws.recv(), 15), raw=False)


async def skip_handshake(ws) -> dict:
    welcome = await recv_msg(ws)
    assert welcome["type"] == "welcome", welcome
    while True:
        m = await recv_msg(ws)
        assert m["type"] == "avatar"
        if m["chunk"] == m["chunks"] - 1:
            return welcome


async def expect_fatal(url: str, messages: list, code: str, close_code: int, after_hello: dict | None = None):
    async with connect(url, compression=None) as ws:
        if after_hello is not None:
            await ws.send(hello(**after_hello))
            await skip_handshake(ws)
        for m in messages:
            await ws.send(m)
        err = await recv_msg(ws)
        assert err["type"] == "error" and err["code"] == code and err["fatal"] is True, err
        assert err["message"]
        with pytest.raises(ConnectionClosed):
            await asyncio.wait_for(ws.recv(), 15)
        assert ws.close_code == close_code
        assert ws.close_reason == code


def wait_idle(server, timeout: float = 10.0) -> None:
    """Until the server has no session left (the strict server allows only one)."""
    deadline = time.monotonic() + timeout
    while httpx.get(f"{server.http_url}/healthz", timeout=5).json()["sessions"] and time.monotonic() < deadline:
        time.sleep(0.02)


HANDSHAKE_CASES = [
    ("not msgpack", [b"\xc1\xc1"], "malformed", 4000),
    ("not a map", [pack([1, 2, 3])], "malformed", 4000),
    ("unknown type", [pack({"type": "hullo"})], "unknown_type", 4001),
    ("no layout", [pack({"type": "hello", "protocol": 1})], "bad_field", 4002),
    ("bad coords", [hello(coords="blender")], "bad_field", 4002),
    ("bs of odd length first", [pack({"type": "bs", "seq": 0, "t": 0, "w": b"abc"})], "bad_length", 4003),
    ("NaN bs first", [bs(value=float("nan"))], "non_finite", 4004),
    ("bs before hello", [bs()], "not_ready", 4005),
    ("protocol 2", [hello(protocol=2)], "unsupported_protocol", 4010),
    ("unknown layout", [hello(layout="arkit99")], "unknown_layout", 4011),
    ("unknown avatar", [hello(avatar="nobody")], "unknown_avatar", 4012),
    ("unknown encoding", [hello(encoding="f8")], "unknown_encoding", 4013),
    ("text message", ["hello as text"], "text_frame", 1003),
    ("avatar fails to load", [hello(avatar="broken")], "internal", 1011),
    ("oversize message", [b"\x00" * 70_000], "message_too_large", 1009),
]


@pytest.mark.parametrize(("messages", "code", "close_code"), [c[1:] for c in HANDSHAKE_CASES],
                         ids=[c[0] for c in HANDSHAKE_CASES])
def test_handshake_errors_are_fatal(messages, code, close_code) -> None:
    server = main_server()
    before = metric(server, "ofera_errors_total", f'code="{code}"')
    run(expect_fatal(server.url, messages, code, close_code))
    assert metric(server, "ofera_errors_total", f'code="{code}"') == before + 1


def test_streaming_errors_that_stay_fatal() -> None:
    server = main_server()
    run(expect_fatal(server.url, ["text after welcome"], "text_frame", 1003, after_hello={}))
    run(expect_fatal(server.url, [b"\x00" * 70_000], "message_too_large", 1009, after_hello={}))


def test_streaming_errors_are_non_fatal() -> None:
    server = main_server()

    async def main() -> None:
        async with connect(server.url, compression=None) as ws:
            await ws.send(hello())
            await skip_handshake(ws)
            cases = [
                (hello(), "duplicate_hello"),
                (pack({"type": "hullo"}), "unknown_type"),
                (pack({"type": "bs", "seq": -1, "t": 0, "w": np.zeros(52, "<f4").tobytes()}), "bad_field"),
                (pack({"type": "bs", "seq": 1, "t": 0.5, "w": np.zeros(52, "<f4").tobytes()}), "bad_field"),
                (b"\x93\x01\x02", "malformed"),
                (bs(n=63), "bad_length"),
                (bs(value=float("inf")), "non_finite"),
            ]
            for data, code in cases:
                await ws.send(data)
                m = await recv_msg(ws)
                assert m["type"] == "error" and m["code"] == code and m["fatal"] is False, (code, m)
            await ws.send(bs(seq=77))
            m = await recv_msg(ws)
            assert m["type"] == "frame" and m["seq"] == 77
            await ws.send(pack({"type": "ping", "t": 42}))
            assert await recv_msg(ws) == {"type": "pong", "t": 42}
            await ws.send(pack({"type": "bye"}))
            with pytest.raises(ConnectionClosed):
                await asyncio.wait_for(ws.recv(), 10)
            assert ws.close_code == 1000

    run(main())


def test_ping_and_bye_before_hello() -> None:
    async def main() -> None:
        async with connect(main_server().url, compression=None) as ws:
            await ws.send(pack({"type": "ping", "t": -5}))
            assert await recv_msg(ws) == {"type": "pong", "t": -5}
            await ws.send(pack({"type": "bye"}))
            with pytest.raises(ConnectionClosed):
                await asyncio.wait_for(ws.recv(), 10)
            assert ws.close_code == 1000

    run(main())


def test_token_auth() -> None:
    server = strict_server()
    wait_idle(server)
    run(expect_fatal(server.url, [hello()], "unauthorized", 1008))
    wait_idle(server)
    run(expect_fatal(server.url, [hello(token="wrong")], "unauthorized", 1008))
    wait_idle(server)

    async def main() -> None:
        async with connect(server.url, compression=None) as ws:
            await ws.send(hello(token=TOKEN))
            welcome = await skip_handshake(ws)
            assert welcome["avatar"]["count"] > 0

    run(main())


def test_server_full_and_rate_limited() -> None:
    server = strict_server()  # max_sessions=1, 5 bs/s with bursts of 3
    wait_idle(server)

    async def main() -> None:
        async with connect(server.url, compression=None) as ws:
            await ws.send(hello(token=TOKEN))
            await skip_handshake(ws)
            await expect_fatal(server.url, [], "server_full", 1013)  # refused on connect, before any hello

            for seq in range(10):  # 3 pass (burst), the rest is dropped with one error
                await ws.send(bs(seq=seq))
            seen: list[dict] = []
            while not any(m["type"] == "frame" and m["seq"] <= 2 for m in seen) or \
                    not any(m["type"] == "error" for m in seen):
                seen.append(await recv_msg(ws))
            await asyncio.sleep(0.3)
            try:
                while True:
                    seen.append(msgpack.unpackb(await asyncio.wait_for(ws.recv(), 0.5), raw=False))
            except asyncio.TimeoutError:
                pass
            errors = [m for m in seen if m["type"] == "error"]
            assert len(errors) == 1, errors  # at most one rate_limited error per second
            assert errors[0]["code"] == "rate_limited" and errors[0]["fatal"] is False
            assert all(m["seq"] <= 2 for m in seen if m["type"] == "frame")

    run(main())


def test_message_limit_is_configurable() -> None:
    server = strict_server()  # 1 KiB messages
    wait_idle(server)
    run(expect_fatal(server.url, [hello(token=TOKEN) + b"\x00" * 1024], "message_too_large", 1009))


def test_hello_timeout_closes() -> None:
    server = strict_server()
    wait_idle(server)

    async def main() -> None:
        async with connect(server.url, compression=None) as ws:
            with pytest.raises(ConnectionClosed):
                await asyncio.wait_for(ws.recv(), 15)
            assert ws.close_code == 1008

    run(main())
