"""Generate the golden vectors of protocol v1: `protocol/vectors/<name>.msgpack` + `<name>.json`.

    python protocol/make_vectors.py          # write the vectors, tables.json, PROTOCOL.md's examples and tables
    python protocol/make_vectors.py --check  # exit 1 if anything on disk differs

Every vector is built from fixed decimal inputs with deterministic arithmetic, so the bytes are the
same on every machine. `vectors/tables.json` holds the protocol's tables (`ofera_protocol.tables`: layouts,
field sizes, limits, error and close codes); every other JSON file describes its message for implementations in
other languages (the C# Unity client tests itself against them):

- `name`, `direction` (`client_to_server` | `server_to_client`), `type`, `size` (bytes), `hex`.
- `fields`: the msgpack map in wire order; a `bin` field is {"dtype", "shape", "values"} with dtype
  one of float32, float16, int8, uint8, uint16, uint32 (all little-endian) and values nested lists.
- delta sessions (PROTOCOL.md 7.1): key, delta, and delta-after-a-dropped-frame vectors per encoding; a delta
  frame's JSON has `after` (the vectors to apply first) and `decoded` = every Gaussian's state afterwards.
- frames: `format` {"encoding", "count", "sparse", "quant"} and `decoded` {"position", "rotation",
  "scale"}: the float32 values a decoder must produce (q13 scale within 1e-6 relative).
- invalid vectors (`invalid_*`): `expect_error` {"code"} and `context` (the `layout` or `format` the
  receiver has negotiated, or null): decoding must fail with exactly that code.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from ofera_protocol import (  # noqa: E402
    Avatar,
    AvatarInfo,
    Blendshapes,
    Bye,
    ErrorMessage,
    Frame,
    FrameFormat,
    Hello,
    Join,
    Leave,
    Ping,
    Pong,
    Quant,
    Welcome,
    encode,
    split_avatar,
)
from ofera_protocol.avatar import avatar_bytes_per_gaussian  # noqa: E402
from ofera_protocol.codec import encode_avatar_chunk, pack_map  # noqa: E402
from ofera_protocol.encodings import SCALE_LEVELS  # noqa: E402
from ofera_protocol.messages import Resync  # noqa: E402
from ofera_protocol.tables import tables, update_markdown  # noqa: E402
from params_vectors import params_vectors, rig_frames  # noqa: E402

VECTOR_DIR = HERE / "vectors"
PROTOCOL_MD = HERE / "PROTOCOL.md"
BEGIN = "<!-- BEGIN GENERATED EXAMPLES (python protocol/make_vectors.py) -->"
END = "<!-- END GENERATED EXAMPLES -->"

C2S, S2C = "client_to_server", "server_to_client"

# dtype and trailing shape of every bin field, per message type and encoding ("*": any encoding).
_F32 = "float32"
BIN_SCHEMA: dict[str, dict[str, tuple[str, tuple[int, ...]]]] = {
    "bs": {"w": (_F32, ()), "conf": (_F32, ())},
    "avatar": {"opacity": (_F32, ()), "sh": (_F32, (3,)), "position": (_F32, (3,)),
               "rotation": (_F32, (4,)), "scale": (_F32, (3,))},
    "welcome.quant": {"pos_min": (_F32, ()), "pos_max": (_F32, ()), "log_scale": (_F32, ())},
    "frame.f32": {"position": (_F32, (3,)), "rotation": (_F32, (4,)), "scale": (_F32, (3,))},
    "frame.f16": {"position": ("float16", (3,)), "rotation": ("float16", (4,)), "scale": ("float16", (3,))},
    "frame.q13": {"position": ("uint16", (3,)), "rotation": ("uint32", ()), "scale": ("uint8", (3,))},
    "frame.delta": {"changed": ("uint8", ()), "moved_position": ("uint8", ()), "moved_rotation": ("uint8", ()),
                    "moved_scale": ("uint8", ()), "wide": ("uint8", ()), "position_delta": ("int8", (3,))},
}

# ----------------------------------------------------------------------------- fixed inputs

COUNT = 4
POSITION = np.array([[0.012, 0.034, 0.101], [-0.047, 0.062, 0.088],
                     [0.031, -0.015, 0.119], [0.005, 0.021, 0.143]], dtype=np.float32)
_ROT64 = np.array([[0.0, 0.0, 0.0, 1.0], [0.1, 0.2, 0.3, 0.9],
                   [0.2, -0.9, 0.1, 0.3], [-0.5, 0.5, -0.5, 0.5]])
ROTATION = (_ROT64 / np.sqrt((_ROT64 ** 2).sum(1, keepdims=True))).astype(np.float32)
SCALE = np.array([[0.0012, 0.0021, 0.0009], [0.003, 0.0025, 0.0011],
                  [0.0008, 0.0016, 0.0045], [0.02, 0.011, 0.0055]], dtype=np.float32)
OPACITY = np.array([0.9, 0.5, 0.25, 1.0], dtype=np.float32)
SH_DEGREE = 1
SH = ((np.arange(COUNT * 4 * 3, dtype=np.float64).reshape(COUNT, 4, 3) - 20) / 64).astype(np.float32)
QUANT = Quant(pos_min=np.array([-0.1, -0.1, -0.05], dtype=np.float32),
              pos_max=np.array([0.1, 0.15, 0.2], dtype=np.float32),
              log_scale=np.array([-9.0, -2.0], dtype=np.float32))
SPARSE_INDEX = np.array([1, 3], dtype=np.uint32)
TIMING = {"decode": 12, "map": 9, "epm": 41, "head": 180, "deform": 230, "encode": 95, "total": 597}
SEQ, T = 42, 1_700_000_000_123_456
W52 = (np.arange(52, dtype=np.float32) / 64).astype(np.float32)
W63 = (np.arange(63, dtype=np.float32) / 64).astype(np.float32)
CONF = np.array([0.75, 0.25], dtype=np.float32)


def _frame_format(encoding: str, sparse: bool) -> FrameFormat:
    return FrameFormat(encoding=encoding, count=COUNT, sparse=sparse, quant=QUANT if encoding == "q13" else None)


def _frame(sparse: bool) -> Frame:
    if not sparse:
        return Frame(seq=SEQ, t=T, timing=TIMING, position=POSITION, rotation=ROTATION, scale=SCALE)
    i = SPARSE_INDEX
    return Frame(seq=SEQ, t=T, timing=TIMING, index=i, position=POSITION[i], rotation=ROTATION[i],
                 scale=SCALE[i])


def _check_scale_margin() -> None:
    """The q13 scale encoder uses float32 log; keep inputs away from rounding ties so that every
    platform's log gives the same codes."""
    lmin, lmax = (float(v) for v in QUANT.log_scale)
    x = (np.log(SCALE.astype(np.float64)) - lmin) * (SCALE_LEVELS / (lmax - lmin))
    frac = np.abs(x - np.floor(x) - 0.5)
    assert (frac > 0.01).all(), "a q13 test scale sits on a rounding tie; pick another value"


# ----------------------------------------------------------------------------- description


def _describe_bins(m: dict[str, Any], schema: dict[str, tuple[str, tuple[int, ...]]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in m.items():
        if isinstance(v, bytes) and k in schema:
            dtype, tail = schema[k]
            a = np.frombuffer(v, dtype=np.dtype(dtype).newbyteorder("<"))
            shape = (-1, *tail) if tail else (-1,)
            a = a.reshape(shape)
            out[k] = {"dtype": dtype, "shape": list(a.shape), "values": a.tolist()}
        else:
            out[k] = v
    return out


def describe(data: bytes, encoding: str | None = None) -> dict[str, Any]:
    """JSON-able view of a valid message's wire map (bin fields as typed arrays)."""
    m = msgpack.unpackb(data, raw=False)
    t = m["type"]
    if t == "frame":
        assert encoding is not None
        schema = BIN_SCHEMA[f"frame.{encoding}"] | {"index": ("uint32", ())} | BIN_SCHEMA["frame.delta"]
        return _describe_bins(m, schema)
    if t in ("welcome", "join") and "quant" in m:
        m = dict(m, quant=_describe_bins(m["quant"], BIN_SCHEMA["welcome.quant"]))
    if t == "avatar":  # sh is n x K x 3
        k = (m["sh_degree"] + 1) ** 2
        return _describe_bins(m, BIN_SCHEMA["avatar"] | {"sh": (_F32, (k, 3))})
    return _describe_bins(m, BIN_SCHEMA.get(t, {}))


def _format_json(fmt: FrameFormat) -> dict[str, Any]:
    q = None
    if fmt.quant is not None:
        q = {"pos_min": fmt.quant.pos_min.tolist(), "pos_max": fmt.quant.pos_max.tolist(),
             "log_scale": fmt.quant.log_scale.tolist()}
    out = {"encoding": fmt.encoding, "count": fmt.count, "sparse": fmt.sparse, "quant": q}
    if fmt.delta:
        out["delta"] = True
    return out


# ----------------------------------------------------------------------------- the vectors


def _valid(name: str, direction: str, data: bytes, note: str, fmt: FrameFormat | None = None,
           decoded: Frame | None = None, after: list[str] | None = None) -> tuple[str, bytes, dict[str, Any]]:
    d: dict[str, Any] = {"name": name, "direction": direction, "type": msgpack.unpackb(data)["type"],
                         "note": note, "size": len(data), "hex": data.hex()}
    if fmt is not None:
        d["format"] = _format_json(fmt)
    d["fields"] = describe(data, fmt.encoding if fmt else None)
    if after is not None:
        d["after"] = after  # delta frames: apply these vectors first; `decoded` is then every Gaussian's state
    if decoded is not None:
        d["decoded"] = {"position": decoded.position.tolist(), "rotation": decoded.rotation.tolist(),
                        "scale": decoded.scale.tolist()}
    return name, data, d


def _invalid(name: str, direction: str, data: bytes, code: str, note: str,
             layout: str | None = None, fmt: FrameFormat | None = None) -> tuple[str, bytes, dict[str, Any]]:
    context: dict[str, Any] | None = None
    if layout is not None:
        context = {"layout": layout}
    elif fmt is not None:
        context = {"format": _format_json(fmt)}
    return name, data, {"name": name, "direction": direction, "note": note, "size": len(data),
                        "hex": data.hex(), "context": context, "expect_error": {"code": code}}


def build_vectors() -> list[tuple[str, bytes, dict[str, Any]]]:
    """All vectors as (name, msgpack bytes, JSON description), in documentation order."""
    from ofera_protocol.codec import decode_frame, unpack_message

    _check_scale_margin()
    out = [
        _valid("hello_minimal", C2S, pack_map({"type": "hello", "protocol": 1, "layout": "arkit52"}),
               "smallest valid hello: every optional field takes its default"),
        _valid("hello_full", C2S, encode(Hello(layout="ovr63", avatar="default", encoding="q13", coords="unity",
                                               sparse=True, device="quest_pro", token="s3cr3t",
                                               max_gaussians=50000)),
               "hello with every field"),
        _valid("bs", C2S, encode(Blendshapes(seq=SEQ, t=T, w=W52)), "arkit52 weights i/64"),
        _valid("bs_conf", C2S, encode(Blendshapes(seq=SEQ, t=T, w=W63, conf=CONF)),
               "ovr63 weights i/64 with the optional face confidence: lower 0.75, upper 0.25"),
        _valid("ping", C2S, encode(Ping(t=T)), "ping"),
        _valid("bye", C2S, encode(Bye()), "bye"),
        _valid("hello_delta", C2S, encode(Hello(layout="arkit52", encoding="q13", delta=True)),
               "hello asking for q13 temporal deltas"),
        _valid("resync", C2S, encode(Resync()), "resync: a delta-session client asks for a key frame"),
        _valid("welcome", S2C, encode(Welcome(session="s-0001", avatar=AvatarInfo("default", COUNT, SH_DEGREE),
                                              layout="arkit52", server="ofera/0.1.0")),
               "welcome for an f32, dense, FLAME-coordinates session"),
        _valid("welcome_q13", S2C, encode(Welcome(session="s-0002", avatar=AvatarInfo("default", COUNT, SH_DEGREE),
                                                  layout="ovr63", encoding="q13", coords="unity", sparse=True,
                                                  quant=QUANT, server="ofera/0.1.0")),
               "welcome for a q13, sparse, Unity-coordinates session, with quantisation parameters"),
        _valid("welcome_delta", S2C, encode(Welcome(session="s-0003", avatar=AvatarInfo("default", COUNT, SH_DEGREE),
                                                    layout="arkit52", encoding="q13", quant=QUANT, delta=True,
                                                    server="ofera/0.1.0")),
               "welcome for a q13 delta session (dense, FLAME coordinates)"),
    ]
    avatar = Avatar(opacity=OPACITY, sh=SH, position=POSITION, rotation=ROTATION, scale=SCALE)
    out.append(_valid("avatar", S2C, encode_avatar_chunk(split_avatar(avatar)[0]),
                      "the whole 4-Gaussian avatar (SH degree 1) in one chunk"))
    for c in split_avatar(avatar, max_chunk_bytes=2 * avatar_bytes_per_gaussian(SH_DEGREE)):
        out.append(_valid(f"avatar_chunk{c.chunk}", S2C, encode_avatar_chunk(c),
                          f"the same avatar in 2 chunks: chunk {c.chunk}"))
    for encoding in ("f32", "f16", "q13"):
        for sparse in (False, True):
            fmt = _frame_format(encoding, sparse)
            data = encode(_frame(sparse), fmt)
            decoded = decode_frame(unpack_message(data, len(data)), fmt)
            name = f"frame_{encoding}" + ("_sparse" if sparse else "")
            note = f"{'sparse' if sparse else 'dense'} frame in {encoding}" + (
                ": Gaussians 1 and 3" if sparse else "")
            out.append(_valid(name, S2C, data, note, fmt, decoded))
    out += _delta_vectors()
    out += [
        _valid("error", S2C, encode(ErrorMessage("bad_length", "bs: field 'w' has 204 bytes; layout arkit52 "
                                                 "needs 52 float32 = 208 bytes", False, seq=SEQ)),
               "non-fatal error about one bs"),
        _valid("error_fatal", S2C, encode(ErrorMessage("unsupported_protocol", "protocol 2 is not supported; "
                                                       "this server speaks protocol 1", True)),
               "fatal error; the server then closes with 4010"),
        _valid("pong", S2C, encode(Pong(t=T)), "pong"),
    ]
    out += _room_vectors(avatar)
    out += params_vectors(SEQ, T, TIMING)  # PROTOCOL.md 13
    out += _invalid_vectors()
    return out


ROOM, ROOM_SECRET, MEMBER, OTHER = "lab-1", b"room-secret", "m-5f2a9c1e0b7d", "m-03c8e1aa42f6"


def room_token(secret: bytes, room: str) -> str:
    """A room's token (PROTOCOL.md 12.1): lowercase hex HMAC-SHA256 of the room name (UTF-8) under the secret."""
    import hashlib
    import hmac

    return hmac.new(secret, room.encode(), hashlib.sha256).hexdigest()


def _room_vectors(avatar: Avatar) -> list[tuple[str, bytes, dict[str, Any]]]:
    """Rooms (PROTOCOL.md 12): hello, welcome, join, member avatar and frames, leave."""
    info = AvatarInfo("default", COUNT, SH_DEGREE)
    q13 = _frame_format("q13", False)
    f16_sparse = _frame_format("f16", True)
    chunk = split_avatar(avatar)[0]
    chunk.member = OTHER
    frame = _frame(False)
    frame.member = OTHER
    sparse = _frame(True)
    sparse.member = OTHER
    return [
        _valid("hello_room", C2S, encode(Hello(layout="arkit52", avatar="default", encoding="q13", room=ROOM,
                                               self=True, room_token=room_token(ROOM_SECRET, ROOM))),
               f"hello joining room {ROOM!r} to publish, also receiving its own avatar, with the room token of "
               f"secret {ROOM_SECRET.decode()!r}"),
        _valid("hello_room_watch", C2S, encode(Hello(layout="arkit52", room=ROOM, publish=False)),
               f"hello watching room {ROOM!r} (watch only: no bs, no avatar of its own)"),
        _valid("welcome_room", S2C, encode(Welcome(session="s-0004", avatar=info, layout="arkit52", encoding="q13",
                                                   server="ofera/0.1.0", room=ROOM, member=MEMBER)),
               "welcome of a publishing room member (q13): its member id; the quantisation comes with each join"),
        _valid("welcome_room_watch", S2C, encode(Welcome(session="s-0005", avatar=None, layout="arkit52",
                                                         server="ofera/0.1.0", room=ROOM, member=OTHER)),
               "welcome of a watch-only room member: no avatar"),
        _valid("join", S2C, encode(Join(member=OTHER, avatar=info, quant=QUANT)),
               "join of a publishing member, sent to a q13 viewer (its avatar's quantisation parameters)"),
        _valid("join_f16", S2C, encode(Join(member=OTHER, avatar=info)),
               "join of a publishing member, sent to an f16 viewer"),
        _valid("join_watch", S2C, encode(Join(member=MEMBER, publish=False)), "join of a watch-only member"),
        _valid("avatar_member", S2C, encode_avatar_chunk(chunk),
               "the joined member's avatar (the 4 Gaussians of `avatar`) in one chunk"),
        _valid("frame_q13_member", S2C, encode(frame, q13), "a frame of a room member in q13 (dense)", q13,
               _decoded(frame, q13)),
        _valid("frame_f16_sparse_member", S2C, encode(sparse, f16_sparse),
               "a sparse frame of a room member in f16: Gaussians 1 and 3", f16_sparse, _decoded(sparse, f16_sparse)),
        _valid("leave", S2C, encode(Leave(member=OTHER, reason="bye")), "the member left the room (it sent bye)"),
    ]


def _decoded(frame: Frame, fmt: FrameFormat) -> Frame:
    from ofera_protocol.codec import decode_frame, unpack_message

    data = encode(frame, fmt)
    return decode_frame(unpack_message(data, len(data)), fmt)


def _delta_motion() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Inputs of the delta vectors: frames A (the avatar), B, C, D. From A to B Gaussian 1 moves 0.2 mm in x
    (a narrow change), Gaussian 2 turns 2 degrees about z, Gaussian 3 moves 1 mm in y (wide) and grows 10 %;
    C (dropped: never sent) moves Gaussian 0 by 0.5 mm in x; D moves it 0.6 mm in x from A and Gaussian 1
    back by 0.1 mm, so D's delta is against B, what the client holds."""
    a = (POSITION.astype(np.float64), _ROT64 / np.sqrt((_ROT64 ** 2).sum(1, keepdims=True)), SCALE.astype(np.float64))
    half = np.radians(2.0) / 2
    turn = np.array([0.0, 0.0, np.sin(half), np.cos(half)])

    def hamilton(q: np.ndarray, r: np.ndarray) -> np.ndarray:  # q r, both (x, y, z, w)
        (x1, y1, z1, w1), (x2, y2, z2, w2) = q, r
        return np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                         w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])

    p, r, s = (x.copy() for x in a)
    p[1, 0] += 2e-4
    r[2] = hamilton(turn, r[2])
    p[3, 1] += 1e-3
    s[3] *= 1.1
    b = (p, r, s)
    c = (p.copy(), r, s)
    c[0][0, 0] += 5e-4
    d = (p.copy(), r, s)
    d[0][0, 0] += 6e-4
    d[0][1, 0] -= 1e-4
    return [tuple(x.astype(np.float32) for x in f) for f in (a, b, c, d)]


def _delta_vectors() -> list[tuple[str, bytes, dict[str, Any]]]:
    """Key frame, delta frame, and the delta frame after a drop, for q13 and f16 (reference encoder)."""
    from ofera_protocol.codec import decode_frame, unpack_message
    from ofera_protocol.delta import DeltaDecoder, DeltaEncoder

    out = []
    frames = _delta_motion()
    for encoding in ("q13", "f16"):
        fmt = FrameFormat(encoding=encoding, count=COUNT, quant=QUANT if encoding == "q13" else None, delta=True)
        enc = DeltaEncoder(fmt, "flame", key_interval=0)
        dec = DeltaDecoder(fmt)
        names = [f"frame_{encoding}_key", f"frame_{encoding}_delta", f"frame_{encoding}_delta_drop"]
        notes = [f"key frame of a {encoding} delta session (frame A: the avatar's values)",
                 f"delta frame B against A in {encoding}: Gaussian 1 moved 0.2 mm (a narrow change), 2 turned 2 "
                 "degrees (its rotation only), 3 moved 1 mm (wide) and grew 10 %",
                 f"delta frame D in {encoding} after frame C was dropped (never sent): against B, what the client "
                 "holds; Gaussian 0 moved 0.6 mm (wide), 1 moved back 0.1 mm"]
        state = None
        for i, f in enumerate((frames[0], frames[1], frames[3])):  # frames[2] (C) is dropped: never encoded
            data = enc.encode(SEQ + (0, 1, 3)[i], T + (0, 1, 3)[i], TIMING, *f)
            msg = decode_frame(unpack_message(data, len(data)), fmt)
            if i == 0:
                dec.key(msg)
                state = [a.copy() for a in (msg.position, msg.rotation, msg.scale)]
            else:
                got = dec.apply(msg)
                for a, b in zip(state, (got.position, got.rotation, got.scale), strict=True):
                    a[got.index] = b
            decoded = Frame(seq=0, t=0, position=state[0], rotation=state[1], scale=state[2])
            out.append(_valid(names[i], S2C, data, notes[i], fmt, decoded, after=names[:i] if i else None))
    return out


def _invalid_vectors() -> list[tuple[str, bytes, dict[str, Any]]]:
    f32 = _frame_format("f32", False)
    f32_sparse = _frame_format("f32", True)
    frame = encode(_frame(False), f32)
    nan_pos = POSITION.copy()
    nan_pos[2, 1] = np.nan
    short_frame = pack_map({"type": "frame", "seq": 1, "t": 0, "timing": {}, "n": COUNT,
                            "position": POSITION.reshape(-1)[:-1], "rotation": ROTATION, "scale": SCALE})
    unsorted = pack_map({"type": "frame", "seq": 1, "t": 0, "timing": {}, "n": 2,
                         "index": np.array([3, 1], dtype="<u4"), "position": POSITION[:2],
                         "rotation": ROTATION[:2], "scale": SCALE[:2]})
    q13_delta = FrameFormat(encoding="q13", count=COUNT, quant=QUANT, delta=True)
    one, zero = np.array([1], np.uint8), np.array([0], np.uint8)
    delta = {"type": "frame", "seq": 1, "t": 0, "timing": {}, "key": False, "n": 1,
             "changed": np.array([0x01], np.uint8), "moved_position": one, "moved_rotation": one, "moved_scale": zero,
             "wide": zero, "position_delta": np.array([[3, -2, 0]], np.int8), "position": np.zeros((0, 3), "<u2"),
             "rotation": np.array([3 << 30], "<u4"), "scale": np.zeros((0, 3), np.uint8)}
    deep: Any = {"x": 1}
    for _ in range(5):
        deep = {"x": deep}
    return [
        _invalid("invalid_not_a_map", C2S, msgpack.packb([1, 2, 3]), "malformed", "a msgpack array"),
        _invalid("invalid_truncated", S2C, frame[:-5], "malformed", "frame_f32 without its last 5 bytes", fmt=f32),
        _invalid("invalid_trailing_bytes", C2S, encode(Ping(t=1)) + b"\x00", "malformed", "ping + one extra byte"),
        _invalid("invalid_non_string_key", C2S, msgpack.packb({"type": "ping", 1: 2}), "malformed",
                 "an integer map key"),
        _invalid("invalid_deep_nesting", C2S, pack_map({"type": "ping", "t": 1, "x": deep}), "malformed",
                 "maps nested 7 deep"),
        _invalid("invalid_huge_bin", C2S, b"\x82\xa4type\xa2bs\xa1w\xc6\xff\xff\xff\xff", "malformed",
                 "declares a 4 GiB bin in 16 bytes"),
        _invalid("invalid_missing_type", C2S, pack_map({"t": 1}), "bad_field", "no type"),
        _invalid("invalid_unknown_type", C2S, pack_map({"type": "teleport"}), "unknown_type", "type teleport"),
        _invalid("invalid_hello_protocol", C2S, encode(Hello(layout="arkit52", protocol=2)),
                 "unsupported_protocol", "hello with protocol 2"),
        _invalid("invalid_hello_layout", C2S, pack_map({"type": "hello", "protocol": 1, "layout": "arkit99"}),
                 "unknown_layout", "hello with layout arkit99"),
        _invalid("invalid_hello_encoding", C2S, pack_map({"type": "hello", "protocol": 1, "layout": "arkit52",
                                                          "encoding": "png"}),
                 "unknown_encoding", "hello with encoding png"),
        _invalid("invalid_hello_room_name", C2S, encode(Hello(layout="arkit52", room="lab 1")), "bad_field",
                 "room name with a space"),
        _invalid("invalid_hello_room_avatar", C2S, pack_map({"type": "hello", "protocol": 1, "layout": "arkit52",
                                                             "room": ROOM}),
                 "bad_field", "publishing in a room without naming the avatar"),
        _invalid("invalid_hello_sparse_type", C2S, pack_map({"type": "hello", "protocol": 1, "layout": "arkit52",
                                                             "sparse": 1}),
                 "bad_field", "sparse must be a bool"),
        _invalid("invalid_bs_length", C2S, encode(Blendshapes(seq=1, t=0, w=W52[:51])), "bad_length",
                 "51 weights in an arkit52 session", layout="arkit52"),
        _invalid("invalid_bs_nan", C2S, encode(Blendshapes(seq=1, t=0, w=np.where(np.arange(52) == 7, np.nan, W52))),
                 "non_finite", "weight 7 is NaN", layout="arkit52"),
        _invalid("invalid_bs_seq_type", C2S, pack_map({"type": "bs", "seq": 1.0, "t": 0, "w": W52}), "bad_field",
                 "seq is a float", layout="arkit52"),
        _invalid("invalid_frame_length", S2C, short_frame, "bad_length", "position 4 bytes short", fmt=f32),
        _invalid("invalid_frame_nan", S2C, pack_map({"type": "frame", "seq": 1, "t": 0, "timing": {}, "n": COUNT,
                                                     "position": nan_pos, "rotation": ROTATION, "scale": SCALE}),
                 "non_finite", "a NaN position", fmt=f32),
        _invalid("invalid_frame_index_unsorted", S2C, unsorted, "bad_field", "index [3, 1]", fmt=f32_sparse),
        _invalid("invalid_delta_count", S2C, pack_map({**delta, "n": 2}), "bad_field",
                 "delta frame with n = 2, 'changed' marks 1", fmt=q13_delta),
        _invalid("invalid_delta_padding", S2C, pack_map({**delta, "changed": np.array([0x21], np.uint8)}),
                 "bad_field", "delta frame with a bit set beyond the 4 Gaussians", fmt=q13_delta),
        _invalid("invalid_delta_length", S2C, pack_map({**delta, "position_delta": np.zeros((2, 3), np.int8)}),
                 "bad_length", "delta frame: 2 position changes for 1 narrow Gaussian", fmt=q13_delta),
    ]


# ----------------------------------------------------------------------------- files


_NUMBER_LIST = re.compile(r"\[\s*([-+0-9.eE,\s]+?)\s*\]")


def json_text(d: dict[str, Any]) -> str:
    """Indented JSON with every innermost list of numbers on one line."""
    text = json.dumps(d, indent=2, ensure_ascii=True)
    text = _NUMBER_LIST.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    return text + "\n"


def _hex_block(data: bytes, width: int = 32) -> str:
    return "\n".join(data[i:i + width].hex(" ") for i in range(0, len(data), width))


def render_examples(vectors: list[tuple[str, bytes, dict[str, Any]]]) -> str:
    """The generated "Worked examples" section of PROTOCOL.md (between BEGIN and END)."""
    lines = [BEGIN, ""]
    for name, data, d in vectors:
        if name.startswith("invalid_"):
            continue
        note = d["note"][0].upper() + d["note"][1:]
        lines += [f"#### `{name}` ({d['direction'].replace('_', ' ')}, {len(data)} B)", "", note + ".", "",
                  "```", _hex_block(data), "```", ""]
    lines += ["#### Invalid inputs", "", "| vector | bytes | receiver context | expected `code` |",
              "|---|---|---|---|"]
    for name, data, d in vectors:
        if not name.startswith("invalid_"):
            continue
        ctx = d["context"]
        ctx_s = "-" if ctx is None else (f"layout {ctx['layout']}" if "layout" in ctx else
                                         f"{ctx['format']['encoding']}, count {ctx['format']['count']}"
                                         + (", sparse" if ctx["format"]["sparse"] else ""))
        shown = data.hex(" ") if len(data) <= 24 else data[:16].hex(" ") + " ..."
        lines.append(f"| `{name}`: {d['note']} | `{shown}` | {ctx_s} | `{d['expect_error']['code']}` |")
    lines += ["", END]
    return "\n".join(lines)


def update_protocol_md(text: str, section: str) -> str:
    a, b = text.index(BEGIN), text.index(END) + len(END)
    return text[:a] + section + text[b:]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="verify instead of writing")
    args = ap.parse_args(argv)
    vectors = build_vectors()
    expected: dict[Path, bytes] = {}
    for name, data, d in vectors:
        expected[VECTOR_DIR / f"{name}.msgpack"] = data
        expected[VECTOR_DIR / f"{name}.json"] = json_text(d).encode()
    md = PROTOCOL_MD.read_text(encoding="utf-8")
    expected[PROTOCOL_MD] = update_markdown(update_protocol_md(md, render_examples(vectors))).encode()
    expected[VECTOR_DIR / "tables.json"] = json_text(tables()).encode()  # the tables the C# and JS tests check
    expected[VECTOR_DIR / "rig_tiny_frames.json"] = json_text(rig_frames(SEQ, T, TIMING)).encode()  # PROTOCOL.md 13
    stale = [p for p, b in expected.items() if not p.exists() or p.read_bytes() != b]
    extra = [p for p in VECTOR_DIR.glob("*") if p not in expected] if VECTOR_DIR.exists() else []
    if args.check:
        for p in stale + extra:
            print(f"out of date: {p.relative_to(HERE.parent)}")
        return 1 if stale or extra else 0
    VECTOR_DIR.mkdir(exist_ok=True)
    for p in extra:
        p.unlink()
    for p in stale:
        p.write_bytes(expected[p])
    print(f"{len(vectors)} vectors in {VECTOR_DIR.relative_to(HERE.parent)}; {len(stale)} file(s) written, "
          f"{len(extra)} removed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
