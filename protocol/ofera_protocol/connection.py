"""Sans-I/O state machines of the two ends of a session (in the style of h11 / websockets' protocol).

Feed each received WebSocket message to `receive` (binary) or `receive_text` (text); get a typed
message back or a ProtocolError. Call the sending methods to get the bytes to send. Nothing here does
I/O: the caller owns the socket, closes it with `ProtocolError.close_code` after a fatal error, and
with 1000 after `bye`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np

from .avatar import DEFAULT_CHUNK_BYTES, Avatar, AvatarAssembler, GaussianState, split_avatar
from .codec import (
    conf_in_range,
    decode_client_message,
    decode_server_message,
    encode,
    encode_avatar_chunk,
    encode_bs,
    encode_frame,
    frame_format,
    member_format,
    read_frame_header,
)
from .constants import (
    COORDS,
    DEFAULT_AVATAR,
    DEFAULT_COORDS,
    DEFAULT_ENCODING,
    HELLO_ENCODINGS,
    LAYOUTS,
    MAX_CLIENT_MESSAGE,
    MAX_SERVER_MESSAGE,
    PARAMS,
    PROTOCOL_VERSION,
)
from .encodings import FrameFormat
from .errors import (
    BAD_FIELD,
    DUPLICATE_HELLO,
    NOT_READY,
    TEXT_FRAME,
    ConnectionUsageError,
    ProtocolError,
)
from .messages import (
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


def _text_error() -> ProtocolError:
    return ProtocolError(TEXT_FRAME, "text WebSocket messages are not allowed; send msgpack as binary", True)


# ============================================================================= server side


class ServerState(Enum):
    AWAITING_HELLO = "awaiting_hello"  # nothing valid received yet
    HELLO_RECEIVED = "hello_received"  # the application must accept() or reject()
    STREAMING = "streaming"            # welcome sent
    CLOSED = "closed"                  # bye received, or a fatal error either way


class ServerConnection:
    """Server end of one session.

    Typical use::

        try:
            msg = conn.receive(data)
        except ProtocolError as e:
            send(conn.error(e)); if e.fatal: close(e.close_code)
        if isinstance(msg, Hello):
            send(conn.accept(session, AvatarInfo(...)))
            for b in conn.avatar(avatar): send(b)
        elif isinstance(msg, Blendshapes):
            send(conn.frame(frame))  # for many viewers: codec.encode_frame once per FrameFormat
    """

    def __init__(self, max_message_size: int = MAX_CLIENT_MESSAGE) -> None:
        self.max_message_size = max_message_size
        self.state = ServerState.AWAITING_HELLO
        self.hello: Hello | None = None
        self.welcome: Welcome | None = None
        self.format: FrameFormat | None = None
        self.avatar_sent = False

    # -- receiving

    def receive(self, data: bytes | bytearray | memoryview) -> ClientMessage:
        """Decode one binary message and advance the state. Raises ProtocolError; a fatal one (any
        error while awaiting hello, or an always-fatal code) moves the connection to CLOSED."""
        if self.state is ServerState.CLOSED:
            raise ConnectionUsageError("receive() on a closed connection")
        try:
            layout = self.hello.layout if self.hello else None
            msg = decode_client_message(data, layout, self.max_message_size)
            return self._advance(msg)
        except ProtocolError as e:
            if self.state is ServerState.AWAITING_HELLO:
                e = e.as_fatal()
            if e.fatal:
                self.state = ServerState.CLOSED
            raise e from None

    def receive_text(self, text: str) -> None:
        """A text message arrived: always a fatal `text_frame` ProtocolError (close 1003)."""
        self.state = ServerState.CLOSED
        raise _text_error()

    def _advance(self, msg: ClientMessage) -> ClientMessage:
        if isinstance(msg, Hello):
            if self.state is not ServerState.AWAITING_HELLO:
                raise ProtocolError(DUPLICATE_HELLO, "hello already received; the first one stays in force")
            self.hello = msg
            self.state = ServerState.HELLO_RECEIVED
        elif isinstance(msg, Blendshapes):
            if self.state is ServerState.AWAITING_HELLO:
                raise ProtocolError(NOT_READY, "bs before hello: send hello first", True)
            if self.state is not ServerState.STREAMING:
                raise ProtocolError(NOT_READY, "bs before welcome: wait for welcome", False)
        elif isinstance(msg, Resync):
            if self.state is ServerState.AWAITING_HELLO:
                raise ProtocolError(NOT_READY, "resync before hello: send hello first", True)
            if self.state is not ServerState.STREAMING or self.welcome is None or not self.welcome.delta:
                raise ProtocolError(NOT_READY, "resync outside a delta session (hello.delta) is ignored", False)
        elif isinstance(msg, Bye):
            self.state = ServerState.CLOSED
        return msg

    # -- sending

    def accept(self, session: str, avatar: AvatarInfo | None, *, encoding: str | None = None,
               quant: Quant | None = None, server: str | None = None, delta: bool | None = None,
               member: str | None = None, rig_bytes: int | None = None) -> bytes:
        """Accept the received hello: returns `welcome` and enters STREAMING. `encoding` defaults to
        the one asked for; `quant` is required for q13 (see encodings.make_quant). `delta` defaults to
        hello.delta where the encoding allows it (f16, q13); a delta session is dense (welcome.sparse false).
        Room sessions (hello.room): `member` is the client's member id; `avatar` is None for a watcher; frames are
        per member (`join`, `member_format`), and a room session has no deltas. A v1 params session (PROTOCOL.md 13)
        announces `rig_bytes`, the size of the rig body its `rig` messages carry (after the avatar's)."""
        if self.state is not ServerState.HELLO_RECEIVED or self.hello is None:
            raise ConnectionUsageError(f"accept() needs a received hello (state {self.state.value})")
        encoding = encoding or self.hello.encoding
        if encoding not in HELLO_ENCODINGS:
            raise ConnectionUsageError(f"unknown encoding {encoding!r}")
        if encoding != PARAMS and rig_bytes is not None:
            raise ConnectionUsageError("only a params session announces rig_bytes")
        room = self.hello.room
        if (room is None) != (member is None) or (avatar is None and (room is None or self.hello.publish)):
            raise ConnectionUsageError("a room session needs a member id (and a publisher its avatar); a v1 session "
                                       "needs its avatar and no member id")
        if avatar is not None and self.hello.max_gaussians is not None and avatar.count > self.hello.max_gaussians:
            raise ConnectionUsageError(f"avatar has {avatar.count} Gaussians, the client allows "
                                     f"{self.hello.max_gaussians}")
        if delta is None:
            delta = self.hello.delta and encoding in ("f16", "q13") and room is None
        welcome = Welcome(session=session, avatar=avatar, layout=self.hello.layout, encoding=encoding,
                          coords=self.hello.coords, sparse=self.hello.sparse and not delta and encoding != PARAMS,
                          quant=quant if encoding == "q13" and room is None else None, server=server, delta=delta,
                          rig_bytes=rig_bytes,
                          room=room, member=member)
        try:
            self.format = frame_format(welcome) if room is None else None
        except ValueError as e:
            raise ConnectionUsageError(str(e)) from None
        data = encode(welcome)
        self.welcome = welcome
        self.state = ServerState.STREAMING
        return data

    def reject(self, code: str, message: str) -> bytes:
        """Refuse the session: returns a fatal `error` and enters CLOSED; close with
        errors.close_code(code)."""
        return self.error(ProtocolError(code, message, True))

    def error(self, err: ProtocolError | str, message: str = "", seq: int | None = None,
              fatal: bool | None = None) -> bytes:
        """`error` message for a ProtocolError (or a code + message). Allowed in every state, so that a
        fatal error from receive() can still be reported. A fatal error closes the connection."""
        if isinstance(err, str):
            err = ProtocolError(err, message, fatal)
        if err.fatal:
            self.state = ServerState.CLOSED
        return encode(ErrorMessage(code=err.code, message=err.message, fatal=err.fatal, seq=seq))

    def avatar(self, avatar: Avatar, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES, member: str | None = None
               ) -> list[bytes]:
        """The `avatar` messages (in session coordinates already), to send right after welcome; in a room
        session, after a `join` of `member` (whose announced avatar the caller checks)."""
        self._require_streaming("avatar()")
        assert self.welcome is not None
        if (member is None) != (self.welcome.room is None):
            raise ConnectionUsageError("avatar messages carry a member in a room session, and only there")
        info = self.welcome.avatar
        if member is None and (avatar.count != info.count or avatar.sh_degree != info.sh_degree):
            raise ConnectionUsageError(f"avatar has {avatar.count} Gaussians of SH degree {avatar.sh_degree}, "
                                     f"welcome announced {info.count} of degree {info.sh_degree}")
        chunks = split_avatar(avatar, max_chunk_bytes)
        if member is not None:
            for c in chunks:
                c.member = member
        out = [encode_avatar_chunk(c) for c in chunks]
        self.avatar_sent = True
        return out

    def join(self, join: Join) -> bytes:
        """Rooms: a `join` (its avatar messages follow: `avatar(..., member=join.member)`)."""
        self._require_room("join()")
        return encode(join)

    def leave(self, member: str, reason: str) -> bytes:
        """Rooms: a `leave`."""
        self._require_room("leave()")
        return encode(Leave(member=member, reason=reason))

    def _require_room(self, what: str) -> None:
        self._require_streaming(what)
        assert self.welcome is not None
        if self.welcome.room is None:
            raise ConnectionUsageError(f"{what} needs a room session (hello.room)")

    def frame(self, frame: Frame) -> bytes:
        """Encode a frame for this session (for many viewers, call codec.encode_frame once instead)."""
        self._require_streaming("frame()")
        if not self.avatar_sent:
            raise ConnectionUsageError("frame() before avatar(): the client needs the avatar first")
        assert self.format is not None
        return encode_frame(frame, self.format)

    def pong(self, t: int) -> bytes:
        if self.state is ServerState.CLOSED:
            raise ConnectionUsageError("pong() on a closed connection")
        return encode(Pong(t=t))

    def _require_streaming(self, what: str) -> None:
        if self.state is not ServerState.STREAMING:
            raise ConnectionUsageError(f"{what} needs state streaming, not {self.state.value}")


# ============================================================================= client side


class ClientState(Enum):
    IDLE = "idle"                          # hello not sent yet
    AWAITING_WELCOME = "awaiting_welcome"
    RECEIVING_AVATAR = "receiving_avatar"  # welcome received, avatar chunks pending
    RECEIVING_RIG = "receiving_rig"        # params sessions: avatar complete, rig chunks pending
    STREAMING = "streaming"                # avatar complete, frames flow
    CLOSED = "closed"


@dataclass
class RoomMember:
    """What a room client knows of one member: its `join`, the format of its frames, its avatar once complete and,
    with `track_gaussians`, its latest Gaussians."""

    join: Join
    format: FrameFormat | None  # None: a watch-only member (no frames)
    assembler: AvatarAssembler | None = None
    avatar: Avatar | None = None
    gaussians: GaussianState | None = None
    frames: int = 0
    rig: Any = None  # params viewers (PROTOCOL.md 13.6): the member's decoded rig (ofera_protocol.rig.Rig)
    rig_assembler: Any = None  # params viewers: its rig.RigAssembler while the rig's chunks arrive

    @property
    def ready(self) -> bool:
        """Its avatar is complete: frames may come."""
        return self.avatar is not None


class ClientConnection:
    """Client end of one session. After the avatar is complete `avatar` holds it and, with
    `track_gaussians`, `gaussians` holds the latest position/rotation/scale (sparse frames applied).

    Room sessions (hello(room=...)): the stream starts at welcome; `members` holds every member announced by `join`
    (removed at `leave`), each with its own avatar, format and Gaussians; `formats` the members whose frames can be
    decoded."""

    def __init__(self, max_message_size: int = MAX_SERVER_MESSAGE, track_gaussians: bool = True) -> None:
        self.max_message_size = max_message_size
        self.track_gaussians = track_gaussians
        self.state = ClientState.IDLE
        self.sent_hello: Hello | None = None
        self.welcome: Welcome | None = None
        self.format: FrameFormat | None = None
        self.avatar: Avatar | None = None
        self.gaussians: GaussianState | None = None
        self._assembler: AvatarAssembler | None = None
        self.delta: Any = None  # delta.DeltaDecoder of a delta session (the codes this client holds)
        self.resync_needed = False
        """A delta frame could not be applied: send `resync()` (the server believes it was)."""
        self.members: dict[str, RoomMember] = {}
        self.formats: dict[str, FrameFormat] = {}  # members whose avatar is complete -> their FrameFormat
        self.rig: Any = None  # params sessions: the decoded rig (ofera_protocol.rig.Rig) once complete
        self._rig: Any = None  # params sessions: the rig.RigAssembler while rig chunks arrive

    # -- sending

    def hello(self, layout: str, avatar: str = DEFAULT_AVATAR, *, encoding: str = DEFAULT_ENCODING,
              coords: str = DEFAULT_COORDS, sparse: bool = False, device: str | None = None,
              token: str | None = None, max_gaussians: int | None = None, delta: bool = False,
              room: str | None = None, publish: bool = True, self_view: bool = False,
              room_token: str | None = None) -> bytes:
        """The `hello`; `room` joins a room (PROTOCOL.md 12): `publish` False watches only, `self_view` also
        receives one's own avatar, `room_token` answers a server that guards its rooms."""
        if self.state is not ClientState.IDLE:
            raise ConnectionUsageError("hello() may be sent once, first")
        for name, value, allowed in (("layout", layout, LAYOUTS), ("encoding", encoding, HELLO_ENCODINGS),
                                     ("coords", coords, COORDS)):
            if value not in allowed:
                raise ConnectionUsageError(f"unknown {name} {value!r}; expected one of {', '.join(allowed)}")
        msg = Hello(layout=layout, avatar=avatar, encoding=encoding, coords=coords, sparse=sparse,
                    device=device, token=token, max_gaussians=max_gaussians, protocol=PROTOCOL_VERSION,
                    delta=delta, room=room, publish=publish, self=self_view, room_token=room_token)
        self.sent_hello = msg
        self.state = ClientState.AWAITING_WELCOME
        return encode(msg)

    def bs(self, seq: int, t: int, w: np.ndarray, conf: np.ndarray | None = None) -> bytes:
        """A blendshape sample: `w` (L,) weights of the session's layout, `t` client clock in µs, `conf`
        optional (2,) [lower, upper] face confidence in [0, 1]."""
        if self.state not in (ClientState.RECEIVING_AVATAR, ClientState.RECEIVING_RIG, ClientState.STREAMING):
            raise ConnectionUsageError(f"bs() needs a welcome first (state {self.state.value})")
        assert self.sent_hello is not None
        if self.sent_hello.room is not None and not self.sent_hello.publish:
            raise ConnectionUsageError("bs() in a watch-only room session (hello publish=False)")
        w = np.asarray(w, dtype=np.float32).reshape(-1)
        n = LAYOUTS[self.sent_hello.layout]
        if w.shape != (n,):
            raise ConnectionUsageError(f"layout {self.sent_hello.layout} needs {n} weights, got {w.shape[0]}")
        if conf is not None:
            conf = np.asarray(conf, dtype=np.float32).reshape(-1)
            if conf.shape != (2,) or not conf_in_range(conf):
                raise ConnectionUsageError(f"conf must be 2 values [lower, upper] in [0, 1], got {conf.tolist()}")
        return encode_bs(Blendshapes(seq=seq, t=t, w=w, conf=conf))

    def ping(self, t: int) -> bytes:
        if self.state is ClientState.CLOSED:
            raise ConnectionUsageError("ping() on a closed connection")
        return encode(Ping(t=t))

    def bye(self) -> bytes:
        self.state = ClientState.CLOSED
        return encode(Bye())

    def resync(self) -> bytes:
        """Ask for a key frame (delta sessions); clears `resync_needed`."""
        if self.state is ClientState.CLOSED:
            raise ConnectionUsageError("resync() on a closed connection")
        self.resync_needed = False
        return encode(Resync())

    # -- receiving

    def receive(self, data: bytes | bytearray | memoryview) -> ServerMessage:
        """Decode one server message and advance the state. Raises ProtocolError (fatal before the
        stream starts; a bad frame is non-fatal)."""
        if self.state is ClientState.CLOSED:
            raise ConnectionUsageError("receive() on a closed connection")
        try:
            members = self.formats if self.welcome is not None and self.welcome.room is not None else None
            msg = decode_server_message(data, self.format, self.max_message_size, members)
            return self._advance(msg)
        except ProtocolError as e:
            raise self._failed(e) from None

    def _failed(self, e: ProtocolError) -> ProtocolError:
        """The error a failed receive raises (fatal before the stream starts), the state updated."""
        if self.delta is not None and self.state is ClientState.STREAMING:
            self.resync_needed = True  # whatever failed may have been a delta frame
        if self.state is not ClientState.STREAMING:
            e = e.as_fatal()
        if e.fatal:
            self.state = ClientState.CLOSED
        return e

    def receive_header(self, data: bytes | bytearray | memoryview) -> ServerMessage | FrameHeader:
        """As `receive`, but a frame comes back as its FrameHeader (codec.read_frame_header): its arrays are neither
        decoded nor checked. The frame is still checked against the state (streaming; in a room, of a member joined
        with a complete avatar) and counted (`RoomMember.frames`); what its arrays carry is not kept, so
        `track_gaussians`, delta and params sessions (whose state the arrays build) raise ConnectionUsageError."""
        if self.state is ClientState.CLOSED:
            raise ConnectionUsageError("receive_header() on a closed connection")
        hello = self.sent_hello
        if self.track_gaussians or (hello is not None and (hello.delta or hello.encoding == PARAMS)):
            raise ConnectionUsageError("receive_header() leaves the arrays of frames unread: it cannot keep Gaussians "
                                       "(track_gaussians) nor follow a delta or params session")
        try:
            head = read_frame_header(data, self.max_message_size)
            if head is not None:
                self._advance_header(head)
        except ProtocolError as e:
            raise self._failed(e) from None
        return self.receive(data) if head is None else head

    def _advance_header(self, head: FrameHeader) -> None:
        """The checks and counts `_advance` does for a frame, on its header (same errors as `receive`)."""
        room = self.welcome is not None and self.welcome.room is not None
        if room and head.member is not None:
            if head.member not in self.formats:
                raise ProtocolError(NOT_READY, f"frame of member {head.member[:64]!r} before its join and avatar",
                                    False)
        elif self.format is None:
            raise ProtocolError(NOT_READY, "frame before welcome: the session's format is unknown")
        if self.state is not ClientState.STREAMING:
            raise ProtocolError(NOT_READY, f"frame before the avatar was complete (state {self.state.value})")
        if head.member is not None:
            if not room:
                raise ProtocolError(NOT_READY, "frame with a member outside a room session")
            self.members[head.member].frames += 1

    def receive_text(self, text: str) -> None:
        self.state = ClientState.CLOSED
        raise _text_error()

    def _advance(self, msg: ServerMessage) -> ServerMessage:
        if isinstance(msg, Welcome):
            if self.state is not ClientState.AWAITING_WELCOME:
                raise ProtocolError(NOT_READY, f"unexpected welcome in state {self.state.value}", True)
            assert self.sent_hello is not None
            if msg.layout != self.sent_hello.layout or msg.coords != self.sent_hello.coords:
                raise ProtocolError(BAD_FIELD, "welcome's layout/coords differ from hello's", True)
            if msg.room != self.sent_hello.room:
                raise ProtocolError(BAD_FIELD, "welcome's room differs from hello's", True)
            if msg.room is not None:  # the room's avatars come with `join`
                self.welcome = msg
                self.state = ClientState.STREAMING
                return msg
            self.welcome, self.format = msg, frame_format(msg)
            if msg.delta:
                from .delta import DeltaDecoder

                self.delta = DeltaDecoder(self.format)
            self._assembler = AvatarAssembler(msg.avatar.count, msg.avatar.sh_degree)
            self.state = ClientState.RECEIVING_AVATAR
        elif isinstance(msg, (Join, Leave)) or getattr(msg, "member", None) is not None:
            self._advance_room(msg)
        elif isinstance(msg, AvatarChunk):
            if self.state is not ClientState.RECEIVING_AVATAR or self._assembler is None:
                raise ProtocolError(NOT_READY, f"unexpected avatar chunk in state {self.state.value}", True)
            if self._assembler.add(msg):
                self.avatar = self._assembler.result()
                self._assembler = None
                if self.track_gaussians:
                    self.gaussians = GaussianState.from_avatar(self.avatar)
                self.state = ClientState.STREAMING
                if self.welcome is not None and self.welcome.encoding == PARAMS:
                    from .rig import RigAssembler

                    self._rig, self.state = RigAssembler(), ClientState.RECEIVING_RIG
        elif isinstance(msg, RigChunk):
            self._advance_rig(msg)
        elif isinstance(msg, ParamsFrame):
            if self.state is not ClientState.STREAMING:
                raise ProtocolError(NOT_READY, f"frame before the rig was complete (state {self.state.value})")
        elif isinstance(msg, (Frame, DeltaFrame)):
            if self.state is not ClientState.STREAMING:
                raise ProtocolError(NOT_READY, "frame before the avatar was complete "
                                    f"(state {self.state.value})")
            if isinstance(msg, DeltaFrame):
                msg = self.delta.apply(msg)  # absolute values of the changed Gaussians (sparse-like)
            elif msg.key:
                self.delta.key(msg)
            if self.gaussians is not None:
                self.gaussians.apply(msg)
        elif isinstance(msg, ErrorMessage):
            if msg.fatal:
                self.state = ClientState.CLOSED
        elif not isinstance(msg, Pong):  # pragma: no cover - decode returns only server messages
            raise AssertionError(msg)
        return msg

    def _advance_rig(self, msg: RigChunk) -> None:
        """Params sessions: the next chunk of the rig; the last one decodes it (PROTOCOL.md 13.2)."""
        from .rig import decode_rig

        if self.state is not ClientState.RECEIVING_RIG or self._rig is None:
            raise ProtocolError(NOT_READY, f"unexpected rig chunk in state {self.state.value}", True)
        assert self.welcome is not None and self.welcome.avatar is not None
        if self.welcome.rig_bytes is not None and msg.size != self.welcome.rig_bytes:
            raise ProtocolError(BAD_FIELD, f"rig of {msg.size} bytes, welcome announced {self.welcome.rig_bytes}", True)
        if self._rig.add(msg):
            rig = decode_rig(self._rig.result())
            if rig.count != self.welcome.avatar.count:
                raise ProtocolError(BAD_FIELD, f"rig for {rig.count} Gaussians, the avatar has "
                                    f"{self.welcome.avatar.count}", True)
            self.rig, self._rig, self.state = rig, None, ClientState.STREAMING

    def _advance_room(self, msg: ServerMessage) -> None:
        """join / leave / a member's avatar chunk or frame, in a room session."""
        if self.state is not ClientState.STREAMING or self.welcome is None or self.welcome.room is None:
            raise ProtocolError(NOT_READY, f"{msg.TYPE} with a member outside a room session")
        if isinstance(msg, Join):  # a known member joining again (the room healed) starts over
            if msg.publish and self.welcome.encoding == "q13" and msg.quant is None:
                raise ProtocolError(BAD_FIELD, f"join of {msg.member!r}: a q13 session needs the member's 'quant'")
            fmt = member_format(self.welcome, msg) if msg.publish else None
            self.formats.pop(msg.member, None)
            assembler = None if msg.avatar is None else AvatarAssembler(msg.avatar.count, msg.avatar.sh_degree)
            self.members[msg.member] = RoomMember(msg, fmt, assembler)
            return
        if isinstance(msg, Leave):
            self.members.pop(msg.member, None)
            self.formats.pop(msg.member, None)
            return
        m = self.members.get(msg.member)  # type: ignore[attr-defined]
        if m is None:
            raise ProtocolError(NOT_READY, f"{msg.TYPE} of member {msg.member!r} before its join")  # type: ignore
        if isinstance(msg, AvatarChunk):
            if m.assembler is None:
                raise ProtocolError(NOT_READY, f"avatar chunk of member {msg.member!r}, whose avatar is complete "
                                    "or who does not publish")
            if m.assembler.add(msg):
                m.avatar, m.assembler = m.assembler.result(), None
                if self.track_gaussians:
                    m.gaussians = GaussianState.from_avatar(m.avatar)
                assert m.format is not None
                if isinstance(m.format, ParamsFormat):  # params: its frames decode once its rig is complete too
                    from .rig import RigAssembler

                    m.rig_assembler = RigAssembler()
                else:
                    self.formats[msg.member] = m.format
        elif isinstance(msg, RigChunk):
            if m.rig_assembler is None:
                raise ProtocolError(NOT_READY, f"rig chunk of member {msg.member!r} before its avatar, after its rig, "
                                    "or outside a params session")
            if m.rig_assembler.add(msg):
                from .rig import decode_rig

                rig = decode_rig(m.rig_assembler.result())
                if m.avatar is None or rig.count != m.avatar.count:
                    raise ProtocolError(BAD_FIELD, f"rig of member {msg.member!r} for {rig.count} Gaussians, its "
                                        "avatar has another count")
                m.rig, m.rig_assembler = rig, None
                assert m.format is not None
                self.formats[msg.member] = m.format
        elif isinstance(msg, ParamsFrame):
            m.frames += 1
        elif isinstance(msg, Frame):
            m.frames += 1
            if m.gaussians is not None:
                m.gaussians.apply(msg)
