"""Rooms: K publishers in one room, each watched by the K-1 others (K(K-1) viewer streams), 72 Hz; p50/p99/drops
per K on one server, and with two servers joined by Redis (the publishers alternate between them).

    python benchmarks/rooms.py --gaussians 100000 --ks 2,3,4,5,6 --encodings f16,q13 --seconds 4

Every client publishes the capture's blendshapes on its own fixed schedule (offset so the K streams interleave)
and stamps the scheduled time in `t` (no coordinated omission); a frame keeps its source's `seq` and `t`, so a
viewer's latency is frame received - the source's scheduled send time (all clients share this process's clock). A
bs that no frame of that member answered at a viewer (newest wins dropped it) counts with the latency of the first
later frame of that member there (`_common.drop_latencies`): drops are counted as late, per viewer per member.
Clients read each message's header only (type, member, seq, t, timing: the arrays are never decoded), and the
report gives the CPU they used besides the servers'. A K passes with p99 under --budget-ms (13.9 ms, one 72 Hz
frame) and at most --max-drop (1 %) of its viewer-stream frames dropped.

Two servers: a real redis-server on a free port, servers a and b attached to it; client i connects to a if i is
even, else b. Streams within one server and streams across servers are reported apart: the Redis hop is the
difference of their p50 (and the servers' own ofera_bus_hop_seconds, publish() to receipt). Each server deforms
every member once for its own viewers, so two servers on one machine do up to twice the deformation work.
Room sessions have no temporal deltas (PROTOCOL.md 12.1): `q13` (and `q13:sparse`) is the most compact Gaussian
encoding in a room (`q13-delta` is q13 there); `params` is run when the server offers it (frames carry expression
values, clients deform): only about one params frame a second carries seq and t, so its latency comes from those and
its drops from frame counts.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import math
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

HEADER_KEYS = frozenset({"type", "member", "seq", "t", "timing", "code", "message", "reason", "publish", "count",
                         "sh_degree", "chunk", "chunks", "offset", "n"})
"""Keys a header read unpacks; it stops at the first other key (a frame's arrays, an avatar's attributes)."""


def read_header(data: bytes) -> dict:
    """The leading small fields of a server message (type, member, seq, t, timing...), its arrays left unread: a
    frame's from the protocol's reader (read_frame_header), another message's up to its first array."""
    from ofera_protocol import read_frame_header

    head = read_frame_header(data)
    if head is not None:
        fields = {"type": "frame", "member": head.member, "seq": head.seq, "t": head.t, "timing": head.timing,
                  "n": head.n}
        return {k: v for k, v in fields.items() if v is not None}
    u = msgpack.Unpacker(io.BytesIO(data), raw=False, read_size=512)
    fields: dict = {}
    for _ in range(u.read_map_header()):
        key = u.unpack()
        if key not in HEADER_KEYS:
            break
        fields[key] = u.unpack()
    return fields


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` (Linux /proc)."""
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


class RedisProcess:
    """A redis-server (no persistence) on a free port, for the two-server runs."""

    def __init__(self) -> None:
        if shutil.which("redis-server") is None:
            raise SystemExit("redis-server is missing (apt-get install redis-server): needed for --servers 2")
        self.port = C.free_port()
        self.dir = tempfile.mkdtemp(prefix="ofera-bench-redis-")
        self.proc = subprocess.Popen(["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
                                      "--appendonly", "no", "--dir", self.dir], stdout=subprocess.DEVNULL)
        for _ in range(200):
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return
            except OSError:
                time.sleep(0.05)
        self.stop()
        raise RuntimeError("redis-server did not start")

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)
        shutil.rmtree(self.dir, ignore_errors=True)


@dataclass
class Member:
    """One benchmark client: publishes, and records what it receives of every other member."""

    index: int
    server: int  # which server (0 or 1) it is connected to
    ws: object
    member: str = ""
    joined: set[str] = field(default_factory=set)
    avatars: set[str] = field(default_factory=set)  # members whose avatar (every chunk) arrived
    arrivals: dict[str, list[tuple[int, float]]] = field(default_factory=dict)  # member -> (seq, arrival us)
    timings: list[dict] = field(default_factory=list)
    frame_bytes: int = 0  # bytes of the frames received in the measured window
    unstamped: dict[str, list[float]] = field(default_factory=dict)  # params: member -> arrivals of frames without seq
    errors: list[str] = field(default_factory=list)

    async def receive(self, first: int, last: int, members: int, done: asyncio.Event) -> None:
        from ofera.client import now_us

        finished: set[str] = set()
        async for data in self.ws:
            if isinstance(data, str):
                continue
            h = read_header(data)
            kind = h.get("type")
            if kind == "frame" and "seq" not in h and "member" in h:  # params: most frames carry no seq
                self.unstamped.setdefault(h["member"], []).append(now_us())
                self.frame_bytes += len(data)
            elif kind == "frame" and "seq" in h:
                seq = h["seq"]
                if seq >= first:
                    self.arrivals.setdefault(h["member"], []).append((seq, now_us()))
                    self.frame_bytes += len(data)
                    if seq >= last:
                        finished.add(h["member"])
                        if len(finished) == members - 1:
                            done.set()
                    if h.get("timing"):
                        self.timings.append(h["timing"])
            elif kind == "join":
                self.joined.add(h["member"])
            elif kind == "avatar" and h.get("chunk") == h.get("chunks", 0) - 1:
                self.avatars.add(h["member"])
            elif kind == "error":
                self.errors.append(f"{h.get('code')}: {h.get('message')}")


def parse_encoding(spec: str) -> tuple[str, bool]:
    """'q13' -> ('q13', dense); 'q13:sparse' -> ('q13', sparse: only the Gaussians that move are sent)."""
    name, _, mode = spec.partition(":")
    if mode not in ("", "sparse"):
        raise SystemExit(f"--encodings: {spec!r}: the only suffix is ':sparse'")
    return name, mode == "sparse"


async def open_member(url: str, index: int, server: int, room: str, layout: str, encoding: str) -> Member:
    from ofera_protocol import Hello
    from ofera_protocol.codec import encode_hello
    from websockets.asyncio.client import connect

    name, sparse = parse_encoding(encoding)
    ws = await connect(url, compression=None, max_size=2**28, ping_interval=None)
    await ws.send(encode_hello(Hello(layout=layout, avatar=C.AVATAR_ID, encoding=name, sparse=sparse, room=room)))
    welcome = msgpack.unpackb(await ws.recv(), raw=False)
    if welcome.get("type") != "welcome":
        await ws.close()
        raise RuntimeError(f"no welcome from {url}: {welcome}")
    return Member(index, server, ws, member=welcome["member"])


async def run_k(urls: list[str], k: int, weights: np.ndarray, layout: str, encoding: str, args) -> dict:
    """One room of k publishers (client i on urls[i % len(urls)]); latencies per stream, drops, CPU."""
    from ofera.client import now_us
    from ofera_protocol import Blendshapes
    from ofera_protocol.codec import encode_bs

    room = f"bench-{k}-{uuid.uuid4().hex[:6]}"
    members = [await open_member(urls[i % len(urls)], i, i % len(urls), room, layout, encoding) for i in range(k)]
    period = 1e6 / args.rate
    total = int((args.warmup + args.seconds) * args.rate)
    first, last = int(args.warmup * args.rate), total - 1
    done = [asyncio.Event() for _ in members]
    receivers = [asyncio.create_task(m.receive(first, last, k, d)) for m, d in zip(members, done)]
    deadline = time.monotonic() + 30
    while any(len(m.avatars - {m.member}) < k - 1 for m in members):  # everybody has everybody's avatar first
        if time.monotonic() > deadline:
            raise RuntimeError(f"K={k}: members did not all see each other: joins {[len(m.joined) for m in members]}"
                               f", avatars {[len(m.avatars) for m in members]}")
        await asyncio.sleep(0.05)
    await asyncio.sleep(0.3)
    start = now_us() + 200_000
    offsets = {m.member: m.index * period / k for m in members}

    async def sender(m: Member) -> None:
        for j in range(total):
            due = start + offsets[m.member] + j * period
            delay = (due - now_us()) / 1e6
            if delay > 0:
                await asyncio.sleep(delay)
            w = weights[(j + 7 * m.index) % len(weights)]
            await m.ws.send(encode_bs(Blendshapes(seq=j, t=int(due), w=w)))

    pids = args.server_pids
    cpu0 = [cpu_seconds(p) for p in pids]
    client0, wall0 = time.process_time(), time.monotonic()
    await asyncio.gather(*(sender(m) for m in members))
    waits = [asyncio.create_task(d.wait()) for d in done]
    await asyncio.wait(waits, timeout=2.0)  # the last frames still on their way
    for w in waits:
        w.cancel()
    end = now_us()
    wall = time.monotonic() - wall0
    client_cpu = time.process_time() - client0
    server_cpu = [cpu_seconds(p) - c for p, c in zip(pids, cpu0)]
    for m in members:
        await m.ws.close()
    for r in receivers:
        r.cancel()
    await asyncio.gather(*receivers, return_exceptions=True)

    streams = {"local": [], "remote": []}  # latencies (ms), dropped bs included
    sent = {"local": 0, "remote": 0}
    frames = {"local": 0, "remote": 0}
    dropped = {"local": 0, "remote": 0}
    for viewer in members:
        for src in members:
            if src is viewer:
                continue
            where = "local" if src.server == viewer.server else "remote"
            scheduled = {j: start + offsets[src.member] + j * period for j in range(first, total)}
            arrivals = viewer.arrivals.get(src.member, [])
            lat = [(t - scheduled[s]) / 1000.0 for s, t in arrivals if s in scheduled]
            late = C.drop_latencies(scheduled, arrivals, end)
            sent[where] += len(scheduled)
            if src.member in viewer.unstamped or parse_encoding(encoding)[0] == "params":
                # params (PROTOCOL.md 13): one frame a second carries seq and t. Latency from those; drops from the
                # count of frames that arrived while the measured bs were due (and one period after).
                window = (scheduled[first], scheduled[total - 1] + period)
                got = len({s for s, _ in arrivals if s in scheduled}) + sum(
                    window[0] <= t <= window[1] for t in viewer.unstamped.get(src.member, []))
                streams[where] += lat
                frames[where] += min(got, len(scheduled))
                dropped[where] += max(0, len(scheduled) - got)
                continue
            streams[where] += lat + list(late.values())
            frames[where] += len({s for s, _ in arrivals if s in scheduled})
            dropped[where] += len(late)
    everything = streams["local"] + streams["remote"]
    n_sent = sum(sent.values())
    stage_ms = {}
    for key in ("map", "deform", "encode", "queue", "total"):
        vals = [t[key] / 1000.0 for m in members for t in m.timings if key in t]
        if vals:
            stage_ms[key] = round(float(np.median(vals)), 3)
    p = C.pct(everything)
    out = {"k": k, "viewer_streams": k * (k - 1), "p50_ms": p["p50"], "p99_ms": p["p99"], "max_ms": p["max"],
           "sent": n_sent, "frames": sum(frames.values()), "dropped": sum(dropped.values()),
           "drop_fraction": round(sum(dropped.values()) / n_sent, 4) if n_sent else 0.0,
           "server_cores_busy": [round(c / wall, 2) for c in server_cpu],
           "client_cores_busy": round(client_cpu / wall, 2), "stage_median_ms": stage_ms,
           "frame_bytes_mean": round(sum(m.frame_bytes for m in members) / max(1, sum(frames.values()))),
           "delivered_mb_per_s": round(sum(m.frame_bytes for m in members) / wall / 1e6, 1),
           "errors": sorted({e for m in members for e in m.errors})}
    if parse_encoding(encoding)[0] == "params":
        out["latency_from"] = "stamped frames only (PROTOCOL.md 13: about one a second); drops from frame counts"
    if len(urls) > 1:
        for where in ("local", "remote"):
            q = C.pct(streams[where])
            out[where] = {"p50_ms": q["p50"], "p99_ms": q["p99"], "sent": sent[where], "frames": frames[where],
                          "dropped": dropped[where]}
    out["passes"] = bool(out["drop_fraction"] <= args.max_drop and out["p99_ms"] is not None
                         and out["p99_ms"] < args.budget_ms)
    return out


def bus_hop_ms(http_urls: list[str]) -> dict | None:
    """publish()-to-receipt time of expression values over Redis (ms), from the servers' ofera_bus_hop_seconds
    histograms: mean, and p50 interpolated within its bucket."""
    total = count = 0.0
    buckets: dict[float, float] = {}
    for url in http_urls:
        with urllib.request.urlopen(f"{url}/metrics", timeout=5) as r:
            for line in r.read().decode().splitlines():
                if line.startswith("ofera_bus_hop_seconds_sum"):
                    total += float(line.split()[-1])
                elif line.startswith("ofera_bus_hop_seconds_count"):
                    count += float(line.split()[-1])
                elif line.startswith("ofera_bus_hop_seconds_bucket"):
                    le = line.split('le="')[1].split('"')[0]
                    buckets[float(le)] = buckets.get(float(le), 0.0) + float(line.split()[-1])
    if not count:
        return None
    lo, below, p50 = 0.0, 0.0, None
    for le, cum in sorted(buckets.items()):  # cumulative counts
        if cum >= count / 2:
            p50 = lo if math.isinf(le) else lo + (le - lo) * (count / 2 - below) / max(cum - below, 1e-12)
            break
        lo, below = le, cum
    return {"mean_ms": round(1000 * total / count, 3), "p50_ms": None if p50 is None else round(1000 * p50, 3),
            "messages": int(count)}


def offered_encodings(http_url: str) -> list[str]:
    import json

    with urllib.request.urlopen(f"{http_url}/v1/avatars", timeout=5) as r:
        return list(json.loads(r.read())["encodings"])


def sweep(avatars: Path, servers: int, encodings: list[str], ks: list[int], weights, layout: str, args) -> dict:
    """Start `servers` server processes (and Redis for two), run every encoding and K; results by encoding."""
    redis = RedisProcess() if servers > 1 else None
    extra = {"redis_url": redis.url} if redis else {}
    procs = [C.ServerProcess(avatars, threads=args.threads, extra=extra) for _ in range(servers)]
    out: dict = {}
    try:
        for p in procs:
            p.start()
        args.server_pids = [p.proc.pid for p in procs]
        offered = offered_encodings(procs[0].url.replace("ws://", "http://").removesuffix("/v1/stream"))
        for enc in encodings:
            if parse_encoding(enc)[0] not in offered:
                print(f"  {enc}: not offered by this server ({offered}): skipped", flush=True)
                continue
            out[enc] = {}
            for k in ks:
                try:
                    r = asyncio.run(run_k([p.url for p in procs], k, weights, layout, enc, args))
                except Exception:
                    for i, p in enumerate(procs):
                        print(f"--- server {i} output (last lines) ---\n{p.output()}", file=sys.stderr)
                    raise
                out[enc][k] = r
                extra_s = ""
                if "remote" in r:
                    extra_s = f" (same server p50 {r['local']['p50_ms']}, across Redis p50 {r['remote']['p50_ms']})"
                print(f"  {servers} server(s) {enc} K={k}: p50 {r['p50_ms']} ms, p99 {r['p99_ms']} ms, dropped "
                      f"{r['dropped']}/{r['sent']} ({100 * r['drop_fraction']:.1f}%), {r['delivered_mb_per_s']} MB/s "
                      f"of frames, servers busy "
                      f"{r['server_cores_busy']} cores, clients {r['client_cores_busy']}{extra_s}", flush=True)
                time.sleep(0.3)
        if redis:
            out["bus_hop"] = bus_hop_ms([p.url.replace("ws://", "http://").removesuffix("/v1/stream")
                                                 for p in procs])
    finally:
        for p in procs:
            p.stop()
        if redis:
            redis.stop()
    return out


def plot(path: Path, runs: dict, budget: float, max_drop: float, title: str) -> None:
    plt = C.pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(13, 4.5))
    for (mode, enc), res in runs.items():
        ks = sorted(res)
        style = "-" if mode == "one server" else ":"
        line = ax[0].plot(ks, [res[k]["p99_ms"] for k in ks], "o" + style, label=f"{enc}, {mode}: p99")[0]
        ax[0].plot(ks, [res[k]["p50_ms"] for k in ks], "x" + style, color=line.get_color(), alpha=0.6,
                   label=f"{enc}, {mode}: p50")
        ax[1].plot(ks, [100 * res[k]["drop_fraction"] for k in ks], "o" + style, color=line.get_color(),
                   label=f"{enc}, {mode}")
    ax[0].axhline(budget, color="grey", ls="--", lw=0.8, label=f"budget {budget} ms")
    ax[0].set_yscale("log")
    ax[0].set_ylabel("viewer latency, drops counted as late (ms, log)")
    ax[1].axhline(100 * max_drop, color="grey", ls="--", lw=0.8, label=f"limit {100 * max_drop:g} %")
    ax[1].set_ylabel("frames dropped per viewer stream (%)")
    for a in ax:
        a.set_xticks(sorted({k for res in runs.values() for k in res}))
        a.set_xlabel("publishers K (each watched by the K-1 others)")
        a.legend(fontsize=7)
    C.save_figure(fig, path, title)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--rate", type=float, default=72.0)
    ap.add_argument("--seconds", type=float, default=4.0, help="measured seconds per K")
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--ks", default="2,3,4,5,6", help="room sizes K >= 2, comma-separated")
    ap.add_argument("--encodings", default="f16,q13,q13:sparse,params", help="comma-separated, ':sparse' for "
                    "sparse frames (hello.sparse); those the server does not offer are skipped")
    ap.add_argument("--servers", default="1,2", help="'1': one server, '2': two servers through Redis, '1,2': both")
    ap.add_argument("--budget-ms", type=float, default=13.9)
    ap.add_argument("--max-drop", type=float, default=0.01)
    ap.add_argument("--threads", type=int, default=2, help="compute threads per server")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "rooms.json")
    ap.add_argument("--floor-seconds", type=float, default=2.0, help="seconds of the loopback transport floor "
                    "per encoding's frame size (0: skip)")
    ap.add_argument("--no-plot", action="store_true")
    args = ap.parse_args(argv)

    weights, layout, _, notes = C.capture()
    avatars, epm_notes = C.avatars_dir(args.gaussians or None)
    notes += epm_notes
    ks = [int(k) for k in args.ks.split(",") if k.strip()]
    if not ks or min(ks) < 2:
        raise SystemExit("--ks: room sizes of at least 2 (a room of one has no viewer streams)")
    encodings = [e.strip() for e in args.encodings.split(",") if e.strip()]
    runs: dict = {}
    hop = None
    for servers in sorted({int(s) for s in args.servers.split(",") if s.strip()}):
        mode = "one server" if servers == 1 else "two servers + Redis"
        print(f"[rooms] {mode}: K = {ks}, {encodings}, {args.rate:g} Hz, {args.seconds:g} s each", flush=True)
        res = sweep(avatars, servers, encodings, ks, weights, layout, args)
        hop = res.pop("bus_hop", hop)
        for enc, by_k in res.items():
            runs[(mode, enc)] = by_k

    limits = {}  # what one frame costs to move at all: loopback WebSocket, no compute (`_common.transport_floor`)
    if args.floor_seconds > 0:
        for enc in dict.fromkeys(enc for _, enc in runs):
            sizes = [r["frame_bytes_mean"] for (_, e), res in runs.items() if e == enc for r in res.values()
                     if r["frame_bytes_mean"]]
            if sizes:
                floor = C.transport_floor(int(np.median(sizes)), rate=args.rate, seconds=args.floor_seconds)
                limits[enc] = {"frame_bytes": floor["bytes"], "loopback_message_ms_p50": floor["p50"],
                               "streams_per_core_by_transport_alone": round(1000 / (args.rate * floor["p50"]), 1)
                               if floor["p50"] else None}
    summary = {}
    for (mode, enc), res in runs.items():
        summary[f"{enc}, {mode}"] = {"largest_passing_k": C.largest_ok(res)}
    redis_adds = {}
    for (mode, enc), res in runs.items():
        one = runs.get(("one server", enc))
        if mode != "one server" and one:
            redis_adds[enc] = {k: {"remote_minus_local_p50_ms": _minus(res[k].get("remote"), res[k].get("local")),
                                   "two_minus_one_server_p50_ms": _minus(res[k], one.get(k))} for k in res}
    report = {
        "benchmark": "rooms", "gaussians": args.gaussians, "rate_hz": args.rate, "seconds": args.seconds,
        "warmup_s": args.warmup, "budget_ms": args.budget_ms, "max_drop": args.max_drop,
        "threads_per_server": args.threads, "client_read": "header only (type, member, seq, t, timing)",
        "summary": summary, "redis_adds": redis_adds, "bus_hop": hop, "transport_limits": limits,
        "runs": {f"{enc}, {mode}": {str(k): v for k, v in res.items()} for (mode, enc), res in runs.items()},
        "machine": C.machine(), "notes": notes + [
            "latency: viewer receipt - the source client's scheduled send time; a bs a viewer never got a frame of "
            "counts with the latency of that member's next frame there (drops counted as late)",
            "all servers, Redis and the clients share this machine's cores: server_cores_busy and "
            "client_cores_busy say who used them",
            "room sessions have no temporal deltas (PROTOCOL.md 12.1): q13 is the compact encoding in a room"],
    }
    path = C.write_json(args.json, report)
    if not args.no_plot and runs:
        plot(C.png_path(path), runs, args.budget_ms, args.max_drop,
             f"Rooms: K publishers x (K-1) viewers, {args.gaussians} Gaussians, {args.rate:g} Hz")
    print(C.table([[name, s["largest_passing_k"]] for name, s in summary.items()], ["run", "largest passing K"]))
    for enc, lim in limits.items():
        print(f"{enc}: a {lim['frame_bytes']} B frame takes {lim['loopback_message_ms_p50']} ms over loopback "
              f"WebSocket alone: at most {lim['streams_per_core_by_transport_alone']} such streams at {args.rate:g} "
              "Hz between one sending and one receiving process, before any compute")
    if hop is not None:
        print(f"Redis hop (servers' publish() to receipt): {hop}; p50 differences (ms): {redis_adds}")
    print(f"wrote {path}")
    return report


def _minus(a: dict | None, b: dict | None) -> float | None:
    if not a or not b or a.get("p50_ms") is None or b.get("p50_ms") is None:
        return None
    return round(a["p50_ms"] - b["p50_ms"], 3)


if __name__ == "__main__":
    main()
