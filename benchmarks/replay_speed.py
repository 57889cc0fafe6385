"""The real 60 fps capture replayed faster than real time: the fraction of its bs a server answers.

    python benchmarks/replay_speed.py --gaussians 100000 --speed 4 --passes 3 --encoding f16 --json out.json

For each implementation (fast path, then the reference), a server in a subprocess and the project's own replay
tool in another (``ofera replay CAPTURE --url URL --speed S --loop --passes P --json -``: the client is its own
process and interpreter, not this one). At --speed 4 the capture's 60 fps become 240 bs/s, a bs every 4.2 ms,
so a server answers all of them only when a whole frame (compute, encode, send) fits in that period; newest-wins
drops the rest (PROTOCOL.md 9). Reports the replay summary (answered fraction, latency percentiles), the CPU
the replay client and the server used, and the machine's load average. Target: answered >= 95 %.

``--decode header`` (the replay tool's default) reads only each frame's seq, t and timing; ``full`` decodes and
checks every frame's arrays (``ofera replay --full-decode``); ``both`` runs the two side by side on one server:

    python benchmarks/replay_speed.py --gaussians 0 --encoding f32 --impl fast --decode both
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

TARGET = 0.95


def replay(url: str, args, decode: str = "header") -> tuple[dict, float, float]:
    """(the replay tool's JSON summary, its CPU seconds, wall seconds); `decode` "full" adds --full-decode."""
    cmd = [sys.executable, "-c", "from ofera.cli.main import main; main()", "replay", str(C.CAPTURE),
           "--url", url.removesuffix("/v1/stream"),
           "--speed", str(args.speed), "--loop", "--passes", str(args.passes), "--encoding", args.encoding,
           "--json", "-", "--quiet"]
    if args.delta:
        cmd.append("--delta")
    if decode == "full":
        cmd.append("--full-decode")
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    cpu = 0.0
    while proc.poll() is None:  # sample the client's CPU until it exits (a reaped process has no /proc entry)
        try:
            cpu = C.cpu_seconds(proc.pid)
        except OSError:
            pass
        time.sleep(0.05)
    out, err = proc.communicate()
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"ofera replay failed ({proc.returncode}):\n{err[-2000:]}\n{out[-2000:]}")
    return json.loads(out[out.index("{"):]), cpu, wall


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000, help="0: the built-in default avatar")
    ap.add_argument("--speed", type=float, default=4.0)
    ap.add_argument("--passes", type=int, default=3, help="times the 180-frame capture is sent")
    ap.add_argument("--encoding", default="f16", choices=["f32", "f16", "q13"])
    ap.add_argument("--delta", action="store_true")
    ap.add_argument("--impl", default="both", choices=["both", *C.IMPLS])
    ap.add_argument("--decode", default="header", choices=["header", "full", "both"],
                    help="what the replay client decodes of each frame (both: full, then header, one server)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--event-loop", default="auto", choices=["auto", "asyncio", "uvloop"])
    ap.add_argument("--pin", action="store_true", help="the server on every CPU but the last (ofera serve --cpus), "
                    "the replay client on the last: no preemption between them (benchmarks/README.md, round nine)")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "replay_speed.json")
    args = ap.parse_args(argv)
    args.pinned = C.pin_split(args.pin)
    if not C.CAPTURE.is_file():
        raise SystemExit(f"the capture {C.CAPTURE} is missing (the shared data folder; $OFERA_CAPTURE names it)")
    avatars, notes = C.avatars_dir(args.gaussians or None)
    impls = list(C.IMPLS) if args.impl == "both" else [args.impl]
    decodes = ["full", "header"] if args.decode == "both" else [args.decode]
    results = {}
    for impl in impls:
        with C.ServerProcess(avatars, impl=impl, threads=args.threads,
                             extra=C.server_extra(args.pinned, event_loop=args.event_loop)) as server:
            for decode in decodes:
                name = impl if len(decodes) == 1 else f"{impl}/{decode}"
                s0 = C.cpu_seconds(server.proc.pid)
                summary, client_cpu, wall = replay(server.url, args, decode)
                server_cpu = C.cpu_seconds(server.proc.pid) - s0
                load = [round(v, 2) for v in os.getloadavg()]
                results[name] = {"decode": decode, "answered": summary["answered"], "sent": summary["sent"],
                                 "received": summary["received"], "latency_ms": summary["latency_ms"],
                                 "meets_target": summary["answered"] >= TARGET,
                                 "cpu": {"client_cores": round(client_cpu / wall, 3),
                                         "server_cores": round(server_cpu / wall, 3), "wall_s": round(wall, 2)},
                                 "loadavg_after": load, "summary": summary}
                print(f"[replay x{args.speed:g}] {name}: answered {summary['answered']:.1%} of {summary['sent']} bs, "
                      f"latency {summary['latency_ms']}, cores client {results[name]['cpu']['client_cores']} server "
                      f"{results[name]['cpu']['server_cores']}, load average {load}", flush=True)
    report = {"benchmark": "replay_speed", "gaussians": args.gaussians, "speed": args.speed, "passes": args.passes,
              "encoding": args.encoding, "delta": args.delta, "decode": args.decode, "capture": str(C.CAPTURE),
              "target_answered": TARGET, "pin": args.pinned,
              "results": results, "machine": C.machine(), "notes": notes}
    out = C.write_json(args.json, report)
    plt = C.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.bar(list(results), [100 * r["answered"] for r in results.values()], color=["tab:blue", "tab:red"][:len(results)])
    ax.axhline(100 * TARGET, color="grey", ls="--", lw=0.8, label=f"target {100 * TARGET:g} %")
    ax.set_ylabel("bs answered (%)")
    ax.legend(fontsize=8)
    C.save_figure(fig, C.png_path(out), f"capture at x{args.speed:g} ({60 * args.speed:g} bs/s), {args.gaussians} "
                  f"Gaussians, {args.encoding}{' delta' if args.delta else ''}")
    print(f"wrote {out} and {C.png_path(out)}")
    return report


if __name__ == "__main__":
    main()
