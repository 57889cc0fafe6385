"""Temporal delta frames (PROTOCOL.md section 7.1): the reference encoder and the client's decoder.

A delta session (``hello.delta``, encodings f16 and q13) sends a *key* frame (every Gaussian's codes,
an ordinary dense frame plus ``key: true``) on join, every N frames and on ``resync``; the frames in
between are *delta* frames carrying, for the Gaussians whose position, rotation or scale moved away from
what the client holds by more than the session's tolerance, the new codes of exactly what moved:

- ``changed``: bitmask over the avatar (bit i of byte i >> 3, LSB first) of the n Gaussians carried;
- ``moved_position``, ``moved_rotation``, ``moved_scale``: bitmasks over those n: which attributes each carries;
- ``wide``: bitmask over the n_p carrying a position: 1 = sent whole (``position``, the encoding's position
  codes), 0 = as a change of its codes (``position_delta``, 3 int8: new code = held code + change, per axis);
- ``rotation`` (n_r) and ``scale`` (n_s): new codes, whole.

Codes are integers: q13's (uint16 position, uint32 rotation, uint8 scale) and f16's bit patterns
(uint16 each); so the client reconstructs exactly what the server computed, and the server, which keeps
the codes it has handed to *this* client's socket, decides against what the client holds (closed loop):
the client's error is at most max(tolerance, the encoding's own error) after any number of frames, and a
frame that is never sent (newest-wins drop) changes nothing on either side.

The selection arithmetic (all float32, +, -, * and comparisons in a fixed order, so numba reproduces it bit for
bit, SIMD lanes included), per attribute, against the held codes' decodings h (rounded to float32)::

    position moved  |p - h_p|^2 > T_p^2
    rotation moved  sum over i < j of (q_i h_j - q_j h_i)^2 > sin^2(T_r / 2) |q|^2 |h_r|^2
    scale moved     on some axis s > h_s e^{T_s} or s < h_s e^{-T_s}

The rotation test is |q|^2 |h|^2 sin^2(angle / 2) > ... written through Lagrange's identity: its 2 x 2 minors
are small when q and h are close, so float32 resolves the 0.45 degree threshold to a few parts per million
(the equivalent (h . q)^2 < cos^2(T_r / 2) |q|^2 |h|^2 compares two numbers equal to 1 - 1.5e-5 and would need
float64).

Kernels (``NumpyKernels.delta_q13`` / ``delta_f16`` here, the numba set in the server) fill the selection;
:class:`DeltaEncoder` builds messages around them. Only numpy and msgpack are needed.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from .codec import MessagePacker, pack_bits, pack_map, unpack_bits  # noqa: F401 - unpack_bits: re-exported
from .encodings import POS_LEVELS, ROT_LEVELS, SCALE_LEVELS, FrameFormat
from .errors import BAD_FIELD, NON_FINITE, NOT_READY, ProtocolError
from .fast_encodings import HEADER_ROOM, BufferPool
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
        """(4,) float32 given to the kernels: [T_p^2, sin^2(T_r / 2), e^{T_s}, e^{-T_s}]."""
        return np.array([self.position_m ** 2, math.sin(math.radians(self.rotation_deg) / 2) ** 2,
                         math.exp(self.log_scale), math.exp(-self.log_scale)], np.float32)


# ----------------------------------------------------------------------------- decoded codes


def _rot_field_lut() -> np.ndarray:
    f = np.arange(1024, dtype=np.int64)
    f = np.where(f >= 512, f - 1024, f)
    return np.maximum(f / ROT_LEVELS, -1.0) / math.sqrt(2.0)


ROT_FIELD64 = _rot_field_lut()
"""(1024,) float64: the component a q13 rotation's 10-bit field decodes to (PROTOCOL.md 6.3, in float64)."""


def q13_decode_rotation64(codes: np.ndarray) -> np.ndarray:
    """(n,) uint32 q13 rotations -> (n, 4) float64 (the decoder of PROTOCOL.md 6.3, in float64)."""
    v = np.asarray(codes, np.uint32).reshape(-1)
    i = (v >> 30).astype(np.int64)
    kept = np.empty((v.size, 3), np.float64)
    d = np.ones(v.size, np.float64)
    for j in range(3):
        c = ROT_FIELD64[(v >> np.uint32(20 - 10 * j)) & 1023]
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


def half_to_f32(bits: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(bits, np.uint16).view(np.float16).astype(np.float32)


# ----------------------------------------------------------------------------- reference kernels


HELD_POSITION, HELD_ROTATION, HELD_SCALE = slice(0, 3), slice(3, 7), slice(7, 10)
"""Rows of a DeltaEncoder's ``dec`` (10, K) float32, the decodings of the held codes, one column per candidate
(structure of arrays: the selection reads them in SIMD lanes)."""


def row_runs(rows: np.ndarray) -> np.ndarray:
    """(R, 3) int64 [first state row, first candidate, length] of the runs of consecutive state rows in ``rows``
    (K,): the fast kernels read each run's state as one contiguous block."""
    rows = np.asarray(rows, np.int64)
    first = np.flatnonzero(np.diff(rows, prepend=rows[:1] - 2) != 1) if rows.size else np.zeros(0, np.int64)
    length = np.diff(np.append(first, rows.size))
    return np.stack([rows[first], first, length], axis=1).astype(np.int64)


def _moved(pos, rot, scale, rows, psign, rsign, tol, dec) -> np.ndarray:
    """(K, 3) bool: position, rotation, scale moved (the rule of the module docstring, vectorised: the spec)."""
    f32 = np.float32
    p = np.asarray(pos, f32)[rows] * psign
    h = dec[HELD_POSITION]
    d0, d1, d2 = p[:, 0] - h[0], p[:, 1] - h[1], p[:, 2] - h[2]
    out = np.empty((rows.size, 3), bool)
    out[:, 0] = d0 * d0 + d1 * d1 + d2 * d2 > tol[0]
    q = np.asarray(rot, f32)[rows] * rsign
    q0, q1, q2, q3 = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    h0, h1, h2, h3 = dec[HELD_ROTATION]
    m01, m02, m03 = q0 * h1 - q1 * h0, q0 * h2 - q2 * h0, q0 * h3 - q3 * h0
    m12, m13, m23 = q1 * h2 - q2 * h1, q1 * h3 - q3 * h1, q2 * h3 - q3 * h2
    cross = m01 * m01 + m02 * m02 + m03 * m03 + m12 * m12 + m13 * m13 + m23 * m23
    n2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    hh = h0 * h0 + h1 * h1 + h2 * h2 + h3 * h3
    out[:, 1] = cross > tol[1] * n2 * hh
    s = np.asarray(scale, f32)[rows]
    hs = dec[HELD_SCALE].T
    out[:, 2] = ((s > hs * tol[2]) | (s < hs * tol[3])).any(axis=1)
    return out


def _select(moved, flags, out_moved):
    """Write the flags of every candidate and of the selection (the n that moved, ``out_moved[:n]``); returns (sel,
    n, and the candidate positions of the moved positions, rotations, scales)."""
    flags[:] = moved[:, 0] | (moved[:, 1].astype(np.uint8) << 1) | (moved[:, 2].astype(np.uint8) << 2)
    sel = np.flatnonzero(moved.any(axis=1))
    n = sel.size
    out_moved[:n] = flags[sel]
    p_sel, r_sel, s_sel = (sel[moved[sel, c]] for c in range(3))
    return sel, n, p_sel, r_sel, s_sel


def _positions(p_sel, ids, new_p, held_p, out_wide, out_res, out_pos) -> tuple[int, int]:
    """Narrow (int8 changes) / wide (whole codes) positions; holds the new codes; returns (n_p, w)."""
    change = new_p.astype(np.int32) - held_p[ids[p_sel]].astype(np.int32)
    wide = ~((change >= -NARROW - 1) & (change <= NARROW)).all(axis=1)
    n_p = p_sel.size
    out_wide[:n_p] = wide
    m = int(n_p - wide.sum())
    out_res[:m] = change[~wide].astype(np.int8)
    out_pos[:n_p - m] = new_p[wide]
    held_p[ids[p_sel]] = new_p
    return n_p, n_p - m


def delta_q13_reference(kern: Any, pos, rot, scale, rows, runs, ids, psign, rsign, lo, k, step, thresholds, scale_lut,
                        rot_lut, tol, held_p, held_r, held_s, dec, flags, work,
                        out_moved, out_wide, out_res, out_pos, out_rot, out_scale) -> tuple[int, ...]:
    """q13 delta kernel (reference). For the K candidates (session ids ``ids``, state rows ``rows``, their runs
    :func:`row_runs`) with held codes ``held_*`` (indexed by session id) and their decodings ``dec`` (10, K)
    float32 (:data:`HELD_POSITION` ...): find what moved (``flags`` (K,) uint8: bit 0, 1, 2 = position, rotation,
    scale), encode it with ``kern`` (the frame kernels), write the flags of the selection (the n candidates that
    moved, in order) ``out_moved[:n]``, ``out_wide[:n_p]``, the narrow changes ``out_res[:n_p - w]``, the wide
    position codes ``out_pos[:w]``, rotation codes ``out_rot[:n_r]``, scale codes ``out_scale[:n_s]``, update the
    held codes and decodings, and return (n, n_p, w, n_r, n_s). ``runs`` and ``work`` (7, K) int32 serve the numba
    kernels (contiguous reads, the lists of what moved, a float32 scratch); the reference needs neither."""
    moved = _moved(pos, rot, scale, rows, psign, rsign, tol, dec)
    sel, n, p_sel, r_sel, s_sel = _select(moved, flags, out_moved)
    new_p = np.empty((p_sel.size, 3), np.uint16)
    kern.q13_position(pos, rows[p_sel], psign, lo, k, new_p.reshape(-1))
    n_p, w = _positions(p_sel, ids, new_p, held_p, out_wide, out_res, out_pos)
    dec[HELD_POSITION, p_sel] = (lo + new_p.astype(np.float64) * step).astype(np.float32).T
    n_r, n_s = r_sel.size, s_sel.size
    kern.q13_rotation(rot, rows[r_sel], rsign, out_rot[:n_r])
    held_r[ids[r_sel]] = out_rot[:n_r]
    dec[HELD_ROTATION, r_sel] = q13_decode_rotation64(out_rot[:n_r]).astype(np.float32).T
    kern.q13_scale(scale, rows[s_sel], thresholds, out_scale[:n_s].reshape(-1))
    held_s[ids[s_sel]] = out_scale[:n_s]
    dec[HELD_SCALE, s_sel] = scale_lut[out_scale[:n_s]].astype(np.float32).T
    return n, n_p, w, n_r, n_s


def delta_f16_reference(kern: Any, pos, rot, scale, rows, runs, ids, psign, rsign, tol, held_p, held_r, held_s,
                        dec, flags, work, out_moved, out_wide, out_res, out_pos, out_rot, out_scale
                        ) -> tuple[int, ...]:
    """f16 delta kernel (reference): :func:`delta_q13_reference` with f16 bit patterns as codes. Returns
    (n, n_p, w, n_r, n_s); ValueError if a value sent is beyond the half range."""
    moved = _moved(pos, rot, scale, rows, psign, rsign, tol, dec)
    sel, n, p_sel, r_sel, s_sel = _select(moved, flags, out_moved)
    n_r, n_s = r_sel.size, s_sel.size
    new_p = np.empty((p_sel.size, 3), np.uint16)
    ok = kern.f16(pos, rows[p_sel], psign, new_p.reshape(-1))
    ok &= kern.f16(rot, rows[r_sel], rsign, out_rot[:n_r].reshape(-1))
    ok &= kern.f16(scale, rows[s_sel], np.ones(3, np.float32), out_scale[:n_s].reshape(-1))
    if not ok:
        raise ValueError("a moved Gaussian has NaN, infinity or values beyond +-65504 (f16)")
    n_p, w = _positions(p_sel, ids, new_p, held_p, out_wide, out_res, out_pos)
    dec[HELD_POSITION, p_sel] = half_to_f32(new_p).T
    held_r[ids[r_sel]] = out_rot[:n_r]
    dec[HELD_ROTATION, r_sel] = half_to_f32(out_rot[:n_r]).T
    held_s[ids[s_sel]] = out_scale[:n_s]
    dec[HELD_SCALE, s_sel] = half_to_f32(out_scale[:n_s]).T
    return n, n_p, w, n_r, n_s


def delta_masks_reference(count: int, id_runs, flags, moved, wide, n: int, n_p: int) -> tuple[np.ndarray, ...]:
    """A delta frame's bitmasks from a kernel's flags and selection (``flags`` (K,) of every candidate, non-zero where
    it changed; ``id_runs`` (R, 3) the runs of consecutive session ids among the candidates, :func:`row_runs` of
    them; ``moved[:n]`` (n,) uint8 the flags of the selection, ``wide[:n_p]``): (changed over the ``count`` Gaussians,
    moved_position, moved_rotation, moved_scale, wide), each uint8 LSB first (:func:`pack_bits`)."""
    changed = np.zeros(count, bool)
    for first_id, first, length in id_runs:
        changed[first_id:first_id + length] = flags[first:first + length] != 0
    m = moved[:n]
    return (pack_bits(changed), pack_bits(m & 1 != 0), pack_bits(m & 2 != 0), pack_bits(m & 4 != 0),
            pack_bits(wide[:n_p]))


DELTA_BINS = ("changed", "moved_position", "moved_rotation", "moved_scale", "wide", "position_delta", "position",
              "rotation", "scale")
"""A delta frame's bin fields, in the order of its map (after ``type``, ``seq``, ``t``, ``timing``, ``key``, ``n``)."""

DELTA_KEYS = np.frombuffer(b"".join(msgpack.packb(k) for k in DELTA_BINS), np.uint8)
"""The msgpack strings of :data:`DELTA_BINS`, one after another (each fixstr's first byte holds its length)."""


def delta_body_size(count: int, n: int, n_p: int, w: int, n_r: int, n_s: int, row_bytes: tuple[int, ...]) -> int:
    """Most bytes :func:`delta_body_reference` writes for these counts (``row_bytes``: the bytes of one row of
    position_delta, position, rotation, scale): the keys, the longest bin headers and the data."""
    r3, r6, rr, rs = row_bytes
    data = ((count + 7) >> 3) + 3 * ((n + 7) >> 3) + ((n_p + 7) >> 3) + r3 * (n_p - w) + r6 * w + rr * n_r + rs * n_s
    return DELTA_KEYS.size + 5 * len(DELTA_BINS) + data


def delta_body_reference(buf: np.ndarray, at: int, count: int, id_runs, flags, moved, wide, n: int, n_p: int,
                         w: int, n_r: int, n_s: int, res, pos, rot, scl, r3: int, r6: int, rr: int, rs: int) -> int:
    """A delta frame's bin fields as msgpack map entries (key, bin; :data:`DELTA_BINS` in order) into buf[at..]
    (uint8): the masks (:func:`delta_masks_reference` of ``count`` .. ``n_p``), then res, pos, rot, scl (the encoder's
    outputs as flat uint8) cut to n_p - w, w, n_r and n_s rows of r3, r6, rr and rs bytes. Returns where they end.
    The message is these entries after its first six (``codec.pack_map`` of the whole frame, the same bytes)."""
    masks = delta_masks_reference(count, id_runs, flags, moved, wide, n, n_p)
    fields = (*masks, res[:r3 * (n_p - w)], pos[:r6 * w], rot[:rr * n_r], scl[:rs * n_s])
    body = pack_map(dict(zip(DELTA_BINS, fields)))[1:]  # (without the 9-entry map's own header byte)
    buf[at:at + len(body)] = np.frombuffer(body, np.uint8)
    return at + len(body)


class ReferenceKernels:
    """The reference kernel set of :class:`DeltaEncoder`: ``fast_encodings.NumpyKernels`` (frames) plus the delta
    kernels of this module, all plain numpy (the spec in code). The server's numba set has the same methods."""

    def __init__(self) -> None:
        from .fast_encodings import NumpyKernels

        self._frames = NumpyKernels()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._frames, name)

    def delta_q13(self, *args) -> tuple[int, ...]:
        return delta_q13_reference(self._frames, *args)

    def delta_f16(self, *args) -> tuple[int, ...]:
        return delta_f16_reference(self._frames, *args)

    def delta_body(self, *args) -> int:
        return delta_body_reference(*args)


# ----------------------------------------------------------------------------- encoder (server)


class DeltaEncoder:
    """The frames of one delta session (one client): key and delta frames against what *this* client holds.

    fmt: the session's FrameFormat (``delta`` set, f16 or q13, dense); coords: ``flame`` or ``unity``;
    gather: (count,) int64 state rows of the session's Gaussians (None: all, in order); candidates: (K,)
    int64 ascending session ids that can move (the rest keep their key-frame value: they never change);
    rows: (K,) their state rows. kernels: frame and delta kernels (:class:`ReferenceKernels` by default; the
    server passes the numba set).

    :meth:`encode` must be called only for frames that are then handed to the client's socket: it advances
    the held state. ``key_interval``: a key frame every that many frames (0: only on join and resync).
    ``stamp_encode``: each frame's timing also carries "encode", the microseconds its encoding took: a delta frame's up
    to writing its header (its fields written), a key frame's before its message was packed.
    """

    def __init__(self, fmt: FrameFormat, coords: str = "flame", gather: np.ndarray | None = None,
                 candidates: np.ndarray | None = None, rows: np.ndarray | None = None, kernels: Any = None,
                 tolerance: DeltaTolerance | None = None, key_interval: int = 720, stamp_encode: bool = False) -> None:
        from .fast_encodings import coord_signs, position_factors, scale_thresholds

        if not fmt.delta or fmt.encoding not in DELTA_ENCODINGS or fmt.sparse:
            raise ValueError(f"a delta encoder needs a dense delta session in {DELTA_ENCODINGS}, got {fmt}")
        n = fmt.count
        self.format, self.coords = fmt, coords
        self.kernels = kernels if kernels is not None else ReferenceKernels()
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
        self.stamp_encode = stamp_encode
        self._packer = MessagePacker()  # messages in reused buffers (memoryviews; a held one is never overwritten)
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
        self.runs = row_runs(self.rows)
        self.id_runs = row_runs(self.ids)  # the changed mask's runs (delta_masks)
        self.dec = np.zeros((10, m), np.float32)  # decodings of the held codes (HELD_POSITION ...)
        self._flags = np.zeros(m, np.uint8)
        self._work = np.zeros((7, m), np.int32)  # the numba kernels' lists and scratch
        self._moved = np.zeros(m, np.uint8)  # the flags of the selection (delta_masks)
        self._wide = np.zeros(m, bool)
        self._res = np.zeros((m, 3), np.int8)
        self._pos = np.zeros((m, 3), np.uint16)
        self._rot = np.zeros((m,) if q13 else (m, 4), self.held_r.dtype)
        self._scale = np.zeros((m, 3), self.held_s.dtype)
        # The outputs as flat bytes and the bytes of one row, which a delta frame's message takes its fields from,
        # and the buffers its messages are written in (reused once nothing references them)
        outputs = (self._res, self._pos, self._rot, self._scale)
        self._flat = tuple(a.reshape(-1).view(np.uint8) for a in outputs)
        self._row_bytes = tuple(a.nbytes // m if m else 0 for a in outputs)
        self._messages = BufferPool(4, make=_bytes_array)
        self._most = HEADER_ROOM + delta_body_size(n, m, m, m, m, m, self._row_bytes)  # any delta frame's message
        self._head = msgpack.Packer(use_bin_type=True)  # (msgpack.packb makes a Packer, a 1 MB buffer, per call)
        # Work on the held state that a writer of this encoder's frames left for later (the server's direct delta
        # frames leave the decodings of the codes they sent until the frame is on its way), run before this encoder
        # reads that state again
        self.pending: Callable[[], None] | None = None
        self.has_key = False
        self._key_asked = True
        self.since_key = 0
        self.frames = 0
        self.key_frames = 0

    def request_key(self) -> None:
        """The next frame will be a key frame (the client sent `resync`). Safe from any thread."""
        self._key_asked = True

    def _stamped(self, timing: dict[str, int], start_ns: int) -> dict[str, int]:
        """`timing`, with "encode" (us since start_ns) if this encoder stamps it."""
        if not self.stamp_encode:
            return timing
        return {**timing, "encode": (time.perf_counter_ns() - start_ns) // 1000}

    def _key(self, seq: int, t: int, timing: dict[str, int], position, rotation, scale, start_ns: int) -> memoryview:
        k, g = self.kernels, self.gather
        if self.format.encoding == "q13":
            k.q13_position(position, g, self.psign, self.lo, self.k, self.held_p.reshape(-1))
            k.q13_rotation(rotation, g, self.rsign, self.held_r)
            k.q13_scale(scale, g, self.thresholds, self.held_s.reshape(-1))
            self.dec[HELD_POSITION] = (self.lo + self.held_p[self.ids].astype(np.float64) * self.step).T
            self.dec[HELD_ROTATION] = q13_decode_rotation64(self.held_r[self.ids]).T
            self.dec[HELD_SCALE] = self.lut[self.held_s[self.ids]].T
        else:
            ok = k.f16(position, g, self.psign, self.held_p.reshape(-1))
            ok &= k.f16(rotation, g, self.rsign, self.held_r.reshape(-1))
            ok &= k.f16(scale, g, np.ones(3, np.float32), self.held_s.reshape(-1))
            if not ok:
                raise ValueError("state has NaN, infinity or values beyond +-65504 (f16)")
            self.dec[HELD_POSITION] = half_to_f32(self.held_p[self.ids]).T
            self.dec[HELD_ROTATION] = half_to_f32(self.held_r[self.ids]).T
            self.dec[HELD_SCALE] = half_to_f32(self.held_s[self.ids]).T
        timing = self._stamped(timing, start_ns)
        return self._packer.pack({"type": "frame", "seq": seq, "t": t, "timing": timing, "key": True,
                                  "n": self.format.count, "position": self.held_p, "rotation": self.held_r,
                                  "scale": self.held_s})

    @property
    def next_is_key(self) -> bool:
        """Whether the next frame will be a key frame (join, resync, key interval)."""
        return self._key_asked or not self.has_key or bool(self.key_interval and self.since_key >= self.key_interval)

    def encode(self, seq: int, t: int, timing: dict[str, int], position: np.ndarray, rotation: np.ndarray,
               scale: np.ndarray) -> memoryview:
        """The next frame message (key or delta; a memoryview of a reused buffer, see MessagePacker) for FLAME-space
        float32 state arrays (N, 3), (N, 4), (N, 3)."""
        start_ns = time.perf_counter_ns()
        if self.pending is not None:
            self.pending()
        if self.next_is_key:
            self.frames += 1
            self._key_asked = False
            data = self._key(seq, t, timing, position, rotation, scale, start_ns)
            self.has_key = True
            self.since_key = 1
            self.key_frames += 1
            return data
        args = (position, rotation, scale, self.rows, self.runs, self.ids, self.psign, self.rsign)
        out = (self._moved, self._wide, self._res, self._pos, self._rot, self._scale)
        if self.format.encoding == "q13":
            counts = self.kernels.delta_q13(
                *args, self.lo, self.k, self.step, self.thresholds, self.lut, ROT_FIELD64, self.tol,
                self.held_p, self.held_r, self.held_s, self.dec, self._flags, self._work, *out)
        else:
            counts = self.kernels.delta_f16(*args, self.tol, self.held_p, self.held_r, self.held_s, self.dec,
                                            self._flags, self._work, *out)
        return self.encode_selected(seq, t, timing, counts, start_ns)

    def encode_selected(self, seq: int, t: int, timing: dict[str, int], counts: tuple[int, ...], start_ns: int
                        ) -> memoryview:
        """The delta frame message of a selection a kernel has just made in this encoder's buffers and held state
        (``counts`` = (n, n_p, w, n_r, n_s), what the delta kernels return; :meth:`encode` runs them on a state, the
        server's deformation may run its own: ``ofera.streaming.direct_delta``). ``start_ns``: when the frame's
        encoding began (perf_counter_ns), for the "encode" stamp. Only where :attr:`next_is_key` was False before the
        kernel ran (a resync asked since then applies to the next frame)."""
        n, n_p, w, n_r, n_s = counts
        # The bin fields first, after room for the header, which is written last, ending where they begin, once the
        # encode time it may carry is known (as fast_encodings.FrameWriter does)
        size = HEADER_ROOM + delta_body_size(self.format.count, n, n_p, w, n_r, n_s, self._row_bytes)
        buf = self._messages.get(size)
        end = self.kernels.delta_body(buf, HEADER_ROOM, self.format.count, self.id_runs, self._flags, self._moved,
                                      self._wide, n, n_p, w, n_r, n_s, *self._flat, *self._row_bytes)
        return self.encode_written(seq, t, timing, n, buf, end, start_ns)

    def body_buffer(self) -> np.ndarray:
        """A message buffer (uint8, from this encoder's pool) with room for the header and any delta frame's body, for
        a kernel that writes the body itself at ``HEADER_ROOM`` (what ``delta_body`` writes) before
        :meth:`encode_written`."""
        return self._messages.get(self._most)

    def encode_written(self, seq: int, t: int, timing: dict[str, int], n: int, buf: np.ndarray, end: int,
                       start_ns: int) -> memoryview:
        """The delta frame message whose body a kernel wrote in ``buf[HEADER_ROOM:end]`` (the bytes of ``delta_body``
        for the selection of ``n`` moved Gaussians it made in this encoder's buffers and held state): its header is
        written in front. Only where :attr:`next_is_key` was False before the kernel ran."""
        if not self.has_key:
            raise RuntimeError("no key frame was sent yet: encode() the first frame from the state")
        self.frames += 1
        self.since_key += 1
        timing = self._stamped(timing, start_ns)
        head = self._head.pack({"type": "frame", "seq": seq, "t": t, "timing": timing, "key": False, "n": int(n)})
        begin = HEADER_ROOM - len(head)
        mv = memoryview(buf)
        if begin < 0:  # (a header longer than the room: one copy of the message)
            return memoryview(b"\x8f" + head[1:] + bytes(mv[HEADER_ROOM:end]))
        mv[begin:HEADER_ROOM] = head
        mv[begin] = 0x8F  # a map of the header's 6 entries and the 9 bin fields
        return mv[begin:end]


def _bytes_array(nbytes: int) -> np.ndarray:
    return np.empty(nbytes, np.uint8)


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
        moved = d.moved
        narrow = ids[moved[:, 0]][~d.wide]
        new = self.position[narrow].astype(np.int32) + d.position_delta.astype(np.int32)
        if new.size and (new.min() < 0 or new.max() > 65535):
            raise ProtocolError(BAD_FIELD, "frame: 'position_delta' takes a code outside 0..65535")
        pos = self.position[ids].copy()  # every carried Gaussian: held codes, then what it carries
        rot = self.rotation[ids].copy()
        scale = self.scale[ids].copy()
        p_new = np.empty((int(moved[:, 0].sum()), 3), np.uint16)
        p_new[~d.wide] = new
        p_new[d.wide] = d.position.view(np.uint16).reshape(-1, 3)
        pos[moved[:, 0]] = p_new
        rot[moved[:, 1]] = d.rotation.view(self.rotation.dtype).reshape(rot[moved[:, 1]].shape)
        scale[moved[:, 2]] = d.scale.view(self.scale.dtype)
        if self.format.encoding == "f16" and ((p_new & 0x7C00) == 0x7C00).any():
            raise ProtocolError(NON_FINITE, "frame: a position change gives NaN or infinity")
        p, r, s = _decode_codes(self.format, pos, rot, scale)
        self.position[ids] = pos
        self.rotation[ids] = rot
        self.scale[ids] = scale
        return Frame(seq=d.seq, t=d.t, timing=d.timing, index=d.index, position=p, rotation=r, scale=s, key=False)
