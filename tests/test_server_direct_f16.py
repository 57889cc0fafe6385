"""Frames the deformation writes itself (`Source.direct`): a v1 dense f16 session on the fast path gets frames whose
Gaussians ``FrameWriter.draft`` laid out and ``FastSession.deform_f16`` wrote, with no float32 state in between.
They must be the frames the state path gives (the same float32 arithmetic, one rounding to half), in either
coordinate system, and a frame the kernel cannot write falls back to that path."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from ofera.avatar import load_avatar
from ofera.avatar.fast import FastAvatar
from ofera.client import connect
from ofera.head.lbs import HeadSubject
from ofera.streaming import roles
from ofera.streaming.direct import DirectF16
from ofera.streaming.encode_fast import frame_writer
from ofera.streaming.metrics import Metrics
from ofera.streaming.roles import Source
from ofera_protocol import Frame, FrameFormat, decode_server_message, encode_frame, to_coords
from test_server_roles import pending
from test_server_support import SMALL, main_server, run

WAIT = 30.0  # seconds a step may take before the test calls it hung (never a performance claim)


@pytest.fixture
def observed(monkeypatch: pytest.MonkeyPatch) -> Any:
    """Records every Source the test server makes and the expression values of every frame it computes."""
    obs = SimpleNamespace(sources=[], values={})
    init, compute = Source.__init__, Source._compute

    def record_init(self: Source, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        obs.sources.append(self)

    def record_compute(self: Source, p: Any) -> roles.ComputedFrame:
        frame = compute(self, p)
        obs.values[frame.seq] = (frame.values.copy(), frame.state)
        return frame

    monkeypatch.setattr(roles.Source, "__init__", record_init)
    monkeypatch.setattr(roles.Source, "_compute", record_compute)
    return obs


@pytest.mark.parametrize("coords", ["flame", "unity"])
def test_a_dense_f16_session_gets_the_frames_the_state_path_gives(observed: Any, coords: str) -> None:
    got = []

    async def main() -> None:
        c = await connect(main_server().url, avatar=SMALL, encoding="f16", coords=coords)
        for k in range(6):
            await c.send_bs(np.full(52, 0.15 * k, np.float32), seq=k)
            got.append(await c.recv_frame(timeout=WAIT))
        (source,) = observed.sources
        assert isinstance(source.direct, DirectF16)
        await c.close()

    run(main())
    (source,) = observed.sources
    pipe = source.pipeline
    fmt = FrameFormat("f16", pipe.assets.count, False, None)
    for frame in got:
        values, state = observed.values[frame.seq]
        assert state is None  # no float32 state was made
        want, _ = pipe.deform_values(values)  # the state path, on the same values
        p, r = to_coords(want.position, want.rotation, coords)
        ref = decode_server_message(encode_frame(Frame(seq=frame.seq, t=frame.t, timing={}, position=p, rotation=r,
                                                       scale=want.scale), fmt), fmt)
        for name in ("position", "rotation", "scale"):
            assert np.array_equal(getattr(frame, name).view(np.uint32), getattr(ref, name).view(np.uint32)), name
        assert "encode" in frame.timing and "deform" in frame.timing


def test_a_frame_the_kernel_cannot_write_takes_the_state_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """deform_values_f16 reporting a value beyond the half range: the frame gets a state and no bytes, so the
    viewer's own encoding reports the error (the one error path of every format)."""
    from ofera.mapping.runtime import Mapper
    from ofera.streaming.pipeline import AvatarAssets, Pipeline

    avatar = load_avatar("default")
    assets = AvatarAssets.create("default", avatar, Mapper.default())
    pipe = Pipeline(assets, "arkit52")
    writer = frame_writer(FrameFormat("f16", avatar.count, False, None))
    source = Source(pipe, None, Metrics())
    source.direct = DirectF16(("f16", "flame", False, None), writer)
    frame = source._compute(pending(1))
    assert frame.state is None and frame.cached(source.direct.key) is not None
    monkeypatch.setattr(pipe, "deform_values_f16", lambda *a: (False, {"head": 0, "deform": 0}))
    frame = source._compute(pending(2))
    assert frame.state is not None and frame.cached(source.direct.key) is None


@pytest.mark.parametrize("parallel", [False, True])
def test_deform_f16_writes_the_bits_of_the_encoded_state(parallel: bool) -> None:
    """The kernel (serial, or over numba's threads), given the vertices or running the head itself (flame_f16),
    against deform + FrameWriter.encode on the default avatar, for both sign conventions, and a draft laid out for
    other varying rows is refused."""
    avatar = load_avatar("default")
    fast = FastAvatar(avatar, HeadSubject.create(avatar.head))
    session = fast.session(parallel=parallel)
    rng = np.random.default_rng(4)
    for coords in ("flame", "unity"):
        writer = frame_writer(FrameFormat("f16", avatar.count, False, None), coords)
        for k in range(3):
            y = np.zeros(68, np.float32)
            y[:50] = rng.normal(0, 1.0, 50)
            y[50:] = [1, 0, 0, 0, 1, 0] * 3
            y[51] = 0.2 * k  # a jaw rotation
            verts = session.head(*session.flame(y)).copy()
            state = session.deform(verts)
            want = bytes(writer.encode(k, k, {"total": k}, state.position, state.rotation, state.scale))
            n = fast.neutral
            draft = writer.draft(fast.varying, (n.position, n.rotation, n.scale))
            assert session.deform_f16(verts, draft, writer.psign, writer.rsign)
            assert session.threaded is parallel
            assert bytes(writer.finish(draft, k, k, {"total": k})) == want
            draft = writer.draft(fast.varying, (n.position, n.rotation, n.scale))  # the head in the same call
            ok, share = session.flame_f16(y, draft, writer.psign, writer.rsign)
            assert ok and session.threaded is parallel and 0 < share < 1  # (the head's, by the kernel's clock)
            np.testing.assert_array_equal(session.lbs.out, verts)
            assert bytes(writer.finish(draft, k, k, {"total": k})) == want
    other = FastAvatar(avatar, fast.subject, gaussians="all")
    n = other.neutral
    with pytest.raises(ValueError, match="varying rows"):
        session.deform_f16(verts, writer.draft(other.varying, (n.position, n.rotation, n.scale)), writer.psign,
                           writer.rsign)
    draft = writer.draft(fast.varying, (fast.neutral.position, fast.neutral.rotation, fast.neutral.scale))
    draft.scale = draft.scale[::2]  # (not what the bound kernels take)
    with pytest.raises(ValueError, match="C-contiguous uint16"):
        session.flame_f16(y, draft, writer.psign, writer.rsign)


def test_f16_blocks_cover_the_runs_in_row_order() -> None:
    """Each block of the f16 writer is consecutive runs on consecutive rows, closed once it holds F16_BLOCK rows."""
    from ofera.avatar.kernels import F16_BLOCK, f16_blocks

    rng = np.random.default_rng(5)
    run_len = rng.integers(1, 40, 500)
    gaps = rng.random(500) < 0.05  # a row gap before 5 % of the runs
    run_row = np.cumsum(run_len + gaps * rng.integers(1, 9, 500)) - run_len
    blocks = f16_blocks(run_row, run_len)
    assert blocks[0] == 0 and blocks[-1] == 500 and np.all(np.diff(blocks) > 0)
    for lo, hi in zip(blocks[:-1], blocks[1:]):
        rows = run_len[lo:hi].sum()
        assert np.array_equal(run_row[lo + 1:hi], run_row[lo] + np.cumsum(run_len[lo:hi])[:-1])  # no gap inside
        assert rows - run_len[hi - 1] < F16_BLOCK  # it grew only while below F16_BLOCK rows
        if hi < 500 and run_row[hi] == run_row[lo] + rows:  # closed without a gap: it was full
            assert rows >= F16_BLOCK
    assert f16_blocks(np.zeros(0, np.int64), np.zeros(0, np.int64)).tolist() == [0]
