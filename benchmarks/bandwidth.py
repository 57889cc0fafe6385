"""Bandwidth of a real session over a socket: bytes per frame, the client's error against the f32 stream at every
frame, and end-to-end latency, for f16, q13, q13+sparse and q13+delta (temporal deltas, PROTOCOL.md 7.1).

    python benchmarks/bandwidth.py                      # 100k Gaussians, 10 s per scheme and input, 72 Hz
    python benchmarks/bandwidth.py --seconds 600 --schemes q13+delta --inputs capture --soak   # drift soak

A server runs in a subprocess (benchmarks/_common.ServerProcess, the fast path, serving the 100k-Gaussian
procedural avatar). For each input and scheme one client opens a session, sends `bs` at 72 Hz on a fixed schedule
(not waiting for frames, so newest-wins drops happen whenever the server falls behind) and receives, decodes and
applies every frame as a client does (ofera.client.fast_decode.FastFrameDecoder; delta frames through the codes it
holds). Inputs: the real capture (_common.CAPTURE, 60 fps, played in real time and looped) and a synthetic
expression sweep (every arkit52 shape in turn, 1 s up and down, four at a time).

- bytes/frame: the length of every frame message as it came off the client's socket (the WebSocket payload the
  server sent; framing adds 2 to 10 bytes), and, as a cross-check, the server's own `ofera_bytes_sent` counter over
  the streaming window divided by its `ofera_frames_sent`.
- error: for every frame received, the client's state (all Gaussians: a dense frame, neutral + the sparse set, or
  key frame + the deltas applied since) against the exact float32 frame of the `bs` it answers, computed after the
  session by the same pipeline in this process (bit-exact with the server's f32 stream): position (mm,
  Euclidean) and rotation (degrees), max and mean over Gaussians and frames. Delta sessions keep every received
  message and replay them in arrival order; self-contained schemes re-encode the exact frame (byte-identical to
  what the server sends; every 30th received frame is checked against it).
- latency: arrival (decoded) - scheduled send time of the `bs`, after a 1 s warm-up; `dropped`: bs never answered.
- encoder: the q13 delta encoder (numba, as the server runs it) timed on the same exact frames; zstd (level 1 and
  3, if the `zstandard` package is installed) and a byte-plane shuffle measured on the delta messages.

`--soak`: q13+delta only, errors computed online in a worker thread at one frame a second (`--sample`), to show
that the error at the end equals the error at the start. Writes JSON and a PNG (docs/images/bandwidth_100k.png is
this PNG for the default run).
"""

from __future__ import annotations

import argparse
import asyncio
import queue
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

SCHEMES = {"f32": ("f32", False, False), "f16": ("f16", False, False), "q13": ("q13", False, False),
           "q13+sparse": ("q13", True, False), "q13+delta": ("q13", False, True), "f16+delta": ("f16", False, True)}
TARGETS = {"bytes_per_gaussian": 2.0, "position_error_mm": 0.05, "rotation_error_deg": 0.5, "e2e_p99_ms_delta": 5.0}


# ----------------------------------------------------------------------------- inputs


def sweep_input(seconds: float = 13.0, fps: float = 60.0) -> np.ndarray:
    """(T, 52) arkit52: shape j rises and falls over 1 s starting at j / 4 s (four shapes active at a time)."""
    t = np.arange(int(seconds * fps)) / fps
    start = np.arange(52) / 4.0
    phase = (t[:, None] - start[None, :]) / 1.0
    w = np.where((phase > 0) & (phase < 1), np.sin(np.pi * np.clip(phase, 0, 1)), 0.0)
    return w.astype(np.float32)


def inputs(names: list[str]) -> dict[str, tuple[np.ndarray, str, float, list[str]]]:
    out = {}
    for name in names:
        if name == "capture":
            out[name] = C.capture()
        elif name == "sweep":
            out[name] = (sweep_input(), "arkit52", 60.0, [])
        else:
            raise SystemExit(f"unknown input {name!r}: capture, sweep")
    return out


def resample(weights: np.ndarray, fps: float, rate: float, frames: int) -> np.ndarray:
    """Frame k of a `rate` Hz stream: the input row at time k / rate (the input looped), real-time motion."""
    idx = (np.floor(np.arange(frames) * fps / rate).astype(np.int64)) % len(weights)
    return weights[idx]


# ----------------------------------------------------------------------------- errors


def errors(pos: np.ndarray, rot: np.ndarray, exact) -> tuple[np.ndarray, np.ndarray]:
    """Per-Gaussian position error (mm, Euclidean) and rotation error (degrees, from the chord) against exact."""
    pe = np.linalg.norm(pos.astype(np.float64) - exact.position, axis=1) * 1e3
    a = rot.astype(np.float64)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = exact.rotation.astype(np.float64)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    sign = np.where(np.sum(a * b, axis=1) < 0, -1.0, 1.0)[:, None]
    re = np.degrees(4 * np.arcsin(np.minimum(np.linalg.norm(a - sign * b, axis=1) / 2, 1.0)))
    return pe, re


class ErrorStats:
    def __init__(self) -> None:
        self.pos_max: list[float] = []  # per frame
        self.rot_max: list[float] = []
        self.pos_sum = self.rot_sum = 0.0
        self.count = 0

    def add(self, pe: np.ndarray, re: np.ndarray) -> None:
        self.pos_max.append(float(pe.max()))
        self.rot_max.append(float(re.max()))
        self.pos_sum += float(pe.sum())
        self.rot_sum += float(re.sum())
        self.count += pe.size

    def report(self) -> dict:
        if not self.pos_max:
            return {}
        return {"position_error_mm": {"max": round(max(self.pos_max), 6), "mean": round(self.pos_sum / self.count, 7)},
                "rotation_error_deg": {"max": round(max(self.rot_max), 5), "mean": round(self.rot_sum / self.count, 6)},
                "frames_checked": len(self.pos_max)}


# ----------------------------------------------------------------------------- a live session


def metric(http: str, name: str) -> float:
    with urllib.request.urlopen(f"{http}/metrics", timeout=10) as r:
        text = r.read().decode()
    for line in text.splitlines():
        if line.startswith(name + " ") or line.startswith(name + "{"):
            return float(line.rsplit(" ", 1)[1])
    return 0.0


async def session(url: str, http: str, scheme: str, weights: np.ndarray, layout: str, rate: float, seconds: float,
                  warmup: float, keep: str, sample: int, on_sample=None) -> dict:
    """One client at `rate` Hz. keep: 'all' (every frame message, for offline errors), 'some' (every 30th),
    'none'. on_sample(seq, position, rotation) gets a copy of the client's state every `sample` frames."""
    from ofera.client import connect, now_us
    from ofera.client.fast_decode import FastFrameDecoder
    from ofera_protocol import Frame, GaussianState

    enc, sparse, delta = SCHEMES[scheme]
    client = await connect(url, layout=layout, encoding=enc, sparse=sparse, delta=delta, max_queue=4)
    fmt = client.conn.format
    dec = FastFrameDecoder(fmt)
    state = GaussianState.from_avatar(client.avatar)
    period_us = 1e6 / rate
    total = int((warmup + seconds) * rate)
    first = int(warmup * rate)
    bytes0, frames0 = metric(http, "ofera_bytes_sent_total"), metric(http, "ofera_frames_sent_total")
    start = now_us() + 200_000
    records: list[tuple[int, float, int, bool]] = []  # seq, latency ms, bytes, key
    kept: list[tuple[int, bytes]] = []
    arrivals: list[tuple[int, float]] = []

    got = 0

    def on_message(data: bytes, _received: float) -> bool:
        nonlocal got
        msg = dec.decode(data)
        if not isinstance(msg, Frame):
            return False
        if msg.index is None:
            state.position[...], state.rotation[...] = msg.position, msg.rotation
        else:
            state.position[msg.index], state.rotation[msg.index] = msg.position, msg.rotation
        now = now_us()  # decoded and applied: the client's view is current
        got += 1
        if keep == "all" or (keep == "some" and got % 30 == 0):
            kept.append((msg.seq, bytes(data)))
        if msg.seq >= first:
            records.append((msg.seq, (now - msg.t) / 1000.0, len(data), bool(msg.key)))
            arrivals.append((msg.seq, now))
            if on_sample is not None and len(records) % sample == 0:
                on_sample(msg.seq, state.position.copy(), state.rotation.copy())
        return msg.seq == total - 1

    end = await C.paced_session(client, weights, start, period_us, total, on_message, tail_s=5.0)
    server_bytes = metric(http, "ofera_bytes_sent_total") - bytes0
    server_frames = metric(http, "ofera_frames_sent_total") - frames0
    await client.close()
    scheduled = {k: start + k * period_us for k in range(first, total)}
    return {"records": records, "kept": kept, "count": client.count, "format": fmt, "sent": total - first,
            "first": first, "server_bytes_per_frame": server_bytes / max(server_frames, 1),
            "dropped_ms": C.drop_latencies(scheduled, arrivals, end), "avatar": client.avatar}


# ----------------------------------------------------------------------------- offline: errors, encoder, entropy


def offline(res: dict, scheme: str, weights: np.ndarray, pipeline, assets) -> dict:
    """Errors at every counted received frame; for self-contained schemes also a check that the kept frames decode
    like the offline encoding of the exact frame."""
    from ofera.client.fast_decode import FastFrameDecoder
    from ofera.streaming.encode_fast import frame_writer
    from ofera_protocol import Frame, GaussianState

    fmt = res["format"]
    enc, sparse, delta = SCHEMES[scheme]
    st = ErrorStats()
    counted = {seq for seq, *_ in res["records"]}
    identical = True
    if delta:
        dec = FastFrameDecoder(fmt)
        state = GaussianState.from_avatar(res["avatar"])
        for seq, data in res["kept"]:
            msg = dec.decode(data)
            if not isinstance(msg, Frame):
                continue
            if msg.index is None:
                state.position[...], state.rotation[...] = msg.position, msg.rotation
            else:
                state.position[msg.index], state.rotation[msg.index] = msg.position, msg.rotation
            if seq in counted:
                exact, _ = pipeline.run(weights[seq])
                st.add(*errors(state.position, state.rotation, exact))
        return {**st.report(), "identical_to_socket": None}
    gather, index = assets.selection(sparse=True, max_gaussians=None) if sparse else (None, None)
    writer = frame_writer(fmt, "flame", gather, index)
    dec = FastFrameDecoder(fmt)
    neutral = GaussianState.from_avatar(res["avatar"])
    kept = dict(res["kept"])
    for seq in sorted(counted):
        exact, _ = pipeline.run(weights[seq])
        mine = dec.decode(bytes(writer.encode(seq, 0, {}, exact.position, exact.rotation, exact.scale)))
        pos, rot = neutral.position.copy(), neutral.rotation.copy()
        sel = slice(None) if mine.index is None else mine.index
        pos[sel], rot[sel] = mine.position, mine.rotation
        if seq in kept:
            theirs = FastFrameDecoder(fmt).decode(kept[seq])
            identical &= bool(np.array_equal(theirs.position, mine.position)
                              and np.array_equal(theirs.rotation, mine.rotation))
        st.add(*errors(pos, rot, exact))
    return {**st.report(), "identical_to_socket": identical}


def encoder_cost(weights: np.ndarray, seqs: list[int], pipeline, assets, fmt) -> dict:
    """Per-frame cost (ms) of the server's encoders on the exact frames: q13 dense (FrameWriter, numba) and the q13
    delta encoder (numba), fed every frame in order."""
    from ofera.streaming.encode_fast import delta_encoder, frame_writer
    from ofera_protocol import FrameFormat

    rows, ids = assets.selection(sparse=True, max_gaussians=None)
    dfmt = FrameFormat("q13", fmt.count, False, fmt.quant, delta=True)
    delta = delta_encoder(dfmt, "flame", None, ids.astype(np.int64), rows, key_interval=0)
    dense = frame_writer(FrameFormat("q13", fmt.count, False, fmt.quant))
    t_delta, t_dense = [], []
    for seq in seqs:
        exact, _ = pipeline.run(weights[seq])
        t0 = time.perf_counter()
        view = dense.encode(seq, 0, {}, exact.position, exact.rotation, exact.scale)
        t1 = time.perf_counter()
        delta.encode(seq, 0, {}, exact.position, exact.rotation, exact.scale)
        t2 = time.perf_counter()
        del view
        t_dense.append((t1 - t0) * 1e3)
        t_delta.append((t2 - t1) * 1e3)
    return {"q13_dense_ms": C.pct(t_dense[1:]), "q13_delta_ms": C.pct(t_delta[2:]),
            "note": "first frames (compilation cache load, key frame) excluded"}


def shuffle_planes(data: bytes, q13: bool) -> bytes:
    """A delta message's arrays with each one's byte planes grouped (byte 0 of every element, then byte 1, ...), the
    masks and int8 changes as they are: what a byte-plane shuffle would hand to an entropy coder."""
    import msgpack

    m = msgpack.unpackb(data, raw=False)
    parts = [m[k] for k in ("changed", "moved_position", "moved_rotation", "moved_scale", "wide", "position_delta")]
    for key, width in (("position", 2), ("rotation", 4 if q13 else 2), ("scale", 1 if q13 else 2)):
        parts.append(np.frombuffer(m[key], np.uint8).reshape(-1, width).T.tobytes())
    return b"".join(parts)


def entropy(kept: list[tuple[int, bytes]], q13: bool) -> dict:
    """zstd (level 1, 3) and byte-plane shuffle + zstd on the delta messages: size ratio, compress / decompress
    cost per frame (ms)."""
    try:
        import zstandard
    except ImportError:
        return {"note": "the zstandard package is not installed: pip install zstandard to measure it"}
    import msgpack

    msgs = [d for _, d in kept if msgpack.unpackb(d, raw=False).get("key") is False]  # delta frames only
    raw = sum(len(d) for d in msgs)
    out = {"raw_bytes_per_frame": round(raw / max(len(msgs), 1), 1)}
    for name, level, shuffle in (("zstd1", 1, False), ("zstd3", 3, False), ("shuffle+zstd1", 1, True),
                                 ("shuffle+zstd3", 3, True)):
        cctx, dctx = zstandard.ZstdCompressor(level=level), zstandard.ZstdDecompressor()
        size = tc = td = 0.0
        for d in msgs:
            src = shuffle_planes(d, q13) if shuffle else d
            t0 = time.perf_counter()
            z = cctx.compress(src)
            t1 = time.perf_counter()
            dctx.decompress(z)
            t2 = time.perf_counter()
            size += len(z)
            tc += t1 - t0
            td += t2 - t1
        k = max(len(msgs), 1)
        out[name] = {"bytes_per_frame": round(size / k, 1), "ratio": round(size / raw, 3),
                     "compress_ms": round(tc / k * 1e3, 3), "decompress_ms": round(td / k * 1e3, 3)}
    return out


# ----------------------------------------------------------------------------- soak


class OnlineErrors:
    """A worker thread computing the error of sampled client states (the soak): its own pipeline, bounded queue."""

    def __init__(self, pipeline_factory, weights: np.ndarray) -> None:
        self.q: queue.Queue = queue.Queue(maxsize=8)
        self.weights = weights
        self.samples: list[tuple[int, float, float]] = []
        self.skipped = 0
        self._factory = pipeline_factory
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def offer(self, seq: int, pos: np.ndarray, rot: np.ndarray) -> None:
        try:
            self.q.put_nowait((seq, pos, rot))
        except queue.Full:
            self.skipped += 1

    def _run(self) -> None:
        pipeline = self._factory()
        while True:
            item = self.q.get()
            if item is None:
                return
            seq, pos, rot = item
            exact, _ = pipeline.run(self.weights[seq])
            pe, re = errors(pos, rot, exact)
            self.samples.append((seq, float(pe.max()), float(re.max())))

    def close(self) -> None:
        self.q.put(None)
        self.thread.join()


# ----------------------------------------------------------------------------- main


def summarize(res: dict, n: int, err: dict) -> dict:
    rec = res["records"]
    b = np.array([r[2] for r in rec], np.float64)
    lat = [r[1] for r in rec]
    keys = sum(1 for r in rec if r[3])
    return {"frames_received": len(rec), "bs_sent": res["sent"], "dropped": res["sent"] - len(rec),
            "key_frames": keys, "bytes_per_frame_mean": round(float(b.mean()), 1),
            "bytes_per_frame_max": int(b.max()), "bytes_per_gaussian_mean": round(float(b.mean()) / n, 4),
            "server_bytes_per_frame": round(res["server_bytes_per_frame"], 1),
            "mbit_per_s_at_72hz": round(float(b.mean()) * 8 * 72 / 1e6, 1), "e2e_ms": C.pct(lat), **err}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000, help="avatar size (0: the default avatar)")
    ap.add_argument("--seconds", type=float, default=10.0, help="streaming time per scheme and input (after warm-up)")
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--rate", type=float, default=72.0, help="bs per second")
    ap.add_argument("--schemes", default="f16,q13,q13+sparse,q13+delta", help=f"comma list of {', '.join(SCHEMES)}")
    ap.add_argument("--inputs", default="capture,sweep", help="capture (the real capture), sweep (synthetic)")
    ap.add_argument("--soak", action="store_true", help="errors online at --sample frames (long runs)")
    ap.add_argument("--sample", type=int, default=72, help="--soak: check the error every N frames")
    ap.add_argument("--threads", type=int, default=2, help="server compute threads")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    out_json = args.json or C.RESULTS / ("bandwidth_soak.json" if args.soak else "bandwidth.json")

    from ofera.streaming.pipeline import AvatarAssets, Pipeline

    load_start = C.machine()["loadavg_at_start"]
    avatar = C.load_bench_avatar(args.gaussians or None)
    mapper, notes = C.mapper()
    assets = AvatarAssets.create(C.AVATAR_ID, avatar, mapper, fast=True)
    n = avatar.count
    avatars, more = C.avatars_dir(args.gaussians or None)
    notes += more
    schemes = [s.strip() for s in args.schemes.split(",") if s.strip()]
    for s in schemes:
        if s not in SCHEMES:
            raise SystemExit(f"unknown scheme {s!r}; choose from {', '.join(SCHEMES)}")
    results: dict = {}
    series: dict = {}
    with C.ServerProcess(avatars, "fast", threads=args.threads) as server:
        http = f"http://127.0.0.1:{server.port}"
        for name, (w, layout, fps, inotes) in inputs([x.strip() for x in args.inputs.split(",")]).items():
            notes += inotes
            frames = int((args.warmup + args.seconds) * args.rate)
            stream = resample(w, fps, args.rate, frames)
            pipeline = Pipeline(assets, layout)
            pipeline.warm_up()
            for scheme in schemes:
                print(f"[bandwidth] {name}: {scheme}, {n} Gaussians, {args.seconds:g} s at {args.rate:g} Hz ...",
                      flush=True)
                online = None
                if args.soak:
                    online = OnlineErrors(lambda layout=layout: Pipeline(assets, layout), stream)
                keep = "none" if args.soak else ("all" if SCHEMES[scheme][2] else "some")
                res = asyncio.run(session(server.url, http, scheme, stream, layout, args.rate, args.seconds,
                                          args.warmup, keep, args.sample, online.offer if online else None))
                if online is not None:
                    online.close()
                    s = online.samples
                    k = max(1, len(s) // 10)
                    err = {"position_error_mm": {"max": round(max(x[1] for x in s), 6)},
                           "rotation_error_deg": {"max": round(max(x[2] for x in s), 5)},
                           "soak": {"samples": len(s), "skipped_samples": online.skipped,
                                    "first_10pct_pos_max_mm": round(max(x[1] for x in s[:k]), 6),
                                    "last_10pct_pos_max_mm": round(max(x[1] for x in s[-k:]), 6),
                                    "first_10pct_rot_max_deg": round(max(x[2] for x in s[:k]), 5),
                                    "last_10pct_rot_max_deg": round(max(x[2] for x in s[-k:]), 5)}}
                    series[f"{name}/{scheme}/soak"] = s
                else:
                    print("[bandwidth]   errors against the f32 stream ...", flush=True)
                    err = offline(res, scheme, stream, pipeline, assets)
                summary = summarize(res, n, err)
                if SCHEMES[scheme][2] and not args.soak:
                    summary["entropy_coding"] = entropy(res["kept"], SCHEMES[scheme][0] == "q13")
                    seqs = [seq for seq, *_ in res["records"]][: int(args.rate * 5)]
                    summary["encoder"] = encoder_cost(stream, seqs, pipeline, assets, res["format"])
                results[f"{name}/{scheme}"] = summary
                series[f"{name}/{scheme}"] = [(r[0], r[2] / n, r[1]) for r in res["records"]]
                print(f"[bandwidth]   {summary['bytes_per_gaussian_mean']} B/Gaussian, pos err max "
                      f"{summary.get('position_error_mm', {}).get('max')} mm, rot err max "
                      f"{summary.get('rotation_error_deg', {}).get('max')} deg, e2e p50 {summary['e2e_ms']['p50']} "
                      f"p99 {summary['e2e_ms']['p99']} ms, dropped {summary['dropped']}", flush=True)
    report = {"benchmark": "bandwidth_soak" if args.soak else "bandwidth", "gaussians": n,
              "movable": int(assets.movable().sum()), "rate_hz": args.rate, "seconds": args.seconds,
              "schemes": results, "targets": TARGETS,
              "delta_tolerance": {"position_mm": 0.045, "rotation_deg": 0.45, "log_scale": 0.02, "key_interval": 720},
              "machine": {**C.machine(), "loadavg_at_start": load_start}, "notes": notes,
              "command": " ".join(["python", "benchmarks/bandwidth.py", *(argv if argv is not None else sys.argv[1:])])}
    rows = []
    for k, r in results.items():
        rows.append([k, r["bytes_per_frame_mean"], r["bytes_per_gaussian_mean"], r["mbit_per_s_at_72hz"],
                     r.get("position_error_mm", {}).get("max"), r.get("rotation_error_deg", {}).get("max"),
                     r["e2e_ms"]["p50"], r["e2e_ms"]["p99"], r["dropped"], r["key_frames"]])
    print(C.table(rows, ["input/scheme", "bytes/frame", "B/Gaussian", "Mbit/s@72", "pos err max mm",
                         "rot err max deg", "e2e p50 ms", "e2e p99 ms", "dropped", "keys"]))
    for m in notes:
        print("note:", m)
    out = C.write_json(out_json, report)
    png = C.png_path(out)
    plot(png, series, results, f"{n} Gaussians at {args.rate:g} Hz, {args.seconds:g} s per scheme")
    print(f"wrote {out} and {png}")
    return report


def plot(path: Path, series: dict, results: dict, title: str) -> None:
    plt = C.pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(14, 4.8))
    for k, s in series.items():
        if k.endswith("/soak"):
            continue
        a = np.asarray(s)
        ax[0].plot(a[:, 1], label=k, lw=1.3 if "delta" in k else 0.8)
        ax[1].plot(np.sort(a[:, 2]), np.linspace(0, 1, len(a)), label=k, lw=1.3 if "delta" in k else 0.8)
    ax[0].axhline(TARGETS["bytes_per_gaussian"], color="grey", ls="--", lw=0.8, label="goal 2 B")
    ax[0].set_yscale("log")
    ax[0].set_xlabel("frame received")
    ax[0].set_ylabel("bytes per Gaussian per frame (log)")
    ax[0].legend(fontsize=7, ncol=2)
    ax[1].axvline(TARGETS["e2e_p99_ms_delta"], color="grey", ls="--", lw=0.8)
    ax[1].set_xscale("log")
    ax[1].set_xlabel("end-to-end latency (ms, log)")
    ax[1].set_ylabel("fraction of frames")
    ax[1].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
