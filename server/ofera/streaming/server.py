"""Running the app under uvicorn: per-message deflate off, TCP_NODELAY and a congestion control that does not pace
(``Settings.tcp_congestion``) on every accepted WebSocket, `send` that waits for the socket to drain (so
newest-wins backpressure works), clean Ctrl-C.

Binary messages skip the websockets library's frame serialisation (which copies the payload twice: into a
BytesIO, then out of it): the protocol writes the few bytes of the WebSocket frame header, then hands the
payload itself (bytes or the frame writer's memoryview) to the transport, which copies into the kernel only
what the socket takes (and, on asyncio's selector loop, keeps a copy of what it could not take yet). The
time each write holds the event loop and the wait for the kernel to take the rest are observed as the
`send` and `drain` stages of /metrics.

`serve(settings)` blocks (the CLI); `ServerThread(settings)` runs a server in a background thread
(tests, benchmarks) and tells its port.
"""

from __future__ import annotations

import socket
import struct
import sys
import threading
import time
from typing import Any

import uvicorn
from ofera_protocol import ENDPOINT
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.protocol import State

from .config import Settings


def _tcp_socket(transport: Any) -> socket.socket | None:
    """A transport's socket if it is TCP (IPv4 or IPv6), else None."""
    sock = transport.get_extra_info("socket")
    return sock if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6) else None


def set_nodelay(transport: Any) -> None:
    """Turn Nagle's algorithm off on a TCP transport's socket (asyncio usually has already)."""
    sock = _tcp_socket(transport)
    if sock is not None:
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:  # the peer may already be gone
            pass


_TCP_CONGESTION = getattr(socket, "TCP_CONGESTION", None)  # Linux only


def set_congestion(transport: Any, choices: str) -> None:
    """Set the first congestion control of `choices` (comma-separated names) that the kernel accepts on a TCP
    transport's socket (nothing on an OS without TCP_CONGESTION)."""
    sock = _tcp_socket(transport)
    if sock is None or _TCP_CONGESTION is None:
        return
    for name in filter(None, (c.strip() for c in choices.split(","))):
        try:
            sock.setsockopt(socket.IPPROTO_TCP, _TCP_CONGESTION, name.encode())
            return
        except OSError:  # not built, not allowed for this process, or the peer is gone
            continue


def tcp_congestion(transport: Any) -> str | None:
    """A TCP transport's congestion control as the kernel reports it (None: not TCP, or not known on this OS)."""
    sock = _tcp_socket(transport)
    if sock is None or _TCP_CONGESTION is None:
        return None
    try:
        return sock.getsockopt(socket.IPPROTO_TCP, _TCP_CONGESTION, 16).split(b"\0", 1)[0].decode()
    except OSError:  # the peer may already be gone
        return None


def ws_binary_header(length: int) -> bytes:
    """RFC 6455 header of an unmasked, unfragmented binary frame (server to client) of `length` payload bytes."""
    if length < 126:
        return bytes((0x82, length))
    if length < 1 << 16:
        return struct.pack("!BBH", 0x82, 126, length)
    return struct.pack("!BBQ", 0x82, 127, length)


SMALL_MESSAGE = 16 * 1024
"""Payloads up to this size are joined to their frame header (one write, one segment); larger ones are written
after it without a copy."""


class StreamingWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's websockets (sans-I/O) protocol with TCP_NODELAY, and a send that returns only once the
    transport's buffer is back under its low-water mark: an awaited send means "handed to the kernel",
    so a session's newest-wins slot, not an ever-growing buffer, absorbs a slow client."""

    close_timeout_s = 10.0
    """Seconds a client has to answer our close frame before the connection is aborted."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.close_timeout = self.close_timeout_s

    def connection_made(self, transport: Any) -> None:
        set_nodelay(transport)
        choices = getattr(getattr(self._hub(), "settings", None), "tcp_congestion", "")
        if choices:
            set_congestion(transport, choices)
        super().connection_made(transport)

    def _hub(self) -> Any:
        """The app's Hub (``app.state.hub``: its settings and metrics), or None (another app, or not started yet)."""
        return getattr(getattr(getattr(self.config, "app", None), "state", None), "hub", None)

    def _metrics(self) -> Any:
        return getattr(self._hub(), "metrics", None)

    def _direct(self, message: Any) -> bool:
        """Whether this message can skip the library's framing: a binary message on an open, uncompressed,
        unfragmented connection with nothing else queued."""
        conn = self.conn
        return (message["type"] == "websocket.send" and message.get("bytes") is not None and self.handshake_complete
                and not self.close_sent and self.initial_response is None and not self.disconnected
                and conn.state is State.OPEN and not conn.extensions and not conn.expect_continuation_frame
                and not conn.writes)

    def write_binary(self, data: Any) -> float:
        """Write one binary message (header, then the payload without a copy); returns the seconds the writes
        held the event loop."""
        t0 = time.perf_counter()
        view = memoryview(data)
        n = view.nbytes
        head = ws_binary_header(n)
        if n <= SMALL_MESSAGE:
            self.transport.write(head + view.cast("B"))
        else:
            self.transport.write(head)
            self.transport.write(view)
        return time.perf_counter() - t0

    async def send(self, message: Any) -> None:
        if message["type"] == "websocket.send" and message.get("bytes") is not None:
            await self.writable.wait()
            metrics = self._metrics()
            if self._direct(message):
                held = self.write_binary(message["bytes"])
            else:
                t0 = time.perf_counter()
                await super().send(message)
                held = time.perf_counter() - t0
            t1 = time.perf_counter()
            await self.writable.wait()  # set again by resume_writing() or connection_lost()
            if metrics is not None:
                metrics.stage_of("send").observe(held)
                metrics.stage_of("drain").observe(time.perf_counter() - t1)
            return
        await super().send(message)
        if message["type"] == "websocket.send":
            await self.writable.wait()  # set again by resume_writing() or connection_lost()
        elif message["type"] == "websocket.close" and self.close_timer is not None:
            # uvicorn's timer calls transport.close(), which waits for the write buffer to drain: never, for a
            # client that stopped reading. Abort instead (RST): the connection and its buffer go away.
            self.close_timer.cancel()
            self.close_timer = self.loop.call_later(self.close_timeout, self.transport.abort)

    def keepalive_timeout(self) -> None:
        """No pong within ws_ping_timeout. uvicorn sends a close and closes the transport gracefully, which
        never completes while a client that stopped reading leaves the write buffer full: the session (and
        its buffered frame) would stay forever. Abort the connection: connection_lost ends the session."""
        super().keepalive_timeout()
        self.transport.abort()

    def shutdown(self) -> None:
        """Server shutdown: close open sessions with 1001 "going away" (PROTOCOL.md section 10;
        uvicorn's own choice is 1012)."""
        if self.handshake_complete and not self.close_sent and not self.transport.is_closing():
            self.stop_keepalive()
            self.queue.put_nowait({"type": "websocket.disconnect", "code": 1001})
            self.conn.send_close(1001, "server shutting down")
            self.transport.write(b"".join(self.conn.data_to_send()))
            self.close_sent = True
            self.transport.close()
            return
        super().shutdown()

    def nodelay(self) -> bool:
        """TCP_NODELAY as the kernel reports it for this connection (for tests and diagnostics)."""
        sock = self.transport.get_extra_info("socket")
        return bool(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))

    def congestion(self) -> str | None:
        """This connection's TCP congestion control as the kernel reports it (None: not known on this OS)."""
        return tcp_congestion(self.transport)


def uvicorn_config(settings: Settings, app: Any = None) -> uvicorn.Config:
    from .app import create_app

    return uvicorn.Config(
        app if app is not None else create_app(settings),
        host=settings.host,
        port=settings.port,
        ws=StreamingWebSocketProtocol,
        ws_per_message_deflate=False,
        loop=settings.event_loop,
        # Larger than our own limit so that the codec answers `message_too_large` with a message;
        # beyond this uvicorn closes with 1009 on its own.
        ws_max_size=max(2 * settings.max_message_bytes, 1 << 20),
        lifespan="on",
        log_level=settings.log_level,
        timeout_graceful_shutdown=5,
        ssl_keyfile=str(settings.ssl_keyfile) if settings.ssl_keyfile else None,
        ssl_certfile=str(settings.ssl_certfile) if settings.ssl_certfile else None,
    )


class StreamingServer(uvicorn.Server):
    """uvicorn.Server that knows its bound port and prints where to connect once it listens."""

    def __init__(self, config: uvicorn.Config, banner: bool = True) -> None:
        super().__init__(config)
        self.banner = banner
        self.port: int | None = None

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await super().startup(sockets)
        if self.servers:
            self.port = self.servers[0].sockets[0].getsockname()[1]
        if self.banner and self.started:
            for line in connect_lines(self.config.host, self.port or self.config.port, self.config.is_ssl):
                print(line, flush=True)

    def connections(self) -> list[Any]:
        return list(self.server_state.connections)


def connect_lines(host: str, port: int, tls: bool = False) -> list[str]:
    shown = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
    if ":" in shown:
        shown = f"[{shown}]"
    ws, http = ("wss", "https") if tls else ("ws", "http")
    return [
        "OFERA server ready:",
        f"  stream   {ws}://{shown}:{port}{ENDPOINT}",
        f"  preview  {http}://{shown}:{port}/",
        f"  health   {http}://{shown}:{port}/healthz",
        f"  metrics  {http}://{shown}:{port}/metrics",
        f"  avatars  {http}://{shown}:{port}/v1/avatars",
        "  Ctrl-C to stop",
    ]


def serve(settings: Settings) -> None:
    """Warm up, then run until Ctrl-C (sessions are closed with 1001, the compute pool stopped).
    Loading failures (missing avatar or EPM files...) raise before anything listens. The `cpus` setting pins the
    process first (before numba sizes its thread pool); numba's idle workers spin at most about 0.3 ms
    (``affinity.bound_spinning``)."""
    from .affinity import bound_spinning

    bound_spinning()
    if settings.cpu_set is not None:
        from .affinity import pin_process

        pinned = pin_process(settings.cpu_set)
        print(f"OFERA server: on CPUs {','.join(map(str, sorted(pinned)))}", flush=True)
    from .app import create_app, warm_up

    app = create_app(settings)
    if settings.warmup:
        warm_up(app.state.hub)
    server = StreamingServer(uvicorn_config(settings, app))
    try:
        server.run()
    except KeyboardInterrupt:  # a second Ctrl-C during shutdown
        pass
    print("OFERA server stopped.", file=sys.stderr, flush=True)
    if not server.started:
        raise SystemExit(1)


class ServerThread:
    """A server on a background thread: `with ServerThread(settings) as s: s.url ...`."""

    def __init__(self, settings: Settings, app: Any = None, banner: bool = False) -> None:
        self.settings = settings
        self.server = StreamingServer(uvicorn_config(settings, app), banner=banner)
        self.thread = threading.Thread(target=self._run, name="ofera-server", daemon=True)
        self.error: BaseException | None = None

    def _run(self) -> None:
        try:
            self.server.run()  # the settings' event loop (no signal handlers off the main thread)
        except BaseException as exc:  # noqa: BLE001 - reported by start()
            self.error = exc

    def start(self, timeout: float = 300.0) -> ServerThread:
        """Start serving; wait until it listens (warm-up included: about two minutes on a 2-core machine whose numba
        cache is empty, seconds after) or `timeout` seconds pass."""
        self.thread.start()
        deadline = threading.Event()
        for _ in range(int(timeout * 20)):
            if self.server.started or not self.thread.is_alive():
                break
            deadline.wait(0.05)
        if not self.server.started:
            self.stop()
            raise RuntimeError(f"server did not start: {self.error!r}")
        return self

    def stop(self, timeout: float = 10.0) -> None:
        self.server.should_exit = True
        self.thread.join(timeout)

    @property
    def port(self) -> int:
        assert self.server.port is not None
        return self.server.port

    @property
    def http_url(self) -> str:
        return f"{'https' if self.settings.tls else 'http'}://{self.settings.host}:{self.port}"

    @property
    def url(self) -> str:
        return f"{'wss' if self.settings.tls else 'ws'}://{self.settings.host}:{self.port}{ENDPOINT}"

    @property
    def app(self) -> Any:
        return self.server.config.app

    def __enter__(self) -> ServerThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
