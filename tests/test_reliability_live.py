"""Bad input over a live socket: each gets its documented error code and close code (non-fatal once the
session streams, where only that message was bad); the server never falls over: the next good bs is
still answered, new sessions still work, the server process's memory stays bounded. Also: path traversal
through avatar and device ids, huge weights, the rate limit, allowed origins, and a raw-bytes fuzzer.
"""

from __future__ import annotations

import asyncio
import functools
import random
import struct

import msgpack
import numpy as np
import pytest
from ofera_protocol import Bye, Hello, ProtocolError, decode_client_message
from test_reliability_support import (
    OP_BINARY,
    OP_TEXT,
    RawWebSocket,
    bs,
    health,
    hello,
    open_streaming,
    pack,
    recv_msg,
    rel_server,
    rel_server_process,
    rel_settings,
    rss_mb,
    start_server,
    wait_idle,
    wait_idle_process,
)
from test_server_support import run
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

HUGE = struct.pack(">I", 0xFFFFFFFF)


@functools.cache
def limited_server():
    """bs_rate 50/s (bursts of 5), and browsers only from https://ok.example."""
    return start_server(bs_rate=50.0, bs_burst=5.0, allowed_origins=["https://ok.example"])


async def good_frame(ws, seq: int, n: int = 52, **kw) -> dict:
    """Send a good bs and wait for its frame (skipping anything else)."""
    await ws.send(bs(seq, n=n, **kw))
    while True:
        m = await recv_msg(ws)
        if m["type"] == "frame" and m["seq"] == seq:
            return m


FLOAT_DTYPES = {"f32": "<f4", "f16": "<f2"}


def positions_finite(frame: dict, encoding: str = "f32") -> bool:
    """Every position of a float-encoded frame is finite (an f16 overflow decodes to infinity: PROTOCOL.md
    6.2 forbids sending it). q13 cannot express a non-finite value, so it is not a question asked here."""
    return bool(np.isfinite(np.frombuffer(frame["position"], FLOAT_DTYPES[encoding])).all())


async def expect_fatal(url: str, messages: list, code: str | None, close_code: int, **connect_kw) -> None:
    """Send `messages` (bytes: binary, str: text) on a fresh connection; expect `code` fatal (None: no error
    message, only the close) then the close with `close_code`."""
    async with connect(url, compression=None, max_size=None, **connect_kw) as ws:
        for m in messages:
            try:
                await ws.send(m)
            except ConnectionClosed:  # the server may close before a large message is fully sent
                break
        if code is not None:
            err = await recv_msg(ws)
            assert err["type"] == "error" and err["code"] == code and err["fatal"] is True, err
            assert err["message"]
        with pytest.raises(ConnectionClosed):
            while True:
                await asyncio.wait_for(ws.recv(), 15)
        assert ws.close_code == close_code, (ws.close_code, ws.close_reason)


# ----------------------------------------------------------------------------- handshake: fatal

TRAVERSAL_IDS = ["../../etc/passwd", "/etc/passwd", "default/../small", "..", ".", "small/", "./small",
                 "small.npz", "small\x00", "small\x00.npz", "%2e%2e%2fetc%2fpasswd", "..%2f..%2fetc%2fpasswd",
                 "..\\..\\windows\\win.ini", "SMALL", "small ", "broken", "C:\\x", "~root", "a" * 256]

HANDSHAKE_CASES = [
    ("empty message", [b""], "malformed", 4000),
    ("random bytes", [bytes(random.Random(1).getrandbits(8) for _ in range(64))], "malformed", 4000),
    ("truncated hello", [hello()[:-4]], "malformed", 4000),
    ("bin32 of 4 GiB", [b"\x82\xa4type\xa2bs\xa1w\xc6" + HUGE], "malformed", 4000),
    ("map32 of 4G entries", [b"\xdf" + HUGE], "malformed", 4000),
    ("deeply nested", [b"\x81\xa4type" + b"\x91" * 500 + b"\x01"], "malformed", 4000),
    ("unknown type", [pack({"type": "teleport"})], "unknown_type", 4001),
    ("wrong type for protocol", [hello(protocol="1")], "bad_field", 4002),
    ("bs before hello", [bs()], "not_ready", 4005),
    ("protocol 2", [hello(protocol=2)], "unsupported_protocol", 4010),
    ("unknown layout", [hello(layout="ovr99")], "unknown_layout", 4011),
    ("unknown encoding", [hello(encoding="jpeg")], "unknown_encoding", 4013),
    ("avatar id too long", [hello(avatar="a" * 257)], "bad_field", 4002),
    ("text frame", ["hello"], "text_frame", 1003),
    ("70 KiB message", [pack({"type": "hello", "pad": b"\0" * 70_000})], "message_too_large", 1009),
    *[(f"avatar {a!r}", [hello(avatar=a)], "unknown_avatar", 4012) for a in TRAVERSAL_IDS],
]


@pytest.mark.parametrize("messages, code, close_code", [c[1:] for c in HANDSHAKE_CASES],
                         ids=[c[0] for c in HANDSHAKE_CASES])
def test_bad_handshake_is_fatal_with_its_code(messages, code, close_code) -> None:
    run(expect_fatal(rel_server().url, messages, code, close_code))


def test_message_beyond_the_websocket_limit_closes_1009() -> None:
    """Past uvicorn's ws_max_size (max(2 x max_message_bytes, 1 MiB)) the WebSocket layer refuses the
    message before it is assembled: close 1009 without an error message."""
    run(expect_fatal(rel_server().url, [b"\0" * (2 << 20)], None, 1009))
    assert health(rel_server())["status"] == "ok"


def test_device_ids_cannot_reach_files() -> None:
    """An unknown device (traversal included) falls back to the avatar's BDA: no error, no file read."""
    async def main() -> None:
        for device in ("../../etc/passwd", "/etc/passwd", "testset/../testset", "testset\x00"):
            ws, welcome = await open_streaming(rel_server().url, device=device)
            assert welcome["avatar"]["id"] == "small"
            await good_frame(ws, 1)
            await ws.close()

    run(main())
    reg = rel_server().app.state.hub.registry
    assert set(reg._bdas) <= {"testset"}


# ----------------------------------------------------------------------------- streaming: non-fatal

STREAMING_CASES = [
    ("empty message", b"", "malformed"),
    ("random bytes", b"\xc1\x00\xff\x13", "malformed"),
    ("truncated bs", bs(1)[:-10], "malformed"),
    ("bin32 of 4 GiB", b"\x82\xa4type\xa2bs\xa1w\xc6" + HUGE, "malformed"),
    ("array32 of 4G entries", b"\x81\xa4type\xdd" + HUGE, "malformed"),
    ("deeply nested", pack({"type": "ping", "t": 1, "a": [[[[1]]]]}), "malformed"),
    ("ext type", b"\x82\xa4type\xa4ping\xa1t\xd6\xff\x00\x00\x00\x00", "malformed"),
    ("not a map", pack([1, 2]), "malformed"),
    ("unknown type", pack({"type": "teleport"}), "unknown_type"),
    ("second hello", hello(), "duplicate_hello"),
    ("second hello, other layout", hello(layout="ovr63"), "duplicate_hello"),
    ("seq is a float", pack({"type": "bs", "seq": 1.5, "t": 0, "w": b"\0" * 208}), "bad_field"),
    ("seq is a str", pack({"type": "bs", "seq": "1", "t": 0, "w": b"\0" * 208}), "bad_field"),
    ("w is a list", pack({"type": "bs", "seq": 1, "t": 0, "w": [0.5] * 52}), "bad_field"),
    ("t missing", pack({"type": "bs", "seq": 1, "w": b"\0" * 208}), "bad_field"),
    ("ping t is a str", pack({"type": "ping", "t": "now"}), "bad_field"),
    ("51 weights", bs(1, n=51), "bad_length"),
    ("70 weights", bs(1, n=70), "bad_length"),
    ("odd byte count", pack({"type": "bs", "seq": 1, "t": 0, "w": b"\0" * 207}), "bad_length"),
    ("NaN", bs(1, value=float("nan")), "non_finite"),
    ("+infinity", bs(1, value=float("inf")), "non_finite"),
    ("-infinity", bs(1, value=float("-inf")), "non_finite"),
]


def test_bad_messages_while_streaming_are_non_fatal() -> None:
    async def main() -> None:
        ws, _ = await open_streaming(rel_server().url)
        for i, (name, data, code) in enumerate(STREAMING_CASES):
            await ws.send(data)
            m = await recv_msg(ws)
            assert m["type"] == "error" and m["code"] == code and m["fatal"] is False, (name, m)
            if i % 5 == 4:  # the session goes on
                assert positions_finite(await good_frame(ws, 100 + i))
        assert positions_finite(await good_frame(ws, 999))
        await ws.send(pack({"type": "ping", "t": 7}))
        assert await recv_msg(ws) == {"type": "pong", "t": 7}
        await ws.close()

    run(main())


@pytest.mark.parametrize("data, code, close_code", [
    ("hello", "text_frame", 1003),
    (pack({"type": "ping", "t": 1, "pad": b"\0" * 70_000}), "message_too_large", 1009),
], ids=["text frame", "70 KiB message"])
def test_errors_that_stay_fatal_while_streaming(data, code, close_code) -> None:
    async def main() -> None:
        ws, _ = await open_streaming(rel_server().url)
        await good_frame(ws, 1)
        await ws.send(data)
        while True:
            m = await recv_msg(ws)
            if m["type"] == "error":
                break
        assert m["code"] == code and m["fatal"] is True, m
        with pytest.raises(ConnectionClosed):
            while True:
                await asyncio.wait_for(ws.recv(), 15)
        assert ws.close_code == close_code

    run(main())
    assert wait_idle(rel_server())


# PROTOCOL.md 4.2: weights are nominally 0..1 and the server clamps them; finite huge values are not errors.
HUGE_WEIGHTS = [
    ("arkit52", np.full(52, 1e30)), ("arkit52", np.full(52, -1e30)), ("arkit52", np.full(52, 3.4e38)),
    ("arkit52", np.where(np.arange(52) % 2, 3.4e38, -3.4e38)), ("livelink61", np.full(61, 1e30)),
    ("mediapipe52", np.full(52, -3.4e38)),
    ("ovr70", np.full(70, 3.4e38)),
]


def overflowing_weights(layout: str, count: int = 2) -> list[np.ndarray]:
    """ovr weights for which the layout adapter overflows (inf - inf = NaN): an arkit weight of an ovr
    layout sums several ovr weights, so finite +-3.4e38 inputs can make NaN inside the pipeline."""
    from ofera.mapping.layouts import LayoutAdapter

    adapter, rng, found = LayoutAdapter(layout), np.random.default_rng(0), []
    with np.errstate(all="ignore"):
        for _ in range(20_000):
            w = rng.choice(np.array([3.4e38, -3.4e38, 0.0], np.float32), adapter.layout.length)
            if not np.isfinite(adapter(w)).all():
                found.append(w)
                if len(found) == count:
                    break
    assert found, f"no overflowing {layout} weights found"
    return found


HUGE_WEIGHTS += [(layout, w) for layout in ("ovr63", "ovr70") for w in overflowing_weights(layout)]


@pytest.mark.parametrize("encoding", ["f32", "f16"])
def test_huge_finite_weights_are_clamped_not_errors(encoding: str) -> None:
    async def main() -> None:
        by_layout: dict[str, list] = {}
        for layout, w in HUGE_WEIGHTS:
            by_layout.setdefault(layout, []).append(w)
        for layout, ws_ in by_layout.items():
            ws, _ = await open_streaming(rel_server().url, layout=layout, encoding=encoding)
            for i, w in enumerate(ws_):
                await ws.send(bs(i, w=w))
                m = await recv_msg(ws)
                assert m["type"] == "frame" and m["seq"] == i, (layout, i, m)
                assert positions_finite(m, encoding), (layout, i)
            zeros = await good_frame(ws, 50, n=len(ws_[0]), value=0.0)
            ones = await good_frame(ws, 51, n=len(ws_[0]), value=1.0)
            await ws.send(bs(52, w=np.full(len(ws_[0]), 1e30)))
            big = await recv_msg(ws)
            # Every layout's arkit weights are clamp(M @ w, 0, 1), M >= 0 with rows summing to >= 1 (PROTOCOL.md
            # 4.2, mapping/layouts.py): all-1e30 and all-1 inputs both map to all ones, the same frame byte for byte.
            assert big["type"] == "frame" and big["position"] == ones["position"], layout
            assert zeros["position"] != ones["position"], layout  # (the comparison can tell frames apart)
            await ws.close()

    run(main())


# ----------------------------------------------------------------------------- limits

def test_rate_limit_drops_the_excess_with_one_error_and_queues_nothing() -> None:
    server = limited_server()  # 50 bs/s, bursts of 5

    async def main() -> None:
        ws, _ = await open_streaming(server.url)
        seen: list[dict] = []

        async def reader() -> None:
            while True:
                seen.append(await recv_msg(ws, 30))

        task = asyncio.create_task(reader())
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        sent = 0
        while loop.time() - t0 < 1.5:  # ~10x the allowed rate for 1.5 s
            await ws.send(bs(sent))
            sent += 1
            await asyncio.sleep(0.002)
        flood_end = loop.time()
        await asyncio.sleep(0.6)
        n_after = len(seen)
        await asyncio.sleep(0.6)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        frames = [m for m in seen if m["type"] == "frame"]
        errors = [m for m in seen if m["type"] == "error"]
        allowed = 5 + 50 * (flood_end - t0) + 5
        assert sent > 3 * allowed, sent
        assert len(frames) <= allowed, (len(frames), allowed)
        assert errors and all(e["code"] == "rate_limited" and e["fatal"] is False for e in errors), errors
        assert len(errors) <= 2  # at most one per second
        assert len(seen) == n_after  # nothing was queued: no frame trickles in after the flood
        await ws.close()

    run(main())


def test_allowed_origins() -> None:
    """A browser Origin outside OFERA_ALLOWED_ORIGINS is refused at the handshake (HTTP 403); no Origin
    (native clients) and listed origins are accepted."""
    server = limited_server()
    bad = RawWebSocket(server, origin="https://evil.example")
    assert bad.status == 403, bad.status
    bad.vanish()
    for origin in (None, "https://ok.example"):
        c = RawWebSocket(server, origin=origin)
        assert c.status == 101, (origin, c.status)
        c.handshake()
        c.close()
    assert wait_idle(server)


# ----------------------------------------------------------------------------- raw-bytes fuzzer

def _fuzz_messages(rng: random.Random, n: int) -> list[bytes]:
    """Random bytes, mutated valid messages and random maps; none decodes to hello or bye (which would
    legitimately end or not affect the session) and none is over the size limit."""
    valid = [hello(), bs(5), pack({"type": "ping", "t": 3}), bs(6, n=63),
             pack({"type": "bs", "seq": 1, "t": 2, "w": np.full(52, 0.5, "<f4").tobytes(), "x": {"y": [1]}})]
    keys = ["type", "seq", "t", "w", "layout", "protocol", "avatar", "x"]
    out: list[bytes] = []
    while len(out) < n:
        kind = rng.random()
        if kind < 0.3:
            data = bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 300)))
        elif kind < 0.7:
            b = bytearray(rng.choice(valid))
            for _ in range(rng.randrange(1, 6)):
                op, i = rng.random(), rng.randrange(len(b))
                if op < 0.5:
                    b[i] = rng.getrandbits(8)
                elif op < 0.75:
                    del b[i:i + rng.randrange(1, 8)]
                else:
                    b[i:i] = bytes(rng.getrandbits(8) for _ in range(rng.randrange(1, 8)))
            data = bytes(b)
        else:
            vals = [None, True, -1, 2**63, 1.5, "", "bs", "ping", b"\0" * 208, [1] * 3, {"a": {}}, "x" * 300]
            m = {rng.choice(keys): rng.choice(vals) for _ in range(rng.randrange(0, 6))}
            if rng.random() < 0.7:
                m["type"] = rng.choice(["bs", "ping", "hullo", 5, None])
            data = msgpack.packb(m, use_bin_type=True)
        try:
            msg = decode_client_message(data, "arkit52")
            if isinstance(msg, (Bye, Hello)):
                continue
        except ProtocolError:
            pass
        out.append(data)
    return out


def test_raw_bytes_fuzzer_against_the_live_endpoint() -> None:
    """Against the server in its own process (so its RSS is measured, not the client's). Mutated messages
    declare lengths far beyond what they carry, and a message is at most max_message_bytes (64 KiB): the
    server's RSS may grow by less than half of what keeping one such buffer per fuzz message would cost."""
    server = rel_server_process()
    rng = random.Random(20240901)
    messages = _fuzz_messages(rng, 400)

    async def warm_up() -> None:  # first-use allocations of a session, before the baseline
        ws, _ = await open_streaming(server.url)
        assert positions_finite(await good_frame(ws, 1))
        await ws.close()

    run(warm_up())
    assert wait_idle_process(server)
    rss0 = rss_mb(server.pid)

    async def main() -> None:
        ws, _ = await open_streaming(server.url)
        seen: list[dict] = []

        async def reader() -> None:
            while True:
                seen.append(await recv_msg(ws, 30))

        task = asyncio.create_task(reader())
        for i, data in enumerate(messages):
            await ws.send(data)
            if i % 50 == 49:
                await asyncio.sleep(0.05)
        await asyncio.sleep(0.5)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        assert all(m["type"] in ("error", "frame", "pong") for m in seen), {m["type"] for m in seen}
        assert not [m for m in seen if m["type"] == "error" and m["fatal"]], "a fatal error"
        assert {m["code"] for m in seen if m["type"] == "error"} <= {
            "malformed", "unknown_type", "bad_field", "bad_length", "non_finite", "duplicate_hello",
            "rate_limited"}
        assert positions_finite(await good_frame(ws, 10_000))  # the session survived
        await ws.close()

        # Handshake fuzz: each connection's first message is random; fatal error (or a welcome), then close.
        for data in messages[:40]:
            async with connect(server.url, compression=None, max_size=None) as c:
                await c.send(data)
                try:
                    m = await recv_msg(c)
                    assert m["type"] == "error" and m["fatal"] is True or m["type"] in ("welcome", "pong"), m
                except ConnectionClosed:
                    pass

        ws, _ = await open_streaming(server.url)  # new sessions still work
        assert positions_finite(await good_frame(ws, 1))
        await ws.close()

    run(main())
    assert health(server)["status"] == "ok"
    assert wait_idle_process(server)
    bound = 0.5 * len(messages) * rel_settings().max_message_bytes / 2**20
    growth = rss_mb(server.pid) - rss0
    print(f"server RSS growth {growth:.2f} MB, bound {bound:.1f} MB")
    assert growth < bound, f"the server's RSS grew {growth:.1f} MB (bound {bound:.1f} MB)"


def test_raw_websocket_frames() -> None:
    """Frames a library would not send: a text frame after hello, fragmented messages, a ping control
    frame, then a clean close."""
    c = RawWebSocket(rel_server())
    assert c.status == 101
    c.handshake()
    c.send(bs(1), OP_BINARY)
    assert c.recv_msg()["type"] == "frame"
    # a binary message in two fragments (FIN=0, then continuation FIN=1)
    data = bs(2)
    from test_reliability_support import ws_frame

    c.send_raw(ws_frame(data[:50], OP_BINARY, fin=False) + ws_frame(data[50:], 0x0, fin=True))
    assert c.recv_msg()["seq"] == 2
    c.send(b"hi", OP_TEXT)
    m = c.recv_msg()
    assert m["code"] == "text_frame" and m["fatal"] is True
    with pytest.raises(ConnectionError) as e:
        c.recv_msg()
    assert e.value.args[1] == 1003
    c.vanish()
    assert wait_idle(rel_server())


# ----------------------------------------------------------------------------- settings: origins, TLS

def test_security_settings_from_the_environment(monkeypatch) -> None:
    from ofera.streaming import Settings

    monkeypatch.setenv("OFERA_ALLOWED_ORIGINS", "https://A.example/, https://b.example")
    assert Settings().origins == frozenset({"https://a.example", "https://b.example"})
    monkeypatch.setenv("OFERA_ALLOWED_ORIGINS", "*")
    assert Settings().origins is None
    monkeypatch.delenv("OFERA_ALLOWED_ORIGINS")
    assert Settings().origins is None
    with pytest.raises(ValueError):
        Settings(ssl_keyfile="key.pem")  # a key without a certificate


def test_tls_serves_wss(tmp_path) -> None:
    """ssl_keyfile / ssl_certfile (`ofera serve --ssl-keyfile --ssl-certfile`) serve wss:// directly."""
    import shutil
    import ssl
    import subprocess

    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out",
                    str(cert), "-days", "1", "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1"],
                   check=True, capture_output=True)
    server = start_server(ssl_keyfile=key, ssl_certfile=cert)
    try:
        assert server.url.startswith("wss://")
        ctx = ssl.create_default_context(cafile=str(cert))

        async def main() -> None:
            async with connect(server.url, ssl=ctx, compression=None, max_size=None) as ws:
                await ws.send(hello(max_gaussians=100))
                assert (await recv_msg(ws))["type"] == "welcome"

        run(main())
    finally:
        server.stop()


STATIC_PATHS = ["/static/../../../../etc/passwd", "/static/%2e%2e/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
                "/static/..%2f..%2f__init__.py", "/static//etc/passwd", "/static/%2fetc%2fpasswd",
                "/static/..\\..\\__init__.py",
                "/static/app.js%00.png"]


@pytest.mark.parametrize("path", STATIC_PATHS)
def test_static_files_cannot_escape(path: str) -> None:
    """The browser preview's /static/ route serves only files inside its folder."""
    import socket

    with socket.create_connection(("127.0.0.1", rel_server().port), 10) as s:
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".encode())
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    assert b"root:" not in data and b"import" not in data, path
    assert int(data.split(b" ", 2)[1]) in (400, 404), (path, data[:200])


def test_max_gaussians_cannot_grow_the_server_without_bound() -> None:
    """Each reduced avatar a server streams is cached: sizes are rounded down to a few levels per avatar, so
    hellos that ask for many different max_gaussians add at most a couple of cache entries."""
    server = rel_server()
    assets = server.app.state.hub.registry.get("small")

    async def main() -> list[int]:
        counts = []
        for asked in [*range(1001, 1013), *range(2001, 2005), 2**32 - 1, 1999, 1681]:
            ws, welcome = await open_streaming(server.url, max_gaussians=asked, coords="unity")
            count = welcome["avatar"]["count"]
            assert count <= asked and (asked < 2000 or count == 2000), (asked, count)
            assert count >= 0.84 * min(asked, 2000)
            counts.append(count)
            await ws.close()
        return counts

    before = {k for k in assets._cache if k[0] == "wire"}
    counts = run(main())
    added = {k for k in assets._cache if k[0] == "wire"} - before
    assert len(added) <= 3, added
    assert set(counts) <= {1000, 1681, 2000}, set(counts)
