"""Delta frames the deformation writes (`streaming.direct_delta`, `Source.direct`): the kernel, serial or on numba's
threads (one, two or three sharing the blocks), gives the bytes and the held codes of the state path
(``FastSession.deform`` then ``DeltaEncoder.encode``, whose numba kernels test_fast_encodings compares with the numpy
reference), for both delta encodings, both coordinate systems and a reduced (gathered) session; a v1 delta session on
the fast path streams them, its key frames from the state."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
import pytest
from ofera.avatar import load_avatar
from ofera.avatar.fast import FastAvatar
from ofera.client import connect
from ofera.streaming import direct_delta
from ofera.streaming.direct import DirectDeltaFrames
from ofera.streaming.direct_delta import BLOCK, DirectDelta, block_faces, block_rows, candidate_runs
from ofera.streaming.encode_fast import delta_encoder
from ofera_protocol import FrameFormat, decode_server_message, make_quant
from ofera_protocol.delta import DeltaEncoder, _decode_codes
from test_server_direct_f16 import observed  # noqa: F401 - the fixture
from test_server_support import SMALL, main_server, run

WAIT = 30.0  # seconds a step may take before the test calls it hung (never a performance claim)


@pytest.fixture(scope="module")
def fast() -> FastAvatar:
    return FastAvatar(load_avatar("default"))


def flame_values(rng: np.random.Generator, frames: int) -> list[np.ndarray]:
    """A random walk of FLAME values (68,): expression steps that move some Gaussians a little (int8 position
    changes), some a lot (whole codes), and a jaw that opens."""
    y = np.zeros(68, np.float32)
    y[50:] = [1, 0, 0, 0, 1, 0] * 3
    out = []
    for k in range(frames):
        y = y.copy()
        y[:50] += rng.normal(0, 0.3 if k % 3 else 0.02, 50).astype(np.float32)
        y[51] = 0.05 * k
        out.append(y)
    return out


def session_of(fast: FastAvatar, enc: str, coords: str, gathered: bool) -> tuple[FrameFormat, Any, Any, Any]:
    """(format, gather, candidates, rows) of a delta session: the whole avatar, or a reduced one (every other row)."""
    n = fast.neutral
    gather = np.arange(0, fast.count, 2, dtype=np.int64) if gathered else None
    rows_all = np.arange(fast.count) if gather is None else gather
    ids = np.flatnonzero(fast.selected[rows_all]).astype(np.int64)  # the session's Gaussians the fast path moves
    quant = make_quant(n.position[rows_all], n.scale[rows_all]) if enc == "q13" else None
    return FrameFormat(enc, rows_all.size, False, quant, delta=True), gather, ids, rows_all[ids]


@pytest.mark.parametrize("enc,coords,gathered", [("q13", "flame", False), ("q13", "unity", True),
                                                 ("f16", "unity", False), ("f16", "flame", True)])
@pytest.mark.parametrize("threads,parallel,block", [(1, False, BLOCK), (3, False, 64), (1, True, BLOCK),
                                                     (2, True, BLOCK), (2, True, 64), (3, True, 64)])
def test_direct_delta_frames_are_the_state_paths(fast: FastAvatar, enc: str, coords: str, gathered: bool,
                                                 threads: int, parallel: bool, block: int,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Blocks of 64 candidates: hundreds of blocks, which threads take in turns that differ from run to run. The
    decodings of what a frame sent are left for after it (``DirectDelta.settle``): every later kernel call, and the
    encoder's own frames (key frames, and frame 6: a delta frame from the state), settle first."""
    monkeypatch.setattr(direct_delta, "BLOCK", block)
    fmt, gather, ids, rows = session_of(fast, enc, coords, gathered)
    ref = delta_encoder(fmt, coords, gather, ids, rows, key_interval=4)
    mine = delta_encoder(fmt, coords, gather, ids, rows, key_interval=4)
    a, b = fast.session(), fast.session(parallel=parallel)
    direct = DirectDelta(fast, mine, threads=threads, head=b.head_args())
    assert direct.threads == threads and direct.blocks >= rows.size // (2 * block)
    direct_frames = narrow = wide = 0
    for k, y in enumerate(flame_values(np.random.default_rng(7), 8)):
        verts = a.flame_head(y).copy()
        state = a.deform(verts)
        want = bytes(ref.encode(k, k, {"total": k}, state.position, state.rotation, state.scale))
        if mine.next_is_key or k == 6:
            got = bytes(mine.encode(k, k, {"total": k}, state.position, state.rotation, state.scale))
        else:  # the head run by the kernel (the session's call) on odd frames, vertices given on even ones
            if k % 2:  # the message body written by the kernel too
                written = b.flame_delta(y, direct)
                assert b.threaded is parallel and 0 < written.head_share < 1  # (by the kernel's clock)
                np.testing.assert_array_equal(b.lbs.out, verts)  # the head's vertices, in its buffer
                got = bytes(mine.encode_written(k, k, {"total": k}, written.counts[0], written.buf, written.end, 0))
            else:
                got = bytes(mine.encode_selected(k, k, {"total": k}, direct.select(verts, parallel), 0))
            direct_frames += 1
            m = decode_server_message(got, fmt)
            narrow, wide = narrow + len(m.position_delta), wide + len(m.position)
        assert got == want, f"frame {k} differs"
    assert not np.array_equal(ref.dec, mine.dec)  # frame 7's decodings, owed
    direct.settle()
    for name in ("held_p", "held_r", "held_s", "dec"):
        np.testing.assert_array_equal(getattr(ref, name), getattr(mine, name))
    assert direct_frames == 5 and narrow > 0 and wide > 0  # key frames at 0 and 4; positions sent both ways


def test_a_direct_delta_and_its_encoder_hold_no_cycle(fast: FastAvatar) -> None:
    """The encoder runs its DirectDelta's settle before reading what it holds (``pending``) through a weak reference:
    a finished session's DirectDelta (MBs of buffers) is freed by reference counting alone, and its encoder goes on."""
    import gc
    import weakref

    fmt, gather, ids, rows = session_of(fast, "q13", "flame", False)
    encoder = delta_encoder(fmt, "flame", gather, ids, rows)
    n = fast.neutral
    gc.collect()
    gc.disable()
    try:
        direct = DirectDelta(fast, encoder, head=fast.session().head_args())
        freed = weakref.ref(direct)
        del direct
        assert freed() is None
    finally:
        gc.enable()
    encoder.encode(0, 0, {}, n.position, n.rotation, n.scale)  # (its pending settle: a no-op now)


def test_candidates_the_fast_path_does_not_deform_are_refused(fast: FastAvatar) -> None:
    n = fast.neutral
    still = int(np.flatnonzero(~fast.selected)[0])
    fmt = FrameFormat("q13", fast.count, False, make_quant(n.position, n.scale), delta=True)
    with pytest.raises(ValueError, match="not among the Gaussians the fast path deforms"):
        DirectDelta(fast, delta_encoder(fmt, candidates=np.array([still], np.int64)))
    with pytest.raises(ValueError, match="numba kernel set"):
        DirectDelta(fast, DeltaEncoder(fmt, candidates=fast.arrays.ids))
    encoder = delta_encoder(fmt, candidates=fast.arrays.ids)
    with pytest.raises(ValueError, match="head_args"):
        DirectDelta(fast, encoder, head=fast.lbs.flame_args(*(np.zeros(k, np.float32) for k in (68, 50, 45))))
    with pytest.raises(ValueError, match="without the session's head"):
        DirectDelta(fast, encoder).head_select(np.zeros(68, np.float32))
    with pytest.raises(ValueError, match="68 entries, got shape \\(67,\\)"):
        DirectDelta(fast, encoder, head=fast.session().head_args()).head_select(np.zeros(67, np.float32))


def test_a_threaded_frame_on_one_thread_does_not_wait_for_itself(fast: FastAvatar) -> None:
    """numba limited to one thread (``set_num_threads(1)``): every iteration of the threaded kernel's regions runs on
    the calling thread, one after another, so none may wait for another's work (the head's last vertex block, the
    back blocks). The frame completes, with the serial kernel's bytes."""
    import threading

    import numba

    fmt, gather, ids, rows = session_of(fast, "q13", "flame", False)
    a, b = fast.session(parallel=False), fast.session(parallel=True)
    mine, ref = (delta_encoder(fmt, "flame", gather, ids, rows) for _ in range(2))
    serial = DirectDelta(fast, ref, head=a.head_args())
    threaded = DirectDelta(fast, mine, threads=2, head=b.head_args())
    neutral = fast.neutral
    for e in (mine, ref):
        e.encode(0, 0, {}, neutral.position, neutral.rotation, neutral.scale)
    y = flame_values(np.random.default_rng(3), 2)[1]
    got: list = []

    def one_thread() -> None:
        numba.set_num_threads(1)  # (per calling thread)
        got.append(b.flame_delta(y, threaded))

    worker = threading.Thread(target=one_thread, daemon=True)
    worker.start()
    worker.join(WAIT)
    assert got, "the threaded kernel on one thread did not finish"
    want = a.flame_delta(y, serial)
    assert b.threaded and got[0].counts == want.counts and want.counts[0] > 0
    frames = [bytes(e.encode_written(1, 1, {}, w.counts[0], w.buf, w.end, 0)) for e, w in ((mine, got[0]), (ref, want))]
    assert frames[0] == frames[1]


def test_no_candidates_select_nothing_on_either_kernel(fast: FastAvatar) -> None:
    """An encoder without candidates (an avatar nothing moves): no block, and both kernels select nothing."""
    n = fast.neutral
    fmt = FrameFormat("q13", fast.count, False, make_quant(n.position, n.scale), delta=True)
    encoder = delta_encoder(fmt, candidates=np.zeros(0, np.int64))
    encoder.encode(0, 0, {}, n.position, n.rotation, n.scale)
    direct = DirectDelta(fast, encoder)
    assert direct.blocks == 0
    verts = fast.session().flame_head(np.zeros(68, np.float32)).copy()
    assert direct.select(verts, False) == (0, 0, 0, 0, 0) == direct.select(verts, True)


def test_blocks_cover_the_candidates_once_with_their_own_faces(fast: FastAvatar) -> None:
    """Runs and blocks: every candidate in one run of consecutive deformed rows on one face, blocks of at least BLOCK
    candidates, each with its own face list naming the faces its runs use."""
    a = fast.arrays
    gface = np.repeat(a.run_face, a.run_len)
    rows = a.ids[::3]  # candidates with gaps: short runs
    run_face, run_m, run_len, blocks = candidate_runs(a.ids, gface, rows)
    assert run_len.sum() == rows.size and blocks[0] == 0 and blocks[-1] == run_len.size
    sizes = np.add.reduceat(run_len, blocks[:-1])
    assert (sizes[:-1] >= BLOCK).all() and (sizes < BLOCK + run_len.max()).all()
    m = np.concatenate([np.arange(s, s + n) for s, n in zip(run_m, run_len)])
    np.testing.assert_array_equal(a.ids[m], rows)
    np.testing.assert_array_equal(np.repeat(run_face, run_len), gface[m])
    brow = block_rows(run_len, blocks)
    assert brow.min() == 0 and (np.diff(brow)[np.diff(brow) != 1] <= 0).all()  # 0, 1, 2 ... within each block
    local, block_u, face_vids = block_faces(run_face, blocks, a.face_vids)
    for b in range(blocks.size - 1):
        q0, q1 = blocks[b], blocks[b + 1]
        assert (block_u[b] <= local[q0:q1]).all() and (local[q0:q1] < block_u[b + 1]).all()
        assert np.unique(local[q0:q1]).size == block_u[b + 1] - block_u[b]  # no face a block does not use
    np.testing.assert_array_equal(face_vids[local], a.face_vids[run_face])


def test_a_delta_session_streams_frames_the_deformation_wrote(observed: Any) -> None:  # noqa: F811
    """v1 q13 delta on the fast path: `Source.direct` writes the delta frames (no state), the key frame comes from the
    state; the server holds the codes an offline encoder holds after the same values through the state, and the
    client's Gaussians are those codes. The frames' encoding reaches /metrics (observed once each is delivered)."""
    got = []

    def encoded(source: Any) -> float:
        return source.metrics.registry.get_sample_value("ofera_stage_seconds_count", {"stage": "encode"}) or 0.0

    async def main() -> None:
        c = await connect(main_server().url, avatar=SMALL, encoding="q13", delta=True, track=True)
        for k in range(5):
            await c.send_bs(np.full(52, 0.2 * k, np.float32), seq=k)
            await c.recv_frame(timeout=WAIT)
            if k == 0:
                (source,) = observed.sources
                before = encoded(source)
        got.extend((c.gaussians.position.copy(), c.gaussians.rotation.copy(), c.gaussians.scale.copy()))
        await asyncio.sleep(0.05)  # (the server's loop observes a frame's stages after delivering it)
        assert encoded(source) - before == 4  # the four delta frames the deformation wrote
        assert source.pipeline.fast.defer == source._after.append and not source._after  # thread-choice records: run
        assert isinstance(source.direct, DirectDeltaFrames)
        direct.append(source.direct)
        await c.close()

    direct: list[DirectDeltaFrames] = []
    run(main())
    (source,) = observed.sources
    pipe, writer = source.pipeline, direct[0].encoder
    assert [observed.values[k][1] is None for k in range(5)] == [False, True, True, True, True]  # key: a state
    offline = DeltaEncoder(writer.format, "flame", None, writer.ids, writer.rows, tolerance=writer.tolerance)
    for k in range(5):
        state, _ = pipe.deform_values(observed.values[k][0])
        offline.encode(k, 0, {}, state.position, state.rotation, state.scale)
    for name in ("held_p", "held_r", "held_s", "dec"):
        np.testing.assert_array_equal(getattr(offline, name), getattr(writer, name))
    assert writer._messages.unpooled == 0  # each body the kernel wrote went into a pooled buffer, reused once sent
    want = _decode_codes(writer.format, offline.held_p, offline.held_r, offline.held_s)
    for a, b in zip(want, got):
        np.testing.assert_array_equal(np.asarray(a).reshape(b.shape), b)
