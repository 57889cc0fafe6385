"""Face-log readers and writers, Live Link packets and captures, VMC accumulation."""

import gzip
import struct
from pathlib import Path

import numpy as np
import pytest
from ofera.mapping.layouts import ARKIT51_NAMES, ARKIT52_NAMES, LIVELINK61_NAMES, get_layout, to_arkit51
from ofera.sources import (
    FaceLog,
    LiveLinkPacketError,
    SourceFormatError,
    VmcBlendshapeAccumulator,
    build_livelink_packet,
    parse_livelink_packet,
    parse_timecode,
    read_facelog,
    read_facelog_csv,
    read_gesichter,
    read_livelink_csv,
    write_facelog,
    write_gesichter,
)
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RNG = np.random.default_rng(11)


def write_text(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# ---------------------------------------------------------------- face-log CSV


def test_facelog_round_trip_with_confidence_and_data_source(tmp_path):
    t = 12.0 + np.arange(20) / 72.0
    log = FaceLog(
        times=t,
        weights=RNG.uniform(0, 1, (20, 70)),
        layout=get_layout("ovr70"),
        confidence=RNG.uniform(0, 1, (20, 2)),
        data_source=np.arange(20) % 2,
        source="Quest Pro recorder",
        metadata={"headset": "Quest Pro"},
    )
    path = tmp_path / "take.csv"
    write_facelog(path, log)
    text = path.read_text()
    assert text.startswith("# ofera facelog 1\n# layout: ovr70\n")
    assert "time,BROW_LOWERER_L," in text and ",confidence_lower,confidence_upper,data_source\n" in text
    back = read_facelog(path)
    assert back.layout.name == "ovr70" and back.source == "Quest Pro recorder"
    assert back.metadata["headset"] == "Quest Pro"
    np.testing.assert_allclose(back.times, t - 12.0, atol=2e-6)
    np.testing.assert_allclose(back.weights, log.weights, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(back.confidence, log.confidence, rtol=1e-5, atol=1e-6)
    assert np.array_equal(back.data_source, log.data_source) and back.data_source.dtype == np.uint8


def test_facelog_unity_names_shuffled_without_layout_comment(tmp_path):
    ovr = get_layout("ovr63")
    unity = [n.title().replace("_", "") for n in ovr.names]  # case and underscores differ
    order = RNG.permutation(63)
    w = RNG.uniform(0, 1, (3, 63)).round(4)
    lines = ["Time," + ",".join(unity[i] for i in order)]
    lines += [f"{0.1 * r:.3f}," + ",".join(str(w[r, i]) for i in order) for r in range(3)]
    log = read_facelog_csv(write_text(tmp_path / "unity.csv", lines))
    assert log.layout is ovr and log.confidence is None and log.data_source is None
    np.testing.assert_allclose(log.weights, w, atol=1e-6)
    np.testing.assert_allclose(log.times, [0.0, 0.1, 0.2])


def test_facelog_layout_comment_must_match_header(tmp_path):
    path = write_text(tmp_path / "x.csv", ["# layout: ovr63", "time," + ",".join(ARKIT52_NAMES), "0" + ",0" * 52])
    with pytest.raises(SourceFormatError, match=r"x\.csv, line 2: .*layout 'ovr63'.*unknown names: eyeBlinkLeft"):
        read_facelog(path)


def arkit_row(t: str, first: str) -> str:
    """A face-log row in arkit51 with eyeBlinkLeft = `first` and the other 50 shapes 0."""
    return f"{t},{first}" + ",0" * 50


ARKIT_HEADER = "time," + ",".join(ARKIT51_NAMES)


@pytest.mark.parametrize(
    ("rows", "match"),
    [
        (
            [arkit_row("0.0", "0.5"), arkit_row("0.1", "oops")],
            "line 4: column 'eyeBlinkLeft': 'oops' is not a",
        ),
        ([arkit_row("0.0", "0.5"), arkit_row("0.1", "nan")], "line 4: column 'eyeBlinkLeft': 'nan' is not a"),
        ([arkit_row("0.5", "0.5"), arkit_row("0.1", "0")], r"line 4: time goes backwards \(0.500000 s"),
        ([arkit_row("0.0", "0.5"), "0.1,0.2"], "line 4: expected 52 fields as in the header, got 2"),
    ],
)
def test_facelog_errors_name_file_line_and_problem(tmp_path, rows, match):
    path = write_text(tmp_path / "bad.csv", ["# layout: arkit51", ARKIT_HEADER, *rows])
    with pytest.raises(SourceFormatError, match=r"bad\.csv, " + match):
        read_facelog(path)


@pytest.mark.parametrize(
    ("header", "row", "match"),
    [
        ("t," + ",".join(ARKIT51_NAMES), arkit_row("0", "0"), "line 1: no time column"),
        (ARKIT_HEADER + ",confidence_lower", arkit_row("0", "0") + ",1", "'confidence_upper' is missing"),
        (ARKIT_HEADER + ",data_source", arkit_row("0", "0") + ",lidar", "line 2: data_source 'lidar' is not"),
        ("frame," + ",".join(ARKIT51_NAMES), arkit_row("0", "0"), "frame column needs a frame rate"),
    ],
)
def test_facelog_column_errors(tmp_path, header, row, match):
    with pytest.raises(SourceFormatError, match=match):
        read_facelog(write_text(tmp_path / "bad.csv", [header, row]))


def test_facelog_data_source_accepts_codes_and_empty_log(tmp_path):
    log = read_facelog(write_text(tmp_path / "a.csv", [ARKIT_HEADER + ",data_source", arkit_row("0", "0") + ",1"]))
    assert log.data_source.tolist() == [1]
    empty = read_facelog(write_text(tmp_path / "e.csv", [ARKIT_HEADER]))
    assert len(empty) == 0 and empty.weights.shape == (0, 51) and empty.duration == 0.0


def test_facelog_rejects_inconsistent_arrays():
    with pytest.raises(ValueError, match="do not fit"):
        FaceLog(np.zeros(3), np.zeros((3, 52)), get_layout("arkit51"))
    with pytest.raises(ValueError, match="non-decreasing"):
        FaceLog(np.array([0.0, 1.0, 0.5]), np.zeros((3, 51)), get_layout("arkit51"))


# ------------------------------------------------------------ MediaPipe / ARKit CSV


def test_mediapipe_csv_with_frame_column(tmp_path):
    mp = get_layout("mediapipe52")
    w = RNG.uniform(0, 1, (4, 52)).round(5)
    lines = ["frame," + ",".join(mp.names)] + [f"{10 + r}," + ",".join(map(str, w[r])) for r in range(4)]
    log = read_facelog(write_text(tmp_path / "mp.csv", lines), fps=30)
    assert log.layout is mp
    np.testing.assert_allclose(log.times, np.arange(4) / 30)
    np.testing.assert_allclose(log.to_arkit51()[:, ARKIT51_NAMES.index("browDownLeft")], w[:, 1], atol=1e-6)
    np.testing.assert_allclose(log.to_arkit51(), to_arkit51("mediapipe52", w), atol=1e-6)


def test_arkit_csv_with_timestamp_ms_and_fps_comment(tmp_path):
    names = sorted(ARKIT51_NAMES)  # MediaPipe order without `_neutral`
    lines = ["timestamp_ms," + ",".join(names), "1000" + ",0.25" * 51, "1033" + ",0.5" * 51]
    log = read_facelog(write_text(tmp_path / "ts.csv", lines))
    assert log.layout.name == "arkit51"
    np.testing.assert_allclose(log.times, [0.0, 0.033])
    assert np.all(log.weights[1] == 0.5)
    framed = ["# fps: 25", "frame," + ",".join(names), "0" + ",0" * 51, "5" + ",0" * 51]
    np.testing.assert_allclose(read_facelog(write_text(tmp_path / "f.csv", framed)).times, [0.0, 0.2])


# ---------------------------------------------------------------- Live Link CSV


def livelink_csv_header(count_column: str) -> list[str]:
    """Live Link Face's CSV column order: JawRight before JawLeft, MouthRight before MouthLeft."""
    names = list(LIVELINK61_NAMES)
    for a, b in (("JawLeft", "JawRight"), ("MouthLeft", "MouthRight")):
        i, j = names.index(a), names.index(b)
        names[i], names[j] = names[j], names[i]
    return ["Timecode", count_column, *names]


@pytest.mark.parametrize("count_column", ["BlendshapeCount", "BlendShapeCount"])
def test_livelink_csv_parses_by_name_across_midnight(tmp_path, count_column):
    header = livelink_csv_header(count_column)
    timecodes = ["23:59:59:58.500", "23:59:59:59.500", "00:00:00:00.500", "00:00:00:01.500"]
    values = RNG.uniform(0, 1, (4, 61)).round(5)
    lines = [",".join(header)] + [f"{tc},61," + ",".join(map(str, v)) for tc, v in zip(timecodes, values, strict=True)]
    log = read_livelink_csv(write_text(tmp_path / "llf.csv", lines))
    assert log.layout.name == "livelink61"
    np.testing.assert_allclose(log.times, np.arange(4) / 60, atol=1e-9)
    ll = get_layout("livelink61")
    file_columns = header[2:]
    for name in ("JawLeft", "JawRight", "MouthLeft", "MouthRight", "HeadYaw"):
        np.testing.assert_allclose(log.weights[:, ll.index(name)], values[:, file_columns.index(name)], atol=1e-6)
    assert read_facelog(tmp_path / "llf.csv").layout.name == "livelink61"


def test_livelink_csv_fps_and_backwards_time(tmp_path):
    header = ",".join(livelink_csv_header("BlendshapeCount"))
    zeros = ",61" + ",0" * 61
    log = read_facelog(write_text(tmp_path / "a.csv", [header, "10:00:00:00" + zeros, "10:00:00:15" + zeros]), fps=30)
    np.testing.assert_allclose(log.times, [0.0, 0.5])
    back = write_text(tmp_path / "b.csv", [header, "10:00:01:00.000" + zeros, "10:00:00:59.000" + zeros])
    with pytest.raises(SourceFormatError, match=r"b\.csv, line 3: time goes backwards"):
        read_livelink_csv(back)
    bad = write_text(tmp_path / "c.csv", [header, "10:00:01" + zeros])
    with pytest.raises(SourceFormatError, match=r"c\.csv, line 2: timecode '10:00:01' is not HH:MM:SS:FF.fff"):
        read_livelink_csv(bad)


def test_parse_timecode():
    assert parse_timecode("13:48:57:14.500") == pytest.approx(13 * 3600 + 48 * 60 + 57 + 14.5 / 60)
    assert parse_timecode("00:00:01:15", fps=30) == pytest.approx(1.5)
    with pytest.raises(ValueError, match="frame 61 is not below 60 fps"):
        parse_timecode("00:00:00:61")
    with pytest.raises(ValueError, match="out of range"):
        parse_timecode("25:00:00:00")


# ------------------------------------------------------------- Live Link packets


def test_packet_round_trip():
    values = RNG.uniform(-1, 1, 61).astype(np.float32)
    data = build_livelink_packet(values, device_id="dev-1", subject="Face", frame_number=1234, subframe=0.25)
    assert len(data) == 1 + 4 + 5 + 4 + 4 + 16 + 1 + 61 * 4
    packet = parse_livelink_packet(data)
    assert (packet.device_id, packet.subject, packet.frame_number, packet.fps_num, packet.fps_den) == (
        "dev-1",
        "Face",
        1234,
        60,
        1,
    )
    assert packet.subframe == 0.25 and packet.time == pytest.approx(1234.25 / 60)
    assert packet.values.dtype == np.float32 and np.array_equal(packet.values, values)


def test_malformed_packets_raise_clear_errors():
    good = build_livelink_packet(np.zeros(61), device_id="abc", subject="s")
    for n in range(len(good)):
        with pytest.raises(LiveLinkPacketError, match="truncated"):
            parse_livelink_packet(good[:n])
    assert issubclass(LiveLinkPacketError, ValueError)
    cases = {
        b"\x05" + good[1:]: "version 5 is not supported",
        good + b"\x00": "1 unexpected trailing bytes",
        good[:1] + struct.pack(">i", -1) + good[5:]: "device id length -1",
        good[:1] + struct.pack(">i", 1 << 30) + good[5:]: "device id length 1073741824",
        good[:5] + b"\xff" + good[6:]: "device id is not UTF-8",
        good[:21] + struct.pack(">i", 0) + good[25:]: "frame rate 0/1 is not positive",
        good[:29] + b"\x34" + good[30:]: "52 values, expected 61",
    }
    for data, match in cases.items():
        with pytest.raises(LiveLinkPacketError, match=match):
            parse_livelink_packet(data)


# ---------------------------------------------------------------- .gesichter


def test_gesichter_built_in_test(tmp_path):
    values = RNG.uniform(0, 1, (5, 61)).astype(np.float32)
    frames = [100, 101, 102, 104, 105]
    packets = [build_livelink_packet(v, frame_number=f, subframe=0.5) for v, f in zip(values, frames, strict=True)]
    body = struct.pack(">BI", 6, 5) + b"".join(struct.pack(">I", len(p)) + p for p in packets)
    path = tmp_path / "take.bin"  # detected by content, not extension
    path.write_bytes(gzip.compress(body))
    log = read_facelog(path)
    assert log.layout.name == "livelink61" and log.metadata["device_id"] == "OFERA-TEST-DEVICE"
    np.testing.assert_allclose(log.times, (np.array(frames) - 100) / 60)
    np.testing.assert_array_equal(log.weights, values)
    write_gesichter(tmp_path / "w.gesichter", packets)
    assert gzip.decompress((tmp_path / "w.gesichter").read_bytes()) == body


def test_gesichter_errors_name_file_and_frame(tmp_path):
    packet = build_livelink_packet(np.zeros(61))
    body = struct.pack(">BI", 6, 3) + (struct.pack(">I", len(packet)) + packet) * 2
    (tmp_path / "short.gesichter").write_bytes(gzip.compress(body))
    with pytest.raises(SourceFormatError, match=r"short\.gesichter, frame 2: truncated"):
        read_gesichter(tmp_path / "short.gesichter")
    broken = struct.pack(">BI", 6, 1) + struct.pack(">I", len(packet)) + b"\x07" + packet[1:]
    (tmp_path / "v.gesichter").write_bytes(gzip.compress(broken))
    with pytest.raises(SourceFormatError, match=r"v\.gesichter, frame 0: Live Link packet version 7"):
        read_gesichter(tmp_path / "v.gesichter")
    (tmp_path / "plain.gesichter").write_bytes(b"not gzip at all")
    with pytest.raises(SourceFormatError, match="not a gzip"):
        read_facelog(tmp_path / "plain.gesichter")
    write_gesichter(tmp_path / "one.gesichter", [packet])
    with pytest.raises(SourceFormatError, match="holds layout 'livelink61', not 'ovr63'"):
        read_facelog(tmp_path / "one.gesichter", layout="ovr63")


def test_real_livelink_capture():
    path = SHARED_DATA / "livelink_dao.gesichter"
    if not path.exists():
        pytest.skip(f"real capture not present at {path} (only in the project's shared data folder)")
    log = read_facelog(path)
    assert len(log) == 180 and log.layout.name == "livelink61"
    assert log.metadata["fps"] == "60/1" and log.metadata["device_id"] == "DEADC0DE-1337-1337-1337-CAFEBABE"
    assert log.times[0] == 0.0 and np.all(np.diff(log.times) > 0)
    np.testing.assert_allclose(log.weights[0, :8], [0.0, 0.164, 0.104, 0.0, 0.0, 0.044, 0.028, 0.0], atol=1e-3)
    a = log.to_arkit51()
    peak = {n: a[:, [ARKIT51_NAMES.index(n + s) for s in ("Left", "Right")]].max() for n in ("eyeBlink", "mouthSmile")}
    assert peak["eyeBlink"] == pytest.approx(0.94, abs=0.03)
    assert peak["mouthSmile"] == pytest.approx(0.92, abs=0.03)
    assert a[:, ARKIT51_NAMES.index("jawOpen")].max() == pytest.approx(0.78, abs=0.03)


# -------------------------------------------------------------------------- VMC


def test_vmc_accumulator():
    acc = VmcBlendshapeAccumulator()
    assert acc.feed("/VMC/Ext/Blend/Val", ["EyeBlinkLeft", 0.5]) is None
    acc.feed("/VMC/Ext/Blend/Val", ["jawopen", 0.75])
    acc.feed("/VMC/Ext/Blend/Val", ["Joy", 1.0])
    acc.feed("/VMC/Ext/Blend/Val", ["mouthSmileLeft"])
    acc.feed("/VMC/Ext/Bone/Pos", ["Head", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    frame = acc.feed("/VMC/Ext/Blend/Apply", [])
    assert frame.shape == (52,) and frame.dtype == np.float32
    assert frame[ARKIT52_NAMES.index("eyeBlinkLeft")] == 0.5 and frame[ARKIT52_NAMES.index("jawOpen")] == 0.75
    assert np.count_nonzero(frame) == 2
    assert (acc.unknown_count, acc.unknown_names, acc.malformed_count) == (1, {"Joy"}, 1)
    frame[0] = 0.0  # a copy: the accumulator keeps its values
    assert acc.feed("/VMC/Ext/Blend/Apply", [])[0] == 0.5


def test_vmc_datagram_bundle():
    bundle = OscBundleBuilder(IMMEDIATELY)
    for name, value in (("TongueOut", 0.25), ("BrowInnerUp", 1.0)):
        msg = OscMessageBuilder("/VMC/Ext/Blend/Val")
        msg.add_arg(name)
        msg.add_arg(value)
        bundle.add_content(msg.build())
    bundle.add_content(OscMessageBuilder("/VMC/Ext/Blend/Apply").build())
    acc = VmcBlendshapeAccumulator()
    (frame,) = acc.feed_datagram(bundle.build().dgram)
    assert frame[51] == 0.25 and frame[ARKIT52_NAMES.index("browInnerUp")] == 1.0
    assert acc.feed_datagram(b"garbage!") == [] and acc.malformed_count == 1
