"""A frame message's top-level map without copying its payload: the fast client's way into msgpack.

``msgpack.unpackb`` copies every bin field into a new bytes object: a dense f16 frame of 100k Gaussians is 2 MB
copied once more after the transport wrote it, 0.2-0.36 ms on a cold CPU (benchmarks/README.md, round fourteen).
:func:`scan_frame` reads the same map with each bin as a memoryview of the message itself. It takes only what
frame messages hold (a map of string keys to integers, booleans, nil, strings, bins and one level of nested maps
of such, as ``timing``), and answers None for anything else or anything off (truncated, trailing bytes, a bad
UTF-8 string, another type, a string or map longer than the codec allows): the caller then runs the codec's
``unpack_message``, which names the fault. What it returns is what ``unpack_message`` returns for the same bytes,
but for memoryviews in place of bytes.
"""

from __future__ import annotations

import struct
from typing import Any

from ofera_protocol.constants import MAX_CONTAINER_LEN, MAX_STR_LEN

_FIXED = {0xC0: None, 0xC2: False, 0xC3: True}
_NUMBERS = {0xCC: struct.Struct(">B"), 0xCD: struct.Struct(">H"), 0xCE: struct.Struct(">I"), 0xCF: struct.Struct(">Q"),
            0xD0: struct.Struct(">b"), 0xD1: struct.Struct(">h"), 0xD2: struct.Struct(">i"), 0xD3: struct.Struct(">q")}
_LENGTHS = {0xC4: struct.Struct(">B"), 0xC5: struct.Struct(">H"), 0xC6: struct.Struct(">I"),  # bin 8 / 16 / 32
            0xD9: struct.Struct(">B"), 0xDA: struct.Struct(">H"), 0xDB: struct.Struct(">I"),  # str 8 / 16 / 32
            0xDE: struct.Struct(">H"), 0xDF: struct.Struct(">I")}  # map 16 / 32
_BINS = (0xC4, 0xC5, 0xC6)
_MAPS = (0xDE, 0xDF)


class _Unknown(Exception):
    """Not a map this scanner takes whole."""


def _length(view: memoryview, i: int, tag: int) -> tuple[int, int]:
    """The length that follows tag byte ``i`` (a str, bin or map header), and where its content starts."""
    fmt = _LENGTHS[tag]
    if i + 1 + fmt.size > len(view):
        raise _Unknown
    return fmt.unpack_from(view, i + 1)[0], i + 1 + fmt.size


def _str(view: memoryview, start: int, n: int) -> str:
    if start + n > len(view) or n > MAX_STR_LEN:  # (the codec refuses longer strings)
        raise _Unknown
    try:
        return str(view[start:start + n], "utf-8")
    except UnicodeDecodeError:
        raise _Unknown from None


def _value(view: memoryview, i: int, nested: bool) -> tuple[Any, int]:
    """The value at byte i and the byte after it; a map only where ``nested`` is allowed (the top map's values)."""
    if i >= len(view):
        raise _Unknown
    tag = view[i]
    if tag < 0x80:  # positive fixint
        return tag, i + 1
    if tag >= 0xE0:  # negative fixint
        return tag - 0x100, i + 1
    if 0xA0 <= tag <= 0xBF:  # fixstr
        return _str(view, i + 1, tag & 0x1F), i + 1 + (tag & 0x1F)
    if tag in _FIXED:
        return _FIXED[tag], i + 1
    if tag in _NUMBERS:
        fmt = _NUMBERS[tag]
        if i + 1 + fmt.size > len(view):
            raise _Unknown
        return fmt.unpack_from(view, i + 1)[0], i + 1 + fmt.size
    if tag in _BINS:
        n, start = _length(view, i, tag)
        if start + n > len(view):
            raise _Unknown
        return view[start:start + n], start + n
    if tag in (0xD9, 0xDA, 0xDB):
        n, start = _length(view, i, tag)
        return _str(view, start, n), start + n
    if nested and (0x80 <= tag <= 0x8F or tag in _MAPS):
        return _map(view, i, False)
    raise _Unknown  # floats, arrays, ext, deeper maps: the codec's


def _map(view: memoryview, i: int, nested: bool) -> tuple[dict[str, Any], int]:
    """The map whose header is at byte i (string keys), and the byte after it."""
    tag = view[i]
    if 0x80 <= tag <= 0x8F:
        n, i = tag & 0x0F, i + 1
    elif tag in _MAPS:
        n, i = _length(view, i, tag)
    else:
        raise _Unknown
    if n > MAX_CONTAINER_LEN:  # (the codec refuses larger maps)
        raise _Unknown
    out: dict[str, Any] = {}
    for _ in range(n):
        if i >= len(view):
            raise _Unknown
        tag = view[i]
        if 0xA0 <= tag <= 0xBF:
            k, start = tag & 0x1F, i + 1
        elif tag == 0xD9:
            k, start = _length(view, i, tag)
        else:
            raise _Unknown  # keys are short strings
        key = _str(view, start, k)
        out[key], i = _value(view, start + k, nested)
    return out, i


def scan_frame(data: bytes | bytearray | memoryview, max_size: int) -> dict[str, Any] | None:
    """``data``'s top-level map with bin fields as memoryviews of it (no copy), if it is one this scanner takes
    whole and at most ``max_size`` bytes; None otherwise (then ``ofera_protocol.codec.unpack_message`` decides)."""
    view = memoryview(data).cast("B").toreadonly()  # (read-only: the frames' f32 arrays are views of it, as msgpack's)
    if not 0 < len(view) <= max_size:
        return None
    try:
        m, end = _map(view, 0, True)
    except _Unknown:
        return None
    return m if end == len(view) else None
