"""Frame encodings: how `position`, `rotation` and `scale` of a frame become `bin` payloads.

Reference implementations in plain vectorised numpy (no per-element Python). A faster path (numba,
fused coordinate mirroring) may be added later next to these; it must match them bit for bit and be
tested against them.

Byte layouts per Gaussian (all little-endian, Gaussian-major, components in order):

==========  ==================  =====================  ==================  ======
encoding    position            rotation (x, y, z, w)  scale               total
==========  ==================  =====================  ==================  ======
``f32``     3 x float32 (12 B)  4 x float32 (16 B)     3 x float32 (12 B)  40 B
``f16``     3 x float16 (6 B)   4 x float16 (8 B)      3 x float16 (6 B)   20 B
``q13``     3 x uint16 (6 B)    1 x uint32 (4 B)       3 x uint8 (3 B)     13 B
==========  ==================  =====================  ==================  ======

q13: positions are quantised uniformly in the box `Quant.pos_min..pos_max`; rotations use "smallest
three" 10.10.10.2; scales are quantised uniformly in ln(scale) over `Quant.log_scale`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .constants import BYTES_PER_GAUSSIAN, ENCODINGS, FIELD_BYTES, UINT32_MAX  # noqa: F401 - FIELD_BYTES: re-exported
from .errors import BAD_LENGTH, NON_FINITE, ProtocolError
from .messages import Quant

SQRT1_2 = float(np.sqrt(0.5))
"""Largest magnitude of a non-largest component of a unit quaternion (1/sqrt 2)."""

POS_LEVELS = 65535
ROT_LEVELS = 511  # SNORM10: -511..511
SCALE_LEVELS = 255


_DTYPES: dict[str, tuple[str, str, str]] = {
    "f32": ("<f4", "<f4", "<f4"),
    "f16": ("<f2", "<f2", "<f2"),
    "q13": ("<u2", "<u4", "u1"),
}
_SHAPES: tuple[int, int, int] = (3, 4, 3)
_FLOAT_LIMIT = {"f32": float(np.finfo(np.float32).max), "f16": float(np.finfo(np.float16).max)}


@dataclass(frozen=True)
class FrameFormat:
    """What a receiver needs to decode a session's frames (all of it is in `welcome`).

    encoding: one of ENCODINGS; count: Gaussians in the avatar; sparse: frames may carry `index`;
    quant: required for `q13`, ignored otherwise.
    """

    encoding: str
    count: int
    sparse: bool = False
    quant: Quant | None = None
    delta: bool = False  # key / delta frames (PROTOCOL.md 7.1); f16 and q13 only, never sparse

    def __hash__(self) -> int:  # usable as a dict key, e.g. to encode a frame once per format
        q = self.quant
        qkey = None if q is None else (q.pos_min.tobytes(), q.pos_max.tobytes(), q.log_scale.tobytes())
        return hash((self.encoding, self.count, self.sparse, qkey, self.delta))

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise ValueError(f"unknown encoding {self.encoding!r}; expected one of {ENCODINGS}")
        if not 0 <= self.count <= UINT32_MAX:
            raise ValueError(f"count {self.count} out of range")
        if self.encoding == "q13":
            if self.quant is None:
                raise ValueError("encoding 'q13' needs quant parameters")
            validate_quant(self.quant)
        else:
            object.__setattr__(self, "quant", None)
        if self.delta and (self.encoding not in ("f16", "q13") or self.sparse):
            raise ValueError(f"delta frames need encoding f16 or q13 and a dense session, not {self.encoding}"
                             f"{' sparse' if self.sparse else ''}")

    def payload_bytes(self, n: int | None = None) -> int:
        """Array bytes of a frame: dense (n None) or sparse with n Gaussians (4 B of index each)."""
        if n is None:
            return self.count * BYTES_PER_GAUSSIAN[self.encoding]
        return n * (BYTES_PER_GAUSSIAN[self.encoding] + 4)


def validate_quant(quant: Quant) -> None:
    """Raise ValueError unless quant holds finite float32 arrays of shapes (3,), (3,), (2,) with max > min."""
    for name, shape in (("pos_min", (3,)), ("pos_max", (3,)), ("log_scale", (2,))):
        a = getattr(quant, name)
        if not isinstance(a, np.ndarray) or a.dtype != np.float32 or a.shape != shape:
            raise ValueError(f"quant.{name} must be a float32 array of shape {shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"quant.{name} must be finite")
    if not (quant.pos_max > quant.pos_min).all():
        raise ValueError("quant.pos_max must exceed quant.pos_min on every axis")
    if not quant.log_scale[1] > quant.log_scale[0]:
        raise ValueError("quant.log_scale must be [min, max] with max > min")


def make_quant(position: np.ndarray, scale: np.ndarray, margin: float = 0.25,
               min_extent: float = 1e-3) -> Quant:
    """q13 parameters covering `position` (N, 3) m and `scale` (N, 3) m, padded for expressions.

    The box is the bounding box grown by `margin` x its extent on every side (each axis at least
    `min_extent` m wide); the log-scale range is [min, max] of ln(scale) grown by `margin` x its width
    (at least 1 wide). Values are float32 so both ends use identical numbers.
    """
    p = np.asarray(position, dtype=np.float64).reshape(-1, 3)
    s = np.asarray(scale, dtype=np.float64).reshape(-1)
    if p.size == 0 or s.size == 0:
        lo, hi = np.full(3, -1.0), np.full(3, 1.0)
        ls = np.array([np.log(1e-4), np.log(1e-1)])
    else:
        lo, hi = p.min(0), p.max(0)
        ext = np.maximum(hi - lo, min_extent)
        mid = (lo + hi) / 2
        lo, hi = mid - ext * (0.5 + margin), mid + ext * (0.5 + margin)
        logs = np.log(np.maximum(s, 1e-12))
        lmin, lmax = logs.min(), logs.max()
        w = max(lmax - lmin, 1.0)
        ls = np.array([(lmin + lmax) / 2 - w * (0.5 + margin), (lmin + lmax) / 2 + w * (0.5 + margin)])
    q = Quant(pos_min=lo.astype(np.float32), pos_max=hi.astype(np.float32), log_scale=ls.astype(np.float32))
    validate_quant(q)
    return q


# ----------------------------------------------------------------------------- q13 building blocks


def quantize_positions(position: np.ndarray, quant: Quant) -> np.ndarray:
    """(N, 3) metres -> (N, 3) uint16: round((p - min) / (max - min) * 65535), clamped to the box.

    Computed in float64, so the result is exact up to ties."""
    lo = quant.pos_min.astype(np.float64)
    return quantize_positions_lk(position, lo, POS_LEVELS / (quant.pos_max.astype(np.float64) - lo))


def quantize_positions_lk(position: np.ndarray, lo: np.ndarray, k: np.ndarray) -> np.ndarray:
    """:func:`quantize_positions` with its float64 factors: q = clip(rint((p - lo) * k), 0, 65535)."""
    q = np.asarray(position, dtype=np.float64).reshape(-1, 3) - lo
    q *= k
    np.rint(q, out=q)
    np.clip(q, 0, POS_LEVELS, out=q)
    return q.astype("<u2")


def dequantize_positions(q: np.ndarray, quant: Quant) -> np.ndarray:
    """(N, 3) uint16 -> (N, 3) float32 metres: min + q * (max - min) / 65535."""
    lo = quant.pos_min.astype(np.float64)
    step = (quant.pos_max.astype(np.float64) - lo) / POS_LEVELS
    return (lo + q.astype(np.float64) * step).astype(np.float32)


def pack_smallest_three(rotation: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w) -> (N,) uint32 "smallest three" 10.10.10.2.

    Bits 31-30: index i of the largest-magnitude component (0=x .. 3=w; the first on ties), dropped.
    The quaternion is normalised, and negated if needed so that component i is >= 0. The three other
    components c, in increasing index order, go to bits 29-20, 19-10, 9-0 as 10-bit two's-complement
    SNORM of c * sqrt2: s = clamp(round(c * sqrt2 * 511), -511, 511). Zero is exact.
    A zero or non-finite quaternion encodes the identity. Computed column-wise in float32.
    """
    q = np.array(np.asarray(rotation, dtype=np.float32).reshape(-1, 4).T, order="C")  # (4, N) copy
    n2 = np.einsum("ij,ij->j", q, q)
    bad = ~(np.isfinite(n2) & (n2 > 0))
    if bad.any():
        q[:, bad] = np.array([[0.0], [0.0], [0.0], [1.0]], dtype=np.float32)
        n2[bad] = 1.0
    # Branch-free selection (np.where on random masks is slow): index of the largest |component|.
    a = np.abs(q)
    hi01, hi23 = a[1] > a[0], a[3] > a[2]
    upper = np.maximum(a[2], a[3]) > np.maximum(a[0], a[1])
    i = upper.astype(np.uint8) * np.uint8(2) + ((upper & hi23) | (~upper & hi01))
    neg = np.zeros(q.shape[1], dtype=bool)
    for c in range(4):
        neg |= (i == c) & (q[c] < 0)
    f = np.float32(np.sqrt(2.0) * ROT_LEVELS) / np.sqrt(n2)
    f *= 1 - 2 * neg.astype(np.float32)
    q *= f
    np.rint(q, out=q)
    np.clip(q, -ROT_LEVELS, ROT_LEVELS, out=q)
    u = (q.astype(np.int32) & 0x3FF).view(np.uint32)  # 10-bit two's complement codes, (4, N)
    x, y, z, w = u[0], u[1], u[2], u[3]
    i32 = i.astype(np.uint32)
    out = i32 << 30
    for c, (k0, k1, k2) in enumerate(((y, z, w), (x, z, w), (x, y, w), (x, y, z))):
        out |= ((k0 << 20) | (k1 << 10) | k2) * (i32 == c).astype(np.uint32)
    return out.astype("<u4")


def unpack_smallest_three(packed: np.ndarray) -> np.ndarray:
    """(N,) uint32 10.10.10.2 -> (N, 4) float32 unit quaternions (x, y, z, w).

    Each kept 10-bit field s (two's complement, -512..511) gives c = max(s / 511, -1) / sqrt2; the
    dropped component is sqrt(max(0, 1 - sum c^2)).
    """
    v = np.asarray(packed).astype(np.uint32).reshape(-1)
    i = v >> 30
    f = np.empty((3, v.shape[0]), dtype=np.int32)
    f[0], f[1], f[2] = (v >> 20) & 1023, (v >> 10) & 1023, v & 1023
    f ^= 512
    f -= 512  # sign-extend 10 bits
    np.maximum(f, -ROT_LEVELS, out=f)
    k = f.astype(np.float32)
    k *= np.float32(SQRT1_2 / ROT_LEVELS)
    d = np.einsum("ij,ij->j", k, k)
    np.subtract(1.0, d, out=d)
    np.maximum(d, 0.0, out=d)
    np.sqrt(d, out=d)
    # Branch-free scatter: output column c takes the dropped value if c == i, else kept[c - (c > i)].
    out = np.empty((v.shape[0], 4), dtype=np.float32)
    for c in range(4):
        col = d * (i == c).astype(np.float32)
        if c < 3:
            col += k[c] * (i > c).astype(np.float32)
        if c > 0:
            col += k[c - 1] * (i < c).astype(np.float32)
        out[:, c] = col
    return out


def quantize_log_scale(scale: np.ndarray, quant: Quant) -> np.ndarray:
    """(N, 3) metres -> (N, 3) uint8: round((ln s - lmin) / (lmax - lmin) * 255), clamped (float32;
    zero, negative or NaN scales give 0)."""
    lmin, lmax = float(quant.log_scale[0]), float(quant.log_scale[1])
    s = np.asarray(scale, dtype=np.float32).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.log(s)
    q -= np.float32(lmin)
    q *= np.float32(SCALE_LEVELS / (lmax - lmin))
    np.nan_to_num(q, copy=False, nan=0.0, posinf=SCALE_LEVELS, neginf=0.0)
    np.rint(q, out=q)
    np.clip(q, 0, SCALE_LEVELS, out=q)
    return q.astype(np.uint8)


def dequantize_log_scale(q: np.ndarray, quant: Quant) -> np.ndarray:
    """(N, 3) uint8 -> (N, 3) float32 metres: exp(lmin + q * (lmax - lmin) / 255)."""
    lmin, lmax = float(quant.log_scale[0]), float(quant.log_scale[1])
    return np.exp(lmin + q.astype(np.float64) * ((lmax - lmin) / SCALE_LEVELS)).astype(np.float32)


# ----------------------------------------------------------------------------- whole frames


def encode_arrays(encoding: str, position: np.ndarray, rotation: np.ndarray, scale: np.ndarray,
                  quant: Quant | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Encode (N, 3), (N, 4), (N, 3) float arrays into three C-contiguous little-endian arrays
    whose raw bytes are the `position`, `rotation` and `scale` bin payloads.

    f32 inputs that are already C-contiguous little-endian float32 are returned without copying.
    Inputs must be finite (f16 also needs |value| <= 65504); ValueError otherwise for f32/f16.
    """
    if encoding == "q13":
        if quant is None:
            raise ValueError("encoding 'q13' needs quant parameters")
        return (quantize_positions(position, quant), pack_smallest_three(rotation),
                quantize_log_scale(scale, quant))
    if encoding not in ("f32", "f16"):
        raise ValueError(f"unknown encoding {encoding!r}")
    dt = _DTYPES[encoding][0]
    limit = _FLOAT_LIMIT[encoding]
    out = []
    for name, a in zip(("position", "rotation", "scale"), (position, rotation, scale), strict=True):
        a = np.asarray(a)
        # min/max propagate NaN, so one comparison each catches NaN, infinity and float16 overflow.
        if a.size and not (-limit <= a.min() and a.max() <= limit):
            raise ValueError(f"{name} has NaN, infinity or values beyond +-{limit:g} ({encoding})")
        out.append(np.ascontiguousarray(a, dtype=dt))
    return out[0], out[1], out[2]


def decode_arrays(encoding: str, n: int, position: bytes, rotation: bytes, scale: bytes,
                  quant: Quant | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode the three bin payloads of n Gaussians into float32 (n, 3), (n, 4), (n, 3).

    Raises ProtocolError `bad_length` if a payload has the wrong size and `non_finite` if a float
    encoding holds NaN or infinity. f32 results are read-only views of the payloads.
    """
    sizes = FIELD_BYTES[encoding]
    bufs = (position, rotation, scale)
    for name, buf, size in zip(("position", "rotation", "scale"), bufs, sizes, strict=True):
        if len(buf) != n * size:
            raise ProtocolError(BAD_LENGTH, f"frame field {name!r} has {len(buf)} bytes; "
                                f"{n} Gaussians in {encoding} need {n * size}")
    dtypes = _DTYPES[encoding]
    if encoding == "q13":
        assert quant is not None
        p = np.frombuffer(position, dtype=dtypes[0]).reshape(n, 3)
        r = np.frombuffer(rotation, dtype=dtypes[1])
        s = np.frombuffer(scale, dtype=dtypes[2]).reshape(n, 3)
        return dequantize_positions(p, quant), unpack_smallest_three(r), dequantize_log_scale(s, quant)
    out = []
    for name, buf, dt, width in zip(("position", "rotation", "scale"), bufs, dtypes, _SHAPES, strict=True):
        a = np.frombuffer(buf, dtype=dt).reshape(n, width)
        if encoding == "f16":
            a = a.astype(np.float32)  # isfinite is much faster on float32 than on float16
        if not np.isfinite(a).all():
            raise ProtocolError(NON_FINITE, f"frame field {name!r} holds NaN or infinity")
        out.append(a)
    return out[0], out[1], out[2]


# ----------------------------------------------------------------------------- error bounds


def position_error_bound(encoding: str, quant: Quant | None = None,
                         magnitude: float | np.ndarray = 1.0) -> np.ndarray:
    """Largest |decoded - sent| per axis (metres) for a position of the given magnitude.

    f32: 0. f16: half an ulp, 2^-11 |x| for |x| >= 2^-14, else 2^-25. q13: half a step,
    (max - min) / 65535 / 2 per axis, for positions inside the box (outside: clamped to it), plus
    the float32 rounding of the result (2^-24 |decoded| <= 2^-24 (|x| + step)).
    """
    m = np.abs(np.asarray(magnitude, dtype=np.float64))
    if encoding == "f32":
        return np.zeros(np.broadcast_shapes(m.shape, (3,)))
    if encoding == "f16":
        return np.broadcast_to(np.maximum(m * 2.0**-11, 2.0**-25), np.broadcast_shapes(m.shape, (3,)))
    assert quant is not None
    step = (quant.pos_max.astype(np.float64) - quant.pos_min.astype(np.float64)) / POS_LEVELS
    return step / 2 + (m + step) * 2.0**-24


Q13_ROTATION_COMPONENT_ERROR = SQRT1_2 / ROT_LEVELS / 2
"""Largest error of one kept component in q13: half a step, (1/sqrt2) / 511 / 2 (about 6.9e-4)."""
Q13_ROTATION_ERROR = 4 * Q13_ROTATION_COMPONENT_ERROR
"""Bound on the Euclidean distance between a unit quaternion and its q13 decoding (up to sign),
about 2.8e-3, i.e. a rotation error below 0.32 degrees."""
F16_ROTATION_ERROR = 2.0**-12
"""Largest per-component error of a unit quaternion in f16 (half an ulp of values in [0.5, 1])."""


LOG_SCALE_SLACK = 1e-5
"""Float32 arithmetic of the reference q13 scale encoder, in ln units (|ln s| < 40)."""


def log_scale_error_bound(quant: Quant) -> float:
    """Largest |ln decoded - ln sent| of a q13 scale inside the log range: half a step,
    (lmax - lmin) / 255 / 2, plus LOG_SCALE_SLACK. Outside the range scales are clamped to it."""
    return float(quant.log_scale[1] - quant.log_scale[0]) / SCALE_LEVELS / 2 + LOG_SCALE_SLACK
