"""ofera.client.frame_scan against the codec's unpack_message (msgpack): the same map for what it takes (bins as
views of the message, no copy), None for everything the codec refuses or it does not take."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ofera.client.frame_scan import BINS, DELTA_FIELDS, MEMBER, SEQ, N, T, scan_delta_frame, scan_frame
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


I64 = st.integers(-(2**63), 2**63 - 1)
DELTA_MAPS = st.fixed_dictionaries(
    {"type": st.just("frame"), "seq": I64, "t": I64, "key": st.just(False), "n": I64,
     "timing": st.dictionaries(st.text(max_size=31).filter(lambda k: len(k.encode()) <= 31), st.integers(0, 2**63 - 1),
                               max_size=15),
     **{k: st.binary(max_size=70_000 if k == "rotation" else 300) for k in DELTA_FIELDS[BINS:]}},
    optional={"member": st.text(max_size=40)})


def scanned(data: bytes) -> tuple[int, np.ndarray, np.ndarray]:
    fields, timing = np.zeros((len(DELTA_FIELDS), 2), np.int64), np.zeros((15, 3), np.int64)
    return scan_delta_frame(np.frombuffer(data, np.uint8), fields, timing), fields, timing


def as_map(data: bytes, stages: int, fields: np.ndarray, timing: np.ndarray) -> dict:
    """What scan_delta_frame found, as the map msgpack gives."""
    m = {"type": "frame", "key": False, **{k: int(fields[r, 0]) for k, r in (("seq", SEQ), ("t", T), ("n", N))}}
    m["timing"] = {data[a:a + k].decode(): v for a, k, v in timing[:stages].tolist()}
    rows = [(k, r) for r, k in enumerate(DELTA_FIELDS) if r >= BINS or (r == MEMBER and fields[MEMBER, 0] >= 0)]
    for k, r in rows:
        a, n = fields[r]
        m[k] = data[a:a + n].decode() if r == MEMBER else data[a:a + n]
    return m


@settings(max_examples=200, deadline=None)
@given(DELTA_MAPS, st.randoms(use_true_random=False))
def test_delta_frames_scan_to_msgpacks_map(m: dict, rnd) -> None:
    """scan_delta_frame reads every delta frame map (its fields in any order, integers of every msgpack width, bins of
    every length class, with or without member) as msgpack does."""
    keys = list(m)
    rnd.shuffle(keys)
    data = msgpack.packb({k: m[k] for k in keys}, use_bin_type=True)
    stages, fields, timing = scanned(data)
    assert stages == len(m["timing"]) and as_map(data, stages, fields, timing) == unpack_message(data, len(data))


@settings(max_examples=300, deadline=None)
@given(DELTA_MAPS, st.data())
def test_damaged_delta_frames_scan_to_nothing_or_msgpacks_map(m: dict, data: st.DataObject) -> None:
    """A delta frame cut short, grown, with a byte changed, a field left out or one added: -1 wherever msgpack or the
    plain delta frame's shape says no (but for strings that are not UTF-8: their decoding, the caller's, refuses
    them); else msgpack's map."""
    how = data.draw(st.sampled_from(["cut", "grow", "flip", "drop", "add"]))
    if how == "drop":
        m.pop(data.draw(st.sampled_from(sorted(m))))
    elif how == "add":
        m[data.draw(st.sampled_from(["index", "key", "x"]))] = data.draw(st.one_of(st.booleans(), st.integers(0, 9)))
    raw = bytearray(msgpack.packb(m, use_bin_type=True))
    if how == "cut":
        raw = raw[:data.draw(st.integers(0, len(raw) - 1))]
    elif how == "grow":
        raw += data.draw(st.binary(min_size=1, max_size=4))
    elif how == "flip":
        raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    raw = bytes(raw)
    stages, fields, timing = scanned(raw)
    try:
        want = unpack_message(raw, MAX_SERVER_MESSAGE)
    except ProtocolError:
        if stages >= 0:  # only its strings' UTF-8 is left to the caller (FastFrameDecoder decodes them)
            with pytest.raises(UnicodeDecodeError):
                as_map(raw, stages, fields, timing)
        return
    plain_delta = (set(want) - {"member"} == set(DELTA_FIELDS) - {"member"} and want["type"] == "frame"
                   and want["key"] is False and all(type(want[k]) is int for k in ("seq", "t", "n")))
    if stages >= 0:
        assert plain_delta and as_map(raw, stages, fields, timing) == want


def test_delta_frames_take_the_one_call_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every delta frame of a stream reaches FastFrameDecoder's kernel with neither msgpack nor the Python scanner;
    key frames, and anything the kernel scan does not take, are read as before."""
    import ofera.client.fast_decode as fd
    from ofera.streaming.encode_fast import delta_encoder

    rng = np.random.default_rng(4)
    n = 400
    pos, scale = rng.normal(0, 0.1, (n, 3)).astype(np.float32), np.full((n, 3), 1e-3, np.float32)
    rot = np.tile(np.float32([0, 0, 0, 1]), (n, 1))
    fmt = FrameFormat("q13", n, False, make_quant(pos, scale), delta=True)
    enc = delta_encoder(fmt, "unity", None, np.arange(n), key_interval=4)
    calls = []
    monkeypatch.setattr(fd, "scan_frame", lambda *a: calls.append(1) or scan_frame(*a))
    dec = fd.FastFrameDecoder(fmt)
    for f in range(8):
        pos = pos + rng.normal(0, 1e-3, pos.shape).astype(np.float32)
        got = dec.decode(bytes(enc.encode(f, 7, {"total": 5, "head": 2}, pos, rot, scale)))
        assert got.key is (f % 4 == 0) and len(calls) == 1 + f // 4
        assert got.timing == {"total": 5, "head": 2}
