"""One WebSocket session from hello to close: handshake (token, avatar, device profile, welcome, avatar
chunks), then a Source and a Viewer (roles.py) for the client's own avatar, the receive loop (bs, ping,
bye, errors), rate limiting, and fatal-error handling (error message, then close with its code)."""

from __future__ import annotations

import asyncio
import hmac
import logging
import math
import secrets
import time
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from ofera_protocol import AvatarInfo, Blendshapes, Bye, FrameFormat, Hello, Ping, ProtocolError, ServerConnection
from ofera_protocol import errors as E
from ofera_protocol.delta import DELTA_ENCODINGS
from ofera_protocol.messages import Resync

from .. import __version__
from .config import Settings
from .metrics import Metrics
from .pipeline import AvatarAssets
from .registry import AvatarRegistry
from .roles import CodecWriter, FrameEncoder, PendingBs, SessionFatal, Source, Viewer

log = logging.getLogger("ofera.streaming")

WEIGHT_LIMIT = 1000.0
"""bs weights are limited to +-WEIGHT_LIMIT before the pipeline (PROTOCOL.md 4.2: the server clamps them).
The layout adapter clamps the arkit weights it computes to [0, 1], but an arkit weight of an ovr layout is a
sum of several ovr weights: finite inputs near float32's limit (+-3.4e38) overflow there to inf - inf = NaN."""


class TokenBucket:
    """`rate` events per second with bursts of up to `burst`."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = rate, burst
        self.tokens = burst
        self.stamp = time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass
class Hub:
    """What every session of one server shares."""

    settings: Settings
    registry: AvatarRegistry
    executor: Executor
    metrics: Metrics
    active: int = 0
    warm: bool = False
    sessions: dict[str, Session] = field(default_factory=dict)


class ConnectionGone(Exception):
    """The client went away (raised by Transport.send); the session ends quietly."""


class Transport:
    """The few socket operations a session needs (implemented over FastAPI's WebSocket in app.py).
    `send` raises ConnectionGone once the client is gone; `close` never raises."""

    async def receive(self) -> bytes | str | None:  # None: the client disconnected
        raise NotImplementedError

    async def send(self, data: bytes) -> None:
        raise NotImplementedError

    async def close(self, code: int, reason: str = "") -> None:
        raise NotImplementedError


def make_writer(fmt: FrameFormat, coords: str, gather: np.ndarray | None, index: np.ndarray | None, fast: bool
                ) -> FrameEncoder:
    """The frame encoder of one wire format: numba kernels writing straight into the message buffer
    (`encode_fast`, byte-identical to the codec) when `fast`, else the codec's reference encoder."""
    if fast:
        from .encode_fast import frame_writer

        return frame_writer(fmt, coords, gather, index)
    return CodecWriter(fmt, coords, gather, index)


def make_delta_writer(fmt: FrameFormat, coords: str, gather: np.ndarray | None, movable: tuple, settings: Settings
                      ) -> FrameEncoder:
    """The DeltaEncoder of one delta session (PROTOCOL.md 7.1): numba kernels when `settings.fast`, else the numpy
    reference; candidates = the avatar's movable Gaussians (`movable` = (state rows, session ids))."""
    from ofera_protocol.delta import DeltaEncoder, DeltaTolerance

    rows, ids = movable
    tol = DeltaTolerance(settings.delta_position_mm * 1e-3, settings.delta_rotation_deg, settings.delta_log_scale)
    kernels = None
    if settings.fast:
        from .encode_fast import numba_kernels

        kernels = numba_kernels()
    return DeltaEncoder(fmt, coords, gather, np.asarray(ids, np.int64), np.asarray(rows, np.int64), kernels=kernels,
                        tolerance=tol, key_interval=settings.key_interval)


def reduced_size(asked: int | None, count: int) -> int | None:
    """How many Gaussians to stream to a client that renders at most `asked` (hello.max_gaussians): None (the
    whole avatar) when it fits, else the largest count x 2^(-k/4), k >= 1, not above `asked` (at most 16 %
    fewer than asked). Avatars cache each reduction they serve, so arbitrary sizes chosen by clients would
    grow the server's memory without bound; these sizes are at most 4 log2(count) + 1 per avatar."""
    if asked is None or asked >= count:
        return None
    k = max(1, math.floor(-4 * math.log2(asked / count)))
    while int(count * 2.0 ** (-k / 4)) > asked:
        k += 1
    return max(1, int(count * 2.0 ** (-k / 4)))


class Session:
    """Runs one connection from hello to close."""

    def __init__(self, transport: Transport, hub: Hub) -> None:
        self.t = transport
        self.hub = hub
        self.settings = hub.settings
        self.metrics = hub.metrics
        self.conn = ServerConnection(max_message_size=hub.settings.max_message_bytes)
        self.id = secrets.token_hex(8)
        self.source: Source | None = None
        self.viewer: Viewer | None = None
        self.bucket = TokenBucket(hub.settings.bs_rate, hub.settings.burst)
        self._movable: tuple | None = None
        self._last_rate_error = 0.0

    # ------------------------------------------------------------------ sending helpers

    async def _send_error(self, err: ProtocolError, seq: int | None = None) -> None:
        self.metrics.errors.labels(err.code).inc()
        await self.t.send(self.conn.error(err, seq=seq))
        if err.fatal:
            await self.t.close(err.close_code, err.code)

    # ------------------------------------------------------------------ life cycle

    async def run(self) -> None:
        hub = self.hub
        full = hub.active >= self.settings.max_sessions
        if not full:
            hub.active += 1
            hub.sessions[self.id] = self
        try:
            if full:
                raise SessionFatal(ProtocolError(E.SERVER_FULL, f"the server is at its limit of "
                                                 f"{self.settings.max_sessions} sessions; retry later", True))
            hello = await self._handshake()
            if hello is not None:
                await self._stream()
        except SessionFatal as f:
            try:
                await self._send_error(f.err)
            except ConnectionGone:
                pass
            # Its traceback holds _stream's frame, whose tasks hold it: drop it, so that reference counting
            # alone frees the session (see _stream's finally).
            f.__traceback__ = None
        except ConnectionGone as g:
            g.__traceback__ = None
        finally:
            if not full:
                hub.active -= 1
                hub.sessions.pop(self.id, None)
            self.source = self.viewer = None

    async def _receive_hello(self) -> Hello | None:
        """Wait for hello (answering ping, honouring bye); None if the client left or took too long."""
        deadline = time.monotonic() + self.settings.hello_timeout
        while True:
            try:
                data = await asyncio.wait_for(self.t.receive(), max(0.0, deadline - time.monotonic()))
            except asyncio.TimeoutError:
                await self.t.close(1008, f"no hello within {self.settings.hello_timeout:g} s")
                return None
            if data is None:
                return None
            try:
                if isinstance(data, str):
                    self.conn.receive_text(data)
                msg = self.conn.receive(data)
            except ProtocolError as e:
                raise SessionFatal(e.as_fatal()) from None
            if isinstance(msg, Hello):
                return msg
            if isinstance(msg, Ping):
                await self.t.send(self.conn.pong(msg.t))
            elif isinstance(msg, Bye):
                await self.t.close(E.CLOSE_NORMAL, "bye")
                return None

    async def _handshake(self) -> Hello | None:
        hello = await self._receive_hello()
        if hello is None:
            return None
        s, reg = self.settings, self.hub.registry

        def refuse(code: str, message: str) -> SessionFatal:
            return SessionFatal(ProtocolError(code, message, True))

        if s.token is not None:
            given = (hello.token or "").encode()
            if not hmac.compare_digest(given, s.token.encode()):
                raise refuse(E.UNAUTHORIZED, "missing or wrong token: send the server's token in hello.token")
        aid = reg.resolve(hello.avatar)
        if aid is None:
            raise refuse(E.UNKNOWN_AVATAR, f"no avatar {hello.avatar!r} on this server; available: "
                         f"{', '.join(reg.sources)} (GET /v1/avatars lists them)")

        def prepare() -> tuple[AvatarAssets, Any, Any, tuple, Any, int | None]:
            # An unknown device falls back to the avatar's own BDA (PROTOCOL.md 4.1: no error).
            device_bda = reg.device_bda(hello.device) if hello.device is not None else None
            assets = reg.get(aid)
            size = reduced_size(hello.max_gaussians, assets.count)
            wire = assets.wire_avatar(hello.coords, size)
            quant = assets.quant(hello.coords, size) if hello.encoding == "q13" else None
            sel = assets.selection(hello.sparse and not delta, size)  # a delta session is dense
            self._movable = assets.selection(True, size) if delta else None  # (state rows, session ids)
            return assets, wire, quant, sel, device_bda, size

        delta = hello.delta and hello.encoding in DELTA_ENCODINGS  # f32: welcome.delta false
        try:
            assets, wire, quant, (gather, index), device_bda, size = \
                await asyncio.get_running_loop().run_in_executor(self.hub.executor, prepare)
        except Exception as exc:
            log.exception("loading avatar %s failed", aid)
            raise refuse(E.INTERNAL, f"the server could not load avatar {aid!r}: {type(exc).__name__}: {exc}") from exc

        info = AvatarInfo(id=aid, count=wire.count, sh_degree=wire.sh_degree, expression=assets.expression)
        welcome = self.conn.accept(self.id, info,
                                   quant=quant, server=f"ofera/{__version__}")
        await self.t.send(welcome)
        for chunk in self.conn.avatar(wire, s.avatar_chunk_bytes):
            await self.t.send(chunk)
            self.metrics.bytes_out.inc(len(chunk))

        pipeline = assets.pipeline(hello.layout, device_bda, s.confidence_threshold)
        self.source = Source(pipeline, self.hub.executor, self.metrics)
        assert self.conn.format is not None
        key: tuple = (hello.encoding, hello.coords, hello.sparse, size)
        if self.conn.format.delta:  # per client: deltas are against what this client's socket was handed
            writer = make_delta_writer(self.conn.format, hello.coords, gather, self._movable, s)
            key = (*key, "delta", self.id)
        else:
            writer = make_writer(self.conn.format, hello.coords, gather, index, s.fast)
        self.viewer = Viewer(self.t.send, writer, key, self.hub.executor, self.metrics)
        self.source.subscribers.append(self.viewer.offer)
        viewer = self.viewer  # a viewer with an unsent frame already (a client not reading) stops the computing
        self.source.demand = lambda: not viewer.slot.full
        self.viewer.on_ready = self.source.wake
        log.info("session %s: avatar %s, layout %s, encoding %s, coords %s%s", self.id, aid, hello.layout,
                 hello.encoding, hello.coords, f", device {hello.device!r}" if hello.device else "")
        return hello

    async def _stream(self) -> None:
        assert self.source is not None and self.viewer is not None
        m = self.metrics
        m.sessions.labels("source").inc()
        m.sessions.labels("viewer").inc()
        tasks = [asyncio.create_task(self.source.run(), name=f"source-{self.id}"),
                 asyncio.create_task(self.viewer.run(), name=f"viewer-{self.id}"),
                 asyncio.create_task(self._receive_loop(), name=f"receive-{self.id}")]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                exc = task.exception()
                if exc is not None:
                    raise exc
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            # The source and the viewer reference each other (offer, wake): break the cycle so that their
            # buffers (MBs per session) are freed now, not at the next full garbage collection.
            self.source.subscribers.clear()
            self.source.demand = None
            self.viewer.on_ready = None
            m.sessions.labels("source").dec()
            m.sessions.labels("viewer").dec()

    async def _receive_loop(self) -> None:
        assert self.source is not None
        while True:
            data = await self.t.receive()
            if data is None:
                return
            received = time.monotonic_ns()
            if isinstance(data, str):
                try:
                    self.conn.receive_text(data)
                except ProtocolError as e:
                    raise SessionFatal(e) from None
            try:
                msg = self.conn.receive(data)
            except ProtocolError as e:
                if e.fatal:
                    raise SessionFatal(e) from None
                if await self._allow(None):  # a flood of bad messages shares the bs/ping budget
                    await self._send_error(e)
                continue
            if isinstance(msg, Blendshapes):
                self.metrics.bs_in.inc()
                if msg.conf is not None:
                    self.metrics.bs_conf.inc()
                if not await self._allow(msg.seq):
                    continue
                if not (np.abs(msg.w) <= WEIGHT_LIMIT).all():  # finite but huge: see WEIGHT_LIMIT
                    msg = replace(msg, w=np.clip(msg.w, -WEIGHT_LIMIT, WEIGHT_LIMIT))
                decode_us = (time.monotonic_ns() - received) // 1000
                self.source.offer(PendingBs(msg, received, decode_us))
            elif isinstance(msg, Ping):
                if await self._allow(None):
                    await self.t.send(self.conn.pong(msg.t))
            elif isinstance(msg, Resync):  # delta sessions: the next frame sent is a key frame
                request = getattr(self.viewer.writer if self.viewer else None, "request_key", None)
                if request is not None:
                    request()
            elif isinstance(msg, Bye):
                await self.t.close(E.CLOSE_NORMAL, "bye")
                return

    async def _allow(self, seq: int | None) -> bool:
        """Rate limit: True if the message may be processed; otherwise drop it, with one non-fatal
        `rate_limited` error per second at most."""
        if self.bucket.take():
            return True
        now = time.monotonic()
        if now - self._last_rate_error >= 1.0:
            self._last_rate_error = now
            await self._send_error(ProtocolError(
                E.RATE_LIMITED, f"more than {self.settings.bs_rate:g} messages (bs, ping or invalid ones) per "
                "second; the excess is dropped",
                False), seq=seq)
        return False
