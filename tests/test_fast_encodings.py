"""Fast frame encoding (ofera_protocol.fast_encodings + ofera.streaming.encode_fast): byte-identical to the
reference codec for every encoding, coordinates and sparse selection; round trips within each encoding's
documented bound; temporal delta frames (numba = reference, byte for byte) keep the client within the tolerance
whatever is dropped."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from ofera.streaming.encode_fast import (
    delta_encoder,
    f16_flat_kernel,
    numba_kernels,
    scale_table,
)
from ofera_protocol import (
    ClientConnection,
    Frame,
    FrameFormat,
    GaussianState,
    decode_server_message,
    encode_frame,
    to_coords,
)
from ofera_protocol.delta import DELTA_BINS, HELD_ROTATION, DeltaDecoder, DeltaEncoder, DeltaTolerance
from ofera_protocol.encodings import (
    F16_ROTATION_ERROR,
    Q13_ROTATION_ERROR,
    log_scale_error_bound,
    make_quant,
    position_error_bound,
    quantize_log_scale,
)
from ofera_protocol.fast_encodings import BufferPool, FrameWriter, NumpyKernels, VaryingRows, scale_thresholds
from ofera_protocol.messages import DeltaFrame

N = 20_000
TIMING = {"decode": 3, "epm": 40, "total": 900}


@pytest.fixture(scope="module")
def kernels():
    return numba_kernels()


def state(rng, n=N, edge_cases=True):
    pos = (rng.standard_normal((n, 3)) * 0.05).astype(np.float32)
    rot = rng.standard_normal((n, 4)).astype(np.float32)
    rot /= np.linalg.norm(rot, axis=1, keepdims=True)
    scale = np.exp(rng.uniform(-9, -2, (n, 3))).astype(np.float32)
    if edge_cases:
        s2 = np.float32(math.sqrt(0.5))
        rot[:12] = [[1, 0, 0, 0], [0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [-0.5, 0.5, 0.5, -0.5], [0, 0, 1, 0],
                    [0, 0, 0, -1], [np.nan, 0, 0, 1], [1e-30, 0, 0, 0], [s2, s2, 0, 0], [-s2, s2, 0, 0],
                    [0, -s2, 0, s2], [np.inf, 1, 0, 0]]
        rot[12:20] *= 3  # not unit
        pos[:4] = [[10, -10, 0], [-0.0, 0.0, 1e-9], [np.float32(1e-30), 0, 0], [0.3, 0.3, 0.3]]  # outside the box
    return pos, rot, scale


def finite_for(enc, pos, rot, scale):
    """The reference refuses non-finite f32/f16 input; q13 defines an encoding for it."""
    if enc == "q13":
        return pos, rot, scale
    return pos, np.nan_to_num(rot, posinf=1.0), np.clip(np.nan_to_num(scale), 0, 100)


@pytest.mark.parametrize("enc", ["f32", "f16", "q13"])
@pytest.mark.parametrize("coords", ["flame", "unity"])
@pytest.mark.parametrize("sparse", [False, True])
@pytest.mark.parametrize("impl", ["numpy", "numba"])
def test_writer_bytes_equal_reference_codec(kernels, enc, coords, sparse, impl) -> None:
    rng = np.random.default_rng(1)
    pos, rot, scale = state(rng)
    scale[:5] = [[0, 1e-30, np.inf], [1e-4, 1e-4, 1e-4], [-1, 2, 3], [np.nan, 1, 1], [1e-12, 1e9, 1]]
    quant = make_quant(pos[100:], scale[100:])
    pos, rot, scale = finite_for(enc, pos, rot, scale)
    fmt = FrameFormat(enc, N, sparse, quant if enc == "q13" else None)
    gather = np.sort(rng.choice(N, N // 3, replace=False)).astype(np.int64) if sparse else None
    index = gather.astype(np.uint32) if sparse else None
    sel = (lambda a: a[gather]) if sparse else (lambda a: a)
    p, r = to_coords(sel(pos), sel(rot), coords)
    ref = encode_frame(Frame(seq=7, t=-5, timing=TIMING, position=p, rotation=r, scale=sel(scale), index=index),
                       fmt)
    writer = FrameWriter(fmt, coords, gather, index, kernels=NumpyKernels() if impl == "numpy" else kernels)
    for _ in range(2):  # the second time from a recycled buffer
        out = writer.encode(7, -5, TIMING, pos, rot, scale)
        assert bytes(out) == ref
        del out


@pytest.mark.parametrize("enc", ["f32", "f16"])
def test_writer_refuses_non_finite_like_the_codec(kernels, enc) -> None:
    rng = np.random.default_rng(2)
    pos, rot, scale = finite_for(enc, *state(rng, 100, edge_cases=False))
    writer = FrameWriter(FrameFormat(enc, 100), kernels=kernels)
    bad = pos.copy()
    bad[5, 1] = np.nan
    with pytest.raises(ValueError, match="position"):
        writer.encode(0, 0, {}, bad, rot, scale)
    if enc == "f16":
        big = scale.copy()
        big[3, 0] = 70000.0
        with pytest.raises(ValueError, match="scale"):
            writer.encode(0, 0, {}, pos, rot, big)


def test_f16_conversion_is_numpys_rounding() -> None:
    rng = np.random.default_rng(3)
    bits = rng.integers(0, 2**32, 2_000_000, dtype=np.uint64).astype(np.uint32)
    x = bits.view(np.float32)
    x = x[np.abs(x) <= 65504]  # finite, in the half range (others are refused before conversion)
    special = np.float32([0.0, -0.0, 65504, 65503.99, 6.1035156e-05, 6.0975552e-05, 5.9604645e-08,
                          2.9802322e-08, 2.9802326e-08, 1.0009765625, 1.00048828125, 1.00146484375])
    x = np.concatenate([x, special, -special, (rng.random(100_000).astype(np.float32) - 0.5) * 1e-3])
    out = np.empty(x.size, np.uint16)
    assert f16_flat_kernel(x, out)
    np.testing.assert_array_equal(out, x.astype(np.float16).view(np.uint16))
    assert not f16_flat_kernel(np.float32([1.0, 65504.01]), out[:2])  # beyond the half range: refused


def test_scale_thresholds_reproduce_the_reference_quantiser() -> None:
    rng = np.random.default_rng(4)
    quant = make_quant(rng.normal(0, 0.05, (100, 3)), np.exp(rng.uniform(-9, -3, (100, 3))))
    thr = scale_thresholds(quant)
    assert np.all(np.diff(thr) > 0)
    near = np.concatenate([thr, np.nextafter(thr, np.float32(0)), np.nextafter(thr, np.float32(np.inf))])
    s = np.concatenate([near, np.exp(rng.uniform(-14, 1, 300_000)).astype(np.float32),
                        np.float32([0, -0.0, -1, np.inf, np.nan, 1e-45, 3e38])]).astype(np.float32)
    s = s[: s.size // 3 * 3].reshape(-1, 3)
    ref = quantize_log_scale(s, quant)
    got = np.empty(s.size, np.uint8)
    NumpyKernels().q13_scale(s, None, thr, got)
    np.testing.assert_array_equal(got.reshape(-1, 3), ref)
    numba_kernels().q13_scale(s, None, thr, got)
    np.testing.assert_array_equal(got.reshape(-1, 3), ref)
    table = scale_table(thr)
    assert table.shape[1] == 2


@pytest.mark.parametrize("enc", ["f32", "f16", "q13"])
def test_round_trip_within_documented_bounds(kernels, enc) -> None:
    rng = np.random.default_rng(5)
    pos, rot, scale = state(rng, edge_cases=False)
    quant = make_quant(pos, scale)
    fmt = FrameFormat(enc, N, False, quant if enc == "q13" else None)
    data = FrameWriter(fmt, "flame", kernels=kernels).encode(1, 2, TIMING, pos, rot, scale)
    frame = decode_server_message(bytes(data), fmt)
    assert isinstance(frame, Frame) and frame.timing == TIMING
    bound = position_error_bound(enc, quant if enc == "q13" else None, np.abs(pos))
    assert np.all(np.abs(frame.position - pos) <= bound * (1 + 1e-6))
    dot = np.abs(np.sum(frame.rotation.astype(np.float64) * rot, axis=1))
    dist = np.sqrt(np.maximum(0.0, 2 - 2 * dot))  # Euclidean distance up to sign, unit quaternions
    if enc == "f32":
        assert np.array_equal(frame.rotation, rot) and np.array_equal(frame.scale, scale)
    elif enc == "f16":
        assert np.abs(frame.rotation - rot).max() <= F16_ROTATION_ERROR
        assert np.all(np.abs(frame.scale - scale) <= np.maximum(scale * 2.0**-11, 2.0**-25))
    else:
        assert dist.max() <= Q13_ROTATION_ERROR
        assert np.abs(np.log(frame.scale) - np.log(scale)).max() <= log_scale_error_bound(quant)


def test_buffer_pool_reuses_only_unreferenced_buffers() -> None:
    pool = BufferPool(size=2)
    a = pool.get(100)
    view = memoryview(a)[:10]
    b = pool.get(100)
    c = pool.get(100)
    assert a is not b and c is not a and c is not b and pool.unpooled == 1
    del a
    assert pool.get(50) is not view.obj  # still referenced through the view
    del view
    d = pool.get(50)
    assert len(d) >= 50


def varying_states(rng, n: int, frames: int):
    """A stream of states that differ only in rows `rows` (spans of several lengths, the first and last rows
    included), as the fast deformation's are, and the VaryingRows they carry."""
    rows = np.concatenate([np.arange(0, 7), np.arange(100, 101), np.arange(500, 2000), rng.choice(n, 300),
                           np.arange(n - 5, n)])
    varying = VaryingRows(rows)
    base = state(rng, n, edge_cases=False)
    out = []
    for _ in range(frames):
        pos, rot, scale = (a.copy() for a in base)
        fresh = state(rng, len(varying), edge_cases=False)
        for a, f in zip((pos, rot, scale), fresh):
            a[varying.indices] = f
        out.append((pos, rot, scale))
    return out, varying


def test_varying_rows_are_spans_of_the_rows() -> None:
    v = VaryingRows(np.array([9, 3, 4, 5, 9, 0]))
    assert v.indices.tolist() == [0, 3, 4, 5, 9] and len(v) == 5 and v.end() == 10
    assert v.start.tolist() == [0, 3, 9] and v.length.tolist() == [1, 3, 1]
    empty = VaryingRows(np.zeros(0, np.int64))
    assert len(empty) == 0 and empty.start.size == 0 and empty.end() == 0
    with pytest.raises(ValueError, match="non-negative"):
        VaryingRows(np.array([-1, 2]))


@pytest.mark.parametrize("enc", ["f32", "f16", "q13"])
@pytest.mark.parametrize("coords", ["flame", "unity"])
@pytest.mark.parametrize("impl", ["numpy", "numba"])
def test_writer_with_varying_rows_gives_the_full_encodes_bytes(kernels, enc, coords, impl) -> None:
    """Pooled buffers re-encode only the varying rows; every frame is still the codec's bytes, whatever the
    header's length (seq and timing grow and shrink) and however the pool hands buffers out (some kept)."""
    rng = np.random.default_rng(7)
    n = 4000
    states, varying = varying_states(rng, n, 12)
    fmt = FrameFormat(enc, n, False, make_quant(states[0][0], states[0][2]) if enc == "q13" else None)
    writer = FrameWriter(fmt, coords, kernels=kernels if impl == "numba" else NumpyKernels(), pool=3)
    kept = []
    for i, (pos, rot, scale) in enumerate(states):
        seq = [1, 2, 70000, 3, 2**40, 5][i % 6]
        timing = TIMING if i % 4 else {**TIMING, "queue": 123456789, "extra": 2**33}
        got = writer.encode(seq, i, timing, pos, rot, scale, varying=varying)
        p, r = to_coords(pos, rot, coords)
        want = encode_frame(Frame(seq=seq, t=i, timing=timing, position=p, rotation=r, scale=scale), fmt)
        assert bytes(got) == want, i
        if i % 5 == 1:
            kept.append(got)  # held: the pool hands out another buffer next
    assert writer.partial >= (6 if enc != "q13" else 0) and (enc != "q13" or writer.partial == 0)


def test_writer_varying_rows_refuse_non_finite_and_recover(kernels) -> None:
    rng = np.random.default_rng(8)
    states, varying = varying_states(rng, 3000, 3)
    fmt = FrameFormat("f16", 3000, False, None)
    writer = FrameWriter(fmt, kernels=kernels, pool=1)
    pos, rot, scale = states[0]
    writer.encode(1, 1, TIMING, pos, rot, scale, varying=varying)
    bad = pos.copy()
    bad[varying.indices[-1], 1] = np.inf
    with pytest.raises(ValueError, match="position"):
        writer.encode(2, 2, TIMING, bad, rot, scale, varying=varying)
    pos, rot, scale = states[1]
    got = writer.encode(3, 3, TIMING, pos, rot, scale, varying=varying)  # the failed frame's buffer: full again
    assert bytes(got) == encode_frame(Frame(seq=3, t=3, timing=TIMING, position=pos, rotation=rot, scale=scale), fmt)


@pytest.mark.parametrize("coords", ["flame", "unity"])
def test_drafts_finished_by_the_caller_are_the_codecs_frames(kernels, coords) -> None:
    """FrameWriter.draft lays out a dense f16 frame whose other rows hold `base`; the caller writes the varying rows
    (here: numpy's half conversion of the state in wire coordinates) and finish() writes the header. Bytes: the
    codec's, whether the buffer was laid out afresh, reused, abandoned in between, or the header is too long."""
    rng = np.random.default_rng(9)
    n = 3000
    states, varying = varying_states(rng, n, 8)
    base = states[0]
    fmt = FrameFormat("f16", n, False, None)
    writer = FrameWriter(fmt, coords, kernels=kernels, pool=2, stamp_encode=False)
    psign, rsign = writer.psign, writer.rsign
    kept = []
    for i, (pos, rot, scale) in enumerate(states):
        draft = writer.draft(varying, base)
        rows = varying.indices
        draft.position.reshape(n, 3)[rows] = (pos[rows] * psign).astype("<f2").view(np.uint16)
        draft.rotation.reshape(n, 4)[rows] = (rot[rows] * rsign).astype("<f2").view(np.uint16)
        draft.scale.reshape(n, 3)[rows] = scale[rows].astype("<f2").view(np.uint16)
        if i == 3:
            continue  # abandoned: its buffer is laid out afresh next time
        timing = TIMING if i != 5 else {f"stage-number-{j}": 2**40 + j for j in range(60)}  # i = 5: > the room
        got = writer.finish(draft, i, i, timing)
        p, r = to_coords(pos, rot, coords)
        assert bytes(got) == encode_frame(Frame(seq=i, t=i, timing=timing, position=p, rotation=r, scale=scale), fmt)
        if i % 3 == 0:
            kept.append(got)
    with pytest.raises(ValueError, match="dense f16"):
        FrameWriter(FrameFormat("f32", n, False, None), kernels=kernels).draft(varying, base)
    bad = (np.full((n, 3), np.inf, np.float32), base[1], base[2])
    with pytest.raises(ValueError, match="base position"):
        FrameWriter(fmt, coords, kernels=kernels).draft(varying, bad)


@pytest.mark.parametrize("k", [3, 4, 5])
@pytest.mark.parametrize("coords", ["flame", "unity"])
def test_rows_kernels_equal_the_reference(kernels, k, coords) -> None:
    rng = np.random.default_rng(k)
    n = 2500
    src = (rng.standard_normal((n, k)) * 3).astype(np.float32)
    sign = np.ones(k, np.float32) if coords == "flame" else np.where(np.arange(k) % 2, -1, 1).astype(np.float32)
    rows = VaryingRows(np.concatenate([np.arange(3, 90), rng.choice(n, 200), [n - 1]]))
    ref = NumpyKernels()
    for name in ("f16_rows", "f32_rows"):
        dt = np.uint16 if name == "f16_rows" else np.float32
        start = rng.integers(0, 60000, n * k).astype(dt) if dt == np.uint16 else rng.standard_normal(n * k).astype(dt)
        a, b = start.copy(), start.copy()
        assert getattr(kernels, name)(src, rows, sign, a) and getattr(ref, name)(src, rows, sign, b)
        assert np.array_equal(a.view(np.uint8), b.view(np.uint8)), name
        other = np.setdiff1d(np.arange(n), rows.indices)
        assert np.array_equal(a.reshape(n, k)[other].view(np.uint8), start.reshape(n, k)[other].view(np.uint8))
        bad = src.copy()
        bad[rows.indices[5], k - 1] = np.nan
        assert not getattr(kernels, name)(bad, rows, sign, a.copy())
        assert not getattr(ref, name)(bad, rows, sign, b.copy())
    bad = src.copy()
    bad[rows.indices[0], 0] = 70000.0  # beyond the half range: f16 only
    assert not kernels.f16_rows(bad, rows, sign, np.zeros(n * k, np.uint16))
    assert kernels.f32_rows(bad, rows, sign, np.zeros(n * k, np.float32))


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between quaternions (n, 4), from the chord (stable for small angles)."""
    a = a.astype(np.float64) / np.linalg.norm(a.astype(np.float64), axis=1, keepdims=True)
    b = b.astype(np.float64) / np.linalg.norm(b.astype(np.float64), axis=1, keepdims=True)
    sign = np.where(np.sum(a * b, axis=1) < 0, -1.0, 1.0)[:, None]
    return np.degrees(4 * np.arcsin(np.minimum(np.linalg.norm(a - sign * b, axis=1) / 2, 1.0)))


def moving(rng, n, frames, candidates):
    """State arrays of `frames` frames in which the candidates move smoothly (some a lot, most a little)."""
    p, r, s = state(rng, n, edge_cases=False)
    out = []
    amp = np.where(np.arange(candidates.size) % 7 == 0, 3e-4, 1e-5)
    for _ in range(frames):
        p, r, s = p.copy(), r.copy(), s.copy()
        p[candidates] += (rng.normal(0, 1, (candidates.size, 3)) * amp[:, None]).astype(np.float32)
        r[candidates] += rng.normal(0, 3e-3, (candidates.size, 4)).astype(np.float32)
        r[candidates] /= np.linalg.norm(r[candidates], axis=1, keepdims=True)
        s[candidates] *= np.exp(rng.normal(0, 0.01, (candidates.size, 3))).astype(np.float32)
        for a in (p, r, s):
            a.flags.writeable = False  # like the fast pipeline's pooled states
        out.append((p, r, s))
    return out


def moving_session(enc, seed, n, candidates, frames):
    """A delta session of n Gaussians in encoding ``enc`` whose ``candidates`` (that many, drawn) move for ``frames``
    frames (:func:`moving`): (candidate ids, frames, FrameFormat)."""
    rng = np.random.default_rng(seed)
    cand = np.sort(rng.choice(n, candidates, replace=False)).astype(np.int64)
    states = moving(rng, n, frames, cand)
    quant = make_quant(states[0][0], states[0][2])
    return cand, states, FrameFormat(enc, n, False, quant if enc == "q13" else None, delta=True)


@pytest.mark.parametrize("enc", ["f16", "q13"])
@pytest.mark.parametrize("coords", ["flame", "unity"])
@pytest.mark.parametrize("gathered", [False, True])
def test_delta_kernels_equal_the_reference(kernels, enc, coords, gathered) -> None:
    """The numba delta kernels select, encode and hold exactly what the numpy reference does: same bytes, for a
    session of the whole state and for one of a subset of its rows (short runs of consecutive rows)."""
    rng = np.random.default_rng(5)
    n = 3000
    gather = np.sort(rng.choice(2 * n, n, replace=False)).astype(np.int64) if gathered else None
    cand = np.sort(rng.choice(n, 1997, replace=False)).astype(np.int64)  # not a multiple of 8: the selection's tail
    frames = moving(rng, 2 * n if gathered else n, 25, cand if gather is None else gather[cand])
    quant = make_quant(frames[0][0], frames[0][2])
    fmt = FrameFormat(enc, n, False, quant if enc == "q13" else None, delta=True)
    ref = DeltaEncoder(fmt, coords, gather, cand, key_interval=10)
    fast = delta_encoder(fmt, coords, gather, cand, key_interval=10)
    sizes, whole, narrow = [], 0, 0
    for f, (p, r, s) in enumerate(frames):
        a, b = ref.encode(f, 1, TIMING, p, r, s), fast.encode(f, 1, TIMING, p, r, s)
        assert a == b, f"frame {f} differs"
        sizes.append(len(a))
        m = decode_server_message(a, fmt)
        if isinstance(m, DeltaFrame):
            whole, narrow = whole + len(m.position), narrow + len(m.position_delta)
    for name in ("held_p", "held_r", "held_s", "dec"):
        np.testing.assert_array_equal(getattr(ref, name), getattr(fast, name))
    assert ref.key_frames == 3 and min(sizes) < max(sizes) * 0.6  # key frames at 0, 10, 20; deltas are smaller
    assert whole > 0 and narrow > 0  # positions sent both ways


def test_delta_body_kernel_equals_the_reference(kernels) -> None:
    """The numba bin fields of a delta frame are delta_body_reference's bytes (its bitmasks those of
    delta_masks_reference), for empty selections, counts that are not multiples of 8, and fields long enough for each
    of msgpack's bin headers (8, 16 and 32 bits of length); the bytes before and after stay as they were."""
    from ofera_protocol.codec import unpack_bits
    from ofera_protocol.delta import delta_body_reference, delta_body_size, delta_masks_reference, row_runs

    rng = np.random.default_rng(11)
    fast = numba_kernels()
    for count in (1, 5, 8, 13, 64, 1000, 4099, 70000):
        for ids in (np.sort(rng.choice(count, max(1, count * 2 // 3), replace=False)),  # short runs
                    np.concatenate([np.arange(count // 7, count // 2), np.arange(count * 3 // 5, count)])):  # long
            ids = np.unique(ids).astype(np.int64)
            id_runs = row_runs(ids)
            m = ids.size
            outputs = [rng.integers(0, 256, m * r, dtype=np.uint8) for r in (3, 6, 8, 6)]  # f16's rows (bytes)
            for n in {0, 1, ids.size // 2, ids.size}:
                sel = np.sort(rng.choice(ids.size, n, replace=False)).astype(np.int64)
                flags = np.zeros(ids.size, np.uint8)
                flags[sel] = rng.integers(1, 8, n)  # a changed candidate moved something, any of the 7 ways
                moved = np.concatenate([flags[sel], rng.integers(0, 8, m - n, dtype=np.uint8)])  # past n: stale
                wide = rng.random(ids.size) < 0.4
                n_p, n_r, n_s = (int((moved[:n] & b).sum() // b) for b in (1, 2, 4))
                w = int(wide[:n_p].sum())
                masks = delta_masks_reference(count, id_runs, flags, moved, wide, n, n_p)
                assert np.array_equal(np.flatnonzero(unpack_bits(masks[0].tobytes(), count, "changed")), ids[sel])
                for c in range(3):
                    assert np.array_equal(unpack_bits(masks[1 + c].tobytes(), n, "moved"), moved[:n] & (1 << c) != 0)
                args = (count, id_runs, flags, moved, wide, n, n_p, w, n_r, n_s, *outputs, 3, 6, 8, 6)
                size = 7 + delta_body_size(count, n, n_p, w, n_r, n_s, (3, 6, 8, 6)) + 5
                want, got = np.full(size, 0xAB, np.uint8), np.full(size, 0xAB, np.uint8)
                end = delta_body_reference(want, 7, *args)
                assert fast.delta_body(got, 7, *args) == end <= size - 5, (count, n)
                assert got.tobytes() == want.tobytes(), (count, n)
                assert masks[0].tobytes() in want.tobytes()


@pytest.mark.parametrize("enc", ["f16", "q13"])
def test_delta_frame_messages_are_their_maps_packed(kernels, enc) -> None:
    """A delta frame's message, its fields written before its header, is ``codec.pack_map`` of its own map (msgpack's
    shortest forms, the codec's key order), from either kernel set, a header too long for the room before the fields
    included (one copy); a message still held keeps its bytes while the next ones are written."""
    from ofera_protocol.codec import pack_map

    cand, frames, fmt = moving_session(enc, 9, 3000, 2500, 8)
    for encoder in (DeltaEncoder(fmt, candidates=cand, stamp_encode=True),
                    delta_encoder(fmt, candidates=cand, stamp_encode=True)):
        encoder.encode(0, 0, {}, *frames[0])
        held = []
        for k, state in enumerate(frames[1:], 1):
            timing = {"decode": k} if k % 3 else {f"stage_{i}": 10 ** 9 + i for i in range(40)}  # > 512 bytes
            data = encoder.encode(k, k, timing, *state)
            m = msgpack.unpackb(bytes(data))
            assert not m["key"] and m["timing"]["encode"] >= 0 and list(m)[6:] == list(DELTA_BINS)
            assert bytes(data) == pack_map(m), (type(encoder.kernels).__name__, k)
            held.append((data, bytes(data)))
        assert all(bytes(data) == kept for data, kept in held)


@pytest.mark.parametrize("enc", ["f16", "q13"])
def test_delta_client_error_is_bounded_whatever_is_dropped(kernels, enc) -> None:
    """Closed loop: after any number of frames and any drops (frames never handed to the socket are never
    encoded), the client's state is within max(tolerance, the encoding's error) of the exact state, and a
    resync (key frame) gives exactly the dense frame's values."""
    n = 3000
    cand, frames, fmt = moving_session(enc, 6, n, 2000, 40)
    quant = fmt.quant
    tol = DeltaTolerance()
    enc_ = delta_encoder(fmt, "unity", None, cand, tolerance=tol, key_interval=0)
    client = ClientConnection()
    client.format, client.delta = fmt, DeltaDecoder(fmt)
    held = None
    dropped = {3, 4, 5, 11, 17, 18, 30}
    if enc == "q13":
        pos_bound = max(tol.position_m, float(np.linalg.norm(position_error_bound("q13", quant, 0.3))))
        rot_bound = max(tol.rotation_deg, math.degrees(2 * math.asin(Q13_ROTATION_ERROR / 2)) * 2)
        s_bound = max(tol.log_scale, log_scale_error_bound(quant))
    else:
        pos_bound = max(tol.position_m, 0.3 * 2.0**-11 * math.sqrt(3))
        rot_bound = max(tol.rotation_deg, 0.05)
        s_bound = max(tol.log_scale, 2.0**-10)
    for f, (p, r, s) in enumerate(frames):
        if f in dropped:
            continue
        if f == 25:
            enc_.request_key()
        msg = decode_server_message(enc_.encode(f, 0, {}, p, r, s), fmt)
        if isinstance(msg, DeltaFrame):
            got = client.delta.apply(msg)
            assert not got.key and got.n < n
            held.position[got.index], held.rotation[got.index], held.scale[got.index] = \
                got.position, got.rotation, got.scale
        else:
            assert msg.key and f in (0, 25)
            client.delta.key(msg)
            held = GaussianState(msg.position, msg.rotation, msg.scale)
            plain = FrameFormat(enc, n, False, fmt.quant)
            ep, er = to_coords(p, r, "unity")
            dense = decode_server_message(encode_frame(Frame(seq=f, t=0, position=ep, rotation=er, scale=s), plain),
                                          plain)
            np.testing.assert_array_equal(held.position, dense.position)
        ep, er = to_coords(p, r, "unity")
        perr = np.linalg.norm(held.position.astype(np.float64) - ep, axis=1).max()
        rerr = rotation_error_deg(held.rotation, er).max()
        serr = np.abs(np.log(held.scale.astype(np.float64)) - np.log(s)).max()
        assert perr <= pos_bound + 1e-7 and rerr <= rot_bound + 1e-3 and serr <= s_bound + 1e-6, (f, perr, rerr, serr)


@pytest.mark.parametrize("parallel", [False, True])
@pytest.mark.parametrize("enc", ["f16", "q13"])
def test_fast_delta_decoder_equals_the_reference(kernels, enc, parallel) -> None:
    """ofera.client.fast_decode (numba) applies key and delta frames exactly like ofera_protocol.delta, on one thread
    or on numba's threads (five blocks of DECODE_BLOCK Gaussians, the last partial)."""
    from ofera.client.fast_decode import DECODE_BLOCK, FastFrameDecoder

    cand, frames, fmt = moving_session(enc, 9, 6000, 5000, 15)
    encoder = delta_encoder(fmt, "unity", None, cand, key_interval=6)
    ref, fast = DeltaDecoder(fmt), FastFrameDecoder(fmt, parallel=parallel)
    sizes = []
    for f, (p, r, s) in enumerate(frames):
        data = encoder.encode(f, 0, {}, p, r, s)
        msg = decode_server_message(data, fmt)
        want = ref.apply(msg) if isinstance(msg, DeltaFrame) else msg
        if not isinstance(msg, DeltaFrame):
            ref.key(msg)
        got = fast.decode(data)
        if isinstance(msg, DeltaFrame):
            sizes.append(msg.n)
            assert fast.threaded is parallel
        assert got.key is want.key and (got.index is None) == (want.index is None)
        if want.index is not None:
            np.testing.assert_array_equal(got.index, want.index)
        for name in ("position", "rotation", "scale"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    for name in ("position", "rotation", "scale"):
        np.testing.assert_array_equal(getattr(fast.delta, name), getattr(ref, name))
    assert max(sizes) > 4 * DECODE_BLOCK and max(sizes) % DECODE_BLOCK  # several blocks, the last partial


def test_fast_delta_decoder_threads_while_alone_and_faster(kernels, monkeypatch) -> None:
    """An automatic decoder (parallel None) decodes a delta frame on threads while it is the only one of its activity
    decoding and its threaded frames were faster; with another decoder active, or serial faster: one thread."""
    import ofera.client.fast_decode as fd
    from ofera.thread_choice import Activity

    monkeypatch.setattr(fd, "load_average", lambda: 0.0)  # the test machine's load is not the subject
    rng = np.random.default_rng(10)
    n = 3000
    cand = np.arange(0, n, 2, dtype=np.int64)
    frames = moving(rng, n, 4, cand)
    fmt = FrameFormat("q13", n, False, make_quant(frames[0][0], frames[0][2]), delta=True)
    encoder = delta_encoder(fmt, "unity", None, cand, key_interval=100)
    data = [encoder.encode(f, 0, {}, *frame) for f, frame in enumerate(frames)]
    a, b = (fd.FastFrameDecoder(fmt, activity=Activity(window_s=60.0)) for _ in range(2))
    a.threads = b.threads = 2
    for dec, faster in ((a, True), (b, False)):
        for _ in range(3):
            dec.choices["delta"].record(True, 1 if faster else 10)
            dec.choices["delta"].record(False, 10 if faster else 1)
        dec.decode(data[0])  # the key frame
    a.decode(data[1])
    assert a.threaded  # alone, threads faster
    b.decode(data[1])
    assert not b.threaded  # alone, serial faster
    b.activity = a.activity
    b.decode(data[2])
    a.decode(data[2])
    assert not a.threaded  # b decoded within the window: one thread each
    times = a.choices["delta"].times
    assert len(times[True]) == 4 and len(times[False]) == 4  # every automatic frame recorded
    assert len(a.choices["dense"].times[False]) == 1  # the key frame, in the dense frames' own choice


def bad_delta_frames(good: dict) -> list[dict]:
    """Delta frames (n = 1 of 20 Gaussians) whose masks are wrong in every way codec.delta_masks checks."""
    one, zero, two = np.ones(1, np.uint8), np.zeros(1, np.uint8), np.full(1, 2, np.uint8)
    return [dict(good, changed=np.array([1, 0], np.uint8)), dict(good, changed=np.array([1, 0, 0, 0], np.uint8)),
            dict(good, changed=np.array([3, 0, 0], np.uint8)), dict(good, changed=np.zeros(3, np.uint8)),
            dict(good, changed=np.array([1, 0, 0x10], np.uint8)), dict(good, n=2), dict(good, n=0),
            dict(good, n=21), dict(good, moved_position=two), dict(good, moved_rotation=np.zeros(2, np.uint8)),
            dict(good, moved_scale=np.zeros(0, np.uint8)), dict(good, wide=one + 1),
            dict(good, wide=np.zeros(0, np.uint8)), dict(good, moved_position=zero, moved_rotation=zero),
            dict(good, wide=one)]


def test_fast_delta_masks_equal_the_codecs(kernels) -> None:
    """FastFrameDecoder's numba masks give codec.delta_masks' arrays and counts on random valid masks, and the
    rows that carry each attribute."""
    from ofera.client.fast_decode import FastFrameDecoder, unpack_delta_masks_kernel
    from ofera_protocol.codec import delta_masks, pack_bits

    rng = np.random.default_rng(3)
    for count in (1, 7, 8, 9, 100, 1001):
        fmt = FrameFormat("q13", count, False, make_quant(np.zeros((count, 3)), np.full((count, 3), 1e-3)),
                          delta=True)
        fast = FastFrameDecoder(fmt)
        for _ in range(5):
            changed = rng.random(count) < rng.random()
            n = int(changed.sum())
            moved = rng.random((n, 3)) < 0.5
            moved[~moved.any(axis=1), rng.integers(0, 3)] = True
            wide = rng.random(int(moved[:, 0].sum())) < 0.3
            m = {"n": n, "changed": pack_bits(changed).tobytes(), "wide": pack_bits(wide).tobytes(),
                 **{k: pack_bits(moved[:, c]).tobytes() for c, k in
                    enumerate(("moved_position", "moved_rotation", "moved_scale"))}}
            bins = [np.frombuffer(m[k], np.uint8) for k in
                    ("changed", "moved_position", "moved_rotation", "moved_scale", "wide")]
            lists = np.zeros((3, count + 8), np.uint32)
            assert unpack_delta_masks_kernel(bins[0], count, n, *bins[1:], np.zeros(count + 8, np.uint32),
                                             np.zeros((3, count + 8), bool), lists, np.zeros(count + 8, bool))[0]
            want, got = delta_masks(m, fmt), fast._masks(m, fmt)
            for a, b in zip(want[:3], got[:3], strict=True):
                np.testing.assert_array_equal(a, b)
            assert want[3] == got[3]
            for c in range(3):  # the rows carrying each attribute, which the apply kernel reads
                np.testing.assert_array_equal(lists[c, :want[3][c]], np.flatnonzero(want[1][:, c]))


def test_delta_decoder_refuses_bad_frames_without_changing_state() -> None:
    from ofera_protocol import ProtocolError
    from ofera_protocol.codec import pack_map

    n = 20
    fmt = FrameFormat("q13", n, False, make_quant(np.zeros((n, 3)), np.full((n, 3), 1e-3)), delta=True)
    dec = DeltaDecoder(fmt)
    one, zero = np.ones(1, np.uint8), np.zeros(1, np.uint8)
    good = {"type": "frame", "seq": 2, "t": 0, "timing": {}, "key": False, "n": 1,
            "changed": np.array([1, 0, 0], np.uint8), "moved_position": one, "moved_rotation": one,
            "moved_scale": zero, "wide": zero, "position_delta": np.array([[5, -3, 1]], np.int8),
            "position": np.zeros((0, 3), "<u2"), "rotation": np.array([3 << 30], "<u4"),
            "scale": np.zeros((0, 3), np.uint8)}
    with pytest.raises(ProtocolError) as e:  # before any key frame
        dec.apply(decode_server_message(pack_map(good), fmt))
    assert e.value.code == "not_ready"
    dec.has_key = True
    before = dec.position.copy()
    for bad, code in ((dict(good, changed=np.array([1, 0, 0, 0], np.uint8)), "bad_length"),
                      (dict(good, changed=np.array([3, 0, 0], np.uint8)), "bad_field"),  # n = 1, two marked
                      (dict(good, changed=np.array([1, 0, 0x10], np.uint8)), "bad_field"),  # padding bit
                      (dict(good, position_delta=np.array([[-5, 0, 0]], np.int8)), "bad_field"),  # code < 0
                      (dict(good, scale=np.zeros((1, 3), np.uint8)), "bad_length"),  # no scale moved
                      (dict(good, moved_position=zero, moved_rotation=zero), "bad_field")):  # carries nothing
        with pytest.raises(ProtocolError) as e:
            dec.apply(decode_server_message(pack_map(bad), fmt))
        assert e.value.code == code
        np.testing.assert_array_equal(dec.position, before)
    from ofera.client.fast_decode import FastFrameDecoder

    fast = FastFrameDecoder(fmt)
    fast.delta.has_key = True
    for bad in bad_delta_frames(good):  # the fast decoder refuses them with the codec's own error
        with pytest.raises(ProtocolError) as want:
            decode_server_message(pack_map(bad), fmt)
        with pytest.raises(ProtocolError) as got:
            fast.decode(pack_map(bad))
        assert (got.value.code, str(got.value)) == (want.value.code, str(want.value))
    with pytest.raises(ProtocolError) as e:
        fast.decode(pack_map(dict(good, position_delta=np.array([[-5, 0, 0]], np.int8))))
    assert e.value.code == "bad_field" and not fast.delta.position.any()
    dec.position[0] = [10, 10, 10]
    dec.scale[0] = [7, 8, 9]
    got = dec.apply(decode_server_message(pack_map(good), fmt))
    assert got.index.tolist() == [0] and dec.position[0].tolist() == [15, 7, 11] and dec.scale[0].tolist() == [7, 8, 9]
    assert dec.rotation[0] == 3 << 30


@pytest.mark.parametrize("parallel", [False, True])
@pytest.mark.parametrize("enc", ["q13", "f16"])
def test_fast_delta_frames_refuse_bad_fields_with_the_codecs_error(kernels, enc, parallel, monkeypatch) -> None:
    """A delta frame decoded in one kernel call (delta_frame_kernel) refuses whatever codec.decode_delta_frame refuses
    in its fields (types, lengths, f16 codes sent whole that are not finite, seq, t, timing) with the codec's own
    error, changing nothing held; the good frame then decodes as the reference does."""
    from ofera.client.fast_decode import FastFrameDecoder
    from ofera_protocol import ProtocolError
    from ofera_protocol.codec import pack_map

    q13 = enc == "q13"
    fmt = FrameFormat(enc, 20, False, make_quant(np.zeros((20, 3)), np.full((20, 3), 1e-3)) if q13 else None,
                      delta=True)
    one = np.ones(1, np.uint8)
    rot = np.array([3 << 30], "<u4") if q13 else np.array([[0, 0, 0, 0x3C00]], "<f2")
    scale, wide_pos = np.zeros((1, 3), np.uint8 if q13 else "<f2"), np.array([[1, 2, 3]], "<u2")
    good = {"type": "frame", "seq": 2, "t": 0, "timing": {"total": 5}, "key": False, "n": 2,
            "changed": np.array([0, 0x12, 0], np.uint8), "moved_position": np.array([3], np.uint8),
            "moved_rotation": one, "moved_scale": np.array([2], np.uint8), "wide": np.array([2], np.uint8),
            "position_delta": np.array([[5, -3, 1]], np.int8), "position": wide_pos, "rotation": rot, "scale": scale}
    nan = np.array([[0x7E00, 0, 0]], "<u2")
    bad = [dict(good, position_delta=np.zeros((2, 3), np.int8)), dict(good, position=np.zeros((0, 3), "<u2")),
           dict(good, rotation=np.zeros(0, np.uint8)), dict(good, scale=np.zeros((2, 3), scale.dtype)),
           dict(good, changed=5), dict(good, position=[1, 2, 3]), dict(good, n=2.0), dict(good, seq=-1),
           dict(good, t="0"), dict(good, timing={"total": -1}), dict(good, timing=3), dict(good, n=None)]
    if not q13:  # f16 codes sent whole: finite
        bad += [dict(good, position=nan), dict(good, scale=nan.view("<f2")),
                dict(good, rotation=np.array([[0, 0, 0, 0x7C00]], "<u2"))]
    ref, fast = DeltaDecoder(fmt), FastFrameDecoder(fmt)
    for held in (ref, fast.delta):
        held.has_key = True
        held.position[:] = 100
    for b in bad:
        with pytest.raises(ProtocolError) as want:
            ref.apply(decode_server_message(pack_map(b), fmt))
        with pytest.raises(ProtocolError) as got:
            fast.decode(pack_map(b))
        assert (got.value.code, str(got.value)) == (want.value.code, str(want.value)), b
        assert (fast.delta.position == 100).all() and not fast.delta.scale.any()
    want = ref.apply(decode_server_message(pack_map(good), fmt))
    import ofera.client.fast_decode

    def never(*args: object) -> None:
        raise AssertionError("a good delta frame took the codec's path")

    monkeypatch.setattr(ofera.client.fast_decode, "frame_parts", never)
    got = fast.decode(pack_map(good))
    assert got.index.tolist() == want.index.tolist() == [9, 12] and got.timing == {"total": 5}
    for name in ("position", "rotation", "scale"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
        np.testing.assert_array_equal(getattr(fast.delta, name), getattr(ref, name))


def test_fast_delta_decoder_refuses_an_f16_change_to_infinity_like_the_reference(kernels) -> None:
    """A narrow f16 position change that lands on an infinite half (0x7BFF + 1) is refused by both decoders with
    non_finite, and neither changes what it holds."""
    from ofera.client.fast_decode import FastFrameDecoder
    from ofera_protocol import ProtocolError
    from ofera_protocol.codec import pack_map

    fmt = FrameFormat("f16", 20, False, None, delta=True)
    one, zero = np.ones(1, np.uint8), np.zeros(1, np.uint8)
    bad = {"type": "frame", "seq": 2, "t": 0, "timing": {}, "key": False, "n": 1,
           "changed": np.array([0, 1, 0], np.uint8), "moved_position": one, "moved_rotation": zero,
           "moved_scale": zero, "wide": zero, "position_delta": np.array([[1, 0, 0]], np.int8),
           "position": np.zeros((0, 3), "<f2"), "rotation": np.zeros((0, 4), "<f2"), "scale": np.zeros((0, 3), "<f2")}
    ref, fast = DeltaDecoder(fmt), FastFrameDecoder(fmt)
    for held in (ref, fast.delta):
        held.has_key = True
        held.position[8] = [0x7BFF, 7, 7]
    with pytest.raises(ProtocolError) as want:
        ref.apply(decode_server_message(pack_map(bad), fmt))
    with pytest.raises(ProtocolError) as got:
        fast.decode(pack_map(bad))
    assert got.value.code == want.value.code == "non_finite"
    assert fast.delta.position[8].tolist() == [0x7BFF, 7, 7] and not fast.delta.position[9:].any()
    ok = fast.decode(pack_map(dict(bad, position_delta=np.array([[-1, 0, 0]], np.int8))))
    assert ok.index.tolist() == [8] and ok.position[0, 0] == np.float32(np.uint16(0x7BFE).view(np.float16))


@pytest.mark.parametrize("parallel", [False, True])
@pytest.mark.parametrize("enc", ["f32", "f16", "q13"])
@pytest.mark.parametrize("sparse", [False, True])
def test_fast_decoder_equals_codec(kernels, enc, sparse, parallel) -> None:
    """FastFrameDecoder gives the codec's values, its dense and sparse frames decoded on one thread or on numba's
    (blocks of DENSE_BLOCK rows, the last partial)."""
    from ofera.client.fast_decode import DENSE_BLOCK, FastFrameDecoder

    assert N > 2 * DENSE_BLOCK and N % DENSE_BLOCK

    rng = np.random.default_rng(8)
    pos, rot, scale = state(rng, edge_cases=False)
    quant = make_quant(pos, scale)
    fmt = FrameFormat(enc, N, sparse, quant if enc == "q13" else None)
    gather = np.arange(0, N, 3) if sparse else None
    data = bytes(FrameWriter(fmt, "unity", gather, None if gather is None else gather.astype(np.uint32),
                             kernels=kernels).encode(4, 5, TIMING, pos, rot, scale))
    ref = decode_server_message(data, fmt)
    dec = FastFrameDecoder(fmt, parallel=parallel)
    got = dec.decode(data)
    assert dec.threaded is (parallel and enc != "f32")
    assert (got.seq, got.t, got.timing) == (ref.seq, ref.t, ref.timing)
    assert (got.index is None) == (ref.index is None)
    for name in ("position", "rotation", "scale"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))


@pytest.mark.parametrize("parallel", [False, True])
def test_fast_decoder_checks_like_the_codec(kernels, parallel) -> None:
    """A dense f16 frame with a non-finite half in any field is refused with the codec's error, naming the field."""
    from ofera.client.fast_decode import FastFrameDecoder
    from ofera_protocol import ProtocolError
    from ofera_protocol.codec import pack_map

    fmt = FrameFormat("f16", 2)
    pos = np.zeros((2, 3), "<f2")
    pos[1, 2] = np.inf
    good = {"type": "frame", "seq": 1, "t": 2, "timing": {}, "n": 2, "position": np.zeros((2, 3), "<f2"),
            "rotation": np.zeros((2, 4), "<f2"), "scale": np.zeros((2, 3), "<f2")}
    dec = FastFrameDecoder(fmt, parallel=parallel)
    assert dec.decode(pack_map(good)).n == 2
    for name in ("position", "rotation", "scale"):
        bad = np.zeros((2, 4 if name == "rotation" else 3), "<f2")
        bad[1, -1] = np.inf
        with pytest.raises(ProtocolError) as want:
            decode_server_message(pack_map({**good, name: bad}), fmt)
        with pytest.raises(ProtocolError) as e:
            dec.decode(pack_map({**good, name: bad}))
        assert (e.value.code, str(e.value)) == (want.value.code, str(want.value)) and e.value.code == "non_finite"
    with pytest.raises(ProtocolError) as e:
        dec.decode(pack_map({**good, "scale": np.zeros((1, 3), "<f2")}))
    assert e.value.code == "bad_length"


@pytest.mark.parametrize("enc", ["f16", "q13"])
@pytest.mark.parametrize("sparse", [False, True])
def test_stamped_encode_time_is_the_codecs_bytes_with_that_timing(kernels, enc, sparse) -> None:
    rng = np.random.default_rng(5)
    pos, rot, scale = finite_for(enc, *state(rng))
    quant = make_quant(pos[100:], scale[100:])
    fmt = FrameFormat(enc, N, sparse, quant if enc == "q13" else None)
    gather = np.sort(rng.choice(N, N // 3, replace=False)).astype(np.int64) if sparse else None
    index = gather.astype(np.uint32) if sparse else None
    sel = (lambda a: a[gather]) if sparse else (lambda a: a)
    writer = FrameWriter(fmt, "unity", gather, index, kernels=kernels, stamp_encode=True)
    for timing in (TIMING, {}, {f"s{i}": i for i in range(15)}, {**TIMING, "encode": 1 << 40}):  # 15: map grows
        out = writer.encode(9, 123, timing, pos, rot, scale)
        stamped = decode_server_message(bytes(out), fmt).timing
        assert set(stamped) == set(timing) | {"encode"} and 0 <= stamped["encode"] < 10_000_000
        p, r = to_coords(sel(pos), sel(rot), "unity")
        ref = encode_frame(Frame(seq=9, t=123, timing={**timing, "encode": stamped["encode"]}, position=p, rotation=r,
                                 scale=sel(scale), index=index), fmt)
        assert bytes(out) == ref
        del out


@pytest.mark.parametrize("k", [3, 4, 5])
@pytest.mark.parametrize("gathered", [False, True])
def test_unrolled_f16_kernel_equals_the_plain_loop(kernels, k, gathered) -> None:
    from ofera.streaming.encode_fast import f16_kernel, f16_kernel_reference

    rng = np.random.default_rng(6)
    src = (rng.standard_normal((3000, k)) * 10.0 ** rng.integers(-8, 5, (3000, k))).astype(np.float32)
    src[:4, 0] = [65504.0, 65520.0, -0.0, 6e-8]  # the largest half, the first value rounding to inf, -0, subnormal
    gather = rng.permutation(3000)[:1000].astype(np.int64) if gathered else np.zeros(0, np.int64)
    n = 1000 if gathered else 3000
    sign = np.where(rng.random(k) < 0.5, -1, 1).astype(np.float32)
    a, b = np.zeros(n * k, np.uint16), np.ones(n * k, np.uint16)
    ok_a, ok_b = f16_kernel(src, gather, n, sign, a), f16_kernel_reference(src, gather, n, sign, b)
    assert ok_a == ok_b and np.array_equal(a, b)
    src[src == 65520.0] = 1.0
    src = np.clip(src, -60000, 60000)
    assert f16_kernel(src, gather, n, sign, a) and f16_kernel_reference(src, gather, n, sign, b)
    assert np.array_equal(a, b)


@pytest.mark.parametrize("gathered", [False, True])
def test_branch_free_q13_positions_equal_the_plain_loop(kernels, gathered) -> None:
    from ofera.streaming.encode_fast import q13_position_kernel, q13_position_kernel_reference

    rng = np.random.default_rng(7)
    src = (rng.standard_normal((4000, 3)) * 0.2).astype(np.float32)
    src[:8] = [[np.nan, np.inf, -np.inf], [3e38, -3e38, 0], [-0.0, 1e-30, -1e-30], [0.15, -0.15, 0.3],
               [1e20, -1e20, 1e-3], [0.5, 0.5, 0.5], [-0.5, -0.5, -0.5], [0, 0, 0]]
    lo, k = np.array([-0.15, -0.2, -0.1]), np.array([65535 / 0.3, 65535 / 0.4, 65535 / 0.2])
    gather = rng.permutation(4000)[:1500].astype(np.int64) if gathered else np.zeros(0, np.int64)
    n = 1500 if gathered else 4000
    for sign in (np.ones(3, np.float32), np.array([-1, 1, 1], np.float32)):
        a, b = np.zeros(3 * n, np.uint16), np.ones(3 * n, np.uint16)
        q13_position_kernel(src, gather, n, sign, lo, k, a)
        q13_position_kernel_reference(src, gather, n, sign, lo, k, b)
        assert np.array_equal(a, b)


def test_delta_rotation_rule_holds_its_threshold_in_float32() -> None:
    """The float32 rotation test (Lagrange's identity, ofera_protocol.delta) decides like the exact angle between the
    float32 rotations, computed in float64, for every angle more than 2e-5 of the threshold away from it (the
    (h . q)^2 < cos^2 form in float32 errs up to 1 % away)."""
    from ofera_protocol.delta import _moved

    rng = np.random.default_rng(12)
    tol, n = DeltaTolerance(), 20000
    limit = math.radians(tol.rotation_deg)
    h = rng.normal(size=(n, 4))
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    theta = limit * (1 + rng.choice([-1, 1], n) * 10 ** rng.uniform(-6, -1, n))
    w, v = np.cos(theta / 2), np.sin(theta / 2)[:, None] * axis  # q = h (x) exp(theta / 2 axis), (x, y, z, w)
    qv = h[:, 3:] * v + w[:, None] * h[:, :3] + np.cross(h[:, :3], v)
    q = np.concatenate([qv, (h[:, 3] * w - np.sum(h[:, :3] * v, axis=1))[:, None]], axis=1).astype(np.float32)
    h32 = h.astype(np.float32)
    q64, h64 = q.astype(np.float64), h32.astype(np.float64)
    dot = np.abs(np.sum(q64 * h64, axis=1))
    angle = 2 * np.arctan2(np.sqrt(np.maximum(np.sum(q64**2, 1) * np.sum(h64**2, 1) - dot**2, 0)), dot)
    dec = np.ones((10, n), np.float32)
    dec[HELD_ROTATION] = h32.T
    ones = np.ones(4, np.float32)
    got = _moved(np.ones((n, 3), np.float32), q, np.ones((n, 3), np.float32), np.arange(n), ones[:3], ones,
                 tol.params(), dec)
    clear = np.abs(angle / limit - 1) > 2e-5
    assert clear.sum() > n * 0.7 and 0 < got[:, 1].sum() < n
    np.testing.assert_array_equal(got[clear, 1], angle[clear] > limit)
    assert not got[:, 0].any() and not got[:, 2].any()


@pytest.mark.parametrize("layout", ["contiguous", "strided", "gathered"])
def test_q13_rotation_and_position_kernels_equal_the_reference_on_every_path(kernels, layout) -> None:
    """q13_rotation_kernel / q13_position_kernel give NumpyKernels' codes on each of their loops: the flat
    (vectorised) one for C-contiguous state, the row one for a strided view, the gathered one."""
    rng = np.random.default_rng(13)
    pos, rot, _ = state(rng)
    rot[20:40] = np.float32([0.5, -0.5, 0.5, -0.5])  # ties between the largest components
    rot[40:60, 1] = rot[40:60, 3] = np.float32(math.sqrt(0.5))
    rot[40:60, 0] = rot[40:60, 2] = 0
    if layout == "strided":
        wide = np.zeros((N, 5), np.float32)
        wide[:, :4] = rot
        rot = wide[:, :4]
        widep = np.zeros((N, 4), np.float32)
        widep[:, :3] = pos
        pos = widep[:, :3]
        assert not rot.flags.c_contiguous and not pos.flags.c_contiguous
    gather = rng.permutation(N)[: N // 2].astype(np.int64) if layout == "gathered" else None
    n = N if gather is None else gather.size
    quant = make_quant(pos[np.isfinite(pos).all(1)], np.ones((1, 3)))
    from ofera_protocol.fast_encodings import position_factors

    lo, k = position_factors(quant)
    for sign4, sign3 in ((np.ones(4, np.float32), np.ones(3, np.float32)),
                         (np.float32([1, -1, -1, 1]), np.float32([-1, 1, 1]))):
        a, b = np.zeros(n, np.uint32), np.ones(n, np.uint32)
        kernels.q13_rotation(rot, gather, sign4, a)
        NumpyKernels().q13_rotation(rot, gather, sign4, b)
        np.testing.assert_array_equal(a, b)
        c, d = np.zeros(3 * n, np.uint16), np.ones(3 * n, np.uint16)
        kernels.q13_position(pos, gather, sign3, lo, k, c)
        NumpyKernels().q13_position(pos, gather, sign3, lo, k, d)
        np.testing.assert_array_equal(c, d)
