"""The client's zero-copy WebSocket transport (`ofera.client.transport`): the sans-I/O FrameReader (every split of
a stream, every ProtocolViolation, the pooled buffers' lifetime), frame_bytes, check_response, and `WebSocket`
live against small raw asyncio servers of this file (what a real server will not do on demand) and a real OFERA
server."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import gc
import hashlib
import random
import re
import socket
import struct
from collections.abc import AsyncIterator, Awaitable, Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from ofera.client import connect
from ofera.client import transport as transport_module
from ofera.client.transport import (
    OP_BINARY,
    OP_CLOSE,
    OP_CONT,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    Control,
    FrameReader,
    HandshakeError,
    MaskKeys,
    Message,
    ProtocolViolation,
    WebSocket,
    check_response,
    close_payload,
    frame_bytes,
    open_websocket,
)
from ofera_protocol.fast_encodings import BufferPool
from test_server_support import SMALL, main_server, run
from websockets.asyncio.client import ClientConnection as WsConnection
from websockets.exceptions import ConnectionClosed, ConnectionClosedError, ConnectionClosedOK

GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
POOLED = 1 << 16  # payloads from this size on land in pooled buffers (transport._POOLED)
WAIT = 15.0  # seconds any single step may take before the test calls it hung (never a performance claim)


# ----------------------------------------------------------------------------- frames, by hand


def server_frame(opcode: int, payload: bytes = b"", fin: bool = True, rsv: int = 0, mask: bytes | None = None,
                 form: int | None = None) -> bytes:
    """A server frame (unmasked unless `mask`); `form` forces the length form (7, 16 or 64 bits)."""
    n = len(payload)
    form = form or (7 if n < 126 else 16 if n < 65536 else 64)
    head = bytes([(0x80 if fin else 0) | rsv | opcode])
    m = 0x80 if mask is not None else 0
    if form == 7:
        head += bytes([m | n])
    elif form == 16:
        head += bytes([m | 126]) + struct.pack("!H", n)
    else:
        head += bytes([m | 127]) + struct.pack("!Q", n)
    if mask is not None:
        return head + mask + unmask(payload, mask)
    return head + payload


def unmask(data: bytes, key: bytes) -> bytes:
    a = np.frombuffer(data, np.uint8)
    return (a ^ np.resize(np.frombuffer(key, np.uint8), a.size)).tobytes()


def parse_client_frame(data: bytes) -> tuple[int, int, bytes, bytes, int]:
    """(first byte, length form 7/16/64, mask key, unmasked payload, bytes used) of one client frame."""
    b1 = data[1]
    assert b1 & 0x80, "a client frame must be masked"
    n = b1 & 0x7F
    if n < 126:
        form, at = 7, 2
    elif n == 126:
        form, at, n = 16, 4, struct.unpack_from("!H", data, 2)[0]
    else:
        form, at, n = 64, 10, struct.unpack_from("!Q", data, 2)[0]
    key = data[at:at + 4]
    return data[0], form, key, unmask(data[at + 4:at + 4 + n], key), at + 4 + n


def blob(n: int, seed: int) -> bytes:
    return random.Random(seed).randbytes(n)


def text_of(n: int, seed: int) -> str:
    """`n` characters, ASCII and multi-byte (2, 3, 4 bytes) mixed."""
    rng = random.Random(seed)
    return "".join(rng.choice("aZ0 é€😀ß\n") for _ in range(n))


def events_of(reader: FrameReader, stream: bytes, cuts: list[int]) -> list:
    """Feed `stream` cut at `cuts` (through buffer()/received() as the asyncio glue does); the events."""
    events: list = []
    at = 0
    for cut in [*sorted(cuts), len(stream)]:
        if cut > at:
            events += reader.feed(stream[at:cut])
            at = cut
    return events


def normal(events: list) -> list[tuple]:
    """Events as comparable tuples: (kind, opcode, value, type of the data)."""
    out = []
    for e in events:
        if isinstance(e, Message):
            value = e.data if isinstance(e.data, str) else bytes(e.data)
            out.append(("message", e.opcode, value, type(e.data)))
        else:
            assert isinstance(e, Control)
            out.append(("control", e.opcode, e.data, type(e.data)))
    return out


def small_stream() -> tuple[bytes, list[tuple]]:
    """Small frames of every kind (7-bit lengths, long forms of short payloads, fragments around control frames):
    (wire bytes, the events expected)."""
    text = text_of(40, 1)
    parts = [
        (server_frame(OP_BINARY, b"hi"), [("message", OP_BINARY, b"hi", bytes)]),
        (server_frame(OP_BINARY, b""), [("message", OP_BINARY, b"", bytes)]),
        (server_frame(OP_TEXT, text.encode()), [("message", OP_TEXT, text, str)]),
        (server_frame(OP_BINARY, blob(300, 2)), [("message", OP_BINARY, blob(300, 2), bytes)]),
        (server_frame(OP_BINARY, b"x" * 5, form=16), [("message", OP_BINARY, b"x" * 5, bytes)]),  # a long form for
        (server_frame(OP_BINARY, b"y" * 7, form=64), [("message", OP_BINARY, b"y" * 7, bytes)]),  # a short payload
        (server_frame(OP_PING, b"ping!"), [("control", OP_PING, b"ping!", bytes)]),
        (server_frame(OP_BINARY, b"frag-", fin=False) + server_frame(OP_PING, b"") +
         server_frame(OP_CONT, b"men", fin=False) + server_frame(OP_PONG, b"pong") + server_frame(OP_CONT, b"ted"),
         [("control", OP_PING, b"", bytes), ("control", OP_PONG, b"pong", bytes),
          ("message", OP_BINARY, b"frag-mented", bytes)]),
        (server_frame(OP_TEXT, "é€".encode()[:3], fin=False) + server_frame(OP_CONT, "é€".encode()[3:]),
         [("message", OP_TEXT, "é€", str)]),  # a character split across fragments
        (server_frame(OP_CLOSE, struct.pack("!H", 1000) + b"x" * 123), [("control", OP_CLOSE,
                                                                        struct.pack("!H", 1000) + b"x" * 123,
                                                                        bytes)]),
    ]
    return b"".join(p[0] for p in parts), [e for p in parts for e in p[1]]


def large_stream() -> tuple[bytes, list[tuple]]:
    """Frames of the three length forms and a large fragmented message around a ping."""
    big = blob(100_000, 3)
    edge = blob(65535, 4)  # the largest 16-bit length: still bytes
    first = blob(POOLED, 5)  # the smallest 64-bit length: pooled
    text = text_of(30_000, 6)  # > 64 KiB of UTF-8
    parts = [
        (server_frame(OP_BINARY, big), [("message", OP_BINARY, big, memoryview)]),
        (server_frame(OP_BINARY, b"tiny"), [("message", OP_BINARY, b"tiny", bytes)]),
        (server_frame(OP_BINARY, edge), [("message", OP_BINARY, edge, bytes)]),
        (server_frame(OP_BINARY, first), [("message", OP_BINARY, first, memoryview)]),
        (server_frame(OP_TEXT, text.encode()), [("message", OP_TEXT, text, str)]),
        (server_frame(OP_BINARY, big[:70_000], fin=False) + server_frame(OP_PING, b"in between") +
         server_frame(OP_CONT, big[70_000:]), [("control", OP_PING, b"in between", bytes),
                                               ("message", OP_BINARY, big, bytes)]),
    ]
    return b"".join(p[0] for p in parts), [e for p in parts for e in p[1]]


# ----------------------------------------------------------------------------- FrameReader


def test_every_split_of_a_stream_into_two_reads() -> None:
    stream, expected = small_stream()
    assert normal(FrameReader(1 << 20).feed(stream)) == expected  # coalesced: one read
    for cut in range(len(stream) + 1):
        assert normal(events_of(FrameReader(1 << 20), stream, [cut])) == expected, cut


def test_one_byte_at_a_time() -> None:
    for stream, expected in (small_stream(), large_stream()):
        assert normal(events_of(FrameReader(1 << 20), stream, list(range(len(stream))))) == expected


def test_large_frames_coalesced_and_split_at_their_edges() -> None:
    stream, expected = large_stream()
    assert normal(FrameReader(1 << 20).feed(stream)) == expected
    edges, at = [], 0
    reader = FrameReader(1 << 20)
    while at < len(stream):  # every frame boundary, and one byte either side of it
        n = stream[at + 1] & 0x7F
        head, size = (2, n) if n < 126 else (4, struct.unpack_from("!H", stream, at + 2)[0]) if n == 126 else \
            (10, struct.unpack_from("!Q", stream, at + 2)[0])
        edges += [at - 1, at, at + 1, at + head - 1, at + head, at + head + 1]
        at += head + size
    cuts = [c for c in edges if 0 < c < len(stream)]
    assert normal(events_of(reader, stream, cuts)) == expected


SIZES = st.one_of(st.integers(0, 125), st.integers(126, 65535), st.integers(65536, 140_000))
ITEMS = st.one_of(
    st.tuples(st.just("binary"), SIZES, st.integers(0, 1 << 30)),
    st.tuples(st.just("text"), st.integers(0, 40_000), st.integers(0, 1 << 30)),
    st.tuples(st.just("ping"), st.integers(0, 125), st.integers(0, 1 << 30)),
    st.tuples(st.just("fragmented"), st.lists(SIZES, min_size=2, max_size=4), st.integers(0, 1 << 30)),
)


def build(items: list[tuple]) -> tuple[bytes, list[tuple]]:
    wire, expected = [], []
    for kind, size, seed in items:
        if kind == "binary":
            data = blob(size, seed)
            wire.append(server_frame(OP_BINARY, data))
            expected.append(("message", OP_BINARY, data, memoryview if size >= POOLED else bytes))
        elif kind == "text":
            text = text_of(size, seed)
            wire.append(server_frame(OP_TEXT, text.encode()))
            expected.append(("message", OP_TEXT, text, str))
        elif kind == "ping":
            wire.append(server_frame(OP_PING, blob(size, seed)))
            expected.append(("control", OP_PING, blob(size, seed), bytes))
        else:  # a fragmented binary message, a ping after its first fragment
            chunks = [blob(n, seed + i) for i, n in enumerate(size)]
            wire.append(server_frame(OP_BINARY, chunks[0], fin=False))
            wire.append(server_frame(OP_PING, b"%d" % seed))
            expected.append(("control", OP_PING, b"%d" % seed, bytes))
            for i, c in enumerate(chunks[1:], 1):
                wire.append(server_frame(OP_CONT, c, fin=i == len(chunks) - 1))
            expected.append(("message", OP_BINARY, b"".join(chunks), bytes))
    return b"".join(wire), expected


READS = st.lists(st.one_of(st.integers(1, 16), st.integers(17, 4096), st.integers(4097, 140_000)), min_size=1,
                 max_size=8)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(items=st.lists(ITEMS, min_size=2, max_size=6), reads=READS, data=st.data())
def test_random_splits_of_mixed_frames(items, reads, data) -> None:
    """The stream arrives in reads of the sizes `reads` (cycled), plus cuts anywhere."""
    stream, expected = build(items)
    cuts, at, i = [], 0, 0
    while at < len(stream):
        at += reads[i % len(reads)]
        cuts.append(min(at, len(stream)))
        i += 1
    cuts += data.draw(st.lists(st.integers(0, len(stream)), max_size=30), label="cuts")
    reader = FrameReader(1 << 20)
    assert normal(events_of(reader, stream, cuts)) == expected
    assert len(reader.buffer()) > 0  # ready for the next frame: staging space again


def test_large_binary_messages_are_views_of_pooled_buffers() -> None:
    pool = BufferPool(2)
    reader = FrameReader(1 << 20, pool)
    data = blob(80_000, 7)
    (m,) = reader.feed(server_frame(OP_BINARY, data))
    assert isinstance(m.data, memoryview) and m.data.obj in pool._bufs and bytes(m.data) == data
    assert not m.data.readonly and len(m.data) == len(data)  # the view is exactly the payload


def test_a_pooled_buffer_is_not_reused_while_a_message_or_a_numpy_view_of_it_lives() -> None:
    pool = BufferPool(2)
    reader = FrameReader(1 << 20, pool)

    def message(fill: int) -> memoryview:
        (m,) = reader.feed(server_frame(OP_BINARY, bytes([fill]) * 70_000))
        return m.data

    def buffer_id(view: memoryview) -> int:  # an id: holding the buffer itself would keep it busy
        return id(view.obj)

    first = message(1)
    buf = buffer_id(first)
    array = np.frombuffer(first, np.uint8)  # a numpy view keeps the buffer alive too
    del first
    second = message(2)
    third = message(3)  # the pool (2) is full: an unpooled buffer
    assert buffer_id(second) != buf and buffer_id(third) != buf
    assert pool.unpooled == 1 and all(id(b) != buffer_id(third) for b in pool._bufs)
    assert (array == 1).all()  # never overwritten
    del second, third
    gc.collect()
    fourth = message(4)
    assert buffer_id(fourth) != buf  # the numpy view still holds the first buffer
    assert (array == 1).all() and bytes(fourth[:3]) == b"\x04" * 3
    del array, fourth
    gc.collect()
    assert buffer_id(message(5)) == buf  # dropped: its buffer is taken again
    assert buffer_id(message(6)) == buf  # and again, once that message is dropped too


def test_small_messages_are_bytes_however_the_reads_split_them() -> None:
    for size in (1, 125, 126, 1000, 65535):
        stream = server_frame(OP_BINARY, blob(size, size))
        for cut in (1, 2, 4, len(stream) // 2, len(stream) - 1):
            (m,) = events_of(FrameReader(1 << 20), stream, [cut])
            assert type(m.data) is bytes and m.data == blob(size, size), (size, cut)


def test_control_frames() -> None:
    reader = FrameReader(1 << 20)
    events = reader.feed(server_frame(OP_PING, b"a" * 125) + server_frame(OP_PONG, b"") +
                         server_frame(OP_CLOSE, struct.pack("!H", 4012) + b"reason"))
    assert events == [Control(OP_PING, b"a" * 125), Control(OP_PONG, b""),
                      Control(OP_CLOSE, struct.pack("!H", 4012) + b"reason")]


def test_text_and_binary_are_told_apart() -> None:
    (t, b) = FrameReader(1 << 20).feed(server_frame(OP_TEXT, "ü".encode()) + server_frame(OP_BINARY, "ü".encode()))
    assert (t.opcode, t.data) == (OP_TEXT, "ü") and (b.opcode, b.data) == (OP_BINARY, "ü".encode())


VIOLATIONS = [
    ("reserved bit 1", server_frame(OP_BINARY, b"x", rsv=0x40), 1002),
    ("reserved bit 2", server_frame(OP_BINARY, b"x", rsv=0x20), 1002),
    ("reserved bit 3", server_frame(OP_BINARY, b"x", rsv=0x10), 1002),
    ("masked server frame", server_frame(OP_BINARY, b"abc", mask=b"\x01\x02\x03\x04"), 1002),
    ("oversized ping", server_frame(OP_PING, b"p" * 126), 1002),
    ("oversized close", server_frame(OP_CLOSE, b"\x03\xe8" + b"c" * 124), 1002),
    ("fragmented ping", server_frame(OP_PING, b"p", fin=False), 1002),
    ("fragmented close", server_frame(OP_CLOSE, b"\x03\xe8", fin=False), 1002),
    ("continuation without a start", server_frame(OP_CONT, b"rest"), 1002),
    ("a new message inside a fragmented one", server_frame(OP_BINARY, b"a", fin=False) +
     server_frame(OP_BINARY, b"b"), 1002),
    ("a text message inside a fragmented one", server_frame(OP_TEXT, b"a", fin=False) +
     server_frame(OP_TEXT, b"b", fin=False), 1002),
    ("unknown data opcode", server_frame(0x3, b"x"), 1002),
    ("unknown control opcode", server_frame(0xB, b"x"), 1002),
    ("message over max_size", server_frame(OP_BINARY, b"m" * 1001), 1009),
    ("fragments over max_size", server_frame(OP_BINARY, b"m" * 600, fin=False) +
     server_frame(OP_CONT, b"m" * 401), 1009),
    ("over max_size, announced by a 64-bit length", server_frame(OP_BINARY, b"m" * 2000, form=64)[:10], 1009),
    ("invalid UTF-8 text", server_frame(OP_TEXT, b"ok \xff\xfe"), 1007),
    ("a truncated character at the end of a text message", server_frame(OP_TEXT, "é".encode()[:1]), 1007),
    ("invalid UTF-8 text, fragmented", server_frame(OP_TEXT, b"ok ", fin=False) + server_frame(OP_CONT, b"\xc0\xaf"),
     1007),
]


@pytest.mark.parametrize(("stream", "code"), [v[1:] for v in VIOLATIONS], ids=[v[0] for v in VIOLATIONS])
def test_protocol_violations(stream: bytes, code: int) -> None:
    with pytest.raises(ProtocolViolation) as e:
        FrameReader(1000).feed(stream)
    assert e.value.code == code and str(e.value)
    for cut in (1, len(stream) - 1):  # the same, however the bytes come
        with pytest.raises(ProtocolViolation) as e:
            events_of(FrameReader(1000), stream, [cut])
        assert e.value.code == code


def test_max_size_is_inclusive_and_ignores_control_frames() -> None:
    reader = FrameReader(1000)
    events = reader.feed(server_frame(OP_BINARY, b"m" * 1000) + server_frame(OP_BINARY, b"a" * 400, fin=False) +
                         server_frame(OP_PING, b"p" * 125) + server_frame(OP_CONT, b"b" * 600))
    assert normal(events) == [("message", OP_BINARY, b"m" * 1000, bytes), ("control", OP_PING, b"p" * 125, bytes),
                              ("message", OP_BINARY, b"a" * 400 + b"b" * 600, bytes)]


# ----------------------------------------------------------------------------- frame_bytes, close_payload


@pytest.mark.parametrize("n", [0, 1, 125, 126, 1000, 65535, 65536, 200_000])
def test_frame_bytes_is_a_masked_final_frame_of_the_right_length_form(n: int) -> None:
    payload = blob(n, n)
    for kind in (bytes, bytearray, memoryview):
        data = frame_bytes(OP_BINARY, kind(payload))
        b0, form, key, body, used = parse_client_frame(data)
        assert b0 == 0x80 | OP_BINARY and used == len(data) and body == payload
        assert form == (7 if n < 126 else 16 if n < 65536 else 64)
        if n >= 8:
            assert data[-n:] != payload  # masked on the wire
    keys = {parse_client_frame(frame_bytes(OP_TEXT, b"k"))[2] for _ in range(4)}
    assert len(keys) > 1  # a fresh key per frame (RFC 6455 5.3)
    b0, _, _, body, _ = parse_client_frame(frame_bytes(OP_PONG, b"echo"))
    assert b0 == 0x80 | OP_PONG and body == b"echo"


def test_mask_keys_come_four_random_bytes_at_a_time_across_refills(monkeypatch) -> None:
    reads: list[int] = []
    real = transport_module.os.urandom
    monkeypatch.setattr(transport_module.os, "urandom", lambda n: reads.append(n) or real(n))
    pool = MaskKeys()
    keys = [pool.take() for _ in range(2 * MaskKeys.SIZE // 4 + 3)]  # three pools
    assert reads == [MaskKeys.SIZE] * 3 and all(len(k) == 4 for k in keys)
    assert len(set(keys)) > len(keys) - 5  # random 32-bit keys: (almost) never equal
    b0, _, key, body, _ = parse_client_frame(frame_bytes(OP_BINARY, b"payload", keys[0]))
    assert key == keys[0] and body == b"payload"


def test_close_payload_keeps_reasons_valid_utf8() -> None:
    assert close_payload(1000) == b"\x03\xe8"
    assert close_payload(4012, "unknown avatar") == struct.pack("!H", 4012) + b"unknown avatar"
    long = close_payload(1001, "é" * 100)  # 200 bytes of UTF-8: cut at a character, within 125 bytes
    assert len(long) <= 125 and long[2:].decode("utf-8") == "é" * 61
    assert len(close_payload(1000, "x" * 500)) == 125


# ----------------------------------------------------------------------------- check_response


def accept(key: str) -> str:
    return base64.b64encode(hashlib.sha1(key.encode() + GUID).digest()).decode()


KEY = "dGhlIHNhbXBsZSBub25jZQ=="  # RFC 6455 1.3's example: its accept value is s3pPLMBiTxaQ9kYGzzhZRbK+xOo=


def response(status: str = "101 Switching Protocols", accept_value: str | None = None, extra: str = "",
             upgrade: str = "websocket") -> bytes:
    value = accept(KEY) if accept_value is None else accept_value
    return (f"HTTP/1.1 {status}\r\nUpgrade: {upgrade}\r\nConnection: Upgrade\r\nSec-WebSocket-Accept: {value}\r\n"
            f"{extra}\r\n").encode()


def test_check_response_accepts_the_upgrade() -> None:
    assert accept(KEY) == "s3pPLMBiTxaQ9kYGzzhZRbK+xOo="
    check_response(response(), KEY)
    check_response(response(upgrade="WebSocket", extra="Server: x\r\n").replace(b"Sec-WebSocket-Accept",
                                                                                  b"sec-websocket-accept"), KEY)


@pytest.mark.parametrize(("head", "status", "words"), [
    (response(accept_value="s3pPLMBiTxaQ9kYGzzhZRbK+xOX="), 101, "does not accept"),
    (response().replace(b"Sec-WebSocket-Accept", b"X-Other"), 101, "does not accept"),
    (response(upgrade="h2c"), 101, "does not accept"),
    (response("404 Not Found"), 404, "HTTP 404"),
    (b"HTTP/1.1 403 Forbidden\r\nContent-Length: 0\r\n\r\n", 403, "HTTP 403"),
    (b"HTTP/1.1 503 Service Unavailable\r\n\r\n", 503, "HTTP 503"),
    (response(extra="Sec-WebSocket-Extensions: permessage-deflate\r\n"), 101, "extensions"),
    (b"garbage\r\n\r\n", 0, "not an HTTP/1.1 response"),
    (b"", 0, "not an HTTP/1.1 response"),
    (b"HTTP/1.1 abc\r\n\r\n", 0, "not an HTTP/1.1 response"),
    (b"SSH-2.0-OpenSSH_9.6\r\n\r\n", 0, "not an HTTP/1.1 response"),
    (b"HTTP/1.0 101 Switching Protocols\r\n\r\n", 0, "not an HTTP/1.1 response"),
], ids=["wrong accept", "no accept", "wrong upgrade", "404", "403", "503", "extensions", "garbage", "empty",
        "status not a number", "not HTTP", "HTTP/1.0"])
def test_check_response_refuses(head: bytes, status: int, words: str) -> None:
    with pytest.raises(HandshakeError) as e:
        check_response(head, KEY)
    assert e.value.status == status and words in str(e.value)


# ----------------------------------------------------------------------------- live: raw servers of this file


class Peer:
    """The server side of one raw connection, after a handshake of the test's choosing."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, key: str) -> None:
        self.reader, self.writer, self.key = reader, writer, key

    def upgrade(self) -> bytes:
        return response(accept_value=accept(self.key))

    def send(self, data: bytes) -> None:
        self.writer.write(data)

    async def frame(self) -> tuple[int, bytes]:
        """The next client frame: (first byte, unmasked payload); asserts it is masked."""
        head = await self.reader.readexactly(2)
        assert head[1] & 0x80, "client frames must be masked"
        n = head[1] & 0x7F
        if n == 126:
            n = struct.unpack("!H", await self.reader.readexactly(2))[0]
        elif n == 127:
            n = struct.unpack("!Q", await self.reader.readexactly(8))[0]
        key = await self.reader.readexactly(4)
        return head[0], unmask(await self.reader.readexactly(n), key)

    async def eof(self) -> bool:
        """True once the client closed TCP (nothing more to read)."""
        return await self.reader.read(1) == b""


Script = Callable[[Peer], Awaitable[object]]


@contextlib.asynccontextmanager
async def raw_server(script: Script, upgrade: bool = True) -> AsyncIterator[tuple[str, asyncio.Future]]:
    """A one-connection server on a free port: reads the client's request, answers 101 (when `upgrade`; else the
    script answers), then runs `script(peer)`. Yields (url, future of the script's result or exception)."""
    done: asyncio.Future = asyncio.get_running_loop().create_future()

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            request = await reader.readuntil(b"\r\n\r\n")
            key = re.search(rb"Sec-WebSocket-Key: (\S+)\r\n", request).group(1).decode()
            assert b"Upgrade: websocket" in request and b"Sec-WebSocket-Version: 13" in request
            peer = Peer(reader, writer, key)
            if upgrade:
                peer.send(peer.upgrade())
            result = await script(peer)
            if not done.done():
                done.set_result(result)
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            if not done.done():
                done.set_exception(exc)
        finally:
            writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        yield f"ws://127.0.0.1:{port}/v1/stream", done
    finally:
        server.close()
        await server.wait_closed()


async def closing_handshake(peer: Peer, code: int = 1000) -> bytes:
    """Wait for the client's close frame, answer it with `code`, close TCP; the client's close payload."""
    b0, payload = await peer.frame()
    assert b0 == 0x80 | OP_CLOSE
    peer.send(server_frame(OP_CLOSE, struct.pack("!H", code)))
    await peer.writer.drain()
    return payload


LOOPS = ["asyncio", "uvloop"]


def run_on(loop: str, coro: Awaitable[None]) -> None:
    """Run `coro` on asyncio's loop or on uvloop (which ofera serve picks when installed; skipped without it)."""
    if loop == "asyncio":
        run(coro)
        return
    uvloop = pytest.importorskip("uvloop")
    uvloop.run(coro)


async def opened(url: str, **kwargs) -> WebSocket:
    return await asyncio.wait_for(open_websocket(url, max_size=kwargs.pop("max_size", 1 << 20), **kwargs), WAIT)


@pytest.mark.parametrize("loop", LOOPS)
def test_a_ping_is_answered_with_a_pong_of_the_same_payload(loop: str) -> None:
    payload = b"are you there? \x00\xff"

    async def script(peer: Peer) -> bytes:
        peer.send(server_frame(OP_PING, payload))
        b0, pong = await peer.frame()
        assert b0 == 0x80 | OP_PONG
        peer.send(server_frame(OP_BINARY, b"done"))
        await closing_handshake(peer)
        return pong

    async def main() -> None:
        async with raw_server(script) as (url, done):
            ws = await opened(url)
            assert await asyncio.wait_for(ws.recv(), WAIT) == b"done"  # only after the pong: the server's order
            await asyncio.wait_for(ws.close(), WAIT)
            assert await asyncio.wait_for(done, WAIT) == payload

    run_on(loop, main())


@pytest.mark.parametrize(("close", "cls", "code"), [
    (struct.pack("!H", 4012) + b"unknown avatar", ConnectionClosedError, 4012),
    (struct.pack("!H", 1000) + b"bye", ConnectionClosedOK, 1000),
    (struct.pack("!H", 1001), ConnectionClosedOK, 1001),
    (b"", ConnectionClosedOK, 1005),  # no status code: a normal closure too (as websockets has it)
], ids=["4012", "1000", "1001", "no code"])
def test_a_server_close_frame_is_echoed_and_ends_recv(close: bytes, cls: type, code: int) -> None:
    async def script(peer: Peer) -> bytes:
        peer.send(server_frame(OP_BINARY, b"last message") + server_frame(OP_CLOSE, close))
        b0, echo = await peer.frame()
        assert b0 == 0x80 | OP_CLOSE
        return echo  # then TCP closes (the server's side: RFC 6455 7.1.1)

    async def main() -> None:
        async with raw_server(script) as (url, done):
            ws = await opened(url)
            assert await asyncio.wait_for(ws.recv(), WAIT) == b"last message"  # what came before the close
            with pytest.raises(cls) as e:
                await asyncio.wait_for(ws.recv(), WAIT)
            assert type(e.value) is cls and e.value.rcvd.code == code and e.value.rcvd_then_sent is True
            if close:
                assert e.value.rcvd.reason == close[2:].decode() and e.value.sent.code == code
            echo = await asyncio.wait_for(done, WAIT)
            assert echo == close[:2]  # the code echoed (RFC 6455 5.5.1), nothing for a close without one
            await asyncio.wait_for(ws.wait_closed(), WAIT)
            assert ws.close_code == code
            with pytest.raises(cls):
                await ws.recv()
            with pytest.raises(ConnectionClosed):
                await ws.send(b"too late")
            await asyncio.wait_for(ws.close(), WAIT)  # nothing more to do, returns

    run(main())


def test_close_sends_a_masked_close_frame_and_returns() -> None:
    async def script(peer: Peer) -> bytes:
        return await closing_handshake(peer)  # then the server closes TCP first (RFC 6455 7.1.1)

    async def main() -> None:
        async with raw_server(script) as (url, done):
            ws = await opened(url, close_timeout=60)  # returning means the handshake completed, not a time-out
            assert ws.close_code is None
            await asyncio.wait_for(ws.close(4000, "bye now"), WAIT)
            assert await asyncio.wait_for(done, WAIT) == struct.pack("!H", 4000) + b"bye now"
            assert ws.close_code == 1000 and ws.sent.code == 4000 and ws.rcvd.code == 1000
            with pytest.raises(ConnectionClosedError) as e:  # 4000 is no normal closure
                await ws.recv()
            assert e.value.rcvd_then_sent is False
            with pytest.raises(ConnectionClosed):
                await ws.send(b"x")
            await asyncio.wait_for(ws.close(), WAIT)  # idempotent

    run(main())


def test_close_gives_up_after_close_timeout_when_the_server_never_answers() -> None:
    async def script(peer: Peer) -> bool:
        b0, _ = await peer.frame()
        assert b0 == 0x80 | OP_CLOSE
        return await peer.eof()  # no answer: the client closes TCP itself

    async def main() -> None:
        async with raw_server(script) as (url, done):
            ws = await opened(url, close_timeout=0.2)
            await asyncio.wait_for(ws.close(), WAIT)
            assert await asyncio.wait_for(done, WAIT) is True
            await asyncio.wait_for(ws.wait_closed(), WAIT)
            assert ws.close_code == 1006  # closed without the server's close frame
            with pytest.raises(ConnectionClosedError):
                await ws.recv()

    run(main())


def test_abort_drops_the_connection_without_a_close_frame() -> None:
    """`ws.transport` is the asyncio transport, as on websockets' ClientConnection (tests abort() with it)."""

    async def script(peer: Peer) -> bool:
        peer.send(server_frame(OP_BINARY, b"hello"))
        return await peer.eof()

    async def main() -> None:
        async with raw_server(script) as (url, done):
            ws = await opened(url)
            assert await asyncio.wait_for(ws.recv(), WAIT) == b"hello"
            ws.transport.abort()
            await asyncio.wait_for(ws.wait_closed(), WAIT)
            assert await asyncio.wait_for(done, WAIT) is True
            assert ws.close_code == 1006 and ws.sent is None
            with pytest.raises(ConnectionClosedError):
                await ws.recv()

    run(main())


@pytest.mark.parametrize("loop", LOOPS)
def test_reading_pauses_at_max_queue_unread_messages_and_resumes_after_recv(loop: str) -> None:
    count, size = 12, 100_000  # each read completes at most one such message (payloads land in their buffers)

    async def script(peer: Peer) -> None:
        for i in range(count):
            peer.send(server_frame(OP_BINARY, bytes([i]) * size))
        await peer.writer.drain()
        await closing_handshake(peer)

    async def paused(ws: WebSocket) -> None:
        while ws.protocol.transport.is_reading():
            await asyncio.sleep(0.005)

    async def main() -> None:
        async with raw_server(script) as (url, done):
            ws = await opened(url, max_queue=2)
            await asyncio.wait_for(paused(ws), WAIT)
            assert len(ws._messages) == 2  # two unread: reading stopped there
            first = await ws.recv()
            assert bytes(first[:1]) == b"\x00" and len(first) == size
            await asyncio.wait_for(paused(ws), WAIT)  # resumed, read one more, paused again
            assert len(ws._messages) == 2
            got = [first]
            while len(got) < count:
                got.append(await asyncio.wait_for(ws.recv(), WAIT))
            assert [bytes(m[:1])[0] for m in got] == list(range(count))
            assert all(bytes(m) == bytes([i]) * size for i, m in enumerate(got))  # none overwritten by a later one
            assert ws.protocol.transport.is_reading()  # below max_queue again
            del got, first
            await asyncio.wait_for(ws.close(), WAIT)
            await asyncio.wait_for(done, WAIT)

    run_on(loop, main())


@pytest.mark.parametrize("loop", LOOPS)
def test_frames_in_the_same_segment_as_the_101_response_are_parsed(loop: str) -> None:
    big = blob(200_000, 9)
    frame = server_frame(OP_BINARY, big)

    async def script(peer: Peer) -> bytes:
        # one write: the response, a ping, two messages and the start of a large one (the rest comes later)
        peer.send(peer.upgrade() + server_frame(OP_PING, b"early") + server_frame(OP_BINARY, b"first") +
                  server_frame(OP_TEXT, "second ü".encode()) + frame[:1000])
        b0, pong = await peer.frame()
        assert b0 == 0x80 | OP_PONG
        peer.send(frame[1000:])
        await closing_handshake(peer)
        return pong

    async def main() -> None:
        async with raw_server(script, upgrade=False) as (url, done):
            ws = await opened(url)
            assert await asyncio.wait_for(ws.recv(), WAIT) == b"first"
            assert await asyncio.wait_for(ws.recv(), WAIT) == "second ü"
            m = await asyncio.wait_for(ws.recv(), WAIT)
            assert isinstance(m, memoryview) and m == big
            await asyncio.wait_for(ws.close(), WAIT)
            assert await asyncio.wait_for(done, WAIT) == b"early"

    run_on(loop, main())


@pytest.mark.parametrize(("bad", "code"), [
    (server_frame(OP_BINARY, b"masked", mask=b"abcd"), 1002),
    (server_frame(OP_BINARY, b"x" * 2000), 1009),
    (server_frame(OP_TEXT, b"\xff"), 1007),
], ids=["masked", "too large", "invalid UTF-8"])
def test_a_protocol_violation_fails_the_connection_with_its_code(bad: bytes, code: int) -> None:
    async def script(peer: Peer) -> tuple[int, bool]:
        peer.send(server_frame(OP_BINARY, b"fine") + bad)
        b0, payload = await peer.frame()
        assert b0 == 0x80 | OP_CLOSE
        return struct.unpack("!H", payload[:2])[0], await peer.eof()  # and the client closes TCP

    async def main() -> None:
        async with raw_server(script) as (url, done):
            ws = await opened(url, max_size=1000)
            assert await asyncio.wait_for(done, WAIT) == (code, True)
            with pytest.raises(ConnectionClosedError) as e:
                while True:  # the message before the violation may or may not come first
                    await asyncio.wait_for(ws.recv(), WAIT)
            assert e.value.rcvd is None and e.value.sent.code == code
            await asyncio.wait_for(ws.wait_closed(), WAIT)
            assert ws.close_code == 1006

    run(main())


def test_an_http_error_answer_is_a_handshake_error_with_its_status() -> None:
    async def script(peer: Peer) -> None:
        peer.send(b"HTTP/1.1 404 Not Found\r\nContent-Type: text/plain\r\nContent-Length: 9\r\n\r\nnot found")
        await peer.writer.drain()

    async def main() -> None:
        async with raw_server(script, upgrade=False) as (url, done):
            with pytest.raises(HandshakeError) as e:
                await opened(url)
            assert e.value.status == 404 and "404" in str(e.value)
            await asyncio.wait_for(done, WAIT)

    run(main())


def test_a_wrong_accept_key_is_a_handshake_error() -> None:
    async def script(peer: Peer) -> bool:
        peer.send(response(accept_value=accept("another key")))
        return await peer.eof()  # the client hangs up

    async def main() -> None:
        async with raw_server(script, upgrade=False) as (url, done):
            with pytest.raises(HandshakeError) as e:
                await opened(url)
            assert e.value.status == 101
            assert await asyncio.wait_for(done, WAIT) is True

    run(main())


def test_a_closed_connection_during_the_handshake() -> None:
    async def script(peer: Peer) -> None:
        peer.send(b"HTTP/1.1 101 Switching")  # half a status line, then the server hangs up

    async def main() -> None:
        async with raw_server(script, upgrade=False) as (url, _):
            with pytest.raises(ConnectionError):
                await opened(url)

    run(main())


def test_connection_refused_is_an_oserror_and_bad_urls_a_valueerror() -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    async def main() -> None:
        with pytest.raises(OSError):
            await opened(f"ws://127.0.0.1:{port}/v1/stream")
        for url in ("http://127.0.0.1:1/", "127.0.0.1:1", "ws:///path"):
            with pytest.raises(ValueError, match="not a WebSocket URL"):
                await opened(url)

    run(main())


# ----------------------------------------------------------------------------- live: a real OFERA server


def test_both_transports_stream_the_same_frames_from_a_real_server() -> None:
    server = main_server()
    w = np.linspace(0, 0.8, 52, dtype=np.float32)

    async def main() -> None:
        frames = {}
        for transport, kind in (("fast", WebSocket), ("websockets", WsConnection)):
            c = await connect(server.url, avatar=SMALL, transport=transport)
            assert isinstance(c.ws, kind) and c.count > 0
            await c.send_bs(w, seq=5, t=99)
            f = await c.recv_frame(timeout=WAIT)
            assert (f.seq, f.t) == (5, 99) and f.position.shape == (c.count, 3)
            frames[transport] = f
            if transport == "fast":  # an f32 frame of 2000 Gaussians: over 64 KiB, a pooled view
                await c.send_bs(w, seq=6, t=100)
                data = await asyncio.wait_for(c.ws.recv(), WAIT)
                assert isinstance(data, memoryview) and len(data) >= POOLED
                assert c.conn.receive(data).seq == 6
            await asyncio.wait_for(c.close(), WAIT)
            assert c.ws.close_code == 1000
        for name in ("position", "rotation", "scale"):
            np.testing.assert_array_equal(getattr(frames["fast"], name), getattr(frames["websockets"], name))

    run(main())


def test_fast_transport_against_a_real_server_raw() -> None:
    """open_websocket alone: the server's fatal error and close code come through; an unknown path is refused."""
    server = main_server()

    async def main() -> None:
        with pytest.raises(HandshakeError) as e:
            await opened(server.url.replace("/v1/stream", "/v1/nowhere"))
        assert e.value.status in (403, 404)
        ws = await opened(server.url, max_size=1 << 26)
        await ws.send(b"\xc1")  # not msgpack: fatal `malformed`, close 4000
        error = await asyncio.wait_for(ws.recv(), WAIT)
        assert b"malformed" in bytes(error)
        with pytest.raises(ConnectionClosedError) as closed:
            await asyncio.wait_for(ws.recv(), WAIT)
        assert closed.value.rcvd.code == 4000 and closed.value.rcvd.reason == "malformed"
        await asyncio.wait_for(ws.wait_closed(), WAIT)
        assert ws.close_code == 4000

    run(main())


def test_an_unknown_transport_is_a_value_error() -> None:
    async def main() -> None:
        with pytest.raises(ValueError, match="unknown transport 'h3'"):
            await connect(main_server().url, transport="h3")

    run(main())


def test_messages_before_a_violation_in_the_same_read_are_kept() -> None:
    """A valid message and a bad frame in one read: the violation carries the message (the client delivers it
    before closing, as the websockets library does)."""
    reader = FrameReader(1 << 20)
    data = server_frame(OP_BINARY, b"kept") + server_frame(OP_BINARY, b"x", mask=b"\x01\x02\x03\x04")
    with pytest.raises(ProtocolViolation) as e:
        reader.feed(data)
    assert e.value.code == 1002
    assert [(ev.opcode, ev.data) for ev in e.value.events] == [(OP_BINARY, b"kept")]


def test_an_http_error_body_is_never_read_as_frames() -> None:
    """The bytes after a non-101 response's headers are its body, not WebSocket frames: a body that happens to
    look like a close frame gets no close frame back (HandshakeError, and TCP closed)."""
    async def script(peer: Peer) -> bytes:
        body = server_frame(OP_CLOSE, struct.pack("!H", 1000))
        peer.send(b"HTTP/1.1 400 Bad Request\r\nContent-Length: %d\r\n\r\n" % len(body) + body)
        await peer.writer.drain()
        return await peer.reader.read()  # everything the client sent after its request, until it closed TCP

    async def main() -> None:
        async with raw_server(script, upgrade=False) as (url, done):
            with pytest.raises(HandshakeError) as e:
                await opened(url)
            assert e.value.status == 400
            assert await asyncio.wait_for(done, WAIT) == b""

    run(main())


def test_close_with_reading_paused_still_reads_the_servers_close_frame() -> None:
    """max_queue unread messages pause reading; close() resumes it (dropping those messages) so that the server's
    close reply is read at once instead of after close_timeout."""
    async def script(peer: Peer) -> bytes:
        for k in range(6):  # more than max_queue: the client stops reading
            peer.send(server_frame(OP_BINARY, bytes([k]) * 10))
        await peer.writer.drain()
        return await closing_handshake(peer)

    async def main() -> None:
        async with raw_server(script) as (url, done):
            ws = await opened(url, max_queue=2, close_timeout=30)
            await asyncio.sleep(0.3)  # the messages arrive; reading pauses at 2
            t0 = asyncio.get_running_loop().time()
            await asyncio.wait_for(ws.close(), WAIT)
            assert asyncio.get_running_loop().time() - t0 < 5  # not the 30 s close_timeout
            assert struct.unpack("!H", (await asyncio.wait_for(done, WAIT))[:2])[0] == 1000
            assert ws.close_code == 1000

    run(main())
