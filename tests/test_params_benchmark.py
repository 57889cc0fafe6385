"""benchmarks/params.py runs end to end at toy size (5k Gaussians, no room, no browser) and writes its JSON and
PNG, with params frames of 294 B. Performance claims live in the benchmark's own output."""

from __future__ import annotations

import pytest
from test_benchmarks_smoke import SMALL, check_outputs, load


@pytest.mark.timeout(600)
def test_params_benchmark_smoke(tmp_path) -> None:
    out = tmp_path / "params.json"
    load("params").main(["--gaussians", SMALL, "--seconds", "0.5", "--reps", "3", "--room", "no", "--browser", "no",
                         "--json", str(out)])
    r = check_outputs(out)
    assert r["rig"]["gaussians"] <= r["rig"]["of"] and r["rig"]["body_bytes"] > 0
    b = r["bytes"]
    assert all(b[e]["frames"] > 0 for e in ("params", "f16", "q13"))
    assert b["params"]["bytes_min"] == 294 and b["params"]["bytes_mean"] < b["q13"]["bytes_mean"] / 100
    assert set(r["server_encode_us"]) == {"params", "f16 (fast writer)", "q13 (fast writer)"}
