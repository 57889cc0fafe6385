"""`bs.conf` (PROTOCOL.md 4.2): the codec's checks, the region hold of streaming.confidence, the pipeline
holding a low-confidence region, and a live server answering a bad `conf` with a non-fatal error."""

from __future__ import annotations

import asyncio

import msgpack
import numpy as np
import pytest
from ofera.mapping.layouts import ARKIT51_NAMES, OVR63_NAMES, to_arkit51
from ofera.streaming.confidence import BOTH_REGIONS, LOWER_FACE, UPPER_FACE, RegionHold
from ofera_protocol import (
    AvatarInfo,
    Blendshapes,
    ClientConnection,
    ConnectionUsageError,
    ProtocolError,
    ServerConnection,
    decode_client_message,
)
from ofera_protocol import encode as encode_msg

W63 = np.linspace(0, 1, 63, dtype=np.float32)


def raw_bs(conf: object, n: int = 63) -> bytes:
    m = {"type": "bs", "seq": 3, "t": 7, "w": np.full(n, 0.25, "<f4").tobytes()}
    if conf is not None:
        m["conf"] = conf
    return msgpack.packb(m, use_bin_type=True)


# ----------------------------------------------------------------------------- codec


def test_conf_round_trip_and_absent():
    m = Blendshapes(seq=1, t=2, w=W63, conf=np.array([0.75, 0.25], np.float32))
    back = decode_client_message(encode_msg(m), "ovr63")
    assert back == m and back.conf.dtype == np.float32
    plain = decode_client_message(encode_msg(Blendshapes(seq=1, t=2, w=W63)), "ovr63")
    assert plain.conf is None and b"conf" not in encode_msg(Blendshapes(seq=1, t=2, w=W63))
    nil = decode_client_message(msgpack.packb({"type": "bs", "seq": 1, "t": 0, "w": W63.tobytes(), "conf": None}),
                                "ovr63")
    assert nil.conf is None  # nil is absent


@pytest.mark.parametrize(("conf", "code", "text"), [
    (np.array([1.5, 0.5], "<f4").tobytes(), "bad_field", r"'conf' = \[1.5, 0.5\].*outside \[0, 1\]"),
    (np.array([-0.1, 0.5], "<f4").tobytes(), "bad_field", "outside"),
    (np.array([0.5], "<f4").tobytes(), "bad_length", "'conf' has 4 bytes, expected 8"),
    (np.array([np.nan, 0.5], "<f4").tobytes(), "non_finite", "'conf' holds NaN"),
    (0.5, "bad_field", "'conf' must be bin"),
])
def test_bad_conf_is_a_clear_non_fatal_error_after_hello(conf, code, text):
    with pytest.raises(ProtocolError, match=text) as info:
        decode_client_message(raw_bs(conf), "ovr63")
    assert info.value.code == code


def test_client_connection_refuses_bad_conf_before_sending():
    srv, conn = ServerConnection(), ClientConnection()
    srv.receive(conn.hello("ovr63"))
    conn.receive(srv.accept("s", AvatarInfo("a", 1, 0)))
    good = srv.receive(conn.bs(1, 0, W63, conf=[0.5, 1.0]))
    np.testing.assert_array_equal(good.conf, [0.5, 1.0])
    with pytest.raises(ConnectionUsageError, match=r"conf must be 2 values \[lower, upper\] in \[0, 1\]"):
        conn.bs(1, 0, W63, conf=[0.5, 2.0])


# ----------------------------------------------------------------------------- regions


def test_regions_follow_meta_upper_lower_definition():
    names = np.array(ARKIT51_NAMES)
    assert UPPER_FACE.sum() == 19 and LOWER_FACE.sum() == 27 and BOTH_REGIONS.sum() == 5
    assert not (UPPER_FACE & LOWER_FACE).any() and (UPPER_FACE | LOWER_FACE | BOTH_REGIONS).all()
    assert set(names[BOTH_REGIONS]) == {"cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft",
                                        "noseSneerRight"}
    assert {"eyeBlinkLeft", "browInnerUp"} <= set(names[UPPER_FACE])
    assert {"jawOpen", "mouthSmileLeft", "mouthClose"} <= set(names[LOWER_FACE])


def test_region_hold():
    hold = RegionHold(0.5)
    good = np.linspace(0.1, 0.6, 51).astype(np.float32)
    assert np.array_equal(hold(good.copy(), np.array([0.9, 0.9])), good)
    garbage = np.full(51, 0.95, np.float32)
    out = hold(garbage.copy(), np.array([0.2, 0.9]))  # lower face unsure: mouth, jaw, cheeks, nose held
    np.testing.assert_array_equal(out[LOWER_FACE | BOTH_REGIONS], good[LOWER_FACE | BOTH_REGIONS])
    np.testing.assert_array_equal(out[UPPER_FACE], garbage[UPPER_FACE])
    out = hold(np.zeros(51, np.float32), np.array([0.9, 0.1]))  # now the upper face is unsure
    np.testing.assert_array_equal(out[UPPER_FACE | BOTH_REGIONS], np.where(UPPER_FACE, 0.95, good)[UPPER_FACE
                                                                                                 | BOTH_REGIONS])
    np.testing.assert_array_equal(out[LOWER_FACE], 0)
    assert hold.held == 2
    assert np.array_equal(hold(garbage.copy(), None), garbage)  # no conf: full confidence
    off = RegionHold(0.0)
    assert np.array_equal(off(garbage.copy(), np.zeros(2)), garbage)
    fresh = RegionHold(0.5)
    assert not fresh(garbage.copy(), np.array([0.1, 1.0]))[LOWER_FACE].any()  # neutral before a confident one
    with pytest.raises(ValueError, match="threshold"):
        RegionHold(1.5)


@pytest.mark.parametrize("threshold", [0.5, 0.7, 0.3])
def test_conf_at_the_threshold_passes_through(threshold):
    """"Below the threshold" holds, "at or above" passes, with conf as the wire carries it (float32: 0.7
    arrives as 0.69999999, which a float64 comparison would call below 0.7)."""
    hold = RegionHold(threshold)
    hold(np.zeros(51, np.float32), np.array([1.0, 1.0], np.float32))
    x = np.full(51, 0.8, np.float32)
    at = np.array([threshold, threshold], np.float32)
    np.testing.assert_array_equal(hold(x.copy(), at), x)
    assert hold.held == 0
    below = np.nextafter(at, np.float32(0))  # the float32 just below: held, at the values passed above
    np.testing.assert_array_equal(hold(np.full(51, 0.2, np.float32), below), x)
    assert hold.held == 1


def test_pipeline_holds_a_low_confidence_region(tmp_path):
    from ofera.streaming.config import Settings
    from ofera.streaming.registry import registry_for
    from replay_support import small_avatar_dir

    reg = registry_for(Settings(avatars=small_avatar_dir(tmp_path, 500), default_avatar="small", warmup=False))
    assets = reg.get("small")
    pipe = assets.pipeline("ovr63")
    calm = np.zeros(63, np.float32)
    jaw = calm.copy()
    jaw[OVR63_NAMES.index("JAW_DROP")] = 0.9
    assert to_arkit51("ovr63", jaw)[ARKIT51_NAMES.index("jawOpen")] == pytest.approx(0.9)
    a = pipe.run(calm, np.array([1.0, 1.0], np.float32))[0].position.copy()
    b = pipe.run(jaw, np.array([0.1, 1.0], np.float32))[0].position.copy()  # lower face unsure: jaw held shut
    np.testing.assert_array_equal(a, b)
    c = pipe.run(jaw, np.array([0.9, 1.0], np.float32))[0].position.copy()
    assert np.abs(c - a).max() > 1e-4
    d = pipe.run(jaw, None)[0].position.copy()  # without conf: as the tracker says
    np.testing.assert_array_equal(c, d)
    off = assets.pipeline("ovr63", confidence_threshold=0.0)
    off.run(calm)
    np.testing.assert_array_equal(off.run(jaw, np.array([0.0, 0.0], np.float32))[0].position, c)


# ----------------------------------------------------------------------------- live server


def test_server_answers_bad_conf_with_a_non_fatal_error(tmp_path):
    from ofera.client import connect
    from ofera_protocol import ErrorMessage, Frame
    from replay_support import small_server

    async def session(url: str) -> tuple[ErrorMessage, Frame]:
        client = await connect(url, layout="ovr63")
        try:
            await client.send_raw(raw_bs(np.array([2.0, 0.5], "<f4").tobytes()))
            err = await client.recv(timeout=30)
            await client.send_bs(W63, seq=4, conf=np.array([0.9, 0.2], np.float32))
            frame = await client.recv(timeout=30)
            return err, frame
        finally:
            await client.close()

    with small_server(tmp_path, 500) as server:
        err, frame = asyncio.run(session(server.url))
    assert isinstance(err, ErrorMessage) and err.code == "bad_field" and not err.fatal and err.seq is None
    assert "conf" in err.message and "[0, 1]" in err.message
    assert isinstance(frame, Frame) and frame.seq == 4


def _metric(http_url: str, name: str) -> float:
    import urllib.request

    text = urllib.request.urlopen(f"{http_url}/metrics", timeout=30).read().decode()
    return sum(float(line.split()[-1]) for line in text.splitlines() if line.startswith(name + " "))


def test_live_session_holds_a_low_confidence_region(tmp_path):
    """Through a live server (threshold 0.7): a neutral confident frame, then a jaw-open frame whose lower-face
    confidence is 0.1 comes back with the neutral frame's positions (the jaw held shut); the same jaw at
    exactly the threshold passes through ("at or above"). Counted in ofera_bs_conf_total and
    ofera_bs_conf_held_total."""
    from ofera.client import connect
    from ofera_protocol import Frame
    from replay_support import small_server

    calm = np.zeros(63, np.float32)
    jaw = calm.copy()
    jaw[OVR63_NAMES.index("JAW_DROP")] = 0.9

    async def session(url: str) -> list[Frame]:
        client = await connect(url, layout="ovr63")
        frames = []
        try:
            for seq, (w, conf) in enumerate([(calm, [1.0, 1.0]), (jaw, [0.1, 1.0]), (jaw, [0.7, 1.0]),
                                             (calm, None)]):
                await client.send_bs(w, seq=seq, conf=None if conf is None else np.array(conf, np.float32))
                frame = await client.recv_frame(timeout=60)  # one at a time: newest-wins never skips one
                assert frame.seq == seq and not client.errors, client.errors
                frames.append(frame)
        finally:
            await client.close()
        return frames

    with small_server(tmp_path, 500, confidence_threshold=0.7) as server:
        before = _metric(server.http_url, "ofera_bs_conf_total"), _metric(server.http_url, "ofera_bs_conf_held_total")
        neutral, held, at, plain = asyncio.run(session(server.url))
        after = _metric(server.http_url, "ofera_bs_conf_total"), _metric(server.http_url, "ofera_bs_conf_held_total")
    np.testing.assert_array_equal(held.position, neutral.position)  # low lower-face confidence: jaw held shut
    assert np.abs(at.position - neutral.position).max() > 1e-4  # conf == threshold: the jaw opens
    np.testing.assert_array_equal(plain.position, neutral.position)  # no conf: as sent (calm again)
    assert after[0] - before[0] == 3 and after[1] - before[1] == 1
