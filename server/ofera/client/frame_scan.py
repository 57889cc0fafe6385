"""A frame message's top-level map without copying its payload: the fast client's way into msgpack.

``msgpack.unpackb`` copies every bin field into a new bytes object: a dense f16 frame of 100k Gaussians is 2 MB
copied once more after the transport wrote it, 0.2-0.36 ms on a cold CPU (benchmarks/README.md, round fourteen).
:func:`scan_frame` reads the same map with each bin as a memoryview of the message itself. It takes only what
frame messages hold (a map of string keys to integers, booleans, nil, strings, bins and one level of nested maps
of such, as ``timing``), and answers None for anything else or anything off (truncated, trailing bytes, a bad
UTF-8 string, another type, a string or map longer than the codec allows): the caller then runs the codec's
``unpack_message``, which names the fault. What it returns is what ``unpack_message`` returns for the same bytes,
but for memoryviews in place of bytes.

A delta frame needs no map at all: :func:`scan_delta_frame` (numba) finds where each of its fields is in the message,
which the decoder's kernel then reads in place (16 us on a cold CPU, where the Python scanner took 134 and msgpack
138, round fourteen).
"""

from __future__ import annotations

import struct
from typing import Any

import numba as nb
import numpy as np
from ofera_protocol.constants import MAX_CONTAINER_LEN, MAX_STR_LEN
from ofera_protocol.delta import DELTA_BINS

from ..jit import NB as _NB

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


# ----------------------------------------------------------------------------- a delta frame's fields, in numba

DELTA_FIELDS = ("type", "seq", "t", "timing", "key", "n", "member", *DELTA_BINS)
"""The keys of a delta frame's map (``member`` optional), in the rows of :func:`scan_delta_frame`'s ``fields``."""
SEQ, T, N, MEMBER, BINS = 1, 2, 5, 6, 7  # rows of fields: the integers' values; member's and the bins' (start, length)
_TYPE, _TIMING, _KEY = 0, 3, 4


def _name_table(names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Short ASCII names as rows of bytes (K, 16) uint8 and their lengths (K,) int64 (numba's constants)."""
    table = np.zeros((len(names), 16), np.uint8)
    for row, name in enumerate(names):
        table[row, :len(name)] = np.frombuffer(name.encode(), np.uint8)
    return table, np.array([len(k) for k in names], np.int64)


_NAMES, _NAME_LENGTHS = _name_table(DELTA_FIELDS)
_REQUIRED = ((1 << len(DELTA_FIELDS)) - 1) & ~(1 << MEMBER)
_FRAME = np.frombuffer(b"\xa5frame", np.uint8)  # the type's value: fixstr "frame"
_INT64_MAX = np.uint64(2**63 - 1)


@nb.njit(inline="always", **_NB)
def _field(buf, i, k):
    """The row of DELTA_FIELDS whose name is buf[i:i + k], or -1."""
    for f in range(_NAMES.shape[0]):
        if _NAME_LENGTHS[f] == k:
            same = True
            for c in range(k):
                same &= buf[i + c] == _NAMES[f, c]
            if same:
                return f
    return -1


@nb.njit(inline="always", **_NB)
def _int(buf, i):
    """The msgpack integer at buf[i] (any width; a uint64 above INT64_MAX refused): (ok, value, next byte)."""
    n = buf.shape[0]
    tag = np.int64(buf[i])
    if tag < 0x80:
        return True, tag, i + 1
    if tag >= 0xE0:
        return True, tag - 256, i + 1
    if 0xCC <= tag <= 0xCF:
        size, signed = 1 << (tag - 0xCC), False
    elif 0xD0 <= tag <= 0xD3:
        size, signed = 1 << (tag - 0xD0), True
    else:
        return False, np.int64(0), i
    if i + 1 + size > n:
        return False, np.int64(0), i
    v = np.uint64(0)
    for c in range(size):
        v = (v << np.uint64(8)) | np.uint64(buf[i + 1 + c])
    if signed and size < 8 and v >> np.uint64(8 * size - 1):
        v |= ~np.uint64(0) << np.uint64(8 * size)  # sign-extend
    if not signed and v > _INT64_MAX:
        return False, np.int64(0), i
    return True, np.int64(v), i + 1 + size


@nb.njit(inline="always", **_NB)
def _sized(buf, i, width):
    """The big-endian length of ``width`` bytes after tag byte i: (its start, the length), or (-1, 0) past the end."""
    if i + 1 + width > buf.shape[0]:
        return -1, 0
    v = 0
    for c in range(width):
        v = (v << 8) | np.int64(buf[i + 1 + c])
    return i + 1 + width, v


@nb.njit(inline="always", **_NB)
def delta_bin(buf, fields, j):
    """The j-th bin of a scanned delta frame (0 = changed ... 8 = scale: DELTA_FIELDS from BINS), a view of buf."""
    start = fields[BINS + j, 0]
    return buf[start:start + fields[BINS + j, 1]]


@nb.njit(**_NB)
def scan_delta_frame(buf, fields, timing):
    """A delta frame's map (PROTOCOL.md 7.1) as received (buf (size,) uint8) into ``fields`` (len(DELTA_FIELDS), 2)
    int64: the integers' values (row, 0) and member's (start -1 if none) and each bin's (start, length) in buf;
    ``timing`` (>= 15, 3) int64: each stage name's (start, length) and its duration. Returns the number of
    stages, or -1 for anything but a plain delta frame: type "frame", key false, every field once (fixstr keys,
    known ones only), integers of any width, a timing map of at most 64 stages of short names and durations 0 ..
    INT64_MAX, nothing after the map; the caller then reads the message as the codec does (which names any fault).
    The checks of the fields' values (ranges, lengths, masks) are the caller's."""
    size = buf.shape[0]
    fields[MEMBER, 0] = -1  # (none unless the map has one)
    if size < 3:
        return -1
    tag = np.int64(buf[0])
    if 0x80 <= tag <= 0x8F:
        count, i = tag & 0x0F, 1
    elif tag == 0xDE:
        i, count = _sized(buf, 0, 2)
    else:
        return -1
    seen, stages = 0, 0
    for _ in range(count):
        if i >= size or not 0xA0 <= buf[i] <= 0xBF:
            return -1
        k = np.int64(buf[i] & 0x1F)
        if i + 1 + k >= size:
            return -1
        f = _field(buf, i + 1, k)
        if f < 0 or seen >> f & 1:
            return -1
        seen |= 1 << f
        i += 1 + k
        tag = np.int64(buf[i])
        if f == _TYPE:
            if i + 6 > size:
                return -1
            for c in range(6):
                if buf[i + c] != _FRAME[c]:
                    return -1
            i += 6
        elif f == _KEY:
            if tag != 0xC2:
                return -1
            i += 1
        elif f == _TIMING:
            if not 0x80 <= tag <= 0x8F:
                return -1
            stages, i = tag & 0x0F, i + 1
            for s in range(stages):
                if i >= size or not 0xA0 <= buf[i] <= 0xBF:
                    return -1
                k = np.int64(buf[i] & 0x1F)
                timing[s, 0], timing[s, 1] = i + 1, k
                i += 1 + k
                if i >= size:
                    return -1
                ok, v, i = _int(buf, i)
                if not ok or v < 0:
                    return -1
                timing[s, 2] = v
        elif f == SEQ or f == T or f == N:
            ok, v, i = _int(buf, i)
            if not ok:
                return -1
            fields[f, 0] = v
        else:  # member (a str) or a bin
            if f == MEMBER and 0xA0 <= tag <= 0xBF:
                start, n = i + 1, tag & 0x1F
            elif f == MEMBER and tag == 0xD9:
                start, n = _sized(buf, i, 1)
            elif f != MEMBER and 0xC4 <= tag <= 0xC6:
                start, n = _sized(buf, i, 1 << (tag - 0xC4))
            else:
                return -1
            if start < 0 or start + n > size:
                return -1
            fields[f, 0], fields[f, 1] = start, n
            i = start + n
    if i != size or seen & _REQUIRED != _REQUIRED:
        return -1
    return stages
