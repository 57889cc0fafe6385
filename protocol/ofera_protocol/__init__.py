"""OFERA wire protocol v1: sans-I/O codec (no sockets, no asyncio; numpy + msgpack only).

The normative text is protocol/PROTOCOL.md. Modules: `constants` (versions, limits, field sizes), `layouts`
(names in wire order), `errors` (codes, close codes, ProtocolError, ConnectionUsageError), `tables` (all of
these as tables.json and PROTOCOL.md tables), `messages` (typed messages), `encodings` (frame array
encodings f32/f16/q13), `coords` (FLAME <-> Unity), `avatar` (chunks, client state), `codec`
(bytes <-> messages), `connection` (ServerConnection / ClientConnection state machines).
"""

from .avatar import Avatar, AvatarAssembler, GaussianState, split_avatar
from .codec import (
    decode_client_message,
    decode_server_message,
    encode,
    encode_avatar_chunk,
    encode_frame,
    frame_format,
    member_format,
    read_frame_header,
)
from .connection import ClientConnection, ClientState, ServerConnection, ServerState
from .constants import (
    BYTES_PER_GAUSSIAN,
    COORDS,
    ENCODINGS,
    ENDPOINT,
    LAYOUTS,
    MAX_CLIENT_MESSAGE,
    MAX_SERVER_MESSAGE,
    PROTOCOL_VERSION,
)
from .coords import mirror_x_position, mirror_x_rotation, mirror_x_sh, to_coords
from .encodings import FrameFormat, decode_arrays, encode_arrays, make_quant
from .errors import CLOSE_NORMAL, ERRORS, ConnectionUsageError, ProtocolError, close_code
from .messages import (
    AvatarChunk,
    AvatarInfo,
    Blendshapes,
    Bye,
    ClientMessage,
    ErrorMessage,
    Frame,
    FrameHeader,
    Hello,
    Join,
    Leave,
    Message,
    Ping,
    Pong,
    Quant,
    ServerMessage,
    Welcome,
)

__all__ = [
    "BYTES_PER_GAUSSIAN", "CLOSE_NORMAL", "COORDS", "ENCODINGS", "ENDPOINT", "ERRORS", "LAYOUTS",
    "MAX_CLIENT_MESSAGE", "MAX_SERVER_MESSAGE", "PROTOCOL_VERSION",
    "Avatar", "AvatarAssembler", "AvatarChunk", "AvatarInfo", "Blendshapes", "Bye", "ClientConnection",
    "ClientMessage", "ClientState", "ConnectionUsageError", "ErrorMessage", "Frame", "FrameFormat", "FrameHeader",
    "GaussianState", "Hello", "Join", "Leave", "Message", "Ping", "Pong", "ProtocolError", "Quant", "ServerConnection",
    "ServerMessage", "ServerState", "Welcome",
    "close_code", "decode_arrays", "decode_client_message", "decode_server_message", "encode",
    "encode_arrays", "encode_avatar_chunk", "encode_frame", "frame_format", "make_quant", "member_format",
    "mirror_x_position", "mirror_x_rotation", "mirror_x_sh", "read_frame_header", "split_avatar", "to_coords",
]
