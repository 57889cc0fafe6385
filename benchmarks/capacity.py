"""Concurrent sessions: K clients (1..16) streaming at 72 Hz each from one server; p99 latency per K.

    python benchmarks/capacity.py --gaussians 100000 --rate 72 --seconds 3 --encoding f16 --json out.json

One server (subprocess, fast path) and K clients in one asyncio process (``--client-procs P``: spread over P
processes, so one client event loop is not the bottleneck measured), each sending the capture's
blendshapes on its own fixed schedule (offset so the K streams interleave) and stamping the scheduled
time (no coordinated omission). Latency = frame received - scheduled send time; a bs that no frame answered
(newest-wins dropped it) counts too, with the latency of the first later frame (its arrival - the dropped
bs's scheduled time). By default clients read
each frame's header only (``--decode header``: a renderer decodes on its own machine; here K decoders
would compete with the server for the same 2 cores); ``--decode full`` decodes the arrays too (numba
decoder, the codec's checks and values). ``--encoding params`` (PROTOCOL.md 13): the server stamps every params
frame (OFERA_PARAMS_STAMP_INTERVAL=0); with ``--decode full`` each client deforms its Gaussians itself
(``ofera.client.params.RigDeformer``), which a frame's latency then includes.
The result: p50/p99 per K, frames skipped (bs dropped), and the largest K such that every K' <= K passes:
at most --max-drop of its bs dropped (1 %) and p99 below --budget-ms (13.9 ms, one 72 Hz frame). The
reference server (numpy) is run the same way for --reference-sessions.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402
from latency import _frame_header  # noqa: E402


async def run_k(clients, k: int, weights, rate: float, seconds: float, warmup: float, decode: bool,
                seq0: int, indices: list[int] | None = None, start: float | None = None) -> dict:
    """Clients[:k] stream for warmup + seconds; returns latencies (ms) after warm-up, answered and dropped bs
    alike, and counts. ``indices``: the session numbers (of k) of ``clients`` when they are a worker's share
    (default 0..k-1); ``start``: the common start time (us, wall clock) of every worker."""
    from ofera.client import now_us
    from ofera.client.fast_decode import FastFrameDecoder
    from ofera_protocol import Frame

    period = 1e6 / rate
    total = int((warmup + seconds) * rate)
    first = seq0 + int(warmup * rate)
    last = seq0 + total - 1
    start = now_us() + 200_000 if start is None else start
    indices = list(range(k)) if indices is None else indices
    lat: list[float] = []
    dropped: list[float] = []
    received = np.zeros(k, np.int64)

    async def one(i: int, client) -> None:
        offset = i * period / k
        params = client.conn.rig is not None  # a params session: the values, then (decode) the client's deformation
        decoder = FastFrameDecoder(client.conn.format) if decode and not params else None
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
                if params:
                    msg = C.read_params_frame(client, data, client.rig_deformer)
                    if msg is None:
                        continue
                    seq, t = msg.seq, msg.t
                elif decoder is not None:
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

    await asyncio.gather(*(one(i, c) for i, c in zip(indices, clients)))
    sent = len(indices) * (total - int(warmup * rate))
    return {"lat": lat + dropped, "sent": sent, "received": int(received.sum()), "dropped": len(dropped),
            "next_seq": seq0 + total}


def hello(args) -> dict:
    params = args.encoding == "params"
    return {"encoding": args.encoding, "sparse": args.sparse, "delta": args.delta,
            "track": params and args.decode == "full"}


async def worker_main(spec: dict) -> None:
    """A client process (--client-procs > 1): connect this share of the sessions, print "ready", read the common
    start time from stdin, stream, print the result (JSON) with the CPU this process used."""
    from ofera.client import connect
    from ofera.client.fast_decode import decoder_warm

    weights, layout, _, _ = C.capture()
    decoder_warm()  # compiled (or loaded) before connecting: a first compile blocks the loop past the keepalive
    clients = [await connect(spec["url"], layout=layout, **spec["hello"]) for _ in spec["indices"]]
    print("ready", flush=True)
    start = float(await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline))
    cpu0 = C.cpu_seconds()
    r = await run_k(clients, spec["k"], weights, spec["rate"], spec["seconds"], spec["warmup"], spec["decode"],
                    spec["seq0"], spec["indices"], start)
    r["cpu_s"] = C.cpu_seconds() - cpu0
    for c in clients:
        await c.close()
    print(json.dumps(r), flush=True)


def run_k_processes(url: str, k: int, procs: int, args, seq0: int) -> dict:
    """run_k with the k sessions spread over `procs` client processes (each its own interpreter and GIL)."""
    from ofera.client import now_us

    shares = [list(range(k))[i::procs] for i in range(min(procs, k))]
    workers = []
    for share in shares:
        spec = {"url": url, "hello": hello(args), "indices": share, "k": k, "rate": args.rate,
                "seconds": args.seconds, "warmup": args.warmup, "decode": args.decode == "full", "seq0": seq0}
        workers.append(subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True))
    try:
        for w in workers:
            line = w.stdout.readline()
            if line.strip() != "ready":
                raise RuntimeError(f"a client process failed to connect: {line!r}")
        start = now_us() + 300_000
        t0 = time.monotonic()
        for w in workers:
            w.stdin.write(f"{start}\n")
            w.stdin.flush()
        results = [json.loads(w.stdout.readline()) for w in workers]
        wall = time.monotonic() - t0
    finally:
        for w in workers:
            if w.poll() is None:
                w.kill()
            w.wait()
    return {"lat": [x for r in results for x in r["lat"]], "sent": sum(r["sent"] for r in results),
            "received": sum(r["received"] for r in results), "dropped": sum(r["dropped"] for r in results),
            "next_seq": results[0]["next_seq"], "client_cores": round(sum(r["cpu_s"] for r in results) / wall, 3)}


async def sweep(url: str, ks: list[int], weights, layout: str, args, server_pid: int | None = None) -> dict:
    from ofera.client import connect
    from ofera.client.fast_decode import decoder_warm

    decoder_warm()  # compiled (or loaded) before connecting: a first compile blocks the loop past the keepalive
    clients = []
    if args.client_procs <= 1:
        for _ in range(max(ks)):
            clients.append(await connect(url, layout=layout, **hello(args)))
    out = {}
    seq = 0
    try:
        for k in ks:
            with C.CpuMeter(server_pid) as cpu:
                if args.client_procs > 1:
                    r = await asyncio.get_running_loop().run_in_executor(None, run_k_processes, url, k,
                                                                         args.client_procs, args, seq)
                else:
                    r = await run_k(clients[:k], k, weights, args.rate, args.seconds, args.warmup,
                                    args.decode == "full", seq)
            seq = r["next_seq"]
            usage = cpu.report()
            if "client_cores" in r:  # client processes: their own CPU time (this process only waited)
                usage["client_cores"] = r["client_cores"]
            p = C.pct(r["lat"])
            out[k] = {"p50_ms": p["p50"], "p99_ms": p["p99"], "max_ms": p["max"], "sent": r["sent"],
                      "frames": r["received"], "skipped": r["dropped"],
                      "drop_fraction": round(r["dropped"] / r["sent"], 4), "cpu": usage, "_lat": r["lat"]}
            out[k]["passes"] = passes(out[k], args.budget_ms, args.max_drop)
            print(f"  K={k:2d}: p50 {p['p50']} ms, p99 {p['p99']} ms, skipped {r['dropped']} of {r['sent']} "
                  f"({100 * out[k]['drop_fraction']:.1f}%), cores: clients {usage['client_cores']}, server "
                  f"{usage['server_cores']}", flush=True)
            await asyncio.sleep(0.3)
    finally:
        for c in clients:
            await c.close()
    return out


def passes(r: dict, budget: float, max_drop: float) -> bool:
    """A K passes with at most `max_drop` of its bs dropped and p99 (dropped bs included) under `budget`."""
    return r["drop_fraction"] <= max_drop and r["p99_ms"] is not None and r["p99_ms"] < budget


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


def session_counts(ap: argparse.ArgumentParser, flag: str, text: str) -> list[int]:
    """A comma list of session counts (each >= 1; '' = none), or the parser's usage error naming the flag."""
    try:
        ks = [int(k) for k in text.split(",") if k.strip()]
    except ValueError:
        ap.error(f"{flag} takes a comma list of whole numbers, got {text!r}")
    if any(k < 1 for k in ks):
        ap.error(f"{flag}: every session count must be at least 1 (use '' for none), got {text!r}")
    return ks


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--rate", type=float, default=72.0)
    ap.add_argument("--seconds", type=float, default=3.0, help="measured seconds per K")
    ap.add_argument("--warmup", type=float, default=0.5)
    ap.add_argument("--sessions", default="1,2,4,6,8,10,12,16", help="K values, comma-separated")
    ap.add_argument("--reference-sessions", default="1,2", help="K values for the reference server ('' = none)")
    ap.add_argument("--encoding", default="f16", choices=["f32", "f16", "q13", "params"],
                    help="params (PROTOCOL.md 13): with --decode full each client deforms its Gaussians itself")
    ap.add_argument("--sparse", action="store_true")
    ap.add_argument("--delta", action="store_true", help="delta sessions (hello.delta): the compact stream")
    ap.add_argument("--decode", default="header", choices=["header", "full"])
    ap.add_argument("--client-procs", type=int, default=1, help="spread the K clients over this many processes "
                    "(1: all in this process's event loop)")
    ap.add_argument("--budget-ms", type=float, default=13.9, help="p99 bound of a passing K")
    ap.add_argument("--max-drop", type=float, default=0.01, help="largest fraction of bs dropped in a passing K")
    ap.add_argument("--event-loop", default="auto", choices=["auto", "asyncio", "uvloop"],
                    help="the server's event loop (auto: what ofera serve picks)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=C.RESULTS / "capacity.json")
    args = ap.parse_args(argv)
    plan = {"fast": session_counts(ap, "--sessions", args.sessions),
            "reference": session_counts(ap, "--reference-sessions", args.reference_sessions)}

    weights, layout, _, notes = C.capture()
    avatars, epm_notes = C.avatars_dir(args.gaussians or None)
    notes += epm_notes
    runs = {}
    for impl, ks in plan.items():
        if not ks:
            continue
        print(f"[capacity] {impl}: K = {ks}, {args.encoding}{' sparse' if args.sparse else ''}, {args.rate:g} Hz, "
              f"{args.seconds:g} s each", flush=True)
        stamped = C.params_stamped_every_frame() if args.encoding == "params" else contextlib.nullcontext()
        with stamped, C.ServerProcess(avatars, impl=impl, threads=args.threads,
                         extra={"event_loop": args.event_loop}) as server:
            runs[impl] = asyncio.run(sweep(server.url, ks, weights, layout, args, server.proc.pid))
    fast = runs["fast"]
    report = {
        "benchmark": "capacity",
        "gaussians": args.gaussians,
        "rate_hz": args.rate,
        "encoding": args.encoding,
        "sparse": args.sparse,
        "client_decode": args.decode,
        "delta": args.delta,
        "client_procs": args.client_procs,
        "budget_ms": args.budget_ms,
        "max_drop": args.max_drop,
        "per_k": {str(k): {kk: v for kk, v in r.items() if not kk.startswith("_")} for k, r in fast.items()},
        "max_sessions_within_budget": C.largest_ok(fast),
        "target_sessions": 8,
        "definitions": {"latency": "frame received (header read) - scheduled send time of its bs, loopback; a "
                                   "dropped bs counts with the arrival of the first later frame",
                        "skipped": "bs sent after warm-up that no frame answered (newest-wins dropped them)",
                        "passes": "drop_fraction <= max_drop and p99_ms < budget_ms",
                        "cpu": "cores used on average per K: the client processes and the server"},
        "machine": C.machine(),
        "notes": notes,
    }
    if "reference" in runs:
        ref = runs["reference"]
        report["reference"] = {"per_k": {str(k): {kk: v for kk, v in r.items() if not kk.startswith("_")}
                                         for k, r in ref.items()},
                               "max_sessions_within_budget": C.largest_ok(ref)}
        report["ratios_p99"] = {str(k): C.ratio(fast[k]["p99_ms"], ref[k]["p99_ms"]) for k in ref if k in fast}
    rows = []
    for impl, res in runs.items():
        for k in sorted(res):
            r = res[k]
            rows.append([impl, k, r["frames"], r["skipped"], f"{100 * r['drop_fraction']:.1f}", r["p50_ms"],
                         r["p99_ms"], r["max_ms"], r["cpu"]["client_cores"], r["cpu"]["server_cores"],
                         "yes" if r["passes"] else "no"])
    print(C.table(rows, ["impl", "K", "frames", "skipped", "drop %", "p50 ms", "p99 ms", "max ms", "client cores",
                         "server cores", f"pass (drop<={100 * args.max_drop:g}%, p99<{args.budget_ms:g})"]))
    print("load average:", C.machine()["loadavg_at_start"])
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


if __name__ == "__main__" and len(sys.argv) == 3 and sys.argv[1] == "--worker":
    asyncio.run(worker_main(json.loads(sys.argv[2])))
elif __name__ == "__main__":
    main()
