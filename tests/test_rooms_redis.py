"""Rooms across two servers joined by a real redis-server (PROTOCOL.md 12.5): two publishers and a watcher spread
over servers a and b see each other's frames with the right `member`, bit for bit (f32) what the offline pipeline
computes; a leaver's `leave` reaches the others within 3 s; Redis killed: local members go on, remote ones leave
as `stale`; Redis restarted: the room heals (new `join`, frames again) without clients reconnecting."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator

import numpy as np
import pytest
from ofera.client import connect, watch
from ofera.streaming import offline_pipeline
from ofera.streaming.server import ServerThread
from ofera_protocol import Frame, Join, Leave
from redis_support import RedisServer, running_redis
from test_server_support import SMALL, metric, settings

ROOM = "redis-lab"
LEAVE_WITHIN_S = 3.0


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    with running_redis() as server:
        yield server


@pytest.fixture(scope="module")
def servers(redis_server: RedisServer) -> Iterator[tuple[ServerThread, ServerThread]]:
    """Servers a and b (separate apps, one process) attached to the same Redis."""
    a = ServerThread(settings(redis_url=redis_server.url)).start()
    try:
        b = ServerThread(settings(redis_url=redis_server.url)).start()
    except BaseException:
        a.stop()
        raise
    try:
        yield a, b
    finally:
        b.stop()
        a.stop()


class Peer:
    """A room member on `ofera.client` whose messages a background task takes: joins, leaves and frames by member."""

    def __init__(self, url: str, publish: bool) -> None:
        self.url, self.publish = url, publish
        self.events: list[tuple] = []  # ("join", member, time) / ("leave", member, reason, time)
        self.frames: dict[str, dict[int, Frame]] = {}  # member -> seq -> frame
        self.task: asyncio.Task | None = None
        self.seq = 0

    async def open(self) -> Peer:
        if self.publish:
            self.client = await connect(self.url, avatar=SMALL, room=ROOM, max_size=2**26)
        else:
            self.client = await watch(self.url, ROOM, max_size=2**26)
        assert self.client.room == ROOM and self.client.member
        self.member = self.client.member
        self.task = asyncio.create_task(self._pump())
        return self

    async def _pump(self) -> None:
        while True:
            msg = await self.client.recv()
            if isinstance(msg, Join):
                self.events.append(("join", msg.member, time.monotonic()))
            elif isinstance(msg, Leave):
                self.events.append(("leave", msg.member, msg.reason, time.monotonic()))
            elif isinstance(msg, Frame) and msg.member is not None:
                self.frames.setdefault(msg.member, {})[msg.seq] = msg

    @property
    def formats(self) -> dict:
        """Members whose avatar is complete (their frames can be decoded)."""
        return self.client.conn.formats

    def present(self) -> set[str]:
        """Members announced and not left since (joins minus leaves, in order)."""
        held: set[str] = set()
        for e in self.events:
            (held.add if e[0] == "join" else held.discard)(e[1])
        return held

    async def send(self, w: np.ndarray) -> int:
        """Publish `w` as the next bs; its seq."""
        self.seq += 1
        await self.client.send_bs(w, seq=self.seq)
        return self.seq

    async def close(self) -> None:
        if self.task is not None:
            self.task.cancel()
            await asyncio.gather(self.task, return_exceptions=True)
        await self.client.close()


async def until(pred, timeout: float = 20.0, what: str = "") -> float:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        await asyncio.sleep(0.02)
    return time.monotonic() - t0


def weights(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, 52).astype(np.float32)


def assert_offline(frame: Frame, w: np.ndarray) -> None:
    state, _ = offline_pipeline(SMALL, "arkit52", w, settings=settings())
    assert frame.index is None and frame.n == state.count
    assert frame.position.tobytes() == state.position.tobytes()
    assert frame.rotation.tobytes() == state.rotation.tobytes()
    assert frame.scale.tobytes() == state.scale.tobytes()


async def exchange(sender: Peer, viewers: list[Peer], w: np.ndarray, tries: int = 5) -> None:
    """`sender` publishes `w` (again, with the next seq, while a viewer still being subscribed to it after a join
    missed it); every viewer gets one such frame, with sender's member id, equal to the offline pipeline."""
    for _ in range(tries):
        sent = await sender.send(w)
        try:
            await until(lambda sent=sent: all(sent in v.frames.get(sender.member, {}) for v in viewers), 4.0)
        except AssertionError:
            continue
        for v in viewers:
            f = v.frames[sender.member][sent]
            assert f.member == sender.member
            assert_offline(f, w)
        return
    raise AssertionError(f"no frame of {sender.member} reached {[v.member for v in viewers]} in {tries} tries")


def test_two_publishers_and_a_watcher_across_two_servers(servers, redis_server: RedisServer) -> None:
    a, b = servers

    async def main() -> None:
        p1 = await Peer(a.url, publish=True).open()  # on a
        p2 = await Peer(b.url, publish=True).open()  # on b
        w = await Peer(b.url, publish=False).open()  # on b, watching
        everyone = {p1.member, p2.member, w.member}
        assert len(everyone) == 3
        for peer in (p1, p2, w):
            await until(lambda peer=peer: peer.present() == everyone - {peer.member}, what=f"joins at {peer.member}")
            await until(lambda peer=peer: all(m in peer.formats for m in (p1.member, p2.member)
                                              if m != peer.member), what=f"avatars at {peer.member}")

        await exchange(p1, [p2, w], weights(1))  # across Redis (a -> b)
        await exchange(p2, [p1, w], weights(2))  # b -> a across Redis, b -> b locally
        assert p1.member not in p1.frames and p2.member not in p2.frames  # no `self`: nobody sees itself
        assert metric(a, "ofera_bus_connected") == 1 and metric(b, "ofera_bus_remote_members") >= 1

        # Redis dies: each server's local members go on, remote ones leave as `stale`.
        redis_server.kill()
        await until(lambda: ("leave", p1.member, "stale") in [e[:3] for e in w.events], what="stale at w")
        await until(lambda: p2.member not in p1.present(), what="stale at p1")
        assert p2.member in w.present()
        await exchange(p2, [w], weights(3))  # b -> b without Redis
        await p1.send(weights(4))
        assert metric(a, "ofera_bus_connected") == 0

        # Redis is back (empty): the servers re-announce their members; the room heals, nobody reconnects.
        redis_server.start()
        await until(lambda: w.present() == {p1.member, p2.member} and p1.present() == {p2.member, w.member},
                    what="the room healed")
        await until(lambda: p1.member in w.formats and p1.member in p2.formats, what="p1's avatar again")
        await exchange(p1, [p2, w], weights(5))
        await exchange(p2, [p1, w], weights(6))
        assert metric(a, "ofera_bus_reconnects_total") >= 1 and metric(b, "ofera_bus_connected") == 1

        # A leaver's leave reaches the others, on both servers, within 3 s.
        t0 = time.monotonic()
        await p1.close()
        for peer in (p2, w):
            await until(lambda peer=peer: p1.member not in peer.present(), LEAVE_WITHIN_S, f"leave at {peer.member}")
        assert time.monotonic() - t0 < LEAVE_WITHIN_S
        assert [e[2] for e in w.events if e[0] == "leave" and e[1] == p1.member][-1] == "bye"
        await w.close()
        await p2.close()

    asyncio.run(main())


def test_a_v1_client_on_a_redis_server_sees_no_change(servers) -> None:
    a, _ = servers

    async def main() -> None:
        w = weights(9)
        async with await connect(a.url, avatar=SMALL) as c:
            assert c.welcome.room is None
            await c.send_bs(w)
            frame = await c.recv_frame(timeout=30)
        assert frame.member is None
        assert_offline(frame, w)

    asyncio.run(main())


def test_a_server_shutting_down_takes_its_members_out(servers, redis_server: RedisServer) -> None:
    a, _ = servers
    c = ServerThread(settings(redis_url=redis_server.url)).start()

    async def main() -> tuple[float, str]:
        watcher = await Peer(a.url, publish=False).open()
        leaving = await Peer(c.url, publish=True).open()
        await until(lambda: leaving.member in watcher.present(), what="the join of c's member at a")
        t0 = time.monotonic()
        await asyncio.get_running_loop().run_in_executor(None, c.stop)
        await until(lambda: leaving.member not in watcher.present(), LEAVE_WITHIN_S, "the leave at a")
        took = time.monotonic() - t0
        reason = [e[2] for e in watcher.events if e[0] == "leave" and e[1] == leaving.member][-1]
        await watcher.close()
        return took, reason

    try:
        took, reason = asyncio.run(main())
    finally:
        c.stop()
    assert took < LEAVE_WITHIN_S and reason in ("closed", "server_closed")
