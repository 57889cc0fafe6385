"""A client that stops reading, beside a normal session: does the normal session's latency suffer, does the
server's memory grow?

    python benchmarks/stalled_client.py --gaussians 100000 --seconds 20 --stalled 2 --json out.json

Starts a server in a subprocess (benchmarks/_common.py) serving a procedural avatar of --gaussians
Gaussians. One measured session sends bs at --rate Hz throughout and records its round trips (frame
decoded - *scheduled* send time, so a stalled sender cannot hide latency). The run alternates --rounds times
between an "alone" segment and a "beside" segment, each --seconds / --rounds long (alternating, so that load
from other processes on a shared machine hits both phases alike): for a "beside" segment, --stalled clients
(plain sockets with a --rcvbuf byte TCP receive buffer) finish the handshake, then keep sending bs at --rate
Hz and never read again; they are reset at the end of the segment. The first --settle seconds of each
segment are not counted. The server's RSS (/proc/PID/status) is sampled every 0.25 s throughout.

Targets: p99 beside the stalled clients within 2x of p99 alone; RSS growth < 300 MB.
JSON: {"alone": {rtt_ms percentiles, frames}, "beside": {...}, "p99_ratio", "rss_mb": {start, end, peak,
growth}, "skipped": {bs, frame}, "pass": {...}}, and a PNG (round trips over time, RSS over time).
"""

from __future__ import annotations

import argparse
import asyncio
import re
import sys
import time
import urllib.request
from pathlib import Path

import msgpack
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common as C  # noqa: E402


def skipped(http_url: str) -> dict[str, int]:
    text = urllib.request.urlopen(f"{http_url}/metrics", timeout=10).read().decode()
    out = {}
    for stage in ("bs", "frame"):
        m = re.search(rf'ofera_frames_skipped_total\{{stage="{stage}"\}}\s+([0-9.eE+]+)', text)
        out[stage] = int(float(m.group(1))) if m else 0
    return out


def bs_bytes(seq: int, t: int, w: np.ndarray) -> bytes:
    return msgpack.packb({"type": "bs", "seq": seq, "t": t, "w": w.astype("<f4").tobytes()}, use_bin_type=True)


async def measured_session(url: str, weights: np.ndarray, layout: str, rate: float, seconds: float, encoding: str,
                           stalled: list, t_origin: float) -> list[tuple[float, float]]:
    """(send time since t_origin, round trip ms) of each frame of a session sending bs on a fixed schedule
    for `seconds`; the raw sockets in `stalled` (changed by the caller as it goes) get the same bs, written
    without blocking and never read."""
    from _raw import ws_frame
    from websockets.asyncio.client import connect

    async with connect(url, compression=None, max_size=None) as ws:
        await ws.send(msgpack.packb({"type": "hello", "protocol": 1, "layout": layout, "encoding": encoding}))
        while True:
            m = msgpack.unpackb(await ws.recv(), raw=False)
            assert m["type"] in ("welcome", "avatar"), m
            if m["type"] == "avatar" and m["chunk"] == m["chunks"] - 1:
                break
        out: list[tuple[float, float]] = []

        async def reader() -> None:
            while True:
                data = await ws.recv()
                now = time.monotonic_ns() // 1000
                m = msgpack.unpackb(data, raw=False)
                if m["type"] == "frame":
                    out.append((m["t"] / 1e6 - t_origin, (now - m["t"]) / 1000))

        task = asyncio.create_task(reader())
        period = 1.0 / rate
        start = time.monotonic() + 0.05
        n = int(seconds * rate)
        for i in range(n):
            due = start + i * period
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            w = weights[i % len(weights)]
            t_sched = int(due * 1e6)  # the *scheduled* time, on the monotonic clock the reader uses
            await ws.send(bs_bytes(i, t_sched, w))
            for s in list(stalled):
                try:
                    s.sock.send(ws_frame(bs_bytes(i, t_sched, w)))
                except (BlockingIOError, OSError):
                    pass  # its send buffer is full as well: the server is not reading it faster than we write
        await asyncio.sleep(0.5)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return out


def in_phase(samples: list[tuple[float, float]], segments: list[tuple[float, float]], settle: float) -> list[float]:
    """Round trips of frames whose bs was sent inside a segment, `settle` seconds after its start."""
    return [r for t, r in samples if any(a + settle <= t < b for a, b in segments)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--seconds", type=float, default=20.0, help="Total length of each phase.")
    ap.add_argument("--rounds", type=int, default=4, help="Alone / beside segments alternate this many times.")
    ap.add_argument("--warmup", type=float, default=3.0, help="Seconds before the first segment.")
    ap.add_argument("--settle", type=float, default=0.5, help="Seconds at the start of each segment not counted.")
    ap.add_argument("--rate", type=float, default=72.0)
    ap.add_argument("--stalled", type=int, default=2, help="Stalled clients beside the measured session.")
    ap.add_argument("--rcvbuf", type=int, default=4096, help="Stalled clients' TCP receive buffer (bytes).")
    ap.add_argument("--encoding", default="f16", choices=["f32", "f16", "q13"])
    ap.add_argument("--threads", type=int, default=2, help="Server compute threads.")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "stalled_client.json")
    args = ap.parse_args()

    from _raw import RawWebSocket

    weights, layout, _, notes = C.capture()
    avatars, more = C.avatars_dir(args.gaussians)
    notes += more
    rss: list[tuple[float, float]] = []
    print(f"stalled client: {args.gaussians} Gaussians, {args.encoding}, {args.rate:g} Hz, {args.stalled} stalled, "
          f"{args.seconds:g} s per phase", flush=True)
    with C.ServerProcess(avatars, threads=args.threads) as server:
        pid = server.proc.pid
        http = f"http://127.0.0.1:{server.port}"
        t_origin = time.monotonic()
        seg = args.seconds / args.rounds
        alone_segs: list[tuple[float, float]] = []
        beside_segs: list[tuple[float, float]] = []
        stalled: list = []
        skipped0 = skipped(http)

        async def sampler(stop: asyncio.Event) -> None:
            while not stop.is_set():
                rss.append((time.monotonic() - t_origin, C.rss_mb(pid)))
                await asyncio.sleep(0.25)

        def open_stalled() -> list:
            out = []
            for _ in range(args.stalled):
                s = RawWebSocket(server, rcvbuf=args.rcvbuf, timeout=120)
                s.handshake(layout=layout, encoding=args.encoding)  # reads the avatar, then never reads again
                s.sock.setblocking(False)
                out.append(s)
            return out

        async def controller() -> None:
            """Alternates alone / beside segments, so that load from outside hits both phases alike."""
            await asyncio.sleep(args.warmup)
            for _ in range(args.rounds):
                t = time.monotonic() - t_origin
                alone_segs.append((t, t + seg))
                await asyncio.sleep(seg)
                stalled.extend(await asyncio.to_thread(open_stalled))
                t = time.monotonic() - t_origin
                beside_segs.append((t, t + seg))
                await asyncio.sleep(seg)
                for s in stalled:
                    s.abort()
                stalled.clear()

        async def run_all() -> list:
            stop = asyncio.Event()
            task = asyncio.create_task(sampler(stop))
            total = args.warmup + 2 * args.seconds + args.rounds * 6.0
            measure = asyncio.create_task(measured_session(server.url, weights, layout, args.rate, total,
                                                           args.encoding, stalled, t_origin))
            await controller()
            samples = await measure
            stop.set()
            await task
            return samples

        samples = asyncio.run(run_all())
        skipped1 = skipped(http)

    alone = in_phase(samples, alone_segs, args.settle)
    beside = in_phase(samples, beside_segs, args.settle)
    alone_s = {"frames": len(alone), "rtt_ms": C.pct(alone)}
    beside_s = {"frames": len(beside), "rtt_ms": C.pct(beside)}
    rss_v = [v for _, v in rss]
    first_beside = beside_segs[0][0] if beside_segs else rss[-1][0]
    before = [v for t, v in rss if t < first_beside] or rss_v[:1]
    rss_start = float(np.median(before[-8:]))
    growth = max(rss_v) - rss_start
    ratio = C.ratio(alone_s["rtt_ms"]["p99"], beside_s["rtt_ms"]["p99"])
    report = {
        "benchmark": "stalled_client", "gaussians": args.gaussians, "encoding": args.encoding, "rate_hz": args.rate,
        "seconds_per_phase": args.seconds, "rounds": args.rounds, "settle_s": args.settle,
        "stalled_clients": args.stalled, "stalled_rcvbuf": args.rcvbuf,
        "server_threads": args.threads, "alone": alone_s, "beside": beside_s, "p99_ratio": ratio,
        "rss_mb": {"start": round(rss_start, 1), "end": round(rss_v[-1], 1), "peak": round(max(rss_v), 1),
                   "growth": round(growth, 1)},
        "skipped": {k: skipped1[k] - skipped0[k] for k in skipped0},
        "pass": {"p99_within_2x": ratio is not None and ratio <= 2.0, "rss_growth_below_300mb": growth < 300},
        "machine": C.machine(), "notes": notes,
    }
    C.write_json(args.json, report)
    print(C.table([["alone", alone_s["frames"], alone_s["rtt_ms"]["p50"], alone_s["rtt_ms"]["p99"]],
                   ["beside stalled", beside_s["frames"], beside_s["rtt_ms"]["p50"], beside_s["rtt_ms"]["p99"]]],
                  ["phase", "frames", "p50 ms", "p99 ms"]))
    print(f"p99 ratio {ratio}  RSS start {rss_start:.0f} MB, peak {max(rss_v):.0f} MB, growth {growth:.0f} MB; "
          f"dropped (newest wins): {report['skipped']}")
    print(f"pass: {report['pass']}  ->  {args.json}")

    plt = C.pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for segs, color, label in ((alone_segs, "C0", "alone"), (beside_segs, "C1", f"beside {args.stalled} stalled")):
        for i, (a, b) in enumerate(segs):
            ax1.axvspan(a, b, color=color, alpha=0.12, label=label if i == 0 else None)
            ax2.axvspan(a, b, color=color, alpha=0.12)
    ax1.plot([t for t, _ in samples], [r for _, r in samples], ".", ms=2, color="k")
    ax1.set_ylabel("round trip, ms")
    ax1.set_yscale("log")
    ax1.legend(loc="upper left")
    ax1.set_title(f"Stalled clients: p99 {alone_s['rtt_ms']['p99']} ms alone, {beside_s['rtt_ms']['p99']} ms beside "
                  f"({args.gaussians} Gaussians, {args.encoding}, {args.rate:g} Hz)")
    ax2.plot([t for t, _ in rss], rss_v, color="C3")
    ax2.set_ylabel("server RSS, MB")
    ax2.set_xlabel("seconds")
    fig.tight_layout()
    fig.savefig(C.png_path(args.json), dpi=110)


if __name__ == "__main__":
    main()
