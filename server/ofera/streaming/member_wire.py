"""Rooms: everything a viewer of one wire format needs for one member (its `join`, avatar messages, `rig` messages
for params viewers, and the writer of its frames), made once and shared by every viewer of that format; and the
parts of a params session (`streaming.params`, PROTOCOL.md 13)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ofera_protocol import (
    AvatarInfo,
    FrameFormat,
    Hello,
    ProtocolError,
    ServerConnection,
    encode,
    encode_avatar_chunk,
    split_avatar,
)
from ofera_protocol.constants import PARAMS
from ofera_protocol.errors import UNKNOWN_ENCODING
from ofera_protocol.messages import Join

from . import params
from .config import Settings
from .pipeline import AvatarAssets
from .roles import SessionFatal
from .wire import make_writer, reduced_size


def params_parts(conn: ServerConnection, assets: AvatarAssets, hello: Hello, member: str | None, chunk_bytes: int
                 ) -> tuple[Any, list[bytes]]:
    """(writer, `rig` messages) of the params encoding (`streaming.params`, PROTOCOL.md 13): a writer with
    `needs_state = False` and the messages that follow the avatar messages."""
    rig = params.rig_messages(conn, assets, hello.coords, hello.max_gaussians, member, chunk_bytes)
    return params.ParamsWriter(), rig


def params_rig_size(assets: AvatarAssets, max_gaussians: int | None) -> int:
    """`welcome.rig_bytes` of a v1 params session (blocking: builds the rig once per avatar and size). An avatar
    without a rig (ARKit-driven) ends the session with a fatal `unknown_encoding` naming why (SessionFatal)."""
    try:
        return params.rig_size(assets, max_gaussians)
    except params.RigError as exc:
        raise SessionFatal(ProtocolError(UNKNOWN_ENCODING, str(exc), True)) from None


def wire_key(hello: Hello, size: int | None) -> tuple:
    """What viewers must share to share a frame's bytes: encoding, coords, sparse and the reduced size."""
    return (hello.encoding, hello.coords, hello.sparse, size)


@dataclass
class MemberWire:
    """One member's avatar in one wire format: `messages` (its `join`, `avatar` chunks with `member`, and `rig`
    messages for params viewers), the `writer` of its frames and the `key` frames are cached under."""

    member: str
    messages: list[bytes]
    writer: Any  # FrameEncoder, or a writer with needs_state False (params)
    key: tuple
    count: int

    @property
    def needs_state(self) -> bool:
        return bool(getattr(self.writer, "needs_state", True))


def prepare_member_wire(conn: ServerConnection, assets: AvatarAssets, member: str, hello: Hello, settings: Settings
                        ) -> MemberWire:
    """Blocking (run it in the executor): `member`'s avatar `assets` in the wire format of a viewer whose hello is
    `hello` (`conn`: that viewer's connection, for the params encoding's rig messages)."""
    size = reduced_size(hello.max_gaussians, assets.count)
    wire = assets.wire_avatar(hello.coords, size)
    quant = assets.quant(hello.coords, size) if hello.encoding == "q13" else None
    info = AvatarInfo(id=assets.id, count=wire.count, sh_degree=wire.sh_degree, expression=assets.expression)
    chunks = split_avatar(wire, settings.avatar_chunk_bytes)
    for c in chunks:
        c.member = member
    messages = [encode(Join(member=member, avatar=info, quant=quant)), *(encode_avatar_chunk(c) for c in chunks)]
    if hello.encoding == PARAMS:
        writer, rig = params_parts(conn, assets, hello, member, settings.avatar_chunk_bytes)
        messages += rig
    else:
        gather, index = assets.selection(hello.sparse, size)
        fmt = FrameFormat(encoding=hello.encoding, count=wire.count, sparse=hello.sparse, quant=quant)
        writer = make_writer(fmt, hello.coords, gather, index, settings.fast)
    return MemberWire(member, messages, writer, wire_key(hello, size), wire.count)
