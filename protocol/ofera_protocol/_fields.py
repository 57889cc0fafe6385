"""Strict field readers for decoded msgpack maps: each raises ProtocolError with the exact problem."""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import Any

import numpy as np

from .constants import INT64_MAX, INT64_MIN, MAX_ID_LEN
from .errors import BAD_FIELD, BAD_LENGTH, NON_FINITE, ProtocolError

_MISSING = object()


def _type_name(v: Any) -> str:
    return {bytes: "bin", str: "str", bool: "bool", int: "int", float: "float", dict: "map",
            list: "array", type(None): "nil"}.get(type(v), type(v).__name__)


def _get(m: dict[str, Any], key: str, where: str, required: bool) -> Any:
    v = m.get(key, _MISSING)
    if v is _MISSING or v is None:
        if required:
            raise ProtocolError(BAD_FIELD, f"{where}: missing field {key!r}")
        return _MISSING
    return v


def get_int(m: dict[str, Any], key: str, where: str, lo: int = INT64_MIN, hi: int = INT64_MAX,
            default: Any = _MISSING) -> Any:
    """Integer field in [lo, hi]; `default` makes it optional (nil counts as absent)."""
    v = _get(m, key, where, default is _MISSING)
    if v is _MISSING:
        return default
    if type(v) is not int:
        raise ProtocolError(BAD_FIELD, f"{where}: field {key!r} must be an int, got {_type_name(v)}")
    if not lo <= v <= hi:
        raise ProtocolError(BAD_FIELD, f"{where}: field {key!r} = {v} is outside [{lo}, {hi}]")
    return v


def get_str(m: dict[str, Any], key: str, where: str, max_len: int = MAX_ID_LEN, min_len: int = 1,
            default: Any = _MISSING) -> Any:
    """String field of min_len..max_len characters; `default` makes it optional."""
    v = _get(m, key, where, default is _MISSING)
    if v is _MISSING:
        return default
    if type(v) is not str:
        raise ProtocolError(BAD_FIELD, f"{where}: field {key!r} must be a str, got {_type_name(v)}")
    if not min_len <= len(v) <= max_len:
        raise ProtocolError(BAD_FIELD, f"{where}: field {key!r} must have {min_len}..{max_len} "
                            f"characters, got {len(v)}")
    return v


def get_choice(m: dict[str, Any], key: str, where: str, choices: Collection[str], code: str,
               default: Any = _MISSING) -> Any:
    """String field that must be one of `choices`; an unknown value raises `code`."""
    v = get_str(m, key, where, default=default)
    if v not in choices:
        raise ProtocolError(code, f"{where}: {key} {v!r} is not one of {', '.join(sorted(choices))}")
    return v


def get_bool(m: dict[str, Any], key: str, where: str, default: Any = _MISSING) -> Any:
    v = _get(m, key, where, default is _MISSING)
    if v is _MISSING:
        return default
    if type(v) is not bool:
        raise ProtocolError(BAD_FIELD, f"{where}: field {key!r} must be a bool, got {_type_name(v)}")
    return v


def get_map(m: dict[str, Any], key: str, where: str, required: bool = True) -> Any:
    v = _get(m, key, where, required)
    if v is _MISSING:
        return None
    if type(v) is not dict:
        raise ProtocolError(BAD_FIELD, f"{where}: field {key!r} must be a map, got {_type_name(v)}")
    return v


def get_bin(m: dict[str, Any], key: str, where: str, required: bool = True) -> Any:
    v = _get(m, key, where, required)
    if v is _MISSING:
        return None
    if type(v) is not bytes and type(v) is not memoryview:  # (memoryview: a zero-copy reader's bin, never msgpack's)
        raise ProtocolError(BAD_FIELD, f"{where}: field {key!r} must be bin, got {_type_name(v)}")
    return v


SMALL_ARRAY = 256
"""float32 arrays of at most this many values are checked for NaN and infinity in Python, not by numpy: a bs
message's weights are checked once per frame, with the CPU's caches cold, where a small numpy call costs 30-110 us
against 3-8 us back to back and a sum over a memoryview about a third of that (benchmarks/cold_cache.py)."""


def _small_f32_finite(buf: bytes) -> bool:
    """Whether packed native float32 values (at most SMALL_ARRAY) are all finite: their float64 sum is finite exactly
    when every value is (NaN and infinities propagate; 256 finite float32 values cannot overflow it)."""
    return math.isfinite(sum(memoryview(buf).cast("f")))


_DTYPES: dict[str, np.dtype] = {}


def get_array(m: dict[str, Any], key: str, where: str, dtype: str, shape: tuple[int, ...],
              finite: bool = True, required: bool = True) -> Any:
    """bin field of packed little-endian `dtype` values -> read-only numpy view of `shape`."""
    buf = get_bin(m, key, where, required)
    if buf is None:
        return None
    dt = _DTYPES.get(dtype)
    if dt is None:  # (a dtype is falsy: len() counts its fields)
        dt = _DTYPES[dtype] = np.dtype(dtype)
    need = math.prod(shape) * dt.itemsize
    if len(buf) != need:
        raise ProtocolError(BAD_LENGTH, f"{where}: field {key!r} has {len(buf)} bytes, expected {need} "
                            f"({'x'.join(map(str, shape)) or '1'} {dt.name})")
    a = np.frombuffer(buf, dtype=dt)
    if len(shape) != 1:
        a = a.reshape(shape)
    if finite and dt.kind == "f":
        small = need <= 4 * SMALL_ARRAY and dt.char == "f" and dt.isnative
        if not (_small_f32_finite(buf) if small else np.isfinite(a).all()):
            raise ProtocolError(NON_FINITE, f"{where}: field {key!r} holds NaN or infinity")
    return a
