"""benchmarks/profile_frame.py and the honest-load options of capacity.py / latency.py run end to end at toy
size: every stage of a frame is attributed, the CPU the clients and the server used is reported, K sessions
spread over client processes add up, and /metrics histograms are read back over a window."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_benchmarks_smoke import BENCH, SMALL, check_outputs, load

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import _common as C  # noqa: E402


@pytest.mark.timeout(300)
def test_profile_attributes_every_stage(tmp_path) -> None:
    out = tmp_path / "profile.json"
    load("profile_frame").main(["--gaussians", SMALL, "--frames", "40", "--warmup", "0.3", "--no-floor",
                                "--json", str(out)])
    r = check_outputs(out)
    fast, ref = r["results"]["fast"], r["results"]["reference"]
    for run in (fast, ref):
        assert run["frames"] + run["frames_skipped"] == run["frames_sent"] == 40
        for stage in ("bs_send", "decode", "queue", "layout", "bda", "epm", "head", "deform", "encode", "send",
                      "drain", "client_decode", "wire_and_loops"):
            assert run["stages_ms"][stage]["p50"] is not None, stage
        assert run["cpu"]["client_cores"] > 0 and run["cpu"]["server_cores"] > 0
    assert ref["stages_ms"]["encode"]["source"].startswith("/metrics")  # the reference stamps no encode time
    assert r["machine"]["loadavg_at_start"] is not None and r["order"][0] == "bs_send"


def test_profile_fits_stage_times_to_the_frame_size() -> None:
    """by_size: a stage that grows with the message (a delta frame's deformation) is told apart from one that
    does not; frames of one size give no fit."""
    by_size = load("profile_frame").by_size
    rng = np.random.default_rng(3)
    kb = rng.uniform(20, 450, 200)
    rows = [{"bytes": int(k * 1e3), "e2e": 2.0 + 0.008 * k} for k in kb]
    per_frame = {"deform": list(1.1 + 0.0036 * kb + rng.normal(0, 0.01, kb.size)),
                 "queue": list(0.2 + rng.normal(0, 0.01, kb.size)), "client_decode": []}
    fit = by_size(rows, per_frame)
    deform, queue = fit["fits"]["deform"], fit["fits"]["queue"]
    assert abs(deform["ms_per_kb"] - 0.0036) < 2e-4 and abs(deform["intercept_ms"] - 1.1) < 0.02
    assert deform["r"] > 0.99 and abs(queue["r"]) < 0.3 and "client_decode" not in fit["fits"]
    assert fit["fits"]["e2e"]["ms_per_kb"] == pytest.approx(0.008, rel=1e-3)
    assert fit["kb"]["min"] >= 20 and fit["kb"]["max"] <= 450
    same = [{"bytes": 2_000_154, "e2e": 3.0 + 0.1 * i} for i in range(50)]
    assert by_size(same, {"deform": [1.0] * 50}) is None


@pytest.mark.timeout(300)
def test_capacity_clients_in_processes_and_delta(tmp_path) -> None:
    out = tmp_path / "capacity.json"
    load("capacity").main(["--gaussians", SMALL, "--seconds", "0.5", "--warmup", "0.3", "--sessions", "1,3",
                           "--reference-sessions", "", "--client-procs", "2", "--encoding", "q13", "--delta",
                           "--json", str(out)])
    r = check_outputs(out)
    assert r["delta"] and r["client_procs"] == 2
    for k, run in r["per_k"].items():
        assert run["frames"] + run["skipped"] == run["sent"] == int(k) * (int(0.8 * 72) - int(0.3 * 72))
        assert run["cpu"]["client_cores"] > 0 and run["cpu"]["server_cores"] > 0


@pytest.mark.timeout(300)
def test_latency_delta_reports_cpu_and_head_deform_encode(tmp_path) -> None:
    out = tmp_path / "latency.json"
    load("latency").main(["--gaussians", SMALL, "--seconds", "0.7", "--warmup", "0.3", "--encoding", "q13",
                          "--delta", "--impl", "fast", "--no-floor", "--json", str(out)])
    r = json.loads(out.read_text())
    assert r["delta"] and r["frames"] > 0 and r["targets"]["e2e_p99_ms"] == 5.0
    assert r["cpu"]["client_cores"] > 0 and r["head_deform_encode_ms"]["p50"] > 0


def test_histogram_window_reads_a_metrics_page() -> None:
    def page(counts: list[int], total: float) -> str:
        bounds = ["0.001", "0.002", "0.005", "+Inf"]
        lines = [f'ofera_stage_seconds_bucket{{le="{b}",stage="send"}} {c}' for b, c in zip(bounds, counts)]
        return "\n".join([*lines, f'ofera_stage_seconds_count{{stage="send"}} {counts[-1]}',
                          f'ofera_stage_seconds_sum{{stage="send"}} {total}'])

    before = C.stage_histograms(page([1, 1, 1, 1], 0.0005))
    after = C.stage_histograms(page([1, 51, 101, 101], 0.0005 + 50 * 0.0015 + 50 * 0.003))
    w = C.histogram_window(before, after, "send")
    assert w["count"] == 100 and w["mean"] == pytest.approx(2.25)
    assert w["p50"] == pytest.approx(2.0) and 4.0 < w["p99"] <= 5.0
    assert C.histogram_window(before, after, "absent")["count"] == 0


@pytest.mark.timeout(300)
@pytest.mark.skipif(not C.CAPTURE.is_file(), reason=f"real capture not available ({C.CAPTURE} is absent: the shared "
                    "data folder is not part of the repository)")
def test_replay_speed_counts_what_the_replay_tool_answered(tmp_path) -> None:
    out = tmp_path / "replay.json"
    load("replay_speed").main(["--gaussians", SMALL, "--passes", "1", "--impl", "fast", "--json", str(out)])
    r = check_outputs(out)["results"]["fast"]
    assert r["sent"] == 180 and 0 < r["received"] <= 180 and r["answered"] == round(r["received"] / 180, 4)
    assert r["meets_target"] == (r["answered"] >= 0.95) and r["cpu"]["client_cores"] > 0


@pytest.mark.timeout(300)
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="--pin needs two CPUs")
def test_profile_pins_the_server_and_the_client_apart(tmp_path) -> None:
    """--pin, in a subprocess (it pins the process that runs it): the server reports the CPUs it was given, the
    client keeps the last one."""
    out = tmp_path / "profile.json"
    subprocess.run([sys.executable, str(BENCH / "profile_frame.py"), "--gaussians", SMALL, "--frames", "20",
                    "--warmup", "0.3", "--no-floor", "--impl", "fast", "--pin", "--json", str(out)],
                   check=True, capture_output=True, timeout=280)
    r = json.loads(out.read_text())
    cpus = sorted(os.sched_getaffinity(0))
    assert r["pin"] == {"server": ",".join(map(str, cpus[:-1])), "client": [cpus[-1]]}
    assert r["results"]["fast"]["server_cpus"] == cpus[:-1] and r["results"]["fast"]["frames"] > 0
