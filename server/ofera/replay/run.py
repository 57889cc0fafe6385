"""Replay a face log through a running server: the `Replayer` schedule over a `Link`, frames received
concurrently, then a short drain so the answer to the last `bs` is counted."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable

from ofera_protocol import ErrorMessage, Frame, FrameHeader

from ofera.replay.core import Replayer, ReplayStats
from ofera.replay.link import Link, LinkError, LinkOptions, open_link
from ofera.replay.record import FrameRecorder


def now_us() -> int:
    return round(time.monotonic() * 1e6)


async def receive_loop(
    link: Link,
    stats: ReplayStats,
    on_frame: Callable[[Frame | FrameHeader, int], None] | None = None,
    on_fatal: Callable[[], None] | None = None,
) -> None:
    """Count every frame and error the server sends until the session ends. A fatal error, or the
    server closing the connection, calls `on_fatal` (the sender stops)."""
    async for msg in link.events():
        if isinstance(msg, (Frame, FrameHeader)) and msg.member is not None and msg.member != link.member:
            stats.on_member_frame(msg.member, now_us(), msg.t)  # rooms: another member's frame
        elif isinstance(msg, (Frame, FrameHeader)):
            t = now_us()
            stats.on_frame(t, msg.t, msg.seq)
            if on_frame is not None:
                on_frame(msg, t)
        elif isinstance(msg, ErrorMessage):
            seq = f" (bs {msg.seq})" if msg.seq is not None else ""
            stats.on_error(f"{msg.code}: {msg.message}{seq}", fatal=msg.fatal)
            if msg.fatal and on_fatal is not None:
                on_fatal()
    if stats.fatal_error is None and link.closed_reason is not None and not link.closing:
        stats.on_error(link.closed_reason, fatal=True)
    if on_fatal is not None:
        on_fatal()


async def replay_through(
    replayer: Replayer,
    url: str,
    options: LinkOptions,
    recorder: FrameRecorder | None = None,
    drain_s: float = 2.0,
    on_tick: Callable[[Replayer], None] | None = None,
    tick_s: float = 0.1,
) -> ReplayStats:
    """Open a session, replay, drain, close. Returns the stats; `stats.fatal_error` is set when the
    server refused or broke the session (a refused handshake is reported the same way)."""
    stats = replayer.stats
    stats.started = time.monotonic()
    link = await _open(url, options, stats)
    if link is None:
        return stats

    answered = asyncio.Event()

    def on_frame(frame: Frame | FrameHeader, t: int) -> None:
        if recorder is not None:
            recorder.add(frame, t, link.client.gaussians)
        answered.set()

    def on_fatal() -> None:
        replayer.stop()
        answered.set()

    def last_answered() -> bool:
        if stats.fatal_error is not None or stats.last_seq_sent is None:
            return True
        if options.room is not None and not options.self_view:
            return True  # a room member sees its own frames only with self_view: nothing answers its bs
        return stats.last_seq_answered is not None and stats.last_seq_answered >= stats.last_seq_sent

    async def ticker() -> None:
        while True:
            on_tick(replayer)  # type: ignore[misc]
            await asyncio.sleep(tick_s)

    receiver = asyncio.create_task(receive_loop(link, stats, on_frame, on_fatal))
    tick = asyncio.create_task(ticker()) if on_tick is not None else None
    try:
        try:
            await replayer.run(link.send)
        except Exception as e:  # the connection broke while sending
            if stats.fatal_error is None:
                stats.on_error(f"sending failed: {link.closed_reason or e}", fatal=True)
        await _drain(last_answered, answered, drain_s)
    finally:
        if tick is not None:
            tick.cancel()
        await _close(link, receiver, stats)
        room_events(stats, link)
        if on_tick is not None:
            on_tick(replayer)
    return stats


async def watch_through(url: str, options: LinkOptions, seconds: float | None, stop: asyncio.Event | None = None,
                        on_tick: Callable[[ReplayStats], None] | None = None, tick_s: float = 0.1) -> ReplayStats:
    """Rooms: watch `options.room` without publishing for `seconds` (None: until `stop` is set), counting every
    member's frames (`stats.members`)."""
    stats = ReplayStats()
    stats.started = time.monotonic()
    options = LinkOptions(**{**vars(options), "publish": False})
    link = await _open(url, options, stats)
    if link is None:
        return stats
    stop = stop or asyncio.Event()
    receiver = asyncio.create_task(receive_loop(link, stats, on_fatal=stop.set))
    try:
        deadline = None if seconds is None else time.monotonic() + seconds
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            if on_tick is not None:
                on_tick(stats)
            left = tick_s if deadline is None else min(tick_s, max(0.0, deadline - time.monotonic()))
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), left)
    finally:
        await _close(link, receiver, stats)
    room_events(stats, link)
    return stats


async def _open(url: str, options: LinkOptions, stats: ReplayStats) -> Link | None:
    """The session's link; None when the server refused or could not be reached (`stats` then has the fatal error
    and its finish time)."""
    try:
        return await open_link(url, options)
    except LinkError as e:
        stats.on_error(str(e), fatal=True)
        stats.finished = time.monotonic()
        return None


async def _close(link: Link, receiver: asyncio.Task, stats: ReplayStats) -> None:
    """Close the session, stop its receive loop, and stamp the stats' finish time."""
    await link.close()
    receiver.cancel()
    with contextlib.suppress(asyncio.CancelledError, Exception):
        await receiver
    stats.finished = time.monotonic()


def room_events(stats: ReplayStats, link: Link) -> None:
    """Rooms: copy the joins and leaves the client saw into `stats`."""
    stats.joined = [j.member for j in link.client.joins]
    stats.left = [(m.member, m.reason) for m in link.client.leaves]


async def _drain(done: Callable[[], bool], event: asyncio.Event, timeout: float) -> None:
    """Wait until `done()` (re-checked whenever `event` fires) or `timeout` seconds pass."""
    deadline = time.monotonic() + timeout
    while not done():
        left = deadline - time.monotonic()
        if left <= 0:
            return
        event.clear()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(event.wait(), left)
