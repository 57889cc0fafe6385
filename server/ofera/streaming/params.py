"""The params encoding on the server (PROTOCOL.md 13): a client deforms the avatar itself.

- `rig_messages(conn, assets, coords, max_gaussians, member, chunk_bytes)`: the `rig` messages of one avatar (its
  rig body built once per avatar and reduction, cached in the assets), sent after its `avatar` messages;
- `rig_size(assets, max_gaussians)`: the body's size in bytes, for `welcome.rig_bytes`;
- `ParamsWriter`: encodes a frame from its expression values (`needs_state = False`: the source need not deform
  for it), stamping `seq`, `t` and `timing` on the first frame and then at least once per `stamp_interval` s.

Refusals: an avatar the rig cannot describe (ARKit-driven, vertex-bound) has no rig: `rig_body`, `rig_size` and
`rig_messages` raise `avatar.rig.RigError` naming the reason (a v1 session turns it into a fatal `unknown_encoding`
before welcome, `member_wire.params_rig_size`; rooms show that member to params viewers as a watch-only join).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable

import numpy as np
from ofera_protocol import ConnectionUsageError, ServerConnection, encode
from ofera_protocol.constants import COORDS, PARAMS
from ofera_protocol.messages import ParamsFrame
from ofera_protocol.rig import DEFAULT_RIG_CHUNK_BYTES, encode_rig, split_rig

from ..avatar.rig import RigError, build_rig
from .pipeline import AvatarAssets
from .wire import reduced_size

PARAMS_LENGTH = 68
"""Values in a params frame: the EPM's FLAME values."""
STAMP_INTERVAL_S = float(os.environ.get("OFERA_PARAMS_STAMP_INTERVAL", "1.0"))
"""The reference server stamps (seq, t, timing) one params frame per second at least (PROTOCOL.md 13.5). The
environment variable OFERA_PARAMS_STAMP_INTERVAL (seconds, read at import) changes it: benchmarks set 0 to stamp
every frame, so that every frame's latency can be measured."""

__all__ = ["PARAMS_LENGTH", "STAMP_INTERVAL_S", "ParamsWriter", "RigError", "rig_body", "rig_messages", "rig_size"]

_build_lock = threading.Lock()


def rig_body(assets: AvatarAssets, max_gaussians: int | None) -> bytes:
    """The rig body of `assets` reduced to `max_gaussians` (hello.max_gaussians; None: the whole avatar): the movable
    Gaussians of the session's avatar in its numbering. Built once, cached in the assets; RigError if the avatar has
    no rig (see the module docstring)."""
    size = reduced_size(max_gaussians, assets.count)
    key = ("rig", size)
    body = assets._cache.get(key)
    if body is None:
        with _build_lock:  # two sessions of a new avatar at once build it once
            body = assets._cache.get(key)
            if body is None:
                rows, ids = assets.selection(True, size)  # state rows, session ids of the movable Gaussians
                count = assets.count if size is None else size
                rig = build_rig(assets.avatar, assets.subject, rows, ids, count)
                body = assets._cache[key] = encode_rig(rig)
    return body


def rig_size(assets: AvatarAssets, max_gaussians: int | None) -> int:
    """`welcome.rig_bytes` of a params session: the size of `rig_body` in bytes."""
    return len(rig_body(assets, max_gaussians))


def rig_messages(conn: ServerConnection, assets: AvatarAssets, coords: str, max_gaussians: int | None,
                 member: str | None, chunk_bytes: int = DEFAULT_RIG_CHUNK_BYTES) -> list[bytes]:
    """The `rig` messages of one avatar for a params session (`conn`: the viewer's connection, which asked for params
    in its hello), each carrying `member` in a room (None outside rooms), at most `chunk_bytes` of body each. The
    rig is in FLAME space whatever `coords` (the client mirrors what it deforms, PROTOCOL.md 13.4)."""
    hello = conn.hello
    if hello is None or hello.encoding != PARAMS:
        raise ConnectionUsageError("rig messages are for a connection whose hello asked for encoding params")
    if coords not in COORDS:
        raise ConnectionUsageError(f"unknown coords {coords!r}; expected one of {COORDS}")
    return [encode(c) for c in split_rig(rig_body(assets, max_gaussians), chunk_bytes, member)]


class ParamsWriter:
    """Encodes params frames (PROTOCOL.md 13.5) from a frame's expression values; one per wire format, shared by its
    viewers (the values do not depend on coords or reduction); `stamp_interval` seconds between stamped frames (None:
    STAMP_INTERVAL_S). Thread-safe."""

    needs_state = False

    def __init__(self, stamp_interval: float | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.stamp_interval = STAMP_INTERVAL_S if stamp_interval is None else stamp_interval
        self.clock = clock
        self._last: dict[str | None, float] = {}  # member -> clock of its last stamped frame
        self._lock = threading.Lock()
        self.stamped = 0

    def _stamp(self, member: str | None) -> bool:
        now = self.clock()
        with self._lock:
            last = self._last.get(member)
            if last is not None and now - last < self.stamp_interval:
                return False
            self._last[member] = now
            self.stamped += 1
            return True

    def encode_values(self, seq: int, t: int, timing: dict[str, int], values: np.ndarray, member: str | None
                      ) -> bytes:
        """One params frame: `values` (68,) float32 FLAME values from `Pipeline.map`; `seq`, `t`, `timing` written
        only when this frame is stamped. ValueError on values of another length or non-finite ones."""
        v = np.ascontiguousarray(values, "<f4").reshape(-1)
        if v.shape != (PARAMS_LENGTH,) or not np.isfinite(v).all():
            raise ValueError(f"params frames carry {PARAMS_LENGTH} finite float32 values, got shape {v.shape}")
        if self._stamp(member):
            return encode(ParamsFrame(params=v, seq=seq, t=t, timing=timing, member=member))
        return encode(ParamsFrame(params=v, member=member))
