"""ofera.client.frame_scan against the codec's unpack_message (msgpack): the same map for what it takes (bins as
views of the message, no copy), None for everything the codec refuses or it does not take."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ofera.client.frame_scan import scan_frame
from ofera_protocol import FrameFormat, ProtocolError, make_quant
from ofera_protocol.codec import unpack_message
from ofera_protocol.constants import MAX_CONTAINER_LEN, MAX_SERVER_MESSAGE, MAX_STR_LEN

INTS = st.one_of(st.integers(-(2**63), 2**64 - 1), st.integers(-40, 300))
SCALARS = st.one_of(INTS, st.booleans(), st.none(), st.text(max_size=40), st.binary(max_size=300))
KEYS = st.text(min_size=1, max_size=40)
MAPS = st.dictionaries(KEYS, st.one_of(SCALARS, st.dictionaries(KEYS, SCALARS, max_size=5)), max_size=20)


def plain(m: dict) -> dict:
    """A scanned map with its memoryviews as bytes (what msgpack gives)."""
    return {k: plain(v) if isinstance(v, dict) else bytes(v) if isinstance(v, memoryview) else v for k, v in m.items()}


@settings(max_examples=300, deadline=None)
@given(MAPS)
def test_scanned_maps_are_msgpacks(m: dict) -> None:
    """Any map of the kinds frames hold (every msgpack width of ints, strings and bins; a nested map) scans to what
    the codec unpacks; its bins are read-only views of the message itself."""
    data = msgpack.packb(m, use_bin_type=True)
    got = scan_frame(data, MAX_SERVER_MESSAGE)
    assert got is not None and plain(got) == unpack_message(data, MAX_SERVER_MESSAGE)
    for v in got.values():
        if isinstance(v, memoryview):
            assert v.readonly and (v.obj is data or v.nbytes == 0 or np.shares_memory(np.frombuffer(v, np.uint8),
                                                                                       np.frombuffer(data, np.uint8)))


@settings(max_examples=300, deadline=None)
@given(MAPS, st.data())
def test_damaged_messages_scan_to_none_or_to_msgpacks_map(m: dict, data: st.DataObject) -> None:
    """A message cut short, grown, or with a byte changed: where the codec refuses it the scanner answers None (the
    codec's error then names the fault); where the codec takes it, the scanner gives its map or None."""
    raw = bytearray(msgpack.packb(m, use_bin_type=True))
    how = data.draw(st.sampled_from(["cut", "grow", "flip"]))
    if how == "cut":
        raw = raw[:data.draw(st.integers(0, len(raw) - 1))]
    elif how == "grow":
        raw += data.draw(st.binary(min_size=1, max_size=4))
    else:
        raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    got = scan_frame(bytes(raw), MAX_SERVER_MESSAGE)
    try:
        want = unpack_message(bytes(raw), MAX_SERVER_MESSAGE)
    except ProtocolError:
        assert got is None
        return
    assert got is None or plain(got) == want


@pytest.mark.parametrize("obj", [
    [1, 2], {"a": 1.5}, {"a": [1]}, {"a": {"b": {"c": 1}}}, {1: 2}, {"a": msgpack.ExtType(1, b"x")},
    {"a": "x" * (MAX_STR_LEN + 1)}, {str(i): i for i in range(MAX_CONTAINER_LEN + 1)}, {"k" * 40: 1},
])
def test_what_frames_never_hold_is_left_to_the_codec(obj) -> None:
    """Arrays, floats, ext types, maps nested two deep, non-string keys, strings and maps past the codec's limits:
    None (the codec unpacks or refuses them itself)."""
    data = msgpack.packb(obj, use_bin_type=True)
    got = scan_frame(data, MAX_SERVER_MESSAGE)
    assert got is None or (isinstance(obj, dict) and plain(got) == unpack_message(data, MAX_SERVER_MESSAGE))
    assert scan_frame(b"", MAX_SERVER_MESSAGE) is None and scan_frame(b"\x80", 0) is None


def test_the_fast_decoder_never_copies_a_dense_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """A dense f16 frame reaches FastFrameDecoder's kernels without msgpack (whose unpacking copies every bin), and
    decodes to the codec's values; a message the scanner leaves alone still decodes through the codec."""
    import ofera.client.fast_decode as fd
    from ofera.streaming.encode_fast import frame_writer
    from ofera_protocol import decode_server_message

    rng = np.random.default_rng(3)
    n = 500
    pos, scale = rng.normal(0, 0.1, (n, 3)).astype(np.float32), np.full((n, 3), 1e-3, np.float32)
    rot = np.tile(np.float32([0, 0, 0, 1]), (n, 1))
    calls = []
    monkeypatch.setattr(fd, "unpack_message", lambda *a: calls.append(1) or unpack_message(*a))
    for enc in ("f16", "q13"):
        fmt = FrameFormat(enc, n, False, make_quant(pos, scale) if enc == "q13" else None)
        data = bytes(frame_writer(fmt).encode(3, 4, {"total": 9}, pos, rot, scale))
        want = decode_server_message(data, fmt)
        got = fd.FastFrameDecoder(fmt).decode(data)
        assert not calls
        for name in ("position", "rotation", "scale"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    stats = msgpack.packb({"type": "stats", "x": [1.5]}, use_bin_type=True)  # an array: the codec's
    with pytest.raises(ProtocolError):
        fd.FastFrameDecoder(fmt).decode(stats)
    assert calls
