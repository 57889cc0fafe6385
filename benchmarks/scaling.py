"""Per-stage server time against avatar size, fast path and reference side by side (in process).

    python benchmarks/scaling.py --sizes 10000,25000,50000,100000,150000,200000 --json out.json

For each size a procedural avatar of N Gaussians runs the server's Pipeline (layout -> BDA -> EPM ->
head -> deform) on the capture's blendshapes, then the frame is encoded (f16 and q13, dense) with the
numba FrameWriter (fast) or ofera_protocol.encode_frame (reference). Medians and p99 per stage in ms,
the reference / fast ratio, and for the fast deformation also the prange variant (2 numba threads).
One frame at a time in one process: no network, no event loop. On a shared machine the minimum is
the best estimate of the uncontended cost; medians and p99 show the contention.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

STAGES = ("layout", "bda", "epm", "head", "deform")


def measure_size(n: int | None, weights, layout, mapper, frames: int, ref_frames: int, parallel: bool) -> dict:
    import numba
    from ofera.streaming.encode_fast import frame_writer
    from ofera.streaming.pipeline import AvatarAssets, Pipeline
    from ofera_protocol import Frame, FrameFormat, encode_frame

    avatar = C.load_bench_avatar(n)
    out = {"gaussians": avatar.count}
    for impl in C.IMPLS:
        fast = impl == "fast"
        assets = AvatarAssets.create(C.AVATAR_ID, avatar, mapper, fast=fast)
        pipe = Pipeline(assets, layout)
        pipe.warm_up(2)
        quant = assets.quant("flame")
        encoders = {}
        for enc in ("f16", "q13"):
            fmt = FrameFormat(enc, avatar.count, False, quant if enc == "q13" else None)
            if fast:
                w = frame_writer(fmt)
                encoders[enc] = lambda st, w=w: w.encode(1, 1, {"total": 1}, st.position, st.rotation, st.scale)
            else:
                encoders[enc] = lambda st, fmt=fmt: encode_frame(
                    Frame(seq=1, t=1, timing={"total": 1}, position=st.position, rotation=st.rotation,
                          scale=st.scale), fmt)
        times: dict[str, list[float]] = {k: [] for k in (*STAGES, "encode_f16", "encode_q13", "total_f16")}
        for i in range(frames if fast else ref_frames):
            state, st = pipe.run(weights[i % len(weights)])
            for k in STAGES:
                times[k].append(st[k] / 1000.0)
            for enc, f in encoders.items():
                t0 = time.perf_counter()
                data = f(state)
                times[f"encode_{enc}"].append((time.perf_counter() - t0) * 1e3)
                del data
            times["total_f16"].append(sum(st[k] for k in STAGES) / 1000.0 + times["encode_f16"][-1])
            del state
        out[impl] = {k: {"p50": C.pct(v)["p50"], "p99": C.pct(v)["p99"], "min": round(float(np.min(v)), 3)}
                     for k, v in times.items()}
        out[impl]["moving"] = assets.fast.moving if fast else avatar.count
        if fast and parallel:  # the same deformation with prange over 2 numba threads
            session = assets.fast.session(parallel=True)
            serial = assets.fast.session(parallel=False)
            numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
            from ofera.mapping.flame_values import split_flame_values

            y = pipe.mapper.map(pipe.bda.apply(pipe.adapter(weights[0])))
            expr, rot = split_flame_values(y)
            verts = serial.head(expr, rot).copy()
            for s in (session, serial):
                s.deform(verts)
            tp, ts = [], []
            for _ in range(frames):
                t0 = time.perf_counter()
                a = session.deform(verts)
                t1 = time.perf_counter()
                b = serial.deform(verts)
                t2 = time.perf_counter()
                tp.append((t1 - t0) * 1e3)
                ts.append((t2 - t1) * 1e3)
                del a, b
            out["deform_prange2"] = {"p50": C.pct(tp)["p50"], "p99": C.pct(tp)["p99"],
                                     "serial_p50": C.pct(ts)["p50"], "serial_p99": C.pct(ts)["p99"]}
    out["ratios_p50"] = {k: C.ratio(out["fast"][k]["p50"], out["reference"][k]["p50"])
                         for k in ("head", "deform", "encode_f16", "encode_q13", "total_f16")}
    out["ratios_min"] = {k: C.ratio(out["fast"][k]["min"], out["reference"][k]["min"])
                         for k in ("head", "deform", "encode_f16", "encode_q13", "total_f16")}
    return out


def plot(path: Path, rows: list[dict], title: str) -> None:
    plt = C.pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(13, 4.8))
    ns = [r["gaussians"] for r in rows]
    for i, (impl, ls) in enumerate((("fast", "-"), ("reference", "--"))):
        for k, color in (("head", "tab:brown"), ("deform", "tab:pink"), ("encode_f16", "tab:green"),
                         ("encode_q13", "tab:olive"), ("epm", "tab:purple"), ("total_f16", "black")):
            ax[i].plot(ns, [r[impl][k]["p50"] for r in rows], ls, marker="o", color=color, label=k)
        ax[i].set_title(impl)
        ax[i].set_xscale("log")
        ax[i].set_yscale("log")
        ax[i].set_xlabel("Gaussians")
        ax[i].set_ylabel("median per frame (ms, log)")
        ax[i].grid(alpha=0.3, which="both")
        ax[i].legend(fontsize=8)
    ax[0].axhline(2.0, color="grey", ls=":", lw=0.8)
    C.save_figure(fig, path, title)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10000,25000,50000,100000,150000,200000")
    ap.add_argument("--frames", type=int, default=60, help="frames per size (fast path)")
    ap.add_argument("--reference-frames", type=int, default=5, help="frames per size (reference)")
    ap.add_argument("--no-parallel", action="store_true", help="skip the prange measurement")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "scaling.json")
    args = ap.parse_args(argv)

    weights, layout, _, notes = C.capture()
    mapper, epm_notes = C.mapper()
    notes += epm_notes
    rows = []
    for n in [int(x) for x in args.sizes.split(",") if x.strip()]:
        print(f"[scaling] {n} Gaussians ...", flush=True)
        rows.append(measure_size(n, weights, layout, mapper, args.frames, args.reference_frames,
                                 not args.no_parallel))
    table_rows = []
    for r in rows:
        f, ref = r["fast"], r["reference"]
        table_rows.append([r["gaussians"], f["moving"], f["epm"]["p50"], f["head"]["p50"], ref["head"]["p50"],
                           f["deform"]["p50"], ref["deform"]["p50"], (r.get("deform_prange2") or {}).get("p50"),
                           f["encode_f16"]["p50"], ref["encode_f16"]["p50"], f["encode_q13"]["p50"],
                           ref["encode_q13"]["p50"], f["total_f16"]["min"], f["total_f16"]["p50"],
                           f["total_f16"]["p99"], ref["total_f16"]["min"], ref["total_f16"]["p50"],
                           r["ratios_p50"]["total_f16"]])
    print(C.table(table_rows, ["N", "moving", "epm", "head", "ref", "deform", "ref", "prange2", "enc f16", "ref",
                               "enc q13", "ref", "total f16 min", "p50", "p99", "ref min", "ref p50", "ratio"]))
    for m in notes:
        print("note:", m)
    report = {"benchmark": "scaling", "unit": "ms per frame", "sizes": rows,
              "definitions": {"total_f16": "layout + bda + epm + head + deform + f16 encode of one frame"},
              "machine": C.machine(), "notes": notes}
    out = C.write_json(args.json, report)
    png = C.png_path(out)
    plot(png, rows, f"per-stage median vs avatar size ({C.machine()['cpus']} CPUs, shared machine)")
    print(f"wrote {out} and {png}")
    return report


if __name__ == "__main__":
    main()
