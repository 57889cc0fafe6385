"""Rooms without sockets: the sans-I/O session core (hello checks, room tokens, rate limit, timeouts) and the
Room / Rooms / RoomViewer core with stand-in avatars and pipelines (subscribe / unsubscribe, per-member frames,
encoding once per wire format, newest wins per viewer per member, limits, and what a cross-server bus reports)."""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import pytest
from ofera.streaming import Settings
from ofera.streaming.bus import ExpressionValues, MemberInfo
from ofera.streaming.core import Close, Compute, Count, KeyFrame, Send, SessionCore, Start, room_token
from ofera.streaming.metrics import Metrics
from ofera.streaming.roles import PendingBs, SessionFatal, Source
from ofera.streaming.rooms import Member, Rooms, RoomViewer
from ofera_protocol import (
    Avatar,
    AvatarInfo,
    Blendshapes,
    ClientConnection,
    ErrorMessage,
    Frame,
    Hello,
    Join,
    Leave,
    ProtocolError,
    ServerConnection,
    encode,
    make_quant,
)
from ofera_protocol import errors as E
from ofera_protocol.messages import Ping
from test_server_support import run

SEC = 1_000_000_000


def settings(**kw) -> Settings:
    base = dict(bs_rate=100.0, bs_burst=3.0, hello_timeout=2.0, room_members=4, max_rooms=2, fast=False)
    base.update(kw)
    return Settings(**base)


# ============================================================================= the session core


def hello(**kw) -> bytes:
    return encode(Hello(layout="arkit52", **kw))


def test_core_accepts_a_v1_hello_and_answers_ping_first() -> None:
    core = SessionCore(settings(), 0)
    (pong,) = core.receive(encode(Ping(t=5)), 1)
    assert isinstance(pong, Send)
    (start,) = core.receive(hello(), 2)
    assert isinstance(start, Start) and start.hello.room is None


def test_core_refuses_a_bad_room_name_fatally() -> None:
    core = SessionCore(settings(), 0)
    send, close = core.receive(encode(Hello(layout="arkit52", room="no spaces")), 1)
    assert isinstance(send, Send) and send.error == E.BAD_FIELD
    assert isinstance(close, Close) and close.code == 4002
    assert core.receive(hello(), 2) == []  # closed: nothing more


@pytest.mark.parametrize("given, ok", [(None, False), ("0" * 64, False), ("right", True)])
def test_core_checks_the_room_token(given: str | None, ok: bool) -> None:
    s = settings(room_secret="app-secret")
    token = room_token("app-secret", "lab-1") if given == "right" else given
    out = SessionCore(s, 0).receive(hello(avatar="default", room="lab-1", room_token=token), 1)
    if ok:
        assert isinstance(out[0], Start)
    else:
        assert out[0].error == E.UNAUTHORIZED and out[1].code == 1008
    # the token is the room's: another room's token does not open this one
    other = SessionCore(s, 0).receive(hello(avatar="default", room="lab-2", room_token=room_token("app-secret",
                                                                                                  "lab-1")), 1)
    assert other[0].error == E.UNAUTHORIZED


def test_room_token_is_the_documented_hmac() -> None:
    import hashlib
    import hmac

    assert room_token("room-secret", "lab-1") == hmac.new(b"room-secret", b"lab-1", hashlib.sha256).hexdigest()


def test_core_hello_timeout_is_a_tick() -> None:
    core = SessionCore(settings(hello_timeout=2.0), 0)
    assert core.tick(SEC) == []
    (close,) = core.tick(2 * SEC)
    assert isinstance(close, Close) and close.code == 1008


def _streaming_core(**hello_kw) -> SessionCore:
    core = SessionCore(settings(), 0)
    (start,) = core.receive(hello(**hello_kw), 0)
    h = start.hello
    watcher = h.room is not None and not h.publish
    core.conn.accept("s1", None if watcher else AvatarInfo("a", 4, 0), member="m-1" if h.room else None)
    return core


def test_core_rate_limits_bs_with_one_error_per_second() -> None:
    core = _streaming_core()
    bs = encode(Blendshapes(seq=1, t=0, w=np.zeros(52, np.float32)))
    kinds = [type(a).__name__ for i in range(6) for a in core.receive(bs, i)]  # 6 bs within 6 ns: burst 3
    assert kinds.count("Compute") == 3 and kinds.count("Send") == 1 and kinds.count("Count") == 6
    later = core.receive(bs, SEC)  # 100 per second: a token is back
    assert any(isinstance(a, Compute) for a in later)


def test_core_clamps_huge_weights_and_counts_conf() -> None:
    core = _streaming_core()
    w = np.full(52, 3e38, np.float32)
    out = core.receive(encode(Blendshapes(seq=1, t=0, w=w, conf=np.float32([1, 1]))), 0)
    assert [a.metric for a in out if isinstance(a, Count)] == ["bs_in", "bs_conf"]
    (c,) = [a for a in out if isinstance(a, Compute)]
    assert float(c.bs.w.max()) == 1000.0


def test_core_watcher_bs_is_a_non_fatal_error() -> None:
    core = _streaming_core(room="lab", publish=False)
    out = core.receive(encode(Blendshapes(seq=4, t=0, w=np.zeros(52, np.float32))), 0)
    (send,) = [a for a in out if isinstance(a, Send)]
    assert send.error == E.NOT_READY and not any(isinstance(a, (Close, Compute)) for a in out)


def test_core_bad_message_after_welcome_costs_one_message() -> None:
    core = _streaming_core()
    out = core.receive(b"\x93\x01\x02\x03", 0)
    assert len(out) == 1 and out[0].error == E.MALFORMED
    assert isinstance(core.receive(encode(Ping(t=1)), 1)[0], Send)


def test_core_bye_closes_normally_and_resync_asks_a_key_frame() -> None:
    from ofera_protocol.messages import Bye, Resync

    core = _streaming_core(encoding="f16", delta=True)
    assert core.receive(encode(Resync()), 1) == [KeyFrame()]
    (close,) = core.receive(encode(Bye()), 2)
    assert close == Close(1000, "bye")
    assert core.receive(encode(Resync()), 3) == []  # closed


# ============================================================================= rooms in memory

N = 6


class FakePipeline:
    """Stands in for Pipeline: values = the first weight everywhere; Gaussians x = values[0]. Counts its work."""

    def __init__(self, n: int = N) -> None:
        self.n = n
        self.mapped = self.deformed = 0
        self.gate = threading.Event()
        self.gate.set()

    def map(self, w, conf=None):
        self.gate.wait(10)
        self.mapped += 1
        return np.full(68, w[0], np.float32), {"epm": 1}

    def deform_values(self, values):
        self.deformed += 1
        pos = np.full((self.n, 3), values[0], np.float32)
        rot = np.tile(np.float32([0, 0, 0, 1]), (self.n, 1))
        return SimpleNamespace(position=pos, rotation=rot, scale=np.full((self.n, 3), 0.01, np.float32)), {"deform": 2}

    def run(self, w, conf=None):
        self.values, mapped = self.map(w)
        state, deformed = self.deform_values(self.values)
        return state, {**mapped, **deformed}


class FakeAssets:
    """Stands in for AvatarAssets: an n-Gaussian avatar (6 by default), its selections and quantisation."""

    def __init__(self, aid: str, n: int = N) -> None:
        self.id, self.count, self.expression, self.sh_degree = aid, n, "flame68", 0
        rng = np.random.default_rng(1)
        self.avatar = Avatar(opacity=np.full(n, 0.5, np.float32), sh=np.zeros((n, 1, 3), np.float32),
                             position=rng.normal(0, 0.05, (n, 3)).astype(np.float32),
                             rotation=np.tile(np.float32([0, 0, 0, 1]), (n, 1)),
                             scale=np.full((n, 3), 0.01, np.float32))
        self.pipelines: list[FakePipeline] = []

    def wire_avatar(self, coords, size=None):
        return self.avatar

    def quant(self, coords, size=None):
        return make_quant(np.concatenate([self.avatar.position, np.full((1, 3), 1.5, np.float32),
                                          np.full((1, 3), -0.5, np.float32)]), self.avatar.scale)

    def selection(self, sparse, size):
        n = self.count
        return (None, None) if not sparse else (np.arange(0, n, 2), np.arange(0, n, 2, dtype=np.uint32))

    def pipeline(self, layout, *args):
        p = FakePipeline(self.count)
        self.pipelines.append(p)
        return p


class FakeArkitAssets(FakeAssets):
    """An ARKit-driven avatar (51 morph weights): it has no rig (params viewers cannot deform it)."""

    def __init__(self, aid: str) -> None:
        super().__init__(aid)
        self.expression, self.subject, self._cache = "arkit51", None, {}
        self.wire, self.avatar = self.avatar, SimpleNamespace(expression="arkit51", name=aid)  # what build_rig reads

    def wire_avatar(self, coords, size=None):
        return self.wire

    def quant(self, coords, size=None):
        return make_quant(self.wire.position, self.wire.scale)


class FakeRegistry:
    def __init__(self) -> None:
        self.assets = {"anna": FakeAssets("anna"), "ben": FakeAssets("ben"), "big": FakeAssets("big", 60),
                       "kim": FakeArkitAssets("kim")}

    def resolve(self, aid):
        return aid if aid in self.assets or aid == "broken" else None

    def get(self, aid):
        if aid == "broken":
            raise ValueError("not an avatar file")
        return self.assets[aid]


class FakeBus:
    server_id = "srv-local"

    def __init__(self) -> None:
        self.events: list[tuple] = []
        self.published: list[ExpressionValues] = []

    async def join(self, room, info):
        self.events.append(("join", room, info.member))

    async def leave(self, room, member, reason):
        self.events.append(("leave", room, member, reason))

    def publish(self, msg):
        self.published.append(msg)


class Peer:
    """A local member as a client sees it: its connection state, what it received, a send that can stall."""

    def __init__(self, world: World, member_id: str, hello: Hello, assets: FakeAssets | None) -> None:
        self.world = world
        self.client = ClientConnection()
        data = self.client.hello(hello.layout, hello.avatar, encoding=hello.encoding, sparse=hello.sparse,
                                 room=hello.room, publish=hello.publish, self_view=hello.self)
        self.conn = ServerConnection()
        self.conn.receive(data)
        info = AvatarInfo(assets.id, N, 0) if assets is not None else None
        self.client.receive(self.conn.accept("s-" + member_id, info, member=member_id))
        self.frames: list[Frame] = []
        self.control: list = []
        self.open = threading.Event()
        self.open.set()
        self.blocked = asyncio.Event()
        self.blocked.set()
        self.viewer = RoomViewer(self.send, world.executor, world.metrics, 1 << 20,
                                 world.rooms.settings.room_control_bytes)
        source = None
        if hello.publish:
            source = Source(assets.pipeline(hello.layout), world.executor, world.metrics)
        self.pipeline = source.pipeline if source is not None else None
        self.member = Member(MemberInfo(member_id, assets.id if assets else "", "srv-local", hello.publish), True,
                             assets, source, self.viewer, hello, self.conn)
        self.tasks = [asyncio.create_task(self.viewer.run())]
        if source is not None:
            self.tasks.append(asyncio.create_task(source.run()))

    async def send(self, data) -> None:
        await self.blocked.wait()
        msg = self.client.receive(bytes(data))
        (self.frames if isinstance(msg, Frame) else self.control).append(msg)

    def bs(self, seq: int, x: float) -> None:
        self.member.source.offer(PendingBs(Blendshapes(seq=seq, t=seq * 100, w=np.full(52, x, np.float32)), 0, 0))

    def by(self, member: str) -> list[Frame]:
        return [f for f in self.frames if f.member == member]

    def stop(self) -> None:
        for t in self.tasks:
            t.cancel()


class World:
    def __init__(self, **kw) -> None:
        self.executor = ThreadPoolExecutor(2)
        self.metrics = Metrics()
        self.registry = FakeRegistry()
        self.rooms = Rooms(settings(**kw), self.registry, self.executor, self.metrics)
        self.peers: list[Peer] = []

    def join(self, member_id: str, room: str = "lab", avatar: str | None = "anna", self_view: bool = False, **kw
             ) -> Peer:
        h = Hello(layout="arkit52", avatar=avatar or "default", room=room, publish=avatar is not None, self=self_view,
                  **kw)
        p = Peer(self, member_id, h, self.registry.assets[avatar] if avatar else None)
        self.rooms.join_local(room, p.member)
        self.peers.append(p)
        return p

    def close(self) -> None:
        for p in self.peers:
            p.stop()
        self.executor.shutdown(wait=False, cancel_futures=True)

    def encodes(self) -> float:
        return self.metrics.registry.get_sample_value("ofera_stage_seconds_count", {"stage": "encode"}) or 0.0


async def until(cond, timeout: float = 10.0) -> None:
    async def poll() -> None:
        while not cond():
            await asyncio.sleep(0.005)

    await asyncio.wait_for(poll(), timeout)


def in_world(body, **kw):
    async def main():
        w = World(**kw)
        try:
            await body(w)
        finally:
            w.close()

    run(main())


def test_three_members_see_each_other_with_the_right_member() -> None:
    async def body(w: World) -> None:
        a = w.join("m-a", avatar="anna", encoding="f16")
        b = w.join("m-b", avatar="ben", encoding="q13")
        c = w.join("m-w", avatar=None)  # watches, f32
        await until(lambda: {"m-a", "m-b"} <= set(c.client.formats) and "m-b" in a.client.formats
                    and "m-a" in b.client.formats)
        assert set(a.client.members) == {"m-b", "m-w"} and a.client.members["m-w"].join.publish is False
        assert set(c.client.members) == {"m-a", "m-b"}
        for i in range(1, 4):
            a.bs(i, 0.1 * i)
            b.bs(i, -0.1 * i)
            await until(lambda i=i: c.by("m-a")[-1:] and c.by("m-a")[-1].seq == i and c.by("m-b")[-1:]
                        and c.by("m-b")[-1].seq == i)
        await until(lambda: a.by("m-b") and a.by("m-b")[-1].seq == 3 and b.by("m-a") and b.by("m-a")[-1].seq == 3)
        assert not a.by("m-a") and not b.by("m-b")  # no self view unless asked
        last = c.by("m-a")[-1]
        assert last.t == 300 and np.allclose(last.position, 0.3)  # the source's seq and t, its Gaussians
        np.testing.assert_allclose(a.by("m-b")[-1].position, -0.3, atol=2e-3)  # q13, the member's quant
        assert {f.member for f in c.frames} == {"m-a", "m-b"}

        w.rooms.leave_local("lab", "m-a", "bye")
        await until(lambda: any(isinstance(m, Leave) for m in c.control) and any(isinstance(m, Leave)
                                                                                 for m in b.control))
        assert [m for m in c.control if isinstance(m, Leave)] == [Leave("m-a", "bye")]
        assert "m-a" not in c.client.members and "m-a" not in b.client.members

    in_world(body)


def test_self_view_and_encoding_once_per_wire_format() -> None:
    async def body(w: World) -> None:
        a = w.join("m-a", avatar="anna", self_view=True)
        v1 = w.join("m-v1", avatar=None)
        v2 = w.join("m-v2", avatar=None)  # same wire format as v1 and as a (f32, flame, dense)
        await until(lambda: all("m-a" in p.client.formats for p in (a, v1, v2)))
        before = w.encodes()
        for i in range(1, 6):
            a.bs(i, 0.01 * i)
            await until(lambda i=i: all(p.by("m-a") and p.by("m-a")[-1].seq == i for p in (a, v1, v2)))
        assert w.encodes() - before == 5  # 5 frames, 3 viewers of one format: 5 encodings
        assert bytes(encode(a.by("m-a")[-1], a.client.formats["m-a"])) == bytes(
            encode(v1.by("m-a")[-1], v1.client.formats["m-a"]))

    in_world(body)


def test_a_stalled_viewer_slows_nobody_and_stops_costing_work() -> None:
    async def body(w: World) -> None:
        a = w.join("m-a", avatar="anna")
        slow = w.join("m-s", avatar=None)
        fast = w.join("m-f", avatar=None, encoding="f16")
        await until(lambda: "m-a" in slow.client.formats and "m-a" in fast.client.formats)
        slow.blocked.clear()  # its socket stops draining
        for i in range(1, 30):
            a.bs(i, 0.01 * i)
            await until(lambda i=i: fast.by("m-a") and fast.by("m-a")[-1].seq == i)
        assert len(fast.by("m-a")) == 29  # every frame, none waited for the stalled viewer
        skipped = slow.viewer.skipped
        assert skipped >= 20  # newest wins in the stalled viewer's slot
        # only the stalled viewer left: once its slot holds a frame, the source computes nothing more
        w.rooms.leave_local("lab", "m-f", "bye")
        await asyncio.sleep(0.05)
        done = a.pipeline.deformed
        for i in range(30, 40):
            a.bs(i, 0.5)
            await asyncio.sleep(0.01)
        assert a.pipeline.deformed == done
        slow.blocked.set()  # it reads again: it gets the newest frame
        await until(lambda: slow.by("m-a") and slow.by("m-a")[-1].seq == 39)

    in_world(body)


def test_a_viewer_that_needs_no_gaussians_means_no_deformation() -> None:
    from ofera.streaming.member_wire import MemberWire

    class ValuesWriter:
        needs_state = False

        def encode_values(self, seq, t, timing, values, member):
            return encode(ErrorMessage("values", f"{member}:{seq}:{values[0]:.2f}", False))

    async def body(w: World) -> None:
        a = w.join("m-a", avatar="anna")
        v = w.join("m-v", avatar=None)
        await until(lambda: "m-a" in v.client.formats)
        slot = v.viewer.slots["m-a"]
        slot.wire = MemberWire("m-a", [], ValuesWriter(), ("values",), N)  # what a params viewer's wire holds
        got: list[str] = []
        v.control.clear()
        for i in range(1, 4):
            a.bs(i, 0.25)
            await until(lambda i=i: any(getattr(m, "message", "").endswith(f":{i}:0.25") for m in v.control))
        got = [m.message for m in v.control if isinstance(m, ErrorMessage)]
        assert got[-1] == "m-a:3:0.25"
        assert a.pipeline.deformed == 0 and a.pipeline.mapped == 3

    in_world(body)


def test_limits_room_full_and_too_many_rooms() -> None:
    async def body(w: World) -> None:
        for i in range(4):
            w.join(f"m-{i}", avatar=None)
        with pytest.raises(ProtocolError) as full:
            w.rooms.admit("lab")
        assert full.value.code == E.ROOM_FULL and full.value.close_code == 4014 and full.value.fatal
        w.join("m-x", room="other", avatar=None)
        with pytest.raises(ProtocolError) as many:
            w.rooms.admit("third")
        assert many.value.code == E.TOO_MANY_ROOMS
        w.rooms.leave_local("other", "m-x", "bye")  # an empty room closes: a new one may open
        w.rooms.admit("third")

    in_world(body, room_members=4, max_rooms=2)


def test_the_bus_carries_values_and_remote_members_are_deformed_once() -> None:
    async def body(w: World) -> None:
        bus = w.rooms.bus = FakeBus()
        a = w.join("m-a", avatar="anna")
        v1 = w.join("m-v1", avatar=None)
        v2 = w.join("m-v2", avatar=None)
        await until(lambda: ("join", "lab", "m-v2") in bus.events)
        a.bs(1, 0.2)
        await until(lambda: bus.published)
        msg = bus.published[0]
        assert (msg.room, msg.member, msg.seq, msg.t) == ("lab", "m-a", 1, 100) and msg.values.shape == (68,)

        w.rooms.remote_joined("lab", MemberInfo("m-r", "ben", "srv-2", True))
        w.rooms.remote_joined("lab", MemberInfo("m-u", "nobody", "srv-2", True))  # an avatar not here
        await until(lambda: "m-r" in v1.client.formats and "m-r" in v2.client.formats and "m-r" in a.client.formats)
        remote = w.registry.assets["ben"].pipelines[-1]
        for i in range(1, 4):
            w.rooms.remote_values(ExpressionValues("lab", "m-r", i, i * 7, np.full(68, 0.1 * i, np.float32)))
            await until(lambda i=i: all(p.by("m-r") and p.by("m-r")[-1].seq == i for p in (v1, v2, a)))
        assert remote.deformed == 3  # once per frame for three local viewers
        assert v1.by("m-r")[-1].t == 21 and np.allclose(v1.by("m-r")[-1].position, 0.3)
        assert "m-u" not in v1.client.members  # invisible: no join, no frames
        assert w.metrics.registry.get_sample_value("ofera_room_unresolved_total") == 1

        w.rooms.bus_state(False)  # lost: remote members are stale
        await until(lambda: Leave("m-r", "stale") in v1.control and Leave("m-r", "stale") in v2.control)
        assert not any(isinstance(m, Leave) and m.member == "m-u" for m in v1.control)
        w.rooms.bus_state(True)
        w.rooms.remote_joined("lab", MemberInfo("m-r", "ben", "srv-2", True))  # replayed by the bus: healed
        await until(lambda: "m-r" in v1.client.formats)
        assert sum(isinstance(m, Join) and m.member == "m-r" for m in v1.control) == 2
        w.rooms.remote_values(ExpressionValues("lab", "m-r", 9, 90, np.full(68, 0.5, np.float32)))
        await until(lambda: v1.by("m-r")[-1].seq == 9)
        w.rooms.remote_left("lab", "m-r", "server_lost")
        await until(lambda: Leave("m-r", "server_lost") in v1.control)

        for p in (a, v1, v2):
            w.rooms.leave_local("lab", p.member.id, "bye")
        await until(lambda: ("leave", "lab", "m-a", "bye") in bus.events)
        assert "lab" not in w.rooms.rooms

    in_world(body, room_members=5)  # 3 local, 2 remote members


def test_a_remote_member_whose_one_viewer_stalled_costs_no_deformation() -> None:
    async def body(w: World) -> None:
        w.rooms.bus = FakeBus()
        a = w.join("m-a", avatar=None)
        w.rooms.remote_joined("lab", MemberInfo("m-r", "ben", "srv-2", True))
        await until(lambda: "m-r" in a.client.formats)
        remote = w.registry.assets["ben"].pipelines[-1]
        a.blocked.clear()  # its one viewer stops reading: after one frame in its slot, nothing is deformed
        for i in range(1, 20):
            w.rooms.remote_values(ExpressionValues("lab", "m-r", i, i, np.full(68, 0.1, np.float32)))
            await asyncio.sleep(0.005)
        assert remote.deformed <= 2

    in_world(body)


def test_a_remote_member_without_local_viewers_costs_no_deformation() -> None:
    async def body(w: World) -> None:
        w.rooms.bus = FakeBus()
        p = w.join("m-p", avatar=None, encoding="params")  # an ARKit avatar has no rig: no slot, no viewer of it
        w.rooms.remote_joined("lab", MemberInfo("m-k", "kim", "srv-2", True))
        await until(lambda: "m-k" in p.client.members)
        remote = w.registry.assets["kim"].pipelines[-1]
        for i in range(1, 10):
            w.rooms.remote_values(ExpressionValues("lab", "m-k", i, i, np.full(51, 0.1, np.float32)))
            await asyncio.sleep(0.005)
        assert remote.deformed == 0 and not p.frames

    in_world(body)


def _sample(w: World, name: str, **labels: str) -> float:
    return w.metrics.registry.get_sample_value(name, labels) or 0.0


def test_bad_remote_values_are_dropped_and_no_viewer_session_ends() -> None:
    """Values that do not fit the member's avatar (length, magnitude) are dropped and counted; the viewers go on."""

    async def body(w: World) -> None:
        w.rooms.bus = FakeBus()
        v = w.join("m-v", avatar=None, encoding="f16")
        a = w.join("m-a", avatar="anna", encoding="f16")
        w.rooms.remote_joined("lab", MemberInfo("m-r", "ben", "srv-2", True))
        await until(lambda: "m-r" in v.client.formats and "m-r" in a.client.formats)
        w.rooms.remote_values(ExpressionValues("lab", "m-r", 1, 1, np.full(51, 0.1, np.float32)))  # a FLAME avatar
        w.rooms.remote_values(ExpressionValues("lab", "m-r", 2, 2, np.full(68, 1e6, np.float32)))  # f16 overflows
        w.rooms.remote_values(ExpressionValues("lab", "m-r", 3, 3, np.full(68, 0.2, np.float32)))
        await until(lambda: v.by("m-r") and a.by("m-r"))
        assert [f.seq for f in v.by("m-r")] == [3] and [f.seq for f in a.by("m-r")] == [3]
        assert _sample(w, "ofera_bus_malformed_total") == 2
        assert not any(t.done() for p in (v, a) for t in p.tasks)

    in_world(body)


def test_a_frame_that_fails_to_encode_is_dropped_for_its_viewer_only(caplog, monkeypatch) -> None:
    from ofera.streaming import rooms
    from ofera.streaming.member_wire import MemberWire
    from ofera.streaming.rooms import LogLimit, PendingValues

    monkeypatch.setattr(rooms, "limited", LogLimit(rooms.log))  # no record held back by an earlier test

    class FlakyWriter:
        needs_state = False

        def encode_values(self, seq, t, timing, values, member):
            if values[0] > 0.5:
                raise ValueError("not encodable")
            return encode(ErrorMessage("values", f"{member}:{seq}", False))

    async def body(w: World) -> None:
        a = w.join("m-a", avatar="anna")
        v = w.join("m-v", avatar=None)
        await until(lambda: "m-a" in v.client.formats)
        v.viewer.slots["m-a"].wire = MemberWire("m-a", [], FlakyWriter(), ("flaky",), N)
        v.control.clear()
        for seq, x in ((1, 0.9), (2, 0.9), (3, 0.25)):
            a.bs(seq, x)
            await until(lambda seq=seq: a.pipeline.mapped == seq)
            await asyncio.sleep(0.02)
        await until(lambda: any(getattr(m, "message", "") == "m-a:3" for m in v.control))
        assert not any(t.done() for t in v.tasks + a.tasks)
        assert _sample(w, "ofera_room_events_total", event="bad_frame") == 2
        assert len([r for r in caplog.records if "encoding frame" in r.getMessage()]) == 1  # rate-limited

        w.rooms.remote_joined("lab", MemberInfo("m-r", "ben", "srv-2", True))  # a remote member's deform fails
        await until(lambda: "m-r" in v.client.formats)
        src = w.rooms.rooms["lab"].members["m-r"].source
        for seq in (1, 2, 3):
            src._failed(PendingValues(ExpressionValues("lab", "m-r", seq, 0, np.zeros(68, np.float32)), 0),
                        RuntimeError("deform failed"))
        assert len([r for r in caplog.records if "deforming frame" in r.getMessage()]) == 1

    in_world(body)


def test_remote_members_beyond_room_members_wait_for_a_place() -> None:
    async def body(w: World) -> None:
        a = w.join("m-a", avatar=None)
        for i in range(10):
            w.rooms.remote_joined("lab", MemberInfo(f"m-r{i}", "", "srv-2", False))
        r = w.rooms.rooms["lab"]
        await until(lambda: len(a.client.members) == 3)
        await asyncio.sleep(0.05)
        assert len(r.members) == 4 and set(a.client.members) == {"m-r0", "m-r1", "m-r2"}
        assert _sample(w, "ofera_room_events_total", event="over_limit") == 7
        w.rooms.remote_left("lab", "m-r4", "bye")  # a waiting member leaves: never shown
        w.rooms.remote_left("lab", "m-r0", "bye")  # a place: the first waiting member takes it
        await until(lambda: "m-r3" in a.client.members)
        assert "m-r0" not in a.client.members and len(r.members) == 4 and list(r.waiting) == [f"m-r{i}" for i in
                                                                                              range(5, 10)]
        w.rooms.bus_state(False)  # remote members are gone: the bus replays them when it is back
        assert not r.waiting and len(r.members) == 1

    in_world(body, room_members=4)


def test_a_stalled_viewer_queues_nothing_for_members_that_came_and_went() -> None:
    async def body(w: World) -> None:
        a = w.join("m-a", avatar="anna")
        v = w.join("m-v", avatar=None)
        await until(lambda: "m-a" in v.client.formats)
        v.blocked.clear()  # v stops reading: a frame of m-a stays in flight
        a.bs(1, 0.1)
        await until(lambda: v.viewer.sends == 1)
        for i in range(50):
            p = w.join(f"m-x{i}", avatar="ben")
            await asyncio.sleep(0.002 * (i % 3))
            w.rooms.leave_local("lab", p.member.id, "bye")
            p.stop()
        await asyncio.sleep(0.1)
        assert len(v.viewer.control) == 0 and v.viewer.control_bytes == 0
        w.rooms.remote_joined("lab", MemberInfo("m-w", "", "srv-2", False))  # a join that stays
        await until(lambda: len(v.viewer.control) == 1)
        v.blocked.set()
        await until(lambda: "m-w" in v.client.members)
        assert not [m for m in v.control if isinstance(m, (Join, Leave)) and m.member.startswith("m-x")]

    in_world(body, room_members=4)


def test_a_viewer_whose_control_queue_overflows_ends_with_server_full() -> None:
    async def body(w: World) -> None:
        a = w.join("m-a", avatar="anna")
        v = w.join("m-v", avatar=None)
        await until(lambda: "m-a" in v.client.formats)
        assert v.viewer.control_limit == 1 << 20  # the setting
        v.viewer.control_limit = 1500  # this viewer's only (a's announcements come in bursts too)
        v.blocked.clear()
        a.bs(1, 0.1)
        await until(lambda: v.viewer.sends == 1)  # stuck on the socket
        for i in range(5):  # ~500 bytes of join and avatar each (remote: no viewers of their own here)
            w.rooms.remote_joined("lab", MemberInfo(f"m-x{i}", "ben", "srv-2", True))
        await until(lambda: v.tasks[0].done())
        err = v.tasks[0].exception()
        assert isinstance(err, SessionFatal) and err.err.code == E.SERVER_FULL and err.err.fatal
        assert "room_control_bytes" in err.err.message and not v.viewer.control
        assert _sample(w, "ofera_room_events_total", event="overflow") == 1
        assert not a.tasks[0].done()  # nobody else is affected

    in_world(body, room_members=8, room_control_bytes=1 << 20)


def test_a_large_member_is_not_starved_by_smaller_ones_under_room_send_bytes() -> None:
    """Head of line: a member whose frame does not fit in room_send_bytes now goes next once it fits; smaller
    members' frames do not overtake it."""
    from ofera.streaming.roles import ComputedFrame

    def frame(member: str, seq: int) -> ComputedFrame:
        n = 60 if member == "m-b" else N
        state = SimpleNamespace(position=np.full((n, 3), 0.1, np.float32), scale=np.full((n, 3), 0.01, np.float32),
                                rotation=np.tile(np.float32([0, 0, 0, 1]), (n, 1)))
        return ComputedFrame(seq, seq, state, {}, 0, None, member)

    async def body(w: World) -> None:
        peers = [w.join(m, avatar=a) for m, a in (("m-b", "big"), ("m-s1", "anna"), ("m-s2", "ben"))]
        v = w.join("m-v", avatar=None)
        await until(lambda: {"m-b", "m-s1", "m-s2"} <= set(v.client.formats))
        for p in peers:
            p.bs(1, 0.1)
            await until(lambda p=p: v.by(p.member.id))
        viewer = v.viewer
        viewer.slots = {m: viewer.slots[m] for m in ("m-b", "m-s1", "m-s2")}  # this round-robin order
        small, large = viewer.slots["m-s1"].size, viewer.slots["m-b"].size
        assert large > small + 1
        viewer.limit = 2 * small + 1  # two small frames fit in flight; a small one and the large one do not
        viewer._turn = 0
        gates: list[asyncio.Future] = []
        sizes: list[int] = []
        send = viewer.send

        async def held(data) -> None:
            gate = asyncio.get_running_loop().create_future()
            gates.append(gate)
            sizes.append(len(data))
            await gate
            await send(data)

        viewer.send = held
        viewer.slots["m-s1"].offer(frame("m-s1", 2))
        await until(lambda: len(gates) == 1)
        viewer.slots["m-b"].offer(frame("m-b", 2))
        viewer.slots["m-s2"].offer(frame("m-s2", 2))
        await until(lambda: len(gates) == 2)  # m-s2 fits next to m-s1; m-b does not
        for seq in range(3, 9):  # one send completes, one small member has a new frame, in turn
            next(g for g in gates if not g.done()).set_result(None)
            await asyncio.sleep(0.02)
            member = "m-s1" if seq % 2 else "m-s2"
            viewer.slots[member].offer(frame(member, seq))
            await asyncio.sleep(0.02)
        assert max(sizes) > 2 * small, sizes  # m-b was sent while the small ones kept coming
        for g in gates:
            if not g.done():
                g.set_result(None)
        await until(lambda: v.by("m-b")[-1].seq == 2)

    in_world(body)


def test_a_params_viewer_sees_a_member_without_rig_as_a_member_without_avatar(caplog) -> None:
    async def body(w: World) -> None:
        k = w.join("m-k", avatar="kim")  # ARKit-driven: no rig
        p1 = w.join("m-p1", avatar=None, encoding="params")
        p2 = w.join("m-p2", avatar=None, encoding="params")
        f = w.join("m-f", avatar=None)
        await until(lambda: "m-k" in f.client.formats and "m-k" in p1.client.members and "m-k" in p2.client.members)
        for p in (p1, p2):
            assert p.client.members["m-k"].join == Join(member="m-k", publish=False) and "m-k" not in p.client.formats
        k.bs(1, 0.3)
        await until(lambda: f.by("m-k"))
        await asyncio.sleep(0.05)
        assert not p1.frames and not p2.frames
        rig_logs = [r for r in caplog.records if "has no rig" in r.getMessage()]
        assert len(rig_logs) == 1 and rig_logs[0].exc_info is None
        w.rooms.leave_local("lab", "m-k", "bye")
        await until(lambda: Leave("m-k", "bye") in p1.control)

    in_world(body, room_members=5)


# ============================================================================= the protocol additions


def test_watchers_need_no_layout_and_publishers_name_their_avatar() -> None:
    from ofera_protocol import decode_client_message
    from ofera_protocol.codec import pack_map

    h = decode_client_message(pack_map({"type": "hello", "protocol": 1, "room": "lab", "publish": False}))
    assert h.room == "lab" and h.publish is False and h.layout == "arkit52"
    with pytest.raises(ProtocolError) as e:
        decode_client_message(pack_map({"type": "hello", "protocol": 1, "room": "lab"}))
    assert e.value.code == E.BAD_FIELD and "avatar" in e.value.message
    v1 = decode_client_message(pack_map({"type": "hello", "protocol": 1, "layout": "arkit52", "publish": False}))
    assert v1.room is None  # without a room, publish means nothing: a v1 session


def test_client_refuses_inconsistent_joins_and_drops_frames_of_unknown_members() -> None:
    from ofera_protocol import ClientState, Welcome, decode_server_message
    from ofera_protocol.codec import pack_map

    with pytest.raises(ProtocolError) as e:
        decode_server_message(pack_map({"type": "join", "member": "m", "publish": False,
                                        "avatar": {"id": "a", "count": 1, "sh_degree": 0}}))
    assert e.value.code == E.BAD_FIELD
    c = ClientConnection()
    c.hello("arkit52", room="lab", encoding="q13")
    c.receive(encode(Welcome(session="s", avatar=AvatarInfo("a", 4, 0), layout="arkit52", encoding="q13", room="lab",
                             member="m-me")))
    with pytest.raises(ProtocolError) as q:
        c.receive(encode(Join(member="m-x", avatar=AvatarInfo("a", 4, 0))))  # q13 without the member's quant
    assert q.value.code == E.BAD_FIELD and not q.value.fatal
    frame = pack_map({"type": "frame", "member": "m-y", "seq": 1, "t": 0, "timing": {}, "n": 0})
    with pytest.raises(ProtocolError) as nf:
        c.receive(frame)
    assert nf.value.code == E.NOT_READY and not nf.value.fatal and c.state is ClientState.STREAMING


@pytest.mark.parametrize("limit, concurrent", [(1, 1), (1 << 20, 2)])
def test_bytes_in_flight_per_connection_are_bounded(limit: int, concurrent: int) -> None:
    """Frames of several members go to one socket concurrently up to room_send_bytes (one always may)."""

    async def body(w: World) -> None:
        a = w.join("m-a", avatar="anna")
        b = w.join("m-b", avatar="ben")
        v = w.join("m-v", avatar=None)
        v.viewer.limit = limit
        await until(lambda: {"m-a", "m-b"} <= set(v.client.formats))
        a.bs(1, 0.1)
        await until(lambda: v.by("m-a"))  # the first frame sets the size estimate
        b.bs(1, 0.2)
        await until(lambda: v.by("m-b"))
        v.blocked.clear()  # the socket stops draining: sends stay in flight
        a.bs(2, 0.3)
        b.bs(2, 0.4)
        await until(lambda: v.viewer.inflight > 0)
        await asyncio.sleep(0.1)
        assert v.viewer.sends == concurrent
        assert v.viewer.inflight <= max(limit, v.viewer.slots["m-a"].size)
        v.blocked.set()
        await until(lambda: v.by("m-a")[-1].seq == 2 and v.by("m-b")[-1].seq == 2)

    in_world(body)


def test_a_remote_avatar_that_fails_to_load_stays_invisible() -> None:
    async def body(w: World) -> None:
        w.rooms.bus = FakeBus()
        v = w.join("m-v", avatar=None)
        w.rooms.remote_joined("lab", MemberInfo("m-b", "broken", "srv-2", True))
        w.rooms.remote_joined("lab", MemberInfo("m-r", "ben", "srv-2", True))
        await until(lambda: "m-r" in v.client.formats)
        await until(lambda: w.metrics.registry.get_sample_value("ofera_room_unresolved_total") == 1)
        assert "m-b" not in v.client.members
        w.rooms.remote_left("lab", "m-b", "bye")  # nothing was announced: nothing to take back
        w.rooms.remote_left("lab", "m-r", "bye")
        await until(lambda: Leave("m-r", "bye") in v.control)
        assert [m.member for m in v.control if isinstance(m, Leave)] == ["m-r"]

    in_world(body)
