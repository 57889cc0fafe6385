"""The contract between rooms and what joins them across servers (a `RoomBus`; `redis_bus.RedisBus` is the one
implementation; without `--redis` a server has no bus and its rooms are in-process).

What crosses servers is a publishing member's mapped expression (`ExpressionValues`: the avatar's expression
values, 68 FLAME values or 51 ARKit weights, with member, seq, t), never Gaussians, plus membership
(`MemberInfo`). Each server deforms every remote member once per frame for all of its local viewers, resolving the
member's avatar id from its own avatars.

Rooms (`rooms.py`) call the bus; the bus calls a `BusListener` (the rooms of this server) back, on the event loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import OferaError


class BusUnavailable(OferaError):
    """The bus could not be reached at start (the message names the URL)."""


@dataclass(frozen=True)
class MemberInfo:
    """One member of a room, as every server sees it."""

    member: str  # unique in the room across servers (welcome.member)
    avatar: str  # the avatar id it publishes (resolved by each server from its own avatars); "" if watch-only
    server: str  # id of the server the member is connected to
    publish: bool  # False: watch-only (no frames will come)


@dataclass(frozen=True)
class ExpressionValues:
    """One frame of a publishing member: what its server's EPM made of one bs."""

    room: str
    member: str
    seq: int  # the source's bs.seq
    t: int  # the source's bs.t (client clock, us)
    values: np.ndarray  # (68,) float32 FLAME values, or (51,) float32 ARKit weights (an arkit51 avatar)


class BusListener(Protocol):
    """What a bus reports to this server's rooms (called on the event loop)."""

    def remote_joined(self, room: str, info: MemberInfo) -> None: ...

    def remote_left(self, room: str, member: str, reason: str) -> None: ...

    def remote_values(self, msg: ExpressionValues) -> None: ...

    def bus_state(self, connected: bool) -> None:
        """The bus was lost (False: remote members are stale) or is back (True: the rooms heal)."""
        ...


class RoomBus(Protocol):
    """Rooms across servers. Every method is called on the event loop; none may block it."""

    server_id: str

    async def start(self, listener: BusListener) -> None:
        """Connect and start listening; raises BusUnavailable naming the URL if the bus cannot be reached."""
        ...

    async def close(self) -> None:
        """Withdraw this server's members and disconnect."""
        ...

    async def join(self, room: str, info: MemberInfo) -> None:
        """A local member joined `room`: announce it (and replay the room's remote members to the listener)."""
        ...

    async def leave(self, room: str, member: str, reason: str) -> None:
        """A local member left `room`."""
        ...

    def publish(self, msg: ExpressionValues) -> None:
        """Send a local member's frame to the other servers of its room; never blocks (dropped, and counted, while
        the bus is down)."""
        ...
