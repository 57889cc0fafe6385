"""numba frame-encoding kernels (the accelerator the server passes to the protocol's FrameWriter and
DeltaEncoder): the fast kernel set, same signatures and same bytes as the reference (plain numpy,
``ofera_protocol.fast_encodings.NumpyKernels`` over ``ofera_protocol.encodings`` / ``.delta``).

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

Temporal deltas (PROTOCOL.md 7.1): :func:`delta_q13_kernel` / :func:`delta_f16_kernel` do the selection of
``ofera_protocol.delta`` (same float32 operations in the same order, so the same Gaussians are selected) in SIMD
lanes over each run of consecutive movable rows (:func:`flag_run`), compact what moved into per-attribute
lists without a branch, then encode each attribute in a pass of its own and update the codes the client holds.
The client-side decoder is in ``ofera.client.fast_decode``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from ofera_protocol.delta import DELTA_KEYS, DeltaEncoder, DeltaTolerance, ReferenceKernels
from ofera_protocol.encodings import POS_LEVELS, ROT_LEVELS, SCALE_LEVELS, FrameFormat
from ofera_protocol.fast_encodings import (
    F16_MAX,
    F32_MAX,
    FrameWriter,
    NumpyKernels,
)

from ..jit import NB as _NB
from ..jit import f16_bits_to_f32, f32_to_f16_bits

_SQRT2_511 = np.float32(np.sqrt(2.0) * ROT_LEVELS)  # the reference's float32 constant


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
def f16_kernel_reference(src, gather, count, sign, dst):
    """dst[m k + c] = half bits of src[row m, c] * sign[c]; False if any value is NaN, infinite or
    beyond +-65504. The plain loop :func:`f16_kernel` is tested against (any k)."""
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
def _f16_rows3(src, gather, count, s0, s1, s2, dst):
    """k = 3 of :func:`f16_kernel`: the components unrolled and the gather test hoisted (the loop vectorises)."""
    ok = True
    if gather.shape[0] == 0:
        for m in range(count):
            v0, v1, v2 = src[m, 0] * s0, src[m, 1] * s1, src[m, 2] * s2
            ok &= (abs(v0) <= F16_MAX) & (abs(v1) <= F16_MAX) & (abs(v2) <= F16_MAX)
            dst[3 * m] = f32_to_f16_bits(v0)
            dst[3 * m + 1] = f32_to_f16_bits(v1)
            dst[3 * m + 2] = f32_to_f16_bits(v2)
    else:
        for m in range(count):
            r = gather[m]
            v0, v1, v2 = src[r, 0] * s0, src[r, 1] * s1, src[r, 2] * s2
            ok &= (abs(v0) <= F16_MAX) & (abs(v1) <= F16_MAX) & (abs(v2) <= F16_MAX)
            dst[3 * m] = f32_to_f16_bits(v0)
            dst[3 * m + 1] = f32_to_f16_bits(v1)
            dst[3 * m + 2] = f32_to_f16_bits(v2)
    return ok


@nb.njit(**_NB)
def _f16_rows4(src, gather, count, s0, s1, s2, s3, dst):
    """k = 4 of :func:`f16_kernel` (see :func:`_f16_rows3`)."""
    ok = True
    if gather.shape[0] == 0:
        for m in range(count):
            v0, v1, v2, v3 = src[m, 0] * s0, src[m, 1] * s1, src[m, 2] * s2, src[m, 3] * s3
            ok &= (abs(v0) <= F16_MAX) & (abs(v1) <= F16_MAX) & (abs(v2) <= F16_MAX) & (abs(v3) <= F16_MAX)
            dst[4 * m] = f32_to_f16_bits(v0)
            dst[4 * m + 1] = f32_to_f16_bits(v1)
            dst[4 * m + 2] = f32_to_f16_bits(v2)
            dst[4 * m + 3] = f32_to_f16_bits(v3)
    else:
        for m in range(count):
            r = gather[m]
            v0, v1, v2, v3 = src[r, 0] * s0, src[r, 1] * s1, src[r, 2] * s2, src[r, 3] * s3
            ok &= (abs(v0) <= F16_MAX) & (abs(v1) <= F16_MAX) & (abs(v2) <= F16_MAX) & (abs(v3) <= F16_MAX)
            dst[4 * m] = f32_to_f16_bits(v0)
            dst[4 * m + 1] = f32_to_f16_bits(v1)
            dst[4 * m + 2] = f32_to_f16_bits(v2)
            dst[4 * m + 3] = f32_to_f16_bits(v3)
    return ok


@nb.njit(**_NB)
def f16_kernel(src, gather, count, sign, dst):
    """dst[m k + c] = half bits of src[row m, c] * sign[c]; False if any value is NaN, infinite or
    beyond +-65504. Positions and rotations (k = 3, 4) take unrolled loops; same bits as
    :func:`f16_kernel_reference`."""
    k = src.shape[1]
    if k == 3:
        return _f16_rows3(src, gather, count, sign[0], sign[1], sign[2], dst)
    if k == 4:
        return _f16_rows4(src, gather, count, sign[0], sign[1], sign[2], sign[3], dst)
    return f16_kernel_reference(src, gather, count, sign, dst)


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
def f16_rows_kernel(src, start, length, sign, dst):
    """Rows start[q] .. start[q] + length[q] - 1 of src (N, k) times sign -> their places in dst (N k,) as half
    bits (the other rows of dst untouched); False if any is NaN, infinite or beyond +-65504. Spans of a flat
    row-major src with no mirroring take one vectorised loop each; else the row kernels of :func:`f16_kernel`."""
    k = src.shape[1]
    flat = src.reshape(-1)
    plain = True
    for c in range(k):
        plain &= sign[c] == 1.0
    ok = True
    for q in range(start.shape[0]):
        a = start[q]
        b = a + length[q]
        if plain:
            for i in range(np.uint64(a * k), np.uint64(b * k)):  # unsigned: no wrap-around test (vectorises)
                v = flat[i]
                ok &= abs(v) <= F16_MAX
                dst[i] = f32_to_f16_bits(v)
        elif k == 3:
            ok &= _f16_rows3(src[a:b], _NO_GATHER, b - a, sign[0], sign[1], sign[2], dst[a * 3:b * 3])
        elif k == 4:
            ok &= _f16_rows4(src[a:b], _NO_GATHER, b - a, sign[0], sign[1], sign[2], sign[3], dst[a * 4:b * 4])
        else:
            ok &= f16_kernel_reference(src[a:b], _NO_GATHER, b - a, sign, dst[a * k:b * k])
    return ok


@nb.njit(**_NB)
def f32_rows_kernel(src, start, length, sign, dst):
    """:func:`f16_rows_kernel` for f32 (the values themselves); False if any is NaN or infinite."""
    k = src.shape[1]
    ok = True
    for q in range(start.shape[0]):
        a = start[q]
        b = a + length[q]
        for r in range(a, b):
            for c in range(k):
                v = src[r, c] * sign[c]
                ok &= abs(v) <= F32_MAX
                dst[r * k + c] = v
    return ok


@nb.njit(**_NB)
def q13_position_kernel_reference(src, gather, count, sign, lo, k, dst):
    """uint16 q = clip(rint((float64(p) - lo) * k), 0, 65535) per axis (the reference's float64 steps): the
    plain loop :func:`q13_position_kernel` is tested against."""
    for m in range(count):
        r = _row(gather, m)
        for c in range(3):
            q = (np.float64(src[r, c] * sign[c]) - lo[c]) * k[c]
            if abs(q) < 2.0**50:
                q = _rint(q)
            q = min(max(q, 0.0), POS_LEVELS)  # NaN -> 0
            dst[m * 3 + c] = np.uint16(q)


@nb.njit(inline="always", **_NB)
def _pos_code(v, lo, k):
    """clip(rint((float64(v) - lo) * k), 0, 65535), branch-free: clamping first (NaN -> 0) gives the same
    integer (rint is monotonic and 0, 65535 are integers), and on [0, 65535] the magic-number rint is exact."""
    q = (np.float64(v) - lo) * k
    q = q if q > 0.0 else 0.0
    q = q if q < POS_LEVELS else np.float64(POS_LEVELS)
    return np.uint16(_rint(q))


@nb.njit(**_NB)
def q13_position_kernel(src, gather, count, sign, lo, k, dst):
    """:func:`q13_position_kernel_reference` with the axes unrolled, the gather test hoisted and no branch in
    the loop (it vectorises); the same codes. src: C-contiguous."""
    s0, s1, s2 = sign[0], sign[1], sign[2]
    l0, l1, l2 = lo[0], lo[1], lo[2]
    k0, k1, k2 = k[0], k[1], k[2]
    if gather.shape[0] == 0:
        flat = src.reshape(-1)  # src C-contiguous (NumbaKernels); flat indices: see q13_rotation_kernel
        for m in range(np.uint64(count)):
            dst[3 * m] = _pos_code(flat[3 * m] * s0, l0, k0)
            dst[3 * m + 1] = _pos_code(flat[3 * m + 1] * s1, l1, k1)
            dst[3 * m + 2] = _pos_code(flat[3 * m + 2] * s2, l2, k2)
    else:
        for m in range(count):
            r = gather[m]
            dst[3 * m] = _pos_code(src[r, 0] * s0, l0, k0)
            dst[3 * m + 1] = _pos_code(src[r, 1] * s1, l1, k1)
            dst[3 * m + 2] = _pos_code(src[r, 2] * s2, l2, k2)


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
    """One (x, y, z, w) float32 quaternion -> q13 "smallest three" uint32 (reference arithmetic).

    Selects only, no branch and no switch (a zero, NaN or infinite norm becomes the identity by selection; the
    largest component is picked by comparisons, not by its index): LLVM then runs a loop of it in SIMD lanes,
    4.4 against 16.6 ns a quaternion over the capture's rotations (measured in process)."""
    n2 = x * x
    n2 = n2 + y * y
    n2 = n2 + z * z
    n2 = n2 + w * w
    good = (n2 > 0) & (n2 <= np.float32(F32_MAX))  # finite and positive
    zero = np.float32(0.0)
    x = x if good else zero
    y = y if good else zero
    z = z if good else zero
    w = w if good else np.float32(1.0)
    n2 = n2 if good else np.float32(1.0)
    a0 = abs(x)
    a1 = abs(y)
    a2 = abs(z)
    a3 = abs(w)
    upper = max(a2, a3) > max(a0, a1)
    hi = a3 > a2
    lo = a1 > a0
    i = np.uint32(2 * upper) + np.uint32((upper & hi) | ((not upper) & lo))
    big = (w if hi else z) if upper else (y if lo else x)
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
    """dst[m] = :func:`pack_rotation` of row m (the gather test hoisted out of the loop). src: C-contiguous."""
    s0, s1, s2, s3 = sign[0], sign[1], sign[2], sign[3]
    if gather.shape[0] == 0:
        # src C-contiguous (NumbaKernels), read by flat indices: with src[m, c], LLVM versions the loop on a unit row
        # stride and always takes its scalar copy (2.2 against 0.46 ms for 100k rotations, measured)
        flat = src.reshape(-1)
        for m in range(np.uint64(count)):
            dst[m] = pack_rotation(flat[4 * m] * s0, flat[4 * m + 1] * s1, flat[4 * m + 2] * s2, flat[4 * m + 3] * s3)
    else:
        for m in range(count):
            r = gather[m]
            dst[m] = pack_rotation(src[r, 0] * s0, src[r, 1] * s1, src[r, 2] * s2, src[r, 3] * s3)


SCALE_BUCKET_SHIFT = 12
"""Scale codes are looked up by the float32 bit pattern >> 12: a bucket spans a relative width of 2^-11
(0.05 %), below the spacing of two codes (>= 0.39 %: the log range is >= 1 wide), so it holds at most
one threshold and one comparison finishes the lookup."""


def scale_table(thresholds: np.ndarray) -> np.ndarray:
    """Lookup table of :func:`scale_code` from the 255 thresholds: int32 (B + 1, 2) rows
    [count of thresholds below the bucket, bits of the bucket's threshold or +inf]; row 0 holds the
    first and last bucket numbers. int32, not int64: half the cache lines for the delta encoder's scattered
    lookups (every value fits: counts <= 255, bits <= 0x7F800001)."""
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
    table = np.empty((buckets.size + 1, 2), np.int32)
    table[0] = b0, b1
    table[1:, 0] = below
    table[1:, 1] = nxt
    return table


@nb.njit(inline="always", **_NB)
def scale_code(v, table):
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
    row = bucket - np.int64(table[0, 0]) + 1
    return np.int64(table[row, 0]) + (1 if b >= table[row, 1] else 0)


@nb.njit(**_NB)
def q13_scale_kernel(src, gather, count, table, dst):
    for m in range(count):
        r = _row(gather, m)
        for c in range(3):
            dst[m * 3 + c] = np.uint8(scale_code(src[r, c], table))


_NO_GATHER = np.zeros(0, np.int64)
NO_TABLE = np.zeros((1, 2), np.int32)  # encode_scales' q13 arguments in f16 mode (unused)
NO_LUT = np.zeros(1, np.float64)


def rotations_u64(codes: np.ndarray) -> np.ndarray:
    """f16 rotation codes (n, 4) uint16, C-contiguous, viewed as (n,) uint64 (component c in bits 16 c, little-endian):
    how :func:`encode_rotations_f16` holds and writes them."""
    return codes.view(np.uint64).reshape(-1)


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

    def f32_rows(self, src, rows, sign, dst) -> bool:
        return bool(f32_rows_kernel(src, rows.start, rows.length, sign, dst))

    def f16_rows(self, src, rows, sign, dst) -> bool:
        if not src.flags.c_contiguous:
            src = np.ascontiguousarray(src)
        return bool(f16_rows_kernel(src, rows.start, rows.length, sign, dst))

    def q13_position(self, src, gather, sign, lo, k, dst) -> None:
        g, n = self._g(src, gather)
        q13_position_kernel(np.ascontiguousarray(src), g, n, sign, lo, k, dst)  # states are; a view is copied

    def q13_rotation(self, src, gather, sign, dst) -> None:
        g, n = self._g(src, gather)
        q13_rotation_kernel(np.ascontiguousarray(src), g, n, sign, dst)

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

    def delta_q13(self, pos, rot, scale, rows, runs, ids, psign, rsign, lo, k, step, thresholds, scale_lut, rot_lut,
                  tol, held_p, held_r, held_s, dec, flags, work, *out) -> tuple[int, ...]:
        """ofera_protocol.delta.delta_q13_reference by :func:`delta_q13_kernel` (same signature, same bytes).
        work: (7, K) int32, rows 0-2 the lists of what moved, rows 3-6 the kernel's float32 scratch."""
        args = (pos, rot, scale, rows, runs, ids, psign, rsign, lo, k, step)
        state = (held_p, held_r, held_s, dec, flags, work)
        table = self.table(thresholds)
        if table is None:
            return ReferenceKernels().delta_q13(*args, thresholds, scale_lut, rot_lut, tol, *state, *out)
        gathered = work[3:].view(np.float32).reshape(-1)
        return tuple(int(x) for x in delta_q13_kernel(*args, table, scale_lut, rot_lut, tol, *state, *out, gathered))

    def delta_body(self, buf, at, *args) -> int:
        """ofera_protocol.delta.delta_body_reference by :func:`delta_body_kernel` (same bytes)."""
        return delta_body_kernel(buf, at, DELTA_KEYS, *args)

    def delta_f16(self, pos, rot, scale, rows, runs, ids, psign, rsign, tol, held_p, held_r, held_s, dec, flags,
                  work, out_moved, out_wide, out_res, out_pos, out_rot, out_scale) -> tuple[int, ...]:
        """ofera_protocol.delta.delta_f16_reference in one numba pass (same signature, same bytes); the rotations'
        codes held and written as one uint64 each (:func:`rotations_u64`)."""
        *out, ok = delta_f16_kernel(pos, rot, scale, rows, runs, ids, psign, rsign, tol, held_p, rotations_u64(held_r),
                                    held_s, dec, flags, work, out_moved, out_wide, out_res, out_pos,
                                    rotations_u64(out_rot), out_scale)
        if not ok:
            raise ValueError("a moved Gaussian has NaN, infinity or values beyond +-65504 (f16)")
        return tuple(int(x) for x in out)


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


def frame_writer(fmt: FrameFormat, coords: str = "flame", gather: np.ndarray | None = None,
                 index: np.ndarray | None = None, pool: int = 4, stamp_encode: bool = False) -> FrameWriter:
    """A FrameWriter using the numba kernels; ``stamp_encode``: each frame's timing carries its own "encode" (us)."""
    return FrameWriter(fmt, coords, gather, index, kernels=numba_kernels(), pool=pool, stamp_encode=stamp_encode)


# ============================================================================= temporal deltas (PROTOCOL.md 7.1)



@nb.njit(**_NB)
def flag_run(p, q, s, hp0, hp1, hp2, hr0, hr1, hr2, hr3, hs0, hs1, hs2, flags, ps, rs, tol):
    """One run of consecutive state rows: flags[m] = position | rotation << 1 | scale << 2 moved, for the run's state
    p, q, s (flat float32, 3 / 4 / 3 per row) against the held decodings h* (float32, one array per component), by
    the rule of ofera_protocol.delta (same float32 operations in the same order). Branch-free over separate
    arrays: LLVM runs it in SIMD lanes (8 Gaussians per AVX2 instruction)."""
    s0, s1, s2 = ps[0], ps[1], ps[2]
    r0, r1, r2, r3 = rs[0], rs[1], rs[2], rs[3]
    t0, t1, t2, t3 = tol[0], tol[1], tol[2], tol[3]
    for m in range(np.uint64(flags.shape[0])):
        d0 = p[3 * m] * s0 - hp0[m]
        d1 = p[3 * m + 1] * s1 - hp1[m]
        d2 = p[3 * m + 2] * s2 - hp2[m]
        mp = d0 * d0 + d1 * d1 + d2 * d2 > t0
        q0, q1, q2, q3 = q[4 * m] * r0, q[4 * m + 1] * r1, q[4 * m + 2] * r2, q[4 * m + 3] * r3
        h0, h1, h2, h3 = hr0[m], hr1[m], hr2[m], hr3[m]
        m01, m02, m03 = q0 * h1 - q1 * h0, q0 * h2 - q2 * h0, q0 * h3 - q3 * h0
        m12, m13, m23 = q1 * h2 - q2 * h1, q1 * h3 - q3 * h1, q2 * h3 - q3 * h2
        cross = m01 * m01 + m02 * m02 + m03 * m03 + m12 * m12 + m13 * m13 + m23 * m23
        n2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
        hh = h0 * h0 + h1 * h1 + h2 * h2 + h3 * h3
        mr = cross > t1 * n2 * hh
        v0, v1, v2 = s[3 * m], s[3 * m + 1], s[3 * m + 2]
        ms = ((v0 > hs0[m] * t2) | (v0 < hs0[m] * t3) | (v1 > hs1[m] * t2) | (v1 < hs1[m] * t3)
              | (v2 > hs2[m] * t2) | (v2 < hs2[m] * t3))
        flags[m] = np.uint8(mp) | (np.uint8(mr) << 1) | (np.uint8(ms) << 2)


@nb.njit(**_NB)
def _select(pos, rot, scale, runs, psign, rsign, tol, dec, flags, lists, out_moved):
    """What moved: the flags of every candidate (:func:`flag_run` per run of rows), then, branch-free, the
    selection's flags (out_moved[:n]) and the lists (candidate positions) of the moved positions, rotations and
    scales (lists[0, :n_p], [1, :n_r], [2, :n_s]). Returns (n, n_p, n_r, n_s)."""
    pf, rf, sf = pos.reshape(-1), rot.reshape(-1), scale.reshape(-1)
    for x in range(runs.shape[0]):
        a, j, e = runs[x, 0], runs[x, 1], runs[x, 1] + runs[x, 2]
        b = a + runs[x, 2]
        flag_run(pf[3 * a:3 * b], rf[4 * a:4 * b], sf[3 * a:3 * b], dec[0, j:e], dec[1, j:e], dec[2, j:e],
                  dec[3, j:e], dec[4, j:e], dec[5, j:e], dec[6, j:e], dec[7, j:e], dec[8, j:e], dec[9, j:e],
                  flags[j:e], psign, rsign, tol)
    word = flags[: (flags.shape[0] >> 3) << 3].view(np.uint64)
    return compact_range(flags, word, 0, flags.shape[0], (0, 0, 0, 0), lists, out_moved)


@nb.njit(inline="always", **_NB)
def compact_range(flags, word, lo, hi, counts, lists, out_moved):
    """:func:`compact_flags` of flags lo..hi-1, a word of 8 flags at a time where whole words of ``word`` (the flags
    viewed as uint64) lie inside: a word of zeros (nothing moved) is skipped whole."""
    wa, wb = (lo + 7) >> 3, hi >> 3
    if wa >= wb:
        return compact_flags(flags, lo, hi, counts, lists, out_moved)
    counts = compact_flags(flags, lo, wa << 3, counts, lists, out_moved)
    for b in range(np.uint64(wa), np.uint64(wb)):
        if word[b] != 0:
            counts = compact_flags(flags, 8 * b, 8 * b + 8, counts, lists, out_moved)
    return compact_flags(flags, wb << 3, hi, counts, lists, out_moved)


@nb.njit(inline="always", **_NB)
def compact_flags(flags, lo, hi, counts, lists, out_moved):
    """Flags lo..hi-1 into the selection and the lists, branch-free: each write lands on the next free slot; the
    count moves only if it belongs. counts: (n, n_p, n_r, n_s) so far -> after (int64; unsigned inside: a signed
    slot is checked for wrap-around at every store, 6-40 % of the pass, measured 5 December 2026)."""
    one, two = np.uint64(1), np.uint64(2)
    n, n_p, n_r, n_s = np.uint64(counts[0]), np.uint64(counts[1]), np.uint64(counts[2]), np.uint64(counts[3])
    for j in range(np.uint64(lo), np.uint64(hi)):
        f = np.uint64(flags[j])
        out_moved[n] = np.uint8(f)
        n += np.uint64(f != 0)
        lists[0, n_p] = j
        n_p += f & one
        lists[1, n_r] = j
        n_r += (f >> one) & one
        lists[2, n_s] = j
        n_s += f >> two
    return np.int64(n), np.int64(n_p), np.int64(n_r), np.int64(n_s)


@nb.njit(**_NB)
def encode_positions(q13, pos, rows, ids, moved, n_p, psign, lo, k, step, held_p, dec, out_wide, out_res, out_pos,
                     decode):
    """The moved positions (candidates moved[:n_p]): their codes (q13, else f16 bits), split into int8 changes from
    the held codes (out_res) and whole codes (out_wide set, out_pos); held codes updated, and their decodings if
    ``decode`` (False: :func:`decode_moved` writes them later). Returns (w, the number sent whole; ok: False if an
    f16 value is NaN, infinite or beyond +-65504). The per-axis constants are loaded once (array elements would be
    reloaded after every store, which might alias them) and the output slots are unsigned (no wrap-around check per
    store)."""
    s0, s1, s2 = psign[0], psign[1], psign[2]
    l0, l1, l2 = lo[0], lo[1], lo[2]
    k0, k1, k2 = k[0], k[1], k[2]
    t0, t1, t2 = step[0], step[1], step[2]
    w = m = np.uint64(0)
    one = np.uint64(1)
    ok = True
    for x in range(np.uint64(n_p)):
        j = np.uint64(moved[x])  # unsigned indices: no wrap-around code (see ofera.avatar.kernels)
        r, i = np.uint64(rows[j]), np.uint64(ids[j])
        v0, v1, v2 = pos[r, 0] * s0, pos[r, 1] * s1, pos[r, 2] * s2
        if q13:
            c0, c1, c2 = _pos_code(v0, l0, k0), _pos_code(v1, l1, k1), _pos_code(v2, l2, k2)
        else:
            ok &= abs(v0) <= F16_MAX and abs(v1) <= F16_MAX and abs(v2) <= F16_MAX
            c0, c1, c2 = f32_to_f16_bits(v0), f32_to_f16_bits(v1), f32_to_f16_bits(v2)
        if decode:
            _decode_position(q13, c0, c1, c2, j, l0, l1, l2, t0, t1, t2, dec)
        d0 = np.int32(c0) - np.int32(held_p[i, 0])
        d1 = np.int32(c1) - np.int32(held_p[i, 1])
        d2 = np.int32(c2) - np.int32(held_p[i, 2])
        wide = d0 < -128 or d0 > 127 or d1 < -128 or d1 > 127 or d2 < -128 or d2 > 127
        out_wide[x] = wide
        if wide:
            out_pos[w, 0], out_pos[w, 1], out_pos[w, 2] = c0, c1, c2
            w += one
        else:
            out_res[m, 0], out_res[m, 1], out_res[m, 2] = np.int8(d0), np.int8(d1), np.int8(d2)
            m += one
        held_p[i, 0], held_p[i, 1], held_p[i, 2] = c0, c1, c2
    return np.int64(w), ok


@nb.njit(**_NB)
def encode_rotations_q13(rot, rows, ids, moved, n_r, rsign, rot_lut, held_r, dec, gathered, out_rot, decode):
    """The moved rotations (candidates moved[:n_r]): their q13 codes (out_rot), held codes updated, and their
    decodings if ``decode`` (as :func:`encode_positions`). Three loops: the rows gathered into `gathered` ((4 n_r)
    float32, signs applied), :func:`pack_rotation` over them in SIMD lanes, then the scatter. Packing the rows where
    they lie ran scalar, 2x slower in all."""
    s0, s1, s2, s3 = rsign[0], rsign[1], rsign[2], rsign[3]
    for x in range(np.uint64(n_r)):
        r = np.uint64(rows[np.uint64(moved[x])])
        gathered[4 * x] = rot[r, 0] * s0
        gathered[4 * x + 1] = rot[r, 1] * s1
        gathered[4 * x + 2] = rot[r, 2] * s2
        gathered[4 * x + 3] = rot[r, 3] * s3
    for x in range(np.uint64(n_r)):
        out_rot[x] = pack_rotation(gathered[4 * x], gathered[4 * x + 1], gathered[4 * x + 2], gathered[4 * x + 3])
    for x in range(np.uint64(n_r)):
        j = np.uint64(moved[x])
        v = out_rot[x]
        held_r[np.uint64(ids[j])] = v
        if decode:
            _decode_rotation_q13(v, j, rot_lut, dec)


@nb.njit(inline="always", **_NB)
def _decode_rotation_q13(v, j, rot_lut, dec):
    """dec[3:7, j] = the float64 decoding of q13 rotation code v (ofera_protocol.delta.q13_decode_rotation64), as
    float32."""
    one, two, three, four, five = np.uint64(1), np.uint64(2), np.uint64(3), np.uint64(4), np.uint64(5)
    a0 = rot_lut[(v >> 20) & 1023]
    a1 = rot_lut[(v >> 10) & 1023]
    a2 = rot_lut[v & 1023]
    d = 1.0 - a0 * a0
    d = d - a1 * a1
    d = d - a2 * a2
    big = math.sqrt(max(d, 0.0))
    drop = np.uint64(v >> 30)  # rows by computed slot (the three small ones around the largest, in order):
    dec[three + np.uint64(drop < one), j] = np.float32(a0)  # selects on the index compile to branches here,
    dec[four + np.uint64(drop <= one), j] = np.float32(a1)  # which mispredict (client.fast_decode, the same)
    dec[five + np.uint64(drop <= two), j] = np.float32(a2)
    dec[three + drop, j] = np.float32(big)


@nb.njit(inline="always", **_NB)
def _decode_position(q13, c0, c1, c2, j, l0, l1, l2, t0, t1, t2, dec):
    """dec[0:3, j] = the decoding of position codes c0..c2: q13 (lo + code * step, in float64, as float32), else
    f16 bits."""
    if q13:
        dec[0, j] = np.float32(l0 + np.float64(c0) * t0)
        dec[1, j] = np.float32(l1 + np.float64(c1) * t1)
        dec[2, j] = np.float32(l2 + np.float64(c2) * t2)
    else:
        dec[0, j], dec[1, j], dec[2, j] = f16_bits_to_f32(c0), f16_bits_to_f32(c1), f16_bits_to_f32(c2)


@nb.njit(**_NB)
def decode_moved(q13, moved, counts, ids, held_p, held_r, held_s, lo, step, scale_lut, rot_lut, dec):
    """The decodings the encoding passes left out (``decode=False``): dec[:, j] from the held codes of the candidates
    j in moved[0, :n_p] (positions), moved[1, :n_r] (rotations) and moved[2, :n_s] (scales), counts = (n_p, n_r,
    n_s); q13, else f16 bits (held_r: each rotation's four as one uint64, :func:`rotations_u64`). The same values
    the passes would have written."""
    l0, l1, l2 = lo[0], lo[1], lo[2]
    t0, t1, t2 = step[0], step[1], step[2]
    for x in range(np.uint64(counts[0])):
        j = np.uint64(moved[0, x])
        i = np.uint64(ids[j])
        _decode_position(q13, held_p[i, 0], held_p[i, 1], held_p[i, 2], j, l0, l1, l2, t0, t1, t2, dec)
    for x in range(np.uint64(counts[1])):
        j = np.uint64(moved[1, x])
        v = held_r[np.uint64(ids[j])]
        if q13:
            _decode_rotation_q13(v, j, rot_lut, dec)
        else:
            for c in range(4):
                dec[3 + c, j] = f16_bits_to_f32(np.uint16((v >> np.uint64(16 * c)) & np.uint64(0xFFFF)))
    for x in range(np.uint64(counts[2])):
        j = np.uint64(moved[2, x])
        i = np.uint64(ids[j])
        for c in range(np.uint64(3)):
            if q13:
                dec[7 + c, j] = np.float32(scale_lut[held_s[i, c]])
            else:
                dec[7 + c, j] = f16_bits_to_f32(np.uint16(held_s[i, c]))


@nb.njit(**_NB)
def delta_q13_kernel(pos, rot, scale, rows, runs, ids, psign, rsign, lo, k, step, table, scale_lut, rot_lut, tol,
                     held_p, held_r, held_s, dec, flags, work, out_moved, out_wide, out_res, out_pos,
                     out_rot, out_scale, gathered):
    """ofera_protocol.delta.delta_q13_reference: :func:`_select`, then one pass per attribute over what moved
    (gathered: (4 K) float32 scratch). Returns (n, n_p, w, n_r, n_s)."""
    n, n_p, n_r, n_s = _select(pos, rot, scale, runs, psign, rsign, tol, dec, flags, work, out_moved)
    w, _ = encode_positions(True, pos, rows, ids, work[0], n_p, psign, lo, k, step, held_p, dec, out_wide, out_res,
                            out_pos, True)
    encode_rotations_q13(rot, rows, ids, work[1], n_r, rsign, rot_lut, held_r, dec, gathered, out_rot, True)
    encode_scales(True, scale, rows, ids, work[2], n_s, table, scale_lut, held_s, dec, out_scale, True)
    return n, n_p, w, n_r, n_s


@nb.njit(**_NB)
def encode_scales(q13, scale, rows, ids, moved, n_s, table, scale_lut, held_s, dec, out_scale, decode):
    """The moved scales (candidates moved[:n_s], values scale[rows[j]]): their q13 codes (``table``, ``scale_lut``),
    else f16 bits (the q13 arguments stand-ins); held codes updated, and their decodings if ``decode`` (as
    :func:`encode_positions`). False if an f16 value is NaN, infinite or beyond +-65504."""
    ok = True
    for x in range(np.uint64(n_s)):
        j = np.uint64(moved[x])
        r, i = np.uint64(rows[j]), np.uint64(ids[j])
        for c in range(np.uint64(3)):
            v = scale[r, c]
            if q13:
                code = scale_code(v, table)
                out_scale[x, c] = code
                held_s[i, c] = code
                if decode:
                    dec[7 + c, j] = np.float32(scale_lut[code])
            else:
                ok &= abs(v) <= F16_MAX
                h = f32_to_f16_bits(v)
                out_scale[x, c] = h
                held_s[i, c] = h
                if decode:
                    dec[7 + c, j] = f16_bits_to_f32(h)
    return ok


@nb.njit(**_NB)
def encode_rotations_f16(rot, rows, ids, moved, n_r, rsign, held_r, dec, out_rot, decode):
    """The moved rotations' f16 bits (candidates moved[:n_r], values rot[rows[j]] times rsign), each rotation's four
    as one uint64 (component c in bits 16 c: held_r and out_rot are the (.., 4) uint16 arrays viewed so); held codes
    updated, and their decodings if ``decode`` (as :func:`encode_positions`). False if one is NaN, infinite or beyond
    +-65504."""
    ok = True
    for x in range(n_r):
        j = np.uint64(moved[x])
        r = np.uint64(rows[j])
        code = np.uint64(0)
        for c in range(4):
            v = rot[r, c] * rsign[c]
            ok &= abs(v) <= F16_MAX
            h = f32_to_f16_bits(v)
            code |= np.uint64(h) << np.uint64(16 * c)
            if decode:
                dec[3 + c, j] = f16_bits_to_f32(h)
        out_rot[x] = code
        held_r[np.uint64(ids[j])] = code
    return ok


@nb.njit(**_NB)
def delta_f16_kernel(pos, rot, scale, rows, runs, ids, psign, rsign, tol, held_p, held_r, held_s, dec, flags, work,
                     out_moved, out_wide, out_res, out_pos, out_rot, out_scale):
    """ofera_protocol.delta.delta_f16_reference: :func:`_select`, then one pass per attribute. Returns (n, n_p, w,
    n_r, n_s, ok); ok False if a value sent is NaN, infinite or beyond +-65504."""
    n, n_p, n_r, n_s = _select(pos, rot, scale, runs, psign, rsign, tol, dec, flags, work, out_moved)
    # f16: lo, k, step unused (psign stands in)
    w, ok = encode_positions(False, pos, rows, ids, work[0], n_p, psign, psign, psign, psign, held_p, dec, out_wide,
                             out_res, out_pos, True)
    ok &= encode_rotations_f16(rot, rows, ids, work[1], n_r, rsign, held_r, dec, out_rot, True)
    ok &= encode_scales(False, scale, rows, ids, work[2], n_s, NO_TABLE, NO_LUT, held_s, dec, out_scale, True)
    return n, n_p, w, n_r, n_s, ok


_LOW_BITS = np.uint64(0x0101010101010101)  # bit 0 of each byte of a word
_GATHER = np.uint64(0x0102040810204080)  # times a word of 0 / 1 bytes: byte k's bit to bit 56 + k (no carries)


@nb.njit(inline="always", **_NB)
def _word8(a, j):
    """a[j..j+7] (uint8) as one little-endian uint64 (LLVM makes it one load)."""
    eight = np.uint64(8)
    x = np.uint64(0)
    for t in range(eight):
        x |= np.uint64(a[j + t]) << (eight * t)
    return x


@nb.njit(inline="always", **_NB)
def _gather8(x):
    """A word of 0 / 1 bytes -> one byte, byte k's bit at bit k (LSB first)."""
    return np.uint8((x * _GATHER) >> np.uint64(56))


@nb.njit(inline="always", **_NB)
def _flag_bits(flags, first, i0, i1, changed):
    """Bits i0..i1-1 of ``changed`` (within one byte or the edges of a run) OR-ed from flags[first..] != 0."""
    for i in range(i0, i1):
        changed[i >> np.uint64(3)] |= np.uint8(flags[first + i - i0] != 0) << np.uint8(i & np.uint64(7))


@nb.njit(inline="always", **_NB)
def _changed_run(flags, first_id, first, length, changed):
    """Candidates first..first+length-1 (session ids first_id..) into ``changed``: whole bytes 8 flags at a time (one
    word, the non-zero test and the bit gather by multiplication), the edges bit by bit."""
    eight = np.uint64(8)
    i0, i1 = np.uint64(first_id), np.uint64(first_id + length)
    a = min(i1, (i0 + np.uint64(7)) & ~np.uint64(7))  # the run's first byte boundary
    _flag_bits(flags, np.uint64(first), i0, a, changed)
    whole = max(a, i1 & ~np.uint64(7))
    j = np.uint64(first) + (a - i0)
    for b in range(a >> np.uint64(3), whole >> np.uint64(3)):
        x = _word8(flags, j)
        changed[b] = _gather8((x | (x >> np.uint64(1)) | (x >> np.uint64(2))) & _LOW_BITS)  # flags are 3 bits
        j += eight
    _flag_bits(flags, np.uint64(first) + (whole - i0), whole, i1, changed)


@nb.njit(inline="always", **_NB)
def _bin_head_size(size):
    """The bytes of :func:`_bin_head` for a bin of ``size`` bytes."""
    return 2 if size < 0x100 else 3 if size < 0x10000 else 5


@nb.njit(inline="always", **_NB)
def _bin_head(buf, o, size):
    """msgpack's header of a bin of ``size`` bytes at buf[o..] (the shortest: bin 8, 16 or 32); returns its end."""
    if size < 0x100:
        buf[o], buf[o + 1] = 0xC4, size
        return o + 2
    if size < 0x10000:
        buf[o], buf[o + 1], buf[o + 2] = 0xC5, size >> 8, size & 0xFF
        return o + 3
    buf[o] = 0xC6
    for b in range(4):
        buf[o + 1 + b] = (size >> (24 - 8 * b)) & 0xFF
    return o + 5


@nb.njit(inline="always", **_NB)
def copy_rows(src, dst, k, first, to, count):
    """Rows first.. of a flat (rows k,) array to rows to.. of another: unsigned indices, so LLVM makes it a
    memcpy-speed loop (a numba slice assignment took 3x as long for 150 kB, a signed loop 9x; round fifteen)."""
    a, b = np.uint64(k * first), np.uint64(k * to)
    for i in range(np.uint64(k * count)):
        dst[b + i] = src[a + i]


@nb.njit(inline="always", **_NB)
def _key(buf, o, keys, k):
    """The msgpack string at keys[k..] (a fixstr: its first byte holds its length) to buf[o..]: (both ends after)."""
    length = 1 + (keys[k] & 0x1F)
    copy_rows(keys, buf, 1, k, o, length)
    return o + length, k + length


@nb.njit(**_NB)
def delta_body_kernel(buf, at, keys, count, id_runs, flags, moved, wide, n, n_p, w, n_r, n_s, res, pos, rot, scl, r3,
                      r6, rr, rs):
    """ofera_protocol.delta.delta_body_reference (same bytes): a delta frame's bin fields as msgpack entries into
    buf[at..], the masks written in place (:func:`write_body` of one stream of outputs). Returns where they end."""
    counts = (n, n_p, w, n_r, n_s)
    front = (moved, wide.view(np.uint8), res, pos, rot, scl)
    none = (_NO_BLOCKS, 0, 0, _NO_BLOCKS[0])
    rows = (r3, r6, rr, rs)
    write_body(0, buf, at, keys, count, id_runs, flags, counts, counts, front, front, none, rows)
    return write_body(1, buf, at, keys, count, id_runs, flags, counts, counts, front, front, none, rows)


_NO_BLOCKS = np.zeros((1, 7), np.int64)  # write_body's table of no other streams (a constant in the kernel)


@nb.njit(inline="always", **_NB)
def write_body(part, buf, at, keys, count, id_runs, flags, totals, front_counts, front, back, blocks, rows):
    """Part of a delta frame's body (delta_body_reference's bytes) into buf[at..]: ``part`` 0 the changed mask, 1
    the other four masks and the four data fields (each part writes its own keys and bin heads; the two can run on
    two threads: the changed mask, over every session id, is most of the masks' time: 63 against 23 us p50, where the
    five masks took 54 against the data's 24 in a faster minute, round eighteen), another nothing (only where the
    body ends). The selection's outputs are one stream in ``front`` (moved, wide as uint8, res, pos,
    rot, scl as flat uint8) with ``front_counts`` (n, n_p, w, n_r, n_s), then the streams of ``blocks`` = (table,
    first, last, block_j): blocks b in first..last-1, table[b] their counts, their rows from block_j[b] in ``back``
    (direct_delta's threaded kernel: what its other threads wrote). ``totals``: the counts of all. ``rows``: the data
    fields' row bytes (r3, r6, rr, rs). The changed mask comes from the candidates' flags run by run (a scatter of the
    selection's ids into the mask took 77 us a frame on a cold CPU, its read-modify-writes chained through memory;
    round twelve). Returns where the body ends."""
    n, n_p, w, n_r, n_s = totals
    table, first, last, block_j = blocks
    sizes = ((count + 7) >> 3, (n + 7) >> 3, (n + 7) >> 3, (n + 7) >> 3, (n_p + 7) >> 3,
             rows[0] * (n_p - w), rows[1] * w, rows[2] * n_r, rows[3] * n_s)
    o, k = at, 0
    for f in range(9):  # changed, moved_position, moved_rotation, moved_scale, wide, then the data
        if part != (0 if f < 1 else 1):  # another part's entry: only where it ends
            length = 1 + (keys[k] & 0x1F)
            k += length
            o += length + _bin_head_size(sizes[f]) + sizes[f]
            continue
        o, k = _key(buf, o, keys, k)
        o = _bin_head(buf, o, sizes[f])
        if f == 0:
            out = buf[o:o + sizes[0]]
            out[:] = 0
            for r in range(id_runs.shape[0]):
                _changed_run(flags, id_runs[r, 0], id_runs[r, 1], id_runs[r, 2], out)
        elif f < 5:
            out = buf[o:o + sizes[f]]
            out[:] = 0
            src, back_src, col = (front[0], back[0], 0) if f < 4 else (front[1], back[1], 1)
            bit = f - 1 if f < 4 else 0
            at_bit = front_counts[col]
            pack_bits_at(src, 0, at_bit, bit, out, 0)
            for b in range(first, last):
                pack_bits_at(back_src, block_j[b], table[b, col], bit, out, at_bit)
                at_bit += table[b, col]
        else:
            d = f - 5
            rb = rows[d]
            fr = front_counts[1] - front_counts[2] if d == 0 else front_counts[d + 1]
            copy_rows(front[2 + d], buf, 1, 0, o, rb * fr)
            to = o + rb * fr
            for b in range(first, last):
                m = table[b, 1] - table[b, 2] if d == 0 else table[b, d + 1]
                copy_rows(back[2 + d], buf, 1, rb * block_j[b], to, rb * m)
                to += rb * m
        o += sizes[f]
    return o


@nb.njit(inline="always", **_NB)
def pack_bits_at(src, first, count, bit, out, at):
    """Bit ``bit`` of src[first..first+count-1] (uint8) OR-ed into the bit string ``out`` (uint8, LSB first) from
    bit ``at`` on, 8 flags a word; out's bits there must be 0. The selection's bools as (n, 3) columns, gathered a
    bit at a time, took 45 us a frame on a cold CPU (round twelve)."""
    bit, first, at = np.uint64(bit), np.uint64(first), np.uint64(at)
    shift, byte = at & np.uint64(7), at >> np.uint64(3)
    full = np.uint64(count) >> np.uint64(3)
    for b in range(full):
        v = np.uint64(_gather8((_word8(src, first + np.uint64(8) * b) >> bit) & _LOW_BITS))
        out[byte + b] |= np.uint8((v << shift) & np.uint64(0xFF))
        if shift:
            out[byte + b + np.uint64(1)] |= np.uint8(v >> (np.uint64(8) - shift))
    for t in range(np.uint64(8) * full, np.uint64(count)):
        i = at + t
        out[i >> np.uint64(3)] |= ((src[first + t] >> np.uint8(bit)) & np.uint8(1)) << np.uint8(i & np.uint64(7))


def delta_kernel_warm() -> None:
    """Compile the delta kernels for writable and read-only float32 state arrays: a key and a delta frame of a
    two-Gaussian encoder per encoding (the encoder's own argument types)."""
    from ofera_protocol import make_quant

    k = NumbaKernels()
    for readonly in (False, True):
        p, r, s = np.zeros((2, 3), np.float32), np.zeros((2, 4), np.float32), np.full((2, 3), 1e-3, np.float32)
        p[1], r[:, 3] = 0.1, 1
        moved = p + np.float32(0.01), r[::-1].copy(), s * np.float32(2)
        for a in (p, r, s, *moved):
            a.flags.writeable = not readonly
        for encoding in ("q13", "f16"):
            fmt = FrameFormat(encoding, 2, False, make_quant(p, s) if encoding == "q13" else None, delta=True)
            enc = DeltaEncoder(fmt, kernels=k)
            enc.encode(0, 0, {}, p, r, s)
            enc.encode(1, 0, {}, *moved)  # a delta frame: its masks too


def delta_encoder(fmt: FrameFormat, coords: str = "flame", gather: np.ndarray | None = None,
                  candidates: np.ndarray | None = None, rows: np.ndarray | None = None,
                  tolerance: DeltaTolerance | None = None, key_interval: int = 720,
                  stamp_encode: bool = False) -> DeltaEncoder:
    """A DeltaEncoder (ofera_protocol.delta) using the numba kernels."""
    return DeltaEncoder(fmt, coords, gather, candidates, rows, kernels=numba_kernels(), tolerance=tolerance,
                        key_interval=key_interval, stamp_encode=stamp_encode)
