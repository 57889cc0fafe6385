"""RedisBus against a real redis-server: two buses ("servers") in one process exchange membership and values; a
killed server's members leave within 3 s; Redis killed and restarted heals; malformed input is counted, not fatal."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator

import msgpack
import numpy as np
import pytest
from ofera.streaming.bus import BusUnavailable, ExpressionValues, MemberInfo
from ofera.streaming.redis_bus import LOST_REASON, RedisBus, decode_message, redact
from redis_support import RedisServer, free_port, running_redis

ROOM = "lab.1"


@pytest.fixture
def redis_server() -> Iterator[RedisServer]:
    with running_redis() as server:
        yield server


class Recorder:
    """A BusListener that records every call as a tuple."""

    def __init__(self) -> None:
        self.events: list[tuple] = []

    def remote_joined(self, room: str, info: MemberInfo) -> None:
        self.events.append(("joined", room, info))

    def remote_left(self, room: str, member: str, reason: str) -> None:
        self.events.append(("left", room, member, reason))

    def remote_values(self, msg: ExpressionValues) -> None:
        self.events.append(("values", msg))

    def bus_state(self, connected: bool) -> None:
        self.events.append(("state", connected))

    def of(self, kind: str) -> list[tuple]:
        return [e for e in self.events if e[0] == kind]

    async def wait(self, pred: Callable[[], bool], timeout: float = 5.0) -> float:
        """Seconds until pred() held; fails after `timeout`."""
        t0 = time.monotonic()
        while not pred():
            if time.monotonic() - t0 > timeout:
                raise AssertionError(f"timed out; events: {self.events}")
            await asyncio.sleep(0.01)
        return time.monotonic() - t0


def bus(url: str, name: str, **kw) -> RedisBus:
    return RedisBus(url, server_id=name, backoff_s=(0.05, 0.2), **kw)


def values(seed: int, n: int = 68) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal(n).astype(np.float32)


def metric(b: RedisBus, name: str, **labels: str) -> float:
    return b.metrics.registry.get_sample_value(name, labels) or 0.0


ALICE = MemberInfo(member="alice", avatar="default", server="A", publish=True)
BOB = MemberInfo(member="bob", avatar="", server="B", publish=False)


def test_two_buses_exchange_membership_and_values(redis_server: RedisServer) -> None:
    async def main() -> None:
        a, b = bus(redis_server.url, "A"), bus(redis_server.url, "B")
        ra, rb = Recorder(), Recorder()
        await a.start(ra)
        await b.start(rb)
        assert ra.of("state") == [("state", True)] and metric(a, "ofera_bus_connected") == 1
        await a.join(ROOM, ALICE)
        await b.join(ROOM, BOB)  # B's first member: A's alice is replayed to B at once
        assert rb.of("joined") == [("joined", ROOM, ALICE)]
        await ra.wait(lambda: ra.of("joined") == [("joined", ROOM, BOB)])  # the join event
        assert metric(a, "ofera_bus_remote_members") == 1 and metric(b, "ofera_bus_remote_members") == 1

        sent = [ExpressionValues(ROOM, "alice", seq=i, t=1000 * i - 5, values=values(i)) for i in range(5)]
        for m in sent:
            a.publish(m)
            await asyncio.sleep(0.02)
        await rb.wait(lambda: len(rb.of("values")) == 5)
        for m, (_, got) in zip(sent, rb.of("values")):
            assert (got.room, got.member, got.seq, got.t) == (m.room, m.member, m.seq, m.t)
            assert got.values.dtype == np.float32 and got.values.tobytes() == m.values.tobytes()
        assert ra.of("values") == []  # a server never hears its own messages
        assert metric(a, "ofera_bus_published_total", kind="v") == 5
        assert metric(b, "ofera_bus_received_total", kind="v") == 5
        assert metric(b, "ofera_bus_hop_seconds_count") == 5

        # A watch-only member's values and a stranger's are dropped (counted), not delivered.
        b.publish(ExpressionValues(ROOM, "bob", 1, 1, values(9)))
        await ra.wait(lambda: metric(a, "ofera_bus_dropped_total", reason="unknown_member") == 1)
        assert ra.of("values") == []

        await a.leave(ROOM, "alice", "bye")
        await rb.wait(lambda: rb.of("left") == [("left", ROOM, "alice", "bye")])
        await asyncio.sleep(3 * b.heartbeat_s)  # reconciliation agrees: nobody re-joins, nobody leaves twice
        assert len(rb.of("joined")) == 1 and len(rb.of("left")) == 1
        await b.close()
        await a.close()
        assert metric(a, "ofera_bus_connected") == 0

    asyncio.run(main())


def test_rooms_are_separate_and_a_late_server_sees_who_is_there(redis_server: RedisServer) -> None:
    async def main() -> None:
        a, b = bus(redis_server.url, "A"), bus(redis_server.url, "B")
        ra, rb = Recorder(), Recorder()
        await a.start(ra)
        await b.start(rb)
        await a.join(ROOM, ALICE)
        await a.join("other", MemberInfo("carol", "default", "A", True))
        await asyncio.sleep(0.1)
        assert rb.events == [("state", True)]  # B has nobody in either room: it hears nothing
        await b.join("other", BOB)
        assert rb.of("joined") == [("joined", "other", MemberInfo("carol", "default", "A", True))]
        a.publish(ExpressionValues(ROOM, "alice", 1, 1, values(1)))
        a.publish(ExpressionValues("other", "carol", 2, 2, values(2)))
        await rb.wait(lambda: len(rb.of("values")) == 1)
        await asyncio.sleep(0.1)
        assert [e[1].member for e in rb.of("values")] == ["carol"]
        await b.leave("other", "bob", "closed")  # B's last member there: B stops listening to the room
        a.publish(ExpressionValues("other", "carol", 3, 3, values(3)))
        await asyncio.sleep(0.2)
        assert len(rb.of("values")) == 1
        await a.close()
        await b.close()

    asyncio.run(main())


def test_the_remote_members_of_a_room_are_bounded(redis_server: RedisServer) -> None:
    """Beyond max_remote, remote members are not reported; once one leaves, a reconcile reports the next."""

    async def main() -> None:
        a, b = bus(redis_server.url, "A", max_remote=2), bus(redis_server.url, "B")
        ra, rb = Recorder(), Recorder()
        await a.start(ra)
        await b.start(rb)
        await a.join(ROOM, ALICE)
        others = [MemberInfo(f"m{i}", "", "B", False) for i in range(4)]
        for info in others:
            await b.join(ROOM, info)
        await ra.wait(lambda: len(ra.of("joined")) == 2)
        await asyncio.sleep(3 * a.heartbeat_s)  # reconciliations find the others: still ignored
        assert [e[2].member for e in ra.of("joined")] == ["m0", "m1"] and metric(a, "ofera_bus_remote_members") == 2
        await b.leave(ROOM, "m0", "bye")
        await ra.wait(lambda: len(ra.of("joined")) == 3)  # a place: the next heartbeat reports one more
        assert ra.of("joined")[-1][2].member in ("m2", "m3") and metric(a, "ofera_bus_remote_members") == 2
        await b.close()
        await a.close()

    asyncio.run(main())


def test_publish_is_newest_wins_and_never_waits(redis_server: RedisServer) -> None:
    async def main() -> None:
        a, b = bus(redis_server.url, "A"), bus(redis_server.url, "B")
        rb = Recorder()
        await a.start(Recorder())
        await b.start(rb)
        await a.join(ROOM, ALICE)
        await b.join(ROOM, BOB)
        t0 = time.perf_counter()
        for i in range(100):  # no await in between: the sender task cannot run, so only the last one goes
            a.publish(ExpressionValues(ROOM, "alice", i, i, values(i)))
        assert time.perf_counter() - t0 < 0.5
        await rb.wait(lambda: len(rb.of("values")) == 1)
        await asyncio.sleep(0.1)
        assert [e[1].seq for e in rb.of("values")] == [99]
        assert metric(a, "ofera_bus_dropped_total", reason="superseded") == 99
        await a.close()
        await b.close()

    asyncio.run(main())


_DYING_SERVER = textwrap.dedent("""
    import asyncio, sys
    from ofera.streaming.bus import MemberInfo
    from ofera.streaming.redis_bus import RedisBus

    class Quiet:
        def remote_joined(self, *a): pass
        def remote_left(self, *a): pass
        def remote_values(self, *a): pass
        def bus_state(self, *a): pass

    async def main():
        bus = RedisBus(sys.argv[1], server_id="D")
        await bus.start(Quiet())
        await bus.join("lab.1", MemberInfo("dora", "default", "D", True))
        print("ready", flush=True)
        await asyncio.sleep(600)

    asyncio.run(main())
""")


def test_a_killed_server_takes_its_members_out_within_3s(redis_server: RedisServer) -> None:
    proc = subprocess.Popen([sys.executable, "-c", _DYING_SERVER, redis_server.url], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"

        async def main() -> float:
            b = bus(redis_server.url, "B")
            rb = Recorder()
            await b.start(rb)
            await b.join(ROOM, BOB)
            assert [e[2].member for e in rb.of("joined")] == ["dora"]
            await asyncio.sleep(0.5)
            proc.kill()  # no goodbye: only its liveness key's TTL tells
            t0 = time.monotonic()
            await rb.wait(lambda: rb.of("left") != [], timeout=5.0)
            took = time.monotonic() - t0
            assert rb.of("left") == [("left", ROOM, "dora", LOST_REASON)]
            await b.close()
            return took

        took = asyncio.run(main())
        assert took < 3.0, f"the dead server's member left after {took:.2f} s"
    finally:
        proc.kill()
        proc.wait(10)


def test_redis_killed_and_restarted_the_room_heals(redis_server: RedisServer) -> None:
    async def main() -> None:
        a, b = bus(redis_server.url, "A"), bus(redis_server.url, "B")
        ra, rb = Recorder(), Recorder()
        await a.start(ra)
        await b.start(rb)
        await a.join(ROOM, ALICE)
        await b.join(ROOM, BOB)
        await ra.wait(lambda: len(ra.of("joined")) == 1)

        redis_server.kill()
        await ra.wait(lambda: ra.of("state")[-1] == ("state", False))
        await rb.wait(lambda: rb.of("state")[-1] == ("state", False))
        assert metric(a, "ofera_bus_connected") == 0 and metric(a, "ofera_bus_remote_members") == 0
        a.publish(ExpressionValues(ROOM, "alice", 7, 7, values(7)))  # while down: dropped, counted, no error
        assert metric(a, "ofera_bus_dropped_total", reason="down") >= 1
        await a.join(ROOM, MemberInfo("ann", "default", "A", True))  # local members go on joining while down
        await asyncio.sleep(0.3)

        redis_server.start()  # same port, empty (no persistence): the servers re-announce their members
        await ra.wait(lambda: ra.of("state")[-1] == ("state", True))
        await rb.wait(lambda: rb.of("state")[-1] == ("state", True))
        await rb.wait(lambda: {e[2].member for e in rb.events[rb.events.index(("state", True), 2):]
                               if e[0] == "joined"} == {"alice", "ann"})
        await ra.wait(lambda: [e[2].member for e in ra.events[ra.events.index(("state", True), 2):]
                               if e[0] == "joined"] == ["bob"])
        assert metric(a, "ofera_bus_reconnects_total") >= 1 and metric(a, "ofera_bus_connected") == 1
        before = len(rb.of("values"))
        a.publish(ExpressionValues(ROOM, "alice", 8, 8, values(8)))
        await rb.wait(lambda: len(rb.of("values")) == before + 1)
        assert rb.of("values")[-1][1].values.tobytes() == values(8).tobytes()
        await a.close()
        await b.close()

    asyncio.run(main())


def present_after_heal(rec: Recorder) -> set[str]:
    """Remote members the listener holds now: joins minus leaves since its last bus_state(True)."""
    last = max(i for i, e in enumerate(rec.events) if e == ("state", True))
    held: set[str] = set()
    for e in rec.events[last:]:
        if e[0] == "joined":
            held.add(e[2].member)
        elif e[0] == "left":
            held.discard(e[2])
    return held


def test_a_member_leaving_while_redis_is_unreachable_is_withdrawn_when_it_is_back(redis_server: RedisServer) -> None:
    async def main() -> None:
        import redis.asyncio as aioredis

        a, b = bus(redis_server.url, "A"), bus(redis_server.url, "B")
        a.backoff_s = (0.5, 0.5)  # A stays down a while, B comes back first and still sees alice in Redis
        ra, rb = Recorder(), Recorder()
        await a.start(ra)
        await b.start(rb)
        await a.join(ROOM, ALICE)
        await a.join(ROOM, MemberInfo("ann", "default", "A", True))
        await b.join(ROOM, BOB)
        raw = aioredis.from_url(redis_server.url)
        for kind in ("pubsub", "normal"):  # a network blip: Redis keeps its data, the servers lose their links
            await raw.client_kill_filter(_type=kind, skipme=True)
        await raw.aclose()
        await ra.wait(lambda: ra.of("state")[-1] == ("state", False))
        await a.leave(ROOM, "alice", "bye")
        await rb.wait(lambda: len(rb.of("state")) == 3 and present_after_heal(rb) == {"ann"})
        await ra.wait(lambda: len(ra.of("state")) == 3 and present_after_heal(ra) == {"bob"})
        await asyncio.sleep(3 * b.heartbeat_s)
        assert present_after_heal(rb) == {"ann"}
        await a.close()
        await b.close()

    asyncio.run(main())


def test_close_ends_a_loop_whose_cancellation_was_swallowed(redis_server: RedisServer) -> None:
    """Before Python 3.12 `asyncio.wait_for` can swallow a cancellation that arrives as its inner call completes;
    a bus loop that lost its cancellation so must still end, and close() return, not hang (CI once hung here)."""
    async def main() -> None:
        a = bus(redis_server.url, "A", heartbeat_s=0.05, ttl_s=1.0)
        await a.start(Recorder())
        await a.join(ROOM, ALICE)
        real, swallowed = a._heartbeat_once, []

        async def swallowing(link):  # noqa: ANN001, ANN202 - stands in for a wait_for that swallows
            try:
                await asyncio.sleep(0.5)  # a slow Redis: the loop sits here when close() cancels it
                return await real(link)
            except asyncio.CancelledError:
                swallowed.append(1)
                return False

        a._heartbeat_once = swallowing
        await asyncio.sleep(0.3)
        closing = asyncio.ensure_future(a.close())
        await asyncio.sleep(0)  # close() starts: the loops are cancelled while one may sit in a heartbeat
        await asyncio.wait_for(closing, 5.0)
        assert swallowed and not a.connected

    asyncio.run(main())


def test_a_redis_that_stops_answering_is_lost_and_found_again(redis_server: RedisServer) -> None:
    """A hung Redis (SIGSTOP: connections stay open, nothing answers) is seen through timeouts, not only resets."""
    async def main() -> None:
        a, b = bus(redis_server.url, "A", timeout_s=0.5), bus(redis_server.url, "B", timeout_s=0.5)
        ra, rb = Recorder(), Recorder()
        await a.start(ra)
        await b.start(rb)
        await a.join(ROOM, ALICE)
        await b.join(ROOM, BOB)
        redis_server.proc.send_signal(signal.SIGSTOP)
        try:
            # both buses see the hang (each through its own timeouts) before Redis answers again
            await ra.wait(lambda: ra.of("state")[-1] == ("state", False), timeout=5.0)
            await rb.wait(lambda: rb.of("state")[-1] == ("state", False), timeout=5.0)
            a.publish(ExpressionValues(ROOM, "alice", 1, 1, values(1)))  # returns at once, counted as dropped
        finally:
            redis_server.proc.send_signal(signal.SIGCONT)
        await rb.wait(lambda: len(rb.of("state")) >= 3 and rb.of("state")[-1] == ("state", True)
                      and present_after_heal(rb) == {"alice"}, timeout=10.0)
        await ra.wait(lambda: len(ra.of("state")) >= 3 and present_after_heal(ra) == {"bob"}, timeout=10.0)
        before = len(rb.of("values"))
        a.publish(ExpressionValues(ROOM, "alice", 2, 2, values(2)))
        await rb.wait(lambda: len(rb.of("values")) == before + 1)
        await a.close()
        await b.close()

    asyncio.run(main())


def test_malformed_messages_are_counted_and_dropped(redis_server: RedisServer) -> None:
    good = {"k": "v", "s": "A", "m": "alice", "q": 1, "t": 2, "v": values(1).tobytes(), "ts": time.time_ns()}
    nan = np.full(68, np.nan, "<f4").tobytes()
    bad = [b"\xc1 not msgpack", msgpack.packb([1, 2, 3]), msgpack.packb({**good, "k": "x"}),
           msgpack.packb({**good, "v": b"\x00" * 12}), msgpack.packb({**good, "v": nan}),
           msgpack.packb({**good, "q": -1}), msgpack.packb({**good, "m": "bad name!"}),
           msgpack.packb({k: v for k, v in good.items() if k != "t"}), msgpack.packb({**good, "s": 3}),
           msgpack.packb({"k": "join", "s": "A", "m": "x", "a": "default", "p": "yes"})]

    async def main() -> None:
        import redis.asyncio as aioredis

        a, b = bus(redis_server.url, "A"), bus(redis_server.url, "B")
        rb = Recorder()
        await a.start(Recorder())
        await a.join(ROOM, ALICE)
        raw = aioredis.from_url(redis_server.url)
        await raw.hset(b.members_key(ROOM), mapping={"mallory": b"\x93garbage", "bad name!": msgpack.packb(
            {"a": "default", "s": "A", "p": True})})
        await b.start(rb)
        await b.join(ROOM, BOB)
        assert [e[2].member for e in rb.of("joined")] == ["alice"]
        malformed_entries = metric(b, "ofera_bus_malformed_total")
        assert malformed_entries >= 2
        for data in bad:
            await raw.publish(b.channel(ROOM), data)
        await raw.publish(b.channel(ROOM), msgpack.packb(good))
        await rb.wait(lambda: len(rb.of("values")) == 1)
        assert metric(b, "ofera_bus_malformed_total") - malformed_entries >= len(bad)
        assert rb.of("values")[0][1].values.tobytes() == values(1).tobytes()
        assert [e[0] for e in rb.events].count("joined") == 1 and rb.of("left") == []
        assert b.connected
        await raw.aclose()
        await a.close()
        await b.close()

    asyncio.run(main())


def test_decode_message_reference() -> None:
    v = values(3, 51)
    d = decode_message(msgpack.packb({"k": "v", "s": "A", "m": "m-1", "q": 5, "t": -3, "v": v.tobytes(), "ts": 9}))
    assert (d["m"], d["q"], d["t"], d["ts"]) == ("m-1", 5, -3, 9) and np.array_equal(d["v"], v)
    assert decode_message(msgpack.packb({"k": "join", "s": "A", "m": "w", "a": "", "p": False}))["a"] == ""
    with pytest.raises(ValueError, match="'a'"):  # a publisher needs an avatar
        decode_message(msgpack.packb({"k": "join", "s": "A", "m": "w", "a": "", "p": True}))
    with pytest.raises(ValueError, match="'r'"):
        decode_message(msgpack.packb({"k": "leave", "s": "A", "m": "w", "r": 1}))


def test_start_without_redis_names_the_url() -> None:
    url = f"redis://:hunter2@127.0.0.1:{free_port()}/0"

    async def main() -> None:
        with pytest.raises(BusUnavailable, match=r"cannot reach Redis at redis://:\*\*\*@127\.0\.0\.1:\d+/0"):
            await RedisBus(url, timeout_s=1.0).start(Recorder())

    asyncio.run(main())
    assert "hunter2" not in redact(url)


def test_the_serve_path_imports_redis_only_with_a_redis_url() -> None:
    probe = ("import sys; from ofera.streaming import Settings, create_app; import ofera.cli.serve; "
             "create_app(Settings(warmup=False)); print(sorted(m for m in sys.modules if m.split('.')[0] == 'redis'))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]"


def test_serve_refuses_to_start_without_redis_in_one_line() -> None:
    from ofera.cli.main import app
    from typer.testing import CliRunner

    url = f"redis://127.0.0.1:{free_port()}/0"
    out = CliRunner().invoke(app, ["serve", "--redis", url, "--port", "0"])
    assert out.exit_code == 2 and "Traceback" not in out.output
    lines = out.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: cannot reach Redis at {url}")
    bad = CliRunner().invoke(app, ["serve", "--redis", "http://127.0.0.1:1", "--port", "0"])
    assert bad.exit_code == 2 and "not a Redis URL" in bad.output
