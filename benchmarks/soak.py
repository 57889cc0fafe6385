"""Soak: several sessions at 72 Hz for a bounded time; does anything drift (memory, latency, errors)?

    python benchmarks/soak.py                      # 10 minutes, 4 sessions, 20,000 Gaussians
    python benchmarks/soak.py --seconds 120 --sessions 4 --json out.json

Starts a server in a subprocess (benchmarks/_common.py) serving a procedural avatar of --gaussians
Gaussians, and runs --sessions clients, each sending bs on a fixed 72 Hz schedule (the real capture,
looped; `t` is the scheduled time, so a stall cannot hide latency), reading every frame, pinging every 5 s.
Every --churn seconds one session is closed and a new one opened in its place (sessions come and go in a
real deployment). The server's RSS (/proc/PID/status) is sampled every second.

Reports, as JSON and a PNG next to it: RSS over time and its linear-fit slope in MB/min (after --warmup
seconds; also over the second half alone: growth that levels off is not a leak), round-trip p50/p99 per
--bucket seconds (default: per minute) and the drift of p99 (last bucket vs first), errors (error
messages, unexpected closes), bs sent vs frames received (the rest were dropped by newest-wins
backpressure), and the final /healthz.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
import urllib.request
from pathlib import Path

import msgpack
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common as C  # noqa: E402


class Totals:
    def __init__(self) -> None:
        self.sent = 0
        self.frames = 0
        self.pongs = 0
        self.errors: dict[str, int] = {}
        self.closes: dict[str, int] = {}
        self.sessions = 0
        self.samples: list[tuple[float, float]] = []  # (seconds since start, round trip ms)


async def session(url: str, weights: np.ndarray, layout: str, rate: float, end: float, t0: float, totals: Totals,
                  encoding: str, offset: int) -> None:
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    totals.sessions += 1
    async with connect(url, compression=None, max_size=None, open_timeout=60) as ws:
        await ws.send(msgpack.packb({"type": "hello", "protocol": 1, "layout": layout, "encoding": encoding}))
        while True:
            m = msgpack.unpackb(await ws.recv(), raw=False)
            if m["type"] == "error":
                totals.errors[m["code"]] = totals.errors.get(m["code"], 0) + 1
                return
            if m["type"] == "avatar" and m["chunk"] == m["chunks"] - 1:
                break

        async def reader() -> None:
            try:
                while True:
                    data = await ws.recv()
                    now = time.monotonic_ns() // 1000
                    m = msgpack.unpackb(data, raw=False)
                    if m["type"] == "frame":
                        totals.frames += 1
                        totals.samples.append((time.monotonic() - t0, (now - m["t"]) / 1000))
                    elif m["type"] == "pong":
                        totals.pongs += 1
                    elif m["type"] == "error":
                        totals.errors[m["code"]] = totals.errors.get(m["code"], 0) + 1
            except ConnectionClosed as e:
                if e.rcvd is None or e.rcvd.code != 1000:
                    key = str(e.rcvd.code) if e.rcvd else "no close frame"
                    totals.closes[key] = totals.closes.get(key, 0) + 1

        task = asyncio.create_task(reader())
        period = 1.0 / rate
        start = time.monotonic()
        i = 0
        try:
            while True:
                due = start + i * period
                if due >= end:
                    break
                await asyncio.sleep(max(0.0, due - time.monotonic()))
                w = weights[(offset + i) % len(weights)].astype("<f4")
                await ws.send(msgpack.packb({"type": "bs", "seq": i, "t": int(due * 1e6), "w": w.tobytes()},
                                            use_bin_type=True))
                totals.sent += 1
                if i % int(5 * rate) == 0:
                    await ws.send(msgpack.packb({"type": "ping", "t": time.monotonic_ns() // 1000}))
                i += 1
            await asyncio.sleep(0.3)
            await ws.send(msgpack.packb({"type": "bye"}))
            await asyncio.wait_for(ws.wait_closed(), 10)
        except ConnectionClosed:
            pass
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)


def linear_slope(points: list[tuple[float, float]]) -> float | None:
    """MB per minute of a least-squares line through (seconds, MB)."""
    if len(points) < 3:
        return None
    t = np.array([p[0] for p in points]) / 60.0
    v = np.array([p[1] for p in points])
    return round(float(np.polyfit(t, v, 1)[0]), 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=600.0, help="Length of the soak (default 10 minutes).")
    ap.add_argument("--sessions", type=int, default=4)
    ap.add_argument("--gaussians", type=int, default=20_000)
    ap.add_argument("--rate", type=float, default=72.0)
    ap.add_argument("--encoding", default="f16", choices=["f32", "f16", "q13"])
    ap.add_argument("--churn", type=float, default=30.0, help="Seconds between replacing one session (0: never).")
    ap.add_argument("--warmup", type=float, default=15.0, help="Seconds left out of the RSS fit.")
    ap.add_argument("--bucket", type=float, default=60.0, help="Seconds per latency bucket.")
    ap.add_argument("--threads", type=int, default=2, help="Server compute threads.")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "soak.json")
    args = ap.parse_args()

    weights, layout, _, notes = C.capture()
    avatars, more = C.avatars_dir(args.gaussians)
    notes += more
    totals = Totals()
    rss: list[tuple[float, float]] = []
    print(f"soak: {args.sessions} sessions x {args.rate:g} Hz, {args.gaussians} Gaussians, {args.encoding}, "
          f"{args.seconds:g} s", flush=True)
    with C.ServerProcess(avatars, threads=args.threads) as server:
        pid = server.proc.pid

        async def run_all() -> None:
            t0 = time.monotonic()
            end = t0 + args.seconds
            done = False

            async def sampler() -> None:
                last_print = 0.0
                while not done:
                    t = time.monotonic() - t0
                    rss.append((t, C.rss_mb(pid)))
                    if t - last_print >= 30:
                        last_print = t
                        recent = [r for s, r in totals.samples if s > t - 30]
                        p99 = f"{np.percentile(recent, 99):.1f}" if recent else "-"
                        print(f"  {t:6.0f} s  RSS {rss[-1][1]:.0f} MB  frames {totals.frames}  p99(30 s) {p99} ms  "
                              f"errors {sum(totals.errors.values())}", flush=True)
                    await asyncio.sleep(1.0)

            async def slot(k: int) -> None:
                """Session slot k: runs sessions back to back, each for `churn x sessions` seconds."""
                life = args.churn * args.sessions if args.churn > 0 else args.seconds
                first = t0 + (k + 1) * args.churn if args.churn > 0 else end
                stop = min(end, first)
                while time.monotonic() < end:
                    began = time.monotonic()
                    try:
                        await session(server.url, weights, layout, args.rate, stop, t0, totals, args.encoding,
                                      offset=k * 997 + totals.sessions)
                    except Exception as e:  # noqa: BLE001 - counted, the soak goes on
                        key = type(e).__name__
                        totals.closes[key] = totals.closes.get(key, 0) + 1
                    if time.monotonic() - began < 1.0:  # refused (e.g. server_full): do not spin
                        await asyncio.sleep(1.0)
                    stop = min(end, time.monotonic() + life)

            task = asyncio.create_task(sampler())
            await asyncio.gather(*(slot(k) for k in range(args.sessions)))
            await asyncio.sleep(1.0)
            done = True
            await task

        asyncio.run(run_all())
        health = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=10).read())
        server_output = server.output()

    fit = [p for p in rss if p[0] >= args.warmup] or rss
    slope = linear_slope(fit)
    late = linear_slope([p for p in fit if p[0] >= (fit[0][0] + fit[-1][0]) / 2])  # levelling off: not a leak
    buckets = []
    n_buckets = max(1, int(np.ceil(args.seconds / args.bucket)))
    for b in range(n_buckets):
        lo, hi = b * args.bucket, (b + 1) * args.bucket
        r = [v for t, v in totals.samples if lo <= t < hi]
        buckets.append({"from_s": lo, "to_s": min(hi, args.seconds), "frames": len(r),
                        "p50_ms": C.pct(r)["p50"], "p99_ms": C.pct(r)["p99"]})
    p99s = [b["p99_ms"] for b in buckets if b["p99_ms"] is not None]
    report = {
        "benchmark": "soak", "seconds": args.seconds, "sessions": args.sessions, "gaussians": args.gaussians,
        "rate_hz": args.rate, "encoding": args.encoding, "churn_s": args.churn, "server_threads": args.threads,
        "rss_mb": {"start": round(rss[0][1], 1), "after_warmup": round(fit[0][1], 1), "end": round(rss[-1][1], 1),
                   "peak": round(max(v for _, v in rss), 1), "slope_mb_per_min": slope,
                   "slope_second_half_mb_per_min": late},
        "latency_ms": {"all": C.pct([v for _, v in totals.samples]), "per_bucket": buckets,
                       "p99_drift_ms": round(p99s[-1] - p99s[0], 3) if len(p99s) >= 2 else None},
        "bs_sent": totals.sent, "frames_received": totals.frames, "pongs": totals.pongs,
        "sessions_opened": totals.sessions, "errors": totals.errors, "unexpected_closes": totals.closes,
        "final_health": health, "machine": C.machine(), "notes": notes,
        "server_log_tail": server_output[-1500:] if (totals.errors or totals.closes) else "",
    }
    C.write_json(args.json, report)
    print(f"RSS {report['rss_mb']}  slope {slope} MB/min (second half {late} MB/min)")
    print(C.table([[f"{b['from_s']:.0f}-{b['to_s']:.0f}", b["frames"], b["p50_ms"], b["p99_ms"]] for b in buckets],
                  ["seconds", "frames", "p50 ms", "p99 ms"]))
    print(f"bs sent {totals.sent}, frames {totals.frames}, errors {totals.errors}, unexpected closes "
          f"{totals.closes}, sessions {totals.sessions}  ->  {args.json}")

    plt = C.pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    ax1.plot([t for t, _ in rss], [v for _, v in rss], color="C3", label="server RSS")
    if slope is not None and len(fit) >= 3:
        t = np.array([p[0] for p in fit])
        c = np.polyfit(t / 60, [p[1] for p in fit], 1)
        ax1.plot(t, np.polyval(c, t / 60), "k--", lw=1, label=f"fit: {slope:+.2f} MB/min")
    ax1.set_ylabel("MB")
    ax1.legend(loc="lower right")
    ax1.set_title(f"Soak: {args.sessions} sessions x {args.rate:g} Hz, {args.gaussians} Gaussians, {args.encoding}")
    win = 10.0
    edges = np.arange(0, args.seconds + win, win)
    mids, p50, p99 = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        r = [v for t, v in totals.samples if lo <= t < hi]
        if r:
            mids.append((lo + hi) / 2)
            p50.append(np.percentile(r, 50))
            p99.append(np.percentile(r, 99))
    ax2.plot(mids, p50, label="p50 (10 s windows)")
    ax2.plot(mids, p99, label="p99 (10 s windows)")
    ax2.set_ylabel("round trip, ms")
    ax2.set_xlabel("seconds")
    ax2.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(C.png_path(args.json), dpi=110)


if __name__ == "__main__":
    main()
