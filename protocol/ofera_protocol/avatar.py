"""The static avatar sent once per session: splitting into `avatar` chunks, reassembling them, and the
client-side state that frames (dense or sparse) update."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .constants import MAX_SH_DEGREE, UINT32_MAX
from .errors import BAD_FIELD, ProtocolError
from .messages import AvatarChunk, Frame, _ArrayEq

DEFAULT_CHUNK_BYTES = 4 * 1024 * 1024
"""Default upper bound on the array bytes of one `avatar` message."""


def sh_coeffs(sh_degree: int) -> int:
    """Number of SH coefficients per colour channel: (degree + 1)^2."""
    return (sh_degree + 1) ** 2


def avatar_bytes_per_gaussian(sh_degree: int) -> int:
    """Array bytes per Gaussian in an `avatar` message: opacity 4 + sh 12 K + position 12 + rotation 16
    + scale 12."""
    return 4 + 12 * sh_coeffs(sh_degree) + 12 + 16 + 12


@dataclass(eq=False)
class Avatar(_ArrayEq):
    """A whole avatar. opacity (N,) 0..1; sh (N, K, 3) with K = (deg+1)^2; position (N, 3) m;
    rotation (N, 4) unit quaternion (x, y, z, w); scale (N, 3) m. float32, session coordinates."""

    opacity: np.ndarray
    sh: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray

    def __post_init__(self) -> None:
        n = self.opacity.shape[0] if self.opacity.ndim == 1 else -1
        k = self.sh.shape[1] if self.sh.ndim == 3 else -1
        degrees = [d for d in range(MAX_SH_DEGREE + 1) if sh_coeffs(d) == k]
        if (n < 0 or not degrees or self.sh.shape != (n, k, 3) or self.position.shape != (n, 3)
                or self.rotation.shape != (n, 4) or self.scale.shape != (n, 3) or n > UINT32_MAX):
            raise ValueError(
                "avatar arrays must be opacity (N,), sh (N, (d+1)^2, 3) with d <= 3, position (N, 3), "
                f"rotation (N, 4), scale (N, 3); got {self.opacity.shape}, {self.sh.shape}, "
                f"{self.position.shape}, {self.rotation.shape}, {self.scale.shape}")
        for name in ("opacity", "sh", "position", "rotation", "scale"):
            a = getattr(self, name)
            if a.dtype != np.float32:
                setattr(self, name, a.astype(np.float32))

    @property
    def count(self) -> int:
        return int(self.opacity.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1


def split_avatar(avatar: Avatar, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES) -> list[AvatarChunk]:
    """Cut `avatar` into consecutive chunks of at most `max_chunk_bytes` array bytes (at least one
    Gaussian per chunk, and one empty chunk for an empty avatar). Chunks hold views, not copies."""
    per = avatar_bytes_per_gaussian(avatar.sh_degree)
    step = max(1, max_chunk_bytes // per)
    n = avatar.count
    starts = list(range(0, n, step)) or [0]
    return [
        AvatarChunk(count=n, sh_degree=avatar.sh_degree, chunk=c, chunks=len(starts), offset=s,
                    opacity=avatar.opacity[s:s + step], sh=avatar.sh[s:s + step],
                    position=avatar.position[s:s + step], rotation=avatar.rotation[s:s + step],
                    scale=avatar.scale[s:s + step])
        for c, s in enumerate(starts)
    ]


class AvatarAssembler:
    """Collects the `avatar` chunks of one session, which must arrive in order without gaps."""

    def __init__(self, count: int, sh_degree: int) -> None:
        self.count = count
        self.sh_degree = sh_degree
        self._chunks: list[AvatarChunk] = []
        self._next_offset = 0
        self._total: int | None = None

    @property
    def complete(self) -> bool:
        return self._total is not None and len(self._chunks) == self._total

    def add(self, chunk: AvatarChunk) -> bool:
        """Add the next chunk; True once the avatar is complete. ProtocolError `bad_field` if it does
        not continue the sequence (count, degree, chunk number, offset, or too many Gaussians)."""
        if self.complete:
            raise ProtocolError(BAD_FIELD, "avatar chunk after the avatar was complete")
        expected = len(self._chunks)
        problems = []
        if chunk.count != self.count:
            problems.append(f"count {chunk.count} != welcome's {self.count}")
        if chunk.sh_degree != self.sh_degree:
            problems.append(f"sh_degree {chunk.sh_degree} != welcome's {self.sh_degree}")
        if chunk.chunk != expected:
            problems.append(f"chunk {chunk.chunk} arrived, expected {expected}")
        if self._total is not None and chunk.chunks != self._total:
            problems.append(f"chunks {chunk.chunks} != {self._total} announced before")
        if chunk.offset != self._next_offset:
            problems.append(f"offset {chunk.offset} != {self._next_offset}")
        last = chunk.chunk == chunk.chunks - 1
        if last and chunk.offset + chunk.n != self.count:
            problems.append(f"last chunk ends at {chunk.offset + chunk.n}, avatar has {self.count}")
        if problems:
            raise ProtocolError(BAD_FIELD, "bad avatar chunk: " + "; ".join(problems))
        self._total = chunk.chunks
        self._chunks.append(chunk)
        self._next_offset += chunk.n
        return self.complete

    def result(self) -> Avatar:
        """The whole avatar (new arrays). Only once `complete`."""
        if not self.complete:
            raise RuntimeError("avatar is not complete")

        def cat(name: str) -> np.ndarray:
            return np.concatenate([getattr(c, name) for c in self._chunks], axis=0)

        return Avatar(opacity=cat("opacity"), sh=cat("sh"), position=cat("position"),
                      rotation=cat("rotation"), scale=cat("scale"))


class GaussianState:
    """The client's current position/rotation/scale of every Gaussian, float32 (N, 3/4/3).

    Starts from the neutral avatar; a dense frame replaces everything, a sparse frame replaces the
    listed Gaussians and leaves the others at their latest value.
    """

    def __init__(self, position: np.ndarray, rotation: np.ndarray, scale: np.ndarray) -> None:
        self.position = np.array(position, dtype=np.float32, copy=True)
        self.rotation = np.array(rotation, dtype=np.float32, copy=True)
        self.scale = np.array(scale, dtype=np.float32, copy=True)

    @classmethod
    def from_avatar(cls, avatar: Avatar) -> GaussianState:
        return cls(avatar.position, avatar.rotation, avatar.scale)

    def apply(self, frame: Frame) -> None:
        """Update from a decoded, validated frame."""
        if frame.index is None:
            self.position[...] = frame.position
            self.rotation[...] = frame.rotation
            self.scale[...] = frame.scale
        else:
            self.position[frame.index] = frame.position
            self.rotation[frame.index] = frame.rotation
            self.scale[frame.index] = frame.scale
