"""Encode a frame straight into its outgoing message buffer (numpy + msgpack only; kernels pluggable).

:func:`codec.encode_frame` builds the three encoded arrays, then joins them with the msgpack header
(two full copies of the payload, plus gather / mirror copies in the caller). :class:`FrameWriter`
instead lays the message out once per frame and lets a *kernel* read the server's float32 state and
write each encoded field directly into its place in one buffer, selecting the frame's Gaussians
(`gather`) and mirroring coordinates on the way. The bytes are identical to
``encode_frame(Frame(...), fmt)`` after ``to_coords`` and the gather (tests check it).

Kernels are a :class:`FrameKernels`, five methods (:class:`NumpyKernels` is the plain numpy one; every value is
finite float32 state, the frame's Gaussians are ``src[gather]``, times ``sign`` per component):

    f32(src (N, k) f32, gather (M,) int64 | None, sign (k,) f32, dst (M k,) f32) -> bool finite
    f16(src, gather, sign, dst (M k,) uint16 [IEEE half bits])             -> bool finite, |x| <= 65504
    q13_position(src (N, 3), gather, sign (3,), lo (3,) f64, k (3,) f64, dst (M 3,) uint16)
                 [q = clip(rint((float64(p) - lo) * k), 0, 65535), see :func:`position_factors`]
    q13_rotation(src (N, 4), gather, sign (4,), dst (M,) uint32)
    q13_scale(src (N, 3), gather, thresholds (255,) f32, dst (M 3,) uint8)
    f32_rows / f16_rows(src (N, k), rows: VaryingRows, sign, dst (N k,)) -> bool  [only the rows of `rows`;
                 the others of dst are left as they are]
    (and, for :class:`.delta.DeltaEncoder`, delta_q13 / delta_f16: see :class:`.delta.ReferenceKernels`)

The protocol package stays importable with numpy and msgpack only: the numba kernels live in the
server (``ofera.streaming.encode_fast.numba_kernels()``), which passes them in.

q13 scales are encoded by threshold search: :func:`scale_thresholds` finds, with the reference
quantiser itself, the smallest float32 scale of every code 1..255, so a kernel reproduces the
reference's float32 logarithm bit for bit without computing one (valid because the quantiser is
monotonic in the scale).

Buffers come from a small pool: a returned ``memoryview`` is not reused while it (or anything made from
it) is still referenced, so it can be cached and sent later; a steady stream allocates nothing.

Rows that do not change: a caller whose states leave most rows the same from frame to frame (the fast
deformation keeps every Gaussian no expression moves at its neutral value) passes ``varying``, a
:class:`VaryingRows` object it attaches to all such states. A pooled buffer that last held a dense f16 or f32
frame encoded with the same object keeps its other rows, so only the varying ones are encoded again (fewer
bytes read and written: the encode is bound by memory traffic). The bytes are those of a full encode.
:meth:`FrameWriter.draft` goes one step further for dense f16: it hands out such a buffer's fields, and the
caller's own kernel writes the varying rows straight into them (the fast deformation does, with no float32
state in between); :meth:`FrameWriter.finish` writes the header.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import msgpack
import numpy as np

from .encodings import (
    POS_LEVELS,
    SCALE_LEVELS,
    FrameFormat,
    pack_smallest_three,
    quantize_log_scale,
    quantize_positions_lk,
)
from .messages import Quant

_SIGN = {"flame": (np.ones(3, np.float32), np.ones(4, np.float32)),
         "unity": (np.array([-1, 1, 1], np.float32), np.array([1, -1, -1, 1], np.float32))}
_ONES3 = np.ones(3, np.float32)
F16_MAX = 65504.0
F32_MAX = float(np.finfo(np.float32).max)


def coord_signs(coords: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-component factors (position (3,), rotation (4,)) that express FLAME values in `coords`."""
    if coords not in _SIGN:
        raise ValueError(f"unknown coords {coords!r}; expected one of {tuple(_SIGN)}")
    return _SIGN[coords]


def position_factors(quant: Quant) -> tuple[np.ndarray, np.ndarray]:
    """(lo, k) float64 of the reference position quantiser: q = rint((p - lo) * k)."""
    lo = quant.pos_min.astype(np.float64)
    return lo, POS_LEVELS / (quant.pos_max.astype(np.float64) - lo)


def scale_thresholds(quant: Quant) -> np.ndarray:
    """(255,) float32: entry c-1 is the smallest positive float32 scale the reference quantiser
    (:func:`encodings.quantize_log_scale`) maps to a code >= c. A scale's code is the number of
    entries <= it (0 for zero, negative and NaN scales)."""
    target = np.arange(1, SCALE_LEVELS + 1)
    lo = np.zeros(SCALE_LEVELS, np.int64)  # bits of +0.0: code 0
    hi = np.full(SCALE_LEVELS, 0x7F800000, np.int64)  # bits of +inf: code 255
    while True:  # binary search on the bit patterns of positive floats (monotonic in the value)
        open_ = hi - lo > 1
        if not open_.any():
            break
        mid = (lo + hi) // 2
        vals = mid.astype(np.uint32).view(np.float32)
        codes = quantize_log_scale(np.repeat(vals, 3).reshape(-1, 3), quant)[:, 0].astype(np.int64)
        up = codes >= target
        hi = np.where(open_ & up, mid, hi)
        lo = np.where(open_ & ~up, mid, lo)
    return hi.astype(np.uint32).view(np.float32).copy()


class VaryingRows:
    """The rows that may differ between the states that carry this object (its identity is the contract: outside
    these rows, every state carrying it holds the same values). start, length (R,) int64: ascending disjoint
    spans; indices (M,) int64: the rows themselves."""

    __slots__ = ("start", "length", "indices")

    def __init__(self, rows: np.ndarray) -> None:
        rows = np.unique(np.asarray(rows, np.int64).reshape(-1))
        if rows.size and rows[0] < 0:
            raise ValueError("varying rows must be non-negative")
        brk = np.flatnonzero(np.diff(rows) != 1) + 1
        start = np.concatenate([[0], brk]).astype(np.int64) if rows.size else np.zeros(0, np.int64)
        self.indices = rows
        self.start = rows[start] if rows.size else start
        self.length = np.diff(np.concatenate([start, [rows.size]])).astype(np.int64) if rows.size else start

    def __len__(self) -> int:
        return int(self.indices.size)

    def end(self) -> int:
        """One past the last row (0 if none)."""
        return int(self.indices[-1]) + 1 if self.indices.size else 0


class FrameKernels(Protocol):
    """The kernel interface of :class:`FrameWriter` (the module docstring says each method's contract)."""

    def f32(self, src: np.ndarray, gather: np.ndarray | None, sign: np.ndarray, dst: np.ndarray) -> bool: ...

    def f16(self, src: np.ndarray, gather: np.ndarray | None, sign: np.ndarray, dst: np.ndarray) -> bool: ...

    def q13_position(self, src: np.ndarray, gather: np.ndarray | None, sign: np.ndarray, lo: np.ndarray,
                     k: np.ndarray, dst: np.ndarray) -> None: ...

    def q13_rotation(self, src: np.ndarray, gather: np.ndarray | None, sign: np.ndarray, dst: np.ndarray) -> None: ...

    def q13_scale(self, src: np.ndarray, gather: np.ndarray | None, thresholds: np.ndarray,
                  dst: np.ndarray) -> None: ...

    def f32_rows(self, src: np.ndarray, rows: VaryingRows, sign: np.ndarray, dst: np.ndarray) -> bool: ...

    def f16_rows(self, src: np.ndarray, rows: VaryingRows, sign: np.ndarray, dst: np.ndarray) -> bool: ...


class NumpyKernels:
    """The reference frame kernels: the functions of :mod:`.encodings` (plain numpy, the spec in code) behind the
    kernel signatures (:class:`.delta.ReferenceKernels` adds the delta kernels); the server's numba set
    (``ofera.streaming.encode_fast.NumbaKernels``) has the same signatures and is tested byte for byte against it."""

    @staticmethod
    def _take(src: np.ndarray, gather: np.ndarray | None, sign: np.ndarray) -> np.ndarray:
        a = np.asarray(src if gather is None else src[gather], np.float32)
        return a if (sign == 1).all() else a * sign

    def f32(self, src, gather, sign, dst) -> bool:
        a = self._take(src, gather, sign)
        if a.size and not (-F32_MAX <= a.min() and a.max() <= F32_MAX):
            return False
        dst[...] = a.reshape(-1)
        return True

    def f16(self, src, gather, sign, dst) -> bool:
        a = self._take(src, gather, sign)
        if a.size and not (-F16_MAX <= a.min() and a.max() <= F16_MAX):
            return False
        dst[...] = a.reshape(-1).astype("<f2").view(np.uint16)
        return True

    def f32_rows(self, src, rows, sign, dst) -> bool:
        a = self._take(src, rows.indices, sign)
        if a.size and not (-F32_MAX <= a.min() and a.max() <= F32_MAX):
            return False
        dst.reshape(-1, src.shape[1])[rows.indices] = a
        return True

    def f16_rows(self, src, rows, sign, dst) -> bool:
        a = self._take(src, rows.indices, sign)
        if a.size and not (-F16_MAX <= a.min() and a.max() <= F16_MAX):
            return False
        dst.reshape(-1, src.shape[1])[rows.indices] = a.astype("<f2").view(np.uint16)
        return True

    def q13_position(self, src, gather, sign, lo, k, dst) -> None:
        dst[...] = quantize_positions_lk(self._take(src, gather, sign), lo, k).reshape(-1)

    def q13_rotation(self, src, gather, sign, dst) -> None:
        dst[...] = pack_smallest_three(self._take(src, gather, sign))

    def q13_scale(self, src, gather, thresholds, dst) -> None:
        # The reference quantiser tabulated: thresholds[c-1] is its smallest scale of code c (scale_thresholds).
        s = np.asarray(src if gather is None else src[gather], np.float32).reshape(-1)
        code = np.searchsorted(thresholds, s, side="right")
        code[np.isnan(s)] = 0
        dst[...] = code.astype(np.uint8)


def _bin_header(n: int) -> bytes:
    if n < 0x100:
        return b"\xc4" + n.to_bytes(1, "big")
    if n < 0x10000:
        return b"\xc5" + n.to_bytes(2, "big")
    return b"\xc6" + n.to_bytes(4, "big")


_PACK = msgpack.Packer(use_bin_type=True)


class BufferPool:
    """bytearrays (or what ``make(nbytes)`` makes: a buffer of at least that many bytes) handed out as memoryviews and
    reused once nothing references them (thread-safe)."""

    def __init__(self, size: int = 4, make: Callable[[int], Any] = bytearray) -> None:
        self.size = size
        self._make = make
        self._bufs: list[bytearray] = []
        self._idle: list[int] = []
        self._lock = threading.Lock()
        self.unpooled = 0

    @staticmethod
    def _count(bufs: list[bytearray], i: int) -> int:
        return sys.getrefcount(bufs[i])

    def get(self, nbytes: int) -> bytearray:
        return self.get_slot(nbytes)[0]

    def get_slot(self, nbytes: int) -> tuple[bytearray, int | None, bool]:
        """(buffer of at least `nbytes`, its slot in the pool or None if unpooled, whether it is new: a reused
        buffer still holds what was last written into it)."""
        with self._lock:
            for i in range(len(self._bufs)):
                if self._count(self._bufs, i) == self._idle[i]:
                    fresh = len(self._bufs[i]) < nbytes
                    if fresh:
                        self._bufs[i] = self._make(nbytes + (nbytes >> 4))
                        self._idle[i] = self._count(self._bufs, i)
                    return self._bufs[i], i, fresh
            if len(self._bufs) < self.size:
                self._bufs.append(self._make(nbytes + (nbytes >> 4)))
                self._idle.append(self._count(self._bufs, len(self._bufs) - 1))
                return self._bufs[-1], len(self._bufs) - 1, True
            self.unpooled += 1
            return self._make(nbytes), None, True


@dataclass(eq=False)
class FrameDraft:
    """A pooled buffer laid out for one dense f16 frame (:meth:`FrameWriter.draft`): the fields position (N 3,),
    rotation (N 4,), scale (N 3,) as uint16 views (IEEE half bits, wire coordinates, rows in state order) for the
    caller to write the varying rows into; the header goes before `slack`."""

    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    varying: VaryingRows
    buf: bytearray
    slot: int | None
    slack: int
    total: int
    spent_ns: int  # time draft() took


class FrameWriter:
    """Encodes the frames of one wire format (FrameFormat + coords + selection) into pooled buffers.

    gather: (M,) int64 rows of the server state a frame carries (None: all, dense); index: the wire
    `index` (M,) uint32 of a sparse session (None: dense frames). kernels: see the module docstring
    (default: :class:`NumpyKernels`).
    """

    takes_varying = True  # encode(..., varying=) (see the module docstring)

    def __init__(self, fmt: FrameFormat, coords: str = "flame", gather: np.ndarray | None = None,
                 index: np.ndarray | None = None, kernels: FrameKernels | None = None, pool: int = 4,
                 stamp_encode: bool = False) -> None:
        self.format = fmt
        self.stamp_encode = stamp_encode  # timing["encode"] = this call's own duration (us), see encode()
        self.coords = coords
        self.kernels = kernels if kernels is not None else NumpyKernels()
        self.gather = None if gather is None else np.ascontiguousarray(gather, np.int64)
        self.n = fmt.count if gather is None else int(self.gather.shape[0])
        if index is not None:
            if not fmt.sparse:
                raise ValueError("an index needs a sparse session")
            index = np.ascontiguousarray(index, "<u4")
            if index.shape != (self.n,):
                raise ValueError(f"index has shape {index.shape}, the frame carries {self.n} Gaussians")
        elif self.n != fmt.count:
            raise ValueError(f"a dense frame carries all {fmt.count} Gaussians, the selection has {self.n}")
        self.index = index
        self.psign, self.rsign = coord_signs(coords)
        if fmt.encoding == "q13":
            assert fmt.quant is not None
            self.lo, self.k = position_factors(fmt.quant)
            self.thresholds = scale_thresholds(fmt.quant)
        self._sizes = [self.n * b for b in _FIELD_BYTES[fmt.encoding]]
        tail = b""
        if index is not None:
            tail += _PACK.pack("index") + _bin_header(index.nbytes)
        self._index_prefix = tail
        self._field_heads = [_PACK.pack(name) + _bin_header(size)
                             for name, size in zip(("position", "rotation", "scale"), self._sizes)]
        self.pool = BufferPool(pool)
        self._fields_bytes = sum(len(h) for h in self._field_heads) + sum(self._sizes)  # every frame's, after `n`
        self._held: dict[int, tuple[int, VaryingRows]] = {}  # pool slot -> (slack, varying) of the frame it holds
        self.partial = 0  # frames whose varying rows alone were encoded

    def header(self, seq: int, t: int, timing: dict[str, int], member: str | None = None) -> bytes:
        keys = (9 if self.index is not None else 8) + (member is not None)
        who = b"" if member is None else _PACK.pack("member") + _PACK.pack(member)  # rooms: right after `type`
        return b"".join((bytes([0x80 | keys]), _PACK.pack("type"), _PACK.pack("frame"), who, _PACK.pack("seq"),
                         _PACK.pack(seq), _PACK.pack("t"), _PACK.pack(t), _PACK.pack("timing"), _PACK.pack(timing),
                         _PACK.pack("n"), _PACK.pack(self.n)))

    def encode(self, seq: int, t: int, timing: dict[str, int], position: np.ndarray, rotation: np.ndarray,
               scale: np.ndarray, member: str | None = None, varying: VaryingRows | None = None) -> memoryview:
        """The frame message for FLAME-space float32 state arrays (N, 3), (N, 4), (N, 3); `member`: a room's frame.
        ValueError if f32/f16 values are non-finite or out of the half range (like encode_frame).
        With `stamp_encode`, the header's timing also carries "encode": the microseconds this call took up to
        writing the header (the bytes are those of encode_frame with that timing). `varying`: the state's
        :class:`VaryingRows` (dense f16 and f32: only those rows are encoded into a buffer that holds a frame
        encoded with the same object; other encodings ignore it)."""
        start_ns = time.perf_counter_ns()
        head = self.header(seq, t, timing, member)
        # Everything after `timing` has a fixed size: lay it out after room for the longest header, so that the
        # header can be written last, ending where it must, once the encode time it may carry is known. The room
        # is rounded up, so that a pooled buffer's fields usually stay where they were (see `varying`).
        need = len(head) + (_ENCODE_STAMP_BYTES if self.stamp_encode else 0)
        body = self._fields_bytes
        if self.index is not None:
            body += len(self._index_prefix) + self.index.nbytes
        room = -(-need // _SLACK_STEP) * _SLACK_STEP
        buf, slot, fresh = self.pool.get_slot(room + body)
        held = None if fresh or slot is None else self._held.pop(slot, None)
        rows = varying if (varying is not None and self.gather is None and self.format.encoding != "q13") else None
        if rows is not None and held is not None and held[1] is rows and held[0] >= need:
            slack = held[0]  # the buffer holds a frame of the same varying rows, laid out the same way
            self.partial += 1
        else:
            held = None
            slack = room
        total = slack + body
        mv = memoryview(buf)
        off = slack
        if self.index is not None:
            p = self._index_prefix
            mv[off:off + len(p)] = p
            off += len(p)
            mv[off:off + self.index.nbytes] = self.index.view(np.uint8)
            off += self.index.nbytes
        views = []
        for h, size in zip(self._field_heads, self._sizes):
            mv[off:off + len(h)] = h
            off += len(h)
            views.append((off, size))
            off += size
        enc = self.format.encoding
        kern = self.kernels
        (po, ps), (ro, rs), (so, ss) = views
        if enc == "q13":
            kern.q13_position(position, self.gather, self.psign, self.lo, self.k,
                              np.frombuffer(buf, np.uint16, ps // 2, po))
            kern.q13_rotation(rotation, self.gather, self.rsign, np.frombuffer(buf, np.uint32, rs // 4, ro))
            kern.q13_scale(scale, self.gather, self.thresholds, np.frombuffer(buf, np.uint8, ss, so))
        else:
            if held is not None:
                fn, dt = (kern.f32_rows, np.float32) if enc == "f32" else (kern.f16_rows, np.uint16)
            else:
                fn, dt = (kern.f32, np.float32) if enc == "f32" else (kern.f16, np.uint16)
            which = rows if held is not None else self.gather
            width = np.dtype(dt).itemsize
            for name, src, sign, (o, size) in (("position", position, self.psign, (po, ps)),
                                               ("rotation", rotation, self.rsign, (ro, rs)),
                                               ("scale", scale, _ONES3, (so, ss))):
                if not fn(src, which, sign, np.frombuffer(buf, dt, size // width, o)):
                    limit = F16_MAX if enc == "f16" else F32_MAX
                    raise ValueError(f"{name} has NaN, infinity or values beyond +-{limit:g} ({enc})")
        if rows is not None and slot is not None:
            self._held[slot] = (slack, rows)
        if self.stamp_encode:
            timing = {**timing, "encode": (time.perf_counter_ns() - start_ns) // 1000}
            head = self.header(seq, t, timing, member)
        begin = slack - len(head)
        mv[begin:slack] = head
        return mv[begin:total]


    def draft(self, varying: VaryingRows, base: tuple[np.ndarray, np.ndarray, np.ndarray]) -> FrameDraft:
        """A dense f16 frame to be written by the caller: a pooled buffer whose fields hold, outside `varying`, the
        encoding of `base` (FLAME-space float32 position, rotation, scale: what every state carrying `varying`
        holds there; encoded now unless the buffer holds a frame of the same `varying` already). The caller
        writes the varying rows (half bits of its values in this writer's coordinates: `psign`, `rsign`), then
        calls :meth:`finish`. ValueError for other formats, or if `base` is out of the half range."""
        start_ns = time.perf_counter_ns()
        if self.format.encoding != "f16" or self.gather is not None:
            raise ValueError(f"a draft is a dense f16 frame, this writer makes {self.format.encoding} "
                             f"{'sparse' if self.gather is not None else 'dense'} frames")
        buf, slot, fresh = self.pool.get_slot(HEADER_ROOM + self._fields_bytes)
        held = None if fresh or slot is None else self._held.pop(slot, None)
        slack = held[0] if held is not None and held[1] is varying else HEADER_ROOM
        mv = memoryview(buf)
        off = slack
        fields = []
        for h, size in zip(self._field_heads, self._sizes):
            mv[off:off + len(h)] = h
            off += len(h)
            fields.append(np.frombuffer(buf, np.uint16, size // 2, off))
            off += size
        if held is None or held[1] is not varying:
            for name, src, sign, dst in zip(("position", "rotation", "scale"), base,
                                            (self.psign, self.rsign, _ONES3), fields):
                if not self.kernels.f16(src, None, sign, dst):
                    raise ValueError(f"base {name} has NaN, infinity or values beyond +-{F16_MAX:g} (f16)")
        return FrameDraft(*fields, varying, buf, slot, slack, off, time.perf_counter_ns() - start_ns)

    def finish(self, draft: FrameDraft, seq: int, t: int, timing: dict[str, int], member: str | None = None
               ) -> memoryview:
        """The message of a :meth:`draft` whose varying rows the caller wrote: its header written (with
        `stamp_encode`, timing["encode"] = the microseconds draft() took). A draft is finished at
        most once; one never finished (its writer failed) leaves its buffer to be laid out afresh."""
        if self.stamp_encode:
            timing = {**timing, "encode": draft.spent_ns // 1000}
        head = self.header(seq, t, timing, member)
        begin = draft.slack - len(head)
        if begin < 0:  # a header longer than the room the draft left (not seen): one copy of the message
            return memoryview(bytes(head) + bytes(memoryview(draft.buf)[draft.slack:draft.total]))
        mv = memoryview(draft.buf)
        mv[begin:draft.slack] = head
        if draft.slot is not None:
            self._held[draft.slot] = (draft.slack, draft.varying)
        return mv[begin:draft.total]


HEADER_ROOM = 512
"""Room for a frame's header before fields written first (a draft's, a delta frame's; bytes): a header is under 300."""

_SLACK_STEP = 64
"""Header room is a multiple of this (bytes): headers of one stream differ by a few bytes."""


_ENCODE_STAMP_BYTES = len(_PACK.pack("encode")) + 9 + 2
"""Most bytes an "encode" timing entry adds to a header: its key, a msgpack integer (up to 9 bytes), and 2 if the
timing map grows from 15 to 16 entries (fixmap -> map16)."""


_FIELD_BYTES = {"f32": (12, 16, 12), "f16": (6, 8, 6), "q13": (6, 4, 3)}
