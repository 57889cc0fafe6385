"""Per-frame server cost of a LAM avatar (20k Gaussians, ARKit morph head, no EPM) next to the default avatar.

    python benchmarks/lam.py --zip ../shared/data/lam_statue.zip --json benchmarks/results/lam.json

One process, one frame at a time (no network): the server's Pipeline (layout -> BDA -> EPM -> head ->
deform) on the capture's blendshapes, then the dense f16 frame encoding, for

- ``lam``: the imported LAM zip (vertex binding; the "epm" stage is skipped, "head" is the sparse
  morph-target blend of the moving vertices, "deform" the vertex-offset binding);
- ``default_20k``: the procedural default avatar generated at the same size (FLAME-structured head, EPM,
  triangle binding), so both sides deform about as many Gaussians;
- ``default``: the default avatar itself (about 115k Gaussians).

Each runs the fast path (numba) and the numpy reference, interleaved round by round so that load from other
processes on a shared machine hits every variant alike. Medians and p99 per stage in ms; the minimum is the
best estimate of the uncontended cost. Writes JSON and a PNG (stacked medians) next to it.
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
DEFAULT_ZIP = C.SHARED_DATA / "lam_statue.zip"


def variants(zip_path: Path, sizes: list[str]):
    """(name, avatar, mapper or None) for each variant asked for."""
    from ofera.avatar.lam import import_lam_cached

    mapper, notes = C.mapper()
    out = []
    for name in sizes:
        if name == "lam":
            out.append((name, import_lam_cached(zip_path), None))
        elif name == "default_20k":
            out.append((name, C.load_bench_avatar(20000), mapper))
        elif name == "default":
            out.append((name, C.load_bench_avatar(None), mapper))
        else:
            raise SystemExit(f"unknown variant {name!r} (lam, default_20k, default)")
    return out, notes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--zip", type=Path, default=DEFAULT_ZIP, help="LAM export .zip")
    ap.add_argument("--variants", default="lam,default_20k,default")
    ap.add_argument("--frames", type=int, default=400, help="fast-path frames per variant")
    ap.add_argument("--ref-frames", type=int, default=60, help="reference frames per variant")
    ap.add_argument("--json", type=Path, default=C.RESULTS / "lam.json")
    args = ap.parse_args()
    if not args.zip.is_file():
        raise SystemExit(f"{args.zip}: no such file (give a LAM export with --zip)")
    from ofera.streaming.encode_fast import frame_writer
    from ofera.streaming.pipeline import AvatarAssets, Pipeline
    from ofera_protocol import FrameFormat

    weights, layout, fps, notes = C.capture()
    found, epm_notes = variants(args.zip, args.variants.split(","))
    runs = []
    for name, avatar, mapper in found:
        for impl in C.IMPLS:
            assets = AvatarAssets.create(name, avatar, mapper, fast=impl == "fast")
            pipe = Pipeline(assets, layout)
            pipe.warm_up(3)
            writer = frame_writer(FrameFormat("f16", avatar.count, False, None))
            runs.append({"name": name, "impl": impl, "pipe": pipe, "writer": writer, "avatar": avatar,
                         "moving": assets.fast.moving if assets.fast is not None else avatar.count,
                         "n": args.frames if impl == "fast" else args.ref_frames,
                         "times": {k: [] for k in (*STAGES, "encode_f16", "compute", "total_f16")}})
    print(f"{len(weights)} capture frames ({layout}, {fps:.0f} fps); {len(runs)} runs", flush=True)
    for i in range(max(r["n"] for r in runs)):  # interleaved: contention hits every variant alike
        for r in runs:
            if i >= r["n"]:
                continue
            state, st = r["pipe"].run(weights[i % len(weights)])
            t0 = time.perf_counter()
            data = r["writer"].encode(1, 1, {"total": 1}, state.position, state.rotation, state.scale)
            enc = (time.perf_counter() - t0) * 1e3
            del data, state
            t = r["times"]
            for k in STAGES:
                t[k].append(st[k] / 1000.0)
            t["encode_f16"].append(enc)
            t["compute"].append(sum(st[k] for k in STAGES) / 1000.0)
            t["total_f16"].append(t["compute"][-1] + enc)
    results = {}
    rows = []
    for r in runs:
        stats = {k: {"p50": C.pct(v)["p50"], "p99": C.pct(v)["p99"], "min": round(float(np.min(v)), 4)}
                 for k, v in r["times"].items()}
        a = r["avatar"]
        results.setdefault(r["name"], {"gaussians": a.count, "sh_degree": a.sh_degree,
                                       "binding": a.binding_type,
                                       "expression": getattr(a, "expression", "flame68")})[r["impl"]] = {
            "moving": r["moving"], "frames": r["n"], **stats}
        rows.append([r["name"], r["impl"], a.count, r["moving"], *(stats[k]["p50"] for k in STAGES),
                     stats["compute"]["p50"], stats["encode_f16"]["p50"], stats["total_f16"]["p50"],
                     stats["total_f16"]["p99"]])
    headers = ["avatar", "impl", "N", "moving", *STAGES, "compute", "enc f16", "total p50", "total p99"]
    print(C.table(rows, headers))
    report = {"benchmark": "lam", "zip": args.zip.name, "capture_layout": layout, "capture_frames": len(weights),
              "machine": C.machine(), "notes": notes + epm_notes + [
                  "one frame at a time in one process; medians (p50), p99 and minimum in ms",
                  "lam: the 'epm' stage is skipped (ARKit weights drive the morph targets directly)"],
              "results": results}
    C.write_json(args.json, report)
    plot(results, C.png_path(args.json))
    print(f"wrote {args.json} and {C.png_path(args.json)}")


def plot(results: dict, path: Path) -> None:
    """Stacked median stage times per avatar, one panel per implementation (linear ms)."""
    plt = C.pyplot()
    keys = (*STAGES, "encode_f16")
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, impl in zip(axes, C.IMPLS):
        names = [n for n, r in results.items() if impl in r]
        stacks = np.array([[results[n][impl][k]["p50"] for k in keys] for n in names]).reshape(len(names), -1)
        bottom = np.zeros(len(names))
        labels = [f"{n}\n{results[n]['gaussians'] / 1000:.0f}k" for n in names]
        for j, k in enumerate(keys):
            ax.bar(labels, stacks[:, j], bottom=bottom, label=k)
            bottom += stacks[:, j]
        for x, total in enumerate(bottom):
            ax.text(x, total, f"{total:.2f} ms", ha="center", va="bottom", fontsize=8)
        ax.set_title(f"{impl} path")
        ax.set_ylabel("median ms per frame")
    axes[0].legend(fontsize=8)
    fig.suptitle("Per-frame server cost: LAM statue (ARKit morph, 20k) vs the default avatar")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
