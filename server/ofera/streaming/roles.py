"""The two roles of a client, kept apart so that rooms (one source, several viewers) can come later.

- Source: a client whose `bs` drive one avatar. At most one pending bs (newest wins: a bs replaced
  before its computation starts is counted as skipped 'bs'); the pipeline runs in a thread pool, one
  frame at a time per source, so one session's compute never blocks another's I/O. Each result is a
  ComputedFrame handed to every subscriber.
- Viewer: a client that receives an avatar's frames in its own wire format (encoding, coordinates,
  sparse / reduced selection). At most one unsent frame (newest wins: a frame replaced before it was
  handed to the socket is counted as skipped 'frame'); a ComputedFrame is encoded once per wire format
  however many viewers share it. Sending awaits the socket draining (server.py), so a slow client only
  ever has its newest frame queued and never slows anyone else.

In v1 each session is one Source with one Viewer subscribed, for its own avatar. In a room (rooms.py) a Source
has a viewer per member watching it, and a connection watches every member through one RoomViewer.

A source deforms only when some subscriber wants Gaussians (`needs_state`); a viewer whose writer declares
`needs_state = False` (the params encoding) is handed the frame's expression values instead.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, Generic, Protocol, TypeVar

import numpy as np
from ofera_protocol import Blendshapes, Frame, FrameFormat, ProtocolError, encode_frame, to_coords
from ofera_protocol import errors as E

from ..avatar.state import GaussianState
from .compute_pool import offload
from .direct import DirectWriter
from .metrics import Metrics
from .pipeline import Pipeline

log = logging.getLogger("ofera.streaming")

T = TypeVar("T")
SendBytes = Callable[[Any], Awaitable[None]]  # bytes-like


class LatestSlot(Generic[T]):
    """Holds at most one item: `put` replaces what is there (returns True if it replaced something),
    `get` waits for an item and takes it. Event-loop only."""

    def __init__(self) -> None:
        self._item: T | None = None
        self._full = False
        self._event = asyncio.Event()

    def put(self, item: T) -> bool:
        replaced = self._full
        self._item, self._full = item, True
        self._event.set()
        return replaced

    @property
    def full(self) -> bool:
        return self._full

    async def get(self) -> T:
        while not self._full:
            self._event.clear()
            await self._event.wait()
        item, self._item, self._full = self._item, None, False
        return item  # type: ignore[return-value]


@dataclass
class PendingBs:
    bs: Blendshapes
    received_ns: int
    decode_us: int

    @property
    def seq(self) -> int:
        return self.bs.seq


@dataclass
class ComputedFrame:
    """One pipeline result, shared by every viewer of a source; encoded once per wire format."""

    seq: int
    t: int
    state: GaussianState | None  # in FLAME space; None when no subscriber needed Gaussians (values only)
    timing: dict[str, int]
    received_ns: int
    values: np.ndarray | None = None  # the avatar's expression values (68 FLAME values; arkit51: 51 weights)
    member: str | None = None  # rooms: whose avatar (frame.member)
    restate: Callable[[], GaussianState] | None = None  # a frame written with no state (Source.direct): deforms it
    _encoded: dict[tuple, bytes] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def cached(self, key: tuple) -> Any:
        """The bytes of wire format `key` if some viewer made them already, else None (no lock: a dict read)."""
        return self._encoded.get(key)

    def store(self, key: tuple, data: Any) -> None:
        """Record the bytes of wire format `key`, made by the source itself (Source.direct)."""
        with self._lock:
            self._encoded[key] = data

    def forget(self, key: tuple) -> None:
        """Drop the bytes of wire format `key` (made against a state the client no longer matches)."""
        with self._lock:
            self._encoded.pop(key, None)

    def encoded(self, key: tuple, make: Callable[[ComputedFrame], Any]) -> tuple[Any, bool]:
        """Bytes for wire format `key` (made once, by whoever asks first); True if made by this call."""
        with self._lock:
            data = self._encoded.get(key)
            if data is not None:
                return data, False
            data = self._encoded[key] = make(self)
            return data, True


class SessionFatal(Exception):
    """Ends the session with a fatal protocol error."""

    def __init__(self, err: ProtocolError) -> None:
        super().__init__(str(err))
        self.err = err


AFTER_FRAME_S = 0.002
"""How long after a frame is delivered the source of a session alone on its server runs the work the frame left for
later (``Source._after``), unless the next frame starts first: a client on this machine decodes a 150 kB delta frame
in about 0.6 ms (round nineteen). With other sessions the work runs at once: their frames share the loop (four
compact sessions' p99 5.6 / 7.2 -> 7.3 / 8.0 ms with the delay)."""


class Source:
    """Client role 1: its bs drive one avatar's pipeline (newest bs wins). Publishes ComputedFrames."""

    def __init__(self, pipeline: Pipeline, executor: Executor, metrics: Metrics) -> None:
        self.pipeline = pipeline
        self.executor = executor
        self.metrics = metrics
        self.slot: LatestSlot[PendingBs] = LatestSlot()
        self.subscribers: list[Callable[[ComputedFrame], None]] = []
        # Demand: None computes every bs it can; otherwise the next bs is computed only once demand() is true
        # (some viewer has no unsent frame), so that a client that stopped reading costs no computation: its
        # bs replace each other in the slot. Viewers call wake() when they take a frame.
        self.demand: Callable[[], bool] | None = None
        # needs_state: None or True-returning: deform (map + deform_values); False: map only (no subscriber wants
        # Gaussians now: params viewers, or only the bus, or every Gaussian viewer has an unsent frame).
        self.needs_state: Callable[[], bool] | None = None
        self.member: str | None = None  # rooms: stamped on every frame
        self.on_values: Callable[[ComputedFrame], None] | None = None  # rooms: each frame's values, to the bus
        # Wire formats encoded in the compute thread right after the deformation, (key, make) as in
        # ComputedFrame.encoded: the state is still in cache and the viewer needs no second hop to the pool.
        # A delta format (its encoder advances per frame handed to a socket) only where every computed frame is
        # handed to its viewer's socket: a solo session, whose demand holds the computing while the slot is full.
        self.eager: list[tuple[tuple, Callable[[ComputedFrame], Any]]] = []
        # A wire format whose frames the deformation writes itself, with no float32 state in between (direct.py:
        # dense f16, or a delta session's delta frames); such frames carry no state. Only for a source whose every
        # frame goes to viewers of that one format (a v1 session and its own viewer).
        self.direct: DirectWriter | None = None
        # in_loop: None or False-returning: frames are computed on the pool; True: this frame on the event loop's
        # thread, no hand-off to the pool and back (a session alone on its server: Session sets it).
        self.in_loop: Callable[[], bool] | None = None
        self._wake = asyncio.Event()
        self.skipped = 0
        self.computed = 0
        # Work a frame does not wait for, (fn, args), run once it is delivered (a session alone: AFTER_FRAME_S
        # later) or before the next frame is computed, whichever comes first (_run_after): a direct frame's encode
        # histogram, the fast session's thread-choice record, a delta frame's decodings (DirectDelta.settle); appended
        # from the compute thread (deque appends are atomic). A cold histogram observation took 17 us p50, a record
        # 8.5-16 (benchmarks/README.md, round sixteen), a settle 276 (round eighteen).
        self._after: deque[tuple[Callable[..., Any], tuple]] = deque()
        self._after_timer: asyncio.Handle | None = None
        # alone: None or False-returning: that work runs at once (other sessions' frames share the loop); True: it
        # waits AFTER_FRAME_S for this session's client to read the frame (a session alone on its server: Session).
        self.alone: Callable[[], bool] | None = None
        fast = getattr(pipeline, "fast", None)
        if fast is not None and hasattr(fast, "defer"):
            fast.defer = self._after.append

    def wake(self) -> None:
        self._wake.set()

    def offer(self, pending: PendingBs) -> None:
        if self.slot.put(pending):
            self.skipped += 1
            self.metrics.skipped_bs.inc()

    def _compute(self, p: PendingBs) -> ComputedFrame:
        start = time.monotonic_ns()
        conf = p.bs.conf  # optional face confidence: passed only when sent (pipeline stand-ins take w alone)
        hold = getattr(self.pipeline, "hold", None)  # streaming.confidence.RegionHold (not on stand-ins)
        held = hold.held if hold is not None else 0
        args = (p.bs.w,) if conf is None else (p.bs.w, conf)
        state: GaussianState | None = None
        written = None
        if self.needs_state is not None and not self.needs_state():
            values, stages = self.pipeline.map(*args)
        elif self.direct is not None and self.direct.ready():
            values, stages = self.pipeline.map(*args)
            written, deformed = self.direct.deform(self.pipeline, values)
            if written is None:  # the kernel could not write it: the state, whose encoding reports why
                state, deformed = self.pipeline.deform_values(values)
            stages = {**stages, **deformed}
        else:
            state, stages = self.pipeline.run(*args)
            values = getattr(self.pipeline, "values", None)
        if hold is not None and hold.held != held:
            self.metrics.conf_held.inc()
        end = time.monotonic_ns()
        # PROTOCOL.md section 9 names (`map` = layout adapter + BDA), plus the pipeline's own stages.
        timing = {"decode": p.decode_us, "queue": (start - p.received_ns) // 1000, **stages}
        if "layout" in stages and "bda" in stages:
            timing["map"] = stages["layout"] + stages["bda"]
        timing["total"] = (end - p.received_ns) // 1000
        frame = ComputedFrame(p.bs.seq, p.bs.t, state, timing, p.received_ns, values, self.member)
        if written is not None:
            t0 = time.perf_counter_ns()
            data, spent_ns = self.direct.finish(written, frame)
            frame.store(self.direct.key, data)
            frame.restate = lambda: self.pipeline.deform_values(values)[0]
            seconds = (spent_ns + time.perf_counter_ns() - t0) * 1e-9
            self._after.append((self.metrics.stage_of("encode").observe, (seconds,)))
        elif state is not None:
            self._encode_eagerly(frame)
        return frame

    def _encode_eagerly(self, frame: ComputedFrame) -> None:
        """Make the `eager` wire formats of `frame` now. A format that fails is left to its viewer, whose own
        encoding then raises the error the session reports (one error path for every format)."""
        for key, make in self.eager:
            try:
                encode_timed(frame, key, make, self.metrics)
            except Exception:
                log.debug("eager encoding of frame %d failed; its viewer retries", frame.seq, exc_info=True)

    def _failed(self, pending: Any, exc: Exception) -> None:
        """The pipeline raised on `pending`: end the session (a remote source logs and goes on instead)."""
        log.exception("pipeline failed on bs %d", pending.seq)
        raise SessionFatal(ProtocolError(E.INTERNAL, f"the server failed computing bs {pending.seq}: "
                                         f"{type(exc).__name__}; please report it", True)) from exc

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            while self.demand is not None and not self.demand():
                self._wake.clear()
                await self._wake.wait()
            pending = await self.slot.get()
            self._run_after()  # (the last frame's, if its time has not come: before this frame's kernels need it)
            try:
                if self.needs_state is not None and not self.needs_state():
                    frame = self._compute(pending)  # map only (~0.05 ms): cheaper here than a hop to the pool
                elif self.in_loop is not None and self.in_loop():
                    frame = self._compute(pending)  # nothing else to serve meanwhile: the hops cost more
                else:
                    frame = await offload(self.executor, self._compute, pending)
            except Exception as exc:
                self._failed(pending, exc)
                continue
            self.computed += 1
            if self.on_values is not None and frame.values is not None:
                self.on_values(frame)
            for deliver in list(self.subscribers):
                deliver(frame)
            # The metrics after the viewers' tasks (woken above) have written the frame: on a cold CPU the
            # histograms' Python code costs about 0.1 ms a frame (benchmarks/cold_cache.py). The rest later still,
            # once the client has read the frame: it would run on the loop's thread, where the kernel's wake-up of a
            # client reading a local socket often puts the client too (benchmarks/README.md, round nineteen).
            loop.call_soon(self._account, frame.timing)
            if self._after and self._after_timer is None:
                alone = self.alone is not None and self.alone()
                self._after_timer = (loop.call_later(AFTER_FRAME_S, self._run_after) if alone
                                     else loop.call_soon(self._run_after))

    def _account(self, timing: dict[str, int]) -> None:
        self.metrics.frames_computed.inc()
        self.metrics.observe_timings(timing)

    def _run_after(self) -> None:
        """Run the work frames left for later (``_after``), now."""
        if self._after_timer is not None:
            self._after_timer.cancel()
            self._after_timer = None
        while self._after:
            fn, args = self._after.popleft()
            fn(*args)


class FrameEncoder(Protocol):
    """What a Viewer encodes frames with: :class:`CodecWriter` (the reference),
    ``ofera_protocol.fast_encodings.FrameWriter`` (numba kernels, the same bytes) or, in a delta session,
    ``ofera_protocol.delta.DeltaEncoder``. The result is bytes or a pooled memoryview (not reused while referenced)."""

    def encode(self, seq: int, t: int, timing: dict[str, int], position: np.ndarray, rotation: np.ndarray,
               scale: np.ndarray) -> bytes | memoryview: ...


def encode_timed(frame: ComputedFrame, key: tuple, make: Callable[[ComputedFrame], Any], metrics: Metrics) -> Any:
    """`frame`'s bytes in wire format `key` (made by `make` once, by whoever asks first); the making is observed as
    the `encode` stage."""
    t0 = time.perf_counter_ns()
    data, made = frame.encoded(key, make)
    if made:
        metrics.stage_of("encode").observe((time.perf_counter_ns() - t0) * 1e-9)
    return data


def encode_computed(writer: Any, frame: ComputedFrame) -> bytes | memoryview:
    """`frame` through `writer`: its expression values for a writer with `needs_state = False` (params), else its
    Gaussians (with `member` in a room: CodecWriter and the fast FrameWriter take it)."""
    if not getattr(writer, "needs_state", True):
        return writer.encode_values(frame.seq, frame.t, frame.timing, frame.values, frame.member)
    s = frame.state
    if s is None:
        raise RuntimeError(f"frame {frame.seq} was not deformed but a viewer needs its Gaussians")
    extra: dict[str, Any] = {} if frame.member is None else {"member": frame.member}
    varying = getattr(s, "varying", None)
    if varying is not None and getattr(writer, "takes_varying", False):
        extra["varying"] = varying  # only the rows the fast path deformed are encoded again
    return writer.encode(frame.seq, frame.t, frame.timing, s.position, s.rotation, s.scale, **extra)


class CodecWriter:
    """The reference frame encoder of one wire format: gather, `to_coords`, `codec.encode_frame`.
    Same interface as `ofera_protocol.fast_encodings.FrameWriter`, which produces identical bytes."""

    def __init__(self, fmt: FrameFormat, coords: str = "flame", gather: np.ndarray | None = None,
                 index: np.ndarray | None = None) -> None:
        self.format, self.coords, self.gather, self.index = fmt, coords, gather, index

    def encode(self, seq: int, t: int, timing: dict[str, int], position: np.ndarray, rotation: np.ndarray,
               scale: np.ndarray, member: str | None = None) -> bytes:
        if self.gather is not None:
            position, rotation, scale = position[self.gather], rotation[self.gather], scale[self.gather]
        position, rotation = to_coords(position, rotation, self.coords)
        return encode_frame(Frame(seq=seq, t=t, position=position, rotation=rotation, scale=scale,
                                  index=self.index, timing=timing, member=member), self.format)


class Viewer:
    """Client role 2: receives an avatar's frames in its own wire format (newest unsent frame wins).

    `writer` encodes a frame of this viewer's wire format (a `FrameEncoder`: CodecWriter, the numba FrameWriter of
    `encode_fast`, or a delta session's DeltaEncoder); `key` names that format: viewers with equal keys share one
    encoding per frame."""

    def __init__(self, send: SendBytes, writer: FrameEncoder, key: tuple, executor: Executor, metrics: Metrics
                 ) -> None:
        self.send = send
        self.writer = writer
        self.key = key
        self.executor = executor
        self.metrics = metrics
        self.slot: LatestSlot[ComputedFrame] = LatestSlot()
        self.on_ready: Callable[[], None] | None = None  # called when the slot empties (Source.wake)
        self.sent = 0
        self.skipped = 0

    def offer(self, frame: ComputedFrame) -> None:
        if self.slot.put(frame):
            self.skipped += 1
            self.metrics.skipped_frame.inc()
            self._replaced(frame)

    def _replaced(self, frame: ComputedFrame) -> None:
        """An unsent frame was just replaced by `frame`. A delta writer that encoded both eagerly (in the compute
        thread) holds codes the client will never get, and `frame`'s bytes were made against them: `frame` is
        encoded again, here, as a key frame. Here, on the loop and before its source's next computation, no other
        encoding of this writer can run, so its frames stay in the order they are sent. A frame the deformation wrote
        is deformed again from its values first (its source is between computations here). A solo session never
        gets here (its source computes only while the slot is empty); this keeps a client right wherever it would."""
        request_key = getattr(self.writer, "request_key", None)
        if request_key is not None and frame.cached(self.key) is not None:
            request_key()
            frame.forget(self.key)
            if frame.state is None and frame.restate is not None:  # written by the deformation (Source.direct)
                frame.state = frame.restate()
            encode_timed(frame, self.key, self.make, self.metrics)

    def make(self, frame: ComputedFrame) -> bytes | memoryview:
        """This viewer's wire format of `frame` (no cache)."""
        return encode_computed(self.writer, frame)

    def _encode(self, frame: ComputedFrame) -> bytes:
        return encode_timed(frame, self.key, self.make, self.metrics)

    async def run(self) -> None:
        while True:
            frame = await self.slot.get()
            if self.on_ready is not None:
                self.on_ready()
            try:  # bytes, or a pooled memoryview (not reused while referenced)
                data = frame.cached(self.key)  # made in the compute thread (Source.eager), else now
                if data is None and getattr(self.writer, "needs_state", True):
                    data = await offload(self.executor, self._encode, frame)
                elif data is None:  # params (~0.01 ms): cheaper here than a hop to the pool
                    data = self._encode(frame)
            except Exception as exc:
                log.exception("encoding frame %d failed", frame.seq)
                raise SessionFatal(ProtocolError(E.INTERNAL, f"the server failed encoding frame {frame.seq}: "
                                                 f"{type(exc).__name__}", True)) from exc
            await self.send(data)
            self.sent += 1
            self.metrics.frames_out.inc()
            self.metrics.bytes_out.inc(len(data))
            self.metrics.server_latency.observe((time.monotonic_ns() - frame.received_ns) * 1e-9)
