"""benchmarks/rooms.py runs end to end at toy size (5k Gaussians, rooms of 2 and 3, one server and two through a
real redis-server) and writes its JSON and PNG; every viewer-stream frame is either received or counted as dropped.
Performance claims live in the benchmark's own output, never here."""

from __future__ import annotations

import importlib.util
import json
import sys

import pytest
from redis_support import require_redis
from test_benchmarks_smoke import BENCH


def load_rooms():
    """benchmarks/rooms.py as a module (registered in sys.modules: its dataclasses look themselves up there)."""
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location("bench_rooms", BENCH / "rooms.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.mark.timeout(600)
def test_rooms_benchmark_smoke(tmp_path) -> None:
    require_redis()
    out = tmp_path / "rooms.json"
    load_rooms().main(["--gaussians", "5000", "--seconds", "0.5", "--warmup", "0.3", "--ks", "2,3",
                        "--encodings", "f16,q13", "--servers", "1,2", "--floor-seconds", "0.5",
                             "--json", str(out)])
    assert out.is_file() and out.with_suffix(".png").stat().st_size > 10_000
    r = json.loads(out.read_text())
    measured = int(0.8 * 72) - int(0.3 * 72)
    assert set(r["runs"]) == {"f16, one server", "q13, one server", "f16, two servers + Redis",
                              "q13, two servers + Redis"}
    for name, by_k in r["runs"].items():
        assert set(by_k) == {"2", "3"}
        for k, run in by_k.items():
            k = int(k)
            assert run["viewer_streams"] == k * (k - 1) and run["errors"] == []
            assert run["frames"] + run["dropped"] == run["sent"] == k * (k - 1) * measured
            assert run["frames"] > 0 and run["client_cores_busy"] >= 0
            assert run["passes"] == (run["drop_fraction"] <= r["max_drop"] and run["p99_ms"] < r["budget_ms"])
            if "Redis" in name:  # client i on server i % 2: streams within a server and across Redis
                assert len(run["server_cores_busy"]) == 2
                assert run["local"]["sent"] + run["remote"]["sent"] == run["sent"] and run["remote"]["frames"] > 0
    assert r["bus_hop"]["messages"] > 0 and r["bus_hop"]["mean_ms"] > 0 and r["bus_hop"]["p50_ms"] > 0
    assert set(r["redis_adds"]) == {"f16", "q13"} and set(r["transport_limits"]) == {"f16", "q13"}
    assert r["transport_limits"]["q13"]["frame_bytes"] < r["transport_limits"]["f16"]["frame_bytes"]
