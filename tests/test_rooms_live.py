"""Rooms through a real server (PROTOCOL.md 12): two publishers and a watcher in one room each see the others'
frames with the right `member` (f32 frames bit for bit the offline pipeline's), a leaver's `leave` reaches the
rest within 3 s, the limits and room tokens refuse clearly, a v1 client sees no change, and `ofera replay --room`
/ `--watch` make recordings meet."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from ofera.cli.main import app
from ofera.client import ServerError, connect, watch
from ofera.mapping.layouts import get_layout
from ofera.sources import FaceLog, write_facelog
from ofera.streaming import offline_pipeline
from ofera.streaming.core import room_token
from ofera_protocol import ClientConnection, Frame, Join, Leave
from test_server_support import SMALL, _start, metric, run, settings
from typer.testing import CliRunner

pytestmark = pytest.mark.timeout(180)

SECRET = "app-secret"


@functools.cache
def room_server():
    """Rooms with small limits: 3 members per room, 3 rooms (no room secret: `guarded_server` has one)."""
    return _start(settings(room_members=3, max_rooms=3))


@functools.cache
def guarded_server():
    return _start(settings(room_secret=SECRET))


def weights(seed: int, n: int = 52) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, n).astype(np.float32)


async def frames_until(client, want: dict[str, int], timeout: float = 20.0) -> dict[str, list[Frame]]:
    """Read frames until `want[member]` frames of each member arrived."""
    got: dict[str, list[Frame]] = {}
    deadline = time.monotonic() + timeout
    while any(len(got.get(m, [])) < n for m, n in want.items()):
        f = await client.recv_frame(timeout=max(0.1, deadline - time.monotonic()))
        got.setdefault(f.member, []).append(f)
    return got


def test_two_publishers_and_a_watcher_meet_and_a_leave_arrives_within_3_s() -> None:
    server = room_server()

    async def main() -> None:
        a = await connect(server.url, room="meet", avatar=SMALL, encoding="f32")
        b = await connect(server.url, room="meet", avatar=SMALL, encoding="q13", layout="ovr63")
        w = await watch(server.url, "meet", encoding="f32")
        assert len({a.member, b.member, w.member}) == 3 and a.room == w.room == "meet"
        assert a.welcome.avatar.id == SMALL and w.welcome.avatar is None
        sent_a, sent_b = weights(1), weights(2, 63)

        async def publish(c, w8: np.ndarray) -> None:
            for _ in range(40):
                await c.send_bs(w8)
                await asyncio.sleep(1 / 72)

        pubs = asyncio.gather(publish(a, sent_a), publish(b, sent_b))
        got_w, got_a, got_b = await asyncio.gather(frames_until(w, {a.member: 5, b.member: 5}),
                                                   frames_until(a, {b.member: 5}), frames_until(b, {a.member: 5}))
        await pubs
        assert set(got_a) == {b.member} and set(got_b) == {a.member}  # nobody sees itself (no self view)
        assert set(got_w) == {a.member, b.member}
        # the watcher's f32 frames of A are the offline pipeline's, bit for bit
        s = server.settings
        state, _ = offline_pipeline(SMALL, "arkit52", sent_a, settings=s)
        f = got_w[a.member][-1]
        assert f.position.tobytes() == state.position.astype(np.float32).tobytes()
        assert f.rotation.tobytes() == state.rotation.astype(np.float32).tobytes()
        assert f.scale.tobytes() == state.scale.astype(np.float32).tobytes()
        assert got_a[b.member][-1].n == w.members[b.member].join.avatar.count
        # who is there: each saw a join for both others (the watcher's with publish false)
        assert {j.member for j in a.joins} == {b.member, w.member}
        assert [j.publish for j in a.joins if j.member == w.member] == [False]

        t0 = time.monotonic()
        await a.ws.send(a.conn.bye())  # the leaver says bye

        async def leave_of(c) -> float:
            while not any(lv.member == a.member for lv in c.leaves):
                await c.recv(timeout=3)
            return time.monotonic() - t0

        late_w, late_b = await asyncio.gather(leave_of(w), leave_of(b))
        assert late_w < 3 and late_b < 3
        assert [lv.reason for lv in w.leaves] == ["bye"] and a.member not in w.members
        await a.ws.close()
        for c in (b, w):
            await c.close()

    run(main())


def test_a_member_that_stopped_reading_still_leaves_within_3_s_of_its_bye() -> None:
    """Its socket is full of another member's frames (5 MB f32 frames of the default avatar, a client that reads
    nothing): closing it waits for that client, its leave must not."""
    server = room_server()

    async def main() -> None:
        import websockets

        stalled = await connect(server.url, room="stall", avatar=SMALL, encoding="f32", max_queue=1)
        publisher = await connect(server.url, room="stall", avatar="default", encoding="f16")
        w = await watch(server.url, "stall", encoding="f16", max_gaussians=1000)
        for _ in range(30):  # the stalled member never reads: its socket fills with the publisher's frames
            await publisher.send_bs(weights(4))
            await stalled.send_bs(weights(5))
            await asyncio.sleep(1 / 72)
        await asyncio.sleep(1.0)
        t0 = time.monotonic()
        await stalled.ws.send(stalled.conn.bye())
        while not any(lv.member == stalled.member for lv in w.leaves):
            await w.recv(timeout=3)
        assert time.monotonic() - t0 < 3
        assert [lv.reason for lv in w.leaves if lv.member == stalled.member] == ["bye"]
        stalled.ws.transport.abort()
        with contextlib.suppress(websockets.ConnectionClosed):
            await stalled.ws.wait_closed()
        for c in (publisher, w):
            await c.close()

    run(main())


def test_self_view_sends_ones_own_frames_with_ones_member_id() -> None:
    server = room_server()

    async def main() -> None:
        me = await connect(server.url, room="mirror", avatar=SMALL, self_view=True, encoding="f16", sparse=True,
                           max_gaussians=1000)
        await me.send_bs(weights(3))
        got = await frames_until(me, {me.member: 1})
        f = got[me.member][0]
        join = me.members[me.member].join
        assert f.index is not None and join.avatar.id == SMALL  # sparse, per member
        assert join.avatar.count <= 1000 and join.avatar.count == me.welcome.avatar.count  # reduced for this viewer
        assert me.members[me.member].avatar.count == join.avatar.count
        await me.close()

    run(main())


def test_limits_and_names_refuse_with_clear_errors() -> None:
    server = room_server()

    async def main() -> None:
        with pytest.raises(ServerError) as bad:
            await connect(server.url, room="no spaces", avatar=SMALL)
        assert bad.value.code == "bad_field" and "room" in bad.value.message and bad.value.close_code == 4002
        members = [await watch(server.url, "full") for _ in range(3)]
        with pytest.raises(ServerError) as full:
            await watch(server.url, "full")
        assert full.value.code == "room_full" and full.value.close_code == 4014 and "3 members" in full.value.message
        others = [await watch(server.url, f"r{i}") for i in range(2)]  # rooms: full, r0, r1 = 3
        with pytest.raises(ServerError) as many:
            await watch(server.url, "r2")
        assert many.value.code == "too_many_rooms" and many.value.close_code == 4015
        for c in members + others:
            await c.close()
        assert metric(server, "ofera_room_events_total", 'event="refused"') >= 2

    run(main())


def test_room_tokens_are_the_rooms_hmac() -> None:
    server = guarded_server()

    async def main() -> None:
        for token in (None, room_token(SECRET, "other")):
            with pytest.raises(ServerError) as refused:
                await watch(server.url, "lab", room_token=token)
            assert refused.value.code == "unauthorized" and refused.value.close_code == 1008
        c = await watch(server.url, "lab", room_token=room_token(SECRET, "lab"))
        assert c.member is not None
        await c.close()
        v1 = await connect(server.url, avatar=SMALL)  # a v1 session needs no room token
        await v1.close()

    run(main())


def test_a_v1_client_sees_no_change() -> None:
    server = room_server()

    async def main() -> None:
        import websockets

        raw: list[bytes] = []
        async with websockets.connect(server.url, compression=None, max_size=None) as ws:
            conn = ClientConnection()
            await ws.send(conn.hello("arkit52", SMALL, encoding="q13", sparse=True))
            while conn.avatar is None:
                data = await ws.recv()
                raw.append(data)
                conn.receive(data)
            await ws.send(conn.bs(0, 123, weights(5)))
            data = await ws.recv()
            raw.append(data)
            msg = conn.receive(data)
        assert isinstance(msg, Frame) and msg.member is None and msg.seq == 0 and msg.t == 123
        maps = [msgpack.unpackb(d, raw=False) for d in raw]
        assert maps[0]["type"] == "welcome" and "room" not in maps[0] and "member" not in maps[0]
        assert all("member" not in m for m in maps)
        assert {m["type"] for m in maps} == {"welcome", "avatar", "frame"}

    run(main())


def _log(path: Path, seconds: float, seed: int) -> Path:
    lay = get_layout("arkit52")
    n = int(seconds * 60)
    t = np.arange(n) / 60.0
    w = (0.5 + 0.4 * np.sin(t[:, None] * 3 + np.random.default_rng(seed).uniform(0, 6, 52))).astype(np.float32)
    write_facelog(path, FaceLog(times=t, weights=w, layout=lay))
    return path


def test_replays_into_one_room_are_people_meeting(tmp_path: Path) -> None:
    """Two logs replayed into one room (`replay_through`, what `ofera replay LOG --room` runs, on a thread) while
    `ofera replay --room party --watch` watches: everyone sees the others."""
    from ofera.replay import LinkOptions, Replayer, replay_through
    from ofera.sources import read_facelog

    server = room_server()
    logs = [read_facelog(_log(tmp_path / f"p{i}.csv", 2.0, i)) for i in range(2)]
    published: list = []

    async def publishers() -> None:
        await asyncio.sleep(1.0)  # the watcher is there first
        opts = LinkOptions(layout="arkit52", avatar=SMALL, room="party")
        published.extend(await asyncio.gather(*(replay_through(Replayer(log), server.url, opts) for log in logs)))

    thread = threading.Thread(target=lambda: asyncio.run(publishers()))
    thread.start()
    out = tmp_path / "watch.json"
    res = CliRunner().invoke(app, ["replay", "--url", server.url, "--room", "party", "--watch", "--seconds", "5",
                                   "--json", str(out), "--quiet"])
    thread.join(60)
    assert res.exit_code == 0, res.output
    watched = json.loads(out.read_text())
    assert len(watched["members"]) == 2 and all(m["received"] > 20 for m in watched["members"].values())
    assert len(watched["joined"]) == 2 and sorted(r for _, r in watched["left"]) == ["bye", "bye"]
    p0, p1 = (s.summary() for s in published)
    assert p0["fatal_error"] is None and p0["sent"] > 100 and len(p0["members"]) == 1 and len(p1["members"]) == 1
    assert set(p0["members"]) | set(p1["members"]) == set(watched["members"])


def test_watch_needs_a_room() -> None:
    res = CliRunner().invoke(app, ["replay", "--watch", "--seconds", "1"])
    assert res.exit_code == 2 and "--room" in res.output


def test_join_and_leave_decode_in_the_client() -> None:
    """The client state machine: a join then the avatar with member, a frame, a leave (the golden vectors')."""
    conn = ClientConnection()
    conn.hello("arkit52", room="lab-1", publish=False)
    from ofera_protocol import AvatarInfo, Welcome, encode

    conn.receive(encode(Welcome(session="s", avatar=None, layout="arkit52", room="lab-1", member="m-me")))
    conn.receive(encode(Join(member="m-x", avatar=AvatarInfo("default", 4, 1))))
    data = (Path(__file__).resolve().parents[1] / "protocol" / "vectors" / "avatar_member.msgpack").read_bytes()
    other = msgpack.unpackb(data, raw=False)["member"]
    conn.receive(encode(Join(member=other, avatar=AvatarInfo("default", 4, 1))))
    conn.receive(data)
    assert other in conn.formats and "m-x" not in conn.formats
    conn.receive(encode(Leave(member=other, reason="bye")))
    assert other not in conn.members and other not in conn.formats
