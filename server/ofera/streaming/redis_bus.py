"""`RedisBus`: rooms across servers through Redis (`ofera serve --redis redis://HOST:PORT/DB`).

Layout in Redis (``P`` is the key prefix, ``ofera`` by default):

- ``P:room:<room>`` (pub/sub channel): msgpack maps, one per message, ``k`` its kind and ``s`` the sending server:
  ``{"k": "v", "s", "m": member, "q": seq, "t": t, "v": float32 little-endian bytes, "ts": sender wall clock ns}``,
  ``{"k": "join", "s", "m", "a": avatar, "p": publish}``, ``{"k": "leave", "s", "m", "r": reason}``.
- ``P:room:<room>:members`` (hash): member -> msgpack ``{"a": avatar, "s": server, "p": publish}``; the truth about
  who is in the room (events are only the fast path: every heartbeat reconciles the hash with what was reported).
- ``P:server:<server id>`` (string with a TTL of `ttl_s`, refreshed every `heartbeat_s`): the server is alive. A
  member whose server key is gone has left (reason ``server_lost``): a dead server's members leave the room within
  ``ttl_s + heartbeat_s`` (2.4 s by default) on every other server.
- ``P:server:<server id>:inbox`` (channel): subscribed so that the pub/sub connection is open (and its loss seen at
  once) even while this server has no room.

A server subscribes to a room's channel while it has local members there, reports only that room's remote members,
and ignores its own messages. Lost Redis: ``bus_state(False)`` (every remote member is then gone for the listener),
reconnection with exponential backoff, then this server's members re-announced, ``bus_state(True)`` and every remote
member replayed with ``remote_joined``. `publish` never waits: one pending message per member (newest wins), sent by
a background task; drops are counted by reason. Avatars never cross: every server resolves a member's avatar id in
its own avatars (PROTOCOL.md 12.5). Metrics: `ofera_bus_*` (streaming.metrics).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import re
import socket
import time
import uuid
from dataclasses import dataclass, field
from urllib.parse import urlsplit, urlunsplit

import msgpack
import numpy as np
import redis.asyncio as aioredis
from redis.asyncio.retry import Retry
from redis.backoff import NoBackoff
from redis.exceptions import RedisError

from .bus import BusListener, BusUnavailable, ExpressionValues, MemberInfo
from .metrics import Metrics

log = logging.getLogger("ofera.streaming.redis_bus")

VALUE_SIZES = (68, 51)
"""Accepted lengths of ExpressionValues.values: 68 FLAME values or 51 ARKit weights (bus.ExpressionValues)."""
_NAME = re.compile(r"[A-Za-z0-9._-]{1,64}")
_MAX_TEXT = 256  # longest avatar id, server id or reason accepted from another server
_U32 = 1 << 32
_I64 = 1 << 63

MAX_REMOTE_MEMBERS = 1024
"""Most remote members of one room reported to the listener (`RedisBus.max_remote`): the hash and the channel are
open to every server of the Redis; more are ignored (logged once while the room is full) until one leaves. Keep it
above the servers' `room_members` (the listener applies that limit itself)."""

LOST_REASON = "server_lost"  # remote_left reason: the member's server stopped heart-beating
CLOSED_REASON = "server_closed"  # leave reason for members still present when this server closes its bus


def redact(url: str) -> str:
    """The URL without its password (for messages and logs)."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    netloc = f"{parts.username or ''}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit((parts.scheme, netloc, parts.path, parts.query, parts.fragment))


def _client(url: str, timeout_s: float) -> aioredis.Redis:
    # No retries inside redis-py: a lost connection must surface here, where the bus reconnects on its own terms.
    return aioredis.from_url(url, retry=Retry(NoBackoff(), 0), socket_connect_timeout=timeout_s,
                             socket_timeout=timeout_s)


async def check_redis(url: str, timeout_s: float = 2.0) -> None:
    """Raise BusUnavailable (naming the URL) unless Redis at `url` answers a PING within `timeout_s`."""
    try:
        client = _client(url, timeout_s)
    except ValueError as exc:
        raise BusUnavailable(f"bad Redis URL {redact(url)}: {exc}") from None
    try:
        await asyncio.wait_for(client.ping(), timeout_s)
    except (RedisError, OSError, asyncio.TimeoutError) as exc:
        raise BusUnavailable(f"cannot reach Redis at {redact(url)}: {exc or type(exc).__name__}") from None
    finally:
        await client.aclose()


def _text(d: dict, key: str, name: bool = False, empty: bool = False) -> str:
    v = d.get(key)
    if not isinstance(v, str) or len(v) > _MAX_TEXT or (not v and not empty) or (name and not _NAME.fullmatch(v)):
        raise ValueError(f"bad {key!r}")
    return v


def _int(d: dict, key: str, lo: int, hi: int) -> int:
    v = d.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v < hi:
        raise ValueError(f"bad {key!r}")
    return v


def decode_message(data: bytes) -> dict:
    """One channel message, validated: a dict with ``k`` in (v, join, leave) and that kind's fields of the right
    types (values: 68 or 51 finite float32, decoded as a read-only (n,) array under ``v``). Raises ValueError."""
    try:
        d = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as exc:  # noqa: BLE001 - msgpack raises several unrelated types for garbage
        raise ValueError(f"not msgpack: {type(exc).__name__}") from None
    if not isinstance(d, dict):
        raise ValueError("not a map")
    kind = d.get("k")
    out: dict = {"k": kind, "s": _text(d, "s"), "m": _text(d, "m", name=True)}
    if kind == "v":
        raw = d.get("v")
        if not isinstance(raw, bytes) or len(raw) % 4 or len(raw) // 4 not in VALUE_SIZES:
            raise ValueError("bad 'v'")
        values = np.frombuffer(raw, "<f4")
        if not np.isfinite(values).all():
            raise ValueError("non-finite values")
        out.update(q=_int(d, "q", 0, _U32), t=_int(d, "t", -_I64, _I64), v=values, ts=_int(d, "ts", 0, _I64))
    elif kind == "join":
        out.update(_join_fields(d))
    elif kind == "leave":
        out.update(r=_text(d, "r", empty=True))
    else:
        raise ValueError("bad 'k'")
    return out


def _join_fields(d: dict) -> dict:
    p = d.get("p")
    if not isinstance(p, bool):
        raise ValueError("bad 'p'")
    return {"a": _text(d, "a", empty=not p), "p": p}


def decode_member(member: bytes, entry: bytes) -> MemberInfo:
    """A members-hash field and value (msgpack {a, s, p}) as MemberInfo; raises ValueError."""
    try:
        d = msgpack.unpackb(entry, raw=False, strict_map_key=True)
        name = member.decode("utf-8")
    except Exception as exc:  # noqa: BLE001 - msgpack raises several unrelated types for garbage
        raise ValueError(f"not msgpack: {type(exc).__name__}") from None
    if not isinstance(d, dict):
        raise ValueError("not a map")
    fields = _join_fields(d)
    return MemberInfo(member=_text({"m": name}, "m", name=True), avatar=fields["a"], server=_text(d, "s"),
                      publish=fields["p"])


@dataclass
class _Link:
    """One connection to Redis (a client with its pool, and the pub/sub connection) and the tasks using it."""

    client: aioredis.Redis
    pubsub: aioredis.client.PubSub
    tasks: list[asyncio.Task] = field(default_factory=list)
    stopped: bool = False  # set before its tasks are cancelled: a loop whose cancellation was swallowed ends anyway


class RedisBus:
    """A `RoomBus` on Redis pub/sub and hashes (see the module docstring for the layout and the timings)."""

    def __init__(self, url: str, metrics: Metrics | None = None, server_id: str | None = None, *,
                 prefix: str = "ofera", ttl_s: float = 2.0, heartbeat_s: float = 0.4, timeout_s: float = 2.0,
                 backoff_s: tuple[float, float] = (0.1, 2.0), max_remote: int = MAX_REMOTE_MEMBERS) -> None:
        if not 0 < heartbeat_s < ttl_s:
            raise ValueError(f"heartbeat_s ({heartbeat_s}) must be positive and below ttl_s ({ttl_s})")
        self.url = url
        self.metrics = metrics if metrics is not None else Metrics()
        self.server_id = server_id or f"{socket.gethostname()[:40]}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.prefix = prefix
        self.ttl_ms = max(1, round(ttl_s * 1000))
        self.heartbeat_s = heartbeat_s
        self.timeout_s = timeout_s
        self.backoff_s = backoff_s
        self.max_remote = max_remote
        self._listener: BusListener | None = None
        self._link: _Link | None = None  # None while Redis is lost (or before start / after close)
        self._reconnect: asyncio.Task | None = None
        self._closing: set[asyncio.Task] = set()  # lost links being closed
        self._closed = False
        self._local: dict[str, dict[str, MemberInfo]] = {}  # room -> this server's members there
        self._remote: dict[str, dict[str, MemberInfo]] = {}  # room -> remote members reported to the listener
        self._full: set[str] = set()  # rooms whose remote members reached max_remote (logged)
        self._events: dict[str, int] = {}  # room -> membership events seen (a reconcile racing one is skipped)
        self._pending: dict[tuple[str, str], bytes] = {}  # (room, member) -> newest packed values, not yet sent
        self._withdraw: dict[tuple[str, str], str] = {}  # (room, member) -> reason: left while Redis was lost
        self._wake = asyncio.Event()
        self._ops = asyncio.Lock()  # join and leave one at a time, in call order (a leave never overtakes its join)

    # --- keys -------------------------------------------------------------------------------------------------
    def channel(self, room: str) -> str:
        return f"{self.prefix}:room:{room}"

    def members_key(self, room: str) -> str:
        return f"{self.prefix}:room:{room}:members"

    def server_key(self, server: str) -> str:
        return f"{self.prefix}:server:{server}"

    @property
    def connected(self) -> bool:
        return self._link is not None

    # --- RoomBus ----------------------------------------------------------------------------------------------
    async def start(self, listener: BusListener) -> None:
        self._listener = listener
        try:
            async with self._ops:
                self._link = await self._connect()
        except (RedisError, OSError, asyncio.TimeoutError, ValueError) as exc:
            raise BusUnavailable(f"cannot reach Redis at {redact(self.url)}: {exc or type(exc).__name__}") from None
        self._set_connected(True)
        log.info("rooms bus: Redis at %s, server id %s", redact(self.url), self.server_id)

    async def close(self) -> None:
        self._closed = True
        reconnect, self._reconnect = self._reconnect, None
        if reconnect is not None:
            await _cancel([reconnect])
        await asyncio.gather(*self._closing, return_exceptions=True)  # lost links, being closed
        link, self._link = self._link, None
        if link is None:
            return
        link.stopped = True
        await _cancel(link.tasks)
        with contextlib.suppress(RedisError, OSError, asyncio.TimeoutError):
            pipe = link.client.pipeline(transaction=False)
            for room, members in self._local.items():
                for member in members:
                    pipe.hdel(self.members_key(room), member)
                    pipe.publish(self.channel(room), self._pack(k="leave", m=member, r=CLOSED_REASON))
            pipe.delete(self.server_key(self.server_id))
            await asyncio.wait_for(pipe.execute(), self.timeout_s)
        await _drop(link, self.timeout_s)
        self._local.clear()
        self._remote.clear()
        self.metrics.bus_connected.set(0)
        self.metrics.bus_remote_members.set(0)

    async def join(self, room: str, info: MemberInfo) -> None:
        if info.server != self.server_id:
            info = dataclasses.replace(info, server=self.server_id)
        async with self._ops:
            self._withdraw.pop((room, info.member), None)
            first = room not in self._local
            self._local.setdefault(room, {})[info.member] = info
            link = self._link
            if link is None:
                return  # announced when the bus is back
            try:
                if first:
                    await asyncio.wait_for(link.pubsub.subscribe(self.channel(room)), self.timeout_s)
                await self._announce(link, room, [info])
                if first:
                    await self._reconcile(link, room)
            except (RedisError, OSError, asyncio.TimeoutError) as exc:
                self._lost(link, exc)

    async def leave(self, room: str, member: str, reason: str) -> None:
        async with self._ops:
            members = self._local.get(room)
            if members is None or members.pop(member, None) is None:
                return
            last = not members
            if last:
                del self._local[room]
                self._forget(room)
            self._pending.pop((room, member), None)
            link = self._link
            if link is None:
                self._withdraw[(room, member)] = reason[:_MAX_TEXT]  # taken out of Redis when the bus is back
                return
            try:
                pipe = link.client.pipeline(transaction=False)
                pipe.hdel(self.members_key(room), member)
                pipe.publish(self.channel(room), self._pack(k="leave", m=member, r=reason[:_MAX_TEXT]))
                await asyncio.wait_for(pipe.execute(), self.timeout_s)
                self._count_published("leave")
                if last:
                    await asyncio.wait_for(link.pubsub.unsubscribe(self.channel(room)), self.timeout_s)
            except (RedisError, OSError, asyncio.TimeoutError) as exc:
                self._lost(link, exc)

    def publish(self, msg: ExpressionValues) -> None:
        if self._link is None:
            self.metrics.bus_dropped.labels("down").inc()
            return
        key = (msg.room, msg.member)
        if key in self._pending:
            self.metrics.bus_dropped.labels("superseded").inc()
        self._pending[key] = self._pack(k="v", m=msg.member, q=int(msg.seq), t=int(msg.t),
                                        v=np.ascontiguousarray(msg.values, "<f4").tobytes(), ts=time.time_ns())
        self._wake.set()

    # --- connection -------------------------------------------------------------------------------------------
    async def _connect(self) -> _Link:
        """Connect, subscribe (inbox and every room with local members), withdraw the members that left while
        Redis was lost, announce the others; tasks started."""
        client = _client(self.url, self.timeout_s)
        pubsub = client.pubsub()
        link = _Link(client, pubsub)
        try:
            await asyncio.wait_for(client.ping(), self.timeout_s)
            channels = [f"{self.server_key(self.server_id)}:inbox", *map(self.channel, self._local)]
            await asyncio.wait_for(pubsub.subscribe(*channels), self.timeout_s)
            await self._heartbeat_once(link)
            if self._withdraw:
                pipe = client.pipeline(transaction=False)
                for (room, member), reason in self._withdraw.items():
                    pipe.hdel(self.members_key(room), member)
                    pipe.publish(self.channel(room), self._pack(k="leave", m=member, r=reason))
                await asyncio.wait_for(pipe.execute(), self.timeout_s)
                self._count_published("leave", len(self._withdraw))
                self._withdraw.clear()
            for room, members in self._local.items():
                await self._announce(link, room, list(members.values()))
        except BaseException:
            await _drop(link, self.timeout_s)
            raise
        link.tasks = [asyncio.create_task(f(link), name=f"ofera-bus-{f.__name__}")
                      for f in (self._read_loop, self._heartbeat_loop, self._send_loop)]
        return link

    def _set_connected(self, up: bool) -> None:
        self.metrics.bus_connected.set(1 if up else 0)
        if self._listener is not None:
            self._call(self._listener.bus_state, up)

    def _lost(self, link: _Link, exc: BaseException) -> None:
        """`link` failed: remote members are gone for the listener; reconnect in the background."""
        if self._link is not link or self._closed:
            return
        self._link = None
        link.stopped = True
        log.warning("rooms bus: lost Redis at %s (%s); local members go on, reconnecting", redact(self.url),
                    exc or type(exc).__name__)
        for task in link.tasks:
            if task is not asyncio.current_task():
                task.cancel()
        closing = asyncio.get_running_loop().create_task(_drop(link, self.timeout_s))
        self._closing.add(closing)  # held until done (the loop keeps only weak references to tasks)
        closing.add_done_callback(self._closing.discard)
        self.metrics.bus_dropped.labels("down").inc(len(self._pending))
        self._pending.clear()
        for room in list(self._remote):
            self._forget(room)
        self._set_connected(False)
        self._reconnect = asyncio.get_running_loop().create_task(self._reconnect_loop(), name="ofera-bus-reconnect")

    async def _reconnect_loop(self) -> None:
        delay, most = self.backoff_s
        while not self._closed:
            await asyncio.sleep(delay)
            async with self._ops:  # no join or leave between what _connect announces and the link being up
                try:
                    link = await self._connect()
                except (RedisError, OSError, asyncio.TimeoutError) as exc:
                    log.debug("rooms bus: reconnect failed: %s", exc)
                    delay = min(most, delay * 2)
                    continue
                if self._closed:  # closed while connecting (a cancellation the connect swallowed)
                    link.stopped = True
                    await _cancel(link.tasks)
                    await _drop(link, self.timeout_s)
                    return
                self._link = link
            self.metrics.bus_reconnects.inc()
            log.warning("rooms bus: Redis at %s is back; rooms heal", redact(self.url))
            self._set_connected(True)
            for room in list(self._local):
                try:
                    await self._reconcile(link, room)
                except (RedisError, OSError, asyncio.TimeoutError) as exc:
                    self._lost(link, exc)
                    return
            return

    # --- background tasks -------------------------------------------------------------------------------------
    async def _read_loop(self, link: _Link) -> None:
        try:
            while not link.stopped:
                msg = await link.pubsub.get_message(ignore_subscribe_messages=True, timeout=1.0)
                if msg is not None and msg.get("type") == "message":
                    self._on_message(msg["channel"], msg["data"])
        except (RedisError, OSError, asyncio.TimeoutError) as exc:
            self._lost(link, exc)

    async def _heartbeat_loop(self, link: _Link) -> None:
        try:
            while not link.stopped:
                await asyncio.sleep(self.heartbeat_s)
                if await self._heartbeat_once(link):
                    log.warning("rooms bus: this server's liveness key had expired: members re-announced")
                    for room, members in list(self._local.items()):
                        await self._announce(link, room, list(members.values()))
                for room in list(self._local):
                    await self._reconcile(link, room)
        except (RedisError, OSError, asyncio.TimeoutError) as exc:
            self._lost(link, exc)

    async def _send_loop(self, link: _Link) -> None:
        try:
            while not link.stopped:
                await self._wake.wait()
                self._wake.clear()
                batch, self._pending = self._pending, {}
                if not batch:
                    continue
                if len(batch) == 1:  # the usual case at a frame's pace: one PUBLISH, no pipeline
                    [((room, _member), data)] = batch.items()
                    await link.client.publish(self.channel(room), data)  # bounded by the socket timeout
                else:
                    pipe = link.client.pipeline(transaction=False)
                    for (room, _member), data in batch.items():
                        pipe.publish(self.channel(room), data)
                    await pipe.execute()
                self._count_published("v", len(batch))
        except (RedisError, OSError, asyncio.TimeoutError) as exc:
            self._lost(link, exc)

    async def _heartbeat_once(self, link: _Link) -> bool:
        """Refresh this server's liveness key and its rooms' hashes; True if the key had expired (or never was)."""
        pipe = link.client.pipeline(transaction=False)
        pipe.set(self.server_key(self.server_id), b"1", px=self.ttl_ms, get=True)
        for room in self._local:
            pipe.pexpire(self.members_key(room), 30 * self.ttl_ms)  # a hash nobody refreshes goes away
        before = (await asyncio.wait_for(pipe.execute(), self.timeout_s))[0]
        return before is None

    async def _announce(self, link: _Link, room: str, infos: list[MemberInfo]) -> None:
        if not infos:
            return
        pipe = link.client.pipeline(transaction=False)
        pipe.hset(self.members_key(room), mapping={
            i.member: msgpack.packb({"a": i.avatar, "s": i.server, "p": i.publish}) for i in infos})
        pipe.pexpire(self.members_key(room), 30 * self.ttl_ms)
        for i in infos:
            pipe.publish(self.channel(room), self._pack(k="join", m=i.member, a=i.avatar, p=i.publish))
        await asyncio.wait_for(pipe.execute(), self.timeout_s)
        self._count_published("join", len(infos))

    async def _reconcile(self, link: _Link, room: str) -> None:
        """Make what the listener knows of `room`'s remote members what Redis says (members of dead servers
        leave, with reason server_lost, and are removed from the hash)."""
        seen = self._events.get(room, 0)
        entries = await asyncio.wait_for(link.client.hgetall(self.members_key(room)), self.timeout_s)
        present: dict[str, MemberInfo] = {}
        stale: list[str] = []
        for raw_member, raw_info in entries.items():
            try:
                info = decode_member(raw_member, raw_info)
            except ValueError as exc:
                self.metrics.bus_malformed.inc()
                log.info("rooms bus: dropped a malformed member entry in %s: %s", room, exc)
                continue
            if info.server != self.server_id:
                present[info.member] = info
            elif info.member not in self._local.get(room, {}):
                stale.append(info.member)  # this server's, left already (an entry a race left behind)
        known = self._remote.get(room, {})
        servers = sorted({i.server for i in present.values()} | {i.server for i in known.values()})
        alive: dict[str, bool] = {}
        if servers:
            pipe = link.client.pipeline(transaction=False)
            for s in servers:
                pipe.exists(self.server_key(s))
            alive = dict(zip(servers, map(bool, await asyncio.wait_for(pipe.execute(), self.timeout_s))))
        dead = [m for m, i in present.items() if not alive[i.server]]
        if dead or stale:
            await asyncio.wait_for(link.client.hdel(self.members_key(room), *dead, *stale), self.timeout_s)
        if self._link is not link or room not in self._local or self._events.get(room, 0) != seen:
            return  # the room changed while Redis was asked: the next heartbeat reconciles it
        for member in dead:
            del present[member]
        for member, info in list(known.items()):
            if present.get(member) != info:
                self._remote_left(room, member, "left" if alive.get(info.server) else LOST_REASON)
        for info in present.values():
            if self._remote.get(room, {}).get(info.member) is None:
                self._remote_joined(room, info)

    # --- incoming ---------------------------------------------------------------------------------------------
    def _on_message(self, channel: bytes, data: bytes) -> None:
        room = channel.decode("utf-8", "replace").removeprefix(f"{self.prefix}:room:")
        if room not in self._local:
            return  # the inbox, or a room this server has just left
        try:
            d = decode_message(data)
        except ValueError as exc:
            self.metrics.bus_malformed.inc()
            log.info("rooms bus: dropped a malformed message on %s: %s", room, exc)
            return
        if d["s"] == self.server_id:
            return
        kind = d["k"]
        self.metrics.bus_received.labels(kind).inc()
        if kind == "v":
            info = self._remote.get(room, {}).get(d["m"])
            if info is None or info.server != d["s"] or not info.publish:
                self.metrics.bus_dropped.labels("unknown_member").inc()
                return
            self.metrics.bus_hop.observe(max(0, time.time_ns() - d["ts"]) * 1e-9)
            self._call(self._listener.remote_values,
                       ExpressionValues(room=room, member=d["m"], seq=d["q"], t=d["t"], values=d["v"]))
        elif kind == "join":
            self._events[room] = self._events.get(room, 0) + 1
            info = MemberInfo(member=d["m"], avatar=d["a"], server=d["s"], publish=d["p"])
            known = self._remote.get(room, {}).get(info.member)
            if known != info:
                if known is not None:
                    self._remote_left(room, info.member, "replaced")
                self._remote_joined(room, info)
        else:
            self._events[room] = self._events.get(room, 0) + 1
            known = self._remote.get(room, {}).get(d["m"])
            if known is not None and known.server == d["s"]:
                self._remote_left(room, d["m"], d["r"])

    def _remote_joined(self, room: str, info: MemberInfo) -> None:
        members = self._remote.setdefault(room, {})
        if info.member not in members and len(members) >= self.max_remote:
            if room not in self._full:  # a reconcile offers it again once a member left
                self._full.add(room)
                log.warning("rooms bus: room %s has %d remote members (max_remote): member %s of server %s and "
                            "others are ignored until one leaves", room, len(members), info.member, info.server)
            return
        members[info.member] = info
        self.metrics.bus_remote_members.inc()
        self._call(self._listener.remote_joined, room, info)

    def _remote_left(self, room: str, member: str, reason: str) -> None:
        members = self._remote.get(room, {})
        if members.pop(member, None) is None:
            return
        self._full.discard(room)
        if not members:
            del self._remote[room]
        self.metrics.bus_remote_members.dec()
        self._call(self._listener.remote_left, room, member, reason)

    def _forget(self, room: str) -> None:
        """Drop `room`'s remote members without telling the listener (the room is gone here, or the bus is)."""
        self.metrics.bus_remote_members.dec(len(self._remote.pop(room, {})))
        self._events.pop(room, None)
        self._full.discard(room)

    # --- helpers ----------------------------------------------------------------------------------------------
    def _pack(self, **fields: object) -> bytes:
        return msgpack.packb({"s": self.server_id, **fields})

    def _count_published(self, kind: str, n: int = 1) -> None:
        self.metrics.bus_published.labels(kind).inc(n)

    @staticmethod
    def _call(fn, *args) -> None:  # noqa: ANN001 - a listener callback
        """Call a listener callback; its failure is logged, never the bus's."""
        try:
            fn(*args)
        except Exception:  # noqa: BLE001 - a listener bug must not stop the bus
            log.exception("rooms bus: listener %s failed", getattr(fn, "__name__", fn))


async def _cancel(tasks: list[asyncio.Task]) -> None:
    """Cancel `tasks` (but the current one) and wait until they are done, cancelling again while any runs on:
    before Python 3.12, `asyncio.wait_for` swallows a cancellation that arrives as its inner call completes."""
    current = asyncio.current_task()
    others = [t for t in tasks if t is not current]
    running = {t for t in others if not t.done()}
    while running:
        for t in running:
            t.cancel()
        _, running = await asyncio.wait(running, timeout=0.05)
    await asyncio.gather(*others, return_exceptions=True)  # their exceptions retrieved (logged by the loops)


async def _drop(link: _Link, timeout_s: float) -> None:
    """Close a link's connections within `timeout_s` each, ignoring errors (it may be dead or hung already)."""
    with contextlib.suppress(Exception):
        await asyncio.wait_for(link.pubsub.aclose(), timeout_s)
    with contextlib.suppress(Exception):
        await asyncio.wait_for(link.client.aclose(), timeout_s)


__all__ = ["RedisBus", "check_redis", "decode_message", "redact", "VALUE_SIZES", "MAX_REMOTE_MEMBERS", "LOST_REASON",
           "CLOSED_REASON"]
