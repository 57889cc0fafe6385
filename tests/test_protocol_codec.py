"""Codec of protocol v1: round trips of every message, strict validation with exact error codes, fuzz."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "protocol"))

from ofera_protocol import (  # noqa: E402
    COORDS,
    ENCODINGS,
    LAYOUTS,
    MAX_CLIENT_MESSAGE,
    AvatarChunk,
    AvatarInfo,
    Blendshapes,
    Bye,
    ErrorMessage,
    Frame,
    FrameFormat,
    FrameHeader,
    Hello,
    Ping,
    Pong,
    ProtocolError,
    Quant,
    Welcome,
    decode_client_message,
    decode_server_message,
    encode,
    read_frame_header,
)
from ofera_protocol.codec import MessagePacker, pack_map  # noqa: E402
from ofera_protocol.errors import ERRORS, Fatality, close_code  # noqa: E402
from ofera_protocol.messages import ParamsFormat, ParamsFrame  # noqa: E402

FAST = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])

QUANT = Quant(pos_min=np.array([-0.2, -0.2, -0.2], np.float32), pos_max=np.array([0.2, 0.3, 0.25], np.float32),
              log_scale=np.array([-10.0, -1.0], np.float32))

int64s = st.integers(-(2**63), 2**63 - 1)
seqs = st.integers(0, 2**63 - 1)
ids = st.text(st.characters(codec="utf-8", exclude_categories=["Cs"]), min_size=1, max_size=30)
f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)


def raises(code: str, fn, *args, **kw) -> ProtocolError:
    with pytest.raises(ProtocolError) as ei:
        fn(*args, **kw)
    assert ei.value.code == code, ei.value
    return ei.value


def client(d: dict, layout: str | None = None) -> object:
    return decode_client_message(msgpack.packb(d), layout)


def server(d: dict, fmt: FrameFormat | None = None) -> object:
    return decode_server_message(msgpack.packb(d), fmt)


# ============================================================================= round trips


@st.composite
def hellos(draw: st.DrawFn) -> Hello:
    return Hello(layout=draw(st.sampled_from(sorted(LAYOUTS))), avatar=draw(ids),
                 encoding=draw(st.sampled_from(ENCODINGS)), coords=draw(st.sampled_from(COORDS)),
                 sparse=draw(st.booleans()), device=draw(st.none() | ids),
                 token=draw(st.none() | st.text(min_size=1, max_size=60)),
                 max_gaussians=draw(st.none() | st.integers(1, 2**32 - 1)))


@FAST
@given(hellos())
def test_hello_round_trip(h: Hello) -> None:
    assert decode_client_message(encode(h)) == h


@FAST
@given(st.sampled_from(sorted(LAYOUTS)), seqs, int64s, st.data())
def test_bs_round_trip(layout: str, seq: int, t: int, data: st.DataObject) -> None:
    w = data.draw(hnp.arrays(np.float32, LAYOUTS[layout], elements=f32))
    m = Blendshapes(seq=seq, t=t, w=w)
    assert decode_client_message(encode(m), layout) == m
    assert decode_client_message(encode(m)) == m  # without a layout: any known length


@FAST
@given(int64s)
def test_ping_pong_bye_round_trip(t: int) -> None:
    assert decode_client_message(encode(Ping(t))) == Ping(t)
    assert decode_server_message(encode(Pong(t))) == Pong(t)
    assert decode_client_message(encode(Bye())) == Bye()


@FAST
@given(ids, ids, st.integers(0, 2**32 - 1), st.integers(0, 3), st.sampled_from(sorted(LAYOUTS)),
       st.sampled_from(ENCODINGS), st.sampled_from(COORDS), st.booleans(), st.none() | ids)
def test_welcome_round_trip(session, avatar_id, count, deg, layout, encoding, coords, sparse, srv) -> None:
    m = Welcome(session=session, avatar=AvatarInfo(avatar_id, count, deg), layout=layout, encoding=encoding,
                coords=coords, sparse=sparse, quant=QUANT if encoding == "q13" else None, server=srv)
    assert decode_server_message(encode(m)) == m


@FAST
@given(st.text(max_size=40), st.text(max_size=200), st.booleans(), st.none() | seqs)
def test_error_round_trip(code: str, message: str, fatal: bool, seq: int | None) -> None:
    m = ErrorMessage(code=code or "x", message=message, fatal=fatal, seq=seq)
    assert decode_server_message(encode(m)) == m


@st.composite
def avatar_chunks(draw: st.DrawFn) -> AvatarChunk:
    deg = draw(st.integers(0, 3))
    n = draw(st.integers(0, 6))
    offset = draw(st.integers(0, 5))
    count = offset + n + draw(st.integers(0, 5))
    chunks = draw(st.integers(1, 4))

    def arr(*shape: int) -> np.ndarray:
        return draw(hnp.arrays(np.float32, shape, elements=f32))

    return AvatarChunk(count=count, sh_degree=deg, chunk=draw(st.integers(0, chunks - 1)), chunks=chunks,
                       offset=offset,
                       opacity=draw(hnp.arrays(np.float32, n, elements=st.floats(0, 1, width=32))),
                       sh=arr(n, (deg + 1) ** 2, 3), position=arr(n, 3), rotation=arr(n, 4), scale=arr(n, 3))


@FAST
@given(avatar_chunks())
def test_avatar_chunk_round_trip(m: AvatarChunk) -> None:
    assert decode_server_message(encode(m)) == m


@FAST
@given(st.integers(0, 8), st.booleans(), seqs, int64s,
       st.dictionaries(st.text(min_size=1, max_size=10), st.integers(0, 2**63 - 1), max_size=8), st.data())
def test_frame_f32_round_trip_exact(count, sparse, seq, t, timing, data) -> None:
    fmt = FrameFormat("f32", count, sparse=sparse)
    index = None
    n = count
    if sparse and data.draw(st.booleans()):
        index = np.array(sorted(data.draw(st.sets(st.integers(0, max(count - 1, 0)), max_size=count))),
                         dtype=np.uint32) if count else np.zeros(0, np.uint32)
        n = len(index)
    m = Frame(seq=seq, t=t, timing=timing, index=index,
              position=data.draw(hnp.arrays(np.float32, (n, 3), elements=f32)),
              rotation=data.draw(hnp.arrays(np.float32, (n, 4), elements=f32)),
              scale=data.draw(hnp.arrays(np.float32, (n, 3), elements=f32)))
    assert decode_server_message(encode(m, fmt), fmt) == m


def test_frame_lossy_encodings_round_trip_shapes() -> None:
    rng = np.random.default_rng(3)
    n = 50
    pos = rng.uniform(-0.1, 0.1, (n, 3)).astype(np.float32)
    rot = rng.normal(size=(n, 4)).astype(np.float32)
    rot /= np.linalg.norm(rot, axis=1, keepdims=True)
    scale = np.exp(rng.uniform(-8, -3, (n, 3))).astype(np.float32)
    for enc in ENCODINGS:
        fmt = FrameFormat(enc, n, quant=QUANT)
        out = decode_server_message(encode(Frame(1, 2, pos, rot, scale), fmt), fmt)
        assert out.position.dtype == np.float32 and out.position.shape == (n, 3)
        assert out.rotation.shape == (n, 4) and out.scale.shape == (n, 3)
        np.testing.assert_allclose(out.position, pos, atol=1e-3)
        np.testing.assert_allclose(np.abs((out.rotation * rot).sum(1)), 1, atol=1e-3)
        np.testing.assert_allclose(out.scale, scale, rtol=0.02)


def test_frame_size_is_header_plus_payload() -> None:
    n = 1000
    z3, z4 = np.zeros((n, 3), np.float32), np.tile(np.float32([0, 0, 0, 1]), (n, 1))
    for enc, per in (("f32", 40), ("f16", 20), ("q13", 13)):
        fmt = FrameFormat(enc, n, quant=QUANT)
        size = len(encode(Frame(1, 2, z3, z4, z3 + 0.01), fmt))
        assert n * per < size < n * per + 100
        assert fmt.payload_bytes() == n * per and fmt.payload_bytes(10) == 10 * (per + 4)


def test_encoder_refuses_inconsistent_frames() -> None:
    z3, z4 = np.zeros((4, 3), np.float32), np.zeros((4, 4), np.float32)
    with pytest.raises(ValueError, match="dense frame"):
        encode(Frame(1, 2, z3, z4, z3), FrameFormat("f32", 5))
    with pytest.raises(ValueError, match="not sparse"):
        encode(Frame(1, 2, z3, z4, z3, index=np.arange(4, dtype=np.uint32)), FrameFormat("f32", 5))
    with pytest.raises(ValueError, match="ascending"):
        encode(Frame(1, 2, z3, z4, z3, index=np.array([0, 2, 1, 3], np.uint32)), FrameFormat("f32", 5, True))
    with pytest.raises(ValueError, match=r"\(n, 4\)"):
        encode(Frame(1, 2, z3, z4[:, :3], z3), FrameFormat("f32", 4))
    with pytest.raises(ValueError, match="FrameFormat"):
        encode(Frame(1, 2, z3, z4, z3))
    with pytest.raises(ValueError, match="NaN"):
        encode(Frame(1, 2, z3 + np.nan, z4, z3), FrameFormat("f16", 4))
    with pytest.raises(TypeError):
        encode("hello")  # type: ignore[arg-type]


def test_hello_defaults_and_unknown_keys_ignored() -> None:
    h = client({"type": "hello", "protocol": 1, "layout": "ovr70", "future_field": [1, 2], "device": None})
    assert h == Hello(layout="ovr70")
    assert h.avatar == "default" and h.encoding == "f32" and h.coords == "flame" and h.sparse is False


def test_keys_in_any_order() -> None:
    assert client({"t": 5, "type": "ping"}) == Ping(5)


# ============================================================================= error codes


def test_error_table_is_complete_and_consistent() -> None:
    expected = {"malformed", "unknown_type", "bad_field", "bad_length", "non_finite", "not_ready",
                "duplicate_hello", "unsupported_protocol", "unknown_layout", "unknown_avatar",
                "unknown_encoding", "unauthorized", "message_too_large", "rate_limited", "server_full",
                "text_frame", "internal", "room_full", "too_many_rooms"}
    assert set(ERRORS) == expected
    for spec in ERRORS.values():
        assert (spec.close_code is None) == (spec.fatality is Fatality.NEVER)
        assert ProtocolError(spec.code, "x").fatal == (spec.fatality is Fatality.ALWAYS)
    assert {ERRORS[c].close_code for c in ("unauthorized", "text_frame", "message_too_large")} == {1008, 1003, 1009}
    codes = [s.close_code for s in ERRORS.values() if s.close_code is not None]
    assert len(codes) == len(set(codes))
    assert close_code("some_future_code") == 4000


def test_protocol_md_error_table_matches_code() -> None:
    text = (Path(__file__).resolve().parents[1] / "protocol" / "PROTOCOL.md").read_text(encoding="utf-8")
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and cells[0].startswith("`") and cells[0].strip("`") in ERRORS:
            rows[cells[0].strip("`")] = (cells[1], cells[2])
    assert set(rows) == set(ERRORS)
    for code, (fatal, close) in rows.items():
        spec = ERRORS[code]
        assert fatal == spec.fatality.value
        assert close == ("-" if spec.close_code is None else str(spec.close_code))


@pytest.mark.parametrize("data", [
    b"", b"\xc1", b"\x93\x01\x02\x03", b"\xa4ping",  # not msgpack / not a map
    msgpack.packb({"type": "ping", "t": 1}) + b"\x00",  # trailing bytes
    msgpack.packb({"type": "ping", 1: 2}),  # non-string key
    msgpack.packb({b"type": "ping", "t": 1}, use_bin_type=True),  # bin key
    msgpack.packb({"type": "ping", "t": msgpack.ExtType(1, b"x")}),  # ext type
    msgpack.packb({"type": "ping", "t": 1, "x": {"a": {"b": {"c": {"d": 1}}}}}),  # depth 5
    msgpack.packb({"type": "ping", "t": 1, "x": [[[[1]]]]}),  # depth 5 via arrays
    msgpack.packb({"type": "ping", "t": 1, "x": list(range(300))}),  # too many entries
    msgpack.packb({"type": "ping", "t": 1, "x": "a" * 5000}),  # string too long
    b"\x82\xa4type\xa4ping\xa1t\xa3\xff\xfe\xfd",  # invalid UTF-8
    b"\x82\xa4type\xa2bs\xa1w\xc6\xff\xff\xff\xff",  # declares a 4 GiB bin
    b"\xdf\xff\xff\xff\xff",  # declares a map of 4 billion entries
    b"\x82\xa4type\xa4ping\xa1x" + b"\x91" * 5000 + b"\xc0",  # 5000 nested arrays
])
def test_malformed(data: bytes) -> None:
    raises("malformed", decode_client_message, data)


def test_depth_four_is_allowed() -> None:
    assert client({"type": "ping", "t": 1, "x": {"a": {"b": [1]}}}) == Ping(1)


def test_not_bytes_is_malformed() -> None:
    raises("malformed", decode_client_message, "not bytes")  # type: ignore[arg-type]


def test_message_too_large() -> None:
    big = pack_map({"type": "ping", "t": 1, "pad": np.zeros(MAX_CLIENT_MESSAGE, np.uint8)})
    e = raises("message_too_large", decode_client_message, big)
    assert e.fatal and e.close_code == 1009
    raises("message_too_large", decode_server_message, big, None, 1000)


def test_unknown_type() -> None:
    raises("unknown_type", client, {"type": "teleport"})
    raises("unknown_type", client, {"type": "frame"})  # a server message sent by a client
    raises("unknown_type", server, {"type": "bs"})
    raises("bad_field", client, {"t": 1})
    raises("bad_field", client, {"type": 7})


GOOD_BS = {"type": "bs", "seq": 1, "t": 2, "w": np.zeros(52, "<f4").tobytes()}


@pytest.mark.parametrize("change", [
    {"seq": -1}, {"seq": 1.0}, {"seq": True}, {"seq": "1"}, {"seq": None}, {"t": 2**63}, {"t": 1.5},
    {"w": [0.0] * 52}, {"w": "abc"},
])
def test_bs_bad_field(change: dict) -> None:
    raises("bad_field", client, GOOD_BS | change, "arkit52")


def test_bs_lengths_and_values() -> None:
    raises("bad_length", client, GOOD_BS | {"w": np.zeros(51, "<f4").tobytes()}, "arkit52")
    raises("bad_length", client, GOOD_BS | {"w": b"\x00" * 207}, "arkit52")
    raises("bad_length", client, GOOD_BS | {"w": b"\x00" * 207})
    raises("bad_length", client, GOOD_BS | {"w": b""})
    raises("bad_length", client, GOOD_BS | {"w": np.zeros(10, "<f4").tobytes()})  # no layout has 10
    for layout, n in LAYOUTS.items():
        assert client(GOOD_BS | {"w": np.ones(n, "<f4").tobytes()}, layout).w.shape == (n,)
    for bad in (np.nan, np.inf, -np.inf):
        w = np.zeros(52, "<f4")
        w[3] = bad
        raises("non_finite", client, GOOD_BS | {"w": w.tobytes()}, "arkit52")


@settings(max_examples=300, deadline=None)
@given(hnp.arrays(np.float32, st.integers(0, 300), elements=st.floats(width=32)), st.booleans())
def test_field_arrays_refuse_nan_and_infinity_exactly_like_numpy(values: np.ndarray, extremes: bool) -> None:
    """get_array's Python check of small float32 arrays (a float64 sum) and numpy's of larger ones say the same
    as np.isfinite, also for the largest finite values, which must not overflow the sum."""
    from ofera_protocol._fields import get_array

    if extremes:
        values = np.where(np.isfinite(values), np.float32(3.4028235e38), values).astype(np.float32)
    m = {"a": values.tobytes()}
    if np.isfinite(values).all():
        assert np.array_equal(get_array(m, "a", "t", "<f4", values.shape), values)
    else:
        with pytest.raises(ProtocolError) as e:
            get_array(m, "a", "t", "<f4", values.shape)
        assert e.value.code == "non_finite"


HELLO = {"type": "hello", "protocol": 1, "layout": "arkit52"}


def test_hello_errors() -> None:
    assert raises("unsupported_protocol", client, HELLO | {"protocol": 2}).fatal
    # the version is checked before anything else, so a v2 hello with v2 fields still gets the right code
    raises("unsupported_protocol", client, {"type": "hello", "protocol": 2, "layout": {"v2": 1}})
    raises("bad_field", client, {"type": "hello", "layout": "arkit52"})
    raises("bad_field", client, HELLO | {"protocol": "1"})
    assert raises("unknown_layout", client, HELLO | {"layout": "arkit53"}).fatal
    raises("bad_field", client, HELLO | {"layout": 52})
    raises("bad_field", client, HELLO | {"layout": None})
    assert raises("unknown_encoding", client, HELLO | {"encoding": "png"}).fatal
    raises("bad_field", client, HELLO | {"coords": "unreal"})
    raises("bad_field", client, HELLO | {"sparse": 1})
    raises("bad_field", client, HELLO | {"avatar": ""})
    raises("bad_field", client, HELLO | {"avatar": "x" * 300})
    raises("bad_field", client, HELLO | {"max_gaussians": 0})
    raises("bad_field", client, HELLO | {"token": 123})
    raises("bad_field", client, HELLO | {"device": b"quest"})


WELCOME = {"type": "welcome", "protocol": 1, "session": "s", "avatar": {"id": "a", "count": 4, "sh_degree": 0},
           "layout": "arkit52", "encoding": "f32", "coords": "flame", "sparse": False}
QUANT_MAP = {"pos_min": np.zeros(3, "<f4").tobytes(), "pos_max": np.ones(3, "<f4").tobytes(),
             "log_scale": np.array([-5, -1], "<f4").tobytes()}


def test_welcome_errors() -> None:
    assert isinstance(server(WELCOME), Welcome)
    raises("unsupported_protocol", server, WELCOME | {"protocol": 2})
    raises("bad_field", server, WELCOME | {"avatar": {"id": "a", "count": -1, "sh_degree": 0}})
    raises("bad_field", server, WELCOME | {"avatar": {"id": "a", "count": 1, "sh_degree": 4}})
    raises("bad_field", server, WELCOME | {"avatar": "a"})
    raises("bad_field", server, WELCOME | {"sparse": None})
    raises("unknown_encoding", server, WELCOME | {"encoding": "q12"})
    raises("bad_field", server, WELCOME | {"encoding": "q13"})  # q13 needs quant
    assert server(WELCOME | {"encoding": "q13", "quant": QUANT_MAP}).quant is not None
    raises("bad_length", server, WELCOME | {"encoding": "q13", "quant": QUANT_MAP | {"pos_min": b"\x00" * 8}})
    raises("bad_field", server, WELCOME | {"encoding": "q13", "quant": QUANT_MAP | {"pos_max": QUANT_MAP["pos_min"]}})
    raises("bad_field", server, WELCOME | {"encoding": "q13",
                                           "quant": QUANT_MAP | {"log_scale": np.array([1, 1], "<f4").tobytes()}})
    raises("non_finite", server, WELCOME | {"encoding": "q13",
                                            "quant": QUANT_MAP | {"pos_max": np.full(3, np.inf, "<f4").tobytes()}})


def _avatar_map(n: int = 2, count: int = 4, offset: int = 0, deg: int = 0) -> dict:
    k = (deg + 1) ** 2
    return {"type": "avatar", "count": count, "sh_degree": deg, "chunk": 0, "chunks": 2, "offset": offset, "n": n,
            "opacity": np.full(n, 0.5, "<f4").tobytes(), "sh": np.zeros((n, k, 3), "<f4").tobytes(),
            "position": np.zeros((n, 3), "<f4").tobytes(), "rotation": np.zeros((n, 4), "<f4").tobytes(),
            "scale": np.ones((n, 3), "<f4").tobytes()}


def test_avatar_errors() -> None:
    assert server(_avatar_map()).n == 2
    raises("bad_field", server, _avatar_map(n=3, offset=2))  # offset + n > count
    raises("bad_field", server, _avatar_map() | {"chunk": 2})
    raises("bad_field", server, _avatar_map() | {"chunks": 0})
    raises("bad_length", server, _avatar_map(deg=1) | {"sh": np.zeros((2, 1, 3), "<f4").tobytes()})
    raises("bad_length", server, _avatar_map() | {"rotation": np.zeros((2, 3), "<f4").tobytes()})
    raises("bad_field", server, _avatar_map() | {"opacity": np.array([0.5, 1.5], "<f4").tobytes()})
    raises("non_finite", server, _avatar_map() | {"scale": np.full((2, 3), np.nan, "<f4").tobytes()})


FMT = FrameFormat("f32", 4)
SFMT = FrameFormat("f32", 4, sparse=True)


def _frame_map(n: int = 4, dtype: str = "<f4", **kw: object) -> dict:
    d = {"type": "frame", "seq": 3, "t": 4, "timing": {"epm": 5}, "n": n,
         "position": np.zeros((n, 3), dtype).tobytes(), "rotation": np.zeros((n, 4), dtype).tobytes(),
         "scale": np.zeros((n, 3), dtype).tobytes()}
    d.update(kw)
    return d


def test_frame_errors() -> None:
    assert server(_frame_map(), FMT).n == 4
    raises("not_ready", server, _frame_map(), None)
    raises("bad_length", server, _frame_map(n=3), FMT)  # dense frame must carry count
    raises("bad_length", server, _frame_map(position=b"\x00" * 44), FMT)
    raises("bad_length", server, _frame_map(scale=b""), FMT)
    raises("bad_field", server, _frame_map(rotation=None), FMT)
    raises("bad_field", server, _frame_map(timing={"epm": -1}), FMT)
    raises("bad_field", server, _frame_map(timing={"epm": 1.0}), FMT)
    raises("bad_field", server, _frame_map(timing=[1]), FMT)
    raises("bad_field", server, _frame_map(timing={f"s{i}": 1 for i in range(65)}), FMT)
    idx = np.array([0, 2], "<u4").tobytes()
    raises("bad_field", server, _frame_map(n=2, index=idx), FMT)  # index in a dense session
    assert server(_frame_map(n=2, index=idx), SFMT).index.tolist() == [0, 2]
    raises("bad_field", server, _frame_map(n=2, index=np.array([2, 0], "<u4").tobytes()), SFMT)
    raises("bad_field", server, _frame_map(n=2, index=np.array([1, 1], "<u4").tobytes()), SFMT)
    raises("bad_field", server, _frame_map(n=2, index=np.array([1, 4], "<u4").tobytes()), SFMT)
    raises("bad_length", server, _frame_map(n=2, index=idx[:4]), SFMT)
    pos = np.zeros((4, 3), "<f4")
    pos[1, 2] = np.inf
    raises("non_finite", server, _frame_map(position=pos.tobytes()), FMT)
    half = np.zeros((4, 4), "<u2")
    half[0, 0] = 0x7E00  # float16 NaN
    raises("non_finite", server, _frame_map(dtype="<f2", rotation=half.tobytes()), FrameFormat("f16", 4))


def test_error_and_pong_errors() -> None:
    raises("bad_field", server, {"type": "error", "code": "x", "message": "m", "fatal": 1})
    raises("bad_field", server, {"type": "error", "code": "x", "fatal": True})
    raises("bad_field", server, {"type": "pong"})


# ============================================================================= fuzz

VALID = [
    encode(Hello(layout="arkit52")), encode(Blendshapes(1, 2, np.zeros(52, np.float32))), encode(Ping(3)),
    encode(Welcome("s", AvatarInfo("a", 4, 0), "arkit52")),
    encode(Frame(1, 2, np.zeros((4, 3), np.float32), np.zeros((4, 4), np.float32), np.ones((4, 3), np.float32)),
           FMT),
]
FORMATS = [None, FMT, SFMT, FrameFormat("f16", 4), FrameFormat("q13", 4, True, QUANT)]


def _only_protocol_errors(data: bytes) -> None:
    for layout in (None, "arkit52"):
        try:
            decode_client_message(data, layout)
        except ProtocolError:
            pass
    for fmt in FORMATS:
        try:
            decode_server_message(data, fmt)
        except ProtocolError:
            pass


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_random_bytes(data: bytes) -> None:
    _only_protocol_errors(data)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(VALID), st.data())
def test_fuzz_mutated_valid_messages(msg: bytes, data: st.DataObject) -> None:
    b = bytearray(msg)
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        pos = data.draw(st.integers(0, len(b)))
        if op == "flip" and pos < len(b):
            b[pos] = data.draw(st.integers(0, 255))
        elif op == "cut":
            del b[pos:pos + data.draw(st.integers(1, 8))]
        else:
            b[pos:pos] = data.draw(st.binary(min_size=1, max_size=4))
    _only_protocol_errors(bytes(b))


_scalars = (st.none() | st.booleans() | st.integers(-(2**64), 2**64 - 1) | st.floats() | st.text(max_size=8)
            | st.binary(max_size=64))
_values = st.recursive(_scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c,
                                                                                      max_size=3), max_leaves=6)
_keys = st.sampled_from(["type", "protocol", "layout", "seq", "t", "w", "n", "index", "position", "rotation",
                         "scale", "timing", "avatar", "count", "sh_degree", "chunk", "chunks", "offset",
                         "opacity", "sh", "quant", "encoding", "sparse", "code", "message", "fatal"])
_types = st.sampled_from(["hello", "bs", "ping", "bye", "welcome", "avatar", "frame", "error", "pong", "x"])


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_types, st.dictionaries(_keys, _values, max_size=8))
def test_fuzz_structured_maps(t: str, d: dict) -> None:
    d["type"] = t
    try:
        data = msgpack.packb(d, use_bin_type=True)
    except (OverflowError, ValueError):
        return
    _only_protocol_errors(data)


# ----------------------------------------------------------------------------- header-only reading

VECTOR_DIR = Path(__file__).resolve().parents[1] / "protocol" / "vectors"
FRAME_VECTORS = sorted(p.stem for p in VECTOR_DIR.glob("*frame*.msgpack") if not p.stem.startswith("invalid_"))


def _vector_format(d: dict) -> FrameFormat | ParamsFormat:
    if d["encoding"] == "params":
        return ParamsFormat()
    q = d["quant"]
    quant = None if q is None else Quant(*(np.array(q[k], np.float32) for k in ("pos_min", "pos_max", "log_scale")))
    return FrameFormat(d["encoding"], d["count"], d["sparse"], quant, delta=d.get("delta", False))


def test_frame_vectors_cover_members_deltas_and_params() -> None:
    assert {"frame_q13_member", "frame_f16_sparse_member", "frame_f16_delta", "frame_q13_key",
            "params_frame", "params_frame_stamped", "frame_f32"} <= set(FRAME_VECTORS)


@pytest.mark.parametrize("name", FRAME_VECTORS)
def test_read_frame_header_matches_vector_and_full_decode(name: str) -> None:
    data = (VECTOR_DIR / f"{name}.msgpack").read_bytes()
    spec = json.loads((VECTOR_DIR / f"{name}.json").read_text(encoding="utf-8"))
    head = read_frame_header(data)
    fields = spec["fields"]
    assert head == FrameHeader(seq=fields.get("seq"), t=fields.get("t"), timing=fields.get("timing"), size=len(data),
                               n=fields.get("n"), key=fields.get("key"), member=fields.get("member"))
    full = decode_server_message(data, _vector_format(spec["format"]))
    assert (head.seq, head.t, head.timing, head.member) == (full.seq, full.t, full.timing,
                                                            getattr(full, "member", None))
    if not isinstance(full, ParamsFrame):
        assert head.n == full.n and head.key == (full.key if isinstance(full, Frame) else False)
    assert read_frame_header(memoryview(bytearray(data))) == head


@pytest.mark.parametrize("name", ["welcome", "welcome_room", "avatar_chunk0", "avatar_member", "join", "leave",
                                  "error_fatal", "pong", "rig_tiny"])
def test_read_frame_header_is_none_for_other_server_messages(name: str) -> None:
    assert read_frame_header((VECTOR_DIR / f"{name}.msgpack").read_bytes()) is None


@pytest.mark.parametrize("name", ["invalid_truncated", "invalid_trailing_bytes", "invalid_not_a_map",
                                  "invalid_non_string_key", "invalid_deep_nesting", "invalid_huge_bin",
                                  "invalid_missing_type", "invalid_unknown_type", "invalid_params_seq_without_t"])
def test_read_frame_header_refuses_what_the_codec_refuses(name: str) -> None:
    spec = json.loads((VECTOR_DIR / f"{name}.json").read_text(encoding="utf-8"))
    raises(spec["expect_error"]["code"], read_frame_header, (VECTOR_DIR / f"{name}.msgpack").read_bytes())


def test_read_frame_header_checks_small_fields_not_arrays() -> None:
    ok = {"type": "frame", "seq": 1, "t": 2, "timing": {"total": 3}, "n": 1, "position": b"\0" * 3}
    assert read_frame_header(pack_map(ok)) == FrameHeader(1, 2, {"total": 3}, len(pack_map(ok)), n=1)
    raises("bad_field", read_frame_header, pack_map({**ok, "seq": -1}))
    raises("bad_field", read_frame_header, pack_map({**ok, "t": "now"}))
    raises("bad_field", read_frame_header, pack_map({**ok, "timing": {"total": -1}}))
    raises("bad_field", read_frame_header, pack_map({k: v for k, v in ok.items() if k != "n"}))
    raises("bad_field", read_frame_header, pack_map({**ok, "key": 1}))
    raises("bad_field", read_frame_header, pack_map({**ok, "member": ""}))
    raises("malformed", read_frame_header, pack_map({**ok, "x": msgpack.ExtType(1, b"ab")}))
    raises("malformed", read_frame_header, "frame")
    raises("message_too_large", read_frame_header, pack_map(ok), 10)
    for name in ("invalid_frame_nan", "invalid_frame_length", "invalid_delta_count"):  # bad arrays: not read
        assert read_frame_header((VECTOR_DIR / f"{name}.msgpack").read_bytes()) is not None


@FAST
@given(st.sampled_from(ENCODINGS), st.integers(0, 6), st.booleans(), seqs, int64s,
       st.dictionaries(st.text(min_size=1, max_size=10), st.integers(0, 2**63 - 1), max_size=8),
       st.none() | ids, st.data())
def test_read_frame_header_agrees_with_full_decodes(enc, count, fast, seq, t, timing, member, data) -> None:
    fmt = FrameFormat(enc, count, quant=QUANT if enc == "q13" else None)
    rng = np.random.default_rng(seq % 1000)
    pos, rot, scale = (rng.uniform(0.01, 0.1, (count, k)).astype(np.float32) for k in (3, 4, 3))
    if fast:
        from ofera_protocol.fast_encodings import FrameWriter

        wire = bytes(FrameWriter(fmt).encode(seq, t, timing, pos, rot, scale, member=member))
    else:
        wire = encode(Frame(seq, t, pos, rot, scale, timing=timing, member=member), fmt)
    full = decode_server_message(wire, fmt)
    head = read_frame_header(wire)
    assert head == FrameHeader(full.seq, full.t, full.timing, len(wire), n=full.n, member=full.member)


def test_read_frame_header_leaves_arrays_uncopied() -> None:
    import tracemalloc

    n = 115_600
    fmt = FrameFormat("f32", n)
    wire = encode(Frame(7, 8, np.zeros((n, 3), np.float32), np.zeros((n, 4), np.float32),
                        np.zeros((n, 3), np.float32), timing={"total": 1}), fmt)
    assert len(wire) > 4_000_000
    tracemalloc.start()
    head = read_frame_header(wire)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert head is not None and (head.seq, head.n, head.size) == (7, n, len(wire)) and peak < 64_000


@pytest.mark.parametrize("avatar", ["absent", None])
def test_a_room_publisher_must_name_its_avatar_nil_is_absent(avatar) -> None:
    """PROTOCOL.md 12.1: publishing in a room needs `avatar`; a nil value counts as absent (section 2)."""
    m = {"type": "hello", "protocol": 1, "layout": "arkit52", "room": "lab"}
    if avatar != "absent":
        m["avatar"] = avatar
    with pytest.raises(ProtocolError) as e:
        decode_client_message(msgpack.packb(m))
    assert e.value.code == "bad_field" and "avatar" in e.value.message


def test_pack_map_packs_arrays_as_bin_and_refuses_what_is_not_a_field_array() -> None:
    """pack_map's one msgpack call: arrays of any shape and dtype (empty ones too) are their raw bytes as bin, in key
    order; a non-contiguous array and a numpy scalar (it exports a buffer too) are refused, not packed."""
    a = np.arange(12, dtype="<u2").reshape(4, 3)
    data = pack_map({"z": 1, "a": a, "e": np.zeros((0, 3), np.int8), "t": {"x": 2}})
    assert list(msgpack.unpackb(data)) == ["z", "a", "e", "t"]
    assert msgpack.unpackb(data) == {"z": 1, "a": a.tobytes(), "e": b"", "t": {"x": 2}}
    with pytest.raises(ValueError, match="C-contiguous"):
        pack_map({"a": a[:, :2]})
    with pytest.raises(TypeError, match="int64"):
        pack_map({"n": np.int64(3)})


def test_message_packer_gives_pack_maps_bytes_and_never_overwrites_a_held_message() -> None:
    """MessagePacker: the bytes of pack_map, in reused buffers; a message still referenced keeps its bytes (the
    next one goes to another buffer), a released buffer is reused."""
    rng = np.random.default_rng(3)
    packer = MessagePacker()
    items = [{"type": "frame", "seq": k, "bits": rng.integers(0, 255, 1000 * (k + 1), dtype=np.uint8)}
             for k in range(4)]
    held = packer.pack(items[0])
    assert bytes(held) == pack_map(items[0])
    for k in (1, 2, 3):  # `held` is kept: each of these lands elsewhere; each is released before the next
        assert bytes(packer.pack(items[k])) == pack_map(items[k])
    assert bytes(held) == pack_map(items[0]) and len(packer._packers) == 2
    del held
    assert bytes(packer.pack(items[2])) == pack_map(items[2]) and len(packer._packers) == 2
