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
- q13 scales: threshold search (:func:`ofera_protocol.fast_encodings.scale_thresholds`), so no float32
  logarithm has to match numpy's.

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
from ofera_protocol.fast_encodings import F16_MAX, F32_MAX, FrameWriter, position_factors, scale_thresholds
from ofera_protocol.messages import Quant

_NB = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy", "boundscheck": False}


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
def q13_position_kernel(src, gather, count, sign, lo, k, dst):
    """uint16 q = clip(rint((float64(p) - lo) * k), 0, 65535) per axis (the reference's float64 steps)."""
    for m in range(count):
        r = _row(gather, m)
        for c in range(3):
            q = (np.float64(src[r, c] * sign[c]) - lo[c]) * k[c]
            q = np.rint(q)
            if q < 0.0:
                q = 0.0
            elif q > POS_LEVELS:
                q = POS_LEVELS
            dst[m * 3 + c] = np.uint16(q)


@nb.njit(**_NB)
def _snorm10(v):
    q = np.rint(np.float64(v))
    if q < -ROT_LEVELS:
        q = -ROT_LEVELS
    elif q > ROT_LEVELS:
        q = ROT_LEVELS
    return np.uint32(np.int32(q) & 0x3FF)


@nb.njit(**_NB)
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
    if upper:
        i = 3 if a3 > a2 else 2
    else:
        i = 1 if a1 > a0 else 0
    big = x if i == 0 else (y if i == 1 else (z if i == 2 else w))
    f = np.float32(np.sqrt(2.0) * ROT_LEVELS) / np.sqrt(n2)
    if big < 0:
        f = -f
    sx = _snorm10(x * f)
    sy = _snorm10(y * f)
    sz = _snorm10(z * f)
    sw = _snorm10(w * f)
    if i == 0:
        body = (sy << 20) | (sz << 10) | sw
    elif i == 1:
        body = (sx << 20) | (sz << 10) | sw
    elif i == 2:
        body = (sx << 20) | (sy << 10) | sw
    else:
        body = (sx << 20) | (sy << 10) | sz
    return (np.uint32(i) << 30) | body


@nb.njit(**_NB)
def q13_rotation_kernel(src, gather, count, sign, dst):
    for m in range(count):
        r = _row(gather, m)
        dst[m] = pack_rotation(src[r, 0] * sign[0], src[r, 1] * sign[1], src[r, 2] * sign[2], src[r, 3] * sign[3])


@nb.njit(**_NB)
def _scale_code(v, thresholds):
    """Number of thresholds <= v (binary search; NaN -> 0)."""
    if not v >= thresholds[0]:
        return 0
    lo = 0  # thresholds[lo] <= v
    hi = thresholds.shape[0]  # thresholds[hi] > v (virtual)
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if thresholds[mid] <= v:
            lo = mid
        else:
            hi = mid
    return lo + 1


@nb.njit(**_NB)
def q13_scale_kernel(src, gather, count, thresholds, dst):
    for m in range(count):
        r = _row(gather, m)
        for c in range(3):
            dst[m * 3 + c] = np.uint8(_scale_code(src[r, c], thresholds))


_NO_GATHER = np.zeros(0, np.int64)


class NumbaKernels:
    """The numba kernel set for :class:`ofera_protocol.fast_encodings.FrameWriter`."""

    @staticmethod
    def _g(src: np.ndarray, gather: np.ndarray | None) -> tuple[np.ndarray, int]:
        return (_NO_GATHER, src.shape[0]) if gather is None else (gather, gather.shape[0])

    def f32(self, src, gather, sign, dst) -> bool:
        g, n = self._g(src, gather)
        return bool(f32_kernel(src, g, n, sign, dst))

    def f16(self, src, gather, sign, dst) -> bool:
        g, n = self._g(src, gather)
        return bool(f16_kernel(src, g, n, sign, dst))

    def q13_position(self, src, gather, sign, lo, k, dst) -> None:
        g, n = self._g(src, gather)
        q13_position_kernel(src, g, n, sign, lo, k, dst)

    def q13_rotation(self, src, gather, sign, dst) -> None:
        g, n = self._g(src, gather)
        q13_rotation_kernel(src, g, n, sign, dst)

    def q13_scale(self, src, gather, thresholds, dst) -> None:
        g, n = self._g(src, gather)
        q13_scale_kernel(src, g, n, thresholds, dst)


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
    """Compile every kernel for the types the server uses (float32 state, full and gathered rows)."""
    k = NumbaKernels()
    p = np.zeros((2, 3), np.float32)
    r = np.zeros((2, 4), np.float32)
    r[:, 3] = 1
    s = np.full((2, 3), 1e-3, np.float32)
    ones3, ones4 = np.ones(3, np.float32), np.ones(4, np.float32)
    lo, kk = np.zeros(3), np.ones(3)
    thr = np.linspace(1e-4, 1e-2, SCALE_LEVELS).astype(np.float32)
    for gather in (None, np.arange(2, dtype=np.int64)):
        k.f32(p, gather, ones3, np.zeros(6, np.float32))
        k.f16(p, gather, ones3, np.zeros(6, np.uint16))
        k.f16(r, gather, ones4, np.zeros(8, np.uint16))
        k.q13_position(p, gather, ones3, lo, kk, np.zeros(6, np.uint16))
        k.q13_rotation(r, gather, ones4, np.zeros(2, np.uint32))
        k.q13_scale(s, gather, thr, np.zeros(6, np.uint8))
    # Unaligned destinations (fields inside a message buffer) are their own numba specialisation.
    buf = bytearray(64)
    k.f16(p, None, ones3, np.frombuffer(buf, np.uint16, 6, 1))
    k.f32(p, None, ones3, np.frombuffer(buf, np.float32, 6, 1))
    k.q13_position(p, None, ones3, lo, kk, np.frombuffer(buf, np.uint16, 6, 1))
    k.q13_rotation(r, None, ones4, np.frombuffer(buf, np.uint32, 2, 1))
    delta_kernel_warm()


def frame_writer(fmt: FrameFormat, coords: str = "flame", gather: np.ndarray | None = None,
                 index: np.ndarray | None = None, pool: int = 4) -> FrameWriter:
    """A FrameWriter using the numba kernels."""
    return FrameWriter(fmt, coords, gather, index, kernels=numba_kernels(), pool=pool)


# ============================================================================= delta (moved since last sent)


@nb.njit(**_NB)
def _delta_select(pos, rot, scale, ids, psign, rsign, lo, k, step, thresholds, log_lo, log_step,
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
            code = _scale_code(scale[r, c], thresholds)
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


def delta_kernel_warm() -> None:
    z3, z4 = np.zeros((1, 3), np.float32), np.zeros((1, 4), np.float32)
    z4[0, 3] = 1
    _delta_select(z3, z4, z3 + 1e-3, np.zeros(1, np.int64), np.ones(3, np.float32), np.ones(4, np.float32),
                  np.zeros(3), np.ones(3), np.ones(3), np.linspace(1e-4, 1e-2, 255).astype(np.float32), -9.0, 0.01,
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
        self.scale_thr = scale_thresholds(quant)
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
                          self.scale_thr, self.log_lo, self.log_step, self.held_pos, self.held_rot, self.held_slo,
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
