"""Rooms (PROTOCOL.md 12): members who meet, each publishing member's frames watched by every other one.

- `RoomViewer`: one connection's view of a room: one slot per member it watches (newest wins per member), a
  queue of control messages (`join`, avatar chunks, `leave`; at most `room_control_bytes`, else the session ends),
  and one sender that encodes a member's frame only when it is about to be sent (through the frame's shared cache:
  once per wire format; a frame that fails is dropped) and keeps at most `room_send_bytes` of frames in flight on
  the socket (head of line: a frame that does not fit goes next once it does).
- `Room`: the members of one room (local ones, connected here, and remote ones, on other servers through the
  bus), with subscribe / unsubscribe between their Sources and the local members' RoomViewers. Each member's
  avatar is prepared once per wire format (`wire.MemberWire`) for all viewers of that format.
- `Rooms`: this server's rooms, their limits, and the `BusListener` a cross-server bus reports to. A remote
  member is a `RemoteSource` fed with its mapped expression values and deformed once per frame for all local
  viewers, only while some local viewer wants a frame.

Everything runs on the event loop; avatar preparation, deformation and encoding run in the hub's executor.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections import deque
from collections.abc import Awaitable, Callable, Hashable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from ofera_protocol import Hello, ProtocolError, ServerConnection, encode
from ofera_protocol import errors as E
from ofera_protocol.messages import Join, Leave

from ..avatar.rig import RigError
from .bus import BusListener, ExpressionValues, MemberInfo, RoomBus
from .compute_pool import offload
from .config import ROOM_CONTROL_BYTES, Settings
from .member_wire import MemberWire, prepare_member_wire, wire_key
from .metrics import Metrics
from .pipeline import AvatarAssets
from .registry import AvatarRegistry
from .roles import ComputedFrame, SendBytes, SessionFatal, Source, encode_computed
from .wire import reduced_size

log = logging.getLogger("ofera.streaming.rooms")

BYE, CLOSED, STALE = "bye", "closed", "stale"
"""`leave.reason`s of this server: the member sent bye; its connection closed; the bus was lost (12.5)."""

VALUES_LENGTH = {"flame68": 68, "arkit51": 51}
"""Length of a remote member's expression values by its avatar's `expression` (bus.ExpressionValues)."""
VALUE_LIMIT = 100.0
"""Largest |value| accepted in a remote member's expression values; a frame beyond it is dropped (counted in
`ofera_bus_malformed_total`). Ten times what real frames reach (the EPM's FLAME expression coefficients are O(1-10),
its 6D rotation entries within +-1, ARKit weights within [0, 1]), and far below values whose deformed Gaussians
could overflow a viewer's wire format (f16: +-65504)."""
WAITING_LIMIT = 1024
"""Most remote members of one room kept waiting (beyond `room_members`) for a place; more are ignored."""


class LogLimit:
    """Logs at most one record per key every `interval_s` seconds; the next one says how many were held back.
    Event-loop only."""

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0) -> None:
        self.logger, self.interval_s = logger, interval_s
        self._last: dict[Hashable, tuple[float, int]] = {}  # key -> (time of its last record, records held back)

    def __call__(self, key: Hashable, level: int, msg: str, *args: object) -> None:
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last[0] < self.interval_s:
            self._last[key] = (last[0], last[1] + 1)
            return
        if len(self._last) >= 4096:  # keys of members long gone
            self._last = {k: v for k, v in self._last.items() if now - v[0] < self.interval_s}
        self._last[key] = (now, 0)
        if last is not None and last[1]:
            msg, args = msg + " (and %d more like it since the last report)", (*args, last[1])
        self.logger.log(level, msg, *args)


limited = LogLimit(log)
"""The rooms' rate-limited log (per key: a member's bad frames, a room's ignored members)."""


def new_member_id() -> str:
    """A member id unique across servers with overwhelming probability (48 random bits)."""
    return "m-" + secrets.token_hex(6)


class MemberSlot:
    """One member as one viewer sees it: at most one unsent frame (newest wins)."""

    def __init__(self, viewer: RoomViewer, wire: MemberWire, wake: Callable[[], None]) -> None:
        self.viewer, self.wire, self.wake = viewer, wire, wake
        self.frame: ComputedFrame | None = None
        self.busy = False  # a frame of this member is on its way to the socket
        self.size = 0  # bytes of its last frame (the next one's estimate)

    @property
    def full(self) -> bool:
        return self.frame is not None

    def offer(self, frame: ComputedFrame) -> None:
        if frame.state is None and self.wire.needs_state:
            return  # computed without Gaussians while this slot was full (needs_state): keep what it holds
        if self.frame is not None:
            self.viewer.skipped += 1
            self.viewer.metrics.skipped_frame.inc()
        self.frame = frame
        self.viewer.ready()

    def take(self) -> ComputedFrame:
        frame, self.frame = self.frame, None
        assert frame is not None
        self.wake()  # its source may compute again
        return frame


class RoomViewer:
    """Frames and control messages of one connection in a room. `run` sends until the connection fails."""

    def __init__(self, send: SendBytes, executor: Executor, metrics: Metrics, limit_bytes: int,
                 control_bytes: int = ROOM_CONTROL_BYTES) -> None:
        self.send = send
        self.executor = executor
        self.metrics = metrics
        self.limit = limit_bytes
        self.control_limit = control_bytes  # the server's room_control_bytes
        self.slots: dict[str, MemberSlot] = {}
        self.joined: set[str] = set()  # members whose join this viewer was sent (or queued)
        # (member, message) for its join, avatar and rig messages; (None, message) for a leave
        self.control: deque[tuple[str | None, bytes]] = deque()
        self.control_bytes = 0  # bytes of the messages in `control`
        self._unsent: set[str] = set()  # members whose join is still in `control`
        self.inflight = 0
        self.sent = 0
        self.skipped = 0
        self._event = asyncio.Event()
        self._sending: set[asyncio.Task] = set()
        self._error: BaseException | None = None
        self._fatal: SessionFatal | None = None  # the control queue overflowed: run() ends with it
        self._task: asyncio.Task | None = None  # run()'s
        self._turn = 0

    def ready(self) -> None:
        self._event.set()

    @property
    def sends(self) -> int:
        """Frames on their way to the socket now (their bytes: `inflight`)."""
        return len(self._sending)

    # ------------------------------------------------------------------ membership

    def announce(self, member: str, messages: list[bytes]) -> None:
        """Queue `member`'s join (and avatar messages): sent before any of its frames."""
        self.joined.add(member)
        self._unsent.add(member)
        self._queue(member, messages)

    def _queue(self, owner: str | None, messages: list[bytes]) -> None:
        """Queue control messages. Beyond `control_limit` bytes queued (one announcement always may) the viewer
        fails: its session ends with a fatal `server_full` (PROTOCOL.md 12.6)."""
        if self._fatal is not None:
            return
        n = sum(len(m) for m in messages)
        if self.control and self.control_bytes + n > self.control_limit:
            self._overflow(n)
            return
        self.control.extend((owner, m) for m in messages)
        self.control_bytes += n
        self.ready()

    def _overflow(self, n: int) -> None:
        log.warning("a room viewer reads too slowly: %d bytes of join, avatar and leave messages queued, %d more "
                    "would exceed room_control_bytes (%d): its session ends", self.control_bytes, n,
                    self.control_limit)
        self.metrics.room_events.labels("overflow").inc()
        self._fatal = SessionFatal(ProtocolError(
            E.SERVER_FULL, f"this connection reads too slowly: the room's join, avatar and leave messages waiting for "
            f"it exceed the server's limit (room_control_bytes, {self.control_limit} bytes)", True))
        self.control.clear()
        self.control_bytes = 0
        self._unsent.clear()
        if self._task is not None:
            self._task.cancel()  # run() may wait on a socket that never drains: it raises _fatal instead

    def add(self, wire: MemberWire, wake: Callable[[], None]) -> MemberSlot:
        """Watch `wire.member`: its join and avatar go out first, then its frames (`slot.offer`)."""
        self.announce(wire.member, wire.messages)
        slot = self.slots[wire.member] = MemberSlot(self, wire, wake)
        return slot

    def remove(self, member: str, reason: str) -> MemberSlot | None:
        """Stop watching `member`: its unsent frame and its queued join, avatar and rig messages are dropped; a
        `leave` follows if its join was sent."""
        slot = self.slots.pop(member, None)
        if member in self.joined:
            self.joined.discard(member)
            if any(owner == member for owner, _ in self.control):
                self.control = deque(c for c in self.control if c[0] != member)
                self.control_bytes = sum(len(m) for _, m in self.control)
            if member in self._unsent:
                self._unsent.discard(member)  # the client never heard of it: no leave
            else:
                self._queue(None, [encode(Leave(member=member, reason=reason))])
        return slot

    # ------------------------------------------------------------------ sending

    def _next(self) -> tuple[int, MemberSlot] | None:
        """The next member (round robin from `_turn`) with a frame to send and none on its way, and its turn."""
        slots = list(self.slots.values())
        for i in range(len(slots)):
            turn = (self._turn + i) % len(slots)
            if slots[turn].full and not slots[turn].busy:
                return turn, slots[turn]
        return None

    def _encode(self, wire: MemberWire, frame: ComputedFrame) -> Any:
        t0 = time.perf_counter_ns()
        data, made = frame.encoded(wire.key, lambda f: encode_computed(wire.writer, f))
        if made:
            self.metrics.stage_of("encode").observe((time.perf_counter_ns() - t0) * 1e-9)
        return data

    async def _send_frame(self, slot: MemberSlot, data: Any, frame: ComputedFrame) -> None:
        n = len(data)
        try:
            await self.send(data)
            self.sent += 1
            self.metrics.frames_out.inc()
            self.metrics.bytes_out.inc(n)
            self.metrics.server_latency.observe((time.monotonic_ns() - frame.received_ns) * 1e-9)
        except Exception as exc:  # noqa: BLE001 - handed to run(), which ends the session
            self._error = exc
        finally:
            self.inflight -= n
            slot.busy = False
            self.ready()

    async def _drain(self) -> None:
        """Wait until no frame is on its way (control messages keep their order with every member's frames)."""
        while self._sending:
            await asyncio.wait(set(self._sending))
        if self._error is not None:
            raise self._error

    async def run(self) -> None:
        """Send until the connection fails (its exception) or the control queue overflows (SessionFatal)."""
        self._task = asyncio.current_task()
        try:
            while True:
                if self._fatal is not None:
                    raise self._fatal
                if self._error is not None:
                    raise self._error
                if self.control:
                    await self._drain()
                    while self.control:
                        owner, data = self.control.popleft()
                        self.control_bytes -= len(data)
                        if owner is not None:
                            self._unsent.discard(owner)  # a member's first message is its join: it goes out now
                        await self.send(data)
                        self.metrics.bytes_out.inc(len(data))
                    continue
                picked = self._next()
                if picked is None:
                    self._event.clear()
                    await self._event.wait()
                    continue
                turn, slot = picked
                if self.inflight and self.inflight + slot.size > self.limit:
                    self._turn = turn  # head of line: this member goes next, once its frame fits
                    self._event.clear()
                    await self._event.wait()
                    continue
                self._turn = turn + 1
                frame = slot.take()
                data = frame.cached(slot.wire.key)  # another viewer of this format encoded it: no thread hop
                if data is None:
                    slot.busy = True
                    try:
                        if slot.wire.needs_state:
                            data = await offload(self.executor, self._encode, slot.wire, frame)
                        else:  # params (~0.01 ms): cheaper here than a hop to the pool
                            data = self._encode(slot.wire, frame)
                    except Exception as exc:  # noqa: BLE001 - one member's bad frame: dropped, the viewer goes on
                        self.metrics.room_events.labels("bad_frame").inc()
                        limited(("encode", slot.wire.member), logging.ERROR, "encoding frame %d of member %s failed "
                                "(%s: %s): the frame is dropped", frame.seq, slot.wire.member, type(exc).__name__, exc)
                        continue
                    finally:
                        slot.busy = False
                    if self.slots.get(slot.wire.member) is not slot:
                        continue  # it left (its leave is queued) while the frame was encoded
                slot.busy = True
                slot.size = len(data)
                self.inflight += slot.size
                task = asyncio.create_task(self._send_frame(slot, data, frame))
                self._sending.add(task)
                task.add_done_callback(self._sending.discard)
        except asyncio.CancelledError:
            if self._fatal is None:
                raise
            task = asyncio.current_task()
            assert task is not None
            task.uncancel()  # our own cancel (_overflow): end with its error instead
            raise self._fatal from None
        finally:
            self._task = None
            for task in list(self._sending):
                task.cancel()



@dataclass
class Member:
    """One member of a room. Local: connected here (`viewer`, `hello`, `conn`); remote: on another server."""

    info: MemberInfo
    local: bool
    assets: AvatarAssets | None = None  # None: watch-only, or (remote) an avatar this server does not have
    source: Source | None = None
    viewer: RoomViewer | None = None
    hello: Hello | None = None
    conn: ServerConnection | None = None
    slots: list[MemberSlot] = field(default_factory=list)  # the viewers' slots of this member
    task: asyncio.Task | None = None  # remote: its source's task
    visible: bool = True  # False: a remote member whose avatar this server cannot resolve (no join is sent)

    @property
    def id(self) -> str:
        return self.info.member

    @property
    def wants(self) -> bool:
        """Some viewer of this member has room for a frame."""
        return any(not s.full for s in self.slots)

    @property
    def wants_state(self) -> bool:
        """Some viewer with room for a frame needs Gaussians (not only expression values)."""
        return any(not s.full and s.wire.needs_state for s in self.slots)


class Room:
    """The members of one room and who watches whom (subscribe / unsubscribe)."""

    def __init__(self, name: str, rooms: Rooms) -> None:
        self.name = name
        self.rooms = rooms
        self.members: dict[str, Member] = {}
        self.waiting: dict[str, MemberInfo] = {}  # remote members beyond room_members, in arrival order
        self._wires: dict[tuple, asyncio.Future[MemberWire]] = {}
        self._tasks: set[asyncio.Task] = set()
        self._unrigged: set[str] = set()  # members whose avatar has no rig (logged once)

    @property
    def local_count(self) -> int:
        return sum(m.local for m in self.members.values())

    def add(self, member: Member) -> None:
        """`member` is in the room: every local viewer learns of it; a local member watches everyone present."""
        self.members[member.id] = member
        for other in list(self.members.values()):
            if other.viewer is not None and (other is not member or (member.hello is not None and member.hello.self)):
                self.subscribe(other, member)
            if member.viewer is not None and other is not member:
                self.subscribe(member, other)

    def remove(self, member_id: str, reason: str) -> Member | None:
        """`member_id` left: its viewers get a `leave`; its own viewer and source stop."""
        member = self.members.pop(member_id, None)
        if member is None:
            return None
        for other in self.members.values():
            if other.viewer is not None:
                slot = other.viewer.remove(member_id, reason)
                if slot is not None and slot in member.slots:
                    member.slots.remove(slot)
            for slot in [s for s in other.slots if s.viewer is member.viewer]:
                other.slots.remove(slot)
                if other.source is not None:
                    other.source.subscribers.remove(slot.offer)
        if member.viewer is not None:
            member.viewer.slots.clear()
        member.slots.clear()
        if member.source is not None:
            member.source.subscribers.clear()
            member.source.demand = member.source.needs_state = member.source.on_values = None
        if member.task is not None:
            member.task.cancel()
        for key in [k for k in self._wires if k[0] == member_id]:
            del self._wires[key]
        self._unrigged.discard(member_id)
        return member

    def subscribe(self, viewer: Member, target: Member) -> None:
        """`viewer` (local) watches `target`: a watcher's join at once; a publisher's once its wire is ready."""
        assert viewer.viewer is not None
        if not target.visible or target.id in viewer.viewer.joined:
            return
        if not target.info.publish:
            viewer.viewer.announce(target.id, [encode(Join(member=target.id, publish=False))])
            return
        if target.assets is None or target.source is None:
            return  # a remote publisher still loading: add() runs again when it is ready
        task = asyncio.create_task(self._subscribe(viewer, target))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _subscribe(self, viewer: Member, target: Member) -> None:
        try:
            wire = await self._wire(target, viewer)
        except RigError as exc:  # a params viewer of an avatar without a rig: it sees a member without avatar
            if self.members.get(target.id) is target and self.members.get(viewer.id) is viewer:
                self._unrig(viewer, target, exc)
            return
        except Exception:
            log.exception("room %s: preparing member %s for member %s failed", self.name, target.id, viewer.id)
            return
        if self.members.get(target.id) is not target or self.members.get(viewer.id) is not viewer:
            return  # one of them left meanwhile
        assert viewer.viewer is not None and target.source is not None
        if target.id in viewer.viewer.joined:
            return
        slot = viewer.viewer.add(wire, target.source.wake)
        target.slots.append(slot)
        target.source.subscribers.append(slot.offer)
        target.source.wake()

    def _unrig(self, viewer: Member, target: Member, exc: RigError) -> None:
        """PROTOCOL.md 13.6: a params viewer is sent a `join` without avatar (as for a watch-only member) for a
        publishing member whose avatar has no rig, and none of its frames."""
        assert viewer.viewer is not None
        if target.id not in self._unrigged:
            self._unrigged.add(target.id)
            log.warning("room %s: member %s has no rig (%s): params viewers see it without avatar or frames",
                        self.name, target.id, exc)
        if target.id not in viewer.viewer.joined:
            viewer.viewer.announce(target.id, [encode(Join(member=target.id, publish=False))])

    def _wire(self, target: Member, viewer: Member) -> asyncio.Future[MemberWire]:
        """`target`'s avatar in `viewer`'s wire format, prepared once per format (in the executor; a failure other
        than RigError is tried again for the next viewer)."""
        assert viewer.hello is not None and viewer.conn is not None and target.assets is not None
        hello = viewer.hello
        key = (target.id, *wire_key(hello, reduced_size(hello.max_gaussians, target.assets.count)))
        fut = self._wires.get(key)
        if fut is None or (fut.done() and fut.exception() is not None and not isinstance(fut.exception(), RigError)):
            loop = asyncio.get_running_loop()
            fut = self._wires[key] = loop.run_in_executor(self.rooms.executor, prepare_member_wire, viewer.conn,
                                                          target.assets, target.id, hello, self.rooms.settings)
        return fut


class RemoteSource(Source):
    """A member on another server: its expression values (from the bus) are deformed here, once per frame for all
    local viewers, and only while one of them has room for a frame (`demand`)."""

    def _compute(self, p: PendingValues) -> ComputedFrame:  # type: ignore[override]
        start = time.monotonic_ns()
        msg = p.msg
        state = None
        stages: dict[str, int] = {}
        if self.needs_state is None or self.needs_state():
            state, stages = self.pipeline.deform_values(msg.values)
        end = time.monotonic_ns()
        timing = {"queue": (start - p.received_ns) // 1000, **stages, "total": (end - p.received_ns) // 1000}
        return ComputedFrame(msg.seq, msg.t, state, timing, p.received_ns, msg.values, self.member)

    def _failed(self, pending: Any, exc: Exception) -> None:
        """The frame is dropped (logged at most once per 10 s per member, counted as room event `bad_frame`)."""
        self.metrics.room_events.labels("bad_frame").inc()
        limited(("deform", self.member), logging.ERROR, "deforming frame %d of remote member %s failed: %s: %s",
                pending.seq, self.member, type(exc).__name__, exc)


@dataclass
class PendingValues:
    """A remote member's frame waiting to be deformed."""

    msg: ExpressionValues
    received_ns: int

    @property
    def seq(self) -> int:
        return self.msg.seq


class Rooms(BusListener):
    """This server's rooms: limits, local members joining and leaving, and what the bus reports."""

    def __init__(self, settings: Settings, registry: AvatarRegistry, executor: Executor, metrics: Metrics) -> None:
        self.settings = settings
        self.registry = registry
        self.executor = executor
        self.metrics = metrics
        self.rooms: dict[str, Room] = {}
        self.bus: RoomBus | None = None
        self.connected = True  # the bus (when there is one) is reachable
        self._tasks: set[asyncio.Task] = set()

    # ------------------------------------------------------------------ local members

    def admit(self, room: str) -> None:
        """Raise the fatal ProtocolError of a full room or a server at its room limit (PROTOCOL.md 12.6)."""
        r = self.rooms.get(room)
        if r is None and len(self.rooms) >= self.settings.max_rooms:
            self.metrics.room_events.labels("refused").inc()
            raise ProtocolError(E.TOO_MANY_ROOMS, f"this server holds its limit of {self.settings.max_rooms} rooms; "
                                "join an existing room or retry later", True)
        if r is not None and len(r.members) >= self.settings.room_members:
            self.metrics.room_events.labels("refused").inc()
            raise ProtocolError(E.ROOM_FULL, f"room {room!r} has its limit of {self.settings.room_members} members; "
                                "retry later", True)

    def join_local(self, room: str, member: Member) -> Room:
        """A local member enters `room` (limits checked again: avatars load between admit and join)."""
        self.admit(room)
        r = self.rooms.get(room)
        if r is None:
            r = self.rooms[room] = Room(room, self)
            self.metrics.rooms.set(len(self.rooms))
        src = member.source
        if src is not None:
            src.member = member.id
            src.demand = lambda: self.bus is not None or member.wants
            src.needs_state = lambda: member.wants_state
            if self.bus is not None:
                src.on_values = lambda f: self._publish(room, f)
        r.add(member)
        self.metrics.room_members.labels("local").inc()
        self.metrics.room_events.labels("join").inc()
        if self.bus is not None:
            self._spawn(self.bus.join(room, member.info), f"bus join {member.id}")
        log.info("room %s: member %s joined (%s, %d members)", room, member.id,
                 f"avatar {member.info.avatar}" if member.info.publish else "watching", len(r.members))
        return r

    def leave_local(self, room: str, member_id: str, reason: str) -> None:
        r = self.rooms.get(room)
        if r is None or r.remove(member_id, reason) is None:
            return
        self.metrics.room_members.labels("local").dec()
        self.metrics.room_events.labels("leave").inc()
        if self.bus is not None:
            self._spawn(self.bus.leave(room, member_id, reason), f"bus leave {member_id}")
        log.info("room %s: member %s left (%s)", room, member_id, reason)
        self._close_if_empty(r)
        self._admit_waiting(r)

    def _close_if_empty(self, r: Room) -> None:
        if r.local_count == 0:  # remote members only: this server no longer takes part
            for m in list(r.members.values()):
                self._drop_remote(r, m.id, CLOSED)
            self.rooms.pop(r.name, None)
            self.metrics.rooms.set(len(self.rooms))

    def _publish(self, room: str, frame: ComputedFrame) -> None:
        assert self.bus is not None and frame.member is not None and frame.values is not None
        self.bus.publish(ExpressionValues(room, frame.member, frame.seq, frame.t, frame.values))

    def _spawn(self, coro: Awaitable[None], what: str) -> None:
        async def guarded() -> None:
            try:
                await coro
            except Exception as exc:  # noqa: BLE001 - the bus reports its own state; this server goes on
                log.warning("%s failed: %s: %s", what, type(exc).__name__, exc)

        task = asyncio.create_task(guarded())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ------------------------------------------------------------------ BusListener

    def remote_joined(self, room: str, info: MemberInfo) -> None:
        r = self.rooms.get(room)
        if r is None:
            return
        known = r.members.get(info.member)
        if known is not None:
            if known.local or known.info == info:
                return
            self._drop_remote(r, info.member, CLOSED)
        elif len(r.members) >= self.settings.room_members:
            self._wait(r, info)
            return
        r.waiting.pop(info.member, None)
        member = Member(info=info, local=False)
        self.metrics.room_members.labels("remote").inc()
        if not info.publish:
            r.add(member)
            return
        aid = self.registry.resolve(info.avatar)
        if aid is None:
            log.warning("room %s: remote member %s publishes avatar %r, which this server does not have: its viewers "
                        "here see nothing of it", room, info.member, info.avatar)
            self.metrics.room_unresolved.inc()
            member.visible = False
            r.members[member.id] = member
            return
        r.members[member.id] = member  # counted now; visible once its avatar is loaded
        self._spawn(self._load_remote(r, member, aid), f"loading avatar {aid} of remote member {info.member}")

    async def _load_remote(self, r: Room, member: Member, aid: str) -> None:
        def load() -> tuple[AvatarAssets, Any]:
            assets = self.registry.get(aid)
            return assets, assets.pipeline("arkit52")  # only deform_values is used: the layout does not matter

        try:
            assets, pipeline = await asyncio.get_running_loop().run_in_executor(self.executor, load)
        except Exception as exc:  # noqa: BLE001 - a broken avatar file: that member stays invisible here
            log.error("room %s: loading avatar %r of remote member %s failed (%s: %s): its viewers here see nothing "
                      "of it", r.name, aid, member.id, type(exc).__name__, exc)
            self.metrics.room_unresolved.inc()
            member.visible = False
            return
        if r.members.get(member.id) is not member or self.rooms.get(r.name) is not r:
            return
        src = RemoteSource(pipeline, self.executor, self.metrics)
        src.member = member.id
        src.demand = lambda: member.wants
        src.needs_state = lambda: member.wants_state
        member.assets, member.source = assets, src
        member.task = asyncio.create_task(src.run(), name=f"remote-{member.id}")
        r.add(member)

    def _wait(self, r: Room, info: MemberInfo) -> None:
        """A remote member beyond `room_members` (12.6): it waits, invisible here, until a member leaves (at most
        WAITING_LIMIT per room; more are ignored). Counted as room event `over_limit`."""
        if info.member not in r.waiting:
            self.metrics.room_events.labels("over_limit").inc()
            limited(("over_limit", r.name), logging.WARNING, "room %s has its limit of %d members: remote member %s "
                    "is not shown here until a member leaves", r.name, self.settings.room_members, info.member)
            if len(r.waiting) >= WAITING_LIMIT:
                return
        r.waiting[info.member] = info

    def _admit_waiting(self, r: Room) -> None:
        """Remote members waiting for a place in `r` take the places free now, in arrival order."""
        while r.waiting and len(r.members) < self.settings.room_members and self.rooms.get(r.name) is r:
            self.remote_joined(r.name, r.waiting.pop(next(iter(r.waiting))))

    def remote_left(self, room: str, member: str, reason: str) -> None:
        r = self.rooms.get(room)
        if r is not None:
            r.waiting.pop(member, None)
            self._drop_remote(r, member, reason)
            self._admit_waiting(r)

    def _drop_remote(self, r: Room, member: str, reason: str) -> None:
        m = r.members.get(member)
        if m is None or m.local:
            return
        r.remove(member, reason)
        self.metrics.room_members.labels("remote").dec()

    def remote_values(self, msg: ExpressionValues) -> None:
        """A remote member's frame, deformed here if its values fit its avatar (VALUES_LENGTH, VALUE_LIMIT); else
        dropped and counted in `ofera_bus_malformed_total`."""
        r = self.rooms.get(msg.room)
        m = r.members.get(msg.member) if r is not None else None
        if m is None or m.local or m.source is None or m.assets is None:
            return
        v = msg.values
        length = VALUES_LENGTH.get(m.assets.expression)
        if v.shape != (length,) or not bool((np.abs(v) <= VALUE_LIMIT).all()):
            self.metrics.bus_malformed.inc()
            limited(("values", msg.member), logging.WARNING, "room %s: dropped frame %d of remote member %s: %s "
                    "values (its %s avatar takes %s, each within +-%g)", msg.room, msg.seq, msg.member, v.shape,
                    m.assets.expression, length, VALUE_LIMIT)
            return
        m.source.offer(PendingValues(msg, time.monotonic_ns()))

    def bus_state(self, connected: bool) -> None:
        """Lost: every remote member leaves with reason `stale`; back: the bus replays them (`remote_joined`)."""
        self.connected = connected
        if connected:
            log.info("rooms: the bus is back; remote members rejoin")
            return
        log.warning("rooms: the bus is lost; remote members are stale")
        for r in list(self.rooms.values()):
            r.waiting.clear()  # the bus replays them when it is back

            for m in [m for m in r.members.values() if not m.local]:
                self._drop_remote(r, m.id, STALE)
                self.metrics.room_events.labels("stale").inc()
