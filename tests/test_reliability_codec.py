"""Bad input through the codec (no sockets): every refusal is a ProtocolError with the documented code,
never another exception, and huge declared lengths are refused without being allocated.

Property-based: arbitrary bytes, structured-but-wrong msgpack maps (known keys, values of every type) and
random message sequences through ServerConnection raise nothing but ProtocolError.
"""

from __future__ import annotations

import struct
import tracemalloc

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from ofera_protocol import (
    LAYOUTS,
    MAX_CLIENT_MESSAGE,
    AvatarInfo,
    Blendshapes,
    FrameFormat,
    Hello,
    ProtocolError,
    Quant,
    ServerConnection,
    decode_client_message,
    decode_server_message,
)
from ofera_protocol.connection import ServerState
from test_reliability_support import hello, pack

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def code_of(data: bytes, layout: str | None = "arkit52") -> str | None:
    """The error code decoding `data` as a client message gives (None: it decoded)."""
    try:
        decode_client_message(data, layout)
    except ProtocolError as e:
        assert e.message and isinstance(e.fatal, bool)
        return e.code
    return None


def nested(depth: int) -> dict:
    d: dict = {"type": "ping", "t": 1}
    inner = d
    for _ in range(depth - 1):
        inner["x"] = {}
        inner = inner["x"]
    return d


HUGE = 0xFFFFFFFF
PING = b"\x82\xa4type\xa4ping\xa1t\x01"  # {"type": "ping", "t": 1}

# (name, bytes, expected code): each checked with a 52-weight arkit52 session layout.
CODEC_CASES = [
    ("empty", b"", "malformed"),
    ("one nil byte", b"\xc0", "malformed"),
    ("reserved byte 0xc1", b"\xc1", "malformed"),
    ("truncated ping", PING[:-3], "malformed"),
    ("trailing byte", PING + b"\x00", "malformed"),
    ("two messages in one", PING + PING, "malformed"),
    ("bin32 declaring 4 GiB", b"\x82\xa4type\xa2bs\xa1w\xc6" + struct.pack(">I", HUGE), "malformed"),
    ("str32 declaring 4 GiB", b"\x81\xa4type\xdb" + struct.pack(">I", HUGE), "malformed"),
    ("array32 of 4G entries", b"\x81\xa4type\xdd" + struct.pack(">I", HUGE), "malformed"),
    ("map32 of 4G entries", b"\xdf" + struct.pack(">I", HUGE), "malformed"),
    ("array32 at top", b"\xdd" + struct.pack(">I", HUGE), "malformed"),
    ("ext32 declaring 4 GiB", b"\x81\xa4type\xc9" + struct.pack(">I", HUGE) + b"\x01", "malformed"),
    ("timestamp ext", b"\x81\xa4type\xd6\xff" + b"\x00" * 4, "malformed"),
    ("map of 257 entries", pack({"type": "ping", "t": 1, **{f"k{i}": i for i in range(255)}}), "malformed"),
    ("array of 257 entries", pack({"type": "ping", "t": 1, "a": list(range(257))}), "malformed"),
    ("string of 4097 bytes", pack({"type": "ping", "t": 1, "s": "x" * 4097}), "malformed"),
    ("nesting 5 deep", pack(nested(5)), "malformed"),
    ("nesting 1000 deep (arrays)", b"\x82\xa4type\xa4ping\xa1t" + b"\x91" * 1000 + b"\x01", "malformed"),
    ("invalid UTF-8 string", b"\x81\xa4type\xa2\xff\xfe", "malformed"),
    ("integer key", b"\x82\xa4type\xa4ping\x01\x02", "malformed"),
    ("bin key", b"\x82\xa4type\xa4ping\xc4\x01t\x01", "malformed"),
    ("not a map (array)", pack([1, 2, 3]), "malformed"),
    ("not a map (int)", pack(7), "malformed"),
    ("not a map (bin)", pack(b"\x00" * 10), "malformed"),
    ("no type", pack({"t": 1}), "bad_field"),
    ("type is an int", pack({"type": 3}), "bad_field"),
    ("type is bin", pack({"type": b"bs"}), "bad_field"),
    ("type is empty", pack({"type": ""}), "bad_field"),
    ("unknown type", pack({"type": "teleport"}), "unknown_type"),
    ("server type from a client", pack({"type": "frame"}), "unknown_type"),
    ("ping t is a float", pack({"type": "ping", "t": 1.5}), "bad_field"),
    ("ping t is a bool", pack({"type": "ping", "t": True}), "bad_field"),
    ("ping t beyond int64", pack({"type": "ping", "t": 2**64 - 1}), "bad_field"),
    ("hello protocol 2", hello(protocol=2), "unsupported_protocol"),
    ("hello protocol 0", hello(protocol=0), "unsupported_protocol"),
    ("hello protocol '1'", hello(protocol="1"), "bad_field"),
    ("hello protocol missing", pack({"type": "hello", "layout": "arkit52"}), "bad_field"),
    ("hello unknown layout", hello(layout="arkit99"), "unknown_layout"),
    ("hello layout int", hello(layout=52), "bad_field"),
    ("hello unknown encoding", hello(encoding="png"), "unknown_encoding"),
    ("hello coords blender", hello(coords="blender"), "bad_field"),
    ("hello sparse 1", hello(sparse=1), "bad_field"),
    ("hello avatar empty", hello(avatar=""), "bad_field"),
    ("hello avatar 257 chars", hello(avatar="a" * 257), "bad_field"),
    ("hello avatar int", hello(avatar=5), "bad_field"),
    ("hello token 4097 bytes", hello(token="t" * 4097), "malformed"),
    ("hello max_gaussians 0", hello(max_gaussians=0), "bad_field"),
    ("hello max_gaussians 2^32", hello(max_gaussians=2**32), "bad_field"),
    ("bs w missing", pack({"type": "bs", "seq": 0, "t": 0}), "bad_field"),
    ("bs w is a list", pack({"type": "bs", "seq": 0, "t": 0, "w": [0.0] * 52}), "bad_field"),
    ("bs w is a str", pack({"type": "bs", "seq": 0, "t": 0, "w": "x" * 208}), "bad_field"),
    ("bs w empty", pack({"type": "bs", "seq": 0, "t": 0, "w": b""}), "bad_length"),
    ("bs 51 weights for arkit52", pack({"type": "bs", "seq": 0, "t": 0, "w": b"\0" * 204}), "bad_length"),
    ("bs 209 bytes", pack({"type": "bs", "seq": 0, "t": 0, "w": b"\0" * 209}), "bad_length"),
    ("bs seq negative", pack({"type": "bs", "seq": -1, "t": 0, "w": b"\0" * 208}), "bad_field"),
    ("bs seq float", pack({"type": "bs", "seq": 1.0, "t": 0, "w": b"\0" * 208}), "bad_field"),
    ("bs t missing", pack({"type": "bs", "seq": 0, "w": b"\0" * 208}), "bad_field"),
    ("bs NaN", pack({"type": "bs", "seq": 0, "t": 0, "w": np.full(52, np.nan, "<f4").tobytes()}), "non_finite"),
    ("bs +inf", pack({"type": "bs", "seq": 0, "t": 0, "w": np.full(52, np.inf, "<f4").tobytes()}), "non_finite"),
    ("bs -inf", pack({"type": "bs", "seq": 0, "t": 0, "w": np.full(52, -np.inf, "<f4").tobytes()}), "non_finite"),
    ("bs 1e30 (finite)", pack({"type": "bs", "seq": 0, "t": 0, "w": np.full(52, 1e30, "<f4").tobytes()}), None),
    ("bs float32 max", pack({"type": "bs", "seq": 0, "t": 0, "w": np.full(52, 3.4e38, "<f4").tobytes()}), None),
    ("bs with unknown keys", pack({"type": "bs", "seq": 0, "t": 0, "w": b"\0" * 208, "zz": [1, {"a": 2}]}), None),
    ("bs nil seq", pack({"type": "bs", "seq": None, "t": 0, "w": b"\0" * 208}), "bad_field"),
]


@pytest.mark.parametrize("name, data, code", CODEC_CASES, ids=[c[0] for c in CODEC_CASES])
def test_codec_refuses_bad_input_with_the_documented_code(name: str, data: bytes, code: str | None) -> None:
    assert code_of(data) == code


def test_oversized_message_is_refused_before_decoding() -> None:
    data = pack({"type": "ping", "t": 1, "pad": b"\0" * MAX_CLIENT_MESSAGE})
    assert code_of(data) == "message_too_large"
    with pytest.raises(ProtocolError) as e:
        decode_client_message(data)
    assert e.value.fatal and e.value.close_code == 1009


def test_huge_declared_lengths_allocate_nothing() -> None:
    """4 GiB promised in a few bytes: refused with at most a few KiB allocated."""
    headers = [b"\xc6", b"\xdb", b"\xdd", b"\xdf", b"\xc9"]
    tracemalloc.start()
    try:
        for h in headers:
            for prefix in (b"", b"\x81\xa4type"):
                with pytest.raises(ProtocolError):
                    decode_client_message(prefix + h + struct.pack(">I", HUGE) + b"\x00" * 8)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, f"peak {peak} bytes"


def test_state_machine_bad_sequences() -> None:
    """bs before hello: fatal not_ready; a second hello: non-fatal duplicate_hello; after a fatal error
    the connection is closed."""
    c = ServerConnection()
    with pytest.raises(ProtocolError) as e:
        c.receive(pack({"type": "bs", "seq": 0, "t": 0, "w": b"\0" * 208}))
    assert e.value.code == "not_ready" and e.value.fatal and c.state is ServerState.CLOSED

    c = ServerConnection()
    assert isinstance(c.receive(hello()), Hello)
    with pytest.raises(ProtocolError) as e:  # bs while the server decides: dropped, non-fatal
        c.receive(pack({"type": "bs", "seq": 0, "t": 0, "w": b"\0" * 208}))
    assert e.value.code == "not_ready" and not e.value.fatal
    c.accept("s", AvatarInfo(id="default", count=4, sh_degree=0))
    with pytest.raises(ProtocolError) as e:
        c.receive(hello())
    assert e.value.code == "duplicate_hello" and not e.value.fatal
    with pytest.raises(ProtocolError) as e:
        c.receive(b"\xc1")
    assert e.value.code == "malformed" and not e.value.fatal  # streaming: only that message was bad
    assert isinstance(c.receive(pack({"type": "bs", "seq": 1, "t": 0, "w": b"\0" * 208})), Blendshapes)

    c = ServerConnection()
    with pytest.raises(ProtocolError) as e:
        c.receive(b"garbage")
    assert e.value.fatal and c.state is ServerState.CLOSED  # any error before hello is fatal
    with pytest.raises(ProtocolError) as e:
        c.receive_text("hello")
    assert e.value.code == "text_frame" and e.value.close_code == 1003


# ----------------------------------------------------------------------------- property-based

KEYS = ["type", "protocol", "layout", "avatar", "encoding", "coords", "sparse", "device", "token",
        "max_gaussians", "seq", "t", "w", "code", "message", "fatal", "count", "n", "index", "timing"]
TYPES = ["hello", "bs", "ping", "bye", "frame", "welcome", "avatar", "error", "pong", "", "x" * 300]

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**64) + 1, max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=40), st.binary(max_size=400),
    st.sampled_from(TYPES + list(LAYOUTS) + ["f32", "f16", "q13", "flame", "unity", "default", "../../etc/passwd"]),
    st.builds(lambda n, v: np.full(n, v, "<f4").tobytes(), st.sampled_from(sorted(set(LAYOUTS.values()))),
              st.floats(width=32, allow_nan=True, allow_infinity=True)),
)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=5)),
                      max_leaves=12)
wrong_maps = st.builds(
    lambda base, t: {**base, "type": t} if t is not None else base,
    st.dictionaries(st.sampled_from(KEYS), values, max_size=10),
    st.one_of(st.none(), st.sampled_from(TYPES), values),
)


Q13 = FrameFormat("q13", 4, True, Quant(np.full(3, -1, np.float32), np.ones(3, np.float32),
                                       np.array([-9, -2], np.float32)))


def _only_protocol_errors(fn, *args) -> None:
    try:
        fn(*args)
    except ProtocolError as e:
        assert isinstance(e.code, str) and e.code and isinstance(e.fatal, bool)


@FUZZ
@given(st.binary(max_size=600))
def test_fuzz_arbitrary_bytes(data: bytes) -> None:
    for layout in (None, "arkit52", "ovr70"):
        _only_protocol_errors(decode_client_message, data, layout)
    _only_protocol_errors(decode_server_message, data, FrameFormat("f32", 4, True))


@FUZZ
@given(st.binary(min_size=1, max_size=200), st.integers(0, 199))
def test_fuzz_corrupted_valid_messages(noise: bytes, at: int) -> None:
    """Valid messages with bytes overwritten or cut: still only ProtocolError."""
    for msg in (hello(), pack({"type": "bs", "seq": 3, "t": 9, "w": b"\0" * 208}), PING):
        i = at % len(msg)
        _only_protocol_errors(decode_client_message, msg[:i] + noise + msg[i + len(noise):], "arkit52")
        _only_protocol_errors(decode_client_message, msg[:i], "arkit52")


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(wrong_maps)
def test_fuzz_structured_but_wrong_maps(m: dict) -> None:
    try:
        data = msgpack.packb(m, use_bin_type=True)
    except (ValueError, OverflowError, TypeError):
        return  # not representable in msgpack
    for layout in (None, "arkit52"):
        _only_protocol_errors(decode_client_message, data, layout)
    _only_protocol_errors(decode_server_message, data, Q13)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(wrong_maps.map(lambda m: ("map", m)), st.binary(max_size=64).map(lambda b: ("raw", b)),
                          st.just(("hello", None)), st.just(("bs", None)), st.just(("text", None))), max_size=8))
def test_fuzz_server_state_machine(steps: list) -> None:
    """Random message sequences: ProtocolError or a message; a fatal error always leaves CLOSED."""
    c = ServerConnection()
    for kind, v in steps:
        if c.state is ServerState.CLOSED:
            break
        try:
            if kind == "text":
                c.receive_text("x")
            elif kind == "hello":
                c.receive(hello())
                if c.state is ServerState.HELLO_RECEIVED:
                    c.accept("s", AvatarInfo(id="default", count=4, sh_degree=0))
            elif kind == "bs":
                c.receive(pack({"type": "bs", "seq": 1, "t": 0, "w": b"\0" * 208}))
            else:
                try:
                    data = msgpack.packb(v, use_bin_type=True) if kind == "map" else v
                except (ValueError, OverflowError, TypeError):
                    continue
                c.receive(data)
        except ProtocolError as e:
            if e.fatal:
                assert c.state is ServerState.CLOSED
