"""End-to-end latency over a loopback WebSocket: a `bs` sent on a fixed schedule -> its frame decoded.

    python benchmarks/latency.py --gaussians 100000 --rate 72 --seconds 5 --encoding f16 --json out.json

Starts a server in a subprocess serving a procedural avatar of --gaussians Gaussians, connects with the
asyncio client library (ofera.client), and sends the real capture's blendshapes (looped) at --rate Hz.
Send times are fixed by the schedule, and every bs carries its *scheduled* time in `t`, so a stalled
sender or server cannot hide latency (no coordinated omission): latency = decoded - scheduled.
The first --warmup seconds are not counted. Frames skipped = bs sent but never answered (the server's
newest-wins backpressure drops the older ones); each still counts, with the latency of the first later frame
(its arrival - the skipped bs's scheduled time), so dropping frames cannot improve the percentiles.

Runs the fast path (numba head/deform, numba frame writer) and then the straightforward reference
(numpy lbs + Deformer + codec.encode_frame) the same way, and reports both and their ratio
(--impl fast|reference to run one). The client decodes every frame with the numba decoder
(--client-decode fast: the codec's checks and values; a Unity client decodes natively)
or the reference codec. ``--encoding params`` (PROTOCOL.md 13, the most compact stream: 295 B a frame) counts a
frame once the client has deformed its Gaussians from it (``ofera.client.params.RigDeformer``, numba; with
``--client-decode header`` the deformation is skipped); the server then stamps every params frame
(OFERA_PARAMS_STAMP_INTERVAL=0) so that each carries its bs's seq and t.
Prints a table, writes --json and a PNG next to it.
JSON: {"gaussians", "rate_hz", "encoding", "frames", "frames_sent", "frames_skipped", "drop_fraction",
"e2e_ms": {p50, p90, p99, p999, max} (every bs sent, skipped ones included), "answered_e2e_ms" (frames that
arrived only), "server_ms": {p50, p99}, "stages_ms": {...}, "bytes_per_frame", ..., "reference": {same},
"ratios": {...}}.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import re
import sys
import urllib.request
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

COMPUTE_STAGES = ("layout", "bda", "epm", "head", "deform")


def metric_means(http_url: str) -> dict[str, float]:
    """Means (ms) of the server's encode stage and bs -> socket latency, from /metrics."""
    try:
        text = urllib.request.urlopen(f"{http_url}/metrics", timeout=5).read().decode()
    except OSError:
        return {}

    def value(pattern: str) -> float | None:
        m = re.search(pattern + r"\s+([0-9.eE+-]+)", text)
        return float(m.group(1)) if m else None

    out = {}
    for name, base in (("encode", r'ofera_stage_seconds_(sum|count)\{stage="encode"\}'),
                       ("to_socket", r"ofera_server_latency_seconds_(sum|count)")):
        s, c = value(base.replace("(sum|count)", "sum")), value(base.replace("(sum|count)", "count"))
        if s is not None and c:
            out[name] = round(s / c * 1e3, 3)
    for stage in ("bs", "frame"):
        v = value(rf'ofera_frames_skipped_total\{{stage="{stage}"\}}')
        if v is not None:
            out[f"skipped_{stage}"] = int(v)
    return out


async def run_session(url: str, weights: np.ndarray, layout: str, rate: float, seconds: float, warmup: float,
                      encoding: str, sparse: bool = False, decode: str = "fast", delta: bool = False) -> dict:
    """One client: bs on a fixed schedule, frames received and decoded; per-frame records after warm-up.
    decode: 'fast' (numba FastFrameDecoder, same checks and values as the codec), 'reference'
    (ofera_protocol's decoder, via the client library's connection), 'header' (arrays left undecoded).
    delta: a delta session (hello.delta); the decoder applies its delta frames to the codes it holds."""
    from ofera.client import connect, now_us
    from ofera.client.fast_decode import FastFrameDecoder, decoder_warm
    from ofera_protocol import Frame

    params = encoding == "params"
    if decode == "fast" and not params:
        decoder_warm()  # compiled (or loaded) before connecting: a first compile blocks the loop past the keepalive
    client = await connect(url, layout=layout, encoding=encoding, sparse=sparse, delta=delta,
                           track=params and decode != "header")
    fast = FastFrameDecoder(client.conn.format) if decode == "fast" and not params else None  # delta frames too
    deformer = client.rig_deformer  # params: numba (decode "fast"), the float64 numpy reference, or none (header)
    if params and decode == "reference":
        from ofera.client.params import RigDeformer

        deformer = RigDeformer(client.conn.rig, reference=True)
    period_us = 1e6 / rate
    total = int((warmup + seconds) * rate)
    first_counted = int(warmup * rate)
    start = now_us() + 100_000
    records: list[tuple[int, float, dict, int, float]] = []
    arrivals: list[tuple[int, float]] = []  # (seq, decoded time) of every counted frame

    def on_message(data: bytes, t_recv: float) -> bool:
        if params:  # the values, then (unless header only) the client's own deformation of the Gaussians
            msg = C.read_params_frame(client, data, deformer)
            if msg is None:
                return False
            seq, t, timing = msg.seq, msg.t, msg.timing or {}
        elif decode != "header":
            msg = fast.decode(data) if fast is not None else client.conn.receive(data)
            if not isinstance(msg, Frame):
                return False
            seq, t, timing = msg.seq, msg.t, msg.timing
        else:  # header only: the arrays are left undecoded
            seq, t, timing = _frame_header(data)
            if seq is None:
                return False
        now = now_us()
        if seq >= first_counted:
            records.append((seq, (now - t) / 1000.0, timing, len(data), (now - t_recv) / 1000.0))
            arrivals.append((seq, now))
        return seq == total - 1

    end = await C.paced_session(client, weights, start, period_us, total, on_message, tail_s=2.0)
    await client.close()
    scheduled = {k: start + k * period_us for k in range(first_counted, total)}
    return {"sent": total - first_counted, "records": records, "count": client.count,
            "dropped_ms": C.drop_latencies(scheduled, arrivals, end)}


def _frame_header(data: bytes) -> tuple[int | None, int, dict]:
    """seq, t, timing of a frame message, read without touching (or copying) its arrays."""
    from ofera_protocol import read_frame_header

    head = read_frame_header(data)
    if head is None:
        return None, 0, {}
    return head.seq, head.t, head.timing or {}


def summarise(run: dict) -> dict:
    recs = run["records"]
    e2e = [r[1] for r in recs]
    stages: dict[str, list[float]] = {}
    for r in recs:
        for k, v in r[2].items():
            stages.setdefault(k, []).append(v / 1000.0)
    compute = [sum(r[2].get(s, 0) for s in COMPUTE_STAGES) / 1000.0 for r in recs]
    hde = [sum(r[2].get(s, 0) for s in ("head", "deform", "encode")) / 1000.0 for r in recs]
    dropped = list(run["dropped_ms"].values())
    e2e_p, answered_p = C.pct(e2e + dropped), C.pct(e2e)
    keys = ("p50", "p90", "p99", "p999", "max", "mean")
    return {
        "frames": len(recs),
        "frames_sent": run["sent"],
        "frames_skipped": len(dropped),
        "drop_fraction": round(len(dropped) / run["sent"], 4) if run["sent"] else None,
        "e2e_ms": {k: e2e_p[k] for k in keys},
        "answered_e2e_ms": {k: answered_p[k] for k in keys},
        "server_ms": {k: C.pct(stages.get("total", []))[k] for k in ("p50", "p99")},
        "compute_ms": {k: C.pct(compute)[k] for k in ("p50", "p99", "max")},
        "head_deform_encode_ms": ({k: C.pct(hde)[k] for k in ("p50", "p99", "max")}
                                  if recs and "encode" in recs[0][2] else None),
        "stages_ms": {k: {"p50": C.pct(v)["p50"], "p99": C.pct(v)["p99"]} for k, v in stages.items()},
        "client_decode_ms": {k: C.pct([r[4] for r in recs])[k] for k in ("p50", "p99")},
        "bytes_per_frame": int(np.median([r[3] for r in recs])) if recs else None,
        "_e2e": e2e,
        "_seq": [r[0] for r in recs],
        "_dropped": dropped,
        "_dropped_seq": list(run["dropped_ms"]),
    }


def run_impl(impl: str, args, weights, layout, avatars: Path) -> dict:
    stamped = C.params_stamped_every_frame() if args.encoding == "params" else contextlib.nullcontext()
    extra = C.server_extra(args.pinned, event_loop=args.event_loop, kernel_threads=args.kernel_threads)
    with stamped, C.ServerProcess(avatars, impl=impl, threads=args.threads, extra=extra) as server:
        with C.CpuMeter(server.proc.pid) as cpu:
            run = asyncio.run(run_session(server.url, weights, layout, args.rate, args.seconds, args.warmup,
                                          args.encoding, args.sparse, args.client_decode, args.delta))
        out = summarise(run)
        out["cpu"] = cpu.report()
        if out["head_deform_encode_ms"] is None and out["frames"]:  # the reference stamps no encode: its mean
            enc = metric_means(f"http://127.0.0.1:{server.port}").get("encode", 0.0)
            out["head_deform_encode_ms"] = {"p50": round(sum((out["stages_ms"].get(s) or {}).get("p50") or 0
                                                             for s in ("head", "deform")) + enc, 3),
                                            "note": "head p50 + deform p50 + encode mean (/metrics)"}
        out["server_metrics_ms"] = metric_means(f"http://127.0.0.1:{server.port}")
        out["event_loop"] = C.server_event_loop(server.port)
        out["count"] = run["count"]
    return out


def plot(path: Path, results: dict, title: str, target_ms: float) -> None:
    plt = C.pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    colors = {"fast": "tab:blue", "reference": "tab:red"}
    for impl, r in results.items():
        e2e = np.sort(np.asarray(r["_e2e"] + r["_dropped"]))
        if e2e.size:
            axes[0].plot(e2e, np.arange(1, e2e.size + 1) / e2e.size, color=colors[impl],
                         label=f"{impl} (p99 {r['e2e_ms']['p99']} ms, {r['frames_skipped']} skipped)")
            axes[1].plot(np.asarray(r["_seq"]), r["_e2e"], ".", ms=3, color=colors[impl], label=impl)
        if r["_dropped"]:
            axes[1].plot(r["_dropped_seq"], r["_dropped"], "x", ms=4, color=colors[impl],
                         label=f"{impl}: skipped bs (first later frame)")
    axes[0].set_xscale("log")
    axes[0].set_xlabel("end-to-end latency (ms, log)")
    axes[0].set_ylabel("fraction of bs sent (skipped ones included)")
    axes[0].axvline(target_ms, color="grey", ls="--", lw=0.8, label=f"target p99 {target_ms:g} ms")
    axes[0].legend(fontsize=8)
    axes[1].set_yscale("log")
    axes[1].set_xlabel("bs seq")
    axes[1].set_ylabel("latency (ms, log)")
    axes[1].legend(fontsize=8)
    names = ["decode", "queue", "layout", "bda", "epm", "head", "deform"]
    impls = list(results)
    bottom = np.zeros(len(impls))
    for name in names:
        vals = np.array([results[i]["stages_ms"].get(name, {}).get("p50") or 0.0 for i in impls])
        axes[2].bar(impls, vals, bottom=bottom, label=name)
        bottom += vals
    enc = np.array([results[i]["server_metrics_ms"].get("encode", 0.0) for i in impls])
    axes[2].bar(impls, enc, bottom=bottom, label="encode (mean)", hatch="//")
    axes[2].set_yscale("symlog", linthresh=1.0)
    axes[2].set_ylabel("server stage, median (ms, symlog)")
    axes[2].legend(fontsize=7, ncol=2)
    C.save_figure(fig, path, title)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000, help="avatar size (0: the default avatar)")
    ap.add_argument("--rate", type=float, default=72.0, help="bs per second")
    ap.add_argument("--seconds", type=float, default=5.0, help="measured duration per implementation")
    ap.add_argument("--warmup", type=float, default=1.0, help="seconds sent first and not counted")
    ap.add_argument("--encoding", default="f16", choices=["f32", "f16", "q13", "params"])
    ap.add_argument("--sparse", action="store_true", help="ask for sparse frames (movable Gaussians only)")
    ap.add_argument("--delta", action="store_true", help="a delta session (hello.delta: key frames, then only what "
                    "moved; f16 or q13): the compact stream")
    ap.add_argument("--impl", default="both", choices=["both", *C.IMPLS])
    ap.add_argument("--kernel-threads", default="auto", choices=["serial", "auto", "parallel"],
                    help="the server's kernel_threads setting (the fast path's deformation on numba's threads)")
    ap.add_argument("--event-loop", default="auto", choices=["auto", "asyncio", "uvloop"],
                    help="the server's event loop (auto: what ofera serve picks)")
    ap.add_argument("--threads", type=int, default=2, help="server compute threads")
    ap.add_argument("--no-floor", action="store_true", help="skip the transport-floor measurement")
    ap.add_argument("--pin", action="store_true", help="the server on every CPU but the last (ofera serve --cpus), "
                    "this client on the last: no preemption between them (benchmarks/README.md, round nine)")
    ap.add_argument("--client-decode", default="fast", choices=["fast", "reference", "header"],
                    help="how the client decodes frames: numba decoder (same values and checks as the codec), "
                    "the reference codec, or the header only")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "latency.json")
    args = ap.parse_args(argv)
    args.pinned = C.pin_split(args.pin)

    weights, layout, fps, notes = C.capture()
    avatars, epm_notes = C.avatars_dir(args.gaussians or None)
    notes += epm_notes
    impls = list(C.IMPLS) if args.impl == "both" else [args.impl]
    results = {}
    for impl in impls:
        print(f"[latency] {impl}: {args.gaussians or 'default'} Gaussians, {args.encoding}, {args.rate:g} Hz, "
              f"{args.seconds:g} s (+{args.warmup:g} s warm-up) ...", flush=True)
        results[impl] = run_impl(impl, args, weights, layout, avatars)
    fast = results.get("fast") or results[impls[0]]
    floor = None
    if not args.no_floor and fast["bytes_per_frame"]:
        print(f"[latency] transport floor: {fast['bytes_per_frame']} B messages, no compute ...", flush=True)
        floor = C.transport_floor(fast["bytes_per_frame"], args.rate, min(args.seconds, 3.0))
    report = {
        "benchmark": "latency",
        "gaussians": fast["count"],
        "rate_hz": args.rate,
        "encoding": args.encoding,
        "sparse": args.sparse,
        "frames": fast["frames"],
        "frames_sent": fast["frames_sent"],
        "frames_skipped": fast["frames_skipped"],
        "drop_fraction": fast["drop_fraction"],
        "e2e_ms": fast["e2e_ms"],
        "answered_e2e_ms": fast["answered_e2e_ms"],
        "server_ms": fast["server_ms"],
        "compute_ms": fast["compute_ms"],
        "head_deform_encode_ms": fast["head_deform_encode_ms"],
        "delta": args.delta,
        "cpu": fast["cpu"],
        "stages_ms": fast["stages_ms"],
        "client_decode_ms": fast["client_decode_ms"],
        "client_decode": args.client_decode,
        "server_metrics_ms": fast["server_metrics_ms"],
        "bytes_per_frame": fast["bytes_per_frame"],
        "transport_floor_ms": floor,
        "impl": impls[0] if len(impls) == 1 else "fast",
        "event_loop": fast.get("event_loop"),
        "kernel_threads": args.kernel_threads,
        "pin": args.pinned,
        "input": {"layout": layout, "capture": str(C.CAPTURE) if C.CAPTURE.is_file() else None, "fps": fps},
        "definitions": {
            "e2e_ms": "client clock: frame decoded - scheduled send time of its bs (loopback, same machine); a "
                      "skipped bs counts with the first later frame's decode time",
            "answered_e2e_ms": "e2e_ms of the frames that arrived only (skipped bs left out)",
            "drop_fraction": "frames_skipped / frames_sent (bs sent after warm-up that no frame answered)",
            "client_decode_ms": "client: message received -> decoded (--client-decode)",
            "server_ms": "frame timing 'total': bs received -> frame computed (includes queueing)",
            "compute_ms": "sum of layout, bda, epm, head, deform of the frame's timing",
            "head_deform_encode_ms": "head + deform + encode of the frame's timing (the issue's server compute)",
            "cpu": "cores used on average during the run: the client process (this one) and the server; steal_pct: the "
                   "machine's CPU time its hypervisor gave to other guests meanwhile (%)",
            "server_metrics_ms": "means from /metrics: encode stage, bs received -> frame handed to the socket",
            "transport_floor_ms": "round trip of a tiny request answered by a message of bytes_per_frame between "
                                  "two Python processes (a websockets server, the client on ofera.client.transport "
                                  "as the benchmark's, no compute)",
            "params": "--encoding params: e2e includes the client's deformation of the Gaussians (RigDeformer)",
        },
        "targets": {"e2e_p99_ms": 5.0 if args.delta or args.encoding == "params" else 8.0,
                    "head_deform_encode_p50_ms": 1.5, "head_deform_encode_p99_ms": 3.0},
        "machine": C.machine(),
        "notes": notes,
    }
    if "reference" in results and "fast" in results:
        ref = {k: v for k, v in results["reference"].items() if not k.startswith("_")}
        report["reference"] = ref
        report["ratios"] = {"e2e_p50": C.ratio(fast["e2e_ms"]["p50"], ref["e2e_ms"]["p50"]),
                            "e2e_p99": C.ratio(fast["e2e_ms"]["p99"], ref["e2e_ms"]["p99"]),
                            "compute_p50": C.ratio(fast["compute_ms"]["p50"], ref["compute_ms"]["p50"]),
                            "compute_p99": C.ratio(fast["compute_ms"]["p99"], ref["compute_ms"]["p99"]),
                            "encode_mean": C.ratio(fast["server_metrics_ms"].get("encode"),
                                                   ref["server_metrics_ms"].get("encode"))}
    rows = []
    for impl, r in results.items():
        e, st = r["e2e_ms"], r["stages_ms"]
        rows.append([impl, r["frames"], f"{r['frames_skipped']} ({100 * (r['drop_fraction'] or 0):.1f}%)",
                     e["p50"], e["p90"], e["p99"], e["p999"], e["max"],
                     r["compute_ms"]["p50"], r["compute_ms"]["p99"], (st.get("head") or {}).get("p50"),
                     (st.get("deform") or {}).get("p50"), r["server_metrics_ms"].get("encode"),
                     (r["head_deform_encode_ms"] or {}).get("p50"), (r["head_deform_encode_ms"] or {}).get("p99"),
                     r["bytes_per_frame"], r["cpu"]["client_cores"], r["cpu"]["server_cores"], r["cpu"]["steal_pct"]])
    print(C.table(rows, ["impl", "frames", "skipped", "e2e p50", "p90", "p99", "p99.9", "max", "compute p50",
                         "p99", "head p50", "deform p50", "encode mean", "h+d+e p50", "h+d+e p99", "bytes/frame",
                         "client cores", "server cores", "steal %"]))
    print("load average:", C.machine()["loadavg_at_start"])
    if "ratios" in report:
        print("reference / fast:", report["ratios"])
    if floor:
        print(f"transport floor ({floor['bytes']} B, no compute): p50 {floor['p50']} ms, p99 {floor['p99']} ms, "
              f"min {floor['min']} ms")
    for n in notes:
        print("note:", n)
    out = C.write_json(args.json, report)
    png = C.png_path(out)
    plot(png, results, f"{report['gaussians']} Gaussians, {args.encoding}{' sparse' if args.sparse else ''}, "
         f"{args.rate:g} Hz, {args.seconds:g} s, loopback WebSocket ({C.machine()['cpus']} CPUs)",
         report["targets"]["e2e_p99_ms"])
    print(f"wrote {out} and {png}")
    return report


if __name__ == "__main__":
    main()
