"""The streaming server on a real socket, driven by the Python client library: bit-exactness against the
offline pipeline, encodings, coordinates, sparse and reduced avatars, device BDA profiles, concurrency,
newest-wins backpressure, HTTP endpoints, TCP_NODELAY, shutdown."""

from __future__ import annotations

import asyncio
import socket

import httpx
import numpy as np
import pytest
from ofera.client import ServerError, connect
from ofera.streaming import offline_pipeline
from ofera.streaming.server import ServerThread, StreamingWebSocketProtocol
from ofera_protocol import LAYOUTS
from ofera_protocol.encodings import position_error_bound
from test_server_support import DEVICE, SMALL, main_server, metric, run, settings

RNG = np.random.default_rng(11)


def weights(layout: str = "arkit52", seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, LAYOUTS[layout]).astype(np.float32)


async def one_frame(url: str, w: np.ndarray, **hello):
    async with await connect(url, **hello) as c:
        await c.send_bs(w)
        return c, await c.recv_frame(timeout=30)


def test_frame_is_bit_exact_with_offline_pipeline() -> None:
    server = main_server()
    w = weights(seed=1)
    client, frame = run(one_frame(server.url, w))
    state, timings = offline_pipeline("default", "arkit52", w, settings=settings())
    assert client.welcome.avatar.id == SMALL and frame.n == state.count == client.count
    assert frame.position.tobytes() == state.position.tobytes()
    assert frame.rotation.tobytes() == state.rotation.tobytes()
    assert frame.scale.tobytes() == state.scale.tobytes()
    assert set(timings) == {"layout", "bda", "epm", "head", "deform"}
    assert {"decode", "queue", "map", "epm", "head", "deform", "encode", "total"} <= set(frame.timing)
    # the avatar message is the neutral avatar
    from ofera.streaming.registry import registry_for

    neutral = registry_for(settings()).get(SMALL).avatar.neutral()
    assert client.avatar.position.tobytes() == neutral.position.tobytes()


def test_other_layouts_and_device_profile() -> None:
    server = main_server()
    s = settings()
    for layout in ("ovr63", "mediapipe52", "livelink61"):
        w = weights(layout, seed=2)
        _, frame = run(one_frame(server.url, w, layout=layout))
        assert frame.position.tobytes() == offline_pipeline(SMALL, layout, w, settings=s)[0].position.tobytes()
    w = weights(seed=3)
    _, frame = run(one_frame(server.url, w, device=DEVICE))
    with_profile = offline_pipeline(SMALL, "arkit52", w, settings=s, device=DEVICE)[0].position
    without = offline_pipeline(SMALL, "arkit52", w, settings=s)[0].position
    assert frame.position.tobytes() == with_profile.tobytes()
    assert not np.array_equal(with_profile, without)
    # an unknown device falls back to the avatar's default alignment, without an error
    _, frame = run(one_frame(server.url, w, device="no-such-headset"))
    assert frame.position.tobytes() == without.tobytes()


def test_unity_coords_mirror_x() -> None:
    server = main_server()
    w = weights(seed=4)
    flame_client, f = run(one_frame(server.url, w))
    unity_client, u = run(one_frame(server.url, w, coords="unity"))
    np.testing.assert_array_equal(u.position, f.position * np.float32([-1, 1, 1]))
    np.testing.assert_array_equal(u.rotation, f.rotation * np.float32([1, -1, -1, 1]))
    np.testing.assert_array_equal(u.scale, f.scale)
    np.testing.assert_array_equal(unity_client.avatar.position, flame_client.avatar.position * np.float32([-1, 1, 1]))
    np.testing.assert_array_equal(unity_client.avatar.sh[:, 0], flame_client.avatar.sh[:, 0])
    np.testing.assert_array_equal(unity_client.avatar.sh[:, 3], -flame_client.avatar.sh[:, 3])


@pytest.mark.parametrize("encoding", ["f16", "q13"])
def test_compact_encodings_decode_close_to_f32(encoding: str) -> None:
    server = main_server()
    w = weights(seed=5)
    _, f = run(one_frame(server.url, w))
    c, q = run(one_frame(server.url, w, encoding=encoding))
    assert c.welcome.encoding == encoding and (c.welcome.quant is not None) == (encoding == "q13")
    bound = position_error_bound(encoding, c.welcome.quant, float(np.abs(f.position).max()))
    assert np.abs(q.position - f.position).max() <= np.max(bound) * 1.01
    dots = np.abs(np.sum(q.rotation * f.rotation, axis=1))
    assert dots.min() > 0.999


def test_sparse_frames_carry_the_movable_gaussians() -> None:
    server = main_server()
    w = weights(seed=6)
    _, dense = run(one_frame(server.url, w))
    c, sparse = run(one_frame(server.url, w, sparse=True))
    from ofera.streaming.registry import registry_for

    movable = registry_for(settings()).get(SMALL).avatar.movable
    assert c.welcome.sparse and sparse.index is not None
    np.testing.assert_array_equal(sparse.index, np.flatnonzero(movable))
    assert 0 < sparse.n < c.count
    np.testing.assert_array_equal(sparse.position, dense.position[sparse.index])
    # the Gaussians not carried keep their neutral values: the dense frame agrees up to float rounding
    still = ~movable
    np.testing.assert_allclose(c.avatar.position[still], dense.position[still], rtol=0, atol=1e-6)


def test_max_gaussians_streams_a_spread_subset() -> None:
    server = main_server()
    w = weights(seed=7)
    _, dense = run(one_frame(server.url, w))
    c, small = run(one_frame(server.url, w, max_gaussians=500))
    assert c.count == 500 == small.n == c.avatar.count
    from ofera.streaming.registry import registry_for

    assets = registry_for(settings()).get(SMALL)
    keep, opacity = assets.subset(500), assets.avatar.opacity
    assert len(np.unique(keep)) == 500 and np.all(np.diff(keep) > 0)
    np.testing.assert_array_equal(c.avatar.opacity, opacity[keep])
    np.testing.assert_array_equal(small.position, dense.position[keep])
    # spread over the head, not only the most opaque (eyes): the subset spans most of the avatar's extent
    span = np.ptp(small.position, axis=0) / np.ptp(dense.position, axis=0)
    assert (span > 0.8).all()


def test_two_concurrent_sessions() -> None:
    server = main_server()
    s = settings()

    async def session(layout: str, seed: int) -> tuple[str, list]:
        ws = [weights(layout, seed + i) for i in range(20)]
        async with await connect(server.url, layout=layout) as c:
            frames = []
            for w in ws:
                await c.send_bs(w)
                frames.append(await c.recv_frame(timeout=30))
                await asyncio.sleep(1 / 72)
            return c.session, [(f, ws[f.seq]) for f in frames]

    async def main():
        return await asyncio.gather(session("arkit52", 100), session("ovr63", 200))

    (sa, fa), (sb, fb) = run(main())
    assert sa != sb
    for layout, frames in (("arkit52", fa), ("ovr63", fb)):
        assert [f.seq for f, _ in frames] == list(range(20))
        for f, w in frames[::7]:
            assert f.position.tobytes() == offline_pipeline(SMALL, layout, w, settings=s)[0].position.tobytes()


def test_newest_wins_under_a_burst() -> None:
    server = main_server()
    before = metric(server, "ofera_frames_skipped_total", 'stage="bs"')

    async def main() -> list:
        async with await connect(server.url) as c:
            for seq in range(50):
                await c.send_bs(weights(seed=seq), seq=seq)
            frames = []
            while not frames or frames[-1].seq != 49:
                frames.append(await c.recv_frame(timeout=30))
            return frames

    frames = run(main())
    seqs = [f.seq for f in frames]
    assert seqs == sorted(set(seqs)) and seqs[-1] == 49
    assert len(frames) < 50
    assert metric(server, "ofera_frames_skipped_total", 'stage="bs"') >= before + (50 - len(frames))


def test_slow_client_does_not_slow_another() -> None:
    server = main_server()

    async def main() -> None:
        slow = await connect(server.url)
        fast = await connect(server.url)
        try:
            for seq in range(150):  # the slow client sends but does not read
                await slow.send_bs(weights(seed=seq), seq=seq)
                if seq % 5 == 0:
                    await fast.send_bs(weights(seed=seq))
                    await fast.recv_frame(timeout=10)
                await asyncio.sleep(0.005)
            frames = []  # the slow client's newest frame still arrives, in order
            while not frames or frames[-1].seq != 149:
                frames.append(await slow.recv_frame(timeout=30))
            seqs = [f.seq for f in frames]
            assert seqs == sorted(set(seqs))
        finally:
            await slow.close()
            await fast.close()

    run(main())


def test_http_endpoints() -> None:
    server = main_server()
    h = httpx.get(f"{server.http_url}/healthz", timeout=10)
    assert h.status_code == 200 and h.json()["status"] == "ok"
    a = httpx.get(f"{server.http_url}/v1/avatars", timeout=10).json()
    ids = {x["id"]: x for x in a["avatars"]}
    assert {"default", SMALL, "broken"} <= set(ids) and a["default"] == SMALL
    assert ids[SMALL]["loaded"] and ids[SMALL]["count"] > 0
    assert a["devices"] == [DEVICE] and "arkit52" in a["layouts"] and "q13" in a["encodings"]
    run(one_frame(server.url, weights()))
    m = httpx.get(f"{server.http_url}/metrics", timeout=10)
    assert m.status_code == 200 and m.headers["content-type"].startswith("text/plain")
    for name in ("ofera_sessions", "ofera_bs_received_total", "ofera_frames_sent_total",
                 "ofera_frames_skipped_total", "ofera_stage_seconds_bucket", "ofera_server_latency_seconds"):
        assert name in m.text, name
    assert metric(server, "ofera_frames_sent_total") >= 1
    assert metric(server, "ofera_stage_seconds_count", 'stage="epm"') >= 1


def test_tcp_nodelay_on_accepted_sockets() -> None:
    server = main_server()

    async def main() -> None:
        async with await connect(server.url) as c:
            await c.send_bs(weights())
            await c.recv_frame(timeout=30)
            ws_conns = [p for p in server.server.connections() if isinstance(p, StreamingWebSocketProtocol)]
            assert ws_conns
            for p in ws_conns:  # getsockopt on the server's accepted socket
                sock = p.transport.get_extra_info("socket")
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
                assert p.nodelay()

    run(main())


def test_streaming_sockets_get_a_congestion_control_that_does_not_pace() -> None:
    """Settings.tcp_congestion (cubic, else reno) on each accepted socket, whatever the system's default (BBR
    on the machine where its pacing held frames back by 10 ms); empty: the system's own."""
    if not hasattr(socket, "TCP_CONGESTION"):
        pytest.skip("TCP_CONGESTION is Linux only")
    with open("/proc/sys/net/ipv4/tcp_congestion_control") as f:
        system = f.read().strip()

    async def names(server: ServerThread) -> list[str | None]:
        async with await connect(server.url) as c:
            await c.send_bs(weights())
            await c.recv_frame(timeout=30)
            return [p.congestion() for p in server.server.connections() if isinstance(p, StreamingWebSocketProtocol)]

    got = run(names(main_server()))
    assert got and all(name in ("cubic", "reno") for name in got), got
    with ServerThread(settings(tcp_congestion="")) as server:
        assert run(names(server)) == [system]


def test_shutdown_closes_sessions_with_1001() -> None:
    server = ServerThread(settings(warmup=False)).start()

    async def main() -> None:
        c = await connect(server.url)
        await c.send_bs(weights())
        await c.recv_frame(timeout=30)
        await asyncio.get_running_loop().run_in_executor(None, server.stop)
        with pytest.raises(ServerError) as e:
            await c.recv_frame(timeout=10)
        assert e.value.close_code == 1001
        await c.close()

    try:
        run(main())
    finally:
        server.stop()


def test_fast_path_matches_the_reference_pipeline() -> None:
    w = weights(seed=8)
    fast, t_fast = offline_pipeline(SMALL, "arkit52", w, settings=settings())
    ref, t_ref = offline_pipeline(SMALL, "arkit52", w, settings=settings(fast=False))
    assert set(t_fast) == set(t_ref)
    np.testing.assert_allclose(fast.position, ref.position, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.abs(np.sum(fast.rotation * ref.rotation, axis=1)), 1.0, atol=1e-5)
    np.testing.assert_allclose(fast.scale, ref.scale, rtol=1e-5)
