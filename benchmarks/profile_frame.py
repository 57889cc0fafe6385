"""Where one frame's time goes, end to end: bs sent on a fixed schedule -> its frame decoded by the client.

    python benchmarks/profile_frame.py --gaussians 100000 --rate 72 --frames 400 --encoding f16 --json prof.json

A server in a subprocess (``_common.ServerProcess``: its own interpreter and GIL), one client here, a bs every
1/--rate s carrying its scheduled time. Every stage is measured where it happens, per frame where it can be:

  client   bs_send      scheduled time -> bs written to the client's socket (loop lateness + bs encoding;
                        the sender spins the last 3 ms: _common.sleep_until)
  server   decode       bs bytes received -> decoded and validated          (frame.timing, per frame)
           queue        decoded -> computation starts (thread pool hand-off) (frame.timing)
           layout, bda, epm, head, deform                                    (frame.timing)
           encode       frame computed -> message written (frame writer)    (frame.timing on the fast path;
                                                                              /metrics on the reference)
           send         message handed to the transport: the writes' time on the event loop (bytes into
                        the kernel; /metrics histogram over the run, no per-frame value)
           drain        until the kernel took every byte (/metrics)
  client   decode       message received -> arrays decoded (numba decoder; --client-decode)
  rest     wire_and_loops  e2e minus everything above: the two loopback hops, the server's receive and
                        viewer hand-offs, the client library reading the message (the part no clock isolates;
                        compare with transport_floor_ms: the same message size echoed with no compute)

Medians and p99 over --frames frames (after --warmup s), fast path and reference in the same run (--impl),
the CPU the client process and the server used (cores), the machine's load average. JSON + PNG (a stacked
bar of the medians per implementation). benchmarks/README.md keeps the table current.

Where frames differ in size (delta sessions: a frame carries what moved), `by_size` fits each per-frame stage and
e2e to the message size: ms = intercept + slope * kB over the frames (least squares), with the correlation and the
size range, so the p99 can be told apart from jitter (a heavy frame's cost) by command.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

SERVER_STAGES = ("decode", "queue", "layout", "bda", "epm", "head", "deform", "encode")
ORDER = ("bs_send", *SERVER_STAGES, "send", "drain", "client_decode", "wire_and_loops")


async def stream(url: str, weights: np.ndarray, layout: str, args) -> dict:
    """One client streaming on a fixed schedule; per-frame client-side stamps (us) and the frame's timing."""
    from ofera.client import connect, now_us
    from ofera.client.fast_decode import FastFrameDecoder, decoder_warm
    from ofera_protocol import Frame

    if args.client_decode == "fast":
        decoder_warm()  # compiled (or loaded) before connecting: a first compile blocks the loop past the keepalive
    client = await connect(url, layout=layout, encoding=args.encoding, sparse=args.sparse, delta=args.delta,
                           transport=args.client_transport)
    fast = FastFrameDecoder(client.conn.format) if args.client_decode == "fast" else None  # delta frames too
    period = 1e6 / args.rate
    first = int(args.warmup * args.rate)
    total = first + args.frames
    start = now_us() + 200_000
    sent_at: dict[int, float] = {}
    rows: list[dict] = []
    arrivals: list[tuple[int, float]] = []
    done = asyncio.Event()

    async def sender() -> None:
        for k in range(total):
            due = start + k * period
            await C.sleep_until(due)
            await client.send_bs(weights[k % len(weights)], seq=k, t=int(due))
            sent_at[k] = now_us()

    async def receiver() -> None:
        while True:
            data = await client.ws.recv()
            got = now_us()
            msg = fast.decode(data) if fast is not None else client.conn.receive(data)
            decoded = now_us()
            if not isinstance(msg, Frame):
                continue
            if msg.seq >= first and msg.seq in sent_at:
                rows.append({"seq": msg.seq, "e2e": (decoded - msg.t) / 1e3,
                             "bs_send": (sent_at[msg.seq] - msg.t) / 1e3, "client_decode": (decoded - got) / 1e3,
                             "timing": dict(msg.timing), "bytes": len(data)})
                arrivals.append((msg.seq, decoded))
            if msg.seq >= total - 1:
                done.set()
                return

    rt = asyncio.create_task(receiver())
    await sender()
    try:
        await asyncio.wait_for(rt, timeout=3.0)
    except asyncio.TimeoutError:
        rt.cancel()
    end = now_us()
    await client.close()
    scheduled = {k: start + k * period for k in range(first, total)}
    return {"rows": rows, "sent": total - first, "dropped_ms": C.drop_latencies(scheduled, arrivals, end),
            "count": client.count}


def profile(impl: str, args, weights, layout, avatars: Path) -> dict:
    with C.ServerProcess(avatars, impl=impl, threads=args.threads,
                         extra=C.server_extra(args.pinned, event_loop=args.event_loop,
                                              kernel_threads=args.kernel_threads),
                         pythonpath=args.server_path) as server:
        http = f"http://127.0.0.1:{server.port}"
        before = C.stage_histograms(C.metrics_text(http))
        with C.CpuMeter(server.proc.pid) as cpu:
            run = asyncio.run(stream(server.url, weights, layout, args))
        after = C.stage_histograms(C.metrics_text(http))
        health = C.server_health(server.port)
    event_loop, server_cpus = health.get("event_loop"), health.get("cpus")
    rows = run["rows"]
    per_frame: dict[str, list[float]] = {k: [] for k in ORDER}
    metrics = {s: C.histogram_window(before, after, s) for s in ("encode", "send", "drain")}
    for r in rows:
        t = r["timing"]
        for s in SERVER_STAGES:
            if s in t:
                per_frame[s].append(t[s] / 1e3)
        per_frame["bs_send"].append(r["bs_send"])
        per_frame["client_decode"].append(r["client_decode"])
        encode = t["encode"] / 1e3 if "encode" in t else (metrics["encode"]["mean"] or 0.0)
        known = (r["bs_send"] + sum(t.get(s, 0) for s in SERVER_STAGES if s != "encode") / 1e3 + encode
                 + (metrics["send"]["mean"] or 0.0) + (metrics["drain"]["mean"] or 0.0) + r["client_decode"])
        per_frame["wire_and_loops"].append(r["e2e"] - known)
    stages = {}
    for s in ORDER:
        if per_frame[s]:
            p = C.pct(per_frame[s])
            stages[s] = {"p50": p["p50"], "p99": p["p99"], "source": "per frame"}
        elif s in metrics and metrics[s]["count"]:
            stages[s] = {"p50": metrics[s]["p50"], "p99": metrics[s]["p99"], "mean": metrics[s]["mean"],
                         "source": "/metrics histogram (bucket-interpolated)"}
    compute = [sum(r["timing"].get(s, 0) for s in ("head", "deform", "encode")) / 1e3 for r in rows]
    e2e = [r["e2e"] for r in rows]
    dropped = list(run["dropped_ms"].values())
    return {"event_loop": event_loop, "server_cpus": server_cpus,
            "frames": len(rows), "frames_sent": run["sent"], "frames_skipped": len(dropped),
            "e2e_ms": C.pct(e2e + dropped), "answered_e2e_ms": C.pct(e2e), "stages_ms": stages,
            "head_deform_encode_ms": C.pct(compute) if rows and "encode" in rows[0]["timing"] else None,
            "bytes_per_frame": int(np.median([r["bytes"] for r in rows])) if rows else None,
            "by_size": by_size(rows, per_frame) if rows else None, "cpu": cpu.report(), "count": run["count"]}


def by_size(rows: list[dict], per_frame: dict[str, list[float]]) -> dict | None:
    """Per stage (and e2e): {intercept_ms, ms_per_kb, r} of a least-squares line against the message size, and the
    sizes' {min, p50, max} kB; None when the frames are all (nearly) one size."""
    kb = np.array([r["bytes"] for r in rows], np.float64) / 1e3
    if kb.size < 10 or kb.max() - kb.min() < 0.05 * kb.max():
        return None
    series = {s: v for s, v in per_frame.items() if len(v) == kb.size}
    series["e2e"] = [r["e2e"] for r in rows]
    fits = {}
    for s, v in series.items():
        y = np.asarray(v, np.float64)
        if y.std() == 0:
            continue
        slope, intercept = np.polyfit(kb, y, 1)
        fits[s] = {"intercept_ms": round(float(intercept), 4), "ms_per_kb": round(float(slope), 6),
                   "r": round(float(np.corrcoef(kb, y)[0, 1]), 3)}
    return {"kb": {"min": round(float(kb.min()), 1), "p50": round(float(np.median(kb)), 1),
                   "max": round(float(kb.max()), 1)}, "fits": fits}


def plot(path: Path, results: dict, title: str) -> None:
    plt = C.pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(14, 4.8))
    impls = list(results)
    for a, key in zip(ax, ("p50", "p99")):
        bottom = np.zeros(len(impls))
        for s in ORDER:
            vals = np.array([max(0.0, (results[i]["stages_ms"].get(s) or {}).get(key) or 0.0) for i in impls])
            a.bar(impls, vals, bottom=bottom, label=s)
            bottom += vals
        a.set_ylabel(f"stage {key}, stacked (ms)")
        a.set_title(f"per-stage {key} (a stack of {key}s is not the e2e {key})", fontsize=9)
    ax[1].legend(fontsize=7, ncol=2, loc="upper right")
    C.save_figure(fig, path, title)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--rate", type=float, default=72.0)
    ap.add_argument("--frames", type=int, default=400, help="frames measured per implementation")
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--encoding", default="f16", choices=["f32", "f16", "q13"])
    ap.add_argument("--sparse", action="store_true")
    ap.add_argument("--delta", action="store_true", help="a delta session (hello.delta; f16 or q13)")
    ap.add_argument("--impl", default="both", choices=["both", *C.IMPLS])
    ap.add_argument("--kernel-threads", default="auto", choices=["serial", "auto", "parallel"],
                    help="the server's kernel_threads setting (the fast path's deformation on numba's threads)")
    ap.add_argument("--event-loop", default="auto", choices=["auto", "asyncio", "uvloop"],
                    help="the server's event loop (auto: what ofera serve picks)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--client-decode", default="fast", choices=["fast", "reference"])
    ap.add_argument("--client-transport", default="fast", choices=["fast", "websockets"],
                    help="the client's WebSocket transport (ofera.client.connect(transport=...))")
    ap.add_argument("--no-floor", action="store_true")
    ap.add_argument("--pin", action="store_true", help="the server on every CPU but the last (ofera serve --cpus), "
                    "this client on the last: no preemption between them (benchmarks/README.md, round nine)")
    ap.add_argument("--server-path", default=None, help="PYTHONPATH of the server process only (before/after "
                    "comparisons: another checkout's 'server:protocol' directories; the client stays this tree's)")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "profile_frame.json")
    args = ap.parse_args(argv)
    args.pinned = C.pin_split(args.pin)

    weights, layout, _, notes = C.capture()
    avatars, epm_notes = C.avatars_dir(args.gaussians or None)
    notes += epm_notes
    impls = list(C.IMPLS) if args.impl == "both" else [args.impl]
    load_before = C.machine()["loadavg_at_start"]
    results = {}
    for impl in impls:
        print(f"[profile] {impl}: {args.frames} frames, {args.encoding}{' sparse' if args.sparse else ''}"
              f"{' delta' if args.delta else ''}, {args.rate:g} Hz", flush=True)
        results[impl] = profile(impl, args, weights, layout, avatars)
    first = results[impls[0]]
    floor = None
    if not args.no_floor and first["bytes_per_frame"]:
        floor = C.transport_floor(first["bytes_per_frame"], args.rate, 3.0)
    report = {"benchmark": "profile_frame", "gaussians": first["count"], "rate_hz": args.rate,
              "encoding": args.encoding, "sparse": args.sparse, "delta": args.delta, "order": list(ORDER),
              "server_path": args.server_path, "event_loop": args.event_loop, "kernel_threads": args.kernel_threads,
              "client_transport": args.client_transport, "pin": args.pinned,
              "results": results, "transport_floor_ms": floor,
              "definitions": {"stages": __doc__.split("\n\n")[2], "percentiles": "per stage over the frames that "
                              "arrived; e2e_ms includes skipped bs (first later frame), answered_e2e_ms does not",
                              "cpu": "cores used on average over the run: this process (the client) and the server; "
                                     "steal_pct: the machine's CPU time its hypervisor gave to other guests (%)"},
              "machine": {**C.machine(), "loadavg_before_runs": load_before}, "notes": notes}
    rows = []
    for s in ORDER:
        rows.append([s, *[v for i in impls for v in ((results[i]["stages_ms"].get(s) or {}).get("p50"),
                                                      (results[i]["stages_ms"].get(s) or {}).get("p99"))]])
    rows.append(["e2e", *[v for i in impls for v in (results[i]["e2e_ms"]["p50"], results[i]["e2e_ms"]["p99"])]])
    print(C.table(rows, ["stage (ms)", *[f"{i} {q}" for i in impls for q in ("p50", "p99")]]))
    for i in impls:
        r = results[i]
        print(f"{i}: {r['frames']} frames, {r['frames_skipped']} skipped, {r['bytes_per_frame']} B/frame, "
              f"cpu {r['cpu']}, head+deform+encode {r['head_deform_encode_ms']}")
        if r["by_size"]:
            kb, fits = r["by_size"]["kb"], r["by_size"]["fits"]
            print(f"{i}: by size ({kb['min']}-{kb['max']} kB, median {kb['p50']}): " + ", ".join(
                f"{s} {f['intercept_ms']:.2f} ms + {1e3 * f['ms_per_kb']:.2f} us/kB (r {f['r']:.2f})"
                for s, f in fits.items() if s in ("deform", "encode", "client_decode", "e2e")))
    if floor:
        print(f"transport floor ({floor['bytes']} B): p50 {floor['p50']} ms, p99 {floor['p99']} ms")
    print("load average:", C.machine()["loadavg_at_start"])
    out = C.write_json(args.json, report)
    png = C.png_path(out)
    plot(png, results, f"one frame end to end: {report['gaussians']} Gaussians, {args.encoding}"
         f"{' sparse' if args.sparse else ''}{' delta' if args.delta else ''}, {args.rate:g} Hz, loopback")
    print(f"wrote {out} and {png}")
    return report


if __name__ == "__main__":
    main()
