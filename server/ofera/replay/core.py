"""The replay core, free of any network: an absolute-time scheduler and the run's accounting.

`Replayer` sends the frames of a `FaceLog` at their recorded times. Frame i of pass p is due at
``start + (p * period + t_i) / speed`` on a monotonic clock (``period`` = log duration plus one frame
interval, so a loop continues at the frame rate). Every frame is scheduled from the same origin, so
sleep overshoot never accumulates: a late wake-up makes one frame late, not the rest of the log.
A frame found more than `max_lag` seconds overdue (the sender stalled) is skipped and counted, so the
replay catches up instead of bursting stale frames; the last frame of the run is always sent.

`ReplayStats` counts what was sent, answered and refused, and turns it into the summary that
`ofera replay --json` writes.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from ofera.sources.facelog import FaceLog

Clock = Callable[[], float]
Sleep = Callable[[float], Awaitable[object]]
SendFn = Callable[..., Awaitable[object]]
"""`send(seq, t_us, weights)`: sends one `bs`; `t_us` is the send time on the replay clock. When the log
has confidences, `send(seq, t_us, weights, conf=(2,) float32 [lower, upper])`."""


def percentiles_ms(values_s: list[float] | np.ndarray, prefix: str = "") -> dict[str, float | None]:
    """p50, p90, p99, mean and max of durations in seconds, in milliseconds (None when empty)."""
    a = np.asarray(values_s, dtype=np.float64)
    if a.size == 0:
        return {f"{prefix}{k}": None for k in ("p50", "p90", "p99", "mean", "max")}
    p50, p90, p99 = np.percentile(a, [50, 90, 99]) * 1e3
    return {
        f"{prefix}p50": round(float(p50), 3),
        f"{prefix}p90": round(float(p90), 3),
        f"{prefix}p99": round(float(p99), 3),
        f"{prefix}mean": round(float(a.mean() * 1e3), 3),
        f"{prefix}max": round(float(a.max() * 1e3), 3),
    }


@dataclass
class ReplayStats:
    """What happened during a replay or an ingest run. Times are seconds on the replay clock."""

    sent: int = 0
    received: int = 0
    skipped: int = 0
    errors: int = 0
    error_messages: list[str] = field(default_factory=list)
    fatal_error: str | None = None
    latencies: list[float] = field(default_factory=list)
    schedule_errors: list[float] = field(default_factory=list)
    first_send: float | None = None
    last_send: float | None = None
    started: float | None = None
    finished: float | None = None
    passes: int = 0
    last_seq_sent: int | None = None
    last_seq_answered: int | None = None
    scheduled: tuple[float, float] | None = None
    """Due offsets (seconds after the start) of the first and last frame sent."""
    members: dict[str, list[float]] = field(default_factory=dict)
    """Rooms: latency (s, from the member's bs.t, same-host clocks) of every frame received from each other member."""
    joined: list[str] = field(default_factory=list)  # rooms: members announced by `join`, in order
    left: list[tuple[str, str]] = field(default_factory=list)  # rooms: (member, reason) of every `leave`

    MAX_MESSAGES = 20

    def on_sent(self, now: float, lateness: float, seq: int | None = None) -> None:
        self.sent += 1
        if seq is not None:
            self.last_seq_sent = seq
        self.schedule_errors.append(lateness)
        if self.first_send is None:
            self.first_send = now
        self.last_send = now

    def on_frame(self, now_us: int, t_us: int, seq: int | None = None) -> None:
        """A frame answering `bs` number `seq`, sent at `t_us`, arrived at `now_us` (same clock, µs)."""
        self.received += 1
        if seq is not None and (self.last_seq_answered is None or seq > self.last_seq_answered):
            self.last_seq_answered = seq
        self.latencies.append(max(0, now_us - t_us) * 1e-6)

    def on_member_frame(self, member: str, now_us: int, t_us: int) -> None:
        """Rooms: a frame of another `member` (its seq is that member's, not an answer to this client's bs)."""
        self.members.setdefault(member, []).append(max(0, now_us - t_us) * 1e-6)

    def on_error(self, text: str, fatal: bool = False) -> None:
        self.errors += 1
        if len(self.error_messages) < self.MAX_MESSAGES:
            self.error_messages.append(text)
        if fatal and self.fatal_error is None:
            self.fatal_error = text

    @property
    def duration(self) -> float:
        """Seconds from the first `bs` sent to the last."""
        if self.first_send is None or self.last_send is None:
            return 0.0
        return self.last_send - self.first_send

    @property
    def expected_duration(self) -> float | None:
        """What `duration` would be on a perfect clock: from the first sent frame's due time to the last's."""
        return None if self.scheduled is None else self.scheduled[1] - self.scheduled[0]

    @property
    def wall(self) -> float:
        if self.started is None:
            return 0.0
        end = self.finished if self.finished is not None else time.monotonic()
        return end - self.started

    def summary(self, **extra: object) -> dict[str, object]:
        """The JSON summary: counts, durations, latency and schedule-error percentiles."""
        out: dict[str, object] = {
            "sent": self.sent,
            "received": self.received,
            "errors": self.errors,
            "skipped": self.skipped,
            "answered": round(self.received / self.sent, 4) if self.sent else None,
            "duration_s": round(self.duration, 4),
            "expected_duration_s": None if self.scheduled is None else round(self.expected_duration, 4),
            "wall_s": round(self.wall, 4),
            "latency_ms": percentiles_ms(self.latencies),
            "schedule_error_ms": percentiles_ms(self.schedule_errors),
            "last_seq_sent": self.last_seq_sent,
            "last_seq_answered": self.last_seq_answered,
        }
        if self.joined or self.members:
            out["joined"], out["left"] = list(self.joined), [list(x) for x in self.left]
            out["members"] = {m: {"received": len(v), "latency_ms": percentiles_ms(v)} for m, v in self.members.items()}
        out.update(extra)
        out["fatal_error"] = self.fatal_error
        out["error_messages"] = list(self.error_messages)
        return out


class Replayer:
    """Sends a face log's frames on an absolute schedule; see the module docstring.

    `clock` (seconds, monotonic) and `sleep` are injectable so the schedule can be tested in virtual
    time. `t_us` handed to `send` is ``round(clock() * 1e6)`` at the moment of sending: frames echo
    it, and `stats.on_frame(now_us, t)` turns it into a latency on the same clock.
    """

    def __init__(
        self,
        log: FaceLog,
        speed: float = 1.0,
        loop: bool = False,
        max_lag: float = 1.0,
        clock: Clock = time.monotonic,
        sleep: Sleep = asyncio.sleep,
        max_passes: int | None = None,
    ) -> None:
        if len(log) == 0:
            raise ValueError(f"the log has no frames ({log.source or 'empty'})")
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a positive number, got {speed}")
        if max_lag <= 0:
            raise ValueError(f"max_lag must be positive, got {max_lag}")
        self.log = log
        self.times = np.asarray(log.times, dtype=np.float64) - float(log.times[0])
        self.speed = float(speed)
        self.loop = loop
        self.max_lag = float(max_lag)
        self.clock = clock
        self.sleep = sleep
        self.max_passes = max_passes if loop else 1
        steps = np.diff(self.times)
        steps = steps[steps > 0]
        self.frame_interval = float(np.median(steps)) if steps.size else 1.0 / 60.0
        self.period = float(self.times[-1]) + self.frame_interval
        """Log seconds from one pass's first frame to the next pass's."""
        self.stats = ReplayStats()
        self.start: float | None = None
        self.position = 0
        """Frames handled so far (sent or skipped), over all passes."""
        self._stop = False

    @property
    def log_duration(self) -> float:
        return float(self.times[-1])

    @property
    def total_frames(self) -> int | None:
        """Frames the run will handle, or None for an unbounded loop."""
        return None if self.max_passes is None else self.max_passes * len(self.times)

    def now_us(self) -> int:
        return round(self.clock() * 1e6)

    def stop(self) -> None:
        """Ask `run` to return before the next frame."""
        self._stop = True

    def schedule(self) -> Iterator[tuple[int, int, float]]:
        """(pass, frame index, due time in seconds after start), in order, forever when looping."""
        p = 0
        while self.max_passes is None or p < self.max_passes:
            base = p * self.period
            for i, t in enumerate(self.times):
                yield p, i, (base + t) / self.speed
            p += 1

    def due(self, p: int, i: int) -> float:
        """Absolute due time of frame i of pass p (needs `start`)."""
        assert self.start is not None
        return self.start + (p * self.period + self.times[i]) / self.speed

    async def run(self, send: SendFn, start: float | None = None) -> ReplayStats:
        """Send every frame when due (await `send` per frame); returns the stats (also `self.stats`)."""
        stats = self.stats
        now = self.clock()
        if stats.started is None:
            stats.started = now
        self.start = now if start is None else start
        total = self.total_frames
        n = len(self.times)
        conf = None
        if self.log.confidence is not None and self.log.confidence.shape[1] == 2:
            conf = np.clip(self.log.confidence, 0.0, 1.0).astype(np.float32)
        for p, i, offset in self.schedule():
            if self._stop:
                break
            due = self.start + offset
            now = self.clock()
            if due > now:
                await self.sleep(due - now)
                now = self.clock()
            lateness = now - due
            self.position += 1
            last = total is not None and self.position == total
            if i == 0:
                stats.passes = p + 1
            if lateness > self.max_lag and not last:
                stats.skipped += 1
                continue
            t_us = round(now * 1e6)
            if conf is None:
                await send(p * n + i, t_us, self.log.weights[i])
            else:
                await send(p * n + i, t_us, self.log.weights[i], conf=conf[i])
            stats.on_sent(now, lateness, p * n + i)
            stats.scheduled = (offset if stats.scheduled is None else stats.scheduled[0], offset)
        return stats
