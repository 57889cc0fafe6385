"""Typed messages of protocol v1: one dataclass per message `type`.

Arrays are numpy arrays in their decoded form: float32, C-contiguous, with the shapes given per field.
Quaternions are (x, y, z, w). Units: metres, microseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import ClassVar

import numpy as np

from .constants import DEFAULT_AVATAR, DEFAULT_COORDS, DEFAULT_ENCODING, PROTOCOL_VERSION


class _ArrayEq:
    """Field-wise equality that compares numpy arrays by shape, dtype and values."""

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for f in fields(self):  # type: ignore[arg-type]
            if not f.compare:
                continue
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
                    return False
                if a.shape != b.shape or a.dtype != b.dtype or not np.array_equal(a, b, equal_nan=True):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


# ----------------------------------------------------------------------------- client -> server


@dataclass
class Hello:
    """`hello`: opens a session. Only `layout` is required besides the protocol version."""

    TYPE: ClassVar[str] = "hello"
    layout: str
    avatar: str = DEFAULT_AVATAR
    encoding: str = DEFAULT_ENCODING
    coords: str = DEFAULT_COORDS
    sparse: bool = False
    device: str | None = None
    token: str | None = None
    max_gaussians: int | None = None
    protocol: int = PROTOCOL_VERSION
    delta: bool = False
    room: str | None = None  # rooms (PROTOCOL.md 12): join this room; None: a v1 session
    publish: bool = True  # rooms: this client's bs drive its avatar; False: watch only
    self: bool = False  # rooms: also receive one's own avatar stream
    room_token: str | None = None  # rooms: hex HMAC-SHA256 of the room name, if the server asks for one


@dataclass(eq=False)
class Blendshapes(_ArrayEq):
    """`bs`: one face-tracking sample. `w`: (L,) float32 in the session's layout, L = LAYOUTS[layout].
    `conf`: optional (2,) float32 face-tracking confidence [lower face, upper face], each in [0, 1]."""

    TYPE: ClassVar[str] = "bs"
    seq: int
    t: int
    w: np.ndarray
    conf: np.ndarray | None = None


@dataclass
class Ping:
    """`ping`: `t` is echoed in `pong` (sender's clock, microseconds)."""

    TYPE: ClassVar[str] = "ping"
    t: int


@dataclass
class Bye:
    """`bye`: the client ends the session; the server closes with 1000."""

    TYPE: ClassVar[str] = "bye"


@dataclass
class Resync:
    """`resync`: a delta-session client asks for a key frame (its state is lost or a delta frame failed)."""

    TYPE: ClassVar[str] = "resync"


# ----------------------------------------------------------------------------- server -> client


@dataclass(eq=False)
class Quant(_ArrayEq):
    """Quantisation parameters of `q13`, fixed for a session.

    pos_min, pos_max: (3,) float32, metres, the box positions are quantised in (pos_max > pos_min).
    log_scale: (2,) float32, [min, max] of ln(scale in metres) (max > min).
    """

    pos_min: np.ndarray
    pos_max: np.ndarray
    log_scale: np.ndarray


@dataclass
class AvatarInfo:
    """`welcome.avatar`: the avatar streamed in this session. `expression`: what drives it, "flame68" (the
    EPM's FLAME values) or "arkit51" (the aligned ARKit weights themselves; an ARKit-bound avatar, e.g. LAM)."""

    id: str
    count: int
    sh_degree: int
    expression: str = "flame68"


@dataclass(eq=False)
class Welcome(_ArrayEq):
    """`welcome`: the server accepted `hello`. Echoes the settings in force for the session."""

    TYPE: ClassVar[str] = "welcome"
    session: str
    avatar: AvatarInfo | None  # None only in a watch-only room session
    layout: str
    encoding: str = DEFAULT_ENCODING
    coords: str = DEFAULT_COORDS
    sparse: bool = False
    quant: Quant | None = None  # present iff encoding == "q13"
    server: str | None = None
    protocol: int = PROTOCOL_VERSION
    delta: bool = False  # frames are key or delta frames (PROTOCOL.md 7.1)
    room: str | None = None  # rooms (PROTOCOL.md 12): the room joined
    member: str | None = None  # rooms: this client's member id, unique in the room
    rig_bytes: int | None = None  # params sessions (PROTOCOL.md 13): size of the rig body the `rig` messages carry


@dataclass(eq=False)
class AvatarChunk(_ArrayEq):
    """`avatar`: Gaussians [offset, offset + n) of the avatar, chunk `chunk` of `chunks`.

    opacity (n,) linear 0..1; sh (n, (sh_degree+1)**2, 3) raw SH coefficients (3DGS order, RGB last);
    position (n, 3) metres, neutral expression; rotation (n, 4) unit quaternion (x, y, z, w);
    scale (n, 3) linear metres. All float32, in the session's coordinates.
    """

    TYPE: ClassVar[str] = "avatar"
    count: int
    sh_degree: int
    chunk: int
    chunks: int
    offset: int
    opacity: np.ndarray
    sh: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    member: str | None = None  # rooms: whose avatar this is (None in a v1 session)

    @property
    def n(self) -> int:
        """Number of Gaussians in this chunk."""
        return int(self.opacity.shape[0])


@dataclass(eq=False)
class Frame(_ArrayEq):
    """`frame`: the Gaussians computed from `bs` number `seq` (its `t` echoed).

    position (n, 3) metres, rotation (n, 4) quaternion (x, y, z, w), scale (n, 3) metres, float32.
    index: None for a dense frame (n == avatar count), else (n,) uint32 strictly ascending ids of the
    Gaussians carried (sparse sessions only). timing: stage name -> duration in microseconds.
    """

    TYPE: ClassVar[str] = "frame"
    seq: int
    t: int
    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    index: np.ndarray | None = None
    timing: dict[str, int] = field(default_factory=dict)
    key: bool | None = None  # delta sessions: True for a key frame, False for an applied delta frame
    codes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, compare=False, repr=False)
    """Key frames of a delta session: the wire codes (position, rotation, scale) the client holds from now."""
    member: str | None = None  # rooms: whose avatar this frame moves (None in a v1 session)

    @property
    def n(self) -> int:
        """Number of Gaussians carried."""
        return int(self.position.shape[0])


@dataclass(eq=False)
class DeltaFrame(_ArrayEq):
    """`frame` with `key: false` in a delta session (PROTOCOL.md 7.1), as on the wire: `index` (n,) uint32 the
    changed Gaussians (the `changed` mask); `moved` (n, 3) bool: which of position, rotation, scale each carries
    (the `moved_*` masks); `wide` (n_p,) bool over the n_p carrying a position; `position_delta` (n_p - w, 3) int8
    code changes; `position` (w, 3), `rotation` (n_r,) / (n_r, 4) and `scale` (n_s, 3) codes (q13: uint16, uint32,
    uint8; f16: float16 arrays whose bits are the codes). `DeltaDecoder.apply` turns it into a Frame."""

    TYPE: ClassVar[str] = "frame"
    seq: int
    t: int
    timing: dict[str, int]
    index: np.ndarray
    moved: np.ndarray
    wide: np.ndarray
    position_delta: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    key: bool = False

    @property
    def n(self) -> int:
        return int(self.index.shape[0])


@dataclass
class ErrorMessage:
    """`error`: `code` is a stable string (see errors.ERRORS); `seq` names the offending `bs` if known."""

    TYPE: ClassVar[str] = "error"
    code: str
    message: str
    fatal: bool
    seq: int | None = None


@dataclass
class Pong:
    """`pong`: answers `ping`, echoing its `t`."""

    TYPE: ClassVar[str] = "pong"
    t: int


@dataclass(eq=False)
class Join(_ArrayEq):
    """`join` (rooms, PROTOCOL.md 12): `member` is in the room. A publishing member's `avatar` (in this viewer's
    reduction) follows as `avatar` messages carrying `member`; `quant`: that avatar's q13 parameters (q13 viewers).
    A watch-only member (`publish` False) has no avatar."""

    TYPE: ClassVar[str] = "join"
    member: str
    avatar: AvatarInfo | None = None
    quant: Quant | None = None
    publish: bool = True


@dataclass
class Leave:
    """`leave` (rooms): `member` left the room; `reason` (PROTOCOL.md 12.5) says why."""

    TYPE: ClassVar[str] = "leave"
    member: str
    reason: str


@dataclass(eq=False)
class RigChunk(_ArrayEq):
    """`rig` (params sessions, PROTOCOL.md 13): bytes [offset, offset + len(data)) of the rig body (`size` bytes
    in all), chunk `chunk` of `chunks`; `member` in a room session (whose avatar the rig deforms). `data`: (len,)
    uint8."""

    TYPE: ClassVar[str] = "rig"
    chunk: int
    chunks: int
    size: int
    offset: int
    data: np.ndarray
    member: str | None = None


@dataclass(frozen=True)
class ParamsFormat:
    """What a receiver needs to decode a params session's frames: `length` float32 values (68 FLAME values). Never
    sparse, never deltas (like a FrameFormat's flags)."""

    length: int = 68
    sparse: ClassVar[bool] = False
    delta: ClassVar[bool] = False


@dataclass(eq=False)
class ParamsFrame(_ArrayEq):
    """`frame` of a params session (PROTOCOL.md 13): `params` (length,) float32 expression values (FLAME: 50
    expression, jaw, left eye, right eye 6D). `seq`, `t` and `timing` only on stamped frames (None otherwise)."""

    TYPE: ClassVar[str] = "frame"
    params: np.ndarray
    seq: int | None = None
    t: int | None = None
    timing: dict[str, int] | None = None
    member: str | None = None


ClientMessage = Hello | Blendshapes | Ping | Bye | Resync
@dataclass
class FrameHeader:
    """The small fields of a `frame` (codec.read_frame_header), its arrays neither decoded nor checked.

    `size`: the message's bytes. `n`: Gaussians carried (None for a params frame, PROTOCOL.md 13); `key`: delta
    sessions only (PROTOCOL.md 7.1); `member`: rooms only. `seq`, `t` and `timing` are None only on an unstamped
    params frame (`timing` also on a stamped one that carries none)."""

    TYPE: ClassVar[str] = "frame"
    seq: int | None
    t: int | None
    timing: dict[str, int] | None
    size: int
    n: int | None = None
    key: bool | None = None
    member: str | None = None


ServerMessage = Welcome | AvatarChunk | Frame | DeltaFrame | ErrorMessage | Pong | Join | Leave | RigChunk | ParamsFrame
Message = ClientMessage | ServerMessage

CLIENT_TYPES: dict[str, type] = {c.TYPE: c for c in (Hello, Blendshapes, Ping, Bye, Resync)}
SERVER_TYPES: dict[str, type] = {c.TYPE: c for c in (Welcome, AvatarChunk, Frame, ErrorMessage, Pong, Join, Leave,
                                                  RigChunk)}
