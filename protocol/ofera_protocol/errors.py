"""Error codes, their fatality and WebSocket close codes, and the exceptions of the codec.

Each code is a stable string sent in `error.code`. Some codes are always fatal, some never, and
some are fatal only during the handshake (a bad `hello` ends the session, a bad `bs` does not).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

MALFORMED = "malformed"
UNKNOWN_TYPE = "unknown_type"
BAD_FIELD = "bad_field"
BAD_LENGTH = "bad_length"
NON_FINITE = "non_finite"
NOT_READY = "not_ready"
DUPLICATE_HELLO = "duplicate_hello"
UNSUPPORTED_PROTOCOL = "unsupported_protocol"
UNKNOWN_LAYOUT = "unknown_layout"
UNKNOWN_AVATAR = "unknown_avatar"
UNKNOWN_ENCODING = "unknown_encoding"
UNAUTHORIZED = "unauthorized"
MESSAGE_TOO_LARGE = "message_too_large"
RATE_LIMITED = "rate_limited"
SERVER_FULL = "server_full"
TEXT_FRAME = "text_frame"
INTERNAL = "internal"
ROOM_FULL = "room_full"
TOO_MANY_ROOMS = "too_many_rooms"


class Fatality(Enum):
    """When an error ends the session."""

    ALWAYS = "always"
    HANDSHAKE = "handshake"  # fatal before the session streams, non-fatal after
    NEVER = "never"


@dataclass(frozen=True)
class ErrorSpec:
    """Static description of one error code."""

    code: str
    fatality: Fatality
    close_code: int | None  # WebSocket close code when fatal; None if never fatal
    description: str


ERRORS: dict[str, ErrorSpec] = {
    s.code: s
    for s in (
        ErrorSpec(MALFORMED, Fatality.HANDSHAKE, 4000, "not msgpack, trailing bytes, not a map, non-string keys, "
                  "ext types, too deep, too many entries"),
        ErrorSpec(UNKNOWN_TYPE, Fatality.HANDSHAKE, 4001, "`type` is not a known message type (for this direction)"),
        ErrorSpec(BAD_FIELD, Fatality.HANDSHAKE, 4002, "a field is missing, has the wrong type, or is out of range"),
        ErrorSpec(BAD_LENGTH, Fatality.HANDSHAKE, 4003, "a `bin` has the wrong number of bytes for its type and shape"),
        ErrorSpec(NON_FINITE, Fatality.HANDSHAKE, 4004, "a float array holds NaN or infinity"),
        ErrorSpec(NOT_READY, Fatality.HANDSHAKE, 4005, "a message not allowed in this state (e.g. `bs` before "
                  "`hello`)"),
        ErrorSpec(DUPLICATE_HELLO, Fatality.NEVER, None, "a second `hello`; ignored, the first stays in force"),
        ErrorSpec(UNSUPPORTED_PROTOCOL, Fatality.ALWAYS, 4010, "`hello.protocol` is not 1"),
        ErrorSpec(UNKNOWN_LAYOUT, Fatality.ALWAYS, 4011, "`hello.layout` is not a known layout"),
        ErrorSpec(UNKNOWN_AVATAR, Fatality.ALWAYS, 4012, "the server has no avatar with that id"),
        ErrorSpec(UNKNOWN_ENCODING, Fatality.ALWAYS, 4013, "the server does not offer that encoding"),
        ErrorSpec(UNAUTHORIZED, Fatality.ALWAYS, 1008, "missing or invalid `token` (policy violation)"),
        ErrorSpec(MESSAGE_TOO_LARGE, Fatality.ALWAYS, 1009, "a message exceeds the receiver's size limit (section 1)"),
        ErrorSpec(RATE_LIMITED, Fatality.NEVER, None, "`bs` or `ping` faster than the server allows; the excess is "
                  "dropped"),
        ErrorSpec(SERVER_FULL, Fatality.ALWAYS, 1013, "no capacity for another session (try again later)"),
        ErrorSpec(TEXT_FRAME, Fatality.ALWAYS, 1003, "a WebSocket text message (only binary is allowed)"),
        ErrorSpec(INTERNAL, Fatality.ALWAYS, 1011, "the server failed; not the client's fault"),
        ErrorSpec(ROOM_FULL, Fatality.ALWAYS, 4014, "rooms: the room has its most members (try again later)"),
        ErrorSpec(TOO_MANY_ROOMS, Fatality.ALWAYS, 4015, "rooms: the server holds its most rooms; a new room "
                  "cannot open (try again later)"),
    )
}
"""Every error code of protocol v1, in documentation order (PROTOCOL.md section 10 is generated from it)."""

CLOSE_NORMAL = 1000
"""WebSocket close code after `bye` or a client's normal close."""
CLOSE_GOING_AWAY = 1001
"""WebSocket close code when the server shuts down."""
CLOSE_UNKNOWN_FATAL = 4000
"""Close code of a fatal error code unknown to v1 (`close_code`)."""


def close_code(code: str) -> int:
    """WebSocket close code that follows a fatal error `code` (4000 for codes unknown to v1)."""
    spec = ERRORS.get(code)
    if spec is None or spec.close_code is None:
        return CLOSE_UNKNOWN_FATAL
    return spec.close_code


class ProtocolError(Exception):
    """A message violated the protocol. Carries the wire error `code`, a human `message` and `fatal`.

    The codec raises it for anything wrong in received bytes; the server also builds one to send
    (`ServerConnection.error`). `close_code` is the WebSocket close code to use when fatal.
    """

    def __init__(self, code: str, message: str, fatal: bool | None = None) -> None:
        if fatal is None:
            spec = ERRORS.get(code)
            fatal = spec is not None and spec.fatality is Fatality.ALWAYS
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.fatal = fatal

    @property
    def close_code(self) -> int:
        return close_code(self.code)

    def as_fatal(self) -> ProtocolError:
        """The same error, fatal (used when it happens during the handshake)."""
        return self if self.fatal else ProtocolError(self.code, self.message, True)

    def __repr__(self) -> str:
        return f"ProtocolError({self.code!r}, {self.message!r}, fatal={self.fatal})"


class ConnectionUsageError(RuntimeError):
    """The local application used a connection wrongly (e.g. sent a frame before `welcome`, or asked for an encoding
    that does not exist): a bug of the caller, found before anything is sent.

    Not a `ProtocolError`: that one carries a wire error code and blames the peer (a server answers it with an
    `error` message and a close code); this one blames the caller and never goes on the wire. (h11's
    `LocalProtocolError` is an HTTP protocol violation by the local side, hence the different name.)
    """

