"""Frames the deformation writes itself (`Source.direct`), for a source whose every frame goes to one wire format's
viewer (a v1 session and its own viewer): no float32 state in between, no encoding pass over it.

- :class:`DirectF16`: a dense f16 session; the deformation writes the frame's half bits into the message buffer
  (``FrameWriter.draft``, ``Pipeline.deform_values_f16``).
- :class:`DirectDeltaFrames`: a delta session (PROTOCOL.md 7.1); the deformation runs the delta encoder's selection
  and encoding passes on what it computes and writes the message body (``direct_delta.DirectDelta``,
  ``Pipeline.deform_values_delta``), and leaves the decodings of what it sent until the frame is delivered. Its key
  frames (join, resync, key interval) take the state path: ``ready()`` is False for them.

Each gives the bytes the state path gives (tested); :func:`direct_writer` picks one for a session, or None.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Protocol

from .pipeline import Pipeline

log = logging.getLogger("ofera.streaming")


class DirectWriter(Protocol):
    """What `Source` asks of a direct writer: `key` (the wire format whose bytes it makes), `ready()` (whether this
    frame can be written so), `deform(pipeline, values)` -> (what `finish` takes, or None for the state path; the
    head and deform durations, us), `finish(written, frame)` -> (the frame's bytes, ns already spent encoding)."""

    key: tuple

    def ready(self) -> bool: ...

    def deform(self, pipeline: Pipeline, values: Any) -> tuple[Any | None, dict[str, int]]: ...

    def finish(self, written: Any, frame: Any) -> tuple[Any, int]: ...


class DirectF16:
    """A dense f16 format's frames written by the deformation (a fast FrameWriter's draft)."""

    def __init__(self, key: tuple, writer: Any) -> None:
        self.key, self.writer = key, writer

    def ready(self) -> bool:
        return True

    def deform(self, pipeline: Pipeline, values: Any) -> tuple[Any | None, dict[str, int]]:
        """The draft with the frame's Gaussians, or None (a value beyond the half range: the state path, whose
        encoding reports it)."""
        n = pipeline.neutral
        draft = self.writer.draft(pipeline.varying, (n.position, n.rotation, n.scale))
        ok, stages = pipeline.deform_values_f16(values, draft, self.writer.psign, self.writer.rsign)
        return (draft if ok else None), stages

    def finish(self, draft: Any, frame: Any) -> tuple[Any, int]:
        return self.writer.finish(draft, frame.seq, frame.t, frame.timing, frame.member), draft.spent_ns


class DirectDeltaFrames:
    """A delta session's delta frames written by the deformation (``direct_delta.DirectDelta``); key frames are
    encoded from the state (``ready()`` False), by the same encoder."""

    def __init__(self, key: tuple, encoder: Any, pipeline: Pipeline) -> None:
        from .direct_delta import DirectDelta

        session = pipeline.fast
        self.key, self.encoder = key, encoder
        # one chunk when the session never runs threads (no gather of chunks), else one a thread
        self.direct = DirectDelta(session.fast, encoder, threads=1 if session.parallel is False else None,
                                  head=session.head_args())

    def ready(self) -> bool:
        return not self.encoder.next_is_key

    def deform(self, pipeline: Pipeline, values: Any) -> tuple[Any, dict[str, int]]:
        """The frame's kernel call; the decodings of what it sent (``DirectDelta.settle``) go to the fast session's
        ``defer`` (the source runs them on the loop's thread once the client has read the frame: roles.AFTER_FRAME_S),
        or to the next frame."""
        written = pipeline.deform_values_delta(values, self.direct)
        defer = pipeline.fast.defer
        if defer is not None:
            defer((self.direct.settle, ()))
        return written

    def finish(self, written: Any, frame: Any) -> tuple[Any, int]:
        """The message whose body the kernel wrote (a ``direct_delta.Written``): its header in front."""
        return self.encoder.encode_written(frame.seq, frame.t, frame.timing, written.counts[0], written.buf,
                                           written.end, time.perf_counter_ns()), 0


def direct_writer(key: tuple, writer: Any, pipeline: Any) -> DirectWriter | None:
    """The direct writer of a session's one wire format, or None where the state path runs: a fast pipeline whose
    kernels write f16 or delta frames (the triangle binding, FLAME values), and a fast writer of dense f16 frames or
    a delta encoder on the numba kernels."""
    if not getattr(pipeline, "writes_f16", False):
        return None
    fmt = getattr(writer, "format", None)
    if fmt is None or fmt.sparse:
        return None
    if fmt.delta:
        from .encode_fast import NumbaKernels

        if not isinstance(getattr(writer, "kernels", None), NumbaKernels):
            return None
        try:
            return DirectDeltaFrames(key, writer, pipeline)
        except ValueError as exc:  # a candidate the fast path does not deform (an avatar's own movable set)
            log.info("delta frames from the state: %s", exc)
            return None
    if fmt.encoding == "f16" and hasattr(writer, "draft") and writer.gather is None:
        return DirectF16(key, writer)
    return None
