"""numba frame-encoding kernels (the accelerator the server passes to the protocol's FrameWriter), and
the "moved since last sent" q13 delta encoder.

Why here and not in ``ofera_protocol``: the protocol package must stay importable with numpy and msgpack
only, so it holds the buffer layout (:class:`ofera_protocol.fast_encodings.FrameWriter`) and a plain
numpy kernel set; the server passes :func:`numba_kernels` in. Every kernel produces the bytes of the
reference encoder (:mod:`ofera_protocol.encodings`) exactly; tests compare them.

- f16: LLVM's ``fptrunc float -> half`` (IEEE round-to-nearest-even, what numpy's astype does; one
  vcvtps2ph on x86 with F16C), about 10x numpy's conversion here. numba has no float16 type, so the
  kernel writes the half's bits as uint16.
- q13 positions: the reference's float64 arithmetic, operation for operation (no fastmath).
- q13 rotations: the reference's float32 arithmetic (|q|^2 summed in component order, as numpy's einsum
  does, a float32 division and products), branch-free selection of the dropped component.
- q13 scales: the reference quantiser's own thresholds
  (:func:`ofera_protocol.fast_encodings.scale_thresholds`) looked up by the float32 bit pattern
  (:func:`scale_table`), so no float32 logarithm has to match numpy's.

:class:`DeltaQ13` keeps, per client, the values that client holds (decoded from what was sent to it)
and sends a Gaussian only when the frame's value has moved away from them by more than a threshold,
so the error the client sees is bounded by the threshold (see its docstring).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic
from ofera_protocol.encodings import POS_LEVELS, ROT_LEVELS, SCALE_LEVELS, FrameFormat
from ofera_protocol.fast_encodings import (
    F16_MAX,
    F32_MAX,
    FrameWriter,
    NumpyKernels,
    position_factors,
    scale_thresholds,
)
from ofera_protocol.messages import Quant

_NB = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy", "boundscheck": False}
_SQRT2_511 = np.float32(np.sqrt(2.0) * ROT_LEVELS)  # the reference's float32 constant


@intrinsic
def f32_to_f16_bits(typingctx, x):
    """float32 -> the uint16 bits of the nearest IEEE binary16 (round half to even)."""
    if not isinstance(x, types.Float) or x.bitwidth != 32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(builder.fptrunc(args[0], ir.HalfType()), ir.IntType(16))

    return types.uint16(x), codegen


@nb.njit(**_NB)
def _row(gather, m):
    return gather[m] if gather.shape[0] > 0 else m


@nb.njit(**_NB)
def f32_kernel(src, gather, count, sign, dst):
    """dst[m k + c] = src[row m, c] * sign[c]; False if any value is NaN or infinite."""
    k = src.shape[1]
    ok = True
    for m in range(count):
        r = _row(gather, m)
        for c in range(k):
            v = src[r, c] * sign[c]
            ok &= abs(v) <= F32_MAX
            dst[m * k + c] = v
    return ok


@nb.njit(**_NB)
def f16_kernel(src, gather, count, sign, dst):
    """dst[m k + c] = half bits of src[row m, c] * sign[c]; False if any value is NaN, infinite or
    beyond +-65504."""
    k = src.shape[1]
    ok = True
    for m in range(count):
        r = _row(gather, m)
        for c in range(k):
            v = src[r, c] * sign[c]
            ok &= abs(v) <= F16_MAX
            dst[m * k + c] = f32_to_f16_bits(v)
    return ok


@nb.njit(**_NB)
def f16_flat_kernel(src, dst):
    """Contiguous no-gather no-mirror case of :func:`f16_kernel` (vectorises): src (n,) f32 -> dst (n,)."""
    ok = True
    for i in range(src.shape[0]):
        v = src[i]
        ok &= abs(v) <= F16_MAX
        dst[i] = f32_to_f16_bits(v)
    return ok


@nb.njit(**_NB)
def f32_flat_kernel(src, dst):
    """Contiguous no-gather no-mirror case of :func:`f32_kernel`."""
    ok = True
    for i in range(src.shape[0]):
        v = src[i]
        ok &= abs(v) <= F32_MAX
        dst[i] = v
    return ok


@nb.njit(**_NB)
def q13_position_kernel(src, gather, count, sign, lo, k, dst):
    """uint16 q = clip(rint((float64(p) - lo) * k), 0, 65535) per axis (the reference's float64 steps)."""
    for m in range(count):
        r = _row(gather, m)
        for c in range(3):
            q = (np.float64(src[r, c] * sign[c]) - lo[c]) * k[c]
            if abs(q) < 2.0**50:
                q = _rint(q)
            q = min(max(q, 0.0), POS_LEVELS)  # NaN -> 0
            dst[m * 3 + c] = np.uint16(q)


_MAGIC = 6755399441055744.0  # 1.5 * 2**52: (x + M) - M rounds |x| < 2**51 to an integer, half to even


@nb.njit(inline="always", **_NB)
def _rint(x):
    """Round half to even (what np.rint does) for finite |x| < 2**51; cheaper than a libm call."""
    return (x + _MAGIC) - _MAGIC


@nb.njit(inline="always", **_NB)
def _snorm10(v):
    q = min(max(_rint(np.float64(v)), -ROT_LEVELS), ROT_LEVELS)
    return np.uint32(np.int32(q) & 0x3FF)


@nb.njit(inline="always", **_NB)
def pack_rotation(x, y, z, w):
    """One (x, y, z, w) float32 quaternion -> q13 "smallest three" uint32 (reference arithmetic)."""
    n2 = x * x
    n2 = n2 + y * y
    n2 = n2 + z * z
    n2 = n2 + w * w
    if not (math.isfinite(n2) and n2 > 0):
        x = np.float32(0.0)
        y = np.float32(0.0)
        z = np.float32(0.0)
        w = np.float32(1.0)
        n2 = np.float32(1.0)
    a0 = abs(x)
    a1 = abs(y)
    a2 = abs(z)
    a3 = abs(w)
    upper = max(a2, a3) > max(a0, a1)
    i = np.uint32(2 * upper + ((upper and a3 > a2) or ((not upper) and a1 > a0)))
    big = x if i == 0 else (y if i == 1 else (z if i == 2 else w))
    f = _SQRT2_511 / np.sqrt(n2)
    f = -f if big < 0 else f
    sx = _snorm10(x * f)
    sy = _snorm10(y * f)
    sz = _snorm10(z * f)
    sw = _snorm10(w * f)
    # kept components in index order: i=0 -> y z w, 1 -> x z w, 2 -> x y w, 3 -> x y z
    k0 = sx if i != 0 else sy
    k1 = sy if i >= 2 else sz
    k2 = sz if i == 3 else sw
    return (i << 30) | (k0 << 20) | (k1 << 10) | k2


@nb.njit(**_NB)
def q13_rotation_kernel(src, gather, count, sign, dst):
    for m in range(count):
        r = _row(gather, m)
        dst[m] = pack_rotation(src[r, 0] * sign[0], src[r, 1] * sign[1], src[r, 2] * sign[2], src[r, 3] * sign[3])


SCALE_BUCKET_SHIFT = 12
"""Scale codes are looked up by the float32 bit pattern >> 12: a bucket spans a relative width of 2^-11
(0.05 %), below the spacing of two codes (>= 0.39 %: the log range is >= 1 wide), so it holds at most
one threshold and one comparison finishes the lookup."""


def scale_table(thresholds: np.ndarray) -> np.ndarray:
    """Lookup table of :func:`_scale_code` from the 255 thresholds: int64 (B + 2, 2) rows
    [count of thresholds below the bucket, bits of the bucket's threshold or +inf]; row 0 holds the
    first and last bucket numbers."""
    bits = np.asarray(thresholds, np.float32).view(np.int32).astype(np.int64)
    b0, b1 = bits[0] >> SCALE_BUCKET_SHIFT, bits[-1] >> SCALE_BUCKET_SHIFT
    buckets = np.arange(b0, b1 + 1)
    start = buckets << SCALE_BUCKET_SHIFT
    below = np.searchsorted(bits, start, side="left")  # thresholds with bits < bucket start
    nxt = np.full(buckets.size, 0x7F800001, np.int64)  # no threshold in the bucket: never reached
    inside = below < bits.size
    inside[inside] = (bits[below[inside]] >> SCALE_BUCKET_SHIFT) == buckets[inside]
    nxt[inside] = bits[below[inside]]
    if np.any(np.diff(bits >> SCALE_BUCKET_SHIFT) == 0):
        raise ValueError("two scale thresholds share a lookup bucket (log-scale range too narrow)")
    table = np.empty((buckets.size + 1, 2), np.int64)
    table[0] = b0, b1
    table[1:, 0] = below
    table[1:, 1] = nxt
    return table


@nb.njit(inline="always", **_NB)
def _scale_code(v, table):
    """Number of thresholds <= v (NaN, zero and negative scales -> 0) via the bucket table."""
    b = np.int64(np.float32(v).view(np.int32))
    if b <= 0:  # +0, negative numbers (sign bit set)
        return 0
    if b > 0x7F800000:  # NaN
        return 0
    bucket = b >> SCALE_BUCKET_SHIFT
    if bucket < table[0, 0]:
        return 0
    if bucket > table[0, 1]:
        return SCALE_LEVELS
    row = bucket - table[0, 0] + 1
    return table[row, 0] + (1 if b >= table[row, 1] else 0)


@nb.njit(**_NB)
def q13_scale_kernel(src, gather, count, table, dst):
    for m in range(count):
        r = _row(gather, m)
        for c in range(3):
            dst[m * 3 + c] = np.uint8(_scale_code(src[r, c], table))


_NO_GATHER = np.zeros(0, np.int64)


class NumbaKernels:
    """The numba kernel set for :class:`ofera_protocol.fast_encodings.FrameWriter`."""

    @staticmethod
    def _g(src: np.ndarray, gather: np.ndarray | None) -> tuple[np.ndarray, int]:
        return (_NO_GATHER, src.shape[0]) if gather is None else (gather, gather.shape[0])

    @staticmethod
    def _flat(src: np.ndarray, gather: np.ndarray | None, sign: np.ndarray) -> np.ndarray | None:
        if gather is None and src.dtype == np.float32 and src.flags.c_contiguous and (sign == 1).all():
            return src.reshape(-1)
        return None

    def f32(self, src, gather, sign, dst) -> bool:
        flat = self._flat(src, gather, sign)
        if flat is not None:  # a plain copy: numpy's min/max and memcpy beat a scalar loop
            if flat.size and not (-F32_MAX <= flat.min() and flat.max() <= F32_MAX):
                return False
            dst[...] = flat
            return True
        g, n = self._g(src, gather)
        return bool(f32_kernel(src, g, n, sign, dst))

    def f16(self, src, gather, sign, dst) -> bool:
        flat = self._flat(src, gather, sign)
        if flat is not None:
            return bool(f16_flat_kernel(flat, dst))
        g, n = self._g(src, gather)
        return bool(f16_kernel(src, g, n, sign, dst))

    def q13_position(self, src, gather, sign, lo, k, dst) -> None:
        g, n = self._g(src, gather)
        q13_position_kernel(src, g, n, sign, lo, k, dst)

    def q13_rotation(self, src, gather, sign, dst) -> None:
        g, n = self._g(src, gather)
        q13_rotation_kernel(src, g, n, sign, dst)

    def __init__(self) -> None:
        self._tables: dict[bytes, np.ndarray | None] = {}

    def table(self, thresholds: np.ndarray) -> np.ndarray | None:
        key = thresholds.tobytes()
        if key not in self._tables:
            try:
                self._tables[key] = scale_table(thresholds)
            except ValueError:  # a log range narrower than 1: the numpy kernel handles it
                self._tables[key] = None
        return self._tables[key]

    def q13_scale(self, src, gather, thresholds, dst) -> None:
        table = self.table(thresholds)
        if table is None:
            NumpyKernels().q13_scale(src, gather, thresholds, dst)
            return
        g, n = self._g(src, gather)
        q13_scale_kernel(src, g, n, table, dst)


_KERNELS: NumbaKernels | None = None


def numba_kernels(warm: bool = True) -> NumbaKernels:
    """The shared kernel set; ``warm`` compiles (or loads from the on-disk cache) every kernel now."""
    global _KERNELS
    if _KERNELS is None:
        _KERNELS = NumbaKernels()
        if warm:
            warm_up()
    return _KERNELS


def warm_up() -> None:
    """Compile every kernel for the types the server uses: float32 state arrays, writable or read-only
    (the fast path's pooled states are read-only, a distinct numba type), full or gathered rows, aligned
    or unaligned destinations (fields inside a message buffer)."""
    k = NumbaKernels()
    p = np.zeros((2, 3), np.float32)
    r = np.zeros((2, 4), np.float32)
    r[:, 3] = 1
    s = np.full((2, 3), 1e-3, np.float32)
    ones3, ones4 = np.ones(3, np.float32), np.ones(4, np.float32)
    lo, kk = np.zeros(3), np.ones(3)
    thr = np.exp(np.linspace(-9, -2, SCALE_LEVELS)).astype(np.float32)
    buf = bytearray(64)
    for readonly in (False, True):
        if readonly:
            p, r, s = (a.copy() for a in (p, r, s))
            for a in (p, r, s):
                a.flags.writeable = False
        for gather in (None, np.arange(2, dtype=np.int64)):
            for dst16, dst32, dstf in ((np.zeros(8, np.uint16), np.zeros(2, np.uint32), np.zeros(8, np.float32)),
                                       (np.frombuffer(buf, np.uint16, 8, 1), np.frombuffer(buf, np.uint32, 2, 1),
                                        np.frombuffer(buf, np.float32, 8, 1))):
                k.f32(p, gather, ones3, dstf[:6])
                k.f32(r, gather, ones4, dstf)
                k.f16(p, gather, ones3, dst16[:6])
                k.f16(r, gather, ones4, dst16)
                k.q13_position(p, gather, ones3, lo, kk, dst16[:6])
                k.q13_rotation(r, gather, ones4, dst32)
                k.q13_scale(s, gather, thr, np.zeros(6, np.uint8))
                k.q13_scale(s, gather, thr, np.frombuffer(buf, np.uint8, 6, 1))
                if gather is None:  # the mirrored (unity) path of the flat kernels' callers
                    k.f16(p, gather, -ones3, dst16[:6])
                    k.f32(p, gather, -ones3, dstf[:6])
    delta_kernel_warm()
    decoder_warm()


def frame_writer(fmt: FrameFormat, coords: str = "flame", gather: np.ndarray | None = None,
                 index: np.ndarray | None = None, pool: int = 4) -> FrameWriter:
    """A FrameWriter using the numba kernels."""
    return FrameWriter(fmt, coords, gather, index, kernels=numba_kernels(), pool=pool)


# ============================================================================= delta (moved since last sent)


@nb.njit(**_NB)
def _delta_select(pos, rot, scale, ids, psign, rsign, lo, k, step, table, log_lo, log_step,
                  held_pos, held_rot, held_slo, held_shi, pos_thr2, rot_dot, log_thr, force, sel, out_pos, out_rot,
                  out_scale):
    """For the M candidate rows ``ids``: quantise, compare with what the client holds, and for the ones
    that moved (or all, if ``force``) write their codes to out_* and update the held values. Returns
    how many were selected (their positions in ``ids`` are sel[:count])."""
    count = 0
    for m in range(ids.shape[0]):
        r = ids[m]
        px = pos[r, 0] * psign[0]
        py = pos[r, 1] * psign[1]
        pz = pos[r, 2] * psign[2]
        dx = np.float64(px) - held_pos[m, 0]
        dy = np.float64(py) - held_pos[m, 1]
        dz = np.float64(pz) - held_pos[m, 2]
        moved = force or dx * dx + dy * dy + dz * dz > pos_thr2
        qx = rot[r, 0] * rsign[0]
        qy = rot[r, 1] * rsign[1]
        qz = rot[r, 2] * rsign[2]
        qw = rot[r, 3] * rsign[3]
        if not moved:
            d = abs(qx * held_rot[m, 0] + qy * held_rot[m, 1] + qz * held_rot[m, 2] + qw * held_rot[m, 3])
            moved = d < rot_dot
        if not moved:
            for c in range(3):
                v = scale[r, c]
                if not (held_slo[m, c] <= v <= held_shi[m, c]):  # ln distance > log_thr (or NaN)
                    moved = True
        if not moved:
            continue
        sel[count] = m
        for c in range(3):
            v = np.float64(pos[r, c] * psign[c])
            q = np.rint((v - lo[c]) * k[c])
            q = min(max(q, 0.0), POS_LEVELS)
            out_pos[count * 3 + c] = np.uint16(q)
            held_pos[m, c] = lo[c] + q * step[c]
        packed = pack_rotation(qx, qy, qz, qw)
        out_rot[count] = packed
        _unpack_into(packed, held_rot, m)
        for c in range(3):
            code = _scale_code(scale[r, c], table)
            out_scale[count * 3 + c] = np.uint8(code)
            held = log_lo + code * log_step
            held_slo[m, c] = math.exp(held - log_thr)
            held_shi[m, c] = math.exp(held + log_thr)
        count += 1
    return count


@nb.njit(**_NB)
def _unpack_into(v, out, m):
    """q13 rotation decode (PROTOCOL.md 6.3) of v into out[m] (x, y, z, w), float64."""
    i = v >> 30
    kept = np.empty(3, np.float64)
    d = 1.0
    for j in range(3):
        f = np.int64((v >> (20 - 10 * j)) & 1023)
        if f >= 512:
            f -= 1024
        c = max(f / ROT_LEVELS, -1.0) / math.sqrt(2.0)
        kept[j] = c
        d -= c * c
    big = math.sqrt(max(d, 0.0))
    j = 0
    for c in range(4):
        if c == i:
            out[m, c] = big
        else:
            out[m, c] = kept[j]
            j += 1


_WARM_TABLE = scale_table(np.exp(np.linspace(-9, -2, SCALE_LEVELS)).astype(np.float32))


def delta_kernel_warm() -> None:
    for readonly in (False, True):
        z3, z4, s3 = np.zeros((1, 3), np.float32), np.zeros((1, 4), np.float32), np.full((1, 3), 1e-3, np.float32)
        z4[0, 3] = 1
        for a in (z3, z4, s3):
            a.flags.writeable = not readonly
        _delta_select(z3, z4, s3, np.zeros(1, np.int64), np.ones(3, np.float32), np.ones(4, np.float32),
                      np.zeros(3), np.ones(3), np.ones(3), _WARM_TABLE, -9.0, 0.01,
                      np.zeros((1, 3)), np.zeros((1, 4)), np.zeros((1, 3)), np.ones((1, 3)), 1e-10, 0.99, 0.01, True,
                      np.zeros(1, np.int64), np.zeros(3, np.uint16), np.zeros(1, np.uint32), np.zeros(3, np.uint8))


@dataclass(frozen=True)
class DeltaThresholds:
    """When a Gaussian counts as moved (any one suffices): its position is more than ``position_m``
    (Euclidean, metres) from the position the client holds; its rotation is more than
    ``rotation_deg`` degrees from the held one; or a scale axis differs from the held one by more than
    ``log_scale`` in ln (0.02 = 2 %). The client's error is then at most the threshold, or the q13
    quantisation error for Gaussians just sent, whichever is larger."""

    position_m: float = 4.5e-5
    rotation_deg: float = 0.5
    log_scale: float = 0.02


class DeltaQ13:
    """Per-client sparse q13 frames of the Gaussians that moved since what this client last received.

    candidates: (M,) int64 rows the server may send (the avatar's movable Gaussians); the rest never
    change. The held state starts at ``neutral`` (what the `avatar` message gave the client, in FLAME
    space, quantised like a frame). :meth:`select` must be called once per frame that is handed to this
    client's socket (never for a frame that is then dropped): it updates the held state. PROTOCOL.md
    section 7: a server that sends only what changed diffs against the last frame sent to that client.
    """

    def __init__(self, quant: Quant, candidates: np.ndarray, neutral_position: np.ndarray,
                 neutral_rotation: np.ndarray, neutral_scale: np.ndarray, coords: str = "flame",
                 thresholds: DeltaThresholds | None = None) -> None:
        from ofera_protocol.fast_encodings import coord_signs

        self.quant = quant
        self.th = thresholds or DeltaThresholds()
        self.ids = np.ascontiguousarray(candidates, np.int64)
        self.psign, self.rsign = coord_signs(coords)
        self.lo, self.k = position_factors(quant)
        self.step = (quant.pos_max.astype(np.float64) - self.lo) / POS_LEVELS
        self.scale_table = scale_table(scale_thresholds(quant))
        lmin, lmax = float(quant.log_scale[0]), float(quant.log_scale[1])
        self.log_lo, self.log_step = lmin, (lmax - lmin) / SCALE_LEVELS
        m = self.ids.size
        self.held_pos = np.zeros((m, 3))
        self.held_rot = np.zeros((m, 4))
        self.held_slo = np.zeros((m, 3))  # held scale x exp(-log_scale) .. x exp(+log_scale): not moved
        self.held_shi = np.zeros((m, 3))
        self._sel = np.zeros(m, np.int64)
        self._pos = np.zeros(3 * m, np.uint16)
        self._rot = np.zeros(m, np.uint32)
        self._scale = np.zeros(3 * m, np.uint8)
        # The client starts from the avatar message (float32, exact): hold those values.
        self.held_pos[:] = neutral_position[self.ids] * self.psign
        self.held_rot[:] = neutral_rotation[self.ids] * self.rsign
        held = neutral_scale[self.ids].astype(np.float64)
        self.held_slo[:] = held * math.exp(-self.th.log_scale)
        self.held_shi[:] = held * math.exp(self.th.log_scale)
        self._pos_thr2 = self.th.position_m ** 2
        self._rot_dot = math.cos(math.radians(self.th.rotation_deg) / 2)
        self.frames = 0

    def select(self, position: np.ndarray, rotation: np.ndarray, scale: np.ndarray,
               force: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """FLAME-space float32 state (N, ...) -> (index (n,) uint32 avatar rows, position codes (n, 3)
        uint16, rotation codes (n,) uint32, scale codes (n, 3) uint8) of the Gaussians to send; views of
        internal buffers, valid until the next call. ``force`` sends every candidate."""
        n = _delta_select(position, rotation, scale, self.ids, self.psign, self.rsign, self.lo, self.k, self.step,
                          self.scale_table, self.log_lo, self.log_step, self.held_pos, self.held_rot, self.held_slo,
                          self.held_shi,
                          self._pos_thr2, self._rot_dot, self.th.log_scale, force, self._sel, self._pos, self._rot,
                          self._scale)
        self.frames += 1
        index = self.ids[self._sel[:n]].astype(np.uint32)
        return index, self._pos[:3 * n].reshape(n, 3), self._rot[:n], self._scale[:3 * n].reshape(n, 3)

    def message(self, seq: int, t: int, timing: dict[str, int], position: np.ndarray, rotation: np.ndarray,
                scale: np.ndarray, force: bool = False) -> bytes:
        """The sparse q13 `frame` message of :meth:`select` (the session must be sparse, q13)."""
        from ofera_protocol.codec import pack_map

        index, p, r, s = self.select(position, rotation, scale, force)
        return pack_map({"type": "frame", "seq": seq, "t": t, "timing": timing, "n": int(index.size),
                         "index": index, "position": p.astype("<u2"), "rotation": r.astype("<u4"),
                         "scale": s})


# ============================================================================= decoding (clients, benchmarks)


@intrinsic
def f16_bits_to_f32(typingctx, h):
    """uint16 bits of an IEEE binary16 -> float32 (exact)."""
    if not isinstance(h, types.Integer) or h.bitwidth != 16:
        return None

    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())

    return types.float32(h), codegen


@nb.njit(**_NB)
def f16_decode_kernel(src, dst):
    """half bits (n,) -> float32 (n,); False if any is NaN or infinite (exponent all ones)."""
    ok = True
    for i in range(src.shape[0]):
        h = src[i]
        ok &= (h & 0x7C00) != 0x7C00
        dst[i] = f16_bits_to_f32(h)
    return ok


@nb.njit(**_NB)
def q13_decode_kernel(pos, rot, scale, lo, step, scale_lut, out_pos, out_rot, out_scale):
    """q13 codes -> float32 (PROTOCOL.md 6.3, the reference decoder's arithmetic)."""
    kf = np.float32(math.sqrt(0.5) / ROT_LEVELS)
    for m in range(rot.shape[0]):
        for c in range(3):
            out_pos[m, c] = np.float32(lo[c] + np.float64(pos[3 * m + c]) * step[c])
            out_scale[m, c] = scale_lut[scale[3 * m + c]]
        v = rot[m]
        i = v >> 30
        a0 = _q13_field(v, 20) * kf
        a1 = _q13_field(v, 10) * kf
        a2 = _q13_field(v, 0) * kf
        d = a0 * a0
        d = d + a1 * a1
        d = d + a2 * a2
        big = np.sqrt(max(np.float32(1.0) - d, np.float32(0.0)))
        out_rot[m, 0] = big if i == 0 else a0
        out_rot[m, 1] = big if i == 1 else (a0 if i == 0 else a1)
        out_rot[m, 2] = big if i == 2 else (a2 if i == 3 else a1)
        out_rot[m, 3] = big if i == 3 else a2


@nb.njit(inline="always", **_NB)
def _q13_field(v, shift):
    f = np.int32((v >> np.uint32(shift)) & 1023)
    f = (f ^ 512) - 512
    return np.float32(max(f, -ROT_LEVELS))


def decoder_warm() -> None:
    """Compile the decoding kernels for message buffers (read-only uint views)."""
    raw = bytes(64)
    f16_decode_kernel(np.frombuffer(raw, "<u2", 6), np.zeros(6, np.float32))
    out3, out4 = np.zeros((2, 3), np.float32), np.zeros((2, 4), np.float32)
    q13_decode_kernel(np.frombuffer(raw, "<u2", 6), np.frombuffer(raw, "<u4", 2), np.frombuffer(raw, np.uint8, 6),
                      np.zeros(3), np.ones(3), np.ones(256, np.float32), out3, out4, out3.copy())


class FastFrameDecoder:
    """Decodes the frames of one session (FrameFormat) into float32 buffers owned by the decoder (reused:
    each call overwrites the previous frame's arrays), with the codec's checks (lengths, finiteness, index).
    A benchmark / test client's fast path: ofera_protocol.decode_server_message is the reference."""

    def __init__(self, fmt: FrameFormat) -> None:
        numba_kernels()  # compiled (or loaded from the cache) before the first frame
        self.format = fmt
        n = fmt.count
        self._pos = np.zeros((n, 3), np.float32)
        self._rot = np.zeros((n, 4), np.float32)
        self._scale = np.zeros((n, 3), np.float32)
        if fmt.encoding == "q13":
            assert fmt.quant is not None
            q = fmt.quant
            self._lo = q.pos_min.astype(np.float64)
            self._step = (q.pos_max.astype(np.float64) - self._lo) / POS_LEVELS
            lmin, lmax = float(q.log_scale[0]), float(q.log_scale[1])
            codes = np.arange(256, dtype=np.float64)
            self._lut = np.exp(lmin + codes * ((lmax - lmin) / SCALE_LEVELS)).astype(np.float32)

    def decode(self, data) -> object:
        """A `frame` message -> ofera_protocol.Frame whose arrays are views of this decoder's buffers;
        other messages are decoded by the reference codec. Raises ProtocolError like the codec."""
        from ofera_protocol import _fields as F
        from ofera_protocol.codec import decode_server_message, decode_timing, unpack_message
        from ofera_protocol.constants import MAX_SERVER_MESSAGE, UINT32_MAX
        from ofera_protocol.encodings import FIELD_BYTES
        from ofera_protocol.errors import BAD_FIELD, BAD_LENGTH, NON_FINITE, ProtocolError
        from ofera_protocol.messages import Frame

        m = unpack_message(data, MAX_SERVER_MESSAGE)
        if m.get("type") != "frame":
            return decode_server_message(data, self.format)
        fmt = self.format
        seq = F.get_int(m, "seq", "frame", lo=0)
        t = F.get_int(m, "t", "frame")
        timing = decode_timing(m)
        n = F.get_int(m, "n", "frame", lo=0, hi=UINT32_MAX)
        index = F.get_array(m, "index", "frame", "<u4", (n,), required=False)
        if index is None and n != fmt.count:
            raise ProtocolError(BAD_LENGTH, f"frame: dense frame carries n={n} Gaussians, the avatar has {fmt.count}")
        if index is not None:
            if not fmt.sparse:
                raise ProtocolError(BAD_FIELD, "frame: 'index' in a session that did not ask for sparse frames")
            if n and (int(index[-1]) >= fmt.count or (n > 1 and not (index[1:] > index[:-1]).all())):
                raise ProtocolError(BAD_FIELD, "frame: 'index' must be strictly ascending and below the count")
        bufs = [F.get_bin(m, k, "frame") for k in ("position", "rotation", "scale")]
        for name, buf, size in zip(("position", "rotation", "scale"), bufs, FIELD_BYTES[fmt.encoding]):
            if len(buf) != n * size:
                raise ProtocolError(BAD_LENGTH, f"frame field {name!r} has {len(buf)} bytes; {n} Gaussians in "
                                    f"{fmt.encoding} need {n * size}")
        p, r, s = self._pos[:n], self._rot[:n], self._scale[:n]
        if fmt.encoding == "q13":
            q13_decode_kernel(np.frombuffer(bufs[0], "<u2"), np.frombuffer(bufs[1], "<u4"),
                              np.frombuffer(bufs[2], np.uint8), self._lo, self._step, self._lut, p, r, s)
        else:
            for name, buf, out in zip(("position", "rotation", "scale"), bufs, (p, r, s)):
                if fmt.encoding == "f16":
                    ok = f16_decode_kernel(np.frombuffer(buf, "<u2"), out.reshape(-1))
                else:
                    a = np.frombuffer(buf, "<f4")
                    ok = bool(np.isfinite(a.min()) and np.isfinite(a.max())) if a.size else True
                if not ok:
                    raise ProtocolError(NON_FINITE, f"frame field {name!r} holds NaN or infinity")
            if fmt.encoding == "f32":  # read-only views of the message, like the codec
                p, r, s = (np.frombuffer(b, "<f4").reshape(n, w) for b, w in zip(bufs, (3, 4, 3)))
        return Frame(seq=seq, t=t, timing=timing, index=index, position=p, rotation=r, scale=s)
