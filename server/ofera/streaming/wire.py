"""A viewer's wire format: the frame encoder of one format (fast or reference) and the reduced avatar size a client
may ask for (rooms: `member_wire`)."""

from __future__ import annotations

import math

import numpy as np
from ofera_protocol import FrameFormat

from .config import Settings
from .roles import CodecWriter, FrameEncoder


def make_writer(fmt: FrameFormat, coords: str, gather: np.ndarray | None, index: np.ndarray | None, fast: bool,
                stamp_encode: bool = True) -> FrameEncoder:
    """The frame encoder of one wire format: numba kernels writing straight into the message buffer
    (`encode_fast`, byte-identical to the codec) when `fast`, else the codec's reference encoder. `stamp_encode`
    (fast only): each frame's `timing.encode` is its own encoding time (us), written into the header last."""
    if fast:
        from .encode_fast import frame_writer

        return frame_writer(fmt, coords, gather, index, stamp_encode=stamp_encode)
    return CodecWriter(fmt, coords, gather, index)


def make_delta_writer(fmt: FrameFormat, coords: str, gather: np.ndarray | None, movable: tuple, settings: Settings
                      ) -> FrameEncoder:
    """The DeltaEncoder of one delta session (PROTOCOL.md 7.1): numba kernels when `settings.fast`, else the numpy
    reference; candidates = the avatar's movable Gaussians (`movable` = (state rows, session ids)). Its frames'
    timing carries "encode"."""
    from ofera_protocol.delta import DeltaEncoder, DeltaTolerance

    rows, ids = np.asarray(movable[0], np.int64), np.asarray(movable[1], np.int64)
    tol = DeltaTolerance(settings.delta_position_mm * 1e-3, settings.delta_rotation_deg, settings.delta_log_scale)
    if settings.fast:
        from .encode_fast import delta_encoder

        return delta_encoder(fmt, coords, gather, ids, rows, tol, settings.key_interval, stamp_encode=True)
    return DeltaEncoder(fmt, coords, gather, ids, rows, tolerance=tol, key_interval=settings.key_interval,
                        stamp_encode=True)


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
