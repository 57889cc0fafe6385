"""ServerConnection / ClientConnection state machines: the session flow of PROTOCOL.md section 3."""

from __future__ import annotations

import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "protocol"))

from ofera_protocol import (  # noqa: E402
    Avatar,
    AvatarInfo,
    Blendshapes,
    Bye,
    ClientConnection,
    ClientState,
    ConnectionUsageError,
    ErrorMessage,
    Frame,
    Hello,
    Ping,
    Pong,
    ProtocolError,
    ServerConnection,
    ServerState,
    Welcome,
    decode_server_message,
    encode,
    encode_frame,
    make_quant,
    mirror_x_position,
    mirror_x_rotation,
    mirror_x_sh,
    to_coords,
)
from ofera_protocol.avatar import avatar_bytes_per_gaussian  # noqa: E402

N = 12


def make_avatar(n: int = N, deg: int = 1) -> Avatar:
    rng = np.random.default_rng(7)
    rot = rng.normal(size=(n, 4))
    return Avatar(opacity=rng.uniform(0, 1, n).astype(np.float32),
                  sh=rng.normal(size=(n, (deg + 1) ** 2, 3)).astype(np.float32),
                  position=rng.uniform(-0.1, 0.1, (n, 3)).astype(np.float32),
                  rotation=(rot / np.linalg.norm(rot, axis=1, keepdims=True)).astype(np.float32),
                  scale=np.exp(rng.uniform(-7, -4, (n, 3))).astype(np.float32))


def handshake(encoding: str = "f32", sparse: bool = False, coords: str = "flame", chunk_bytes: int = 5 * 1024,
              avatar: Avatar | None = None) -> tuple[ServerConnection, ClientConnection, Avatar]:
    avatar = avatar or make_avatar()
    srv, cli = ServerConnection(), ClientConnection()
    hello = srv.receive(cli.hello("ovr63", encoding=encoding, coords=coords, sparse=sparse, device="quest_pro"))
    assert isinstance(hello, Hello) and srv.state is ServerState.HELLO_RECEIVED
    assert (hello.layout, hello.encoding, hello.coords, hello.sparse) == ("ovr63", encoding, coords, sparse)
    quant = make_quant(avatar.position, avatar.scale) if encoding == "q13" else None
    welcome = cli.receive(srv.accept("sess-1", AvatarInfo("default", avatar.count, avatar.sh_degree), quant=quant,
                                     server="test"))
    assert isinstance(welcome, Welcome) and srv.state is ServerState.STREAMING
    assert cli.state is ClientState.RECEIVING_AVATAR and cli.format == srv.format
    for b in srv.avatar(avatar, chunk_bytes):
        cli.receive(b)
    assert cli.state is ClientState.STREAMING and cli.avatar == avatar
    return srv, cli, avatar


def frame_for(avatar: Avatar, seq: int, index: np.ndarray | None = None, shift: float = 0.01) -> Frame:
    sel = slice(None) if index is None else index
    return Frame(seq=seq, t=1000 + seq, timing={"epm": 40, "total": 400}, index=index,
                 position=avatar.position[sel] + np.float32(shift), rotation=avatar.rotation[sel],
                 scale=avatar.scale[sel] * np.float32(1.1))


@pytest.mark.parametrize("encoding", ["f32", "f16", "q13"])
@pytest.mark.parametrize("sparse", [False, True])
def test_full_session(encoding: str, sparse: bool) -> None:
    srv, cli, avatar = handshake(encoding, sparse)
    assert cli.welcome.sparse is sparse and (cli.welcome.quant is not None) == (encoding == "q13")
    bs = srv.receive(cli.bs(0, 123, np.linspace(0, 1, 63)))
    assert isinstance(bs, Blendshapes) and bs.seq == 0 and bs.t == 123 and bs.w.shape == (63,)
    f = cli.receive(srv.frame(frame_for(avatar, 0)))
    assert isinstance(f, Frame) and f.seq == 0 and f.t == 1000 and f.timing == {"epm": 40, "total": 400}
    tol = {"f32": 0, "f16": 1e-3, "q13": 1e-4}[encoding]
    np.testing.assert_allclose(cli.gaussians.position, avatar.position + 0.01, atol=tol)
    if sparse:
        idx = np.array([2, 5, 11], np.uint32)
        cli.receive(srv.frame(frame_for(avatar, 1, idx, shift=0.02)))
        expect = avatar.position + 0.01
        expect[idx] += 0.01
        np.testing.assert_allclose(cli.gaussians.position, expect, atol=tol)
    assert isinstance(srv.receive(cli.ping(77)), Ping)
    assert cli.receive(srv.pong(77)) == Pong(77)
    assert isinstance(srv.receive(cli.bye()), Bye)
    assert srv.state is ServerState.CLOSED and cli.state is ClientState.CLOSED


def test_unity_coords_session() -> None:
    """The server mirrors before encoding (PROTOCOL.md section 8); the client gets Unity-space values."""
    flame = make_avatar()
    p, r = to_coords(flame.position, flame.rotation, "unity")
    unity = Avatar(flame.opacity, mirror_x_sh(flame.sh), p, r, flame.scale)
    srv, cli, _ = handshake(coords="unity", avatar=unity)
    assert cli.welcome.coords == "unity"
    assert np.array_equal(cli.avatar.position[:, 0], -flame.position[:, 0])
    f = frame_for(flame, 3)
    cli.receive(srv.frame(Frame(f.seq, f.t, mirror_x_position(f.position), mirror_x_rotation(f.rotation), f.scale)))
    assert np.array_equal(cli.gaussians.position, mirror_x_position(flame.position + np.float32(0.01)))


def test_fan_out_encodes_once_per_format() -> None:
    srv_a, cli_a, avatar = handshake("f16")
    srv_b, cli_b, _ = handshake("f16")
    data = encode_frame(frame_for(avatar, 9), srv_a.format)
    assert srv_a.format == srv_b.format
    for cli in (cli_a, cli_b):
        assert cli.receive(data).seq == 9


def test_chunked_avatar_arrives_in_several_messages() -> None:
    srv, cli = ServerConnection(), ClientConnection()
    avatar = make_avatar(100, 3)
    srv.receive(cli.hello("arkit52"))
    cli.receive(srv.accept("s", AvatarInfo("a", 100, 3)))
    msgs = srv.avatar(avatar, max_chunk_bytes=10 * avatar_bytes_per_gaussian(3))
    assert len(msgs) == 10
    for m in msgs[:-1]:
        cli.receive(m)
        assert cli.state is ClientState.RECEIVING_AVATAR
    cli.receive(msgs[-1])
    assert cli.avatar == avatar


# ============================================================================= server rules


def test_bs_before_hello_is_fatal() -> None:
    srv = ServerConnection()
    with pytest.raises(ProtocolError) as ei:
        srv.receive(encode(Blendshapes(0, 0, np.zeros(52, np.float32))))
    e = ei.value
    assert (e.code, e.fatal, e.close_code) == ("not_ready", True, 4005)
    assert srv.state is ServerState.CLOSED
    err = decode_server_message(srv.error(e))
    assert err == ErrorMessage("not_ready", e.message, True)
    with pytest.raises(ConnectionUsageError):
        srv.receive(encode(Ping(1)))


def test_bs_between_hello_and_welcome_is_dropped() -> None:
    srv = ServerConnection()
    srv.receive(encode(Hello(layout="arkit52")))
    with pytest.raises(ProtocolError) as ei:
        srv.receive(encode(Blendshapes(0, 0, np.zeros(52, np.float32))))
    assert ei.value.code == "not_ready" and not ei.value.fatal
    assert srv.state is ServerState.HELLO_RECEIVED


def test_duplicate_hello_is_ignored() -> None:
    srv, cli, _ = handshake()
    with pytest.raises(ProtocolError) as ei:
        srv.receive(encode(Hello(layout="arkit51")))
    assert ei.value.code == "duplicate_hello" and not ei.value.fatal
    assert srv.state is ServerState.STREAMING and srv.hello.layout == "ovr63"


@pytest.mark.parametrize("data,code", [
    (b"\xc1", "malformed"), (msgpack.packb({"type": "teleport"}), "unknown_type"),
    (msgpack.packb({"type": "ping"}), "bad_field"),
    (encode(Hello(layout="arkit52", protocol=2)), "unsupported_protocol"),
    (msgpack.packb({"type": "hello", "protocol": 1, "layout": "x"}), "unknown_layout"),
    (msgpack.packb({"type": "hello", "protocol": 1, "layout": "arkit52", "encoding": "x"}), "unknown_encoding"),
])
def test_any_error_while_awaiting_hello_is_fatal(data: bytes, code: str) -> None:
    srv = ServerConnection()
    with pytest.raises(ProtocolError) as ei:
        srv.receive(data)
    assert ei.value.code == code and ei.value.fatal and ei.value.close_code >= 4000
    assert srv.state is ServerState.CLOSED


def test_errors_while_streaming_are_not_fatal_except_always_fatal_ones() -> None:
    srv, cli, _ = handshake()
    for data, code in [(b"\xc1", "malformed"), (msgpack.packb({"type": "x"}), "unknown_type"),
                       (encode(Blendshapes(1, 0, np.zeros(52, np.float32))), "bad_length"),  # session is ovr63
                       (encode(Blendshapes(1, 0, np.full(63, np.nan, np.float32))), "non_finite")]:
        with pytest.raises(ProtocolError) as ei:
            srv.receive(data)
        assert ei.value.code == code and not ei.value.fatal
        assert srv.state is ServerState.STREAMING
    assert isinstance(srv.receive(cli.bs(5, 0, np.zeros(63))), Blendshapes)
    with pytest.raises(ProtocolError) as ei:
        srv.receive(b"\x00" * (srv.max_message_size + 1))
    assert ei.value.code == "message_too_large" and ei.value.fatal and ei.value.close_code == 1009
    assert srv.state is ServerState.CLOSED


def test_text_frames_are_fatal() -> None:
    for conn in (ServerConnection(), ClientConnection()):
        with pytest.raises(ProtocolError) as ei:
            conn.receive_text('{"type": "hello"}')
        assert (ei.value.code, ei.value.fatal, ei.value.close_code) == ("text_frame", True, 1003)


@pytest.mark.parametrize("code,close", [("unknown_avatar", 4012), ("unauthorized", 1008), ("server_full", 1013),
                                        ("internal", 1011), ("unknown_encoding", 4013)])
def test_reject(code: str, close: int) -> None:
    srv = ServerConnection()
    srv.receive(encode(Hello(layout="arkit52", avatar="nobody", token="bad")))
    data = srv.reject(code, "try again")
    assert srv.state is ServerState.CLOSED
    assert decode_server_message(data) == ErrorMessage(code, "try again", True)
    assert ProtocolError(code, "").close_code == close


def test_non_fatal_server_errors() -> None:
    srv, cli, _ = handshake()
    data = srv.error("rate_limited", "slow down: at most 144 bs per second", seq=17)
    assert srv.state is ServerState.STREAMING
    msg = cli.receive(data)
    assert msg == ErrorMessage("rate_limited", "slow down: at most 144 bs per second", False, 17)
    assert cli.state is ClientState.STREAMING
    cli.receive(srv.error("internal", "pipeline crashed"))
    assert cli.state is ClientState.CLOSED and srv.state is ServerState.CLOSED


def test_server_misuse() -> None:
    srv = ServerConnection()
    with pytest.raises(ConnectionUsageError):
        srv.accept("s", AvatarInfo("a", 1, 0))
    srv.receive(encode(Hello(layout="arkit52", encoding="q13", max_gaussians=10)))
    with pytest.raises(ConnectionUsageError, match="quant"):
        srv.accept("s", AvatarInfo("a", 5, 0))
    with pytest.raises(ConnectionUsageError, match="allows"):
        srv.accept("s", AvatarInfo("a", 11, 0), encoding="f16")
    with pytest.raises(ConnectionUsageError):
        srv.accept("s", AvatarInfo("a", 5, 0), encoding="f8")
    with pytest.raises(ConnectionUsageError):
        srv.avatar(make_avatar(5))
    srv.accept("s", AvatarInfo("a", 5, 1), encoding="f16")  # the server may choose another encoding
    with pytest.raises(ConnectionUsageError, match="avatar"):
        srv.frame(frame_for(make_avatar(5), 0))
    with pytest.raises(ConnectionUsageError, match="announced"):
        srv.avatar(make_avatar(6))
    srv.avatar(make_avatar(5))
    srv.frame(frame_for(make_avatar(5), 0))
    srv.receive(encode(Bye()))
    with pytest.raises(ConnectionUsageError):
        srv.pong(1)


# ============================================================================= client rules


def test_client_misuse() -> None:
    cli = ClientConnection()
    with pytest.raises(ConnectionUsageError):
        cli.bs(0, 0, np.zeros(52))
    with pytest.raises(ConnectionUsageError):
        cli.hello("arkit99")
    with pytest.raises(ConnectionUsageError):
        cli.hello("arkit52", coords="unreal")
    cli.hello("arkit52")
    with pytest.raises(ConnectionUsageError):
        cli.hello("arkit52")
    srv = ServerConnection()
    srv.receive(encode(Hello(layout="arkit52")))
    cli.receive(srv.accept("s", AvatarInfo("a", 1, 0)))
    with pytest.raises(ConnectionUsageError, match="52"):
        cli.bs(0, 0, np.zeros(51))
    cli.bs(0, 0, np.zeros(52))  # allowed while the avatar arrives
    cli.bye()
    with pytest.raises(ConnectionUsageError):
        cli.ping(1)


def test_client_rejects_out_of_order_server_messages() -> None:
    srv, cli, avatar = handshake()
    welcome = srv.welcome
    # frame before welcome
    fresh = ClientConnection()
    fresh.hello("ovr63")
    with pytest.raises(ProtocolError) as ei:
        fresh.receive(srv.frame(frame_for(avatar, 0)))
    assert ei.value.code == "not_ready" and ei.value.fatal and fresh.state is ClientState.CLOSED
    # frame before the avatar is complete
    c2 = ClientConnection()
    c2.hello("ovr63")
    c2.receive(encode(welcome))
    with pytest.raises(ProtocolError) as ei:
        c2.receive(srv.frame(frame_for(avatar, 0)))
    assert ei.value.code == "not_ready" and ei.value.fatal
    # welcome twice, avatar after the stream started
    for data in (encode(welcome), srv.avatar(avatar)[0]):
        _, c3, _ = handshake()
        with pytest.raises(ProtocolError) as ei:
            c3.receive(data)
        assert ei.value.fatal and c3.state is ClientState.CLOSED
    # welcome that does not match hello
    c4 = ClientConnection()
    c4.hello("arkit52")
    with pytest.raises(ProtocolError, match="layout"):
        c4.receive(encode(welcome))


def test_client_drops_a_bad_frame_and_goes_on() -> None:
    srv, cli, avatar = handshake()
    bad = msgpack.packb({"type": "frame", "seq": 1, "t": 0, "timing": {}, "n": 2, "position": b"",
                         "rotation": b"", "scale": b""})
    with pytest.raises(ProtocolError) as ei:
        cli.receive(bad)
    assert ei.value.code == "bad_length" and not ei.value.fatal and cli.state is ClientState.STREAMING
    assert cli.receive(srv.frame(frame_for(avatar, 2))).seq == 2


def test_client_without_state_tracking() -> None:
    srv = ServerConnection()
    cli = ClientConnection(track_gaussians=False)
    srv.receive(cli.hello("arkit52"))
    avatar = make_avatar()
    cli.receive(srv.accept("s", AvatarInfo("a", N, 1)))
    for b in srv.avatar(avatar):
        cli.receive(b)
    assert cli.receive(srv.frame(frame_for(avatar, 0))).n == N and cli.gaussians is None


# ----------------------------------------------------------------------------- delta sessions (PROTOCOL.md 7.1)


@pytest.mark.parametrize("encoding,want", [("q13", True), ("f16", True), ("f32", False)])
def test_delta_is_negotiated_for_compact_encodings(encoding: str, want: bool) -> None:
    avatar = make_avatar()
    srv, cli = ServerConnection(), ClientConnection()
    hello = srv.receive(cli.hello("arkit52", encoding=encoding, sparse=True, delta=True))
    assert hello.delta
    quant = make_quant(avatar.position, avatar.scale) if encoding == "q13" else None
    welcome = cli.receive(srv.accept("s", AvatarInfo("default", avatar.count, avatar.sh_degree), quant=quant))
    assert welcome.delta is want and welcome.sparse is (not want)  # a delta session is dense
    assert cli.format.delta is want and (cli.delta is not None) is want


def test_resync_is_accepted_only_in_a_delta_session() -> None:
    from ofera_protocol.messages import Resync

    srv = ServerConnection()
    with pytest.raises(ProtocolError) as e:  # before hello: fatal
        srv.receive(encode(Resync()))
    assert e.value.code == "not_ready" and e.value.fatal
    srv, cli, _ = handshake("q13")
    with pytest.raises(ProtocolError) as e:  # not a delta session: non-fatal
        srv.receive(cli.resync())
    assert e.value.code == "not_ready" and not e.value.fatal and srv.state is ServerState.STREAMING


def test_delta_session_client_applies_key_and_delta_frames_and_asks_for_resync() -> None:
    from ofera_protocol.codec import pack_map
    from ofera_protocol.delta import DeltaEncoder
    from ofera_protocol.messages import Resync

    avatar = make_avatar()
    srv, cli = ServerConnection(), ClientConnection()
    srv.receive(cli.hello("arkit52", encoding="q13", delta=True))
    quant = make_quant(avatar.position, avatar.scale)
    cli.receive(srv.accept("s", AvatarInfo("default", avatar.count, avatar.sh_degree), quant=quant))
    for b in srv.avatar(avatar):
        cli.receive(b)
    enc = DeltaEncoder(srv.format, key_interval=0)
    key = cli.receive(enc.encode(1, 0, {}, avatar.position, avatar.rotation, avatar.scale))
    assert key.key is True and key.index is None
    moved = avatar.position.copy()
    moved[3] += np.float32(1e-3)
    got = cli.receive(enc.encode(2, 0, {}, moved, avatar.rotation, avatar.scale))
    assert got.key is False and got.index.tolist() == [3]
    assert np.abs(cli.gaussians.position[3] - moved[3]).max() < 1e-5
    bad = pack_map({"type": "frame", "seq": 3, "t": 0, "timing": {}, "key": False, "n": 5,
                    "changed": np.zeros(2, np.uint8)})
    with pytest.raises(ProtocolError):
        cli.receive(bad)
    assert cli.resync_needed and cli.state is ClientState.STREAMING
    assert isinstance(srv.receive(cli.resync()), Resync) and not cli.resync_needed
