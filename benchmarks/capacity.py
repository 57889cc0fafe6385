"""Concurrent sessions: K clients (1..16) streaming at 72 Hz each from one server; p99 latency per K.

    python benchmarks/capacity.py --gaussians 100000 --rate 72 --seconds 3 --encoding f16 --json out.json

One server (subprocess, fast path) and K clients in one asyncio process, each sending the capture's
blendshapes on its own fixed schedule (offset so the K streams interleave) and stamping the scheduled
time (no coordinated omission). Latency = frame received - scheduled send time. By default clients read
each frame's header only (``--decode header``: a renderer decodes on its own machine; here K decoders
would compete with the server for the same 2 cores); ``--decode full`` decodes the arrays too (numba
decoder, the codec's checks and values).
The result: p50/p99 per K, frames skipped, and the largest K whose p99 stays below --budget-ms (13.9 ms,
one 72 Hz frame). The reference server (numpy) is run the same way for --reference-sessions.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402
from latency import _frame_header  # noqa: E402


async def run_k(clients, k: int, weights, rate: float, seconds: float, warmup: float, decode: bool,
                seq0: int) -> dict:
    """Clients[:k] stream for warmup + seconds; returns latencies (ms) after warm-up and counts."""
    from ofera.client import now_us
    from ofera.streaming.encode_fast import FastFrameDecoder
    from ofera_protocol import Frame

    period = 1e6 / rate
    total = int((warmup + seconds) * rate)
    first = seq0 + int(warmup * rate)
    last = seq0 + total - 1
    start = now_us() + 200_000
    lat: list[float] = []
    received = np.zeros(k, np.int64)

    async def one(i: int, client) -> None:
        offset = i * period / k
        decoder = FastFrameDecoder(client.conn.format) if decode else None

        async def sender() -> None:
            for j in range(total):
                due = start + offset + j * period
                delay = (due - now_us()) / 1e6
                if delay > 0:
                    await asyncio.sleep(delay)
                await client.send_bs(weights[(j + 7 * i) % len(weights)], seq=seq0 + j, t=int(due))

        async def receiver() -> None:
            while True:
                data = await client.ws.recv()
                if decoder is not None:
                    msg = decoder.decode(data)
                    if not isinstance(msg, Frame):
                        continue
                    seq, t = msg.seq, msg.t
                else:
                    seq, t, _ = _frame_header(data)
                    if seq is None:
                        continue
                if seq >= first:
                    lat.append((now_us() - t) / 1000.0)
                    received[i] += 1
                if seq >= last:
                    return

        rt = asyncio.create_task(receiver())
        await sender()
        try:
            await asyncio.wait_for(rt, timeout=2.0)
        except asyncio.TimeoutError:
            rt.cancel()

    await asyncio.gather(*(one(i, c) for i, c in enumerate(clients[:k])))
    sent = k * (total - int(warmup * rate))
    return {"lat": lat, "sent": sent, "received": int(received.sum()), "next_seq": seq0 + total}


async def sweep(url: str, ks: list[int], weights, layout: str, args) -> dict:
    from ofera.client import connect

    clients = []
    for _ in range(max(ks)):
        clients.append(await connect(url, layout=layout, encoding=args.encoding, sparse=args.sparse))
    out = {}
    seq = 0
    try:
        for k in ks:
            r = await run_k(clients, k, weights, args.rate, args.seconds, args.warmup, args.decode == "full", seq)
            seq = r["next_seq"]
            p = C.pct(r["lat"])
            out[k] = {"p50_ms": p["p50"], "p99_ms": p["p99"], "max_ms": p["max"], "frames": r["received"],
                      "skipped": r["sent"] - r["received"], "_lat": r["lat"]}
            print(f"  K={k:2d}: p50 {p['p50']} ms, p99 {p['p99']} ms, skipped {r['sent'] - r['received']} of "
                  f"{r['sent']}", flush=True)
            await asyncio.sleep(0.3)
    finally:
        for c in clients:
            await c.close()
    return out


def largest_ok(results: dict, budget: float) -> int:
    ok = [k for k, r in results.items() if r["p99_ms"] is not None and r["p99_ms"] < budget]
    # the largest K such that every K' <= K passed (a later pass after a failure is noise)
    best = 0
    for k in sorted(results):
        if k in ok:
            best = k
        else:
            break
    return best


def plot(path: Path, runs: dict, budget: float, title: str) -> None:
    plt = C.pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    colors = {"fast": "tab:blue", "reference": "tab:red"}
    for impl, res in runs.items():
        ks = sorted(res)
        ax[0].plot(ks, [res[k]["p99_ms"] for k in ks], "o-", color=colors[impl], label=f"{impl} p99")
        ax[0].plot(ks, [res[k]["p50_ms"] for k in ks], "o--", color=colors[impl], alpha=0.6, label=f"{impl} p50")
        if impl == "fast":
            ax[1].boxplot([res[k]["_lat"] or [np.nan] for k in ks], positions=ks, widths=0.6, showfliers=False)
    for a in ax:
        a.axhline(budget, color="grey", ls="--", lw=0.8, label=f"budget {budget} ms")
        a.set_xlabel("concurrent sessions K")
        a.set_yscale("log")
    ax[0].set_ylabel("latency (ms, log)")
    ax[0].legend(fontsize=8)
    ax[1].set_ylabel("fast: latency distribution per K (ms, log)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--rate", type=float, default=72.0)
    ap.add_argument("--seconds", type=float, default=3.0, help="measured seconds per K")
    ap.add_argument("--warmup", type=float, default=0.5)
    ap.add_argument("--sessions", default="1,2,4,6,8,10,12,16", help="K values, comma-separated")
    ap.add_argument("--reference-sessions", default="1,2", help="K values for the reference server ('' = none)")
    ap.add_argument("--encoding", default="f16", choices=["f32", "f16", "q13"])
    ap.add_argument("--sparse", action="store_true")
    ap.add_argument("--decode", default="header", choices=["header", "full"])
    ap.add_argument("--budget-ms", type=float, default=13.9)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=C.RESULTS / "capacity.json")
    args = ap.parse_args(argv)

    weights, layout, _, notes = C.capture()
    avatars, epm_notes = C.avatars_dir(args.gaussians or None)
    notes += epm_notes
    plan = {"fast": [int(k) for k in args.sessions.split(",") if k.strip()],
            "reference": [int(k) for k in args.reference_sessions.split(",") if k.strip()]}
    runs = {}
    for impl, ks in plan.items():
        if not ks:
            continue
        print(f"[capacity] {impl}: K = {ks}, {args.encoding}{' sparse' if args.sparse else ''}, {args.rate:g} Hz, "
              f"{args.seconds:g} s each", flush=True)
        with C.ServerProcess(avatars, impl=impl, threads=args.threads) as server:
            runs[impl] = asyncio.run(sweep(server.url, ks, weights, layout, args))
    fast = runs["fast"]
    report = {
        "benchmark": "capacity",
        "gaussians": args.gaussians,
        "rate_hz": args.rate,
        "encoding": args.encoding,
        "sparse": args.sparse,
        "client_decode": args.decode,
        "budget_ms": args.budget_ms,
        "per_k": {str(k): {kk: v for kk, v in r.items() if not kk.startswith("_")} for k, r in fast.items()},
        "max_sessions_within_budget": largest_ok(fast, args.budget_ms),
        "target_sessions": 8,
        "definitions": {"latency": "frame received (header read) - scheduled send time of its bs, loopback"},
        "machine": C.machine(),
        "notes": notes,
    }
    if "reference" in runs:
        ref = runs["reference"]
        report["reference"] = {"per_k": {str(k): {kk: v for kk, v in r.items() if not kk.startswith("_")}
                                         for k, r in ref.items()},
                               "max_sessions_within_budget": largest_ok(ref, args.budget_ms)}
        report["ratios_p99"] = {str(k): C.ratio(fast[k]["p99_ms"], ref[k]["p99_ms"]) for k in ref if k in fast}
    rows = []
    for impl, res in runs.items():
        for k in sorted(res):
            r = res[k]
            rows.append([impl, k, r["frames"], r["skipped"], r["p50_ms"], r["p99_ms"], r["max_ms"],
                         "yes" if r["p99_ms"] is not None and r["p99_ms"] < args.budget_ms else "no"])
    print(C.table(rows, ["impl", "K", "frames", "skipped", "p50 ms", "p99 ms", "max ms",
                         f"p99<{args.budget_ms:g}"]))
    print(f"largest K within budget: fast {report['max_sessions_within_budget']}"
          + (f", reference {report['reference']['max_sessions_within_budget']}" if "reference" in report else ""))
    for n in notes:
        print("note:", n)
    out = C.write_json(args.json, report)
    png = C.png_path(out)
    plot(png, runs, args.budget_ms, f"{args.gaussians} Gaussians, {args.encoding}, {args.rate:g} Hz per session, "
         f"loopback ({C.machine()['cpus']} CPUs, clients on the same machine)")
    print(f"wrote {out} and {png}")
    return report


if __name__ == "__main__":
    main()
