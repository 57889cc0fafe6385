"""The replay core without a network: absolute schedule, speed, loop, skipping, summary, recording."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from ofera.mapping.layouts import get_layout
from ofera.replay import FrameRecorder, Replayer, ReplayStats, percentiles_ms, stream_url
from ofera.sources import FaceLog
from ofera_protocol import Frame, FrameHeader


def synthetic_log(seconds: float = 3.0, fps: float = 60.0, layout: str = "arkit52") -> FaceLog:
    n = int(round(seconds * fps)) + 1
    lay = get_layout(layout)
    t = np.arange(n) / fps
    w = (0.5 + 0.5 * np.sin(t[:, None] * 3.0 + np.arange(lay.length)[None, :])).astype(np.float32)
    return FaceLog(times=t, weights=w, layout=lay)


class VirtualClock:
    """Virtual time whose sleep always oversleeps by `overshoot` seconds (a pessimistic event loop)."""

    def __init__(self, overshoot: float = 0.0) -> None:
        self.now = 100.0
        self.overshoot = overshoot

    def clock(self) -> float:
        return self.now

    async def sleep(self, dt: float) -> None:
        self.now += max(dt, 0.0) + self.overshoot


def run_virtual(replayer: Replayer) -> list[tuple[int, float]]:
    sent: list[tuple[int, float]] = []

    async def send(seq: int, t_us: int, w: np.ndarray) -> None:
        sent.append((seq, t_us * 1e-6))

    asyncio.run(replayer.run(send))
    return sent


def test_absolute_schedule_does_not_drift():
    log = synthetic_log(10.0)
    vc = VirtualClock(overshoot=0.004)
    r = Replayer(log, speed=1.0, clock=vc.clock, sleep=vc.sleep)
    sent = run_virtual(r)
    assert len(sent) == len(log) and r.stats.skipped == 0
    errors = np.array([t - (r.start + log.times[seq]) for seq, t in sent])
    # every frame is late by the one overshoot of its own sleep, never by the sum of earlier ones
    np.testing.assert_allclose(errors[1:], 0.004, atol=1e-6)
    assert r.stats.duration == pytest.approx(log.duration, abs=0.005)


@pytest.mark.parametrize("speed", [0.5, 4.0])
def test_speed_scales_the_schedule(speed):
    log = synthetic_log(2.0)
    vc = VirtualClock()
    r = Replayer(log, speed=speed, clock=vc.clock, sleep=vc.sleep)
    sent = run_virtual(r)
    t = np.array([s[1] for s in sent]) - r.start
    np.testing.assert_allclose(t, log.times / speed, atol=1e-6)
    assert r.stats.duration == pytest.approx(log.duration / speed, abs=1e-6)


def test_loop_continues_at_the_frame_rate():
    log = synthetic_log(1.0, fps=50.0)
    vc = VirtualClock()
    r = Replayer(log, speed=2.0, loop=True, max_passes=3, clock=vc.clock, sleep=vc.sleep)
    sent = run_virtual(r)
    assert [s[0] for s in sent] == list(range(3 * len(log)))
    t = np.array([s[1] for s in sent]) - r.start
    np.testing.assert_allclose(np.diff(t), 0.02 / 2.0, atol=1e-6)  # no pause or burst at the seams
    assert r.stats.passes == 3


def test_stalled_sender_skips_overdue_frames_and_sends_the_last():
    log = synthetic_log(1.0)
    vc = VirtualClock()
    stalled = {"done": False}

    async def send(seq: int, t_us: int, w: np.ndarray) -> None:
        if seq == 10 and not stalled["done"]:
            stalled["done"] = True
            vc.now += 0.5  # the sender blocks for half a second
        sent.append(seq)

    sent: list[int] = []
    r = Replayer(log, max_lag=0.1, clock=vc.clock, sleep=vc.sleep)
    asyncio.run(r.run(send))
    assert r.stats.skipped > 0 and r.stats.sent + r.stats.skipped == len(log)
    assert sent[-1] == len(log) - 1
    assert r.stats.sent == len(sent)


def test_stop_ends_the_run():
    log = synthetic_log(1.0)
    vc = VirtualClock()
    r = Replayer(log, loop=True, clock=vc.clock, sleep=vc.sleep)  # unbounded loop

    async def send(seq: int, t_us: int, w: np.ndarray) -> None:
        if seq == 100:
            r.stop()

    asyncio.run(r.run(send))
    assert r.stats.sent == 101 and r.total_frames is None


def test_bad_arguments():
    log = synthetic_log(0.5)
    with pytest.raises(ValueError, match="speed"):
        Replayer(log, speed=0)
    with pytest.raises(ValueError, match="no frames"):
        Replayer(FaceLog(times=np.zeros(0), weights=np.zeros((0, 52)), layout=get_layout("arkit52")))


def test_real_time_accuracy_over_three_seconds():
    """A synthetic 3 s log on the real monotonic clock and asyncio.sleep: each frame within a few ms of its
    due time, total within a few percent, no drift from the first second to the last."""
    log = synthetic_log(3.0)
    r = Replayer(log)
    sent: list[tuple[int, float]] = []

    async def send(seq: int, t_us: int, w: np.ndarray) -> None:
        sent.append((seq, time.monotonic()))

    t0 = time.monotonic()
    asyncio.run(r.run(send))
    wall = time.monotonic() - t0
    errors = np.array([t - (r.start + log.times[seq]) for seq, t in sent])
    assert r.stats.sent == len(log) == len(sent) and r.stats.skipped == 0
    assert np.median(errors) < 0.003, f"median schedule error {np.median(errors) * 1e3:.2f} ms"
    assert np.percentile(errors, 90) < 0.010, f"p90 schedule error {np.percentile(errors, 90) * 1e3:.2f} ms"
    assert abs(wall - log.duration) < 0.03 * log.duration, f"wall {wall:.3f} s for a {log.duration:.3f} s log"
    # no drift: the last second is as punctual as the first
    assert np.median(errors[-60:]) < np.median(errors[:60]) + 0.003
    summary = r.stats.summary()
    assert summary["schedule_error_ms"]["p50"] == pytest.approx(np.median(errors) * 1e3, abs=0.5)


def test_summary_fields_and_latency():
    s = ReplayStats()
    s.started = 0.0
    for i in range(10):
        s.on_sent(float(i), 0.001)
    for i in range(9):
        s.on_frame(1_000_000 + 5_000 * (i + 1), 1_000_000)
    s.on_error("bad_length: 3 weights", fatal=False)
    s.finished = 12.0
    out = s.summary(log_duration_s=9.0)
    assert out["sent"] == 10 and out["received"] == 9 and out["errors"] == 1 and out["skipped"] == 0
    assert out["duration_s"] == 9.0 and out["wall_s"] == 12.0 and out["log_duration_s"] == 9.0
    assert out["latency_ms"]["p50"] == pytest.approx(25.0)
    assert out["latency_ms"]["p99"] == pytest.approx(44.6, abs=0.01)
    assert out["error_messages"] == ["bad_length: 3 weights"] and out["fatal_error"] is None
    assert percentiles_ms([])["p50"] is None


def test_recorder_npz(tmp_path):
    log = synthetic_log(0.5)
    rec = FrameRecorder("arkit52", log.weights, log.times, positions=True)
    n = 8
    for seq in (0, 1, 3):
        frame = Frame(seq=seq, t=1000 * seq, position=np.full((n, 3), seq, np.float32),
                      rotation=np.zeros((n, 4), np.float32), scale=np.ones((n, 3), np.float32),
                      timing={"map": 10, "deform": 20 + seq})
        rec.add(frame, 1000 * seq + 2500)
    path = rec.save(tmp_path / "rec")
    assert path.name == "rec.npz"
    z = np.load(path)
    np.testing.assert_array_equal(z["seq"], [0, 1, 3])
    np.testing.assert_allclose(z["latency_ms"], 2.5)
    assert list(z["timing_stages"]) == ["deform", "map"]
    np.testing.assert_array_equal(z["timing_us"][:, 0], [20, 21, 23])
    np.testing.assert_array_equal(z["weights"], log.weights[[0, 1, 3]])
    np.testing.assert_allclose(z["log_time"], log.times[[0, 1, 3]])
    assert z["position"].shape == (3, n, 3) and str(z["layout"]) == "arkit52"


def test_recorder_takes_frame_headers_without_positions(tmp_path):
    log = synthetic_log(0.5)
    rec = FrameRecorder("arkit52", log.weights, log.times)
    for seq in (0, 2):
        rec.add(FrameHeader(seq=seq, t=1000 * seq, timing={"map": 10 + seq}, size=300, n=8), 1000 * seq + 1500)
    z = np.load(rec.save(tmp_path / "rec"))
    np.testing.assert_array_equal(z["seq"], [0, 2])
    np.testing.assert_array_equal(z["count"], [8, 8])
    np.testing.assert_allclose(z["latency_ms"], 1.5)
    np.testing.assert_array_equal(z["timing_us"][:, 0], [10, 12])
    with pytest.raises(ValueError, match="needs decoded frames"):
        FrameRecorder("arkit52", log.weights, log.times, positions=True).add(
            FrameHeader(seq=0, t=0, timing={}, size=300, n=8), 10)


def test_stream_url():
    assert stream_url("ws://127.0.0.1:8000") == "ws://127.0.0.1:8000/v1/stream"
    assert stream_url("127.0.0.1:8000") == "ws://127.0.0.1:8000/v1/stream"
    assert stream_url("http://h:1/") == "ws://h:1/v1/stream"
