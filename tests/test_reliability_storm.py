"""Connection storms and faults: ~200 connect/disconnect cycles of every kind (clean bye, close without
hello, TCP reset right after the welcome, i.e. in the middle of the avatar transfer, reset while frames
stream, vanishing without a WebSocket close, half-sent HTTP upgrade), sequential and concurrent. Afterwards
nothing is left: no session (hub and metrics gauge), no connection, asyncio tasks back to the baseline, and
a new session works; against a server in its own process, its RSS does not grow. The heavy version is
benchmarks/storm.py.
"""

from __future__ import annotations

import asyncio
import random
import threading

from test_reliability_support import (
    FRAME_F32_BYTES,
    KINDS,
    bs,
    cycle,
    health,
    open_streaming,
    rel_server,
    rel_server_process,
    rss_mb,
    task_count,
    unpack,
    wait_idle,
    wait_idle_process,
    wait_until,
)
from test_server_support import metric, run

CYCLES = 200


def storm(server, cycles: int, seed: int) -> list[str]:
    """`cycles` cycles of every kind in turn, shuffled: half one after another, half 8 at a time. Returns the kinds."""
    rng = random.Random(seed)
    kinds = [KINDS[i % len(KINDS)] for i in range(cycles)]
    rng.shuffle(kinds)
    for kind in kinds[: cycles // 2]:  # sequential
        cycle(server, kind, rng)

    errors: list[BaseException] = []

    def worker(part: list[str], seed: int) -> None:
        r = random.Random(seed)
        try:
            for kind in part:
                cycle(server, kind, r)
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    rest = kinds[cycles // 2:]
    threads = [threading.Thread(target=worker, args=(rest[i::8], i)) for i in range(8)]  # 8 at a time
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    return kinds


def test_connection_storm_leaves_nothing_behind() -> None:
    server = rel_server()
    assert wait_idle(server)
    hub = server.app.state.hub
    tasks0 = task_count(server)
    storm(server, CYCLES, 9)

    assert wait_idle(server, 20), (hub.active, list(hub.sessions), len(server.server.connections()))
    assert metric(server, "ofera_sessions", 'role="source"') == 0
    assert metric(server, "ofera_sessions", 'role="viewer"') == 0
    assert wait_until(lambda: task_count(server) <= tasks0, 10), (task_count(server), tasks0)
    assert health(server)["sessions"] == 0

    async def good() -> None:
        ws, _ = await open_streaming(server.url)
        async with ws:
            await ws.send(bs(5))
            assert unpack(await asyncio.wait_for(ws.recv(), 10))["seq"] == 5

    run(good())


def test_storm_does_not_grow_the_server_process() -> None:
    """The server in its own process (clients here): after a warm-up storm (first-use allocations), 3 x CYCLES
    more cycles leave its RSS within half of what the sessions that computed a frame (kinds `bye` and
    `reset_streaming`) would keep if each leaked no more than that frame's float32 state."""
    server = rel_server_process()
    storm(server, CYCLES, 1)  # warm-up
    assert wait_idle_process(server)
    tasks0 = health(server)["tasks"]
    rss0 = rss_mb(server.pid)
    kinds = storm(server, 3 * CYCLES, 2)
    assert wait_idle_process(server, 20), health(server)
    assert wait_until(lambda: health(server)["tasks"] <= tasks0, 10), (health(server), tasks0)
    computed = sum(k in ("bye", "reset_streaming") for k in kinds)
    bound = 0.5 * computed * FRAME_F32_BYTES / 2**20
    growth = rss_mb(server.pid) - rss0
    print(f"server RSS growth {growth:.2f} MB, bound {bound:.1f} MB")
    assert growth < bound, f"the server's RSS grew {growth:.1f} MB over {len(kinds)} cycles (bound {bound:.1f} MB)"


def test_sessions_are_freed_without_the_cycle_collector() -> None:
    """A finished session's source, viewer and pipeline (MBs of buffers each) are freed by reference counting
    alone: a reference cycle would keep them until the next full garbage collection, rare in a long-running
    server, so memory would grow with every session (benchmarks/soak.py showed it)."""
    import gc
    import weakref

    server = rel_server()
    assert wait_idle(server)
    hub = server.app.state.hub
    refs: list = []

    async def session(kind: str) -> None:
        ws, _ = await open_streaming(server.url)
        async with ws:
            for i in range(3):
                await ws.send(bs(i))
                assert unpack(await ws.recv())["type"] == "frame"
            s = next(iter(hub.sessions.values()))
            refs.extend(weakref.ref(x) for x in (s, s.source, s.viewer, s.source.pipeline))
            if kind == "bye":
                await ws.send(b"\x81\xa4type\xa3bye")
            elif kind == "fatal":
                await ws.send("text")
            await ws.wait_closed() if kind != "close" else None

    gc.collect()
    gc.disable()
    try:
        for kind in ("bye", "close", "fatal"):
            run(session(kind))
            assert wait_idle(server)
            assert wait_until(lambda: all(r() is None for r in refs), 5), \
                (kind, [type(r()).__name__ for r in refs if r() is not None])
            refs.clear()
    finally:
        gc.enable()
