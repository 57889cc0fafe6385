"""The fast client-side frame decoder (numba): what benchmark and test clients use to keep up with 100k-Gaussian
streams. The reference is the protocol codec (``ofera_protocol.decode_server_message`` + ``ClientConnection``);
this decoder starts from the same field checks (``codec.frame_parts``) and gives the same float32 values.

Delta sessions (PROTOCOL.md 7.1): key frames are decoded here and their codes handed to an
``ofera_protocol.delta.DeltaDecoder``; delta frames' masks are unpacked and checked by
:func:`unpack_delta_masks_kernel` (the twin of ``codec.delta_masks``, which raises the exact error when the kernel
finds one) and applied by :func:`delta_apply_kernel` (the twin of ``DeltaDecoder.apply``).
"""

from __future__ import annotations

import math
from typing import Any

import numba as nb
import numpy as np
from ofera_protocol import Frame, FrameFormat
from ofera_protocol.encodings import POS_LEVELS, ROT_LEVELS, SCALE_LEVELS
from ofera_protocol.messages import DeltaFrame

from ..jit import NB as _NB
from ..jit import f16_bits_to_f32


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
    for m in range(rot.shape[0]):
        for c in range(3):
            out_pos[m, c] = np.float32(lo[c] + np.float64(pos[3 * m + c]) * step[c])
            out_scale[m, c] = scale_lut[scale[3 * m + c]]
        _q13_rotation_into(rot[m], out_rot, m)


@nb.njit(inline="always", **_NB)
def _q13_rotation_into(v, out, j):
    kf = np.float32(math.sqrt(0.5) / ROT_LEVELS)
    i = v >> 30
    a0 = _q13_field(v, 20) * kf
    a1 = _q13_field(v, 10) * kf
    a2 = _q13_field(v, 0) * kf
    d = a0 * a0
    d = d + a1 * a1
    d = d + a2 * a2
    big = np.sqrt(max(np.float32(1.0) - d, np.float32(0.0)))
    out[j, 0] = big if i == 0 else a0
    out[j, 1] = big if i == 1 else (a0 if i == 0 else a1)
    out[j, 2] = big if i == 2 else (a2 if i == 3 else a1)
    out[j, 3] = big if i == 3 else a2


@nb.njit(**_NB)
def delta_apply_kernel(q13, ids, moved, wide, res, wpos, rot, scl, held_p, held_r, held_s, lo, step, lut,
                       out_p, out_r, out_s):
    """A checked DeltaFrame (PROTOCOL.md 7.1) onto the held codes: pass 1 checks every narrow change (0 = ok, 1 = a
    code outside 0..65535, 2 = an f16 position NaN / infinite) and changes nothing on failure; pass 2 holds the new
    codes and decodes the carried Gaussians into out_* (n, 3 / 4 / 3) float32. q13: held_r (count,) uint32 and
    held_s (count, 3) uint8 (viewed as rot / scl); f16: every code uint16, rot (n_r, 4), scl (n_s, 3)."""
    p = 0
    k = 0
    for j in range(ids.shape[0]):
        if moved[j, 0]:
            if not wide[p]:
                i = np.uint64(ids[j])  # unsigned indices: no wrap-around code (see ofera.avatar.kernels)
                for c in range(3):
                    v = np.int32(held_p[i, c]) + np.int32(res[k, c])
                    if v < 0 or v > 65535:
                        return 1
                    if not q13 and (v & 0x7C00) == 0x7C00:
                        return 2
                k += 1
            p += 1
    p = k = w = r = s = 0
    for j in range(ids.shape[0]):
        i = np.uint64(ids[j])
        if moved[j, 0]:
            if wide[p]:
                for c in range(3):
                    held_p[i, c] = wpos[w, c]
                w += 1
            else:
                for c in range(3):
                    held_p[i, c] = np.uint16(np.int32(held_p[i, c]) + np.int32(res[k, c]))
                k += 1
            p += 1
        if moved[j, 1]:
            if q13:
                held_r[i, 0] = rot[r, 0]
            else:
                for c in range(4):
                    held_r[i, c] = rot[r, c]
            r += 1
        if moved[j, 2]:
            for c in range(3):
                held_s[i, c] = scl[s, c]
            s += 1
        for c in range(3):
            if q13:
                out_p[j, c] = np.float32(lo[c] + np.float64(held_p[i, c]) * step[c])
                out_s[j, c] = lut[held_s[i, c]]
            else:
                out_p[j, c] = f16_bits_to_f32(np.uint16(held_p[i, c]))
                out_s[j, c] = f16_bits_to_f32(np.uint16(held_s[i, c]))
        if q13:
            _q13_rotation_into(np.uint32(held_r[i, 0]), out_r, j)
        else:
            for c in range(4):
                out_r[j, c] = f16_bits_to_f32(np.uint16(held_r[i, c]))
    return 0


@nb.njit(inline="always", **_NB)
def _unpack_mask(buf, n, out, col):
    """Bits 0..n-1 of buf (LSB first) into out[:n, col]; the number set, or -1 if buf's length is not ceil(n / 8)
    or a padding bit is set."""
    if buf.shape[0] != (n + 7) // 8:
        return -1
    if n & 7 and buf[n >> 3] >> (n & 7):
        return -1
    ones = 0
    for j in range(n):
        b = (buf[j >> 3] >> (j & 7)) & 1
        out[j, col] = b
        ones += b
    return ones


@nb.njit(**_NB)
def unpack_delta_masks_kernel(changed, count, n, mpos, mrot, mscale, wide_bits, index, moved, wide):
    """A delta frame's masks (PROTOCOL.md 7.1) unpacked and checked in one go: the changed Gaussians into index
    (count,) uint32, the moved bits into moved (n, 3) bool, the wide bits into wide (n, 1) bool. Returns (ok,
    n_p, n_r, n_s, wide ones); ok False for any fault codec.delta_masks reports (it then names it)."""
    if changed.shape[0] != (count + 7) // 8 or (count & 7 and changed[count >> 3] >> (count & 7)):
        return False, 0, 0, 0, 0
    k = 0
    for b in range(changed.shape[0]):
        byte = changed[b]
        if byte == 0:
            continue
        for bit in range(8):
            if (byte >> bit) & 1:
                if k == n:
                    return False, 0, 0, 0, 0
                index[k] = b * 8 + bit
                k += 1
    if k != n:
        return False, 0, 0, 0, 0
    n_p = _unpack_mask(mpos, n, moved, 0)
    n_r = _unpack_mask(mrot, n, moved, 1)
    n_s = _unpack_mask(mscale, n, moved, 2)
    if n_p < 0 or n_r < 0 or n_s < 0:
        return False, 0, 0, 0, 0
    for j in range(n):
        if not (moved[j, 0] or moved[j, 1] or moved[j, 2]):
            return False, 0, 0, 0, 0
    nw = _unpack_mask(wide_bits, n_p, wide, 0)
    return nw >= 0, n_p, n_r, n_s, nw


_Z3 = np.zeros(3)
_Z256 = np.zeros(256, np.float32)


def decoder_warm() -> None:
    """Compile the decoding kernels for message buffers (read-only uint views)."""
    raw = bytes(64)
    f16_decode_kernel(np.frombuffer(raw, "<u2", 6), np.zeros(6, np.float32))
    out3, out4 = np.zeros((2, 3), np.float32), np.zeros((2, 4), np.float32)
    q13_decode_kernel(np.frombuffer(raw, "<u2", 6), np.frombuffer(raw, "<u4", 2), np.frombuffer(raw, np.uint8, 6),
                      np.zeros(3), np.ones(3), np.ones(256, np.float32), out3, out4, out3.copy())
    one = np.frombuffer(b"\x01", np.uint8)
    unpack_delta_masks_kernel(one, 1, 1, one, one, one, np.frombuffer(b"\x00", np.uint8), np.zeros(1, np.uint32),
                       np.zeros((1, 3), bool), np.zeros((1, 1), bool))
    ids, moved, wide = np.zeros(1, np.uint32), np.ones((1, 3), bool), np.zeros(1, bool)  # ids: a DeltaFrame's index
    res = np.frombuffer(raw, np.int8, 3).reshape(1, 3)
    wpos = np.frombuffer(raw, "<u2", 0).reshape(0, 3)
    for q13 in (True, False):
        rot = np.frombuffer(raw, "<u4", 1).reshape(1, 1) if q13 else np.frombuffer(raw, "<u2", 4).reshape(1, 4)
        scl = np.frombuffer(raw, np.uint8 if q13 else "<u2", 3).reshape(1, 3)
        held_r = np.zeros((1, 1), np.uint32) if q13 else np.zeros((1, 4), np.uint16)
        held_s = np.zeros((1, 3), np.uint8 if q13 else np.uint16)
        delta_apply_kernel(q13, ids, moved, wide, res, wpos, rot, scl, np.zeros((1, 3), np.uint16), held_r, held_s,
                           np.zeros(3), np.ones(3), np.ones(256, np.float32), out3[:1], out4[:1], out3[:1].copy())


class FastFrameDecoder:
    """Decodes the frames of one session (FrameFormat) into float32 buffers owned by the decoder (reused:
    each call overwrites the previous frame's arrays), with the codec's checks (lengths, finiteness, index).
    In a delta session it also keeps the codes the client holds (``delta``) and returns delta frames as
    sparse-like Frames (``index`` = the changed Gaussians). ``ofera_protocol.decode_server_message`` is the
    reference."""

    def __init__(self, fmt: FrameFormat) -> None:
        decoder_warm()  # compiled (or loaded from the on-disk cache) before the first frame
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
        if fmt.delta:  # the masks' buffers, reused (a DeltaFrame holds views until the next frame)
            self._index = np.zeros(n, np.uint32)
            self._moved = np.zeros((n, 3), bool)
            self._wide = np.zeros((n, 1), bool)

    def _masks(self, m: dict, fmt: FrameFormat) -> Any:
        """codec.delta_masks by unpack_delta_masks_kernel into this decoder's buffers; the codec's own on any fault (it
        raises the exact ProtocolError)."""
        from ofera_protocol import _fields as F
        from ofera_protocol.codec import delta_masks
        from ofera_protocol.constants import UINT32_MAX

        w = "frame"
        n = F.get_int(m, "n", w, lo=0, hi=UINT32_MAX)
        bins = [np.frombuffer(F.get_bin(m, k, w), np.uint8) for k in
                ("changed", "moved_position", "moved_rotation", "moved_scale", "wide")]
        ok = n <= fmt.count
        if ok:
            ok, n_p, n_r, n_s, nw = unpack_delta_masks_kernel(bins[0], fmt.count, n, *bins[1:], self._index,
                                                              self._moved, self._wide)
        if not ok:
            return delta_masks(m, fmt)
        return self._index[:n].copy(), self._moved[:n], self._wide[:n_p, 0], (n_p, n_r, n_s, nw)  # index: kept

    def _apply_delta(self, d: DeltaFrame) -> Frame:
        """The numba twin of ofera_protocol.delta.DeltaDecoder.apply (same checks, same values)."""
        from ofera_protocol.errors import BAD_FIELD, NON_FINITE, NOT_READY, ProtocolError

        dd, fmt = self.delta, self.format
        if not dd.has_key:
            raise ProtocolError(NOT_READY, "frame: a delta frame before any key frame (send resync)")
        q13 = fmt.encoding == "q13"
        n = d.n
        p, r, s = self._pos[:n], self._rot[:n], self._scale[:n]
        rot = d.rotation.view(np.uint32).reshape(-1, 1) if q13 else d.rotation.view(np.uint16).reshape(-1, 4)
        scl = d.scale.view(np.uint8 if q13 else np.uint16).reshape(-1, 3)
        held_r = dd.rotation.reshape(-1, 1) if q13 else dd.rotation
        lo, step, lut = (self._lo, self._step, self._lut) if q13 else (_Z3, _Z3, _Z256)
        code = delta_apply_kernel(q13, d.index, d.moved, d.wide, d.position_delta,
                                  d.position.view(np.uint16).reshape(-1, 3), rot, scl, dd.position, held_r, dd.scale,
                                  lo, step, lut, p, r, s)
        if code == 1:
            raise ProtocolError(BAD_FIELD, "frame: 'position_delta' takes a code outside 0..65535")
        if code == 2:
            raise ProtocolError(NON_FINITE, "frame: a position change gives NaN or infinity")
        return Frame(seq=d.seq, t=d.t, timing=d.timing, index=d.index, position=p, rotation=r, scale=s, key=False)

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
        parts = frame_parts(m, fmt, self._masks)  # masks: delta frames only
        if isinstance(parts, DeltaFrame):
            return self._apply_delta(parts)
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
