"""Bytes per frame for every encoding (dense, sparse, and q13 "moved since last sent") on a real capture,
with the error a client sees against the exact float32 frame.

    python benchmarks/bandwidth.py --gaussians 100000 --json out.json

Replays the capture (_common.CAPTURE, via ofera.sources.read_facelog; a synthetic log, noted, if
absent) through the server's pipeline, one frame per captured sample, and encodes every
frame as the server would:

- dense f32 / f16 / q13: every Gaussian, every frame;
- sparse (+index): the avatar's movable Gaussians every frame (the reference server's sparse set);
- q13 delta: sparse q13 frames of only the Gaussians that moved since what this client last received
  (ofera.streaming.encode_fast.DeltaQ13): a Gaussian is sent when its position is more than
  --position-threshold-mm (Euclidean) from the one the client holds, its rotation more than
  --rotation-threshold-deg from the held one, or a scale axis more than --log-scale-threshold (ln) off.
  The client's error is then bounded by the threshold (or by q13's own quantisation just after a send).

A simulated client decodes every message with the protocol codec and keeps its latest values (neutral
avatar for Gaussians never sent); errors are measured on that state against the exact frame, over all
Gaussians and frames: position (mm, Euclidean), rotation (degrees), scale (|ln ratio|).
Side by side: every dense / sparse message is also made by the reference codec (ofera_protocol.encode_frame)
and must be byte-identical; encode times of both are reported.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402


class Client:
    """A client's view of the avatar: starts neutral, applies frames (sparse ones by index)."""

    def __init__(self, neutral) -> None:
        self.p, self.r, self.s = neutral.position.copy(), neutral.rotation.copy(), neutral.scale.copy()

    def apply(self, frame) -> None:
        idx = slice(None) if frame.index is None else frame.index
        self.p[idx], self.r[idx], self.s[idx] = frame.position, frame.rotation, frame.scale

    def errors(self, state) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pe = np.linalg.norm(self.p.astype(np.float64) - state.position, axis=1) * 1e3  # mm
        r = self.r.astype(np.float64)
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        q = state.rotation.astype(np.float64)
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        sign = np.where(np.sum(r * q, axis=1) < 0, -1.0, 1.0)[:, None]
        chord = np.linalg.norm(r - sign * q, axis=1)  # stable for small angles, unlike arccos(dot)
        re = np.degrees(4 * np.arcsin(np.minimum(chord / 2, 1.0)))
        se = np.abs(np.log(np.maximum(self.s.astype(np.float64), 1e-30)) - np.log(state.scale)).max(axis=1)
        return pe, re, se


class Stat:
    def __init__(self) -> None:
        self.bytes: list[int] = []
        self.pe_max = self.re_max = self.se_max = 0.0
        self.pe_sum = self.re_sum = self.se_sum = 0.0
        self.count = 0
        self.fast_s = self.ref_s = 0.0
        self.identical = True

    def add(self, size: int, errors) -> None:
        pe, re, se = errors
        self.bytes.append(size)
        self.pe_max, self.re_max, self.se_max = max(self.pe_max, pe.max()), max(self.re_max, re.max()), \
            max(self.se_max, se.max())
        self.pe_sum += pe.sum()
        self.re_sum += re.sum()
        self.se_sum += se.sum()
        self.count += pe.size

    def report(self, n: int, frames: int) -> dict:
        b = np.asarray(self.bytes, np.float64)
        out = {"bytes_per_frame_mean": round(float(b.mean()), 1), "bytes_per_frame_max": int(b.max()),
               "bytes_per_gaussian_mean": round(float(b.mean()) / n, 3),
               "mbit_per_s_at_72hz": round(float(b.mean()) * 8 * 72 / 1e6, 1),
               "position_error_mm": {"max": round(self.pe_max, 6), "mean": round(self.pe_sum / self.count, 7)},
               "rotation_error_deg": {"max": round(self.re_max, 5), "mean": round(self.re_sum / self.count, 6)},
               "log_scale_error": {"max": round(self.se_max, 6), "mean": round(self.se_sum / self.count, 7)}}
        if self.ref_s:
            out["encode_ms_mean"] = {"fast": round(self.fast_s / frames * 1e3, 3),
                                     "reference": round(self.ref_s / frames * 1e3, 3),
                                     "ratio": C.ratio(self.fast_s, self.ref_s)}
            out["identical_to_reference"] = self.identical
        return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000, help="avatar size (0: the default avatar)")
    ap.add_argument("--frames", type=int, default=0, help="use only the first N capture frames (0: all)")
    ap.add_argument("--position-threshold-mm", type=float, default=0.045)
    ap.add_argument("--rotation-threshold-deg", type=float, default=0.5)
    ap.add_argument("--log-scale-threshold", type=float, default=0.02)
    ap.add_argument("--sweep-mm", default="0.01,0.02,0.045,0.1", help="extra delta position thresholds (mm)")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "bandwidth.json")
    args = ap.parse_args(argv)

    from ofera.streaming.encode_fast import DeltaQ13, DeltaThresholds, frame_writer
    from ofera.streaming.pipeline import AvatarAssets, Pipeline
    from ofera_protocol import Frame, FrameFormat, decode_server_message, encode_frame

    weights, layout, fps, notes = C.capture()
    if args.frames:
        weights = weights[: args.frames]
    avatar = C.load_bench_avatar(args.gaussians or None)
    mapper, epm_notes = C.mapper()
    notes += epm_notes
    assets = AvatarAssets.create(C.AVATAR_ID, avatar, mapper, fast=True)
    pipeline = Pipeline(assets, layout)
    pipeline.warm_up()
    ref_assets = AvatarAssets.create(C.AVATAR_ID, avatar, mapper, fast=False)
    ref_pipeline = Pipeline(ref_assets, layout)
    n = avatar.count
    neutral = assets.wire_avatar("flame")
    quant = assets.quant("flame")
    gather, index = assets.selection(sparse=True, max_gaussians=None)
    schemes = {}
    for enc in ("f32", "f16", "q13"):
        for sparse in (False, True):
            fmt = FrameFormat(enc, n, sparse, quant if enc == "q13" else None)
            g, i = (gather, index) if sparse else (None, None)
            schemes[f"{enc}{'+sparse' if sparse else ''}"] = (fmt, g, i, frame_writer(fmt, "flame", g, i))
    deltas = {}
    for mm in sorted({args.position_threshold_mm, *(float(x) for x in args.sweep_mm.split(",") if x.strip())}):
        th = DeltaThresholds(position_m=mm * 1e-3, rotation_deg=args.rotation_threshold_deg,
                             log_scale=args.log_scale_threshold)
        deltas[mm] = DeltaQ13(quant, gather.astype(np.int64), neutral.position, neutral.rotation, neutral.scale,
                              "flame", th)
    stats = {k: Stat() for k in schemes} | {f"q13+delta@{mm}mm": Stat() for mm in deltas}
    clients = {k: Client(neutral) for k in stats}
    q13_sparse_fmt = schemes["q13+sparse"][0]
    state_diff = {"position_m": 0.0, "rotation": 0.0, "scale_rel": 0.0}
    pipe_ms = {"fast": [], "reference": []}
    print(f"[bandwidth] {n} Gaussians ({int(assets.movable().sum())} movable), {len(weights)} frames of {layout} "
          f"at {fps:.0f} fps ...", flush=True)
    for f, w in enumerate(weights):
        t0 = time.perf_counter()
        state, _ = pipeline.run(w)
        t1 = time.perf_counter()
        pipe_ms["fast"].append((t1 - t0) * 1e3)
        if f % 10 == 0:  # the reference pipeline, side by side (slow: every 10th frame)
            t0 = time.perf_counter()
            ref_state, _ = ref_pipeline.run(w)
            pipe_ms["reference"].append((time.perf_counter() - t0) * 1e3)
            state_diff["position_m"] = max(state_diff["position_m"],
                                           float(np.abs(state.position - ref_state.position).max()))
            dot = np.abs(np.sum(state.rotation.astype(np.float64) * ref_state.rotation, axis=1))
            state_diff["rotation"] = max(state_diff["rotation"], float(np.abs(1 - dot).max()))
            state_diff["scale_rel"] = max(state_diff["scale_rel"],
                                          float((np.abs(state.scale - ref_state.scale) / ref_state.scale).max()))
        timing = {"total": 1000}
        for key, (fmt, g, i, writer) in schemes.items():
            st = stats[key]
            t0 = time.perf_counter()
            view = writer.encode(f, f, timing, state.position, state.rotation, state.scale)  # ready to send
            t1 = time.perf_counter()
            data = bytes(view)
            del view
            sel = (lambda a, g=g: a) if g is None else (lambda a, g=g: a[g])
            ref = encode_frame(Frame(seq=f, t=f, timing=timing, position=sel(state.position),
                                     rotation=sel(state.rotation), scale=sel(state.scale), index=i), fmt)
            t2 = time.perf_counter()
            st.fast_s += t1 - t0
            st.ref_s += t2 - t1
            st.identical &= data == ref
            clients[key].apply(decode_server_message(data, fmt))
            st.add(len(data), clients[key].errors(state))
        for mm, delta in deltas.items():
            key = f"q13+delta@{mm}mm"
            data = delta.message(f, f, timing, state.position, state.rotation, state.scale)
            clients[key].apply(decode_server_message(data, q13_sparse_fmt))
            stats[key].add(len(data), clients[key].errors(state))
        del state
    frames = len(weights)
    results = {k: s.report(n, frames) for k, s in stats.items()}
    main_key = f"q13+delta@{args.position_threshold_mm}mm"
    best = results[main_key]
    report = {
        "benchmark": "bandwidth",
        "gaussians": n,
        "movable": int(assets.movable().sum()),
        "frames": frames,
        "input": {"layout": layout, "fps": fps, "capture": str(C.CAPTURE) if C.CAPTURE.is_file() else None},
        "schemes": results,
        "compact": {"scheme": main_key, "bytes_per_gaussian_mean": best["bytes_per_gaussian_mean"],
                    "position_error_mm_max": best["position_error_mm"]["max"],
                    "thresholds": {"position_mm": args.position_threshold_mm,
                                   "rotation_deg": args.rotation_threshold_deg,
                                   "log_scale": args.log_scale_threshold},
                    "targets": {"bytes_per_gaussian": 5.0, "position_error_mm": 0.05}},
        "fast_vs_reference_state_max_diff": state_diff,
        "pipeline_ms_mean": {k: round(float(np.mean(v)), 3) for k, v in pipe_ms.items() if v},
        "threshold_semantics": DeltaThresholds.__doc__.replace("\n    ", " ").strip(),
        "machine": C.machine(),
        "notes": notes,
    }
    rows = []
    for k, r in results.items():
        enc = r.get("encode_ms_mean", {})
        rows.append([k, r["bytes_per_frame_mean"], r["bytes_per_gaussian_mean"], r["mbit_per_s_at_72hz"],
                     r["position_error_mm"]["max"], r["position_error_mm"]["mean"], r["rotation_error_deg"]["max"],
                     r["log_scale_error"]["max"], enc.get("fast"), enc.get("reference"), enc.get("ratio"),
                     r.get("identical_to_reference", "-")])
    print(C.table(rows, ["scheme", "bytes/frame", "B/Gaussian", "Mbit/s@72", "pos err max mm", "mean",
                         "rot err max deg", "ln s err max", "enc fast ms", "enc ref ms", "ratio", "identical"]))
    print(f"compact stream {main_key}: {best['bytes_per_gaussian_mean']} B/Gaussian/frame, position error max "
          f"{best['position_error_mm']['max']} mm (targets 5 B, 0.05 mm)")
    print("fast vs reference pipeline state, max difference:", state_diff)
    for m in notes:
        print("note:", m)
    out = C.write_json(args.json, report)
    png = C.png_path(out)
    plot(png, stats, n, f"{n} Gaussians, {frames} frames of {layout}")
    print(f"wrote {out} and {png}")
    return report


def plot(path: Path, stats: dict, n: int, title: str) -> None:
    plt = C.pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(14, 4.8))
    for k, s in stats.items():
        ax[0].plot(np.asarray(s.bytes) / n, label=k, lw=1.2 if "delta" in k else 0.8)
    ax[0].axhline(5.0, color="grey", ls="--", lw=0.8, label="target 5 B")
    ax[0].set_yscale("log")
    ax[0].set_xlabel("frame")
    ax[0].set_ylabel("bytes per Gaussian per frame (log)")
    ax[0].legend(fontsize=7, ncol=2)
    keys = list(stats)
    mean_b = [np.mean(stats[k].bytes) / n for k in keys]
    err = [max(stats[k].pe_max, 1e-7) for k in keys]
    ax[1].scatter(mean_b, err)
    for k, x, y in zip(keys, mean_b, err):
        ax[1].annotate(k, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax[1].axhline(0.05, color="grey", ls="--", lw=0.8)
    ax[1].axvline(5.0, color="grey", ls="--", lw=0.8)
    ax[1].set_xscale("log")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("mean bytes per Gaussian per frame (log)")
    ax[1].set_ylabel("max position error seen by the client (mm, log)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
