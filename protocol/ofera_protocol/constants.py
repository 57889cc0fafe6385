"""Constants of the OFERA wire protocol v1 (see protocol/PROTOCOL.md)."""

from __future__ import annotations

from .layouts import LAYOUT_NAMES

PROTOCOL_VERSION = 1
"""The only protocol version this codec speaks."""

ENDPOINT = "/v1/stream"
"""WebSocket path of the streaming endpoint."""

LAYOUTS: dict[str, int] = {name: len(names) for name, names in LAYOUT_NAMES.items()}
"""Blendshape layout name -> number of float32 weights in a `bs` message (the names: `layouts.LAYOUT_NAMES`)."""

ENCODINGS: tuple[str, ...] = ("f32", "f16", "q13")
"""Frame encodings, in order of decreasing size."""
PARAMS = "params"
"""`hello.encoding` of expression streaming (PROTOCOL.md 13): frames carry the expression values, the client deforms."""
HELLO_ENCODINGS: tuple[str, ...] = (*ENCODINGS, PARAMS)
"""Every `hello.encoding` / `welcome.encoding`: the frame encodings and `params`."""

FIELD_BYTES: dict[str, tuple[int, int, int]] = {"f32": (12, 16, 12), "f16": (6, 8, 6), "q13": (6, 4, 3)}
"""Frame payload bytes per Gaussian of `position`, `rotation` and `scale` in each encoding (PROTOCOL.md section 6)."""

BYTES_PER_GAUSSIAN: dict[str, int] = {e: sum(sizes) for e, sizes in FIELD_BYTES.items()}
"""Frame payload bytes per Gaussian (position + rotation + scale), excluding a sparse `index`."""

COORDS: tuple[str, ...] = ("flame", "unity")
"""Coordinate conventions: FLAME space (right-handed, y up, face looks +z) or Unity (x mirrored)."""

DEFAULT_ENCODING = "f32"
DEFAULT_COORDS = "flame"
DEFAULT_AVATAR = "default"

MAX_SH_DEGREE = 3

# Limits. A receiver refuses anything larger without allocating it.
MAX_CLIENT_MESSAGE = 64 * 1024
"""Largest client -> server message in bytes (a `bs` of 70 weights is about 320 B)."""
MAX_SERVER_MESSAGE = 64 * 1024 * 1024
"""Largest server -> client message in bytes (a dense f32 frame of 1M Gaussians is 40 MB)."""
MAX_DEPTH = 4
"""Deepest container nesting allowed in a message (the top-level map is depth 1)."""
MAX_CONTAINER_LEN = 256
"""Most entries in any msgpack map or array."""
MAX_STR_LEN = 4096
"""Longest msgpack string in bytes (tokens included)."""
MAX_ID_LEN = 256
"""Longest id-like string (`avatar`, `device`, `session`, timing stage names), in characters."""
MAX_TIMING_STAGES = 64
"""Most entries in a frame's `timing` map."""
ROOM_NAME = r"[A-Za-z0-9._-]{1,64}"
"""A room name (`hello.room`, PROTOCOL.md 12): 1-64 of these characters."""

INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1
UINT32_MAX = 2**32 - 1
