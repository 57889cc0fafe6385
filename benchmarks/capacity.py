"""Concurrent sessions: K clients (1..16) streaming at 72 Hz each from one server; p99 latency per K.

    python benchmarks/capacity.py --gaussians 100000 --rate 72 --seconds 3 --encoding f16 --json out.json

One server (subprocess, fast path) and K clients in one asyncio process, each sending the capture's
blendshapes on its own fixed schedule (offset so the K streams interleave) and stamping the scheduled
time (no coordinated omission). Latency = frame received - scheduled send time; a bs that no frame answered
(newest-wins dropped it) counts too, with the latency of the first later frame (its arrival - the dropped
bs's scheduled time). By default clients read
each frame's header only (``--decode header``: a renderer decodes on its own machine; here K decoders
would compete with the server for the same 2 cores); ``--decode full`` decodes the arrays too (numba
decoder, the codec's checks and values).
The result: p50/p99 per K, frames skipped (bs dropped), and the largest K such that every K' <= K passes:
at most --max-drop of its bs dropped (1 %) and p99 below --budget-ms (13.9 ms, one 72 Hz frame). The
reference server (numpy) is run the same way for --reference-sessions.
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
    """Clients[:k] stream for warmup + seconds; returns latencies (ms) after warm-up, answered and dropped bs
    alike, and counts."""
    from ofera.client import now_us
    from ofera.client.fast_decode import FastFrameDecoder
    from ofera_protocol import Frame

    period = 1e6 / rate
    total = int((warmup + seconds) * rate)
    first = seq0 + int(warmup * rate)
    last = seq0 + total - 1
    start = now_us() + 200_000
    lat: list[float] = []
    dropped: list[float] = []
    received = np.zeros(k, np.int64)

    async def one(i: int, client) -> None:
        offset = i * period / k
        decoder = FastFrameDecoder(client.conn.format) if decode else None
        arrivals: list[tuple[int, float]] = []

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
                    now = now_us()
                    lat.append((now - t) / 1000.0)
                    arrivals.append((seq, now))
                    received[i] += 1
                if seq >= last:
                    return

        rt = asyncio.create_task(receiver())
        await sender()
        try:
            await asyncio.wait_for(rt, timeout=2.0)
        except asyncio.TimeoutError:
            rt.cancel()
        scheduled = {seq0 + j: start + offset + j * period for j in range(first - seq0, total)}
        dropped.extend(C.drop_latencies(scheduled, arrivals, now_us()).values())

    await asyncio.gather(*(one(i, c) for i, c in enumerate(clients[:k])))
    sent = k * (total - int(warmup * rate))
    return {"lat": lat + dropped, "sent": sent, "received": int(received.sum()), "dropped": len(dropped),
            "next_seq": seq0 + total}


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
            out[k] = {"p50_ms": p["p50"], "p99_ms": p["p99"], "max_ms": p["max"], "sent": r["sent"],
                      "frames": r["received"], "skipped": r["dropped"],
                      "drop_fraction": round(r["dropped"] / r["sent"], 4), "_lat": r["lat"]}
            out[k]["passes"] = passes(out[k], args.budget_ms, args.max_drop)
            print(f"  K={k:2d}: p50 {p['p50']} ms, p99 {p['p99']} ms, skipped {r['dropped']} of {r['sent']} "
                  f"({100 * out[k]['drop_fraction']:.1f}%)", flush=True)
            await asyncio.sleep(0.3)
    finally:
        for c in clients:
            await c.close()
    return out


def passes(r: dict, budget: float, max_drop: float) -> bool:
    """A K passes with at most `max_drop` of its bs dropped and p99 (dropped bs included) under `budget`."""
    return r["drop_fraction"] <= max_drop and r["p99_ms"] is not None and r["p99_ms"] < budget


def largest_ok(results: dict) -> int:
    """The largest K such that every K' <= K passed (a later pass after a failure is noise)."""
    best = 0
    for k in sorted(results):
        if not results[k]["passes"]:
            break
        best = k
    return best


def plot(path: Path, runs: dict, budget: float, max_drop: float, title: str) -> None:
    plt = C.pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(17, 4.5))
    colors = {"fast": "tab:blue", "reference": "tab:red"}
    for impl, res in runs.items():
        ks = sorted(res)
        ax[0].plot(ks, [res[k]["p99_ms"] for k in ks], "o-", color=colors[impl], label=f"{impl} p99")
        ax[0].plot(ks, [res[k]["p50_ms"] for k in ks], "o--", color=colors[impl], alpha=0.6, label=f"{impl} p50")
        if impl == "fast":
            ax[1].boxplot([res[k]["_lat"] or [np.nan] for k in ks], positions=ks, widths=0.6, showfliers=False)
        ax[2].plot(ks, [100 * res[k]["drop_fraction"] for k in ks], "o-", color=colors[impl], label=impl)
    for a in ax[:2]:
        a.axhline(budget, color="grey", ls="--", lw=0.8, label=f"budget {budget} ms")
        a.set_yscale("log")
    for a in ax:
        a.set_xlabel("concurrent sessions K")
    ax[0].set_ylabel("latency, dropped bs included (ms, log)")
    ax[0].legend(fontsize=8)
    ax[1].set_ylabel("fast: latency distribution per K (ms, log)")
    ax[2].axhline(100 * max_drop, color="grey", ls="--", lw=0.8, label=f"limit {100 * max_drop:g} %")
    ax[2].set_ylabel("bs dropped (%)")
    ax[2].legend(fontsize=8)
    C.save_figure(fig, path, title)


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
    ap.add_argument("--budget-ms", type=float, default=13.9, help="p99 bound of a passing K")
    ap.add_argument("--max-drop", type=float, default=0.01, help="largest fraction of bs dropped in a passing K")
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
        "max_drop": args.max_drop,
        "per_k": {str(k): {kk: v for kk, v in r.items() if not kk.startswith("_")} for k, r in fast.items()},
        "max_sessions_within_budget": largest_ok(fast),
        "target_sessions": 8,
        "definitions": {"latency": "frame received (header read) - scheduled send time of its bs, loopback; a "
                                   "dropped bs counts with the arrival of the first later frame",
                        "skipped": "bs sent after warm-up that no frame answered (newest-wins dropped them)",
                        "passes": "drop_fraction <= max_drop and p99_ms < budget_ms"},
        "machine": C.machine(),
        "notes": notes,
    }
    if "reference" in runs:
        ref = runs["reference"]
        report["reference"] = {"per_k": {str(k): {kk: v for kk, v in r.items() if not kk.startswith("_")}
                                         for k, r in ref.items()},
                               "max_sessions_within_budget": largest_ok(ref)}
        report["ratios_p99"] = {str(k): C.ratio(fast[k]["p99_ms"], ref[k]["p99_ms"]) for k in ref if k in fast}
    rows = []
    for impl, res in runs.items():
        for k in sorted(res):
            r = res[k]
            rows.append([impl, k, r["frames"], r["skipped"], f"{100 * r['drop_fraction']:.1f}", r["p50_ms"],
                         r["p99_ms"], r["max_ms"], "yes" if r["passes"] else "no"])
    print(C.table(rows, ["impl", "K", "frames", "skipped", "drop %", "p50 ms", "p99 ms", "max ms",
                         f"pass (drop<={100 * args.max_drop:g}%, p99<{args.budget_ms:g})"]))
    print(f"largest K passing: fast {report['max_sessions_within_budget']}"
          + (f", reference {report['reference']['max_sessions_within_budget']}" if "reference" in report else ""))
    for n in notes:
        print("note:", n)
    out = C.write_json(args.json, report)
    png = C.png_path(out)
    plot(png, runs, args.budget_ms, args.max_drop, f"{args.gaussians} Gaussians, {args.encoding}, {args.rate:g} Hz "
         f"per session, loopback ({C.machine()['cpus']} CPUs, clients on the same machine)")
    print(f"wrote {out} and {png}")
    return report


if __name__ == "__main__":
    main()
