"""One WebSocket session from hello to close, driving the sans-I/O `core.SessionCore` over a Transport: it feeds
the core what the socket receives and carries out the actions the core returns (send, close, compute, key frame).

- A v1 session (no `hello.room`): the handshake loads the avatar (device profile, reduced size, wire format),
  sends welcome and the avatar chunks, then runs a Source and a Viewer (roles.py) for the client's own avatar.
- A room session (`hello.room`, PROTOCOL.md 12): the client becomes a member of a room (rooms.py): its Source
  (if it publishes) is watched by the other members, its RoomViewer watches them.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any

from ofera_protocol import AvatarInfo, Hello, ProtocolError
from ofera_protocol import errors as E
from ofera_protocol.delta import DELTA_ENCODINGS

from .. import __version__
from .bus import MemberInfo, RoomBus
from .config import Settings
from .core import Action, Close, Compute, Count, KeyFrame, SessionCore, Start
from .core import Send as SendAction
from .direct import direct_writer
from .member_wire import PARAMS, params_parts, params_rig_size
from .metrics import Metrics
from .pipeline import AvatarAssets, Pipeline
from .registry import AvatarRegistry
from .roles import PendingBs, SessionFatal, Source, Viewer
from .rooms import BYE, CLOSED, Member, Rooms, RoomViewer, new_member_id
from .wire import make_delta_writer, make_writer, reduced_size

__all__ = ["ConnectionGone", "Hub", "Session", "Transport", "make_delta_writer", "make_writer", "reduced_size"]

log = logging.getLogger("ofera.streaming")


@dataclass
class Hub:
    """What every session of one server shares. `bus` is None without Redis (rooms are then in-process)."""

    settings: Settings
    registry: AvatarRegistry
    executor: Executor
    metrics: Metrics
    active: int = 0
    warm: bool = False
    sessions: dict[str, Session] = field(default_factory=dict)
    rooms: Rooms | None = None
    bus: RoomBus | None = None

    def __post_init__(self) -> None:
        if self.rooms is None:
            self.rooms = Rooms(self.settings, self.registry, self.executor, self.metrics)


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


def _refuse(code: str, message: str) -> SessionFatal:
    return SessionFatal(ProtocolError(code, message, True))


class Session:
    """Runs one connection from hello to close."""

    def __init__(self, transport: Transport, hub: Hub) -> None:
        self.t = transport
        self.hub = hub
        self.settings = hub.settings
        self.metrics = hub.metrics
        self.core = SessionCore(hub.settings, time.monotonic_ns())
        self.conn = self.core.conn
        self.id = secrets.token_hex(8)
        self.source: Source | None = None
        self.viewer: Viewer | RoomViewer | None = None
        self.close_reason: str | None = None  # set by a Close action ("bye": the client said bye)
        # Called with the reason before the transport is closed (a room member leaves its room first: closing
        # waits for a client that stopped reading, and the others must not wait for it to be told).
        self.before_close: Any = None
        self._movable: tuple | None = None

    # ------------------------------------------------------------------ actions

    async def _do(self, actions: list[Action]) -> bool:
        """Carry out the core's actions in order; True once the connection is closed."""
        for a in actions:
            if isinstance(a, SendAction):
                if a.error is not None:
                    self.metrics.errors.labels(a.error).inc()
                await self.t.send(a.data)
            elif isinstance(a, Close):
                self.close_reason = a.reason
                if self.before_close is not None:
                    self.before_close(a.reason)
                await self.t.close(a.code, a.reason)
                return True
            elif isinstance(a, Compute):
                if self.source is not None:
                    self.source.offer(PendingBs(a.bs, a.received_ns, (time.monotonic_ns() - a.received_ns) // 1000))
            elif isinstance(a, Count):  # after the loop's next steps (a bs's source hands it to the pool first)
                asyncio.get_running_loop().call_soon(getattr(self.metrics, a.metric).inc)
            elif isinstance(a, KeyFrame):
                request = getattr(getattr(self.viewer, "writer", None), "request_key", None)
                if request is not None:
                    request()
        return False

    # ------------------------------------------------------------------ life cycle

    async def run(self) -> None:
        hub = self.hub
        full = hub.active >= self.settings.max_sessions
        if not full:
            hub.active += 1
            hub.sessions[self.id] = self
        try:
            if full:
                raise _refuse(E.SERVER_FULL, f"the server is at its limit of {self.settings.max_sessions} sessions; "
                              "retry later")
            hello = await self._receive_hello()
            if hello is None:
                pass
            elif hello.room is None:
                await self._handshake(hello)
                await self._stream()
            else:
                await self._room(hello)
        except SessionFatal as f:
            try:
                await self._do(self.core.fail(f.err))
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
        """Feed the core until it accepts a hello (answering ping, honouring bye); None if the client left or
        took too long."""
        while True:
            wait = max(0.0, (self.core.hello_deadline_ns - time.monotonic_ns()) * 1e-9)
            try:
                data = await asyncio.wait_for(self.t.receive(), wait)
            except asyncio.TimeoutError:
                if await self._do(self.core.tick(max(time.monotonic_ns(), self.core.hello_deadline_ns))):
                    return None
                continue
            if data is None:
                return None
            for action in self.core.receive(data, time.monotonic_ns()):
                if isinstance(action, Start):
                    return action.hello
                if await self._do([action]):
                    return None

    async def _load(self, hello: Hello, prepare: Any) -> Any:
        try:
            return await asyncio.get_running_loop().run_in_executor(self.hub.executor, prepare)
        except SessionFatal:
            raise
        except Exception as exc:
            log.exception("loading avatar %s failed", hello.avatar)
            raise _refuse(E.INTERNAL, f"the server could not load avatar {hello.avatar!r}: {type(exc).__name__}: "
                          f"{exc}") from exc

    def _resolve(self, hello: Hello) -> str:
        reg = self.hub.registry
        aid = reg.resolve(hello.avatar)
        if aid is None:
            raise _refuse(E.UNKNOWN_AVATAR, f"no avatar {hello.avatar!r} on this server; available: "
                          f"{', '.join(reg.sources)} (GET /v1/avatars lists them)")
        return aid

    def _pipeline(self, hello: Hello, assets: AvatarAssets, device_bda: Any) -> Pipeline:
        return assets.pipeline(hello.layout, device_bda, self.settings.confidence_threshold)

    async def _handshake(self, hello: Hello) -> None:
        s, reg = self.settings, self.hub.registry
        aid = self._resolve(hello)
        delta = hello.delta and hello.encoding in DELTA_ENCODINGS  # f32: welcome.delta false

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

        assets, wire, quant, (gather, index), device_bda, size = await self._load(hello, prepare)
        rig_bytes = None
        if hello.encoding == PARAMS:  # refused (no rig: an ARKit-driven avatar) before anything is sent
            rig_bytes = await self._load(hello, lambda: params_rig_size(assets, hello.max_gaussians))
        info = AvatarInfo(id=aid, count=wire.count, sh_degree=wire.sh_degree, expression=assets.expression)
        await self.t.send(self.conn.accept(self.id, info, quant=quant, server=f"ofera/{__version__}",
                                           rig_bytes=rig_bytes))
        for chunk in self.conn.avatar(wire, s.avatar_chunk_bytes):
            await self.t.send(chunk)
            self.metrics.bytes_out.inc(len(chunk))

        self.source = Source(self._pipeline(hello, assets, device_bda), self.hub.executor, self.metrics)
        assert self.conn.format is not None
        key: tuple = (hello.encoding, hello.coords, hello.sparse, size)
        if self.conn.format.delta:  # per client: deltas are against what this client's socket was handed
            writer = make_delta_writer(self.conn.format, hello.coords, gather, self._movable, s)
            key = (*key, "delta", self.id)
        elif hello.encoding == PARAMS:
            writer, rig = params_parts(self.conn, assets, hello, None, s.avatar_chunk_bytes)
            for data in rig:
                await self.t.send(data)
            self.source.needs_state = lambda: False  # params frames carry values: the client deforms
        else:
            writer = make_writer(self.conn.format, hello.coords, gather, index, s.fast)
        self.viewer = Viewer(self.t.send, writer, key, self.hub.executor, self.metrics)
        self.source.subscribers.append(self.viewer.offer)
        if hello.encoding != PARAMS:
            # The deformation writes the frames where it can (direct.py: no state, no encoding pass); a frame with a
            # state (a delta session's key frames, any frame elsewhere) is encoded in the compute thread, a delta
            # format included: this source computes only while its one viewer's slot is empty (demand, below), so
            # every frame it computes is handed to this socket (a delta frame is never replaced unsent).
            self.source.direct = direct_writer(key, writer, self.source.pipeline)
            self.source.eager.append((key, self.viewer.make))
        viewer = self.viewer  # a viewer with an unsent frame already (a client not reading) stops the computing
        self.source.demand = lambda: not viewer.slot.full
        hub = self.hub

        def alone() -> bool:  # the only session on this server
            return hub.active == 1

        if s.compute_in_loop == "alone":
            self.source.in_loop = alone
        self.source.alone = alone  # (its frame's deferred work waits for its client: roles)
        self.viewer.on_ready = self.source.wake
        log.info("session %s: avatar %s, layout %s, encoding %s, coords %s%s", self.id, aid, hello.layout,
                 hello.encoding, hello.coords, f", device {hello.device!r}" if hello.device else "")

    async def _stream(self) -> None:
        assert self.source is not None and isinstance(self.viewer, Viewer)
        m = self.metrics
        m.sessions.labels("source").inc()
        m.sessions.labels("viewer").inc()
        try:
            await self._run_tasks([self.source.run(), self.viewer.run(), self._receive_loop()])
        finally:
            # The source and the viewer reference each other (offer, wake): break the cycle so that their
            # buffers (MBs per session) are freed now, not at the next full garbage collection.
            self.source.subscribers.clear()
            self.source.eager.clear()
            self.source.direct = None
            self.source.demand = None
            self.source.in_loop = None
            self.source.alone = None
            self.viewer.on_ready = None
            m.sessions.labels("source").dec()
            m.sessions.labels("viewer").dec()

    async def _run_tasks(self, coros: list[Any]) -> None:
        """Run the session's tasks until one ends; re-raise what it raised; cancel the others."""
        tasks = [asyncio.create_task(c, name=f"{getattr(c, '__name__', 'task')}-{self.id}") for c in coros]
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

    async def _receive_loop(self) -> None:
        while True:
            data = await self.t.receive()
            if data is None:
                return
            if await self._do(self.core.receive(data, time.monotonic_ns())):
                return

    # ------------------------------------------------------------------ rooms

    async def _room(self, hello: Hello) -> None:
        """A room member from welcome to leave (PROTOCOL.md 12)."""
        s, hub, reg = self.settings, self.hub, self.hub.registry
        rooms = hub.rooms
        assert rooms is not None and hello.room is not None
        try:
            rooms.admit(hello.room)
        except ProtocolError as e:
            raise SessionFatal(e) from None
        member_id = new_member_id()
        assets: AvatarAssets | None = None
        info: AvatarInfo | None = None
        if hello.publish:
            aid = self._resolve(hello)

            def prepare() -> tuple[AvatarAssets, Any]:
                device_bda = reg.device_bda(hello.device) if hello.device is not None else None
                return reg.get(aid), device_bda

            assets, device_bda = await self._load(hello, prepare)
            count = reduced_size(hello.max_gaussians, assets.count) or assets.count  # reduced as in v1
            info = AvatarInfo(id=aid, count=count, sh_degree=assets.sh_degree, expression=assets.expression)
            self.source = Source(self._pipeline(hello, assets, device_bda), hub.executor, self.metrics)
        await self.t.send(self.conn.accept(self.id, info, server=f"ofera/{__version__}", member=member_id))
        viewer = self.viewer = RoomViewer(self.t.send, hub.executor, self.metrics, s.room_send_bytes,
                                          s.room_control_bytes)
        server_id = hub.bus.server_id if hub.bus is not None else ""
        member = Member(info=MemberInfo(member_id, info.id if info else "", server_id, hello.publish), local=True,
                        assets=assets, source=self.source, viewer=viewer, hello=hello, conn=self.conn)
        try:
            rooms.join_local(hello.room, member)
        except ProtocolError as e:
            raise SessionFatal(e) from None
        m = self.metrics
        roles = (("source",) if self.source is not None else ()) + ("viewer",)
        for role in roles:
            m.sessions.labels(role).inc()
        self.before_close = lambda reason: rooms.leave_local(hello.room, member_id, BYE if reason == "bye" else CLOSED)
        try:
            coros = [viewer.run(), self._receive_loop()]
            if self.source is not None:
                coros.append(self.source.run())
            await self._run_tasks(coros)
        finally:
            rooms.leave_local(hello.room, member_id, BYE if self.close_reason == "bye" else CLOSED)
            for role in roles:
                m.sessions.labels(role).dec()
