"""Per-frame latency of the run-time mapper (BDA + EPM on ONNX Runtime), batch 1 and batched.

    python benchmarks/mapping_latency.py [--epm PATH] [--frames N] [--out-dir DIR]

Writes ``mapping_latency.json`` (percentiles in microseconds per frame) and ``mapping_latency.png``
(the batch-1 latency distribution and the per-frame time against batch size). Single-threaded session
(``intra_op_num_threads = 1``), as the server runs it. The inputs are realistic weights (sparse, in
[0, 1]); a non-identity BDA is used so that the matrix product is part of the measured path.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
from ofera.mapping.bda import BDA
from ofera.mapping.runtime import Mapper


def _inputs(n: int, rng: np.random.Generator) -> np.ndarray:
    x = rng.random((n, 51), dtype=np.float32) ** 3
    x[rng.random((n, 51)) < 0.5] = 0.0
    return x


def measure(mapper: Mapper, frames: int, batches: tuple[int, ...], rng: np.random.Generator) -> dict:
    x = _inputs(frames, rng)
    for row in x[:500]:  # warm-up
        mapper.map(row)
    single = np.empty(frames)
    clock = time.perf_counter_ns
    for i, row in enumerate(x):
        t0 = clock()
        mapper.map(row)
        single[i] = clock() - t0
    single /= 1000.0  # microseconds
    batched = {}
    for b in batches:
        xb = _inputs(b, rng)
        mapper.map_batch(xb)
        reps = max(20, 20000 // b)
        t0 = clock()
        for _ in range(reps):
            mapper.map_batch(xb)
        batched[str(b)] = (clock() - t0) / 1000.0 / reps / b
    pct = {f"p{q}": float(np.percentile(single, q)) for q in (50, 90, 99, 99.9)}
    return {"batch1_us": {**pct, "mean": float(single.mean()), "min": float(single.min())},
            "batched_us_per_frame": batched, "samples": single}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epm", default="default", help="EPM ONNX file or 'default'")
    ap.add_argument("--frames", type=int, default=20000)
    ap.add_argument("--out-dir", type=Path, default=Path("benchmarks/results"))
    args = ap.parse_args()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    w = np.eye(51) + rng.normal(0, 0.03, (51, 51))
    bda = BDA(w, rng.normal(0, 0.01, 51), device="benchmark")
    load = Mapper.default if args.epm == "default" else (lambda bda=None: Mapper.load(args.epm, bda))
    batches = (1, 8, 64, 512)
    results = {"identity_bda": measure(load(), args.frames, batches, rng),
               "with_bda": measure(load(bda), args.frames, batches, rng)}
    samples = {k: v.pop("samples") for k, v in results.items()}
    report = {
        "benchmark": "mapping_latency",
        "epm": args.epm,
        "onnxruntime": ort.__version__,
        "numpy": np.__version__,
        "machine": platform.machine(),
        "processor": platform.processor(),
        "threads": 1,
        "frames": args.frames,
        "target_us_per_frame": 200.0,
        "results": results,
    }
    out_json = args.out_dir / "mapping_latency.json"
    out_json.write_text(json.dumps(report, indent=2))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6), dpi=120)
    hi = max(float(np.percentile(s, 99.5)) for s in samples.values())
    for k, s in samples.items():
        a.hist(np.clip(s, 0, hi), bins=80, alpha=0.6, label=f"{k} (p50 {np.median(s):.1f} us)")
    a.axvline(200, color="red", ls="--", lw=1, label="target 200 us")
    a.set_xlabel("BDA + EPM, batch 1 (us per frame)")
    a.set_ylabel("frames")
    a.legend(fontsize=8)
    for k, r in results.items():
        xs = [int(n) for n in r["batched_us_per_frame"]]
        b.plot(xs, list(r["batched_us_per_frame"].values()), "o-", label=k)
    b.set_xscale("log")
    b.set_yscale("log")
    b.set_xlabel("batch size")
    b.set_ylabel("us per frame")
    b.legend(fontsize=8)
    fig.suptitle("Run-time mapper latency (ONNX Runtime, 1 thread)", fontsize=10)
    fig.tight_layout()
    out_png = args.out_dir / "mapping_latency.png"
    fig.savefig(out_png)
    plt.close(fig)
    r1 = results["with_bda"]["batch1_us"]
    print(f"BDA + EPM batch 1: p50 {r1['p50']:.1f} us, p99 {r1['p99']:.1f} us per frame")
    print(f"wrote {out_json} and {out_png}")


if __name__ == "__main__":
    main()
