"""Source / viewer roles without a socket: newest-wins slots, and one computed frame fanned out to viewers
(encoded once per wire format), as rooms will need."""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
from ofera.streaming import roles
from ofera.streaming.metrics import Metrics
from ofera.streaming.roles import CodecWriter, LatestSlot, PendingBs, Source, Viewer
from ofera_protocol import Blendshapes, FrameFormat, decode_server_message
from test_server_support import run

N = 5


class FakePipeline:
    """Stands in for Pipeline: position x = the first weight; blocks while `gate` is clear."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.gate.set()
        self.seen: list[float] = []

    def run(self, w):
        self.gate.wait(10)
        self.seen.append(float(w[0]))
        pos = np.full((N, 3), w[0], np.float32)
        rot = np.tile(np.float32([0, 0, 0, 1]), (N, 1))
        return SimpleNamespace(position=pos, rotation=rot, scale=np.full((N, 3), 0.01, np.float32)), {"epm": 1}


async def until(cond, timeout: float = 10.0) -> None:
    async def poll() -> None:
        while not cond():
            await asyncio.sleep(0.005)

    await asyncio.wait_for(poll(), timeout)


def pending(seq: int) -> PendingBs:
    return PendingBs(Blendshapes(seq=seq, t=seq * 10, w=np.full(52, seq, np.float32)), 0, 0)


def test_latest_slot_keeps_only_the_newest() -> None:
    async def main() -> None:
        slot: LatestSlot[int] = LatestSlot()
        assert slot.put(1) is False and slot.put(2) is True
        assert await slot.get() == 2
        waiter = asyncio.create_task(slot.get())
        await asyncio.sleep(0)
        slot.put(3)
        assert await asyncio.wait_for(waiter, 1) == 3

    run(main())


def test_source_computes_only_the_newest_and_fans_out_encoded_once() -> None:
    metrics = Metrics()
    fmt = FrameFormat("f32", N)

    async def main() -> None:
        with ThreadPoolExecutor(2) as pool:
            pipeline = FakePipeline()
            source = Source(pipeline, pool, metrics)
            sent: dict[str, list[bytes]] = {"a": [], "b": []}

            def sender(name: str):
                async def send(data: bytes) -> None:
                    sent[name].append(data)
                return send

            viewers = [Viewer(sender(n), CodecWriter(fmt), ("f32", "flame", False, None), pool, metrics)
                       for n in ("a", "b")]
            for v in viewers:
                source.subscribers.append(v.offer)
            tasks = [asyncio.create_task(x.run()) for x in (source, *viewers)]

            pipeline.gate.clear()  # the pipeline is busy with bs 0 while 1..9 arrive
            source.offer(pending(0))
            await asyncio.sleep(0.05)
            for seq in range(1, 10):
                source.offer(pending(seq))
            pipeline.gate.set()
            await until(lambda: all(sent[n] and decode_server_message(sent[n][-1], fmt).seq == 9 for n in sent))
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

            assert pipeline.seen == [0.0, 9.0]  # 1..8 were replaced before being computed
            assert source.skipped == 8
            for name in ("a", "b"):
                frames = [decode_server_message(d, fmt) for d in sent[name]]
                assert [f.seq for f in frames] == [0, 9] and frames[-1].t == 90
                np.testing.assert_array_equal(frames[-1].position, np.full((N, 3), 9, np.float32))
            assert sent["a"][-1] is sent["b"][-1]  # one encoding shared by both viewers

    run(main())


def test_viewer_keeps_only_the_newest_unsent_frame() -> None:
    metrics = Metrics()
    fmt = FrameFormat("f32", N)

    async def main() -> None:
        with ThreadPoolExecutor(1) as pool:
            release = asyncio.Event()
            got: list[int] = []

            async def slow_send(data: bytes) -> None:
                await release.wait()
                got.append(decode_server_message(data, fmt).seq)

            pipeline = FakePipeline()
            source = Source(pipeline, pool, metrics)
            viewer = Viewer(slow_send, CodecWriter(fmt), ("k",), pool, metrics)
            source.subscribers.append(viewer.offer)
            tasks = [asyncio.create_task(source.run()), asyncio.create_task(viewer.run())]
            for seq in range(6):  # each computed while frame 0 is stuck in the socket
                source.offer(pending(seq))
                await until(lambda seq=seq: source.computed > seq)
            release.set()
            await until(lambda: bool(got) and got[-1] == 5)
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            assert got == [0, 5] and viewer.skipped == 4

    run(main())


def test_fast_frame_writer_gives_the_codec_bytes() -> None:
    from ofera.streaming.session import make_writer
    from ofera_protocol import make_quant

    rng = np.random.default_rng(0)
    n = 64
    pos = rng.normal(0, 0.05, (n, 3)).astype(np.float32)
    rot = rng.normal(0, 1, (n, 4)).astype(np.float32)
    rot /= np.linalg.norm(rot, axis=1, keepdims=True)
    scale = rng.uniform(1e-3, 1e-2, (n, 3)).astype(np.float32)
    index = np.arange(0, n, 3, dtype=np.uint32)
    timing = {"epm": 5, "total": 900}
    for encoding in ("f32", "f16", "q13"):
        quant = make_quant(pos, scale) if encoding == "q13" else None
        for coords in ("flame", "unity"):
            for gather, idx in ((None, None), (index.astype(np.int64), index)):
                fmt = FrameFormat(encoding, n, sparse=idx is not None, quant=quant)
                fast = make_writer(fmt, coords, gather, idx, fast=True, stamp_encode=False)
                ref = make_writer(fmt, coords, gather, idx, fast=False)
                got = fast.encode(7, 11, timing, pos, rot, scale)
                assert bytes(got) == ref.encode(7, 11, timing, pos, rot, scale), (encoding, coords, idx is not None)
                # a room's frame: frame.member in the header, the codec's bytes (rooms, PROTOCOL.md 12)
                member = "m-5f2a9c1e0b7d"
                a = bytes(fast.encode(7, 11, timing, pos, rot, scale, member=member))
                assert a == ref.encode(7, 11, timing, pos, rot, scale, member=member), (encoding, coords, member)
                assert decode_server_message(a, fmt).member == member
                assert decode_server_message(bytes(got), fmt).member is None
                # stamped: the same frame, its timing with the writer's own encode time added
                stamped = make_writer(fmt, coords, gather, idx, fast=True).encode(7, 11, timing, pos, rot, scale)
                frame = decode_server_message(bytes(stamped), fmt)
                assert set(frame.timing) == {*timing, "encode"} and frame.timing["encode"] >= 0
                assert bytes(stamped) == ref.encode(7, 11, frame.timing, pos, rot, scale)


def test_work_left_for_after_a_frame_runs_once_the_client_has_read_it_or_before_the_next_frame(monkeypatch) -> None:
    """Source._after (a delta frame's decodings, thread-choice records): for a session alone on its server,
    AFTER_FRAME_S after the frame is delivered, not at once (the client reading it may share the loop's CPU), or
    before the next frame is computed, if it comes first (its kernels need the decodings); with other sessions, at
    once."""
    metrics = Metrics()

    async def main() -> None:
        with ThreadPoolExecutor(1) as pool:
            pipeline = FakePipeline()
            source = Source(pipeline, pool, metrics)
            ran: list[tuple[str, float]] = []
            delivered: list[float] = []
            loop = asyncio.get_running_loop()
            source.subscribers.append(lambda frame: delivered.append(loop.time()))
            task = asyncio.create_task(source.run())
            real_run = pipeline.run

            def run_leaving_work(w):  # (the compute thread appends, as FastSession.defer does)
                source._after.append((lambda seq: ran.append((f"after {seq}", loop.time())), (int(w[0]),)))
                return real_run(w)

            pipeline.run = run_leaving_work
            source.alone = lambda: True  # (a session alone on its server; with others, the work runs at once)
            source.offer(pending(0))
            await until(lambda: ran)
            assert ran[0][0] == "after 0" and ran[0][1] - delivered[0] >= roles.AFTER_FRAME_S * 0.9
            assert metrics.registry.get_sample_value("ofera_frames_computed_total") == 1  # (the metrics at once)

            monkeypatch.setattr(roles, "AFTER_FRAME_S", 30.0)  # frame 1's work still waits when frame 2 comes
            source.offer(pending(1))
            await until(lambda: len(delivered) == 2)
            await asyncio.sleep(0.02)
            assert len(ran) == 1 and len(source._after) == 1
            source.offer(pending(2))
            await until(lambda: len(delivered) == 3)
            assert [name for name, _ in ran] == ["after 0", "after 1"] and ran[1][1] < delivered[2]
            assert len(source._after) == 1  # frame 2's, in 30 s
            source.alone = lambda: False  # other sessions: at once
            source.offer(pending(3))
            await until(lambda: len(ran) == 4)
            assert [name for name, _ in ran[2:]] == ["after 2", "after 3"] and ran[3][1] - delivered[3] < 1.0
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    run(main())
