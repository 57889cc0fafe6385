"""Quest Pro Unity logs (ofera.sources.quest_csv): every variant of REFERENCE.md 1, "Quest Pro recordings in
the wild", written here, read through `read_facelog` / `read_facelog_report`, `ofera replay inspect` and
`ofera bda fit`."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from ofera.cli.main import app
from ofera.mapping.layouts import OVR63_NAMES, convert, get_layout
from ofera.sources import FaceLog, LogReport, SourceFormatError, read_facelog, read_facelog_report, write_facelog
from ofera.sources.quest_csv import column_key, read_quest_csv_report, sniff_quest_log
from quest_logs import cs_float, v1_names, v2_names, write_quest_log
from typer.testing import CliRunner

runner = CliRunner()


def test_v2_tracker_time_repeats_status_bom_max_label_shuffled(tmp_path):
    path = tmp_path / "v2.csv"
    truth = write_quest_log(path, version=2, bom=True, max_column=True, label=True, shuffle=True)
    assert path.read_bytes().startswith(b"\xef\xbb\xbf")
    log = read_facelog(path)
    assert log.layout.name == "ovr70" and len(log) == len(truth.times)
    np.testing.assert_allclose(log.times, truth.times, atol=1e-9)
    np.testing.assert_array_equal(log.weights, truth.weights)
    np.testing.assert_allclose(log.confidence, truth.confidence, rtol=1e-6)
    _, rep = read_quest_csv_report(path)
    assert rep.format == "quest-v2" and rep.rows == truth.rows and rep.samples == len(truth.times)
    assert rep.invalid == truth.invalid > 0 and rep.duplicates == truth.rows - truth.invalid - rep.samples
    assert rep.time_source.startswith("tracker (Face_Time")
    assert rep.rate_hz == pytest.approx(36.0, rel=1e-3) and rep.row_rate_hz == pytest.approx(83.0, rel=1e-2)
    assert sorted(rep.columns_ignored) == ["Emotion", "Max"]  # in the shuffled header's order
    assert rep.labels == ["Emotion"] and rep.confidence and rep.status_column == "Face_Status"
    assert rep.duration_s == pytest.approx(4.0, abs=1e-6)


def test_csharp_floats_kept_exactly(tmp_path):
    path = tmp_path / "v2.csv"
    write_quest_log(path, seconds=0.5)
    text = path.read_text()
    assert "1.401298E-45" in text and "7.413328E-07" in text
    log = read_facelog(path)
    assert log.weights[0, 5] == np.float32(1.401298e-45) and log.weights[0, 7] == np.float32(7.413328e-07)


def test_v1_unity_clock_repeats_are_identical_rows(tmp_path):
    """No tracker time: a row equal to the previous kept one is a repeat; a sample keeps its first row's time."""
    path = tmp_path / "v1.csv"
    truth = write_quest_log(path, version=1, tracker_time=False, status=False, confidence=False,
                            clock="TimeFromStart", invalid_window=None)
    log, rep = read_facelog_report(path)
    assert log.layout.name == "ovr63" and rep.format == "quest-v1"
    assert len(log) == len(truth.times) and rep.duplicates == truth.rows - len(truth.times)
    np.testing.assert_allclose(log.times, truth.times, atol=2e-5)  # 7 significant digits of C# floats
    np.testing.assert_array_equal(log.weights, truth.weights)
    assert rep.time_source.startswith("unity clock (TimeFromStart") and log.confidence is None


@pytest.mark.parametrize("clock", ["timeSinceStartup", "time", "Timestamp", "TimeFromStart"])
def test_every_unity_clock_name(tmp_path, clock):
    path = tmp_path / "c.csv"
    truth = write_quest_log(path, version=1, tracker_time=False, clock=clock, seconds=1.0)
    log, rep = read_facelog_report(path)
    assert clock in rep.time_source and len(log) == len(truth.times)


def test_tracker_time_beats_unity_clock_and_fps(tmp_path):
    path = tmp_path / "v2.csv"
    truth = write_quest_log(path, seconds=1.0)
    log, rep = read_facelog_report(path, fps=30)
    np.testing.assert_allclose(log.times, truth.times, atol=1e-9)
    assert any("--fps 30 ignored" in p for p in rep.problems)


def test_snapshot_with_label_needs_fps(tmp_path):
    path = tmp_path / "snap.csv"
    truth = write_quest_log(path, version=1, tracker_hz=5, row_hz=5, seconds=3.0, tracker_time=False, clock=None,
                            status=False, confidence=False, label=True, max_column=True, invalid_window=None)
    with pytest.raises(SourceFormatError, match="no time column: give --fps"):
        read_facelog(path)
    log, rep = read_facelog_report(path, fps=30)
    assert len(log) == truth.rows == 16 and rep.time_source.startswith("--fps 30")
    np.testing.assert_allclose(log.times, np.arange(16) / 30.0)
    np.testing.assert_array_equal(log.weights, truth.weights)
    assert rep.labels == ["Emotion"] and "Max" in rep.columns_ignored


def test_headerless_needs_layout_and_fps(tmp_path):
    path = tmp_path / "raw.csv"
    truth = write_quest_log(path, version=1, tracker_hz=10, row_hz=10, seconds=1.0, tracker_time=False, clock=None,
                            status=False, confidence=False, headerless=True, invalid_window=None)
    assert sniff_quest_log(path)
    with pytest.raises(SourceFormatError, match=r"headerless file: give --layout ovr63 or ovr70.*ovr63\?"):
        read_facelog(path)
    with pytest.raises(SourceFormatError, match="no time column: give --fps"):
        read_facelog(path, layout="ovr63")
    with pytest.raises(SourceFormatError, match="headerless rows have 63 values; layout ovr70 needs 70"):
        read_facelog(path, layout="ovr70", fps=30)
    with pytest.raises(SourceFormatError, match="ovr63 or ovr70 weights, not 'arkit52'"):
        read_facelog(path, layout="arkit52", fps=30)
    log, rep = read_facelog_report(path, layout="ovr63", fps=30)
    assert rep.format == "quest-headerless" and len(log) == 11 and log.layout.name == "ovr63"
    np.testing.assert_array_equal(log.weights, truth.weights)


def test_headerless_with_trailing_separators(tmp_path):
    rng = np.random.default_rng(3)
    w = rng.uniform(0, 1, (4, 70)).astype(np.float32)
    path = tmp_path / "raw70.csv"
    path.write_text("".join(",".join(cs_float(v) for v in row) + ",\n" for row in w))
    log = read_facelog(path, layout="ovr70", fps=72)
    assert log.layout.name == "ovr70" and len(log) == 4
    np.testing.assert_allclose(log.weights, w, rtol=1e-6)


def test_names_any_case_separator_and_enum_prefix(tmp_path):
    spellings = [n.lower().replace("_", "-") for n in OVR63_NAMES]
    spellings[24] = "FaceExpression.JawDrop"
    spellings[0] = "brow lowerer L"
    w = np.random.default_rng(1).uniform(0, 1, (3, 63)).round(4)
    lines = ["Face_Time," + ",".join(spellings), *(f"{10 + i / 36:.6f}," + ",".join(map(str, w[i])) for i in range(3))]
    path = tmp_path / "names.csv"
    path.write_text("\n".join(lines) + "\n")
    log = read_facelog(path)
    assert log.layout.name == "ovr63"
    np.testing.assert_allclose(log.weights, w, rtol=1e-6)
    assert column_key("Brow_Lowerer_L") == column_key("BrowLowererL") == column_key("BROW_LOWERER_L")


def test_csharp_bool_status_and_invalid_rows(tmp_path):
    names = v2_names()
    rows = ["Face_Time,Face_Status," + ",".join(names)]
    for i, status in enumerate(["True", "False", "True", "True", "false", "1"]):
        value = "0" if status.lower() in ("false", "0") else str(0.1 * (i + 1))
        rows.append(f"{100 + i / 36:.6f},{status}," + ",".join([value] * 70))
    path = tmp_path / "status.csv"
    path.write_text("\n".join(rows) + "\n")
    log, rep = read_facelog_report(path)
    assert len(log) == 4 and rep.invalid == 2
    np.testing.assert_allclose(log.weights[:, 0], [0.1, 0.3, 0.4, 0.6], rtol=1e-6)
    np.testing.assert_allclose(log.times, (np.array([0, 2, 3, 5])) / 36, atol=1e-6)


def test_truncated_last_line_is_dropped_and_reported(tmp_path):
    path = tmp_path / "cut.csv"
    truth = write_quest_log(path, seconds=1.0)
    text = path.read_text()
    path.write_text(text + text.splitlines()[-1][:40])  # a logger killed mid-line
    log, rep = read_facelog_report(path)
    assert len(log) == len(truth.times) and rep.malformed == 1
    assert any("fields, the header has" in p for p in rep.problems)


def test_mostly_malformed_is_refused(tmp_path):
    path = tmp_path / "bad.csv"
    write_quest_log(path, seconds=0.5, invalid_window=None)
    lines = path.read_text().splitlines()
    lines[2:] = [line.replace(",", ";", 3) for line in lines[2:]]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SourceFormatError, match=r"bad\.csv, line 3: .*rows malformed"):
        read_facelog(path)


def test_bad_number_names_line_and_column(tmp_path):
    names = v1_names()
    rows = ["time," + ",".join(names)] + [f"{i / 30:.4f}," + ",".join(["0.5"] * 63) for i in range(40)]
    rows[5] = rows[5].replace("0.5", "abc", 1)
    path = tmp_path / "num.csv"
    path.write_text("\n".join(rows) + "\n")
    log, rep = read_facelog_report(path)
    assert rep.malformed == 1 and "line 6: column 'BrowLowererL': 'abc' is not a number" in rep.problems[0]
    assert len(log) == 1  # all rows equal: one sample (no tracker time), the bad row dropped


def test_missing_names_and_layout_mismatch(tmp_path):
    names = v1_names()
    path = tmp_path / "short.csv"
    path.write_text("Face_Time," + ",".join(names[:-2] + ["UpperLipRaiserLeft", "Foo"]) + "\n1.0" + ",0" * 63 + "\n")
    with pytest.raises(SourceFormatError, match=r"missing UPPER_LIP_RAISER_L, UPPER_LIP_RAISER_R.*not understood: "
                       r"UpperLipRaiserLeft, Foo"):
        read_facelog(path)
    v2 = tmp_path / "v2.csv"
    write_quest_log(v2, seconds=0.2)
    with pytest.raises(SourceFormatError, match="holds layout 'ovr70', not 'ovr63'"):
        read_facelog(v2, layout="ovr63")


def test_tracker_time_backwards_names_the_line(tmp_path):
    names = v1_names()
    rows = ["Face_Time," + ",".join(names)] + [f"{t}," + ",".join([str(t / 10)] * 63) for t in (1.0, 1.1, 0.9)]
    path = tmp_path / "back.csv"
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(SourceFormatError, match=r"back\.csv, line 4: Face_Time goes backwards"):
        read_facelog(path)


def test_semicolon_and_decimal_comma(tmp_path):
    names = v1_names()
    rows = [";".join(["timeSinceStartup", *names])]
    rows += [";".join([f"{1 + i / 30:.4f}".replace(".", ","), *[f"{0.01 * i:.3f}".replace(".", ",")] * 63])
             for i in range(5)]
    path = tmp_path / "de.csv"
    path.write_text("\n".join(rows) + "\n")
    log = read_facelog(path)
    assert len(log) == 5
    np.testing.assert_allclose(log.weights[:, 0], 0.01 * np.arange(5), atol=1e-7)
    np.testing.assert_allclose(log.times, np.arange(5) / 30, atol=1e-4)


def test_constant_tracker_time_falls_back_to_the_clock(tmp_path):
    names = v1_names()
    rows = ["time,Face_Time," + ",".join(names)] + [f"{i / 30:.4f},0," + ",".join([str(i)] * 63) for i in range(4)]
    path = tmp_path / "zero.csv"
    path.write_text("\n".join(rows) + "\n")
    log, rep = read_facelog_report(path)
    assert len(log) == 4 and rep.time_source.startswith("unity clock (time") and rep.invalid == 0
    assert any("Face_Time never changes (never above 0): not used" in p for p in rep.problems)


def test_the_project_face_log_keeps_its_reader(tmp_path):
    """`# ofera facelog` files with only face-log columns stay with the strict reader (every row a frame);
    the same file with a Face_Time column (what the Unity recorder writes) is read as a Quest log."""
    lay = get_layout("ovr63")
    w = np.repeat(np.random.default_rng(2).uniform(0, 1, (3, 63)), 2, axis=0)
    path = tmp_path / "own.csv"
    write_facelog(path, FaceLog(times=np.arange(6) / 72, weights=w, layout=lay, confidence=np.full((6, 2), 0.9)))
    assert not sniff_quest_log(path) and len(read_facelog(path)) == 6
    lines = path.read_text().splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("time,"))
    lines[head] = lines[head].replace("time,", "time,Face_Time,", 1)
    for i in range(head + 1, len(lines)):
        lines[i] = lines[i].replace(",", f",{500 + (i - head - 1) // 2 / 36:.6f},", 1)
    path.write_text("\n".join(lines) + "\n")
    assert sniff_quest_log(path)
    log = read_facelog(path)
    assert len(log) == 3 and log.confidence is not None
    np.testing.assert_allclose(log.times, np.arange(3) / 36, atol=2e-6)


def test_inspect_cli_text_and_json(tmp_path):
    path = tmp_path / "v2.csv"
    truth = write_quest_log(path, label=True, max_column=True, bom=True)
    result = runner.invoke(app, ["replay", "inspect", str(path)])
    assert result.exit_code == 0, result.output
    for text in ("format        quest-v2", "layout        ovr70", f"rows          {truth.rows}",
                 f"samples kept  {len(truth.times)}", "time source   tracker (Face_Time", "labels: Emotion"):
        assert text in result.output
    result = runner.invoke(app, ["replay", "inspect", str(path), "--json"])
    assert result.exit_code == 0, result.output
    d = json.loads(result.output)
    assert d["samples"] == len(truth.times) and d["invalid"] == truth.invalid and d["format"] == "quest-v2"
    assert d["rate_hz"] == pytest.approx(36.0, rel=1e-3) and d["columns_ignored"]


def test_inspect_cli_errors_and_other_formats(tmp_path):
    snap = tmp_path / "snap.csv"
    write_quest_log(snap, version=1, tracker_hz=5, row_hz=5, seconds=1.0, tracker_time=False, clock=None,
                    status=False, confidence=False, label=True, invalid_window=None)
    result = runner.invoke(app, ["replay", "inspect", str(snap)])
    assert result.exit_code == 2 and "no time column: give --fps" in result.output
    own = tmp_path / "own.csv"
    write_facelog(own, FaceLog(times=np.arange(5) / 60, weights=np.zeros((5, 52)), layout=get_layout("arkit52")))
    result = runner.invoke(app, ["replay", "inspect", str(own)])
    assert result.exit_code == 0 and "format        facelog" in result.output and "arkit52" in result.output


def test_bda_fit_reads_quest_logs_with_layout_and_fps(tmp_path):
    """`ofera bda fit HEADSET TARGET` reads logs as `ofera replay` does, --layout and --fps included: a
    headerless Quest v1 log needs both (they used to be dropped: read_facelog(path) with defaults)."""
    headset = tmp_path / "headset.csv"
    truth = write_quest_log(headset, version=1, tracker_hz=30, row_hz=30, seconds=3.0, tracker_time=False,
                            clock=None, status=False, confidence=False, headerless=True, invalid_window=None)
    target = tmp_path / "target.csv"
    n = len(truth.times)
    write_facelog(target, FaceLog(times=np.arange(n) / 30, weights=convert("ovr63", truth.weights, "arkit52"),
                                  layout=get_layout("arkit52")))
    out = tmp_path / "bda.npz"
    fit = ["bda", "fit", str(headset), str(target), "-o", str(out)]
    result = runner.invoke(app, fit)
    assert result.exit_code == 2 and "give --layout ovr63 or ovr70" in result.output, result.output
    result = runner.invoke(app, [*fit, "--layout", "ovr63"])
    assert result.exit_code == 2 and "no time column: give --fps" in result.output, result.output
    result = runner.invoke(app, [*fit, "--layout", "ovr63", "--fps", "30"])
    assert result.exit_code == 0, result.output
    assert f"fitted on {n} frames" in result.output and out.is_file()
    result = runner.invoke(app, [*fit, "--layout", "ovr63", "--fps", "30", "--target-layout", "ovr70"])
    assert result.exit_code == 2 and re.search(r"target\.csv.*layout 'ovr70'", result.output), result.output
    v2 = tmp_path / "v2.csv"  # a header, tracker time: no flags needed; converts to arkit51 in [0, 1]
    v2_truth = write_quest_log(v2, seconds=0.5)
    x = read_facelog(v2).to_arkit51()
    assert x.shape == (len(v2_truth.times), 51) and np.all((x >= 0) & (x <= 1))


def test_layout_comment_names_a_headerless_file(tmp_path):
    rows = ["# layout: ovr70", *(",".join(["0.25"] * 70) for _ in range(3))]
    path = tmp_path / "commented.csv"
    path.write_text("\n".join(rows) + "\n")
    log = read_facelog(path, fps=60)
    assert log.layout.name == "ovr70" and len(log) == 1  # three equal rows: one sample


def test_header_only_file_says_so(tmp_path):
    path = tmp_path / "empty.csv"
    path.write_text("Face_Time," + ",".join(v1_names()) + "\n")
    with pytest.raises(SourceFormatError, match="line 1: no data rows after the header"):
        read_facelog(path)


# ----- what the review found: Max without cells, tracker time 0, coarse tracker time, FaceState.Time ----------


@pytest.mark.parametrize("after", ["confidence_label", "nothing"])
def test_max_in_header_without_a_value_in_the_rows(tmp_path, after):
    """Enum.GetNames writes `...,UpperLipRaiserR,Max` but the rows hold 63 values: Max is left out of the
    header (it used to make every row "64 fields, the header has 65" and the file refused)."""
    path = tmp_path / "max.csv"
    more = dict(confidence=True, label=True) if after == "confidence_label" else dict(confidence=False, label=False)
    truth = write_quest_log(path, version=1, max_column=True, max_cell=False, seconds=1.0, **more)
    header, row = path.read_text().splitlines()[:2]
    assert header.count(",") == row.count(",") + 1  # one name more than values
    if after == "nothing":
        assert header.endswith("UpperLipRaiserR,Max")
    log, rep = read_facelog_report(path)
    assert rep.malformed == 0 and len(log) == len(truth.times)
    np.testing.assert_array_equal(log.weights, truth.weights)
    np.testing.assert_allclose(log.times, truth.times, atol=1e-9)
    if truth.confidence is not None:
        np.testing.assert_allclose(log.confidence, truth.confidence, rtol=1e-6)
        assert rep.labels == ["Emotion"]
    assert "Max" in rep.columns_ignored
    assert any("Max (from Enum.GetNames, not expressions) has no value in the rows" in p for p in rep.problems)


def test_rows_short_by_more_than_the_enum_extras_are_still_malformed(tmp_path):
    path = tmp_path / "short.csv"
    write_quest_log(path, version=1, max_column=True, max_cell=False, confidence=False, seconds=0.5,
                    invalid_window=None)
    lines = path.read_text().splitlines()
    lines[1:] = [line.rsplit(",", 1)[0] for line in lines[1:]]  # one more value missing than Max
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SourceFormatError, match=r"fields, the header has .*rows malformed"):
        read_facelog(path)


def test_tracker_time_zero_rows_are_invalid(tmp_path):
    """No status column: rows before tracking starts (and while it is lost) carry Face_Time 0 and zeros. They
    are invalid rows, not a sample at t=0 (a 5000 s gap) nor a time going backwards mid-file."""
    path = tmp_path / "zero.csv"
    truth = write_quest_log(path, status=False, lead_s=0.5, invalid_window=(1.0, 1.25), seconds=2.0)
    lines = path.read_text().splitlines()
    assert lines[1].split(",")[1] == "0" and truth.invalid > 0
    log, rep = read_facelog_report(path)
    assert rep.time_source.startswith("tracker (Face_Time") and rep.invalid == truth.invalid
    assert len(log) == len(truth.times) and 1.9 < rep.duration_s == pytest.approx(truth.times[-1], abs=1e-9)
    np.testing.assert_allclose(log.times, truth.times, atol=1e-9)
    np.testing.assert_array_equal(log.weights, truth.weights)
    assert any(f"{truth.invalid} rows with Face_Time <= 0" in p for p in rep.problems)
    assert not any("step(s) over" in p for p in rep.problems)
    assert rep.duplicates == truth.rows - truth.invalid - rep.samples


def test_long_gap_in_the_time_is_kept_and_noted(tmp_path):
    path = tmp_path / "gap.csv"
    truth = write_quest_log(path, status=False, invalid_window=(1.0, 6.0), seconds=7.0)
    log, rep = read_facelog_report(path)
    np.testing.assert_allclose(log.times, truth.times, atol=1e-9)
    assert np.diff(log.times).max() == pytest.approx(5.0, abs=0.03)
    assert any("1 step(s) over 3 s" in p and "the replay waits through it" in p for p in rep.problems)
    assert "step(s) over 3 s" in rep.text()


def test_coarse_tracker_time_falls_back_to_weight_changes_on_the_clock(tmp_path):
    """A float Face_Time at a device uptime of ~1e5 s has 0.1 s steps (C# writes 7 digits): 40 samples at
    36 Hz share 12 tracker times. The samples are found by weight changes, timed by the Unity clock."""
    path = tmp_path / "coarse.csv"
    truth = write_quest_log(path, seconds=40 / 36, device_t0=123456.0, tracker_csharp=True, invalid_window=None)
    written = {line.split(",")[1] for line in path.read_text().splitlines()[1:]}
    assert len(truth.times) == 40 and len(written) == 12
    log, rep = read_facelog_report(path)
    assert len(log) == 40 and rep.time_source.startswith("unity clock (timeSinceStartup")
    np.testing.assert_array_equal(log.weights, truth.weights)
    np.testing.assert_allclose(log.times, truth.times, atol=2e-5)
    assert any("Face_Time is too coarse to tell samples apart" in p and "timed by the Unity clock" in p
               for p in rep.problems)
    nowhere = tmp_path / "coarse_no_clock.csv"
    write_quest_log(nowhere, seconds=40 / 36, device_t0=123456.0, tracker_csharp=True, invalid_window=None,
                    clock=None)
    with pytest.raises(SourceFormatError, match="too coarse to tell samples apart.*no Unity clock: give --fps"):
        read_facelog(nowhere)
    log, rep = read_facelog_report(nowhere, fps=83)
    assert len(log) == 40 and rep.time_source.startswith("--fps 83")
    fine = tmp_path / "fine.csv"  # the same C# floats at a small uptime have 1 ms steps: the tracker is used
    truth = write_quest_log(fine, seconds=1.0, tracker_csharp=True, invalid_window=None)
    log, rep = read_facelog_report(fine)
    assert rep.time_source.startswith("tracker") and len(log) == len(truth.times) == 37
    assert not any("coarse" in p for p in rep.problems)


def test_facestate_time_is_the_tracker_time(tmp_path):
    """`FaceState.Time` (OVRPlugin.FaceState's own field) is the tracker time, not a Unity clock `time`."""
    assert column_key("FaceState.Time") == "facestatetime" and column_key("FaceExpression.JawDrop") == "jawdrop"
    assert column_key("OVRFaceExpressions.FaceExpression.Brow_Lowerer_L") == "browlowererl"
    path = tmp_path / "facestate.csv"
    truth = write_quest_log(path, tracker_name="FaceState.Time", seconds=1.0)
    log, rep = read_facelog_report(path)
    assert rep.time_source.startswith("tracker (FaceState.Time") and "FaceState.Time" not in rep.columns_ignored
    np.testing.assert_allclose(log.times, truth.times, atol=1e-9)
    assert len(log) == len(truth.times)


def test_one_dispatcher_reports_every_format(tmp_path):
    """read_facelog is read_facelog_report's log; every format gets a LogReport."""
    quest = tmp_path / "v2.csv"
    write_quest_log(quest, seconds=0.5)
    own = tmp_path / "own.csv"
    write_facelog(own, FaceLog(times=np.arange(4) / 60, weights=np.zeros((4, 52)), layout=get_layout("arkit52")))
    for path, fmt in ((quest, "quest-v2"), (own, "facelog")):
        log, rep = read_facelog_report(path)
        assert isinstance(rep, LogReport) and rep.format == fmt and rep.samples == len(log)
        np.testing.assert_array_equal(read_facelog(path).weights, log.weights)
    with pytest.raises(SourceFormatError, match="layout 'ovr63'"):
        read_facelog_report(own, layout="ovr63")
