"""A WebSocket client on a plain socket, the protocol's messages by hand, and connection faults: shared by
benchmarks/{stalled_client,storm}.py and tests/test_reliability_*.py (which import it from here).

- `RawWebSocket`: the handshake and masked frames written by hand, for what a library will not do: never read,
  send any bytes as a frame, reset the TCP connection; `ws_frame` one masked client frame.
- `hello`, `bs`, `pack`, `unpack`: protocol messages as msgpack bytes.
- `cycle(server, kind, rng)`: one connect/disconnect cycle of a kind in `KINDS` (clean bye, reset after hello,
  in the avatar transfer, while streaming, vanishing without a close, half-sent HTTP upgrade...).
"""

from __future__ import annotations

import asyncio
import base64
import os
import random
import socket
import struct
import time
from typing import Any

import msgpack
import numpy as np
from websockets.asyncio.client import connect

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


# ----------------------------------------------------------------------------- connection faults


def cycle(server, kind: str, rng: random.Random) -> None:
    if kind == "bye":
        async def main() -> None:
            async with connect(server.url, compression=None, max_size=None) as ws:
                await ws.send(hello(max_gaussians=200))
                while True:
                    m = unpack(await ws.recv())
                    if m["type"] == "avatar" and m["chunk"] == m["chunks"] - 1:
                        break
                await ws.send(bs(1))
                assert unpack(await ws.recv())["type"] == "frame"
                await ws.send(b"\x81\xa4type\xa3bye")
                await ws.wait_closed()

        asyncio.run(main())
        return
    if kind == "half_http":  # TCP reset in the middle of the HTTP upgrade request
        s = socket.create_connection(("127.0.0.1", server.port), 5)
        s.sendall(b"GET /v1/stream HTTP/1.1\r\nHost: x\r\nUpgrade: websock")
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.close()
        return
    c = RawWebSocket(server)
    assert c.status == 101, c.status
    if kind == "no_hello":
        c.close()
    elif kind == "reset_after_hello":  # before the welcome is even sent
        c.send(hello())
        c.abort()
    elif kind == "reset_after_welcome":  # in the middle of the avatar transfer (32 KiB chunks)
        c.send(hello())
        assert c.recv_msg()["type"] == "welcome"
        c.abort()
    elif kind == "reset_streaming":
        c.handshake()
        for i in range(rng.randrange(1, 5)):
            c.send(bs(i))
        c.recv_msg()
        c.abort()
    elif kind == "vanish_streaming":  # FIN without a WebSocket close frame
        c.handshake(max_gaussians=500)
        c.send(bs(0))
        c.vanish()
    elif kind == "vanish_after_hello":
        c.send(hello())
        c.vanish()
    else:
        raise ValueError(kind)


KINDS = ["bye", "half_http", "no_hello", "reset_after_hello", "reset_after_welcome", "reset_streaming",
         "vanish_streaming", "vanish_after_hello"]
