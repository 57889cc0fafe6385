"""Expression streaming through a real server (PROTOCOL.md 13): a params session of the Python client reconstructs
what an f32 session of the same server receives for the same bs, every frame of the real capture in
../shared/data included, from at most 300 B per frame after the handshake; coords, max_gaussians, the refusal of
an ARKit-driven avatar; and the writer's stamping and checks."""

from __future__ import annotations

import time

import lam_fixtures as L
import numpy as np
import pytest
from conftest import SHARED_DATA
from ofera.client import ServerError, connect
from ofera.streaming.params import ParamsWriter
from ofera.streaming.server import ServerThread
from ofera_protocol.codec import decode_server_message
from ofera_protocol.messages import ParamsFormat, ParamsFrame
from test_server_support import SMALL, make_small_avatar, private_cache, run, settings

CAPTURE = SHARED_DATA / "livelink_dao.gesichter"
TOLERANCE_M = 5e-5  # the 0.05 mm
pytestmark = pytest.mark.timeout(900)


@pytest.fixture(scope="module")
def server():
    """The built-in default avatar (`default`, 115,600 Gaussians), the small one, and a LAM zip (`face`)."""
    with private_cache("ofera-params-") as root:
        avatars = root / "avatars"
        make_small_avatar(avatars / f"{SMALL}.npz")
        L.make_zip(avatars / "face.zip")
        srv = ServerThread(settings(avatars=avatars, default_avatar="default")).start()
        try:
            yield srv
        finally:
            srv.stop()


def rotation_error(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.minimum(np.abs(a - b).max(axis=1), np.abs(a + b).max(axis=1)).max())


async def compare(url: str, weights: np.ndarray, layout: str, **hello) -> dict:
    """One params session (the client deforms) and one f32 session of the same avatar, fed the same bs one at a time:
    the largest differences over every Gaussian and frame, and the params frames' sizes."""
    p = await connect(url, layout=layout, encoding="params", track=True, **hello)
    f = await connect(url, layout=layout, encoding="f32", **hello)
    try:
        assert p.welcome.encoding == "params" and p.count == f.count and p.conn.rig is not None
        worst = {"position": 0.0, "rotation": 0.0, "scale": 0.0}
        sizes, stamped = [], []
        start = time.monotonic()
        for i, w in enumerate(weights):
            await p.send_bs(w, seq=i, t=1000 + i)
            await f.send_bs(w, seq=i, t=1000 + i)
            pf, ff = await p.recv_frame(60), await f.recv_frame(60)
            assert isinstance(pf, ParamsFrame) and ff.seq == i
            assert pf.seq in (None, i)
            stamped.append(pf.seq is not None)
            sizes.append(p.last_bytes)
            g = p.gaussians
            worst["position"] = max(worst["position"], float(np.abs(g.position - ff.position).max()))
            worst["rotation"] = max(worst["rotation"], rotation_error(g.rotation, ff.rotation))
            worst["scale"] = max(worst["scale"], float((np.abs(g.scale - ff.scale) / ff.scale).max()))
        return {**worst, "sizes": np.array(sizes), "stamped": np.array(stamped), "seconds": time.monotonic() - start}
    finally:
        await p.close()
        await f.close()


def capture_weights() -> np.ndarray:
    from ofera.sources import read_gesichter

    return read_gesichter(CAPTURE).weights


@pytest.mark.skipif(not CAPTURE.is_file(), reason=f"{CAPTURE} is absent (real capture: ../shared/data)")
def test_every_frame_of_the_real_capture(server):
    """The done-when: the built-in avatar through `ofera serve`, all 180 frames of the Live Link capture."""
    weights = capture_weights()
    r = run(compare(server.url, weights, "livelink61"))
    assert len(r["sizes"]) == len(weights) == 180
    assert r["position"] < TOLERANCE_M, r["position"]
    assert r["rotation"] < 5e-3 and r["scale"] < 5e-3, r
    sizes, stamped = r["sizes"], r["stamped"]
    assert stamped[0] and stamped.sum() <= 2 + r["seconds"]  # the first, then once per second (STAMP_INTERVAL_S)
    assert (sizes[~stamped] == 294).all() and sizes[stamped].max() < 400
    at_72hz = (71 * 294 + sizes[stamped].max()) / 72  # a second of frames at 72 Hz: one stamped
    assert at_72hz <= 300, at_72hz


def test_small_avatar_unity_coords_and_reduction(server):
    rng = np.random.default_rng(5)
    weights = rng.uniform(0, 1, (6, 52)).astype(np.float32)
    for hello in ({"avatar": SMALL, "coords": "unity"}, {"avatar": "default", "max_gaussians": 20_000}):
        r = run(compare(server.url, weights, "arkit52", **hello))
        assert r["position"] < 1e-5 and r["rotation"] < 5e-3, (hello, r)


def test_rig_size_in_welcome_matches_the_rig(server):
    async def main():
        c = await connect(server.url, layout="arkit52", avatar=SMALL, encoding="params")
        try:
            return c.welcome, c.conn.rig
        finally:
            await c.close()

    welcome, rig = run(main())
    assert welcome.sparse is False and welcome.delta is False
    assert rig.count == welcome.avatar.count and 0 < rig.gaussians <= rig.count
    from ofera_protocol.rig import encode_rig

    assert welcome.rig_bytes == len(encode_rig(rig))  # announced by the server (PROTOCOL.md 13.1)


def test_arkit_avatar_is_refused_clearly(server):
    async def main():
        await connect(server.url, layout="arkit52", avatar="face", encoding="params")

    with pytest.raises(ServerError) as e:
        run(main())
    assert e.value.code == "unknown_encoding" and "params needs a FLAME-driven avatar" in e.value.message

    async def first_message() -> object:  # refused before welcome: no avatar is sent for nothing
        import websockets
        from ofera_protocol import ClientConnection

        conn = ClientConnection()
        async with websockets.connect(server.url, max_size=None) as ws:
            await ws.send(conn.hello("arkit52", "face", encoding="params"))
            return decode_server_message(await ws.recv())

    first = run(first_message())
    assert type(first).__name__ == "ErrorMessage" and first.code == "unknown_encoding"


# ----------------------------------------------------------------------------- the writer


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_writer_stamps_once_per_interval_per_member():
    clock = Clock()
    w = ParamsWriter(stamp_interval=1.0, clock=clock)
    y = np.linspace(-1, 1, 68, dtype=np.float32)
    timing = {"total": 5}
    frames = []
    for i in range(5):
        frames.append(w.encode_values(i, 10 * i, timing, y, None))
        clock.now += 0.3
    decoded = [decode_server_message(b, ParamsFormat()) for b in frames]
    assert [d.seq for d in decoded] == [0, None, None, None, 4]
    assert decoded[0].timing == timing and decoded[1].timing is None
    assert [len(b) for b in frames[1:4]] == [294] * 3
    np.testing.assert_array_equal(decoded[2].params, y)
    m = decode_server_message(w.encode_values(5, 50, timing, y, "m-1"), ParamsFormat())
    assert m.member == "m-1" and m.seq == 5  # another member's first frame is stamped


@pytest.mark.parametrize("values", [np.zeros(67, np.float32), np.full(68, np.nan, np.float32)])
def test_writer_refuses_bad_values(values):
    with pytest.raises(ValueError, match="68 finite"):
        ParamsWriter().encode_values(0, 0, {}, values, None)


# ----------------------------------------------------------------------------- rooms


def test_room_viewer_in_params_mode(server):
    """A params viewer of a room (PROTOCOL.md 13.6) receives the publisher's rig after its join and avatar, then its
    params frames, and reconstructs what an f32 viewer of the same room receives."""
    from ofera.client import watch

    room = "params-room"
    rng = np.random.default_rng(9)
    weights = rng.uniform(0, 1, (5, 52)).astype(np.float32)

    async def main():
        publisher = await connect(server.url, layout="arkit52", avatar=SMALL, encoding="f16", room=room)
        p = await watch(server.url, room, encoding="params", track=True)
        f = await watch(server.url, room, encoding="f32")
        worst = 0.0
        try:
            for c in (p, f):  # the publisher's join, avatar (and rig) first: frames before them are dropped
                while publisher.member not in c.conn.formats:
                    await c.recv(60)
            for i, w in enumerate(weights):
                await publisher.send_bs(w, seq=i, t=1000 + i)
                pf = await p.recv_frame(60)
                ff = await f.recv_frame(60)
                assert isinstance(pf, ParamsFrame) and pf.member == publisher.member == ff.member and ff.seq == i
                member = p.conn.members[publisher.member]
                assert member.rig is not None and member.rig.count == ff.n
                worst = max(worst, float(np.abs(member.gaussians.position - ff.position).max()))
            return worst
        finally:
            for c in (publisher, p, f):
                await c.close()

    assert run(main()) < 1e-5
