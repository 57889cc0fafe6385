"""Encode and decode every message of protocol v1 (bytes <-> typed messages), with strict validation.

Decoders raise only ProtocolError, with the exact code and a message naming the field. Encoders
write small fields with msgpack and append numeric arrays as raw `bin` payloads, so a frame's big
arrays are copied once (into the returned bytes) after their encoding.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable, Mapping
from typing import Any

import msgpack
import numpy as np

from . import _fields as F
from .avatar import sh_coeffs
from .constants import (
    COORDS,
    HELLO_ENCODINGS,
    INT64_MAX,
    LAYOUTS,
    MAX_CLIENT_MESSAGE,
    MAX_CONTAINER_LEN,
    MAX_DEPTH,
    MAX_ID_LEN,
    MAX_SERVER_MESSAGE,
    MAX_SH_DEGREE,
    MAX_STR_LEN,
    MAX_TIMING_STAGES,
    PARAMS,
    PROTOCOL_VERSION,
    ROOM_NAME,
    UINT32_MAX,
)
from .encodings import FrameFormat, decode_arrays, encode_arrays, validate_quant
from .errors import (
    BAD_FIELD,
    BAD_LENGTH,
    MALFORMED,
    MESSAGE_TOO_LARGE,
    NON_FINITE,
    NOT_READY,
    UNKNOWN_ENCODING,
    UNKNOWN_LAYOUT,
    UNKNOWN_TYPE,
    UNSUPPORTED_PROTOCOL,
    ProtocolError,
)
from .messages import (
    CLIENT_TYPES,
    SERVER_TYPES,
    AvatarChunk,
    AvatarInfo,
    Blendshapes,
    Bye,
    ClientMessage,
    DeltaFrame,
    ErrorMessage,
    Frame,
    FrameHeader,
    Hello,
    Join,
    Leave,
    Message,
    ParamsFormat,
    ParamsFrame,
    Ping,
    Pong,
    Quant,
    Resync,
    RigChunk,
    ServerMessage,
    Welcome,
)

# ============================================================================= packing


def _as_bin(value: Any) -> memoryview:
    """msgpack's ``default`` in :func:`pack_map`: a C-contiguous numpy array -> its raw bytes (a bin, no copy)."""
    if not isinstance(value, np.ndarray):  # numpy scalars too: they export buffers, but are not fields' arrays
        raise TypeError(f"cannot pack a {type(value).__name__}")
    if not value.flags.c_contiguous:
        raise ValueError("arrays must be C-contiguous to be packed as bin")
    return memoryview(value).cast("B") if value.size else b""  # (a view with a zero in its shape cannot be cast)


def pack_map(items: dict[str, Any]) -> bytes:
    """msgpack a map in key order; numpy arrays (C-contiguous, little-endian) become `bin`. One msgpack call: a
    frame's message is packed on a cold CPU, where a call per field cost ~80 us more (benchmarks/cold_cache.py)."""
    return msgpack.packb(items, use_bin_type=True, default=_as_bin)


class MessagePacker:
    """:func:`pack_map` into reused msgpack buffers, for the large messages of one stream (delta and key frames):
    returns a memoryview of a ``msgpack.Packer``'s own buffer, the same bytes, with no bytes object made and no
    buffer grown per message. A 500 kB delta frame took 66 against 190 us on a cold CPU (round eleven). A Packer
    is reused only once nothing references its view (msgpack refuses to reset an exported buffer), so a message
    may be kept or handed to another thread; the pool grows by one Packer per message still held."""

    def __init__(self) -> None:
        self._packers: list[msgpack.Packer] = []

    def pack(self, items: dict[str, Any]) -> memoryview:
        for packer in self._packers:
            try:
                packer.reset()
            except BufferError:  # its last message is still referenced
                continue
            break
        else:
            packer = msgpack.Packer(use_bin_type=True, autoreset=False, default=_as_bin)
            self._packers.append(packer)
        packer.pack(items)
        return packer.getbuffer()


def pack_bits(mask: np.ndarray) -> np.ndarray:
    """(n,) bool -> ceil(n / 8) uint8, bit i in byte i >> 3 at position i & 7 (LSB first)."""
    return np.packbits(np.asarray(mask, bool), bitorder="little")


def unpack_bits(buf: bytes, n: int, what: str) -> np.ndarray:
    """The inverse of :func:`pack_bits`; ProtocolError if the length is not ceil(n / 8) or a padding bit is set."""
    if len(buf) != (n + 7) // 8:
        raise ProtocolError(BAD_LENGTH, f"frame: '{what}' has {len(buf)} bytes, a mask of {n} needs {(n + 7) // 8}")
    bits = np.unpackbits(np.frombuffer(buf, np.uint8), bitorder="little")
    if bits[n:].any():
        raise ProtocolError(BAD_FIELD, f"frame: '{what}' has bits set beyond its {n} entries")
    return bits[:n].astype(bool)


def _le(a: Any, dtype: str, shape: tuple[int, ...], name: str) -> np.ndarray:
    out = np.ascontiguousarray(a, dtype=dtype)
    if out.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {out.shape}")
    return out


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if v is not None}


# ============================================================================= encoders


def encode_hello(m: Hello) -> bytes:
    return pack_map(_drop_none({
        "type": "hello", "protocol": m.protocol, "layout": m.layout, "avatar": m.avatar,
        "encoding": m.encoding, "coords": m.coords, "sparse": m.sparse, "delta": m.delta or None, "device": m.device,
        "token": m.token, "max_gaussians": m.max_gaussians, "room": m.room,
        "publish": False if m.room is not None and not m.publish else None,
        "self": True if m.room is not None and m.self else None, "room_token": m.room_token,
    }))


def encode_bs(m: Blendshapes) -> bytes:
    """A bs message (pack_map's bytes; the weights copied as bytes, no hook call)."""
    w = np.ascontiguousarray(m.w, dtype="<f4")
    if w.ndim != 1:
        raise ValueError(f"bs.w must be 1-D, got shape {w.shape}")
    d: dict[str, Any] = {"type": "bs", "seq": m.seq, "t": m.t, "w": w.tobytes()}
    if m.conf is not None:
        d["conf"] = _le(m.conf, "<f4", (2,), "bs.conf").tobytes()
    return msgpack.packb(d, use_bin_type=True)


def _avatar_info(a: AvatarInfo) -> dict[str, Any]:
    return {"id": a.id, "count": a.count, "sh_degree": a.sh_degree, "expression": a.expression}


def encode_welcome(m: Welcome) -> bytes:
    d: dict[str, Any] = {"type": "welcome", "protocol": m.protocol, "session": m.session}
    if m.avatar is not None:
        d["avatar"] = _avatar_info(m.avatar)
    elif m.room is None:
        raise ValueError("welcome needs an avatar outside a (watch-only) room session")
    d |= {"layout": m.layout, "encoding": m.encoding, "coords": m.coords, "sparse": m.sparse}
    if m.delta:
        d["delta"] = True
    if m.quant is not None:
        d["quant"] = _quant_map(m.quant)
    if m.server is not None:
        d["server"] = m.server
    if m.rig_bytes is not None:  # params sessions (PROTOCOL.md 13)
        d["rig_bytes"] = m.rig_bytes
    if m.room is not None:
        if m.member is None:
            raise ValueError("a room session's welcome needs its member id")
        d["room"], d["member"] = m.room, m.member
    return pack_map(d)


def _quant_map(q: Quant) -> dict[str, Any]:
    validate_quant(q)
    return {"pos_min": q.pos_min.astype("<f4"), "pos_max": q.pos_max.astype("<f4"),
            "log_scale": q.log_scale.astype("<f4")}


def encode_join(m: Join) -> bytes:
    """`join` (rooms): a publishing member has `avatar` (and `quant` for a q13 viewer); a watch-only one neither."""
    if m.publish != (m.avatar is not None):
        raise ValueError("join: a publishing member has an avatar, a watch-only member none")
    d: dict[str, Any] = {"type": "join", "member": m.member}
    if m.avatar is not None:
        d["avatar"] = _avatar_info(m.avatar)
    if m.quant is not None:
        d["quant"] = _quant_map(m.quant)
    if not m.publish:
        d["publish"] = False
    return pack_map(d)

def encode_avatar_chunk(m: AvatarChunk) -> bytes:
    """`avatar` message; arrays are converted to float32 little-endian (no copy if they already are)."""
    n, k = m.n, sh_coeffs(m.sh_degree)
    member = {} if m.member is None else {"member": m.member}
    return pack_map({
        "type": "avatar", **member, "count": m.count, "sh_degree": m.sh_degree, "chunk": m.chunk,
        "chunks": m.chunks, "offset": m.offset, "n": n,
        "opacity": _le(m.opacity, "<f4", (n,), "opacity"), "sh": _le(m.sh, "<f4", (n, k, 3), "sh"),
        "position": _le(m.position, "<f4", (n, 3), "position"),
        "rotation": _le(m.rotation, "<f4", (n, 4), "rotation"), "scale": _le(m.scale, "<f4", (n, 3), "scale"),
    })


def encode_frame(m: Frame, fmt: FrameFormat) -> bytes:
    """`frame` in the session's encoding. Hot path: encoded arrays are copied once, into the result.

    A dense frame (index None) must carry fmt.count Gaussians; a sparse one needs fmt.sparse and an
    index (n,) of strictly ascending ids below fmt.count. ValueError on misuse.
    """
    n = m.n
    if m.position.shape != (n, 3) or m.rotation.shape != (n, 4) or m.scale.shape != (n, 3):
        raise ValueError(f"frame arrays must be (n, 3), (n, 4), (n, 3); got {m.position.shape}, "
                         f"{m.rotation.shape}, {m.scale.shape}")
    d: dict[str, Any] = {"type": "frame", "seq": m.seq, "t": m.t, "timing": m.timing, "n": n}
    if m.member is not None:  # rooms: after `type` (the fast writer's header does the same)
        d = {"type": "frame", "member": m.member, "seq": m.seq, "t": m.t, "timing": m.timing, "n": n}
    if fmt.delta:  # a key frame (delta frames come from delta.DeltaEncoder or encode_delta_frame)
        if m.key is False or m.index is not None:
            raise ValueError("a Frame of a delta session is a dense key frame")
        d = {"type": "frame", "seq": m.seq, "t": m.t, "timing": m.timing, "key": True, "n": n}
    if m.index is None:
        if n != fmt.count:
            raise ValueError(f"dense frame carries {n} Gaussians, the avatar has {fmt.count}")
    else:
        if not fmt.sparse:
            raise ValueError("frame has an index but the session is not sparse")
        index = _le(m.index, "<u4", (n,), "index")
        if n and (int(index[-1]) >= fmt.count or (n > 1 and not (np.diff(index.astype(np.int64)) > 0).all())):
            raise ValueError(f"index must be strictly ascending and below {fmt.count}")
        d["index"] = index
    d["position"], d["rotation"], d["scale"] = encode_arrays(fmt.encoding, m.position, m.rotation, m.scale,
                                                             fmt.quant)
    return pack_map(d)


def encode_delta_frame(m: DeltaFrame, fmt: FrameFormat) -> bytes:
    """A delta frame (PROTOCOL.md 7.1) from its wire arrays (see DeltaFrame)."""
    changed = np.zeros(fmt.count, bool)
    changed[np.asarray(m.index, np.int64)] = True
    moved = np.asarray(m.moved, bool).reshape(-1, 3)
    return pack_map({"type": "frame", "seq": m.seq, "t": m.t, "timing": m.timing, "key": False, "n": m.n,
                     "changed": pack_bits(changed), "moved_position": pack_bits(moved[:, 0]),
                     "moved_rotation": pack_bits(moved[:, 1]), "moved_scale": pack_bits(moved[:, 2]),
                     "wide": pack_bits(m.wide), "position_delta": np.ascontiguousarray(m.position_delta, np.int8),
                     "position": np.ascontiguousarray(m.position), "rotation": np.ascontiguousarray(m.rotation),
                     "scale": np.ascontiguousarray(m.scale)})


def encode_error(m: ErrorMessage) -> bytes:
    return pack_map(_drop_none({"type": "error", "code": m.code, "message": m.message, "fatal": m.fatal,
                                "seq": m.seq}))


def encode(m: Message, fmt: FrameFormat | None = None) -> bytes:
    """Encode any message; `fmt` is required for Frame."""
    if isinstance(m, Frame):
        if fmt is None:
            raise ValueError("encoding a frame needs the session's FrameFormat")
        return encode_frame(m, fmt)
    if isinstance(m, DeltaFrame):
        if fmt is None:
            raise ValueError("encoding a frame needs the session's FrameFormat")
        return encode_delta_frame(m, fmt)
    if isinstance(m, Hello):
        return encode_hello(m)
    if isinstance(m, Blendshapes):
        return encode_bs(m)
    if isinstance(m, (Ping, Pong)):
        return pack_map({"type": m.TYPE, "t": m.t})
    if isinstance(m, (Bye, Resync)):
        return pack_map({"type": m.TYPE})
    if isinstance(m, Welcome):
        return encode_welcome(m)
    if isinstance(m, AvatarChunk):
        return encode_avatar_chunk(m)
    if isinstance(m, ErrorMessage):
        return encode_error(m)
    if isinstance(m, Join):
        return encode_join(m)
    if isinstance(m, Leave):
        return pack_map({"type": "leave", "member": m.member, "reason": m.reason})
    if isinstance(m, RigChunk):
        return encode_rig_chunk(m)
    if isinstance(m, ParamsFrame):
        return encode_params_frame(m)
    raise TypeError(f"not a protocol message: {type(m).__name__}")


# ============================================================================= decoding


def _check_structure(obj: Any) -> None:
    """Nesting depth <= MAX_DEPTH and string keys everywhere (iterative; visits containers only)."""
    stack = [(obj, 1)]
    while stack:
        o, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise ProtocolError(MALFORMED, f"containers nested deeper than {MAX_DEPTH} levels")
        if isinstance(o, dict):
            for k, v in o.items():
                if type(k) is not str:
                    raise ProtocolError(MALFORMED, f"map key {k!r} is not a string")
                if isinstance(v, (dict, list)):
                    stack.append((v, depth + 1))
        else:
            stack.extend((v, depth + 1) for v in o if isinstance(v, (dict, list)))


def unpack_message(data: bytes | bytearray | memoryview, max_size: int) -> dict[str, Any]:
    """Bytes -> top-level map, refusing oversize input, huge declared lengths, ext types, trailing
    bytes, non-string keys and deep nesting without allocating them."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(MALFORMED, f"expected bytes, got {type(data).__name__}")
    size = memoryview(data).nbytes
    if size > max_size:
        raise ProtocolError(MESSAGE_TOO_LARGE, f"message of {size} bytes exceeds the limit of {max_size}")
    try:
        obj = msgpack.unpackb(
            data, raw=False, strict_map_key=True, use_list=True, max_bin_len=max_size,
            max_str_len=MAX_STR_LEN, max_array_len=MAX_CONTAINER_LEN,
            max_map_len=MAX_CONTAINER_LEN, max_ext_len=0,
        )
    except Exception as e:  # msgpack raises ValueError subclasses, UnicodeDecodeError, StackError...
        raise ProtocolError(MALFORMED, f"not a valid msgpack message: {type(e).__name__}: {e}") from None
    if not isinstance(obj, dict):
        raise ProtocolError(MALFORMED, f"message must be a msgpack map, got {F._type_name(obj)}")
    _check_structure(obj)
    return obj


def _message_type(m: dict[str, Any], known: dict[str, type], direction: str) -> str:
    t = F.get_str(m, "type", "message", max_len=MAX_ID_LEN)
    if t not in known:
        raise ProtocolError(UNKNOWN_TYPE, f"unknown {direction} message type {t!r}; expected one of "
                            f"{', '.join(known)}")
    return t


_ROOM_NAME = re.compile(ROOM_NAME)


def decode_room(m: dict[str, Any], where: str) -> str | None:
    """`hello.room`: None if absent, else a name of 1-64 of [A-Za-z0-9._-] (bad_field otherwise)."""
    room = F.get_str(m, "room", where, max_len=64, default=None)
    if room is not None and not _ROOM_NAME.fullmatch(room):
        raise ProtocolError(BAD_FIELD, f"{where}: field 'room' {room[:64]!r} may hold only letters, digits and . _ -")
    return room


def decode_hello(m: dict[str, Any]) -> Hello:
    w = "hello"
    protocol = F.get_int(m, "protocol", w)
    if protocol != PROTOCOL_VERSION:
        raise ProtocolError(UNSUPPORTED_PROTOCOL, f"protocol {protocol} is not supported; this server "
                            f"speaks protocol {PROTOCOL_VERSION}")
    room = decode_room(m, w)
    publish = F.get_bool(m, "publish", w, default=True)
    if room is not None and publish and m.get("avatar") is None:  # nil is absent (section 2)
        raise ProtocolError(BAD_FIELD, "hello: field 'avatar' is required to publish in a room (or send "
                            "'publish': false to watch)")
    watching = room is not None and not publish  # a watcher sends no bs: its layout is optional
    return Hello(
        protocol=protocol,
        room=room, publish=publish, self=F.get_bool(m, "self", w, default=False),
        room_token=F.get_str(m, "room_token", w, default=None),
        layout=F.get_choice(m, "layout", w, LAYOUTS, UNKNOWN_LAYOUT, **({"default": "arkit52"} if watching else {})),
        avatar=F.get_str(m, "avatar", w, default="default"),
        encoding=F.get_choice(m, "encoding", w, HELLO_ENCODINGS, UNKNOWN_ENCODING, default="f32"),
        coords=F.get_choice(m, "coords", w, COORDS, BAD_FIELD, default="flame"),
        sparse=F.get_bool(m, "sparse", w, default=False),
        delta=F.get_bool(m, "delta", w, default=False),
        device=F.get_str(m, "device", w, default=None),
        token=F.get_str(m, "token", w, max_len=MAX_STR_LEN, default=None),
        max_gaussians=F.get_int(m, "max_gaussians", w, lo=1, hi=UINT32_MAX, default=None),
    )


def conf_in_range(conf: np.ndarray) -> bool:
    """Whether a bs confidence's values all lie in [0, 1] (NaN does not). By Python builtins, not numpy: checked once
    per frame on a cold CPU (see _fields.SMALL_ARRAY)."""
    return all(0.0 <= v <= 1.0 for v in conf.tolist())


def decode_bs(m: dict[str, Any], layout: str | None) -> Blendshapes:
    w = "bs"
    seq = F.get_int(m, "seq", w, lo=0)
    t = F.get_int(m, "t", w)
    buf = F.get_bin(m, "w", w)
    if layout is not None:
        n = LAYOUTS[layout]
    elif len(buf) % 4 == 0 and len(buf) // 4 in LAYOUTS.values():
        n = len(buf) // 4
    else:
        raise ProtocolError(BAD_LENGTH, f"bs: field 'w' has {len(buf)} bytes, which is not 4 x the length "
                            f"of any layout ({', '.join(f'{k} {v}' for k, v in LAYOUTS.items())})")
    if len(buf) != 4 * n:
        raise ProtocolError(BAD_LENGTH, f"bs: field 'w' has {len(buf)} bytes; layout {layout} needs "
                            f"{n} float32 = {4 * n} bytes")
    weights = F.get_array(m, "w", w, "<f4", (n,))
    conf = F.get_array(m, "conf", w, "<f4", (2,), required=False)
    if conf is not None and not conf_in_range(conf):
        raise ProtocolError(BAD_FIELD, f"bs: field 'conf' = [{conf[0]:g}, {conf[1]:g}] (lower, upper face "
                            "confidence) is outside [0, 1]")
    return Blendshapes(seq=seq, t=t, w=weights, conf=conf)


def decode_client_message(data: bytes | bytearray | memoryview, layout: str | None = None,
                          max_size: int = MAX_CLIENT_MESSAGE) -> ClientMessage:
    """Decode a client -> server message. `layout` (the session's) fixes the length of `bs.w`;
    without it any known layout length is accepted. Raises ProtocolError."""
    m = unpack_message(data, max_size)
    t = _message_type(m, CLIENT_TYPES, "client")
    if t == "bs":
        return decode_bs(m, layout)
    if t == "hello":
        return decode_hello(m)
    if t == "ping":
        return Ping(t=F.get_int(m, "t", "ping"))
    if t == "resync":
        return Resync()
    return Bye()


def decode_quant(m: dict[str, Any]) -> Quant:
    w = "welcome.quant"
    q = Quant(pos_min=F.get_array(m, "pos_min", w, "<f4", (3,)).astype(np.float32),
              pos_max=F.get_array(m, "pos_max", w, "<f4", (3,)).astype(np.float32),
              log_scale=F.get_array(m, "log_scale", w, "<f4", (2,)).astype(np.float32))
    try:
        validate_quant(q)
    except ValueError as e:
        raise ProtocolError(BAD_FIELD, f"{w}: {e}") from None
    return q


def decode_welcome(m: dict[str, Any]) -> Welcome:
    w = "welcome"
    protocol = F.get_int(m, "protocol", w)
    if protocol != PROTOCOL_VERSION:
        raise ProtocolError(UNSUPPORTED_PROTOCOL, f"server speaks protocol {protocol}; this client "
                            f"speaks {PROTOCOL_VERSION}")
    room = decode_room(m, w)
    av = F.get_map(m, "avatar", w, required=room is None)  # a watch-only room session has none
    avatar = None if av is None else decode_avatar_info(av, "welcome.avatar")
    encoding = F.get_choice(m, "encoding", w, HELLO_ENCODINGS, UNKNOWN_ENCODING)
    qm = F.get_map(m, "quant", w, required=encoding == "q13" and room is None)  # rooms: quant per join
    return Welcome(
        protocol=protocol, session=F.get_str(m, "session", w), avatar=avatar,
        layout=F.get_choice(m, "layout", w, LAYOUTS, UNKNOWN_LAYOUT), encoding=encoding,
        coords=F.get_choice(m, "coords", w, COORDS, BAD_FIELD),
        sparse=F.get_bool(m, "sparse", w),
        quant=decode_quant(qm) if qm is not None and encoding == "q13" else None,
        server=F.get_str(m, "server", w, default=None),
        delta=F.get_bool(m, "delta", w, default=False),
        room=room, member=None if room is None else F.get_str(m, "member", w),
        rig_bytes=F.get_int(m, "rig_bytes", w, lo=0, hi=UINT32_MAX, default=None),
    )


def decode_avatar_info(av: dict[str, Any], w: str) -> AvatarInfo:
    return AvatarInfo(id=F.get_str(av, "id", w), count=F.get_int(av, "count", w, lo=0, hi=UINT32_MAX),
                      sh_degree=F.get_int(av, "sh_degree", w, lo=0, hi=MAX_SH_DEGREE),
                      expression=F.get_str(av, "expression", w, default="flame68"))


def decode_join(m: dict[str, Any]) -> Join:
    w = "join"
    publish = F.get_bool(m, "publish", w, default=True)
    av = F.get_map(m, "avatar", w, required=publish)
    if av is not None and not publish:
        raise ProtocolError(BAD_FIELD, "join: a watch-only member ('publish': false) has no 'avatar'")
    qm = F.get_map(m, "quant", w, required=False)
    return Join(member=F.get_str(m, "member", w), publish=publish,
                avatar=None if av is None else decode_avatar_info(av, "join.avatar"),
                quant=None if qm is None else decode_quant(qm))


def decode_avatar_chunk(m: dict[str, Any]) -> AvatarChunk:
    w = "avatar"
    count = F.get_int(m, "count", w, lo=0, hi=UINT32_MAX)
    deg = F.get_int(m, "sh_degree", w, lo=0, hi=MAX_SH_DEGREE)
    chunks = F.get_int(m, "chunks", w, lo=1, hi=UINT32_MAX)
    chunk = F.get_int(m, "chunk", w, lo=0, hi=chunks - 1)
    offset = F.get_int(m, "offset", w, lo=0, hi=count)
    n = F.get_int(m, "n", w, lo=0, hi=count - offset)
    opacity = F.get_array(m, "opacity", w, "<f4", (n,))
    if n and not ((opacity >= 0) & (opacity <= 1)).all():
        raise ProtocolError(BAD_FIELD, "avatar: field 'opacity' has values outside [0, 1]")
    return AvatarChunk(
        member=F.get_str(m, "member", w, default=None),
        count=count, sh_degree=deg, chunk=chunk, chunks=chunks, offset=offset, opacity=opacity,
        sh=F.get_array(m, "sh", w, "<f4", (n, sh_coeffs(deg), 3)),
        position=F.get_array(m, "position", w, "<f4", (n, 3)),
        rotation=F.get_array(m, "rotation", w, "<f4", (n, 4)),
        scale=F.get_array(m, "scale", w, "<f4", (n, 3)),
    )


def decode_timing(m: dict[str, Any]) -> dict[str, int]:
    tm = F.get_map(m, "timing", "frame")
    if len(tm) > MAX_TIMING_STAGES:
        raise ProtocolError(BAD_FIELD, f"frame: 'timing' has {len(tm)} stages, at most {MAX_TIMING_STAGES}")
    for k in tm:
        if len(k) > MAX_ID_LEN:
            raise ProtocolError(BAD_FIELD, f"frame: timing stage name longer than {MAX_ID_LEN}")
        F.get_int(tm, k, "frame.timing", lo=0, hi=INT64_MAX)
    return tm


_CODE_DTYPES = {"q13": ("<u2", "<u4", "u1"), "f16": ("<u2", "<u2", "<u2")}
_CODE_WIDTH = {"q13": (3, 1, 3), "f16": (3, 4, 3)}


DeltaMasks = tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int, int, int]]
"""A delta frame's masks: index (n,) uint32, moved (n, 3) bool, wide (n_p,) bool, and (n_p, n_r, n_s, wide ones)."""
MaskDecoder = Callable[[dict[str, Any], FrameFormat], DeltaMasks]
"""What turns a delta frame's map into its checked DeltaMasks: :func:`delta_masks` or a faster twin."""


def delta_masks(m: dict[str, Any], fmt: FrameFormat) -> DeltaMasks:
    """The masks of a delta frame, checked: lengths and padding, n = the number of changed Gaussians, every one
    carrying something. Raises ProtocolError."""
    w = "frame"
    n = F.get_int(m, "n", w, lo=0, hi=UINT32_MAX)
    changed = unpack_bits(F.get_bin(m, "changed", w), fmt.count, "changed")
    index = np.flatnonzero(changed).astype(np.uint32)
    if index.size != n:
        raise ProtocolError(BAD_FIELD, f"frame: n = {n} but 'changed' marks {index.size} Gaussians")
    moved = np.stack([unpack_bits(F.get_bin(m, k, w), n, k) for k in ("moved_position", "moved_rotation",
                                                                      "moved_scale")], axis=1)
    if n and not moved.any(axis=1).all():
        raise ProtocolError(BAD_FIELD, "frame: a changed Gaussian carries nothing (all its 'moved_*' bits are 0)")
    n_p, n_r, n_s = (int(c) for c in moved.sum(axis=0))
    wide = unpack_bits(F.get_bin(m, "wide", w), n_p, "wide")
    return index, moved, wide, (n_p, n_r, n_s, int(wide.sum()))


def decode_delta_frame(m: dict[str, Any], fmt: FrameFormat, seq: int, t: int, timing: dict[str, int],
                       masks: MaskDecoder = delta_masks) -> DeltaFrame:
    """The wire arrays of a delta frame (`key: false`), checked: the masks (`masks`: :func:`delta_masks` or a
    faster twin that gives the same or defers to it), array lengths; f16 codes sent whole must be finite.
    Raises ProtocolError."""
    from .encodings import FIELD_BYTES

    w = "frame"
    index, moved, wide, (n_p, n_r, n_s, nw) = masks(m, fmt)
    res = F.get_array(m, "position_delta", w, "i1", (n_p - nw, 3))
    pb, rb, sb = FIELD_BYTES[fmt.encoding]
    dts = _CODE_DTYPES[fmt.encoding] if fmt.encoding == "q13" else ("<f2", "<f2", "<f2")
    fields = (("position", nw, pb, dts[0], 3), ("rotation", n_r, rb, dts[1], 4 if rb == 8 else 1),
              ("scale", n_s, sb, dts[2], 3))
    arrays = []
    for key, count, size, dt, width in fields:
        buf = F.get_bin(m, key, w)
        if len(buf) != count * size:
            raise ProtocolError(BAD_LENGTH, f"frame field {key!r} has {len(buf)} bytes; {count} Gaussians in "
                                f"{fmt.encoding} need {count * size}")
        a = np.frombuffer(buf, dtype=dt)
        arrays.append(a.reshape(count, width) if width > 1 else a)
        if fmt.encoding == "f16" and ((a.view(np.uint16) & 0x7C00) == 0x7C00).any():
            raise ProtocolError(NON_FINITE, f"frame field {key!r} holds NaN or infinity")
    return DeltaFrame(seq=seq, t=t, timing=timing, index=index, moved=moved, wide=wide, position_delta=res,
                      position=arrays[0], rotation=arrays[1], scale=arrays[2])


FrameParts = tuple[int, int, dict[str, int], bool | None, int, Any, list[bytes]]


def frame_parts(m: dict[str, Any], fmt: FrameFormat,
                masks: MaskDecoder = delta_masks) -> FrameParts | DeltaFrame:
    """The checked fields of a `frame` map: (seq, t, timing, key, n, index, [position, rotation, scale] bins with
    their byte lengths checked), or the DeltaFrame of a delta frame (its masks by `masks`). Every decoder of
    frames starts here."""
    from .encodings import FIELD_BYTES

    w = "frame"
    seq = F.get_int(m, "seq", w, lo=0)
    t = F.get_int(m, "t", w)
    timing = decode_timing(m)
    key = None
    if fmt.delta:
        key = F.get_bool(m, "key", w)
        if not key:
            return decode_delta_frame(m, fmt, seq, t, timing, masks)
    n = F.get_int(m, "n", w, lo=0, hi=UINT32_MAX)
    index = F.get_array(m, "index", w, "<u4", (n,), required=False)
    if key and index is not None:
        raise ProtocolError(BAD_FIELD, "frame: a key frame is dense (no 'index')")
    if index is None:
        if n != fmt.count:
            raise ProtocolError(BAD_LENGTH, f"frame: dense frame carries n={n} Gaussians, the avatar "
                                f"has {fmt.count}")
    else:
        if not fmt.sparse:
            raise ProtocolError(BAD_FIELD, "frame: 'index' in a session that did not ask for sparse frames")
        if n and int(index[-1]) >= fmt.count:
            raise ProtocolError(BAD_FIELD, f"frame: index {int(index[-1])} >= avatar count {fmt.count}")
        if n > 1 and not (index[1:] > index[:-1]).all():
            raise ProtocolError(BAD_FIELD, "frame: 'index' must be strictly ascending")
    bufs = [F.get_bin(m, k, w) for k in ("position", "rotation", "scale")]
    for name, buf, size in zip(("position", "rotation", "scale"), bufs, FIELD_BYTES[fmt.encoding], strict=True):
        if len(buf) != n * size:
            raise ProtocolError(BAD_LENGTH, f"frame field {name!r} has {len(buf)} bytes; {n} Gaussians in "
                                f"{fmt.encoding} need {n * size}")
    return seq, t, timing, key, n, index, bufs


def decode_frame(m: dict[str, Any], fmt: FrameFormat) -> Frame | DeltaFrame:
    parts = frame_parts(m, fmt)
    if isinstance(parts, DeltaFrame):
        return parts
    seq, t, timing, key, n, index, bufs = parts
    p, r, s = decode_arrays(fmt.encoding, n, bufs[0], bufs[1], bufs[2], fmt.quant)
    codes = None
    if key:
        codes = tuple(np.frombuffer(b, dtype=dt) for b, dt in zip(bufs, _CODE_DTYPES[fmt.encoding], strict=True))
    return Frame(seq=seq, t=t, timing=timing, index=index, position=p, rotation=r, scale=s, key=key,
                 codes=codes, member=F.get_str(m, "member", "frame", default=None))  # type: ignore[arg-type]


def decode_server_message(data: bytes | bytearray | memoryview, fmt: FrameFormat | None = None,
                          max_size: int = MAX_SERVER_MESSAGE, members: Mapping[str, FrameFormat] | None = None
                          ) -> ServerMessage:
    """Decode a server -> client message. `fmt` (from `welcome`) is needed for frames; a frame
    without it raises `not_ready`. Room sessions: `members` maps each member (joined, avatar complete) to the
    FrameFormat of its frames (`member_format`); a frame of another member raises a non-fatal `not_ready`.
    Raises ProtocolError."""
    m = unpack_message(data, max_size)
    t = _message_type(m, SERVER_TYPES, "server")
    if t == "frame":
        if members is not None and "member" in m:
            member = F.get_str(m, "member", "frame")
            fmt = members.get(member)
            if fmt is None:
                raise ProtocolError(NOT_READY, f"frame of member {member[:64]!r} before its join and avatar", False)
        if fmt is None:
            raise ProtocolError(NOT_READY, "frame before welcome: the session's format is unknown")
        if isinstance(fmt, ParamsFormat):
            return decode_params_frame(m, fmt)
        return decode_frame(m, fmt)
    if t == "rig":
        return decode_rig_chunk(m)
    if t == "avatar":
        return decode_avatar_chunk(m)
    if t == "welcome":
        return decode_welcome(m)
    if t == "join":
        return decode_join(m)
    if t == "leave":
        return Leave(member=F.get_str(m, "member", "leave"), reason=F.get_str(m, "reason", "leave"))
    if t == "error":
        w = "error"
        return ErrorMessage(code=F.get_str(m, "code", w), message=F.get_str(m, "message", w,
                            max_len=MAX_STR_LEN, min_len=0), fatal=F.get_bool(m, "fatal", w),
                            seq=F.get_int(m, "seq", w, lo=0, default=None))
    return Pong(t=F.get_int(m, "t", "pong"))


# ============================================================================= header-only reading

_SCALARS = {0xc0: None, 0xc2: False, 0xc3: True}
_FIXED = {0xcc: ">B", 0xcd: ">H", 0xce: ">I", 0xcf: ">Q", 0xd0: ">b", 0xd1: ">h", 0xd2: ">i", 0xd3: ">q",
          0xca: ">f", 0xcb: ">d"}
_SIZED = {0xd9: (1, "str"), 0xda: (2, "str"), 0xdb: (4, "str"), 0xc4: (1, "bin"), 0xc5: (2, "bin"),
          0xc6: (4, "bin"), 0xdc: (2, "array"), 0xdd: (4, "array"), 0xde: (2, "map"), 0xdf: (4, "map")}


def _truncated() -> ProtocolError:
    return ProtocolError(MALFORMED, "not a valid msgpack message: truncated")


def _skim(buf: memoryview, pos: int, depth: int) -> tuple[Any, int]:
    """One msgpack value at `pos` -> (value, end). A `bin` comes back as a memoryview of `buf` (neither copied nor
    read); the limits are those of unpack_message."""
    if pos >= len(buf):
        raise _truncated()
    b = buf[pos]
    pos += 1
    if b < 0x80:
        return b, pos
    if b >= 0xe0:
        return b - 0x100, pos
    if b in _SCALARS:
        return _SCALARS[b], pos
    if b in _FIXED:
        fmt = _FIXED[b]
        if pos + struct.calcsize(fmt) > len(buf):
            raise _truncated()
        return struct.unpack_from(fmt, buf, pos)[0], pos + struct.calcsize(fmt)
    if 0xa0 <= b <= 0xbf:
        n, kind = b & 0x1f, "str"
    elif b <= 0x8f:
        n, kind = b & 0x0f, "map"
    elif b <= 0x9f:
        n, kind = b & 0x0f, "array"
    elif b in _SIZED:
        width, kind = _SIZED[b]
        if pos + width > len(buf):
            raise _truncated()
        n, pos = int.from_bytes(buf[pos:pos + width], "big"), pos + width
    else:
        raise ProtocolError(MALFORMED, f"not a valid msgpack message: type byte 0x{b:02x} (ext or reserved)")
    if kind in ("str", "bin"):
        if kind == "str" and n > MAX_STR_LEN:
            raise ProtocolError(MALFORMED, f"not a valid msgpack message: a str of {n} bytes exceeds {MAX_STR_LEN}")
        if pos + n > len(buf):
            raise _truncated()
        if kind == "bin":
            return buf[pos:pos + n], pos + n
        try:
            return str(buf[pos:pos + n], "utf-8"), pos + n
        except UnicodeDecodeError as e:
            raise ProtocolError(MALFORMED, f"not a valid msgpack message: UnicodeDecodeError: {e}") from None
    if n > MAX_CONTAINER_LEN:
        raise ProtocolError(MALFORMED, f"not a valid msgpack message: a {kind} of {n} entries exceeds "
                            f"{MAX_CONTAINER_LEN}")
    if depth > MAX_DEPTH:
        raise ProtocolError(MALFORMED, f"containers nested deeper than {MAX_DEPTH} levels")
    if kind == "array":
        items = []
        for _ in range(n):
            v, pos = _skim(buf, pos, depth + 1)
            items.append(v)
        return items, pos
    out: dict[str, Any] = {}
    for _ in range(n):
        k, pos = _skim(buf, pos, depth + 1)
        if type(k) is not str:
            raise ProtocolError(MALFORMED, f"map key {k!r} is not a string")
        out[k], pos = _skim(buf, pos, depth + 1)
    return out, pos


def read_frame_header(data: bytes | bytearray | memoryview, max_size: int = MAX_SERVER_MESSAGE
                      ) -> FrameHeader | None:
    """The FrameHeader of a `frame` (seq, t, timing, n, key, member, size), None for another server message.

    Reads the msgpack structure only: `bin` payloads (the arrays) are skipped by their length, never read, copied
    or checked, whatever their place in the map; the small fields are checked as decode_server_message checks
    them (so is the type of a non-frame message). Raises ProtocolError (malformed input, bad fields)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(MALFORMED, f"expected bytes, got {type(data).__name__}")
    buf = memoryview(data).cast("B")
    if buf.nbytes > max_size:
        raise ProtocolError(MESSAGE_TOO_LARGE, f"message of {buf.nbytes} bytes exceeds the limit of {max_size}")
    m, end = _skim(buf, 0, 1)
    if end != buf.nbytes:
        raise ProtocolError(MALFORMED, f"not a valid msgpack message: {buf.nbytes - end} bytes after the message")
    if not isinstance(m, dict):
        raise ProtocolError(MALFORMED, f"message must be a msgpack map, got {F._type_name(m)}")
    if _message_type(m, SERVER_TYPES, "server") != "frame":
        return None
    w = "frame"
    member = F.get_str(m, "member", w, default=None)
    if "params" in m:  # a params frame (PROTOCOL.md 13): seq and t together or neither, timing only with them
        seq, t = F.get_int(m, "seq", w, lo=0, default=None), F.get_int(m, "t", w, default=None)
        if (seq is None) != (t is None):
            raise ProtocolError(BAD_FIELD, "frame: a params frame carries 'seq' and 't' together or neither")
        if m.get("timing") is not None and seq is None:
            raise ProtocolError(BAD_FIELD, "frame: 'timing' on a params frame without 'seq' and 't'")
        timing = decode_timing(m) if m.get("timing") is not None else None
        return FrameHeader(seq=seq, t=t, timing=timing, size=buf.nbytes, member=member)
    return FrameHeader(seq=F.get_int(m, "seq", w, lo=0), t=F.get_int(m, "t", w), timing=decode_timing(m),
                       size=buf.nbytes, n=F.get_int(m, "n", w, lo=0, hi=UINT32_MAX),
                       key=F.get_bool(m, "key", w, default=None), member=member)


# ============================================================================= params sessions (PROTOCOL.md 13)


def encode_rig_chunk(m: RigChunk) -> bytes:
    """`rig`: bytes [offset, offset + len(data)) of a rig body (`ofera_protocol.rig`)."""
    member = {} if m.member is None else {"member": m.member}
    return pack_map({"type": "rig", **member, "chunk": m.chunk, "chunks": m.chunks, "size": m.size,
                     "offset": m.offset, "data": np.ascontiguousarray(m.data, np.uint8)})


def decode_rig_chunk(m: dict[str, Any]) -> RigChunk:
    w = "rig"
    chunks = F.get_int(m, "chunks", w, lo=1, hi=UINT32_MAX)
    size = F.get_int(m, "size", w, lo=0, hi=UINT32_MAX)
    return RigChunk(member=F.get_str(m, "member", w, default=None), chunk=F.get_int(m, "chunk", w, lo=0, hi=chunks - 1),
                    chunks=chunks, size=size, offset=F.get_int(m, "offset", w, lo=0, hi=size),
                    data=np.frombuffer(F.get_bin(m, "data", w), np.uint8))


def encode_params_frame(m: ParamsFrame) -> bytes:
    """A params frame: `type`, [`member`], [`seq`, `t`, `timing` on a stamped frame], `params` (float32)."""
    d: dict[str, Any] = {"type": "frame"}
    if m.member is not None:
        d["member"] = m.member
    if (m.seq is None) != (m.t is None):
        raise ValueError("a stamped params frame carries both seq and t, an unstamped one neither")
    if m.seq is not None:
        d["seq"], d["t"] = m.seq, m.t
        if m.timing is not None:
            d["timing"] = m.timing
    d["params"] = np.ascontiguousarray(m.params, "<f4").reshape(-1)
    return pack_map(d)


def decode_params_frame(m: dict[str, Any], fmt: ParamsFormat) -> ParamsFrame:
    """A params frame: `params` of fmt.length finite float32; `seq` and `t` together or neither; `timing` only
    with them."""
    w = "frame"
    seq = F.get_int(m, "seq", w, lo=0, default=None)
    t = F.get_int(m, "t", w, default=None)
    if (seq is None) != (t is None):
        raise ProtocolError(BAD_FIELD, "frame: a params frame carries 'seq' and 't' together or neither")
    timing = None
    if "timing" in m and m["timing"] is not None:
        if seq is None:
            raise ProtocolError(BAD_FIELD, "frame: 'timing' on a params frame without 'seq' and 't'")
        timing = decode_timing(m)
    params = F.get_array(m, "params", w, "<f4", (fmt.length,))
    return ParamsFrame(params=params, seq=seq, t=t, timing=timing, member=F.get_str(m, "member", w, default=None))


def member_format(welcome: Welcome, join: Join) -> FrameFormat | ParamsFormat:
    """Rooms: the FrameFormat of a member's frames (the viewer's encoding and sparseness, the member's avatar
    count and q13 parameters); a params session's ParamsFormat."""
    if join.avatar is None:
        raise ValueError(f"member {join.member!r} does not publish: it has no frames")
    if welcome.encoding == PARAMS:
        return ParamsFormat()
    return FrameFormat(encoding=welcome.encoding, count=join.avatar.count, sparse=welcome.sparse, quant=join.quant)


def frame_format(welcome: Welcome) -> FrameFormat | ParamsFormat:
    """The FrameFormat a `welcome` announces (a params session: its ParamsFormat)."""
    if welcome.avatar is None:
        raise ValueError("a watch-only room session has no frames of its own (member_format: per member)")
    if welcome.encoding == PARAMS:
        return ParamsFormat()
    return FrameFormat(encoding=welcome.encoding, count=welcome.avatar.count, sparse=welcome.sparse,
                       quant=welcome.quant, delta=welcome.delta)
