"""The client's WebSocket transport (RFC 6455, client side, no extensions), built so that receiving a frame copies
nothing: an asyncio ``BufferedProtocol`` hands the kernel the message buffer itself, so each payload is written once,
by ``recv_into``, where the application reads it.

    ws = await open_websocket("ws://127.0.0.1:8000/v1/stream", max_size=1 << 26)
    await ws.send(data)                      # bytes-like (binary) or str (text)
    message = await ws.recv()                # bytes, or a memoryview of a pooled buffer (large messages)
    await ws.close()

Why not the ``websockets`` library's asyncio client (used for the server's tests and kept as
``connect(..., transport="websockets")``): its receive path copies each message several times and resumes a parser
per chunk read. A 2 MB message's round trip from a bare server took 1.66 ms p50 with it, 0.77 ms with this
transport and 0.58 ms with plain socket reads (``benchmarks/transport.py``; 1 MB: 1.32 / 0.37 / 0.31 ms).

Layers, in the style of h11: :class:`FrameReader` is the sans-I/O parser (where the next bytes go, what they
completed); :class:`_Protocol` is the asyncio glue; :class:`WebSocket` is the connection (``send``, ``recv``,
``close``, ``wait_closed``, ``close_code``: the part of ``websockets``' ClientConnection the OFERA client uses, with
the same ``ConnectionClosed`` exceptions).

Large messages land in buffers of a :class:`ofera_protocol.fast_encodings.BufferPool`: a buffer is reused only
once nothing references the memoryview handed out (nor anything made from it, such as numpy views), so keeping a
message is always safe.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import os
import ssl
import struct
from collections import deque
from dataclasses import dataclass
from urllib.parse import urlsplit

from ofera_protocol.fast_encodings import BufferPool
from websockets.exceptions import ConnectionClosed, ConnectionClosedError, ConnectionClosedOK
from websockets.frames import Close

try:  # the websockets library's C helper (the same XOR, ~100x faster than the pure-Python fallback)
    from websockets.speedups import apply_mask
except ImportError:  # pragma: no cover - wheels ship the speedups
    from websockets.utils import apply_mask

OP_CONT, OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
_STAGE = 1 << 16  # bytes read at once while no large payload is being received
_POOLED = 1 << 16  # payloads at least this large land in pooled buffers (smaller ones: bytes)
_MAX_HEAD = 16 << 10  # the longest handshake response accepted
_OK_CODES = (1000, 1001, 1005)  # close codes of a normal closure (websockets.frames.OK_CLOSE_CODES)


class ProtocolViolation(Exception):
    """The server broke RFC 6455: `code` is the close code the client answers with (1002, 1007, 1009); `events`
    the messages and control frames that the same bytes completed before the violation (still delivered)."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.events: list[Message | Control] = []


class HandshakeError(Exception):
    """The server did not upgrade the connection: `status` (HTTP status code, 0 if the response was malformed)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Message:
    """A complete data message: `opcode` OP_TEXT or OP_BINARY, `data` bytes-like."""

    opcode: int
    data: bytes | memoryview


@dataclass(frozen=True)
class Control:
    """A control frame: `opcode` OP_CLOSE, OP_PING or OP_PONG, `data` its payload (<= 125 bytes)."""

    opcode: int
    data: bytes


class FrameReader:
    """Sans-I/O reader of server frames. ``buffer()`` is where the next bytes go (staging space, or the rest of the
    payload being received, in its final buffer); after the caller wrote n bytes there, ``received(n)`` parses and
    returns the Messages and Controls they completed. Raises ProtocolViolation."""

    def __init__(self, max_size: int, pool: BufferPool | None = None) -> None:
        self.max_size = max_size
        self.pool = pool if pool is not None else BufferPool(4)
        self._stage = bytearray(_STAGE)
        self._start = 0  # unparsed bytes: _stage[_start:_end]
        self._end = 0
        self._dest: memoryview | None = None  # a payload being received: _dest[_got:]
        self._got = 0
        self._frame: tuple[bool, int] = (True, OP_BINARY)  # (fin, opcode) of the payload being received
        self._parts: list[bytes | memoryview] = []  # a fragmented message so far
        self._parts_size = 0
        self._message_op = 0  # its opcode (0: none in progress)

    def feed(self, data: bytes) -> list[Message | Control]:
        """``data`` -> the events it completed (copies it in: tests and the handshake's leftover bytes)."""
        events: list[Message | Control] = []
        view = memoryview(data)
        try:
            while view:
                buf = self.buffer()
                n = min(len(buf), len(view))
                buf[:n] = view[:n]
                view = view[n:]
                events += self.received(n)
        except ProtocolViolation as e:
            e.events = events + e.events
            raise
        return events

    def buffer(self) -> memoryview:
        if self._dest is not None:
            return self._dest[self._got:]
        if self._end == len(self._stage):
            self._compact()
        return memoryview(self._stage)[self._end:]

    def received(self, n: int) -> list[Message | Control]:
        events: list[Message | Control] = []
        try:
            self._received(n, events)
        except ProtocolViolation as e:
            e.events = events
            raise
        return events

    def _received(self, n: int, events: list[Message | Control]) -> None:
        if self._dest is not None:
            self._got += n
            if self._got < len(self._dest):
                return
            payload: bytes | memoryview = self._dest
            self._dest = None
            if len(payload) < _POOLED:  # bytes, as when it came in one read (only pooled payloads stay views)
                payload = bytes(payload)
            self._complete(payload, events)
        else:
            self._end += n
        self._parse(events)

    def _compact(self) -> None:
        rest = self._end - self._start
        self._stage[:rest] = self._stage[self._start:self._end]
        self._start, self._end = 0, rest

    def _parse(self, events: list[Message | Control]) -> None:
        stage = self._stage
        while self._dest is None:
            avail = self._end - self._start
            if avail < 2:
                break
            b0, b1 = stage[self._start], stage[self._start + 1]
            size = b1 & 0x7F
            head = 2 if size < 126 else 4 if size == 126 else 10
            if avail < head:
                break
            if size == 126:
                size = struct.unpack_from("!H", stage, self._start + 2)[0]
            elif size == 127:
                size = struct.unpack_from("!Q", stage, self._start + 2)[0]
            fin, opcode = bool(b0 & 0x80), b0 & 0x0F
            self._check(b0, b1, fin, opcode, size)
            self._start += head
            self._frame = (fin, opcode)
            here = min(size, self._end - self._start)
            if here == size and (size < _POOLED or opcode >= OP_CLOSE):  # small and complete: bytes
                payload: bytes | memoryview = bytes(stage[self._start:self._start + size])
                self._start += size
                self._complete(payload, events)
                continue
            dest = self._destination(size)
            dest[:here] = stage[self._start:self._start + here]
            self._start += here
            if here == size:
                self._complete(dest, events)
                continue
            self._dest, self._got = dest, here  # the kernel writes the rest straight into dest
        if self._start == self._end:
            self._start = self._end = 0
        elif self._start > len(stage) // 2:
            self._compact()

    def _check(self, b0: int, b1: int, fin: bool, opcode: int, size: int) -> None:
        if b0 & 0x70:
            raise ProtocolViolation(1002, "reserved bits set (no extension was negotiated)")
        if b1 & 0x80:
            raise ProtocolViolation(1002, "the server masked a frame")
        if opcode in (OP_CLOSE, OP_PING, OP_PONG):
            if not fin or size > 125:
                raise ProtocolViolation(1002, "fragmented or oversized control frame")
        elif opcode in (OP_TEXT, OP_BINARY):
            if self._message_op:
                raise ProtocolViolation(1002, "a new message began inside a fragmented one")
        elif opcode == OP_CONT:
            if not self._message_op:
                raise ProtocolViolation(1002, "continuation frame outside a fragmented message")
        else:
            raise ProtocolViolation(1002, f"unknown opcode {opcode:#x}")
        if opcode < OP_CLOSE and self._parts_size + size > self.max_size:
            raise ProtocolViolation(1009, f"message of over {self._parts_size + size} bytes; the limit is "
                                          f"{self.max_size}")

    def _destination(self, size: int) -> memoryview:
        fin, opcode = self._frame
        if fin and opcode != OP_CONT and size >= _POOLED:
            return memoryview(self.pool.get(size))[:size]
        return memoryview(bytearray(size))

    def _complete(self, payload: bytes | memoryview, events: list[Message | Control]) -> None:
        fin, opcode = self._frame
        if opcode >= OP_CLOSE:
            events.append(Control(opcode, bytes(payload)))
            return
        if opcode != OP_CONT and fin:
            events.append(_message(opcode, payload))
            return
        if opcode != OP_CONT:
            self._message_op = opcode
        self._parts.append(payload)
        self._parts_size += len(payload)
        if fin:
            data = b"".join(self._parts)
            op = self._message_op
            self._parts, self._parts_size, self._message_op = [], 0, 0
            events.append(_message(op, data))


def _message(opcode: int, payload: bytes | memoryview) -> Message:
    if opcode == OP_TEXT:
        try:
            return Message(opcode, str(payload, "utf-8"))  # type: ignore[arg-type]
        except UnicodeDecodeError:
            raise ProtocolViolation(1007, "a text message is not valid UTF-8") from None
    return Message(opcode, payload)


def frame_bytes(opcode: int, payload: bytes | bytearray | memoryview, key: bytes | None = None) -> bytes:
    """One masked, final client frame (RFC 6455 5.2-5.3) of `payload`'s bytes (any buffer: counted in bytes), with
    masking key `key` (4 bytes; default: os.urandom)."""
    payload = memoryview(payload).cast("B")
    n = len(payload)
    head = bytes([0x80 | opcode]) + (bytes([0x80 | n]) if n < 126 else
                                     b"\xfe" + struct.pack("!H", n) if n < 65536 else
                                     b"\xff" + struct.pack("!Q", n))
    key = os.urandom(4) if key is None else key
    return head + key + apply_mask(payload, key)


class MaskKeys:
    """Masking keys from a strong source of entropy (RFC 6455 5.3: os.urandom), read 4 KiB at a time: one system
    call per 1 024 frames rather than one per frame (costly on a cold CPU in a VM). One per connection."""

    SIZE = 4096

    def __init__(self) -> None:
        self._pool = b""
        self._at = self.SIZE

    def take(self) -> bytes:
        if self._at >= self.SIZE:
            self._pool, self._at = os.urandom(self.SIZE), 0
        self._at += 4
        return self._pool[self._at - 4:self._at]


def close_payload(code: int, reason: str = "") -> bytes:
    """A close frame's payload: `code`, then `reason` cut to 123 bytes of UTF-8 (never inside a character)."""
    return struct.pack("!H", code) + reason.encode()[:123].decode("utf-8", "ignore").encode()


class _Protocol(asyncio.BufferedProtocol):
    """asyncio glue: the handshake response, then every byte into FrameReader.buffer()."""

    def __init__(self, ws: WebSocket) -> None:
        self.ws = ws
        self.transport: asyncio.Transport | None = None
        self._head = bytearray()
        self._head_buf = bytearray(4096)
        self.handshake: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        self._writable = asyncio.Event()
        self._writable.set()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def get_buffer(self, sizehint: int) -> memoryview:
        if not self.handshake.done():
            return memoryview(self._head_buf)
        return self.ws.reader.buffer()

    def buffer_updated(self, nbytes: int) -> None:
        if not self.handshake.done():
            self._head += self._head_buf[:nbytes]
            end = self._head.find(b"\r\n\r\n")
            if end >= 0:
                rest = bytes(self._head[end + 4:])
                head = bytes(self._head[:end + 4])
                self.handshake.set_result(head)
                if rest and head.startswith(b"HTTP/1.1 101 "):  # frames sent with the upgrade (never an error's body)
                    self.ws.deliver(rest)
            elif len(self._head) > _MAX_HEAD:
                self.handshake.set_exception(HandshakeError(0, f"handshake response over {_MAX_HEAD} bytes"))
                self.transport.close()  # type: ignore[union-attr]
            return
        self.ws.received(nbytes)

    def eof_received(self) -> bool:
        return False  # close the transport

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.handshake.done():
            self.handshake.set_exception(ConnectionError("the server closed the connection during the handshake"))
        self._writable.set()
        self.ws.lost()

    def pause_writing(self) -> None:
        self._writable.clear()

    def resume_writing(self) -> None:
        self._writable.set()


class WebSocket:
    """An open client connection (see the module docstring). One task receives; sends may come from any task."""

    def __init__(self, max_size: int, max_queue: int, close_timeout: float) -> None:
        self.reader = FrameReader(max_size)
        self.max_queue = max(1, max_queue)
        self.close_timeout = close_timeout
        self.protocol: _Protocol | None = None
        self._messages: deque[str | bytes | memoryview] = deque()
        self._arrived: asyncio.Event = asyncio.Event()
        self._closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._paused = False
        self.rcvd: Close | None = None  # the server's close frame
        self.sent: Close | None = None  # ours
        self._violation: ProtocolViolation | None = None
        self._rcvd_first = False  # whether the server's close frame came before ours
        self._closing = False  # close() was called
        self._keys = MaskKeys()

    # -- events from the protocol

    def received(self, nbytes: int) -> None:
        try:
            events = self.reader.received(nbytes)
        except ProtocolViolation as e:
            self._handle(e.events)  # what came before the violation is delivered
            self._fail(e)
            return
        self._handle(events)

    def deliver(self, data: bytes) -> None:
        try:
            events = self.reader.feed(data)
        except ProtocolViolation as e:
            self._handle(e.events)
            self._fail(e)
            return
        self._handle(events)

    def _handle(self, events: list[Message | Control]) -> None:
        for ev in events:
            if isinstance(ev, Message):
                if self._closing:
                    continue  # after our close frame: only the server's close reply matters
                self._messages.append(ev.data)
                self._arrived.set()
            elif ev.opcode == OP_PING:
                self._write(frame_bytes(OP_PONG, ev.data, self._keys.take()))
            elif ev.opcode == OP_CLOSE:
                self._on_close(ev.data)
        if (len(self._messages) >= self.max_queue and not self._paused and not self._closing
                and self.protocol is not None):
            self._paused = True
            self.protocol.transport.pause_reading()  # type: ignore[union-attr]

    def _on_close(self, data: bytes) -> None:
        if len(data) >= 2:
            code = struct.unpack_from("!H", data)[0]
            reason = data[2:].decode("utf-8", "replace")
        else:
            code, reason = 1005, ""
        self.rcvd = Close(code, reason)
        self._rcvd_first = self.sent is None
        if self.sent is None:  # echo it (RFC 6455 5.5.1); the server then closes TCP
            self.sent = Close(1000 if code == 1005 else code, "")
            self._write(frame_bytes(OP_CLOSE, b"" if code == 1005 else close_payload(code), self._keys.take()))
        self._arrived.set()

    def _fail(self, e: ProtocolViolation) -> None:
        self._violation = e
        if self.sent is None:
            self.sent = Close(e.code, str(e)[:120])
            self._write(frame_bytes(OP_CLOSE, close_payload(e.code, str(e)), self._keys.take()))
        t = self.protocol.transport if self.protocol is not None else None
        if t is not None:
            t.close()  # after the close frame is written; a peer that stopped reading is cut off later
            asyncio.get_running_loop().call_later(self.close_timeout, t.abort)

    def lost(self) -> None:
        if not self._closed.done():
            self._closed.set_result(None)
        self._arrived.set()

    def _write(self, data: bytes) -> None:
        t = self.protocol.transport if self.protocol is not None else None
        if t is not None and not t.is_closing():
            t.write(data)

    # -- the application's side

    @property
    def transport(self) -> asyncio.Transport:
        """The asyncio transport, as websockets' ClientConnection.transport (tests drop a connection with abort())."""
        return self.protocol.transport  # type: ignore[union-attr,return-value]

    @property
    def close_code(self) -> int | None:
        """The server's close code once the connection is closed (1006: closed without a close frame), else None."""
        if not self._closed.done():
            return None
        return self.rcvd.code if self.rcvd is not None else 1006

    def _closed_error(self) -> ConnectionClosed:
        both = self.rcvd is not None and self.sent is not None
        ok = (both and self.rcvd.code in _OK_CODES and self.sent.code in _OK_CODES  # type: ignore[union-attr]
              and self._violation is None)  # as websockets decides: both close frames normal (1005: no code)
        cls = ConnectionClosedOK if ok else ConnectionClosedError
        return cls(self.rcvd, self.sent, self._rcvd_first if both else None)

    async def recv(self) -> str | bytes | memoryview:
        """The next message: str (text), bytes, or a memoryview of a pooled buffer (binary, >= 64 KiB). Raises
        websockets' ConnectionClosedOK / ConnectionClosedError once the connection closed and nothing is queued."""
        while not self._messages:
            if self.rcvd is not None or self._closed.done():
                raise self._closed_error()
            self._arrived.clear()
            await self._arrived.wait()
        data = self._messages.popleft()
        if self._paused and len(self._messages) < self.max_queue:
            self._paused = False
            if not self._closed.done():
                self.protocol.transport.resume_reading()  # type: ignore[union-attr]
        return data

    async def send(self, data: str | bytes | bytearray | memoryview) -> None:
        """One message (str: text, else binary); waits while the kernel's send buffer is full."""
        if self.sent is not None or self._closed.done():
            raise self._closed_error()
        if isinstance(data, str):
            self._write(frame_bytes(OP_TEXT, data.encode(), self._keys.take()))
        else:
            self._write(frame_bytes(OP_BINARY, data, self._keys.take()))
        await self.protocol._writable.wait()  # type: ignore[union-attr]

    async def close(self, code: int = 1000, reason: str = "") -> None:
        """Send a close frame (once), wait up to `close_timeout` s for the server's and for TCP to close."""
        if self.sent is None and not self._closed.done():
            self.sent = Close(code, reason)
            self._write(frame_bytes(OP_CLOSE, close_payload(code, reason), self._keys.take()))
        t = self.protocol.transport if self.protocol is not None else None
        self._closing = True  # messages arriving from here on are dropped; reading resumes for the server's reply
        if self._paused and t is not None and not self._closed.done():
            self._paused = False
            t.resume_reading()
        try:
            await asyncio.wait_for(asyncio.shield(self._closed), self.close_timeout)
        except asyncio.TimeoutError:  # not the builtin TimeoutError before Python 3.11
            if t is not None:
                t.abort()  # no reply, or a peer that stopped reading (close() would wait for it forever)
        finally:
            if t is not None:
                t.close()

    async def wait_closed(self) -> None:
        await asyncio.shield(self._closed)


def _request(host: str, path: str, key: str) -> bytes:
    return (f"GET {path} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\nUser-Agent: ofera-client\r\n\r\n").encode()


def accept_key(key: str) -> str:
    """The Sec-WebSocket-Accept a server answers `key` (Sec-WebSocket-Key) with (RFC 6455 4.2.2)."""
    return base64.b64encode(hashlib.sha1(key.encode() + _GUID).digest()).decode()


def check_response(head: bytes, key: str) -> None:
    """Raise HandshakeError unless `head` (status line + headers) accepts the upgrade asked with `key`."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ", 2)
    if len(parts) < 2 or not parts[0].startswith("HTTP/1.1") or not parts[1].isdigit():
        raise HandshakeError(0, f"not an HTTP/1.1 response: {lines[0][:80]!r}")
    status = int(parts[1])
    if status != 101:
        raise HandshakeError(status, f"server rejected WebSocket connection: HTTP {status}")
    headers = {}
    for line in lines[1:]:
        name, sep, value = line.partition(":")
        if sep:
            headers[name.strip().lower()] = value.strip()
    want = accept_key(key)
    if headers.get("upgrade", "").lower() != "websocket" or headers.get("sec-websocket-accept") != want:
        raise HandshakeError(101, "the server's upgrade response does not accept this WebSocket key")
    extensions = headers.get("sec-websocket-extensions")
    if extensions:
        raise HandshakeError(101, f"the server enabled extensions nobody asked for: {extensions}")


async def open_websocket(url: str, *, max_size: int, max_queue: int = 2, open_timeout: float = 60.0,
                         close_timeout: float = 10.0) -> WebSocket:
    """Connect to ws:// or wss:// `url` and complete the opening handshake (RFC 6455 4.1) within `open_timeout` s.
    Raises OSError (cannot connect), HandshakeError (no upgrade), TimeoutError."""
    parts = urlsplit(url)
    if parts.scheme not in ("ws", "wss") or not parts.hostname:
        raise ValueError(f"not a WebSocket URL: {url!r}")
    secure = parts.scheme == "wss"
    port = parts.port or (443 if secure else 80)
    path = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
    host = parts.netloc.rpartition("@")[2]
    loop = asyncio.get_running_loop()
    ws = WebSocket(max_size, max_queue, close_timeout)
    key = base64.b64encode(os.urandom(16)).decode()

    async def handshake() -> None:
        transport, protocol = await loop.create_connection(lambda: _Protocol(ws), parts.hostname, port,
                                                           ssl=ssl.create_default_context() if secure else None)
        ws.protocol = protocol
        transport.write(_request(host, path, key))
        try:
            check_response(await protocol.handshake, key)
        except BaseException:
            transport.close()
            raise

    await asyncio.wait_for(handshake(), open_timeout)
    return ws
