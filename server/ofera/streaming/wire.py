"""A viewer's wire format: the frame encoder of one format (fast or reference), the reduced avatar size a client may
ask for, and, for rooms, everything a viewer of one wire format needs for one member (its `join`, avatar messages
and frame writer), made once and shared by every viewer of that format."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from ofera_protocol import AvatarInfo, FrameFormat, Hello, ServerConnection, encode, encode_avatar_chunk, split_avatar
from ofera_protocol.messages import Join

from .config import Settings
from .pipeline import AvatarAssets
from .roles import CodecWriter, FrameEncoder

log = logging.getLogger("ofera.streaming")

PARAMS = "params"
"""The encoding whose frames carry expression values (issue 18, `streaming.params`), when that module is there."""


def make_writer(fmt: FrameFormat, coords: str, gather: np.ndarray | None, index: np.ndarray | None, fast: bool
                ) -> FrameEncoder:
    """The frame encoder of one wire format: numba kernels writing straight into the message buffer
    (`encode_fast`, byte-identical to the codec) when `fast`, else the codec's reference encoder."""
    if fast:
        from .encode_fast import frame_writer

        return frame_writer(fmt, coords, gather, index)
    return CodecWriter(fmt, coords, gather, index)


def make_delta_writer(fmt: FrameFormat, coords: str, gather: np.ndarray | None, movable: tuple, settings: Settings
                      ) -> FrameEncoder:
    """The DeltaEncoder of one delta session (PROTOCOL.md 7.1): numba kernels when `settings.fast`, else the numpy
    reference; candidates = the avatar's movable Gaussians (`movable` = (state rows, session ids))."""
    from ofera_protocol.delta import DeltaEncoder, DeltaTolerance

    rows, ids = movable
    tol = DeltaTolerance(settings.delta_position_mm * 1e-3, settings.delta_rotation_deg, settings.delta_log_scale)
    kernels = None
    if settings.fast:
        from .encode_fast import numba_kernels

        kernels = numba_kernels()
    return DeltaEncoder(fmt, coords, gather, np.asarray(ids, np.int64), np.asarray(rows, np.int64), kernels=kernels,
                        tolerance=tol, key_interval=settings.key_interval)


def reduced_size(asked: int | None, count: int) -> int | None:
    """How many Gaussians to stream to a client that renders at most `asked` (hello.max_gaussians): None (the
    whole avatar) when it fits, else the largest count x 2^(-k/4), k >= 1, not above `asked` (at most 16 %
    fewer than asked). Avatars cache each reduction they serve, so arbitrary sizes chosen by clients would
    grow the server's memory without bound; these sizes are at most 4 log2(count) + 1 per avatar."""
    if asked is None or asked >= count:
        return None
    k = max(1, math.floor(-4 * math.log2(asked / count)))
    while int(count * 2.0 ** (-k / 4)) > asked:
        k += 1
    return max(1, int(count * 2.0 ** (-k / 4)))


def params_parts(conn: ServerConnection, assets: AvatarAssets, hello: Hello, size: int | None, member: str | None,
                 chunk_bytes: int) -> tuple[Any, list[bytes]]:
    """(writer, `rig` messages) of the params encoding (`streaming.params`, issue 18): a writer with
    `needs_state = False` and the messages that follow the avatar messages. RuntimeError while that module is
    missing."""
    try:
        from . import params  # type: ignore[attr-defined]
    except ImportError as exc:
        raise RuntimeError("the params encoding is not available on this server (streaming.params missing)") from exc
    rig = params.rig_messages(conn, assets, hello.coords, size, member, chunk_bytes)
    return params.ParamsWriter(assets, hello.coords, size), rig


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
        writer, rig = params_parts(conn, assets, hello, size, member, settings.avatar_chunk_bytes)
        messages += rig
    else:
        gather, index = assets.selection(hello.sparse, size)
        fmt = FrameFormat(encoding=hello.encoding, count=wire.count, sparse=hello.sparse, quant=quant)
        writer = make_writer(fmt, hello.coords, gather, index, settings.fast)
    return MemberWire(member, messages, writer, wire_key(hello, size), wire.count)
