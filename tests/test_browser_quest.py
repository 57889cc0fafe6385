"""The page's drag-and-drop reader (web/static/facelog.js) on Quest Pro Unity logs, in headless Chromium:
the same samples, times and confidences as the Python reader (ofera.sources.quest_csv), and playback of
one through a live server with its confidences on the wire.

Needs /usr/bin/chromium and the `playwright` package, like tests/test_browser_preview.py (skipped otherwise).
"""

from __future__ import annotations

import urllib.request
from pathlib import Path

import numpy as np
import pytest
from browser_support import open_page, page_errors
from ofera.mapping.layouts import convert
from ofera.sources import read_facelog, read_facelog_report
from quest_logs import v1_names, write_quest_log


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from replay_support import small_server

    with small_server(tmp_path_factory.getbasetemp() / "small-avatar-browser-quest", 1000) as s:
        yield s


PARSE = """async ([text, name]) => {
  const F = await import("/static/facelog.js");
  const table = await (await fetch("/static/layouts.json")).json();
  try {
    const log = F.parseFaceLog(text, table, name);
    return { times: Array.from(log.times), frames: Array.from(log.frames), conf: log.conf && Array.from(log.conf),
             layout: log.layout, rows: log.rows, kind: log.kind, report: log.report ?? null };
  } catch (e) { return { error: e.message }; }
}"""


def parse_in_page(page, path: Path) -> dict:
    return page.evaluate(PARSE, [path.read_bytes().decode("utf-8"), path.name])


VARIANTS = {
    "v2_tracker_bom_max_label_shuffled": dict(version=2, bom=True, max_column=True, label=True, shuffle=True),
    "v1_unity_clock_repeats": dict(version=1, tracker_time=False, clock="TimeFromStart", confidence=False),
    "v1_status_timestamp": dict(version=1, tracker_time=False, clock="Timestamp"),
    "v1_max_without_cells": dict(version=1, max_column=True, max_cell=False, label=True),
    "v2_tracker_zero_before_tracking_no_status": dict(version=2, status=False, lead_s=0.5),
    "v2_coarse_tracker_time": dict(version=2, device_t0=123456.0, tracker_csharp=True),
    "v2_facestate_time": dict(version=2, tracker_name="FaceState.Time"),
}


def test_page_reader_matches_the_python_reader(browser, server, tmp_path):
    page = open_page(browser, f"{server.http_url}/static/layouts.json", viewport=None, settle=False)
    try:
        for name, options in VARIANTS.items():
            path = tmp_path / f"{name}.csv"
            write_quest_log(path, seconds=1.5, **options)
            log, rep = read_facelog_report(path)
            got = parse_in_page(page, path)
            assert "error" not in got, (name, got)
            assert got["layout"] == log.layout.name and got["rows"] == len(log), name
            assert got["report"]["invalid"] == rep.invalid and got["report"]["duplicates"] == rep.duplicates, name
            assert got["report"]["problems"] == rep.problems, name  # the same notes, word for word
            assert got["report"]["timeSource"].split(" (")[0] == rep.time_source.split(" (")[0], name
            np.testing.assert_allclose(got["times"], log.times, atol=1e-6, err_msg=name)
            frames = np.array(got["frames"], np.float32).reshape(-1, 52)
            np.testing.assert_allclose(frames, convert(log.layout, log.weights, "arkit52"), atol=1e-5, err_msg=name)
            if log.confidence is None:
                assert got["conf"] is None
            else:
                np.testing.assert_allclose(np.reshape(got["conf"], (-1, 2)), log.confidence, atol=1e-6)
            assert got["report"]["samples"] == len(log) and "Quest Pro log" in got["kind"]

        snap = tmp_path / "snapshot.csv"
        write_quest_log(snap, version=1, tracker_hz=5, row_hz=5, seconds=1.0, tracker_time=False, clock=None,
                        status=False, confidence=False, label=True, invalid_window=None)
        got = parse_in_page(page, snap)
        assert got["rows"] == 6 and "30 rows/s (assumed)" in got["kind"]  # the page's stand-in for --fps
        np.testing.assert_allclose(got["times"], np.arange(6) / 30)

        raw = tmp_path / "headerless.csv"
        write_quest_log(raw, version=1, tracker_hz=10, row_hz=10, seconds=1.0, tracker_time=False, clock=None,
                        status=False, confidence=False, headerless=True, invalid_window=None)
        got = parse_in_page(page, raw)
        assert got["layout"] == "ovr63" and got["rows"] == 11
        np.testing.assert_allclose(np.array(got["frames"]).reshape(-1, 52),
                                   convert("ovr63", read_facelog(raw, "ovr63", 30).weights, "arkit52"), atol=1e-5)

        bad = tmp_path / "short.csv"
        bad.write_text("Face_Time," + ",".join(v1_names()[:40]) + "\n1" + ",0" * 40 + "\n")
        got = parse_in_page(page, bad)
        assert "not a complete Meta ovr63 log: missing LIP_PUCKER_L" in got["error"]
    finally:
        page.close()


def metric(server, name: str) -> float:
    """A counter of the server's /metrics (0 if absent)."""
    text = urllib.request.urlopen(f"{server.http_url}/metrics", timeout=30).read().decode()
    return sum(float(line.split()[-1]) for line in text.splitlines() if line.startswith(name + " "))


def play_log(browser, server, path, truth) -> tuple[int, int, float, str, dict, list]:
    """Play the log at `path` once in a fresh page until it settles: (bs sent, samples the page counted as skipped,
    bs with `conf` the server counted, the #playinfo text, what playText returned, page errors and problems)."""
    page = open_page(browser, f"{server.http_url}/", viewport={"width": 800, "height": 600})
    problems = page_errors(page)
    try:
        page.uncheck("#loop")
        seq = page.evaluate("__ofera.lastSentSeq")
        with_conf = metric(server, "ofera_bs_conf_total")
        out = page.evaluate("t => __ofera.playText(t, 'quest.csv')", path.read_bytes().decode("utf-8"))
        assert out.get("rows") == len(truth.times), out
        info = page.text_content("#playinfo")
        page.wait_for_function("!__ofera.playing && __ofera.settled", timeout=120_000)
        sent, skipped = page.evaluate("__ofera.lastSentSeq") - seq, page.evaluate("__ofera.playSkipped")
        conf = metric(server, "ofera_bs_conf_total") - with_conf
        return sent, skipped, conf, info + " | " + page.text_content("#playinfo"), out, page.evaluate(
            "__ofera.errors") + problems
    finally:
        page.close()


def test_page_plays_a_quest_log_with_its_confidence(browser, server, tmp_path):
    """Every sample is sent once with its confidence, or counted as skipped: the page plays in real time, so a
    timer that fires late (a busy machine) passes rows over and flow control (two bs unanswered) supersedes one.
    At 36 Hz against a small avatar that answers in a few ms most samples go out (here alone: all; in a loaded CI run
    with software WebGL on the page's main thread, 7 of 36 were skipped once); every bs sent carries its `conf`."""
    path = tmp_path / "quest.csv"
    truth = write_quest_log(path, seconds=1.0, bom=True, label=True)
    sent, skipped, conf, info, out, problems = play_log(browser, server, path, truth)
    assert out.get("layout") == "ovr70" and "Quest Pro log (quest-v2" in info, (out, info)
    assert sent + skipped == len(truth.times), ("a sample neither sent nor counted as skipped", sent, skipped)
    assert skipped <= len(truth.times) // 2, f"{skipped} of {len(truth.times)} samples skipped"
    assert conf == sent and not problems, (conf, sent, problems)  # each with its conf, accepted by the server


def test_page_counts_the_samples_it_cannot_send_in_time(browser, server, tmp_path):
    """A log faster than a timer and a round trip (1 kHz) cannot go out sample by sample: what is not sent is
    counted as skipped, never lost silently, and the recording's last sample still goes out with its conf."""
    path = tmp_path / "fast.csv"
    truth = write_quest_log(path, seconds=0.5, tracker_hz=1000.0, row_hz=1000.0)
    sent, skipped, conf, info, _, problems = play_log(browser, server, path, truth)
    assert sent + skipped == len(truth.times) and skipped > 0, (sent, skipped, len(truth.times))
    assert f"{skipped} of {len(truth.times)} samples skipped" in info
    assert conf == sent and not problems, (conf, sent, problems)
