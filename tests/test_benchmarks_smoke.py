"""Every benchmark in benchmarks/ runs end to end at toy size (5k Gaussians, about a second each) and writes
its JSON and PNG. Performance claims live in the benchmarks' own output, never here: this only keeps them
working."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
SMALL = "5000"


def load(name: str):
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(module)
    return module


def check_outputs(path: Path) -> dict:
    assert path.is_file() and path.with_suffix(".png").is_file()
    assert path.with_suffix(".png").stat().st_size > 10_000
    return json.loads(path.read_text())


@pytest.mark.parametrize("flags", [["--sessions", "0"], ["--reference-sessions", "1,x"]])
def test_capacity_refuses_bad_session_counts(flags, capsys) -> None:
    with pytest.raises(SystemExit) as e:
        load("capacity").main(flags)
    assert e.value.code == 2 and flags[0] in capsys.readouterr().err  # a usage error naming the flag, not a crash


@pytest.mark.timeout(600)  # the first test of a clean checkout to start a server: it compiles the server's kernels
def test_latency_smoke(tmp_path) -> None:  # (228-293 s on the 2-core VM, benchmarks/README.md round eighteen)
    out = tmp_path / "latency.json"
    load("latency").main(["--gaussians", SMALL, "--rate", "72", "--seconds", "0.7", "--warmup", "0.3",
                          "--encoding", "f16", "--json", str(out)])
    r = check_outputs(out)
    for key in ("gaussians", "rate_hz", "encoding", "frames", "e2e_ms", "server_ms", "stages_ms", "bytes_per_frame"):
        assert key in r
    assert set(r["e2e_ms"]) >= {"p50", "p90", "p99", "p999", "max"} and set(r["server_ms"]) >= {"p50", "p99"}
    assert r["frames"] > 0 and r["encoding"] == "f16" and 4000 < r["gaussians"] < 6000
    assert r["reference"]["frames"] > 0 and "ratios" in r
    for run in (r, r["reference"]):  # every bs sent after warm-up is either answered or counted as skipped
        assert run["frames"] + run["frames_skipped"] == run["frames_sent"] == int(1.0 * 72) - int(0.3 * 72)
        assert run["drop_fraction"] == round(run["frames_skipped"] / run["frames_sent"], 4)
        assert 0 <= run["cpu"]["steal_pct"] <= 100  # (Linux: /proc/stat's steal over the run)


@pytest.mark.timeout(300)
def test_capacity_smoke(tmp_path) -> None:
    out = tmp_path / "capacity.json"
    load("capacity").main(["--gaussians", SMALL, "--seconds", "0.5", "--warmup", "0.3", "--sessions", "1,2",
                           "--reference-sessions", "1", "--json", str(out)])
    r = check_outputs(out)
    assert set(r["per_k"]) == {"1", "2"} and r["per_k"]["2"]["frames"] > 0
    assert "max_sessions_within_budget" in r and "1" in r["reference"]["per_k"]
    for k, run in r["per_k"].items():
        assert run["frames"] + run["skipped"] == run["sent"] == int(k) * (int(0.8 * 72) - int(0.3 * 72))
        assert run["passes"] == (run["drop_fraction"] <= r["max_drop"] and run["p99_ms"] < r["budget_ms"])
    passing = [k for k in (1, 2) if all(r["per_k"][str(j)]["passes"] for j in range(1, k + 1))]
    assert r["max_sessions_within_budget"] == max(passing, default=0)


@pytest.mark.timeout(300)
def test_params_latency_and_capacity_smoke(tmp_path, monkeypatch) -> None:
    """The compact stream (PROTOCOL.md 13): every params frame stamped, the client deforming its Gaussians."""
    monkeypatch.delenv("OFERA_PARAMS_STAMP_INTERVAL", raising=False)  # the benchmarks set it for their servers
    out = tmp_path / "latency.json"
    load("latency").main(["--gaussians", SMALL, "--seconds", "0.7", "--warmup", "0.3", "--encoding", "params",
                          "--impl", "fast", "--no-floor", "--json", str(out)])
    r = check_outputs(out)
    assert r["encoding"] == "params" and r["targets"]["e2e_p99_ms"] == 5.0
    assert r["frames"] + r["frames_skipped"] == r["frames_sent"] == int(1.0 * 72) - int(0.3 * 72)
    assert r["frames"] > 0 and r["bytes_per_frame"] < 1000  # 68 float32 values and a stamp, not Gaussians
    out = tmp_path / "capacity.json"
    load("capacity").main(["--gaussians", SMALL, "--seconds", "0.5", "--warmup", "0.3", "--sessions", "1,2",
                           "--encoding", "params", "--decode", "full", "--reference-sessions", "", "--json", str(out)])
    r = check_outputs(out)
    for run in r["per_k"].values():
        assert run["frames"] > 0 and run["frames"] + run["skipped"] == run["sent"]


def test_dropped_bs_take_the_latency_of_the_first_later_frame() -> None:
    """bs 1, 2 are dropped and answered by frame 3's arrival; bs 4 by nothing (the end of listening)."""
    sys.path.insert(0, str(BENCH))
    import _common

    scheduled = {seq: 1000.0 * seq for seq in range(5)}
    got = _common.drop_latencies(scheduled, [(0, 500.0), (3, 6000.0)], end_us=9000.0)
    assert got == {1: 5.0, 2: 4.0, 4: 5.0}


@pytest.mark.timeout(300)
def test_bandwidth_smoke(tmp_path) -> None:
    out = tmp_path / "bandwidth.json"
    load("bandwidth").main(["--gaussians", SMALL, "--seconds", "1", "--warmup", "0.5", "--inputs", "sweep",
                            "--schemes", "q13,q13+delta", "--json", str(out)])
    r = check_outputs(out)
    assert set(r["schemes"]) == {"sweep/q13", "sweep/q13+delta"}
    plain, delta = r["schemes"]["sweep/q13"], r["schemes"]["sweep/q13+delta"]
    assert plain["identical_to_socket"] and plain["frames_received"] > 0 and delta["key_frames"] >= 0
    assert delta["position_error_mm"]["max"] <= 0.05 and delta["rotation_error_deg"]["max"] <= 0.5
    assert delta["bytes_per_frame_mean"] < plain["bytes_per_frame_mean"]


@pytest.mark.timeout(300)
def test_scaling_smoke(tmp_path) -> None:
    out = tmp_path / "scaling.json"
    load("scaling").main(["--sizes", "5000,10000", "--frames", "5", "--reference-frames", "2", "--json", str(out)])
    r = check_outputs(out)
    assert [s["gaussians"] for s in r["sizes"]][0] < r["sizes"][1]["gaussians"]
    assert r["sizes"][0]["fast"]["deform"]["p50"] is not None and "ratios_p50" in r["sizes"][0]


@pytest.mark.timeout(300)
def test_transport_smoke(tmp_path) -> None:
    out = tmp_path / "transport.json"
    load("transport").main(["--sizes", "300,70000", "--requests", "20", "--warmup", "3", "--json", str(out)])
    r = check_outputs(out)
    assert r["sizes"] == [300, 70000] and r["clients"] == ["socket", "fast", "websockets"]
    for size in ("300", "70000"):
        for client in r["clients"]:
            run = r["results"][size][client]
            assert run["n"] == 20 and 0 < run["min"] <= run["p50"] <= run["p99"] and run["cpu_ms"] >= 0
        assert set(r["ratios"][size]) == {"websockets_over_fast", "fast_over_socket"}
    assert r["cpu"]["client_cores"] is not None and r["cpu"]["server_cores"] is not None
    assert 0 <= r["cpu"]["steal_pct"] <= 100


@pytest.mark.timeout(120)
def test_cold_cache_smoke(tmp_path) -> None:
    out = tmp_path / "cold_cache.json"
    load("cold_cache").main(["--gaps", "0.5,2", "--reps", "5", "--sleep", "--json", str(out)])
    r = check_outputs(out)
    assert r["gaps_ms"] == [0.5, 2.0] and len(r["results"]) == 8
    for name, series in r["results"].items():
        assert set(series) == {"back_to_back", "after_0.5ms", "after_2ms", "sleep_0.5ms", "sleep_2ms"}, name
        assert series["back_to_back"]["n"] == 4 * 5 and series["after_2ms"]["n"] == 5
        assert all(0 < s["min"] <= s["p50"] <= s["p99"] for s in series.values())
        assert set(r["ratios"][name]) == set(series) - {"back_to_back"}
