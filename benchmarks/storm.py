"""Connection storm against a server in its own process: thousands of connect/disconnect cycles of every
kind (clean bye, no hello, TCP reset after hello / after the welcome / while streaming, vanishing without a
close, half-sent HTTP upgrade), many at a time. Afterwards: no session left, RSS back near where it was.

    python benchmarks/storm.py --cycles 2000 --concurrency 32 --json out.json

The kinds of cycle are `_raw.KINDS`, also run by tests/test_reliability_storm.py (200 cycles there). The server's RSS is
sampled every 0.25 s; /healthz gives the sessions (and asyncio tasks, where the server reports them).
JSON: {cycles, seconds, cycles_per_s, failures, rss_mb {before, peak, after, growth}, health_before,
health_after, good_session_after}, and a PNG of RSS over time.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import threading
import time
import urllib.request
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import _common as C  # noqa: E402


def health(port: int) -> dict:
    return json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=10).read())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cycles", type=int, default=2000)
    ap.add_argument("--concurrency", type=int, default=32)
    ap.add_argument("--gaussians", type=int, default=20_000)
    ap.add_argument("--json", type=Path, default=C.RESULTS / "storm.json")
    args = ap.parse_args()

    from _raw import KINDS, cycle

    avatars, notes = C.avatars_dir(args.gaussians)
    rss: list[tuple[float, float]] = []
    failures: dict[str, int] = {}
    lock = threading.Lock()
    with C.ServerProcess(avatars, max_sessions=max(64, 2 * args.concurrency)) as server:
        pid = server.proc.pid
        t0 = time.monotonic()
        done = threading.Event()

        def sampler() -> None:
            while not done.is_set():
                rss.append((time.monotonic() - t0, C.rss_mb(pid)))
                done.wait(0.25)

        threading.Thread(target=sampler, daemon=True).start()
        time.sleep(1.0)
        before_health = health(server.port)
        rss_before = rss[-1][1]
        rng = random.Random(1)
        kinds = [KINDS[i % len(KINDS)] for i in range(args.cycles)]
        rng.shuffle(kinds)

        def worker(part: list[str], seed: int) -> None:
            r = random.Random(seed)
            for kind in part:
                try:
                    cycle(server, kind, r)
                except Exception as e:  # noqa: BLE001 - counted
                    with lock:
                        key = f"{kind}: {type(e).__name__}"
                        failures[key] = failures.get(key, 0) + 1

        start = time.monotonic()
        threads = [threading.Thread(target=worker, args=(kinds[i::args.concurrency], i))
                   for i in range(args.concurrency)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        elapsed = time.monotonic() - start
        deadline = time.monotonic() + 30
        while health(server.port)["sessions"] and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(2.0)
        after_health = health(server.port)
        good = True
        try:
            cycle(server, "bye", rng)
        except Exception:  # noqa: BLE001
            good = False
        done.set()
        rss_after = C.rss_mb(pid)

    report = {
        "benchmark": "storm", "cycles": args.cycles, "concurrency": args.concurrency, "gaussians": args.gaussians,
        "seconds": round(elapsed, 2), "cycles_per_s": round(args.cycles / elapsed, 1), "failures": failures,
        "rss_mb": {"before": round(rss_before, 1), "peak": round(max(v for _, v in rss), 1),
                   "after": round(rss_after, 1), "growth": round(rss_after - rss_before, 1)},
        "health_before": before_health, "health_after": after_health, "good_session_after": good,
        "pass": {"no_sessions_left": after_health["sessions"] == 0, "good_session_after": good,
                 "rss_growth_below_300mb": rss_after - rss_before < 300},
        "machine": C.machine(), "notes": notes,
    }
    C.write_json(args.json, report)
    print(f"{args.cycles} cycles in {elapsed:.1f} s ({report['cycles_per_s']}/s), failures {failures}")
    print(f"RSS {report['rss_mb']}; health after {after_health}; good session after: {good}")
    print(f"pass: {report['pass']}  ->  {args.json}")

    plt = C.pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.plot([t for t, _ in rss], [v for _, v in rss], color="C3")
    ax.set_xlabel("seconds")
    ax.set_ylabel("server RSS, MB")
    ax.set_title(f"Storm: {args.cycles} cycles, {args.concurrency} at a time")
    fig.tight_layout()
    fig.savefig(C.png_path(args.json), dpi=110)


if __name__ == "__main__":
    main()
