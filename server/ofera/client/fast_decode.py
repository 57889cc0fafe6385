"""The fast client-side frame decoder (numba): what benchmark and test clients use to keep up with 100k-Gaussian
streams. The reference is the protocol codec (``ofera_protocol.decode_server_message`` + ``ClientConnection``);
this decoder starts from the same field checks (``codec.frame_parts``) and gives the same float32 values.

A frame message is read without copying its payload (``frame_scan.scan_frame``: bins as views of the message;
msgpack's unpacking copies every bin), and its codes decoded on numba's threads while the decoder is alone at work
(:func:`dense_decode_kernel_parallel`, :func:`delta_frame_kernel_parallel`; the thread choice of
``ofera.thread_choice``): the frame's own cores are idle while a client decodes (benchmarks/README.md, round
fourteen).

Delta sessions (PROTOCOL.md 7.1): key frames are decoded here and their codes handed to an
``ofera_protocol.delta.DeltaDecoder``; a delta frame is read in place (``frame_scan.scan_delta_frame``: where each
field is, no map) and checked, unpacked and applied from the message in one call, :func:`delta_frame_kernel` (its
masks: the twin of ``codec.delta_masks``; its fields: of ``codec.decode_delta_frame``; then the twin of
``DeltaDecoder.apply``), and where either finds anything off, nothing held has changed and the codec's own checks
run (:func:`unpack_delta_masks_kernel` for the masks, :func:`delta_apply_kernel`), which name the fault.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numba as nb
import numpy as np
from ofera_protocol import Frame, FrameFormat
from ofera_protocol import _fields as F
from ofera_protocol.codec import decode_server_message, delta_masks, frame_parts, unpack_message
from ofera_protocol.constants import MAX_SERVER_MESSAGE, UINT32_MAX
from ofera_protocol.delta import DeltaDecoder
from ofera_protocol.encodings import POS_LEVELS, ROT_LEVELS, SCALE_LEVELS
from ofera_protocol.errors import BAD_FIELD, NON_FINITE, NOT_READY, ProtocolError
from ofera_protocol.messages import DeltaFrame

from ..jit import NB as _NB
from ..jit import atomic_add, f16_bits_to_f32
from ..thread_choice import Activity, ThreadChoice, load_average, use_threads
from .frame_scan import DELTA_FIELDS, MEMBER, SEQ, N, T, delta_bin, scan_delta_frame, scan_frame


@nb.njit(inline="always", **_NB)
def _f16_finite_into(src, lo, hi, dst):
    """half bits src[lo:hi] -> float32 dst[lo:hi]; False if any is NaN or infinite (exponent all ones). (uint16 bits;
    the cast only types the q13 twin's branch, which never runs it.)"""
    ok = True
    for i in range(np.uint64(lo), np.uint64(hi)):
        h = np.uint16(src[i])
        ok &= (h & 0x7C00) != 0x7C00
        dst[i] = f16_bits_to_f32(h)
    return ok


@nb.njit(inline="always", **_NB)
def _q13_field(v, shift):
    f = np.int32((v >> np.uint32(shift)) & 1023)
    f = (f ^ 512) - 512
    return np.float32(max(f, -ROT_LEVELS))


@nb.njit(inline="always", **_NB)
def _dense_rows(q13, start, stop, pos, rot, scale, lo, step, lut, out_p, out_r, out_s):
    """Rows start..stop - 1 of a dense frame's codes (flat, as received: q13 uint16 / uint32 / uint8, f16 uint16 bits)
    -> float32 out_p, out_r, out_s (flat, C order; q13: PROTOCOL.md 6.3, the reference decoder's arithmetic, rotations
    stored by computed slot as :func:`_q13_rotation_at` says). Returns the fields holding NaN or infinity (f16): bit 0
    position, 1 rotation, 2 scale."""
    three, four = np.uint64(3), np.uint64(4)
    a, b = np.uint64(start), np.uint64(stop)
    if q13:
        for m in range(a, b):
            for c in range(three):
                out_p[three * m + c] = np.float32(lo[c] + np.float64(pos[three * m + c]) * step[c])
                out_s[three * m + c] = lut[scale[three * m + c]]
            _q13_rotation_at(rot[m], out_r, four * m)
        return 0
    bad = 0 if _f16_finite_into(pos, three * a, three * b, out_p) else 1
    bad |= 0 if _f16_finite_into(rot, four * a, four * b, out_r) else 2
    return bad | (0 if _f16_finite_into(scale, three * a, three * b, out_s) else 4)


@nb.njit(**_NB)
def dense_decode_kernel(q13, pos, rot, scale, lo, step, lut, out_p, out_r, out_s):
    """A dense q13 or f16 frame's n = len(rot) (q13) or len(rot) / 4 (f16) rows (:func:`_dense_rows`): 100k q13
    rotations of a key frame 0.70 ms stored by computed slot, 1.15 with selects (round eleven)."""
    return _dense_rows(q13, 0, rot.shape[0] if q13 else rot.shape[0] // 4, pos, rot, scale, lo, step, lut, out_p,
                       out_r, out_s)


DENSE_BLOCK = 4096
"""Rows a thread of :func:`dense_decode_kernel_parallel` decodes at a time."""


@nb.njit(parallel=True, **_NB)
def dense_decode_kernel_parallel(threads, claims, q13, pos, rot, scale, lo, step, lut, out_p, out_r, out_s):
    """:func:`dense_decode_kernel` in blocks of :data:`DENSE_BLOCK` rows that ``threads`` of numba's threads claim as
    they go (claims: (1,) int64 scratch): the same values, the same result."""
    n = rot.shape[0] if q13 else rot.shape[0] // 4
    blocks = (n + DENSE_BLOCK - 1) // DENSE_BLOCK
    bad_p, bad_r, bad_s = 0, 0, 0  # (per field: a parallel loop reduces sums, not bit masks)
    claims[0] = 0
    for _t in nb.prange(threads):
        b = atomic_add(claims, 0, 1)
        while b < blocks:
            found = _dense_rows(q13, b * DENSE_BLOCK, min(n, (b + 1) * DENSE_BLOCK), pos, rot, scale, lo, step, lut,
                                out_p, out_r, out_s)
            bad_p += found & 1
            bad_r += found >> 1 & 1
            bad_s += found >> 2 & 1
            b = atomic_add(claims, 0, 1)
    return (1 if bad_p else 0) | (2 if bad_r else 0) | (4 if bad_s else 0)


@nb.njit(inline="always", **_NB)
def _q13_components(v):
    """One q13 rotation code -> (the three kept components in index order, the largest one), float32."""
    kf = np.float32(math.sqrt(0.5) / ROT_LEVELS)
    a0 = _q13_field(v, 20) * kf
    a1 = _q13_field(v, 10) * kf
    a2 = _q13_field(v, 0) * kf
    d = a0 * a0
    d = d + a1 * a1
    d = d + a2 * a2
    return a0, a1, a2, np.sqrt(max(np.float32(1.0) - d, np.float32(0.0)))


@nb.njit(inline="always", **_NB)
def _q13_rotation_at(v, out, b):
    """One q13 rotation code -> its four float32 components at out[b:b + 4], stored by computed slot (the largest at
    its index, the three small ones around it in order): selects on the index compile to branches, which random
    indices mispredict (2.3x the time)."""
    one, two = np.uint64(1), np.uint64(2)
    a0, a1, a2, largest = _q13_components(v)
    big = np.uint64(v >> np.uint32(30))
    out[b + np.uint64(big < one)] = a0
    out[b + one + np.uint64(big <= one)] = a1
    out[b + two + np.uint64(big <= two)] = a2
    out[b + big] = largest


@nb.njit(**_NB)
def delta_apply_kernel(q13, ids, lists, n_p, n_r, n_s, nw, wide, res, wpos, rot, scl, held_p, held_r, held_s, lo, step,
                       lut, out_p, out_r, out_s):
    """A checked DeltaFrame (PROTOCOL.md 7.1) onto the held codes (:func:`_hold_delta`), then the n carried
    Gaussians decoded (:func:`_gathered`): 0, or _hold_delta's fault code (nothing held has changed then)."""
    code = _hold_delta(q13, ids, lists, n_p, n_r, n_s, nw, wide, res, wpos, rot, scl, held_p, held_r, held_s)
    if code == 0:
        _gathered(q13, 0, ids.shape[0], ids, held_p, held_r, held_s, lo, step, lut, out_p, out_r, out_s)
    return code


@nb.njit(inline="always", **_NB)
def _hold_delta(q13, ids, lists, n_p, n_r, n_s, nw, wide, res, wpos, rot, scl, held_p, held_r, held_s):
    """A checked DeltaFrame (PROTOCOL.md 7.1) onto the held codes. Every array is flat (C order): ids (n,) the
    changed Gaussians; lists (4, >= n) the rows j carrying a position / rotation / scale (n_p, n_r, n_s of them:
    unpack_delta_masks_kernel), then scratch; wide (n_p,) bool, nw of them set; res (3 (n_p - nw),) int8; wpos
    (3 nw,), rot (n_r rw,), scl (3 n_s,)
    the codes sent whole; held_p (3 count,) uint16, held_r (rw count,), held_s (3 count,) the held codes (q13:
    rw = 1, uint32 rotations, uint8 scales; f16: rw = 4, every code uint16). Pass 1 checks every narrow change
    (0 = ok, 1 = a code outside 0..65535, 2 = an f16 position NaN / infinite) and changes nothing on failure; pass
    2 holds the new codes. Unsigned indices throughout (no wrap-around code: see ofera.avatar.kernels)."""
    three, rw = np.uint64(3), np.uint64(1 if q13 else 4)
    narrow = lists[0, :n_p]  # the rows carrying a narrow position: all of them unless some are wide
    if nw:
        narrow = lists[3]
        q = np.uint64(0)
        for p in range(np.uint64(n_p)):  # branch-free compaction
            narrow[q] = lists[0, p]
            q += np.uint64(not wide[p])
    out = np.int32(0)  # any bit above 15 (or the sign) set: a code outside 0..65535
    nan = np.int32(0)
    for q in range(np.uint64(n_p - nw)):
        i = three * np.uint64(ids[narrow[q]])
        for c in range(three):
            v = np.int32(held_p[i + c]) + np.int32(res[three * q + c])
            out |= v
            nan |= np.int32((v & 0x7C00) == 0x7C00)
    if out >> 16:
        return 1
    if nan and not q13:
        return 2
    for q in range(np.uint64(n_p - nw)):
        i = three * np.uint64(ids[narrow[q]])
        for c in range(three):
            held_p[i + c] = np.uint16(np.int32(held_p[i + c]) + np.int32(res[three * q + c]))
    w = np.uint64(0)
    for p in range(np.uint64(n_p) if nw else np.uint64(0)):
        if wide[p]:
            i = three * np.uint64(ids[lists[0, p]])
            for c in range(three):
                held_p[i + c] = wpos[three * w + c]
            w += np.uint64(1)
    for r in range(np.uint64(n_r)):
        i = rw * np.uint64(ids[lists[1, r]])
        for c in range(rw):
            held_r[i + c] = rot[rw * r + c]
    for t in range(np.uint64(n_s)):
        i = three * np.uint64(ids[lists[2, t]])
        for c in range(three):
            held_s[i + c] = scl[three * t + c]
    return 0


@nb.njit(inline="always", **_NB)
def _gathered(q13, start, stop, ids, held_p, held_r, held_s, lo, step, lut, out_p, out_r, out_s):
    """The held codes of rows ids[start:stop] -> float32 entries start..stop - 1 of out_p, out_r, out_s (3, 4 and 3
    a row)."""
    if q13:
        _q13_gathered(start, stop, ids, held_p, held_r, held_s, lo, step, lut, out_p, out_r, out_s)
    else:
        _f16_gathered(start, stop, ids, held_p, held_r, held_s, out_p, out_r, out_s)


@nb.njit(inline="always", **_NB)
def _q13_gathered(start, stop, ids, held_p, held_r, held_s, lo, step, lut, out_p, out_r, out_s):
    """Held q13 codes of rows ids[start:stop] -> float32 (PROTOCOL.md 6.3, the reference decoder's arithmetic)."""
    three, four = np.uint64(3), np.uint64(4)
    for j in range(np.uint64(start), np.uint64(stop)):
        i = np.uint64(ids[j])
        for c in range(three):
            out_p[three * j + c] = np.float32(lo[c] + np.float64(held_p[three * i + c]) * step[c])
            out_s[three * j + c] = lut[held_s[three * i + c]]
        _q13_rotation_at(held_r[i], out_r, four * j)


@nb.njit(inline="always", **_NB)
def _f16_gathered(start, stop, ids, held_p, held_r, held_s, out_p, out_r, out_s):
    """Held f16 codes of rows ids[start:stop] -> float32."""
    three, four = np.uint64(3), np.uint64(4)
    for j in range(np.uint64(start), np.uint64(stop)):
        i = np.uint64(ids[j])
        for c in range(three):
            out_p[three * j + c] = f16_bits_to_f32(np.uint16(held_p[three * i + c]))
            out_s[three * j + c] = f16_bits_to_f32(np.uint16(held_s[three * i + c]))
        for c in range(four):
            out_r[four * j + c] = f16_bits_to_f32(np.uint16(held_r[four * i + c]))


def _bit_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every byte value: its 8 bits LSB first as 8 bools in one little-endian uint64 (256,), the positions of
    its set bits first (256, 8) uint32 (the rest 0), and how many are set (256,) uint64."""
    bits = ((np.arange(256)[:, None] >> np.arange(8)) & 1).astype(bool)
    where = np.zeros((256, 8), np.uint32)
    for v in range(256):
        on = np.flatnonzero(bits[v])
        where[v, :on.size] = on
    return bits.view("<u8")[:, 0].copy(), where, bits.sum(axis=1).astype(np.uint64)


BITS8, SET_BITS, ONES = _bit_tables()


@nb.njit(inline="always", **_NB)
def _padding_ok(buf, n):
    """buf holds ceil(n / 8) bytes and no bit past n is set."""
    return buf.shape[0] == (n + 7) // 8 and not (n & 7 and buf[n >> 3] >> (n & 7))


@nb.njit(inline="always", **_NB)
def _set_bits(buf, out):
    """The positions of buf's set bits (LSB first) into out (>= their number + 8 long: written without a branch,
    8 per byte, the next byte's overwriting the unset). Returns the number set. (Unsigned counters: a signed index
    costs a wrap-around select per store, 2.5x the time.)"""
    k = np.uint64(0)
    for b in range(np.uint64(buf.shape[0])):
        v = buf[b]
        base = np.uint32(8 * b)
        for t in range(np.uint64(8)):
            out[k + t] = base + SET_BITS[v, t]
        k += ONES[v]
    return k


@nb.njit(inline="always", **_NB)
def _unpack_bits(buf, out):
    """buf's bits (LSB first) into out (>= len(buf),) uint64, 8 bools per word (a bool array's memory). Returns the
    number set."""
    k = np.uint64(0)
    for b in range(np.uint64(buf.shape[0])):
        out[b] = BITS8[buf[b]]
        k += ONES[buf[b]]
    return k


@nb.njit(inline="always", **_NB)
def _masks_checked(changed, count, n, mpos, mrot, mscale, wide_bits, index, lists, wide):
    """The masks of a delta frame unpacked and checked (see unpack_delta_masks_kernel), but for the moved bools:
    (ok, n_p, n_r, n_s, wide ones)."""
    if not _padding_ok(changed, count) or n > count:
        return False, 0, 0, 0, 0
    if _set_bits(changed, index) != n or not (_padding_ok(mpos, n) and _padding_ok(mrot, n) and _padding_ok(mscale, n)):
        return False, 0, 0, 0, 0
    for b in range(mpos.shape[0]):  # every changed Gaussian carries something
        full = 255 if 8 * b + 8 <= n else (1 << (n & 7)) - 1
        if (mpos[b] | mrot[b] | mscale[b]) != full:
            return False, 0, 0, 0, 0
    n_p = np.int64(_set_bits(mpos, lists[0]))
    n_r = np.int64(_set_bits(mrot, lists[1]))
    n_s = np.int64(_set_bits(mscale, lists[2]))
    if not _padding_ok(wide_bits, n_p):
        return False, 0, 0, 0, 0
    return True, n_p, n_r, n_s, np.int64(_unpack_bits(wide_bits, wide))


@nb.njit(**_NB)
def unpack_delta_masks_kernel(changed, count, n, mpos, mrot, mscale, wide_bits, index, moved, lists, wide):
    """A delta frame's masks (PROTOCOL.md 7.1) unpacked and checked in one go, 8 bits at a time by table: the
    changed Gaussians into index (>= count + 8,) uint32; the moved bits into the rows of moved (3, >= n / 8 + 1)
    uint64 (the memory of bool rows), the rows j that carry each into lists (3, >= n + 8) uint32; the wide bits
    into wide (>= n / 8 + 1,) uint64 (bools).
    Returns (ok, n_p, n_r, n_s, wide ones); ok False for any fault codec.delta_masks reports (it then names it)."""
    ok, n_p, n_r, n_s, nw = _masks_checked(changed, count, n, mpos, mrot, mscale, wide_bits, index, lists, wide)
    if ok:
        _unpack_bits(mpos, moved[0])
        _unpack_bits(mrot, moved[1])
        _unpack_bits(mscale, moved[2])
    return ok, n_p, n_r, n_s, nw


@nb.njit(inline="always", **_NB)
def _finite_f16(codes):
    """No half in codes (uint16) is NaN or infinite (exponent all ones)."""
    bad = np.uint16(0)
    for i in range(np.uint64(codes.shape[0])):
        bad |= np.uint16((codes[i] & np.uint16(0x7C00)) == np.uint16(0x7C00))
    return bad == 0


@nb.njit(inline="always", **_NB)
def _frame_held(q13, count, n, buf, fields, index, lists, wide, wide_bools, held_p, held_r, held_s):
    """A whole delta frame from its message (buf, uint8 as received; fields: where its bins are,
    :func:`.frame_scan.scan_delta_frame`): its masks (:func:`_masks_checked`), the lengths of its code fields and,
    f16, the codes sent whole finite (codec.decode_delta_frame's checks), then :func:`_hold_delta` (wide: the wide
    bits' words, wide_bools the same memory as bools). Returns 0, or non-zero for any fault (nothing held has changed
    then: the codec's path names it)."""
    changed, mpos, mrot, mscale = (delta_bin(buf, fields, 0), delta_bin(buf, fields, 1), delta_bin(buf, fields, 2),
                                   delta_bin(buf, fields, 3))
    wide_bits, res, wpos = delta_bin(buf, fields, 4), delta_bin(buf, fields, 5), delta_bin(buf, fields, 6)
    rot, scl = delta_bin(buf, fields, 7), delta_bin(buf, fields, 8)
    ok, n_p, n_r, n_s, nw = _masks_checked(changed, count, n, mpos, mrot, mscale, wide_bits, index, lists, wide)
    rb, sb = (4, 3) if q13 else (8, 6)
    if not ok or res.shape[0] != 3 * (n_p - nw) or wpos.shape[0] != 6 * nw or rot.shape[0] != rb * n_r \
            or scl.shape[0] != sb * n_s:
        return 3
    wpos16, ids = wpos.view(np.uint16), index[:n]
    if q13:
        return _hold_delta(q13, ids, lists, n_p, n_r, n_s, nw, wide_bools, res.view(np.int8), wpos16,
                           rot.view(np.uint32), scl, held_p, held_r, held_s)
    rot16, scl16 = rot.view(np.uint16), scl.view(np.uint16)
    if not (_finite_f16(wpos16) and _finite_f16(rot16) and _finite_f16(scl16)):
        return 3
    return _hold_delta(q13, ids, lists, n_p, n_r, n_s, nw, wide_bools, res.view(np.int8), wpos16, rot16, scl16, held_p,
                       held_r, held_s)


@nb.njit(**_NB)
def delta_frame_kernel(q13, count, n, buf, fields, index, lists, wide, wide_bools, held_p, held_r, held_s, lo, step,
                       lut, out_p, out_r, out_s):
    """A whole delta frame from its message onto the held codes (:func:`_frame_held`), then its n carried Gaussians
    decoded into out_p, out_r, out_s (:func:`_gathered`). Returns 0, or _frame_held's fault code."""
    code = _frame_held(q13, count, n, buf, fields, index, lists, wide, wide_bools, held_p, held_r, held_s)
    if code == 0:
        _gathered(q13, 0, n, index, held_p, held_r, held_s, lo, step, lut, out_p, out_r, out_s)
    return code


DECODE_BLOCK = 1024
"""Carried Gaussians a thread of :func:`delta_frame_kernel_parallel` decodes at a time."""


@nb.njit(parallel=True, **_NB)
def delta_frame_kernel_parallel(threads, claims, q13, count, n, buf, fields, index, lists, wide, wide_bools, held_p,
                                held_r, held_s, lo, step, lut, out_p, out_r, out_s):
    """:func:`delta_frame_kernel` with the decoding in blocks of :data:`DECODE_BLOCK` Gaussians that ``threads`` of
    numba's threads claim as they go (claims: (1,) int64 scratch): the same values."""
    code = _frame_held(q13, count, n, buf, fields, index, lists, wide, wide_bools, held_p, held_r, held_s)
    if code:
        return code
    blocks = (n + DECODE_BLOCK - 1) // DECODE_BLOCK
    claims[0] = 0
    for _t in nb.prange(threads):
        b = atomic_add(claims, 0, 1)
        while b < blocks:
            _gathered(q13, b * DECODE_BLOCK, min(n, (b + 1) * DECODE_BLOCK), index, held_p, held_r, held_s, lo, step,
                      lut, out_p, out_r, out_s)
            b = atomic_add(claims, 0, 1)
    return 0


def _codes(a: np.ndarray) -> np.ndarray:
    """A DeltaFrame's codes as flat unsigned integers (f16 arrays: their bits)."""
    a = a.reshape(-1)
    return a.view(np.uint16) if a.dtype == np.float16 else a


_Z3 = np.zeros(3)
_Z256 = np.zeros(256, np.float32)
_CODES = {True: ("<u2", "<u4", "u1"), False: ("<u2", "<u2", "<u2")}
"""A dense frame's code fields' dtypes by q13 (else f16): position, rotation, scale."""


def decoder_warm(parallel: bool = True) -> None:
    """Compile the decoding kernels for message buffers (read-only uint views); ``parallel``: the threaded ones as
    well (and start numba's threads)."""
    raw = bytes(64)
    out3, out4 = np.zeros((2, 3), np.float32), np.zeros((2, 4), np.float32)
    threads = nb.get_num_threads()
    for q13 in (True, False):
        dense = (q13, *[np.frombuffer(raw, dt, 2 * w) for dt, w in zip(_CODES[q13], (3, 1 if q13 else 4, 3))],
                 np.zeros(3), np.ones(3), np.ones(256, np.float32), out3.reshape(-1), out4.reshape(-1),
                 out3.copy().reshape(-1))
        dense_decode_kernel(*dense)
        if parallel:
            dense_decode_kernel_parallel(threads, np.zeros(1, np.int64), *dense)
    one = np.frombuffer(b"\x01", np.uint8)
    index, moved, lists, wide = np.zeros(9, np.uint32), np.zeros((3, 1), np.uint64), np.zeros((4, 9), np.uint32), \
        np.zeros(1, np.uint64)
    unpack_delta_masks_kernel(one, 1, 1, one, one, one, np.frombuffer(b"\x00", np.uint8), index, moved, lists, wide)
    buf = np.frombuffer(raw, np.uint8)  # a message as received: a read-only uint8 view
    fields = np.zeros((len(DELTA_FIELDS), 2), np.int64)
    scan_delta_frame(buf, fields, np.zeros((15, 3), np.int64))
    for q13 in (True, False):
        held = (np.zeros(3, np.uint16), np.zeros(1, np.uint32) if q13 else np.zeros(4, np.uint16),
                np.zeros(3, np.uint8 if q13 else np.uint16))
        frame = (q13, 1, 1, buf, fields, index, lists, wide, wide.view(bool), *held, np.zeros(3), np.ones(3),
                 np.ones(256, np.float32), out3[0], out4[0], out3[1])
        delta_frame_kernel(*frame)
        if parallel:
            delta_frame_kernel_parallel(threads, np.zeros(1, np.int64), *frame)
    ids = np.zeros(1, np.uint32)  # the types of a DeltaFrame's arrays (read-only views of the message)
    res = np.frombuffer(raw, np.int8, 3)
    for q13 in (True, False):
        wpos = np.frombuffer(raw, "<u2", 3)
        rot = np.frombuffer(raw, "<u4", 1) if q13 else np.frombuffer(raw, "<u2", 4)
        scl = np.frombuffer(raw, np.uint8 if q13 else "<u2", 3)
        held_r = np.zeros(1, np.uint32) if q13 else np.zeros(4, np.uint16)
        held_s = np.zeros(3, np.uint8 if q13 else np.uint16)
        delta_apply_kernel(q13, ids, lists, 1, 1, 1, 0, wide.view(bool)[:1], res, wpos, rot, scl,
                           np.zeros(3, np.uint16), held_r, held_s, np.zeros(3), np.ones(3), np.ones(256, np.float32),
                           out3[0], out4[0], out3[1])


DECODERS = Activity()
"""The process-wide activity record of automatic decoders (a client process decoding several streams keeps its cores
busy: one thread each)."""


class FastFrameDecoder:
    """Decodes the frames of one session (FrameFormat) into float32 buffers owned by the decoder (reused:
    each call overwrites the previous frame's arrays), with the codec's checks (lengths, finiteness, index).
    In a delta session it also keeps the codes the client holds (``delta``) and returns delta frames as
    sparse-like Frames (``index`` = the changed Gaussians). ``ofera_protocol.decode_server_message`` is the
    reference.

    ``parallel``: a frame's decoding on numba's threads (:func:`dense_decode_kernel_parallel`,
    :func:`delta_frame_kernel_parallel`: the same values) or on one (False); None (the default) chooses per frame as
    the server's sessions do (``ofera.thread_choice``): threads only while this decoder is the only one of
    ``activity`` decoding, the machine is not busy, and its threaded frames (dense and delta ones measured apart) were
    the faster per Gaussian."""

    def __init__(self, fmt: FrameFormat, parallel: bool | None = None, activity: Activity = DECODERS) -> None:
        decoder_warm(parallel is not False)  # compiled (or loaded from the on-disk cache) before the first frame
        self.format = fmt
        self.parallel = parallel  # a frame's decoding on numba's threads; None: automatic (see the class)
        self.activity = activity
        self.choices = {"delta": ThreadChoice(), "dense": ThreadChoice()}
        self.threads = nb.get_num_threads()  # read once (37 us on a cold CPU: ofera.avatar.fast)
        self.threaded = False  # the last decoded frame's mode
        self._claims = np.zeros(1, np.int64)  # the threaded kernels' shared block counter
        n = fmt.count
        self._pos = np.zeros((n, 3), np.float32)
        self._rot = np.zeros((n, 4), np.float32)
        self._scale = np.zeros((n, 3), np.float32)
        self.delta: Any = None
        if fmt.delta:
            self.delta = DeltaDecoder(fmt)
            d = self.delta  # flat views, made once (its held codes change in place; numpy calls cost on a cold CPU)
            self._held_flat = (d.position.reshape(-1), d.rotation.reshape(-1), d.scale.reshape(-1))
        self._out_flat = (self._pos.reshape(-1), self._rot.reshape(-1), self._scale.reshape(-1))  # rows 0..n-1 first
        if fmt.encoding == "q13":
            assert fmt.quant is not None
            q = fmt.quant
            self._lo = q.pos_min.astype(np.float64)
            self._step = (q.pos_max.astype(np.float64) - self._lo) / POS_LEVELS
            lmin, lmax = float(q.log_scale[0]), float(q.log_scale[1])
            codes = np.arange(256, dtype=np.float64)
            self._lut = np.exp(lmin + codes * ((lmax - lmin) / SCALE_LEVELS)).astype(np.float32)
        if fmt.delta:  # the masks' buffers, reused (a DeltaFrame holds views until the next frame); the kernels
            self._index = np.zeros(n + 8, np.uint32)  # write 8 entries per mask byte
            self._lists = np.zeros((4, n + 8), np.uint32)  # + the apply kernel's scratch
            self._moved = np.zeros((3, n // 8 + 1), np.uint64)  # bools, 8 to a word
            self._wide = np.zeros(n // 8 + 1, np.uint64)
            self._wide_bools = self._wide.view(bool)
            self._counts = (0, 0, 0, 0)
            self._fields = np.zeros((len(DELTA_FIELDS), 2), np.int64)  # where a delta frame's fields are
            self._timing = np.zeros((15, 3), np.int64)  # (a fixmap's stages at most)

    def _masks(self, m: dict, fmt: FrameFormat) -> Any:
        """codec.delta_masks by unpack_delta_masks_kernel into this decoder's buffers; the codec's own on any fault (it
        raises the exact ProtocolError)."""
        w = "frame"
        n = F.get_int(m, "n", w, lo=0, hi=UINT32_MAX)
        bins = [np.frombuffer(F.get_bin(m, k, w), np.uint8) for k in
                ("changed", "moved_position", "moved_rotation", "moved_scale", "wide")]
        ok = n <= fmt.count
        if ok:
            ok, n_p, n_r, n_s, nw = unpack_delta_masks_kernel(bins[0], fmt.count, n, *bins[1:], self._index,
                                                              self._moved, self._lists, self._wide)
        if not ok:
            return delta_masks(m, fmt)
        self._counts = (n_p, n_r, n_s, nw)  # the rows in self._lists that _apply_delta reads
        moved, wide = self._moved.view(bool)[:, :n].T, self._wide_bools[:n_p]
        return self._index[:n], moved, wide, (n_p, n_r, n_s, nw)  # views, as the frame's arrays are

    def _delta(self, data: bytes | bytearray | memoryview) -> Frame | None:
        """A delta frame (``key`` false) read by :func:`.frame_scan.scan_delta_frame` and applied by
        :func:`delta_frame_kernel`, one call each (no map, no copy), or None where anything is off or not as usual
        (nothing held has changed then: :meth:`decode` reads it as the codec does, which names the fault). The
        checks and their order are the codec's: seq, t, timing, then the masks and fields."""
        buf = np.frombuffer(memoryview(data).toreadonly(), np.uint8)  # (read-only whatever the buffer: one type)
        if buf.shape[0] > MAX_SERVER_MESSAGE or not self.delta.has_key:
            return None
        stages = scan_delta_frame(buf, self._fields, self._timing)
        if stages < 0:
            return None
        values = self._fields[:, 0].tolist()
        seq, t, n, member = values[SEQ], values[T], values[N], values[MEMBER]
        if seq < 0 or not 0 <= n <= self.format.count:
            return None
        try:  # the stage names and member: UTF-8, as msgpack's strings
            timing = {str(data[a:a + k], "utf-8"): v for a, k, v in self._timing[:stages].tolist()}
            if member >= 0:
                str(data[member:member + int(self._fields[MEMBER, 1])], "utf-8")
        except UnicodeDecodeError:
            return None
        q13 = self.format.encoding == "q13"
        if self._run("delta", n, delta_frame_kernel_parallel, delta_frame_kernel, q13, self.format.count, n, buf,
                     self._fields, self._index, self._lists, self._wide, self._wide_bools, *self._held_flat,
                     *self._coding(q13), *self._out_flat):
            return None
        return Frame(seq=seq, t=t, timing=timing, index=self._index[:n], position=self._pos[:n],
                     rotation=self._rot[:n], scale=self._scale[:n], key=False)

    def _coding(self, q13: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The q13 decoding's constants (lo, step, scale table), or placeholders (f16)."""
        return (self._lo, self._step, self._lut) if q13 else (_Z3, _Z3, _Z256)

    def _run(self, kind: str, work: int, parallel_kernel: Any, kernel: Any, *args: Any) -> int:
        """``kernel(*args)``, or ``parallel_kernel(threads, claims, *args)`` where this frame's thread choice
        says so (``parallel``, or automatic: see the class); an automatic frame's time is recorded for ``work`` units
        in the choice of its ``kind`` (delta and dense frames differ in cost per unit)."""
        par = self.parallel
        choice = self.choices[kind]
        if par is None:
            par = use_threads(self.activity.note(id(self)), self.threads, load_average) and choice.choose()
        self.threaded = par
        start = time.perf_counter_ns()
        out = parallel_kernel(self.threads, self._claims, *args) if par else kernel(*args)
        if self.parallel is None:
            choice.record(par, time.perf_counter_ns() - start, max(work, 1))
        return out

    def _apply_delta(self, d: DeltaFrame) -> Frame:
        """The numba twin of ofera_protocol.delta.DeltaDecoder.apply (same checks, same values)."""
        dd, fmt = self.delta, self.format
        if not dd.has_key:
            raise ProtocolError(NOT_READY, "frame: a delta frame before any key frame (send resync)")
        q13 = fmt.encoding == "q13"
        n = d.n
        p, r, s = self._pos[:n], self._rot[:n], self._scale[:n]
        lo, step, lut = self._coding(q13)
        code = delta_apply_kernel(q13, d.index, self._lists, *self._counts, d.wide, d.position_delta.reshape(-1),
                                  _codes(d.position), _codes(d.rotation), _codes(d.scale), *self._held_flat, lo, step,
                                  lut, *self._out_flat)
        if code == 1:
            raise ProtocolError(BAD_FIELD, "frame: 'position_delta' takes a code outside 0..65535")
        if code == 2:
            raise ProtocolError(NON_FINITE, "frame: a position change gives NaN or infinity")
        return Frame(seq=d.seq, t=d.t, timing=d.timing, index=d.index, position=p, rotation=r, scale=s, key=False)

    def decode(self, data) -> object:
        """A `frame` message -> ofera_protocol.Frame whose arrays are views of this decoder's buffers;
        other messages are decoded by the reference codec. Raises ProtocolError like the codec."""
        if self.delta is not None and isinstance(data, (bytes, bytearray, memoryview)):
            frame = self._delta(data)
            if frame is not None:
                return frame
        m = scan_frame(data, MAX_SERVER_MESSAGE)  # bins as views of data; None: the codec's unpacking decides
        if m is None:
            m = unpack_message(data, MAX_SERVER_MESSAGE)
        if m.get("type") != "frame":
            return decode_server_message(data, self.format)
        fmt = self.format
        parts = frame_parts(m, fmt, self._masks)  # masks: delta frames only
        if isinstance(parts, DeltaFrame):
            return self._apply_delta(parts)
        seq, t, timing, key, n, index, bufs = parts
        p, r, s = self._pos[:n], self._rot[:n], self._scale[:n]
        if fmt.encoding == "f32":
            for name, buf in zip(("position", "rotation", "scale"), bufs):
                a = np.frombuffer(buf, "<f4")
                if a.size and not (np.isfinite(a.min()) and np.isfinite(a.max())):
                    raise ProtocolError(NON_FINITE, f"frame field {name!r} holds NaN or infinity")
            p, r, s = (np.frombuffer(b, "<f4").reshape(n, w) for b, w in zip(bufs, (3, 4, 3)))  # read-only views
        else:
            q13 = fmt.encoding == "q13"
            codes = [np.frombuffer(b, dt) for b, dt in zip(bufs, _CODES[q13])]
            bad = self._run("dense", n, dense_decode_kernel_parallel, dense_decode_kernel, q13, *codes,
                            *self._coding(q13), *self._out_flat)
            for bit, name in enumerate(("position", "rotation", "scale")):
                if bad >> bit & 1:
                    raise ProtocolError(NON_FINITE, f"frame field {name!r} holds NaN or infinity")
        frame = Frame(seq=seq, t=t, timing=timing, index=index, position=p, rotation=r, scale=s, key=key,
                      codes=tuple(codes) if key else None)  # type: ignore[arg-type]
        if key:
            self.delta.key(frame)
        return frame
