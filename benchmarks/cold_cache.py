"""What a frame's small steps cost when the CPU comes back to them after a gap: the machine's cache floor.

    python benchmarks/cold_cache.py [--gaps 1,4,13.9] [--reps 200] [--json out.json]

A 72 Hz session runs each per-frame step once every 13.9 ms. Between two frames the CPU runs other code (the
other stages, the client, other processes and, on a shared host, other tenants), so a step's code and data are
no longer in the caches when its turn comes. This measures that cost for a few steps of the frame path, in this
process: for each gap G (`--gaps`, ms) and step, the CPU spins G ms in Python on `time.perf_counter` (it never
idles, so no wake-up is in the number; the spin itself touches little memory), then the step runs once ("after
G ms") and at once again ("back to back"). `--sleep` adds the same with `time.sleep(G)` instead of the spin
(what the server's threads do between frames). Steps and gaps alternate within each repetition, so that load from
other processes hits them alike.

Steps: the server's `decode` stage (``SessionCore.receive`` of one ``bs``), ``msgpack.unpackb`` of it, one small
numpy call (``np.isfinite(w).all()``, 52 weights), the same check in Python (a float sum over a memoryview,
``ofera_protocol._fields``), a numba kernel over 5 000 q13 rotations (80 kB in, 20 kB out), an empty parallel
region on numba's threads (one add per thread: what any prange kernel pays to wake the pool; the fast path's
``kernel_threads`` setting), and the pipeline's map stage (layout, BDA, EPM: ``Pipeline.map`` of a decoded bs on the
default avatar) on the fast path (``ofera.mapping.map_fast``: numba) and on the reference (numpy and ONNX Runtime).

Prints a table; writes --json and a PNG next to it. JSON: {"gaps_ms", "reps", "results": {step: {"back_to_back":
{p50, p99, min}, "after_<G>ms": {...}, "sleep_<G>ms": {...}}}, "ratios": {step: {gap: p50 after / p50 back to
back}}, "cpu", "machine", "definitions"}.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402


@numba.njit(parallel=True)
def parallel_region(per_thread: np.ndarray) -> None:
    """One add per thread of numba's pool: a parallel region with (almost) nothing in it. Not cached on disk: a
    parallel kernel's cache entry names the module it was compiled in, and this file runs as __main__ or is loaded
    under another name by the smoke test, so a second process could not load the entry (ModuleNotFoundError)."""
    for i in numba.prange(per_thread.size):
        per_thread[i] += 1.0


def steps() -> dict[str, Callable[[], Any]]:
    """The measured steps, each a call with its inputs bound (made once, outside the timing)."""
    import msgpack
    from ofera.avatar import load_avatar
    from ofera.mapping.runtime import Mapper
    from ofera.streaming.config import Settings
    from ofera.streaming.core import SessionCore
    from ofera.streaming.encode_fast import q13_rotation_kernel
    from ofera.streaming.pipeline import AvatarAssets, Pipeline
    from ofera_protocol import AvatarInfo, Blendshapes, Hello, encode

    core = SessionCore(Settings(bs_rate=1e9, bs_burst=1e9), 0)
    core.receive(encode(Hello(layout="arkit52")), 0)
    core.conn.accept("cold-cache", AvatarInfo("bench", 4, 0))
    w = np.random.default_rng(0).random(52).astype(np.float32)
    bs = encode(Blendshapes(seq=0, t=0, w=w))
    clock = iter(range(1, 1 << 62))
    rot = np.random.default_rng(1).normal(size=(5000, 4)).astype(np.float32)
    codes = np.zeros(5000, np.uint32)
    none, one = np.zeros(0, np.int64), np.ones(4, np.float32)
    q13_rotation_kernel(rot, none, 5000, one, codes)  # compiled (or loaded from numba's cache) before timing
    per_thread = np.zeros(numba.get_num_threads())
    parallel_region(per_thread)
    buf = w.tobytes()
    avatar, mapper = load_avatar("default"), Mapper.default()
    fast_map = Pipeline(AvatarAssets.create("default", avatar, mapper), "arkit52")
    reference_map = Pipeline(AvatarAssets.create("default", avatar, mapper, fast=False), "arkit52")
    decoded = np.frombuffer(buf, np.float32)  # a decoded bs's weights: a read-only view
    return {
        "server bs decode (SessionCore.receive)": lambda: core.receive(bs, next(clock) * 14_000_000),
        "msgpack.unpackb (bs)": lambda: msgpack.unpackb(bs),
        "np.isfinite(w).all() (52)": lambda: np.isfinite(w).all(),
        "Python finite check (52)": lambda: math.isfinite(sum(memoryview(buf).cast("f"))),
        "numba: 5k q13 rotations": lambda: q13_rotation_kernel(rot, none, 5000, one, codes),
        f"numba: empty parallel region ({numba.get_num_threads()} threads)": lambda: parallel_region(per_thread),
        "map stage, fast path (layout + BDA + EPM)": lambda: fast_map.map(decoded),
        "map stage, reference (numpy + ONNX Runtime)": lambda: reference_map.map(decoded),
    }


def spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def measure(gaps_ms: list[float], reps: int, sleep: bool) -> dict[str, dict[str, list[float]]]:
    """{step: {series: [us, ...]}}: per repetition, per gap and step, the call after the gap and again at once."""
    fns = steps()
    waits = [(f"after_{g:g}ms", spin, g * 1e-3) for g in gaps_ms]
    if sleep:
        waits += [(f"sleep_{g:g}ms", time.sleep, g * 1e-3) for g in gaps_ms]
    out: dict[str, dict[str, list[float]]] = {s: {"back_to_back": [], **{w[0]: [] for w in waits}} for s in fns}
    for _ in range(3):  # warm: first calls allocate and fill caches of their own
        for f in fns.values():
            f()
    for _ in range(reps):
        for series, wait, seconds in waits:
            for name, f in fns.items():
                wait(seconds)
                t0 = time.perf_counter_ns()
                f()
                t1 = time.perf_counter_ns()
                f()
                t2 = time.perf_counter_ns()
                out[name][series].append((t1 - t0) / 1e3)
                out[name]["back_to_back"].append((t2 - t1) / 1e3)
    return out


def summary(samples: list[float]) -> dict[str, float]:
    a = np.asarray(samples)
    return {"p50": round(float(np.median(a)), 2), "p99": round(float(np.percentile(a, 99)), 2),
            "min": round(float(a.min()), 2), "n": int(a.size)}


def plot(path: Path, report: dict) -> None:
    plt = C.pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    gaps = report["gaps_ms"]
    for name, r in report["results"].items():
        ys = [r["back_to_back"]["p50"]] + [r[f"after_{g:g}ms"]["p50"] for g in gaps]
        ax.plot([0.0, *gaps], ys, marker="o", label=name)
    ax.set_yscale("log")
    ax.set_xlabel("gap before the call (ms of other work; 0 = back to back)")
    ax.set_ylabel("p50 per call (us)")
    ax.legend(fontsize=8)
    C.save_figure(fig, path, "one call after a gap of other work (cold caches)")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaps", default="1,4,13.9", help="gaps in ms, comma-separated (default one 72 Hz frame and less)")
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--sleep", action="store_true", help="also measure after time.sleep(gap)")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "cold_cache.json")
    args = ap.parse_args(argv)
    try:
        gaps = [float(g) for g in args.gaps.split(",") if g.strip()]
    except ValueError:
        ap.error(f"--gaps: expected numbers of ms separated by commas, got {args.gaps!r}")
    if not gaps or min(gaps) <= 0 or args.reps < 1:
        ap.error("--gaps must name positive gaps and --reps must be at least 1")
    with C.CpuMeter() as cpu:
        raw = measure(gaps, args.reps, args.sleep)
    results = {name: {series: summary(v) for series, v in r.items()} for name, r in raw.items()}
    ratios = {name: {series: C.ratio(r["back_to_back"]["p50"], r[series]["p50"]) for series in r
                     if series != "back_to_back"} for name, r in results.items()}
    report = {"gaps_ms": gaps, "reps": args.reps, "results": results, "ratios": ratios, "cpu": cpu.report(),
              "machine": C.machine(),
              "definitions": "per call, us, perf_counter_ns; after_<G>ms: after G ms spinning in Python on "
                             "perf_counter; sleep_<G>ms: after time.sleep(G); back_to_back: the same call again at "
                             "once; ratios: p50 after / p50 back to back"}
    series = ["back_to_back", *(f"after_{g:g}ms" for g in gaps), *((f"sleep_{g:g}ms" for g in gaps)
                                                                     if args.sleep else ())]
    rows = [[name, *(r[s]["p50"] for s in series)] for name, r in results.items()]
    print(C.table(rows, ["step (p50 us)", *series]))
    C.write_json(args.json, report)
    plot(C.png_path(args.json), report)
    print(f"wrote {args.json} and {C.png_path(args.json)}")
    return report


if __name__ == "__main__":
    main()
