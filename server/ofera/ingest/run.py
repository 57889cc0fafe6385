"""Drive an avatar session from live UDP face tracking: receive datagrams, send the newest frame as
`bs`, count frames coming back, report a status line periodically."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from ofera.ingest.receivers import DatagramReceiver, Decoded, LatestSlot, PacketCounters
from ofera.replay.core import ReplayStats, percentiles_ms
from ofera.replay.link import LinkError, LinkOptions, open_link
from ofera.replay.run import now_us, receive_loop


@dataclass
class IngestResult:
    """Counters of an ingest run; `summary()` is what `--json` writes."""

    packets: PacketCounters = field(default_factory=PacketCounters)
    stats: ReplayStats = field(default_factory=ReplayStats)
    replaced: int = 0
    listen: tuple[str, int] | None = None

    def summary(self, **extra: object) -> dict[str, object]:
        out = self.stats.summary(
            packets_ok=self.packets.ok,
            packets_bad=self.packets.bad,
            frames_decoded=self.packets.frames,
            frames_replaced=self.replaced,
            last_packet_problem=self.packets.last_problem,
            listen=f"{self.listen[0]}:{self.listen[1]}" if self.listen else None,
            **extra,
        )
        out.pop("schedule_error_ms")  # frames are sent when they arrive, there is no schedule
        return out

    def status_line(self, window: int = 200) -> str:
        lat = percentiles_ms(self.stats.latencies[-window:])
        p50 = "-" if lat["p50"] is None else f"{lat['p50']:.1f}"
        p99 = "-" if lat["p99"] is None else f"{lat['p99']:.1f}"
        return (f"packets ok {self.packets.ok} bad {self.packets.bad} | bs sent {self.stats.sent} "
                f"| frames received {self.stats.received} | errors {self.stats.errors} "
                f"| latency p50 {p50} ms p99 {p99} ms")


async def run_ingest(
    decoder: Callable[[bytes], Decoded],
    layout: str,
    host: str,
    port: int,
    url: str,
    options: LinkOptions | None = None,
    seconds: float | None = None,
    status_every: float = 1.0,
    on_status: Callable[[IngestResult], None] | None = None,
    on_listening: Callable[[tuple[str, int]], None] | None = None,
    stop: asyncio.Event | None = None,
    result: IngestResult | None = None,
) -> IngestResult:
    """Listen on UDP `host:port`, open a session with `layout` at `url`, run until `seconds` pass, `stop`
    is set, or the server ends the session. Raises OSError when the port cannot be bound; a refused
    session is reported in `result.stats.fatal_error`."""
    result = result or IngestResult()
    stats = result.stats
    stats.started = time.monotonic()
    stop = stop or asyncio.Event()
    slot = LatestSlot()
    loop = asyncio.get_running_loop()
    transport, _ = await loop.create_datagram_endpoint(
        lambda: DatagramReceiver(decoder, slot, result.packets), local_addr=(host, port))
    try:
        result.listen = transport.get_extra_info("sockname")[:2]
        try:
            link = await open_link(url, options or LinkOptions(layout=layout))
        except LinkError as e:
            stats.on_error(str(e), fatal=True)
            return result
        if link.layout != layout:
            raise AssertionError(f"session layout {link.layout} != {layout}")
        slot.take_nowait()  # frames that arrived before the session was open are stale
        if on_listening is not None:
            on_listening(result.listen)

        async def sender() -> None:
            seq = 0
            while True:
                w = await slot.get()
                t = now_us()
                await link.send(seq, t, w)
                stats.on_sent(t * 1e-6, 0.0, seq)
                seq += 1

        async def status() -> None:
            while True:
                await asyncio.sleep(status_every)
                result.replaced = slot.replaced
                if on_status is not None:
                    on_status(result)

        receiver = asyncio.create_task(receive_loop(link, stats, on_fatal=stop.set))
        tasks = [asyncio.create_task(sender()), asyncio.create_task(status())]
        try:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(_wait_stop(stop, tasks[0]), seconds)
            if tasks[0].done() and not tasks[0].cancelled() and tasks[0].exception() is not None:
                if stats.fatal_error is None:
                    stats.on_error(f"sending failed: {link.closed_reason or tasks[0].exception()}", fatal=True)
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            await _drain_last(stats, 2.0)  # let the answer to the last bs arrive
            await link.close()
            receiver.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await receiver
    finally:
        transport.close()
        result.replaced = slot.replaced
        stats.finished = time.monotonic()
    return result


async def _wait_stop(stop: asyncio.Event, sender: asyncio.Task) -> None:
    """Until `stop` is set or the sender task ends (it only ends by failing)."""
    waiter = asyncio.create_task(stop.wait())
    try:
        await asyncio.wait({waiter, sender}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        waiter.cancel()


async def _drain_last(stats: ReplayStats, timeout: float) -> None:
    """Wait (polling) until the last `bs` sent is answered, the session ended, or `timeout` passes."""
    deadline = time.monotonic() + timeout
    while (stats.last_seq_sent is not None and stats.fatal_error is None and time.monotonic() < deadline
           and (stats.last_seq_answered is None or stats.last_seq_answered < stats.last_seq_sent)):
        await asyncio.sleep(0.01)
