"""One WebSocket session: handshake, then a *source* (its bs drive an avatar) and a *viewer* (it receives
that avatar's frames). In v1 every client is both, for its own avatar; the roles are separate objects
so that later one source can fan out to many viewers (rooms) without touching either.

Backpressure, newest wins at both ends:
- Source: at most one pending bs. A bs arriving while the previous one waits is replaced (counted as
  skipped 'bs'); the pipeline runs in a thread pool, one frame at a time per source, so one session's
  compute never blocks another's I/O.
- Viewer: at most one unsent frame. A computed frame arriving while the previous one waits to be sent
  replaces it (skipped 'frame'); sending awaits the socket draining (see server.py), so a slow client
  only ever has its newest frame queued and never slows anyone else.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import secrets
import threading
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np
from ofera_protocol import (
    AvatarInfo,
    Blendshapes,
    Bye,
    Frame,
    FrameFormat,
    Hello,
    Ping,
    ProtocolError,
    ServerConnection,
    encode_frame,
    to_coords,
)
from ofera_protocol import errors as E

from .. import __version__
from .config import Settings
from .metrics import Metrics
from .pipeline import AvatarAssets, Pipeline
from .registry import AvatarRegistry

log = logging.getLogger("ofera.streaming")

T = TypeVar("T")
SendBytes = Callable[[bytes], Awaitable[None]]


class LatestSlot(Generic[T]):
    """Holds at most one item: `put` replaces what is there (returns True if it replaced something),
    `get` waits for an item and takes it. Event-loop only."""

    def __init__(self) -> None:
        self._item: T | None = None
        self._full = False
        self._event = asyncio.Event()

    def put(self, item: T) -> bool:
        replaced = self._full
        self._item, self._full = item, True
        self._event.set()
        return replaced

    async def get(self) -> T:
        while not self._full:
            self._event.clear()
            await self._event.wait()
        item, self._item, self._full = self._item, None, False
        return item  # type: ignore[return-value]


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
class PendingBs:
    bs: Blendshapes
    received_ns: int
    decode_us: int


@dataclass
class ComputedFrame:
    """One pipeline result, shared by every viewer of a source; encoded once per wire format."""

    seq: int
    t: int
    state: Any  # GaussianState in FLAME space
    timing: dict[str, int]
    received_ns: int
    _encoded: dict[tuple, bytes] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def encoded(self, key: tuple, make: Callable[[ComputedFrame], bytes]) -> tuple[bytes, bool]:
        """Bytes for wire format `key` (made once, by whoever asks first); True if made by this call."""
        with self._lock:
            data = self._encoded.get(key)
            if data is not None:
                return data, False
            data = self._encoded[key] = make(self)
            return data, True


class SessionFatal(Exception):
    """Ends the session with a fatal protocol error."""

    def __init__(self, err: ProtocolError) -> None:
        super().__init__(str(err))
        self.err = err


class Source:
    """Client role 1: its bs drive one avatar's pipeline (newest bs wins). Publishes ComputedFrames."""

    def __init__(self, pipeline: Pipeline, executor: Executor, metrics: Metrics) -> None:
        self.pipeline = pipeline
        self.executor = executor
        self.metrics = metrics
        self.slot: LatestSlot[PendingBs] = LatestSlot()
        self.subscribers: list[Callable[[ComputedFrame], None]] = []
        self.skipped = 0
        self.computed = 0

    def offer(self, pending: PendingBs) -> None:
        if self.slot.put(pending):
            self.skipped += 1
            self.metrics.skipped.labels("bs").inc()

    def _compute(self, p: PendingBs) -> ComputedFrame:
        start = time.monotonic_ns()
        state, stages = self.pipeline.run(p.bs.w)
        end = time.monotonic_ns()
        # PROTOCOL.md section 9 names, plus the finer layout/bda split of `map`.
        timing = {"decode": p.decode_us, "queue": (start - p.received_ns) // 1000, "layout": stages["layout"],
                  "bda": stages["bda"], "map": stages["layout"] + stages["bda"], "epm": stages["epm"],
                  "head": stages["head"], "deform": stages["deform"], "total": (end - p.received_ns) // 1000}
        return ComputedFrame(p.bs.seq, p.bs.t, state, timing, p.received_ns)

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            pending = await self.slot.get()
            try:
                frame = await loop.run_in_executor(self.executor, self._compute, pending)
            except Exception as exc:
                log.exception("pipeline failed on bs %d", pending.bs.seq)
                raise SessionFatal(ProtocolError(E.INTERNAL, f"the server failed computing bs {pending.bs.seq}: "
                                                 f"{type(exc).__name__}; please report it", True)) from exc
            self.computed += 1
            self.metrics.frames_computed.inc()
            self.metrics.observe_timings(frame.timing)
            for deliver in self.subscribers:
                deliver(frame)


class Viewer:
    """Client role 2: receives an avatar's frames in its own wire format (newest unsent frame wins)."""

    def __init__(self, send: SendBytes, fmt: FrameFormat, coords: str, gather: np.ndarray | None,
                 index: np.ndarray | None, key: tuple, executor: Executor, metrics: Metrics) -> None:
        self.send = send
        self.format = fmt
        self.coords = coords
        self.gather = gather  # ids (into the avatar) of the Gaussians a frame carries; None: all
        self.index = index  # sparse: the frame's wire index; None: dense
        self.key = key  # frames with equal keys have equal bytes (encoded once per key)
        self.executor = executor
        self.metrics = metrics
        self.slot: LatestSlot[ComputedFrame] = LatestSlot()
        self.sent = 0
        self.skipped = 0

    def offer(self, frame: ComputedFrame) -> None:
        if self.slot.put(frame):
            self.skipped += 1
            self.metrics.skipped.labels("frame").inc()

    def _make(self, frame: ComputedFrame) -> bytes:
        s = frame.state
        pos, rot, scale = s.position, s.rotation, s.scale
        if self.gather is not None:
            pos, rot, scale = pos[self.gather], rot[self.gather], scale[self.gather]
        pos, rot = to_coords(pos, rot, self.coords)
        msg = Frame(seq=frame.seq, t=frame.t, position=pos, rotation=rot, scale=scale, index=self.index,
                    timing=frame.timing)
        return encode_frame(msg, self.format)

    def _encode(self, frame: ComputedFrame) -> bytes:
        t0 = time.perf_counter_ns()
        data, made = frame.encoded(self.key, self._make)
        if made:
            self.metrics.stage.labels("encode").observe((time.perf_counter_ns() - t0) * 1e-9)
        return data

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            frame = await self.slot.get()
            try:
                data = await loop.run_in_executor(self.executor, self._encode, frame)
            except Exception as exc:
                log.exception("encoding frame %d failed", frame.seq)
                raise SessionFatal(ProtocolError(E.INTERNAL, f"the server failed encoding frame {frame.seq}: "
                                                 f"{type(exc).__name__}", True)) from exc
            await self.send(data)
            self.sent += 1
            self.metrics.frames_out.inc()
            self.metrics.bytes_out.inc(len(data))
            self.metrics.server_latency.observe((time.monotonic_ns() - frame.received_ns) * 1e-9)


@dataclass
class Hub:
    """What every session of one server shares."""

    settings: Settings
    registry: AvatarRegistry
    executor: Executor
    metrics: Metrics
    active: int = 0
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
        except ConnectionGone:
            pass
        finally:
            if not full:
                hub.active -= 1
                hub.sessions.pop(self.id, None)

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

        def prepare() -> tuple[AvatarAssets, Any, Any, tuple, Any]:
            # An unknown device falls back to the avatar's own BDA (PROTOCOL.md 4.1: no error).
            device_bda = reg.device_bda(hello.device) if hello.device is not None else None
            assets = reg.get(aid)
            wire = assets.wire_avatar(hello.coords, hello.max_gaussians)
            quant = assets.quant(hello.coords, hello.max_gaussians) if hello.encoding == "q13" else None
            return assets, wire, quant, assets.selection(hello.sparse, hello.max_gaussians), device_bda

        try:
            assets, wire, quant, (gather, index), device_bda = await asyncio.get_running_loop().run_in_executor(
                self.hub.executor, prepare)
        except Exception as exc:
            log.exception("loading avatar %s failed", aid)
            raise refuse(E.INTERNAL, f"the server could not load avatar {aid!r}: {type(exc).__name__}: {exc}") from exc

        welcome = self.conn.accept(self.id, AvatarInfo(id=aid, count=wire.count, sh_degree=wire.sh_degree),
                                   quant=quant, server=f"ofera/{__version__}")
        await self.t.send(welcome)
        for chunk in self.conn.avatar(wire, s.avatar_chunk_bytes):
            await self.t.send(chunk)
            self.metrics.bytes_out.inc(len(chunk))

        pipeline = assets.pipeline(hello.layout, device_bda)
        self.source = Source(pipeline, self.hub.executor, self.metrics)
        assert self.conn.format is not None
        key = (hello.encoding, hello.coords, hello.sparse, hello.max_gaussians)
        self.viewer = Viewer(self.t.send, self.conn.format, hello.coords, gather, index, key, self.hub.executor,
                             self.metrics)
        self.source.subscribers.append(self.viewer.offer)
        log.info("session %s: avatar %s, layout %s, encoding %s, coords %s%s", self.id, aid, hello.layout,
                 hello.encoding, hello.coords, f", device {hello.device}" if hello.device else "")
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
                await self._send_error(e)
                continue
            if isinstance(msg, Blendshapes):
                self.metrics.bs_in.inc()
                if not await self._allow(msg.seq):
                    continue
                decode_us = (time.monotonic_ns() - received) // 1000
                self.source.offer(PendingBs(msg, received, decode_us))
            elif isinstance(msg, Ping):
                if await self._allow(None):
                    await self.t.send(self.conn.pong(msg.t))
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
                E.RATE_LIMITED, f"more than {self.settings.bs_rate:g} bs/ping per second; the excess is dropped",
                False), seq=seq)
        return False
