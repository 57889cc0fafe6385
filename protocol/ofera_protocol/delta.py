"""Temporal delta frames (PROTOCOL.md section 7.1): the reference encoder and the client's decoder.

A delta session (``hello.delta``, encodings f16 and q13) sends a *key* frame (every Gaussian's codes,
an ordinary dense frame plus ``key: true``) on join, every N frames and on ``resync``; the frames in
between are *delta* frames carrying only the Gaussians whose value moved away from what the client holds
by more than the session's tolerance, as code changes:

- ``changed``: bitmask over the avatar (bit i of byte i >> 3, LSB first) of the n Gaussians carried;
- ``wide``: bitmask over those n (same bit order): 1 = its position is sent whole (``position``, the
  encoding's position codes), 0 = as a change of its codes (``position_delta``, 3 int8: new code =
  held code + change, per axis);
- ``rotation`` and ``scale``: the n Gaussians' new codes, whole.

Codes are integers: q13's (uint16 position, uint32 rotation, uint8 scale) and f16's bit patterns
(uint16 each); so the client reconstructs exactly what the server computed, and the server, which keeps
the codes it has handed to *this* client's socket, decides against what the client holds (closed loop):
the client's error is at most max(tolerance, the encoding's own error) after any number of frames, and a
frame that is never sent (newest-wins drop) changes nothing on either side.

The selection arithmetic (all float64, +, -, * and comparisons only, so numba reproduces it bit for bit)::

    moved  = |p - h_p|^2 > T_p^2                          (p, h_p: position, held decoded position)
          or (h_r . q)^2 < cos^2(T_r / 2) |q|^2 |h_r|^2  (q, h_r: rotation, held decoded rotation)
          or any axis s > h_s e^{T_s} or s < h_s e^{-T_s}  (scale)

Kernels (``NumpyKernels.delta_q13`` / ``delta_f16`` here, the numba set in the server) fill the selection;
:class:`DeltaEncoder` builds messages around them. Only numpy and msgpack are needed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .codec import pack_map
from .encodings import POS_LEVELS, ROT_LEVELS, SCALE_LEVELS, FrameFormat
from .errors import BAD_FIELD, BAD_LENGTH, NON_FINITE, NOT_READY, ProtocolError
from .messages import DeltaFrame, Frame

DELTA_ENCODINGS: tuple[str, ...] = ("f16", "q13")
"""Encodings a server may stream as deltas."""
NARROW = 127
"""A position change is sent as int8 when every axis's code change is in [-128, 127]."""
Q13_IDENTITY = np.uint32(3 << 30)
"""q13 code of the identity quaternion (w dropped, x = y = z = 0)."""


@dataclass(frozen=True)
class DeltaTolerance:
    """How far a Gaussian may drift from what the client holds before it is re-sent: position
    (Euclidean, metres), rotation (degrees), scale (|ln ratio| per axis). The client's error is at most
    these, or the encoding's own quantisation error, whichever is larger."""

    position_m: float = 4.5e-5
    rotation_deg: float = 0.45
    log_scale: float = 0.02

    def params(self) -> np.ndarray:
        """(4,) float64 given to the kernels: [T_p^2, cos^2(T_r / 2), e^{T_s}, e^{-T_s}]."""
        return np.array([self.position_m ** 2, math.cos(math.radians(self.rotation_deg) / 2) ** 2,
                         math.exp(self.log_scale), math.exp(-self.log_scale)], np.float64)


# ----------------------------------------------------------------------------- bitmasks


def pack_bits(mask: np.ndarray) -> np.ndarray:
    """(n,) bool -> ceil(n / 8) uint8, bit i in byte i >> 3 at position i & 7 (LSB first)."""
    return np.packbits(np.asarray(mask, bool), bitorder="little")


def unpack_bits(buf: bytes, n: int, what: str) -> np.ndarray:
    """The inverse of :func:`pack_bits`; ProtocolError if the length is not ceil(n / 8) or a padding bit is set."""
    if len(buf) != (n + 7) // 8:
        raise ProtocolError(BAD_LENGTH, f"frame: '{what}' has {len(buf)} bytes, a mask of {n} needs {(n + 7) // 8}")
    bits = np.unpackbits(np.frombuffer(buf, np.uint8), bitorder="little")
    if bits[n:].any():
        raise ProtocolError(BAD_FIELD, f"frame: '{what}' has bits set beyond its {n} entries")
    return bits[:n].astype(bool)


# ----------------------------------------------------------------------------- decoded codes (float64)


def q13_decode_rotation64(codes: np.ndarray) -> np.ndarray:
    """(n,) uint32 q13 rotations -> (n, 4) float64 (the decoder of PROTOCOL.md 6.3, in float64)."""
    v = np.asarray(codes, np.uint32).reshape(-1)
    i = (v >> 30).astype(np.int64)
    kept = np.empty((v.size, 3), np.float64)
    d = np.ones(v.size, np.float64)
    for j in range(3):
        f = ((v >> np.uint32(20 - 10 * j)) & 1023).astype(np.int64)
        f = np.where(f >= 512, f - 1024, f)
        c = np.maximum(f / ROT_LEVELS, -1.0) / math.sqrt(2.0)
        kept[:, j] = c
        d = d - c * c
    big = np.sqrt(np.maximum(d, 0.0))
    out = np.empty((v.size, 4), np.float64)
    for c in range(4):  # kept components fill the other slots in index order
        src = np.where(i > c, c, c - 1)
        out[:, c] = np.where(i == c, big, kept[np.arange(v.size), np.clip(src, 0, 2)])
    return out


def q13_scale_lut(fmt: FrameFormat) -> np.ndarray:
    """(256,) float64: the scale each q13 code decodes to (exp(lmin + code (lmax - lmin) / 255))."""
    assert fmt.quant is not None
    lmin, lmax = float(fmt.quant.log_scale[0]), float(fmt.quant.log_scale[1])
    return np.exp(lmin + np.arange(256, dtype=np.float64) * ((lmax - lmin) / SCALE_LEVELS))


def half_to_f64(bits: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(bits, np.uint16).view(np.float16).astype(np.float64)


# ----------------------------------------------------------------------------- reference kernels


def _moved(pos, rot, scale, rows, psign, rsign, tol, dec_p, dec_r, dec_s) -> np.ndarray:
    """(K,) bool: the selection rule of the module docstring, vectorised (the spec in code)."""
    p = (np.asarray(pos, np.float32)[rows] * psign).astype(np.float64)
    d = p - dec_p
    d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
    moved = d2 > tol[0]
    q = (np.asarray(rot, np.float32)[rows] * rsign).astype(np.float64)
    dot = dec_r[:, 0] * q[:, 0] + dec_r[:, 1] * q[:, 1] + dec_r[:, 2] * q[:, 2] + dec_r[:, 3] * q[:, 3]
    n2 = q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3]
    h2 = dec_r[:, 0] * dec_r[:, 0] + dec_r[:, 1] * dec_r[:, 1] + dec_r[:, 2] * dec_r[:, 2] + dec_r[:, 3] * dec_r[:, 3]
    moved |= dot * dot < tol[1] * n2 * h2
    s = np.asarray(scale, np.float32)[rows].astype(np.float64)
    moved |= ((s > dec_s * tol[2]) | (s < dec_s * tol[3])).any(axis=1)
    return moved


def _split(sel, ids, new_p, held_p, out_sel, out_wide, out_res, out_pos) -> tuple[int, int]:
    """Narrow / wide position changes of the selected rows; writes out_sel, out_wide, out_res, out_pos."""
    n = sel.size
    change = new_p.astype(np.int32) - held_p[ids[sel]].astype(np.int32)
    wide = ~((change >= -NARROW - 1) & (change <= NARROW)).all(axis=1)
    out_sel[:n] = sel
    out_wide[:n] = wide
    m = int(n - wide.sum())
    out_res[:m] = change[~wide].astype(np.int8)
    out_pos[:n - m] = new_p[wide]
    return n, n - m


def delta_q13_reference(kern: Any, pos, rot, scale, rows, ids, psign, rsign, lo, k, step, thresholds, scale_lut,
                        tol, held_p, held_r, held_s, dec_p, dec_r, dec_s,
                        out_sel, out_wide, out_res, out_pos, out_rot, out_scale) -> tuple[int, int]:
    """q13 delta kernel (reference). For the K candidates (session ids ``ids``, state rows ``rows``) with held
    codes ``held_*`` (indexed by session id) and their float64 decodings ``dec_*`` (indexed by candidate):
    select the moved ones, encode them with ``kern`` (the frame kernels), write the selection (candidate
    positions ``out_sel[:n]``, ``out_wide[:n]``), the narrow changes ``out_res[:n - w]``, the wide position
    codes ``out_pos[:w]``, rotation and scale codes ``out_rot[:n]``, ``out_scale[:n]``, update the held codes and
    decodings, and return (n, w)."""
    sel = np.flatnonzero(_moved(pos, rot, scale, rows, psign, rsign, tol, dec_p, dec_r, dec_s))
    n = sel.size
    g = rows[sel]
    new_p = np.empty((n, 3), np.uint16)
    kern.q13_position(pos, g, psign, lo, k, new_p.reshape(-1))
    kern.q13_rotation(rot, g, rsign, out_rot[:n])
    kern.q13_scale(scale, g, thresholds, out_scale[:n].reshape(-1))
    n, w = _split(sel, ids, new_p, held_p, out_sel, out_wide, out_res, out_pos)
    s_ids = ids[sel]
    held_p[s_ids] = new_p
    held_r[s_ids] = out_rot[:n]
    held_s[s_ids] = out_scale[:n]
    dec_p[sel] = lo + new_p.astype(np.float64) * step
    dec_r[sel] = q13_decode_rotation64(out_rot[:n])
    dec_s[sel] = scale_lut[out_scale[:n]]
    return n, w


def delta_f16_reference(kern: Any, pos, rot, scale, rows, ids, psign, rsign, tol, held_p, held_r, held_s,
                        dec_p, dec_r, dec_s, out_sel, out_wide, out_res, out_pos, out_rot, out_scale
                        ) -> tuple[int, int]:
    """f16 delta kernel (reference): :func:`delta_q13_reference` with f16 bit patterns as codes. Returns (n, w);
    ValueError if a selected value is beyond the half range."""
    sel = np.flatnonzero(_moved(pos, rot, scale, rows, psign, rsign, tol, dec_p, dec_r, dec_s))
    n = sel.size
    g = rows[sel]
    new_p = np.empty((n, 3), np.uint16)
    ok = kern.f16(pos, g, psign, new_p.reshape(-1))
    ok &= kern.f16(rot, g, rsign, out_rot[:n].reshape(-1))
    ok &= kern.f16(scale, g, np.ones(3, np.float32), out_scale[:n].reshape(-1))
    if not ok:
        raise ValueError("a moved Gaussian has NaN, infinity or values beyond +-65504 (f16)")
    n, w = _split(sel, ids, new_p, held_p, out_sel, out_wide, out_res, out_pos)
    s_ids = ids[sel]
    held_p[s_ids] = new_p
    held_r[s_ids] = out_rot[:n]
    held_s[s_ids] = out_scale[:n]
    dec_p[sel] = half_to_f64(new_p)
    dec_r[sel] = half_to_f64(out_rot[:n])
    dec_s[sel] = half_to_f64(out_scale[:n])
    return n, w


# ----------------------------------------------------------------------------- encoder (server)


class DeltaEncoder:
    """The frames of one delta session (one client): key and delta frames against what *this* client holds.

    fmt: the session's FrameFormat (``delta`` set, f16 or q13, dense); coords: ``flame`` or ``unity``;
    gather: (count,) int64 state rows of the session's Gaussians (None: all, in order); candidates: (K,)
    int64 ascending session ids that can move (the rest keep their key-frame value: they never change);
    rows: (K,) their state rows. kernels: the frame kernel set (``fast_encodings.NumpyKernels`` by default; the
    server passes the numba set), which also provides ``delta_q13`` / ``delta_f16``.

    :meth:`encode` must be called only for frames that are then handed to the client's socket: it advances
    the held state. ``key_interval``: a key frame every that many frames (0: only on join and resync).
    """

    def __init__(self, fmt: FrameFormat, coords: str = "flame", gather: np.ndarray | None = None,
                 candidates: np.ndarray | None = None, rows: np.ndarray | None = None, kernels: Any = None,
                 tolerance: DeltaTolerance | None = None, key_interval: int = 720) -> None:
        from .fast_encodings import NumpyKernels, coord_signs, position_factors, scale_thresholds

        if not fmt.delta or fmt.encoding not in DELTA_ENCODINGS or fmt.sparse:
            raise ValueError(f"a delta encoder needs a dense delta session in {DELTA_ENCODINGS}, got {fmt}")
        n = fmt.count
        self.format, self.coords = fmt, coords
        self.kernels = kernels if kernels is not None else NumpyKernels()
        self.gather = None if gather is None else np.ascontiguousarray(gather, np.int64)
        if self.gather is not None and self.gather.shape != (n,):
            raise ValueError(f"gather has shape {self.gather.shape}, the session has {n} Gaussians")
        self.ids = np.arange(n, dtype=np.int64) if candidates is None else np.ascontiguousarray(candidates, np.int64)
        if rows is None:
            rows = self.ids if self.gather is None else self.gather[self.ids]
        self.rows = np.ascontiguousarray(rows, np.int64)
        if self.rows.shape != self.ids.shape or (self.ids.size > 1 and not (np.diff(self.ids) > 0).all()):
            raise ValueError("candidates must be strictly ascending session ids, with one state row each")
        if self.ids.size and (self.ids[0] < 0 or self.ids[-1] >= n):
            raise ValueError(f"candidates must be session ids below {n}")
        self.tolerance = tolerance or DeltaTolerance()
        self.tol = self.tolerance.params()
        self.key_interval = int(key_interval)
        self.psign, self.rsign = coord_signs(coords)
        q13 = fmt.encoding == "q13"
        if q13:
            assert fmt.quant is not None
            self.lo, self.k = position_factors(fmt.quant)
            self.step = (fmt.quant.pos_max.astype(np.float64) - self.lo) / POS_LEVELS
            self.thresholds = scale_thresholds(fmt.quant)
            self.lut = q13_scale_lut(fmt)
        rot_shape = (n,) if q13 else (n, 4)
        self.held_p = np.zeros((n, 3), np.uint16)
        self.held_r = np.zeros(rot_shape, np.uint32 if q13 else np.uint16)
        self.held_s = np.zeros((n, 3), np.uint8 if q13 else np.uint16)
        m = self.ids.size
        self.dec_p, self.dec_r, self.dec_s = np.zeros((m, 3)), np.zeros((m, 4)), np.zeros((m, 3))
        self._sel = np.zeros(m, np.int64)
        self._wide = np.zeros(m, bool)
        self._res = np.zeros((m, 3), np.int8)
        self._pos = np.zeros((m, 3), np.uint16)
        self._rot = np.zeros((m,) if q13 else (m, 4), self.held_r.dtype)
        self._scale = np.zeros((m, 3), self.held_s.dtype)
        self.has_key = False
        self._key_asked = True
        self.since_key = 0
        self.frames = 0
        self.key_frames = 0

    def request_key(self) -> None:
        """The next frame will be a key frame (the client sent `resync`). Safe from any thread."""
        self._key_asked = True

    def _key(self, seq: int, t: int, timing: dict[str, int], position, rotation, scale) -> bytes:
        k, g = self.kernels, self.gather
        if self.format.encoding == "q13":
            k.q13_position(position, g, self.psign, self.lo, self.k, self.held_p.reshape(-1))
            k.q13_rotation(rotation, g, self.rsign, self.held_r)
            k.q13_scale(scale, g, self.thresholds, self.held_s.reshape(-1))
            self.dec_p[:] = self.lo + self.held_p[self.ids].astype(np.float64) * self.step
            self.dec_r[:] = q13_decode_rotation64(self.held_r[self.ids])
            self.dec_s[:] = self.lut[self.held_s[self.ids]]
        else:
            ok = k.f16(position, g, self.psign, self.held_p.reshape(-1))
            ok &= k.f16(rotation, g, self.rsign, self.held_r.reshape(-1))
            ok &= k.f16(scale, g, np.ones(3, np.float32), self.held_s.reshape(-1))
            if not ok:
                raise ValueError("state has NaN, infinity or values beyond +-65504 (f16)")
            self.dec_p[:] = half_to_f64(self.held_p[self.ids])
            self.dec_r[:] = half_to_f64(self.held_r[self.ids])
            self.dec_s[:] = half_to_f64(self.held_s[self.ids])
        return pack_map({"type": "frame", "seq": seq, "t": t, "timing": timing, "key": True, "n": self.format.count,
                         "position": self.held_p, "rotation": self.held_r, "scale": self.held_s})

    def encode(self, seq: int, t: int, timing: dict[str, int], position: np.ndarray, rotation: np.ndarray,
               scale: np.ndarray) -> bytes:
        """The next frame message (key or delta) for FLAME-space float32 state arrays (N, 3), (N, 4), (N, 3)."""
        self.frames += 1
        if self._key_asked or not self.has_key or (self.key_interval and self.since_key >= self.key_interval):
            self._key_asked = False
            data = self._key(seq, t, timing, position, rotation, scale)
            self.has_key = True
            self.since_key = 1
            self.key_frames += 1
            return data
        self.since_key += 1
        args = (position, rotation, scale, self.rows, self.ids, self.psign, self.rsign)
        if self.format.encoding == "q13":
            n, w = self.kernels.delta_q13(*args, self.lo, self.k, self.step, self.thresholds, self.lut, self.tol,
                                          self.held_p, self.held_r, self.held_s, self.dec_p, self.dec_r, self.dec_s,
                                          self._sel, self._wide, self._res, self._pos, self._rot, self._scale)
        else:
            n, w = self.kernels.delta_f16(*args, self.tol, self.held_p, self.held_r, self.held_s,
                                          self.dec_p, self.dec_r, self.dec_s,
                                          self._sel, self._wide, self._res, self._pos, self._rot, self._scale)
        changed = np.zeros(self.format.count, bool)
        changed[self.ids[self._sel[:n]]] = True
        return pack_map({"type": "frame", "seq": seq, "t": t, "timing": timing, "key": False, "n": int(n),
                         "changed": pack_bits(changed), "wide": pack_bits(self._wide[:n]),
                         "position_delta": self._res[:n - w], "position": self._pos[:w],
                         "rotation": self._rot[:n], "scale": self._scale[:n]})


# ----------------------------------------------------------------------------- decoder (client)


def _decode_codes(fmt: FrameFormat, p: np.ndarray, r: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, ...]:
    from .encodings import decode_arrays

    return decode_arrays(fmt.encoding, p.shape[0], p.tobytes(), r.tobytes(), s.tobytes(), fmt.quant)


class DeltaDecoder:
    """The codes a delta-session client holds (count Gaussians), updated by key and delta frames.

    :meth:`key` takes a decoded key frame (its ``codes``); :meth:`apply` turns a :class:`DeltaFrame` into a
    sparse-like :class:`Frame` (``index`` = the changed Gaussians, absolute float32 values, ``key`` False).
    A delta frame is checked whole before anything changes: a bad one raises ProtocolError and costs that
    frame only (the client must then send ``resync``, since the server believes it was applied)."""

    def __init__(self, fmt: FrameFormat) -> None:
        if fmt.encoding not in DELTA_ENCODINGS:
            raise ValueError(f"no delta frames in encoding {fmt.encoding!r}")
        self.format = fmt
        n, q13 = fmt.count, fmt.encoding == "q13"
        self.position = np.zeros((n, 3), np.uint16)
        self.rotation = np.zeros((n,) if q13 else (n, 4), np.uint32 if q13 else np.uint16)
        self.scale = np.zeros((n, 3), np.uint8 if q13 else np.uint16)
        self.has_key = False

    def key(self, frame: Frame) -> None:
        if frame.codes is None or frame.index is not None:
            raise ProtocolError(BAD_FIELD, "frame: a key frame of a delta session must be dense")
        p, r, s = frame.codes
        self.position[...] = p.reshape(self.position.shape)
        self.rotation[...] = np.asarray(r).view(self.rotation.dtype).reshape(self.rotation.shape)
        self.scale[...] = np.asarray(s).view(self.scale.dtype).reshape(self.scale.shape)
        self.has_key = True

    def apply(self, d: DeltaFrame) -> Frame:
        if not self.has_key:
            raise ProtocolError(NOT_READY, "frame: a delta frame before any key frame (send resync)")
        ids = d.index.astype(np.int64)
        narrow = ids[~d.wide]
        new = self.position[narrow].astype(np.int32) + d.position_delta.astype(np.int32)
        if new.size and (new.min() < 0 or new.max() > 65535):
            raise ProtocolError(BAD_FIELD, "frame: 'position_delta' takes a code outside 0..65535")
        pos = np.empty((ids.size, 3), np.uint16)
        pos[~d.wide] = new
        pos[d.wide] = d.position.view(np.uint16).reshape(-1, 3)
        rot = d.rotation.view(self.rotation.dtype)
        scale = d.scale.view(self.scale.dtype)
        if self.format.encoding == "f16" and ((pos & 0x7C00) == 0x7C00).any():
            raise ProtocolError(NON_FINITE, "frame: a position change gives NaN or infinity")
        p, r, s = _decode_codes(self.format, pos, rot, scale)  # raises on non-finite f16 values
        self.position[ids] = pos
        self.rotation[ids] = rot
        self.scale[ids] = scale
        return Frame(seq=d.seq, t=d.t, timing=d.timing, index=d.index, position=p, rotation=r, scale=s, key=False)
