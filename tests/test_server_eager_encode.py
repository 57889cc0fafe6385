"""Eager encoding (`Source.eager`): a v1 session's wire format is encoded in the compute thread right after the
deformation, so that its Viewer finds `frame.cached(key)` and needs no second hop to the thread pool, a delta
session's too; params sessions register no eager format; a format whose eager encoding raises is left to its
viewer, which encodes it again (and reports the error, if it raises again, as before)."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from ofera.client import ServerError, connect
from ofera.streaming import roles, session
from ofera.streaming.metrics import Metrics
from ofera.streaming.roles import CodecWriter, SessionFatal, Source, Viewer
from ofera_protocol import FrameFormat, decode_server_message
from ofera_protocol import errors as E
from test_server_roles import FakePipeline, N, pending, until
from test_server_support import SMALL, main_server, run

KEY = ("f32", "flame", False, None)
WAIT = 30.0  # seconds a step may take before the test calls it hung (never a performance claim)


class CountingPool(ThreadPoolExecutor):
    """A thread pool that counts the work handed to it."""

    def __init__(self, name: str) -> None:
        super().__init__(1, thread_name_prefix=name)
        self.submitted = 0

    def submit(self, *args: Any, **kwargs: Any) -> Any:
        self.submitted += 1
        return super().submit(*args, **kwargs)


Failure = Callable[[int, int], bool]
"""(frame seq, how many encodings of that frame so far, this one included) -> whether this one raises."""


def mark_compute(monkeypatch: pytest.MonkeyPatch) -> threading.local:
    """Patches ``Source._compute`` (in this process: the test server runs in a thread) so that the returned
    thread-local's ``on`` is True while the calling thread runs it."""
    inside, compute = threading.local(), roles.Source._compute

    def marked(self: Source, pending: Any) -> Any:
        inside.on = True
        try:
            return compute(self, pending)
        finally:
            inside.on = False

    monkeypatch.setattr(roles.Source, "_compute", marked)
    return inside


class RecordingWriter:
    """Wraps a frame writer: records (seq, thread name) of every encode, and whether it ran inside
    ``Source._compute`` (``in_compute``, where ``inside`` from :func:`mark_compute` is given); `fail(seq, calls)` ->
    raise or not."""

    def __init__(self, inner: Any, fail: Failure | None = None, inside: threading.local | None = None) -> None:
        self.inner = inner
        self.fail = fail
        self.inside = inside
        self.calls: list[tuple[int, str]] = []
        self.in_compute: list[bool] = []
        self._lock = threading.Lock()

    def encode(self, seq: int, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            self.calls.append((seq, threading.current_thread().name))
            self.in_compute.append(getattr(self.inside, "on", False))
            n = sum(1 for s, _ in self.calls if s == seq)
        if self.fail is not None and self.fail(seq, n):
            raise RuntimeError(f"encoding failure {n} of frame {seq}")
        return self.inner.encode(seq, *args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def fails_first_time(seq: int, n: int) -> bool:
    return n == 1


def always(seq: int, n: int) -> bool:
    return True


# ----------------------------------------------------------------------------- roles, no socket


async def stream(source: Source, viewer: Viewer, frames: int, sent: list) -> None:
    """Run `source` and `viewer`, offer `frames` bs one after the other (each sent before the next)."""
    tasks = [asyncio.create_task(source.run()), asyncio.create_task(viewer.run())]
    try:
        for seq in range(frames):
            source.offer(pending(seq))
            await until(lambda seq=seq: len(sent) > seq or any(t.done() for t in tasks), WAIT)
            for t in tasks:
                if t.done():
                    t.result()  # raises what the task raised
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


def roles_session(fail: Failure | None = None, eager: bool = True, pipeline: Any = None) -> tuple:
    """(source, viewer, writer, compute pool, viewer pool, sent): a v1-shaped pair on two counting pools."""
    metrics = Metrics()
    compute, encode = CountingPool("compute"), CountingPool("viewer")
    writer = RecordingWriter(CodecWriter(FrameFormat("f32", N)), fail)
    sent: list = []

    async def send(data: Any) -> None:
        sent.append(data)

    source = Source(pipeline or FakePipeline(), compute, metrics)
    viewer = Viewer(send, writer, KEY, encode, metrics)
    source.subscribers.append(viewer.offer)
    if eager:
        source.eager.append((KEY, viewer.make))
    return source, viewer, writer, compute, encode, sent


def test_eager_formats_are_encoded_in_the_compute_thread_and_the_viewer_sends_them_as_they_are() -> None:
    source, viewer, writer, compute, encode, sent = roles_session()
    made: list = []
    make = viewer.make

    def recording_make(frame: roles.ComputedFrame) -> Any:
        made.append(data := make(frame))
        return data

    source.eager[0] = (KEY, recording_make)
    with compute, encode:
        run(stream(source, viewer, 4, sent))
    assert [seq for seq, _ in writer.calls] == [0, 1, 2, 3]  # once per frame
    assert all(name.startswith("compute") for _, name in writer.calls)
    assert encode.submitted == 0  # no hop to the viewer's pool
    assert all(s is m for s, m in zip(sent, made, strict=True))  # the bytes made in the compute thread, sent
    assert [decode_server_message(d, FrameFormat("f32", N)).seq for d in sent] == [0, 1, 2, 3]


def test_without_an_eager_format_the_viewer_encodes_in_its_pool() -> None:
    """The same observation without `Source.eager`: what the eager path saves."""
    source, viewer, writer, compute, encode, sent = roles_session(eager=False)
    with compute, encode:
        run(stream(source, viewer, 3, sent))
    assert [seq for seq, _ in writer.calls] == [0, 1, 2]
    assert all(name.startswith("viewer") for _, name in writer.calls) and encode.submitted == 3


def test_a_failed_eager_encoding_is_retried_by_the_viewer() -> None:
    source, viewer, writer, compute, encode, sent = roles_session(fail=fails_first_time)
    with compute, encode:
        run(stream(source, viewer, 3, sent))
    by_frame = {seq: [name.split("_")[0] for s, name in writer.calls if s == seq] for seq in range(3)}
    assert by_frame == {seq: ["compute", "viewer"] for seq in range(3)}  # failed eagerly, made again by the viewer
    assert encode.submitted == 3
    frames = [decode_server_message(d, FrameFormat("f32", N)) for d in sent]
    assert [f.seq for f in frames] == [0, 1, 2]
    np.testing.assert_array_equal(frames[2].position, np.full((N, 3), 2, np.float32))


def test_an_encoding_that_always_fails_ends_with_the_viewers_internal_error() -> None:
    source, viewer, writer, compute, encode, sent = roles_session(fail=always)
    with compute, encode, pytest.raises(SessionFatal) as e:
        run(stream(source, viewer, 1, sent))
    assert e.value.err.code == E.INTERNAL and e.value.err.fatal
    assert str(e.value.err.message) == "the server failed encoding frame 0: RuntimeError"
    assert [name.split("_")[0] for _, name in writer.calls] == ["compute", "viewer"] and not sent


class MapOnlyPipeline(FakePipeline):
    def map(self, w: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
        return np.zeros(68, np.float32), {"epm": 1}


def test_frames_not_deformed_are_not_encoded_eagerly() -> None:
    """A source whose subscribers want no Gaussians now (`needs_state` false) maps only: nothing to encode."""
    source, viewer, writer, compute, encode, sent = roles_session(pipeline=MapOnlyPipeline())
    source.needs_state = lambda: False
    with compute, encode:
        frame = source._compute(pending(0))
    assert frame.state is None and frame.values is not None and frame.cached(KEY) is None
    assert writer.calls == []


# ----------------------------------------------------------------------------- live, a real server


@pytest.fixture
def observed(monkeypatch: pytest.MonkeyPatch) -> Any:
    """Patches the server's classes (in this process: the test server runs in a thread) to record every Source
    made, every writer made (wrapped in RecordingWriter; `observed.fail` decides failures) and every call of
    Viewer._encode (the viewer's own encoding, after a hop to the pool or, for params, on the loop)."""

    obs = SimpleNamespace(sources=[], writers=[], viewer_encodes=[], fail=None)
    source_init, viewer_encode, make_writer = Source.__init__, Viewer._encode, session.make_writer
    inside = mark_compute(monkeypatch)

    def init(self: Source, *args: Any, **kwargs: Any) -> None:
        source_init(self, *args, **kwargs)
        obs.sources.append(self)

    def encode(self: Viewer, frame: roles.ComputedFrame) -> Any:
        obs.viewer_encodes.append(frame.seq)
        return viewer_encode(self, frame)

    def writer(*args: Any, **kwargs: Any) -> RecordingWriter:
        w = RecordingWriter(make_writer(*args, **kwargs), obs.fail, inside)
        obs.writers.append(w)
        return w

    monkeypatch.setattr(roles.Source, "__init__", init)
    monkeypatch.setattr(roles.Viewer, "_encode", encode)
    monkeypatch.setattr(session, "make_writer", writer)
    return obs


async def frames_of(c: Any, count: int) -> list:
    """Send `count` bs one at a time, each answered before the next (so none is skipped)."""
    out = []
    for k in range(count):
        await c.send_bs(np.full(52, 0.1 * k, np.float32), seq=k)
        out.append(await c.recv_frame(timeout=WAIT))
    return out


def test_a_v1_q13_session_encodes_its_frames_in_the_compute_thread(observed: Any) -> None:
    """In the thread that computes the frame, right after it (``Source._compute``: the compute pool's thread, or the
    loop's for a session alone, ``compute_in_loop``). (A dense f16 session goes further: its deformation writes the
    frames, test_server_direct_f16.)"""
    async def main() -> None:
        c = await connect(main_server().url, avatar=SMALL, encoding="q13")
        frames = await frames_of(c, 5)
        (source,) = observed.sources
        assert len(source.eager) == 1  # registered for the session ...
        await c.close()
        assert [f.seq for f in frames] == list(range(5))
        await until(lambda: source.eager == [], WAIT)  # ... dropped when it ends (the server's side of the close)

    run(main())
    (writer,) = observed.writers
    assert [seq for seq, _ in writer.calls] == list(range(5))  # once per frame ...
    assert writer.in_compute == [True] * 5
    assert observed.viewer_encodes == []  # ... in Source._compute: the viewer found every frame cached


def test_a_delta_session_encodes_its_frames_in_the_compute_thread(observed: Any) -> None:
    """Its encoder advances per frame handed to the socket, and its source computes only while the viewer's slot
    is empty, so each frame it encodes eagerly is sent (test_server_delta checks the threads and a replacement)."""
    async def main() -> None:
        c = await connect(main_server().url, avatar=SMALL, encoding="q13", delta=True)
        frames = await frames_of(c, 3)
        (source,) = observed.sources
        assert len(source.eager) == 1
        await c.close()
        assert [f.seq for f in frames] == [0, 1, 2] and frames[0].key

    run(main())
    assert observed.viewer_encodes == []  # every frame was cached by the compute thread
    assert observed.writers == []  # its encoder is per client: make_delta_writer


def test_a_params_session_registers_no_eager_format(observed: Any) -> None:
    async def main() -> None:
        c = await connect(main_server().url, avatar=SMALL, encoding="params")
        frames = await frames_of(c, 3)
        await c.close()
        assert len(frames) == 3 and frames[0].seq == 0  # params frames carry seq only when stamped

    run(main())
    (source,) = observed.sources
    assert source.eager == []
    assert observed.viewer_encodes == [0, 1, 2]  # the viewer encodes each frame itself (on the loop)
    assert observed.writers == []  # its encoder is per client: params_parts


def test_a_failed_eager_encoding_is_retried_by_the_viewer_and_the_session_streams_on(observed: Any) -> None:
    observed.fail = fails_first_time

    async def main() -> None:
        c = await connect(main_server().url, avatar=SMALL, encoding="q13")
        frames = await frames_of(c, 4)
        await c.close()
        assert [f.seq for f in frames] == list(range(4)) and not c.errors

    run(main())
    (writer,) = observed.writers
    assert sorted(seq for seq, _ in writer.calls) == [0, 0, 1, 1, 2, 2, 3, 3]  # eagerly (failed), then the viewer
    assert observed.viewer_encodes == [0, 1, 2, 3]


def test_an_encoding_that_always_fails_ends_the_session_with_the_viewers_error(observed: Any) -> None:
    observed.fail = always

    async def main() -> None:
        c = await connect(main_server().url, avatar=SMALL, encoding="q13")
        await c.send_bs(np.full(52, 0.2, np.float32), seq=0)
        with pytest.raises(ServerError) as e:
            await c.recv_frame(timeout=WAIT)
        assert e.value.code == E.INTERNAL and e.value.fatal
        assert e.value.message == "the server failed encoding frame 0: RuntimeError"
        assert e.value.close_code == 1011
        await c.close()

    run(main())
    (writer,) = observed.writers
    assert [seq for seq, _ in writer.calls] == [0, 0]  # the eager attempt, then the viewer's
    assert observed.viewer_encodes == [0]
