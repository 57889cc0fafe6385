"""The fast client-side frame decoder (numba): what benchmark and test clients use to keep up with 100k-Gaussian
streams. The reference is the protocol codec (``ofera_protocol.decode_server_message`` + ``ClientConnection``);
this decoder starts from the same field checks (``codec.frame_parts``) and gives the same float32 values.

Delta sessions (PROTOCOL.md 7.1): key frames are decoded here and their codes handed to an
``ofera_protocol.delta.DeltaDecoder``, which applies delta frames (vectorised numpy: the frames are small).
"""

from __future__ import annotations

import math
from typing import Any

import numba as nb
import numpy as np
from ofera_protocol import Frame, FrameFormat
from ofera_protocol.encodings import POS_LEVELS, ROT_LEVELS, SCALE_LEVELS
from ofera_protocol.messages import DeltaFrame

from ..streaming.encode_fast import _NB, f16_bits_to_f32, numba_kernels


@nb.njit(**_NB)
def f16_decode_kernel(src, dst):
    """half bits (n,) -> float32 (n,); False if any is NaN or infinite (exponent all ones)."""
    ok = True
    for i in range(src.shape[0]):
        h = src[i]
        ok &= (h & 0x7C00) != 0x7C00
        dst[i] = f16_bits_to_f32(h)
    return ok


@nb.njit(inline="always", **_NB)
def _q13_field(v, shift):
    f = np.int32((v >> np.uint32(shift)) & 1023)
    f = (f ^ 512) - 512
    return np.float32(max(f, -ROT_LEVELS))


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
    In a delta session it also keeps the codes the client holds (``delta``) and returns delta frames as
    sparse-like Frames (``index`` = the changed Gaussians). ``ofera_protocol.decode_server_message`` is the
    reference."""

    def __init__(self, fmt: FrameFormat) -> None:
        numba_kernels()  # compiled (or loaded from the cache) before the first frame
        decoder_warm()
        self.format = fmt
        n = fmt.count
        self._pos = np.zeros((n, 3), np.float32)
        self._rot = np.zeros((n, 4), np.float32)
        self._scale = np.zeros((n, 3), np.float32)
        self.delta: Any = None
        if fmt.delta:
            from ofera_protocol.delta import DeltaDecoder

            self.delta = DeltaDecoder(fmt)
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
        from ofera_protocol.codec import decode_server_message, frame_parts, unpack_message
        from ofera_protocol.constants import MAX_SERVER_MESSAGE
        from ofera_protocol.errors import NON_FINITE, ProtocolError

        m = unpack_message(data, MAX_SERVER_MESSAGE)
        if m.get("type") != "frame":
            return decode_server_message(data, self.format)
        fmt = self.format
        parts = frame_parts(m, fmt)
        if isinstance(parts, DeltaFrame):
            return self.delta.apply(parts)
        seq, t, timing, key, n, index, bufs = parts
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
        codes = None
        if key:
            dts = ("<u2", "<u4", "u1") if fmt.encoding == "q13" else ("<u2", "<u2", "<u2")
            codes = tuple(np.frombuffer(b, dt) for b, dt in zip(bufs, dts))
        frame = Frame(seq=seq, t=t, timing=timing, index=index, position=p, rotation=r, scale=s, key=key,
                      codes=codes)  # type: ignore[arg-type]
        if key:
            self.delta.key(frame)
        return frame
