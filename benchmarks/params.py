"""Expression streaming (params, PROTOCOL.md 13): bytes per frame, rig size, client deformation time (Python,
browser), server cost per viewer, and a room of 16 publishers each watched by the 15 others at 72 Hz (240 streams).

    python benchmarks/params.py --gaussians 0 --seconds 5 --json benchmarks/results/params.json

- rig: the rig body and its `rig` messages for the avatar (`--gaussians 0`: the built-in default, 115,600), and how
  long building it takes (once per avatar and reduction; cached).
- bytes: one real session per encoding (params, and f16 / q13 dense for comparison) over a socket, the capture's
  bs at --rate for --seconds: the bytes of every frame off the socket after the handshake, Mbit/s at that rate.
- client: deforming one frame from the rig, median ms, fast path and reference side by side: Python
  (`ofera.client.params.RigDeformer`: its numba fast path, and the protocol's numpy reference `deform_rig`), the
  browser's rig.js in headless Chromium (`RigDeformer` and `deformRigReference` on the same frames, and their
  largest difference; skipped without /usr/bin/chromium and playwright). C# under mono: the C# benchmark adds its own.
- server: per frame, what a source computes (map = BDA + EPM, vs map + deformation) and what a viewer's format
  costs to encode (params vs the fast f16 / q13 writers), in process, medians of the same frames side by side.
- room: benchmarks/rooms.py with K = 16, encoding params, one server of --threads compute threads. Its clients
  count a frame by its seq, so the room's server stamps every params frame (OFERA_PARAMS_STAMP_INTERVAL=0; about
  70 B more per frame than the default, which stamps once a second): its bytes are not the params figure above.

All on this (shared, loaded) machine: compare within one run; the JSON's `machine` has the load average.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--no-sandbox", "--no-first-run"]
BROWSER_SCRIPT = "async ([layout, weights]) => {\n" + C.PARAMS_SESSION_JS + """  const n = welcome.avatar.count;
  const t0 = performance.now();
  const deformer = new R.RigDeformer(R.decodeRig(asm.result()));
  const setupMs = performance.now() - t0;
  const pos = new Float32Array(3 * n), rot = new Float32Array(4 * n), scl = new Float32Array(3 * n);
  const refPos = new Float32Array(3 * n), refRot = new Float32Array(4 * n), refScl = new Float32Array(3 * n);
  const ms = [], refMs = [];
  let maxPos = 0;
  for (let i = 0; i < weights.length; i++) {
    ws.send(P.bsMessage(i, i, weights[i]));
    const f = P.decodeServerMessage(new Uint8Array(await next()));
    let t = performance.now();
    deformer.apply(f.params, pos, rot, scl, "flame");
    ms.push(performance.now() - t);
    t = performance.now();
    R.deformRigReference(deformer.rig, f.params, refPos, refRot, refScl, "flame");
    refMs.push(performance.now() - t);
    for (let k = 0; k < 3 * n; k++) maxPos = Math.max(maxPos, Math.abs(pos[k] - refPos[k]));
  }
  ws.close();
  return { ms, refMs, maxPos, setupMs, gaussians: deformer.rig.gaussians, vertices: deformer.rig.vertices };
}"""


def median_us(fn, reps: int) -> float:
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1e6)
    return round(float(np.median(out)), 1)


# ----------------------------------------------------------------------------- in process


def in_process(avatar_path: Path, weights: np.ndarray, layout: str, reps: int) -> dict:
    """Rig size and build time, client deformation (Python), server cost per source and per viewer format."""
    from ofera.avatar import load_avatar
    from ofera.client.params import RigDeformer
    from ofera.streaming.encode_fast import frame_writer
    from ofera.streaming.params import ParamsWriter, rig_body
    from ofera.streaming.pipeline import AvatarAssets
    from ofera_protocol import FrameFormat, encode, make_quant
    from ofera_protocol.rig import decode_rig, split_rig

    assets = AvatarAssets.create(C.AVATAR_ID, load_avatar(avatar_path), C.mapper()[0])
    t = time.perf_counter()
    body = rig_body(assets, None)
    build_s = time.perf_counter() - t
    rig = decode_rig(body)
    messages = [encode(c) for c in split_rig(body)]
    pipeline = assets.pipeline(layout)
    pipeline.warm_up()
    values = [pipeline.map(w)[0] for w in weights[:reps]]
    client = RigDeformer(rig)
    frames = iter(range(10**9))

    def pick() -> np.ndarray:
        return values[next(frames) % len(values)]

    cols = {"rig": {"body_bytes": len(body), "message_bytes": sum(map(len, messages)), "messages": len(messages),
                    "gaussians": rig.gaussians, "of": assets.count, "vertices": rig.vertices, "faces": rig.faces,
                    "build_s": round(build_s, 3)}}
    reference = RigDeformer(rig, reference=True)
    client.deform(pick())  # compile (numba, cached on disk)
    cols["client_python_ms"] = {"python fast (numba)": median_us(lambda: client.deform(pick()), reps) / 1000,
                                "python reference (deform_rig, numpy)":
                                    median_us(lambda: reference.deform(pick()), reps) / 1000}
    state, _ = pipeline.run(weights[0])
    writer = ParamsWriter()
    pos, rot, scale = state.position, state.rotation, state.scale
    wire = assets.wire_avatar("flame")
    quant = make_quant(wire.position, wire.scale)
    f16 = frame_writer(FrameFormat("f16", assets.count), "flame", None, None)
    q13 = frame_writer(FrameFormat("q13", assets.count, quant=quant), "flame", None, None)
    timing = {"total": 1}
    for w in (f16, q13):
        w.encode(0, 0, timing, pos, rot, scale)  # compile / warm
    cols["server_source_us"] = {
        "map (BDA + EPM): all viewers params": median_us(lambda: pipeline.map(weights[next(frames) % len(weights)]),
                                                          reps),
        "map + deform: some viewer wants Gaussians": median_us(
            lambda: pipeline.run(weights[next(frames) % len(weights)]), reps)}
    cols["server_encode_us"] = {
        "params": median_us(lambda: writer.encode_values(1, 2, timing, pick(), None), reps),
        "f16 (fast writer)": median_us(lambda: f16.encode(1, 2, timing, pos, rot, scale), reps),
        "q13 (fast writer)": median_us(lambda: q13.encode(1, 2, timing, pos, rot, scale), reps)}
    return cols


# ----------------------------------------------------------------------------- over a socket


async def paced(url: str, encoding: str, weights: np.ndarray, layout: str, rate: float, seconds: float) -> dict:
    """One session at `rate` Hz: sizes of the frames after the handshake (header and arrays: the whole message)."""
    from ofera.client import connect

    c = await connect(url, layout=layout, encoding=encoding, max_queue=64)
    sizes: list[int] = []
    stamped = 0
    total = int(rate * seconds)

    async def receive() -> None:
        nonlocal stamped
        while len(sizes) < total:
            f = await c.recv_frame(10)
            sizes.append(c.last_bytes)
            stamped += getattr(f, "seq", 0) is not None

    task = asyncio.create_task(receive())
    start = time.monotonic()
    for i in range(total):
        await asyncio.sleep(max(0.0, start + i / rate - time.monotonic()))
        await c.send_bs(weights[i % len(weights)])
    try:
        await asyncio.wait_for(task, 10)
    except asyncio.TimeoutError:
        task.cancel()
    await c.close()
    a = np.array(sizes)
    return {"frames_sent": total, "frames": int(a.size), "skipped_by_server": total - int(a.size),
            "bytes_mean": round(float(a.mean()), 1) if a.size else None,
            "bytes_min": int(a.min()) if a.size else None, "bytes_max": int(a.max()) if a.size else None,
            "stamped_frames": stamped, "mbit_s_at_rate": round(float(a.mean()) * 8 * rate / 1e6, 3) if a.size else None}


def browser_client(http: str, weights: np.ndarray, layout: str) -> dict | str:
    """rig.js in headless Chromium, on frames of a live params session: median ms per frame of the fast
    `RigDeformer` and of `deformRigReference` (same frames), their largest position difference (m)."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return "skipped: the playwright package is missing"
    if not Path(CHROMIUM).exists():
        return f"skipped: {CHROMIUM} is missing"
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page()
            page.goto(f"{http}/static/index.html")
            r = page.evaluate(BROWSER_SCRIPT, [layout, weights.tolist()])
        finally:
            browser.close()
    return {"ms_per_frame": round(float(np.median(r["ms"][3:])), 2),
            "reference_ms_per_frame": round(float(np.median(r["refMs"][3:])), 2), "max_position_diff_m": r["maxPos"],
            "setup_ms": round(r["setupMs"], 1),
            "frames": len(r["ms"]), "gaussians": r["gaussians"], "vertices": r["vertices"]}


def room(gaussians: int, seconds: float, threads: int, rate: float) -> dict:
    """benchmarks/rooms.py, K = 16, params, one server (every params frame stamped, see the module docstring)."""
    import importlib.util
    import tempfile

    spec = importlib.util.spec_from_file_location("bench_rooms", Path(__file__).resolve().parent / "rooms.py")
    rooms = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = rooms
    spec.loader.exec_module(rooms)
    out = Path(tempfile.mkdtemp(prefix="ofera-params-room-")) / "room.json"
    with C.params_stamped_every_frame():  # inherited by the server process rooms.py starts
        report = rooms.main(["--gaussians", str(gaussians), "--ks", "16", "--encodings", "params", "--servers", "1",
                             "--seconds", str(seconds), "--threads", str(threads), "--rate", str(rate),
                             "--floor-seconds", "0", "--no-plot", "--json", str(out)])
    runs = report.get("runs", {})
    run = next(iter(runs.values()), {}).get("16") if runs else None
    return {"run": run, "summary": report.get("summary")}


# ----------------------------------------------------------------------------- main


def plot(path: Path, report: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2), gridspec_kw={"width_ratios": [1, 1.3, 1.3]})
    by = {k: v["bytes_mean"] for k, v in report["bytes"].items() if v.get("bytes_mean")}
    ax[0].bar(list(by), list(by.values()), color=["tab:green" if k == "params" else "tab:grey" for k in by])
    ax[0].set_yscale("log")
    ax[0].axhline(300, color="tab:red", ls="--", lw=0.8, label="goal 300 B")
    ax[0].set_ylabel("bytes per frame (mean)")
    ax[0].set_title(f"frame size, {report['rig']['of']} Gaussians")
    ax[0].legend()
    client = dict(report["client_python_ms"])
    if isinstance(report.get("client_browser"), dict):
        client["browser rig.js"] = report["client_browser"]["ms_per_frame"]
        client["browser rig.js reference"] = report["client_browser"]["reference_ms_per_frame"]
    ax[1].barh(list(client), list(client.values()), color="tab:blue")
    ax[1].set_xlabel("ms per frame (median)")
    ax[1].set_title(f"client: deform {report['rig']['gaussians']} Gaussians")
    enc = report["server_encode_us"] | report["server_source_us"]
    ax[2].barh(list(enc), list(enc.values()), color="tab:orange")
    ax[2].set_xscale("log")
    ax[2].set_xlabel("µs per frame (median)")
    ax[2].set_title("server: per source / per format")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=0, help="avatar size (0: the built-in default, 115,600)")
    ap.add_argument("--rate", type=float, default=72.0)
    ap.add_argument("--seconds", type=float, default=5.0, help="seconds per session and of the room run")
    ap.add_argument("--reps", type=int, default=60, help="repetitions of each in-process timing")
    ap.add_argument("--threads", type=int, default=2, help="compute threads of the servers")
    ap.add_argument("--room", choices=("yes", "no"), default="yes", help="run the room of 16")
    ap.add_argument("--room-gaussians", type=int, default=20_000, help="avatar size in the room run: params viewers "
                    "never deform, so it only sizes the handshake (16 x 15 avatars and rigs: at 115k that is ~3 GB "
                    "over loopback, beyond rooms.py's 30 s join deadline on a 2-core machine)")
    ap.add_argument("--browser", choices=("yes", "no"), default="yes")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "params.json")
    ap.add_argument("--no-plot", action="store_true")
    args = ap.parse_args(argv)

    weights, layout, _, notes = C.capture()
    avatars, epm_notes = C.avatars_dir(args.gaussians or None)
    notes += epm_notes
    avatar_path = next(p for p in avatars.iterdir() if p.name.startswith(C.AVATAR_ID) and p.suffix == ".npz")
    print(f"[params] in process ({avatar_path.name}) ...", flush=True)
    report: dict = {"benchmark": "params", "gaussians": args.gaussians or "default", "rate_hz": args.rate,
                    "seconds": args.seconds, "layout": layout}
    report |= in_process(avatar_path, weights, layout, args.reps)
    report["bytes"] = {}
    with C.ServerProcess(avatars, threads=args.threads) as server:
        for enc in ("params", "f16", "q13"):
            print(f"[params] {enc} session at {args.rate:g} Hz for {args.seconds:g} s ...", flush=True)
            report["bytes"][enc] = asyncio.run(paced(server.url, enc, weights, layout, args.rate, args.seconds))
        if args.browser == "yes":
            print("[params] rig.js in headless Chromium ...", flush=True)
            report["client_browser"] = browser_client(f"http://127.0.0.1:{server.port}", weights[:60], layout)
    report["client_csharp_ms"] = "added by the C# benchmark (mono)"
    if args.room == "yes":
        print(f"[params] room: 16 publishers x 15 viewers at {args.rate:g} Hz ...", flush=True)
        report["room_16"] = {"gaussians": args.room_gaussians,
                             **room(args.room_gaussians, args.seconds, args.threads, args.rate)}
    report["goal"] = {"bytes_per_frame": 300, "room_p99_ms": 13.9, "room_max_drop": 0.01}
    p = report["bytes"]["params"]
    report["goal_met"] = {"bytes_per_frame": p["bytes_mean"] is not None and p["bytes_mean"] <= 300}
    run = (report.get("room_16") or {}).get("run")
    if run:
        report["goal_met"]["room_16"] = bool(run.get("passes"))
    report["machine"] = C.machine()
    report["notes"] = notes + ["bytes: whole WebSocket messages (msgpack) after the handshake; the rig and the "
                               "avatar are sent once (rig.message_bytes)"]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps({k: report[k] for k in ("rig", "bytes", "client_python_ms", "client_browser", "server_source_us",
                                              "server_encode_us", "goal_met") if k in report}, indent=1))
    if not args.no_plot:
        png = C.png_path(args.json)
        plot(png, report)
        print(f"wrote {args.json} and {png}")
    return report


if __name__ == "__main__":
    main()
