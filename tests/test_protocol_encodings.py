"""Frame encodings (f32, f16, q13): byte layouts, documented error bounds, the smallest-three rotation
packing against a per-element transcription of PROTOCOL.md, coordinate mirroring, avatar chunks."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "protocol"))

from ofera_protocol import (  # noqa: E402
    Avatar,
    AvatarAssembler,
    Frame,
    GaussianState,
    ProtocolError,
    Quant,
    split_avatar,
)
from ofera_protocol import encodings as E  # noqa: E402
from ofera_protocol.avatar import avatar_bytes_per_gaussian  # noqa: E402
from ofera_protocol.coords import (  # noqa: E402
    SH_ODD_IN_X,
    mirror_x_position,
    mirror_x_rotation,
    mirror_x_sh,
    to_coords,
)

FAST = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
QUANT = Quant(pos_min=np.array([-0.15, -0.2, -0.1], np.float32), pos_max=np.array([0.15, 0.25, 0.3], np.float32),
              log_scale=np.array([-11.0, -1.5], np.float32))


def unit_quats(n_max: int = 64) -> st.SearchStrategy[np.ndarray]:
    comp = st.floats(-1, 1, width=32)
    return (hnp.arrays(np.float32, st.tuples(st.integers(1, n_max), st.just(4)), elements=comp)
            .filter(lambda q: bool((np.linalg.norm(q, axis=1) > 1e-3).all()))
            .map(lambda q: (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)))


def quat_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance between unit quaternions, up to sign."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    return np.minimum(np.linalg.norm(a - b, axis=1), np.linalg.norm(a + b, axis=1))


# ============================================================================= f32 / f16


@FAST
@given(hnp.arrays(np.float32, st.tuples(st.integers(0, 20), st.just(3)),
                  elements=st.floats(width=32, allow_nan=False, allow_infinity=False)))
def test_f32_is_exact_and_zero_copy(p: np.ndarray) -> None:
    n = p.shape[0]
    r = np.zeros((n, 4), np.float32)
    enc = E.encode_arrays("f32", p, r, p)
    assert enc[0] is p  # already C-contiguous little-endian float32: no conversion, no copy
    out = E.decode_arrays("f32", n, enc[0].tobytes(), enc[1].tobytes(), enc[2].tobytes())
    assert np.array_equal(out[0], p) and out[0].dtype == np.float32


@FAST
@given(hnp.arrays(np.float32, st.tuples(st.integers(1, 30), st.just(3)),
                  elements=st.floats(-60000, 60000, width=32)), unit_quats(30))
def test_f16_error_bound(p: np.ndarray, r: np.ndarray) -> None:
    n = min(len(p), len(r))
    p, r = p[:n], r[:n]
    enc = E.encode_arrays("f16", p, r, np.abs(p))
    assert [a.dtype.str for a in enc] == ["<f2"] * 3
    dp, dr, ds = E.decode_arrays("f16", n, *(a.tobytes() for a in enc))
    bound = E.position_error_bound("f16", magnitude=p)
    assert (np.abs(dp.astype(np.float64) - p) <= bound).all()
    assert (np.abs(dr.astype(np.float64) - r) <= E.F16_ROTATION_ERROR).all()
    assert (np.abs(ds.astype(np.float64) - np.abs(p)) <= bound).all()


def test_float_encoders_refuse_unsendable_values() -> None:
    z3, z4 = np.zeros((1, 3), np.float32), np.zeros((1, 4), np.float32)
    with pytest.raises(ValueError, match="65504"):
        E.encode_arrays("f16", z3 + 70000, z4, z3)
    for enc in ("f32", "f16"):
        for bad in (np.nan, np.inf, -np.inf):
            with pytest.raises(ValueError):
                E.encode_arrays(enc, z3, z4 + bad, z3)
    with pytest.raises(ValueError):
        E.encode_arrays("f32", np.full((1, 3), 1e300), z4, z3)  # beyond float32
    with pytest.raises(ValueError):
        E.encode_arrays("q13", z3, z4, z3)  # q13 without quant
    with pytest.raises(ValueError):
        E.encode_arrays("png", z3, z4, z3)


def test_sizes_and_formats() -> None:
    from ofera_protocol import BYTES_PER_GAUSSIAN, ENCODINGS, FrameFormat

    assert {e: sum(E.FIELD_BYTES[e]) for e in ENCODINGS} == BYTES_PER_GAUSSIAN == {"f32": 40, "f16": 20, "q13": 13}
    assert FrameFormat("f16", 3, quant=QUANT) == FrameFormat("f16", 3)  # quant only matters for q13
    assert len({FrameFormat("q13", 3, quant=QUANT), FrameFormat("q13", 3, quant=Quant(*(
        a.copy() for a in (QUANT.pos_min, QUANT.pos_max, QUANT.log_scale))))}) == 1
    for bad in (dict(encoding="f8", count=1), dict(encoding="f32", count=-1), dict(encoding="q13", count=1),
                dict(encoding="q13", count=1, quant=Quant(QUANT.pos_max, QUANT.pos_min, QUANT.log_scale))):
        with pytest.raises(ValueError):
            FrameFormat(**bad)


def test_decode_arrays_lengths() -> None:
    with pytest.raises(ProtocolError) as ei:
        E.decode_arrays("q13", 2, b"\x00" * 12, b"\x00" * 8, b"\x00" * 5, QUANT)
    assert ei.value.code == "bad_length" and "scale" in ei.value.message
    for enc, sizes in E.FIELD_BYTES.items():
        out = E.decode_arrays(enc, 3, *(b"\x00" * (3 * s) for s in sizes), QUANT)
        assert [a.shape for a in out] == [(3, 3), (3, 4), (3, 3)]


# ============================================================================= q13 position / scale


@FAST
@given(st.data())
def test_q13_position_error_bound_inside_box(data: st.DataObject) -> None:
    n = data.draw(st.integers(1, 40))
    cols = [data.draw(hnp.arrays(np.float32, n, elements=st.floats(float(lo), float(hi), width=32)))
            for lo, hi in zip(QUANT.pos_min, QUANT.pos_max, strict=True)]
    p = np.stack(cols, axis=1)
    q = E.quantize_positions(p, QUANT)
    assert q.dtype.str == "<u2"
    d = E.dequantize_positions(q, QUANT)
    bound = E.position_error_bound("q13", QUANT, magnitude=np.abs(p))
    assert (np.abs(d.astype(np.float64) - p) <= bound).all()
    # decoding the decoded value again gives the same codes (stable under re-encoding)
    assert np.array_equal(E.quantize_positions(d, QUANT), q)


def test_q13_position_box_ends_and_clamping() -> None:
    p = np.stack([QUANT.pos_min, QUANT.pos_max, QUANT.pos_min - 1, QUANT.pos_max + 1])
    q = E.quantize_positions(p, QUANT)
    assert q.tolist() == [[0] * 3, [65535] * 3, [0] * 3, [65535] * 3]
    d = E.dequantize_positions(q, QUANT)
    assert np.array_equal(d[0], QUANT.pos_min) and np.array_equal(d[1], QUANT.pos_max)
    assert np.allclose(E.position_error_bound("q13", QUANT, 0.0) * 2 * 65535,
                       QUANT.pos_max.astype(np.float64) - QUANT.pos_min)


@FAST
@given(st.data())
def test_q13_log_scale_error_bound(data: st.DataObject) -> None:
    lmin, lmax = (float(v) for v in QUANT.log_scale)
    ls = data.draw(hnp.arrays(np.float64, st.tuples(st.integers(1, 30), st.just(3)),
                              elements=st.floats(lmin, lmax)))
    s = np.exp(ls).astype(np.float32)
    q = E.quantize_log_scale(s, QUANT)
    assert q.dtype == np.uint8
    d = E.dequantize_log_scale(q, QUANT)
    err = np.abs(np.log(d.astype(np.float64)) - np.log(s.astype(np.float64)))
    assert (err <= E.log_scale_error_bound(QUANT)).all()


def test_q13_scale_clamping_and_degenerate_values() -> None:
    lmin, lmax = (float(v) for v in QUANT.log_scale)
    s = np.array([[math.exp(lmin), math.exp(lmax), 1e-30], [0.0, -1.0, np.nan], [np.inf, 1e3, 1e-9]], np.float32)
    q = E.quantize_log_scale(s, QUANT)
    assert q.tolist() == [[0, 255, 0], [0, 0, 0], [255, 255, 0]]
    assert np.allclose(E.dequantize_log_scale(np.array([[0, 255, 0]], np.uint8), QUANT)[0, :2],
                       [math.exp(lmin), math.exp(lmax)], rtol=1e-6)


def test_make_quant_covers_input_with_margin() -> None:
    rng = np.random.default_rng(5)
    p = rng.normal(0, 0.05, (500, 3)).astype(np.float32)
    s = np.exp(rng.uniform(-9, -4, (500, 3))).astype(np.float32)
    q = E.make_quant(p, s)
    ext = p.max(0) - p.min(0)
    assert (q.pos_min <= p.min(0) - 0.24 * ext).all() and (q.pos_max >= p.max(0) + 0.24 * ext).all()
    assert q.log_scale[0] < np.log(s.min()) and q.log_scale[1] > np.log(s.max())
    assert all(a.dtype == np.float32 for a in (q.pos_min, q.pos_max, q.log_scale))
    flat = E.make_quant(np.zeros((3, 3)), np.full((3, 3), 0.01))  # zero extent still gives a valid box
    assert (flat.pos_max - flat.pos_min >= 1e-3).all()
    E.make_quant(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError):
        E.validate_quant(Quant(q.pos_max, q.pos_min, q.log_scale))


# ============================================================================= q13 rotation


def spec_pack(q: np.ndarray) -> tuple[int, list[int], list[float]]:
    """PROTOCOL.md section 6.3 for one quaternion, in float64: (i, stored fields, unrounded values)."""
    x = [float(c) for c in q]
    n = math.sqrt(sum(c * c for c in x))
    x = [c / n for c in x]
    i = max(range(4), key=lambda k: (abs(x[k]), -k))
    if x[i] < 0:
        x = [-c for c in x]
    exact = [x[k] * math.sqrt(2) * 511 for k in range(4) if k != i]
    return i, [max(-511, min(511, round(e))) & 0x3FF for e in exact], exact


def spec_unpack(v: int) -> list[float]:
    i = v >> 30
    kept = []
    for shift in (20, 10, 0):
        s = (v >> shift) & 0x3FF
        s = s - 1024 if s >= 512 else s
        kept.append(max(s / 511, -1.0) / math.sqrt(2))
    q = kept[:i] + [math.sqrt(max(0.0, 1 - sum(c * c for c in kept)))] + kept[i:]
    return q


def test_smallest_three_matches_spec_transcription() -> None:
    rng = np.random.default_rng(11)
    q = rng.normal(size=(3000, 4)).astype(np.float32)
    packed = E.pack_smallest_three(q)
    assert packed.dtype.str == "<u4"
    for r, v in zip(q, packed.tolist(), strict=True):
        i, fields, exact = spec_pack(r)
        assert v >> 30 == i
        for shift, f, e in zip((20, 10, 0), fields, exact, strict=True):
            got = (v >> shift) & 0x3FF
            # the reference computes in float32: a value within 1e-3 of a rounding tie may go either way
            assert got == f or (abs(abs(e - math.floor(e)) - 0.5) < 1e-3 and abs(got - f) in (1, 1023)), (r, v)
    words = np.concatenate([packed, rng.integers(0, 2**32, 500, dtype=np.uint64).astype(np.uint32)])
    np.testing.assert_allclose(E.unpack_smallest_three(words), [spec_unpack(int(v)) for v in words], atol=1e-6)


@FAST
@given(unit_quats())
def test_smallest_three_error_bound(q: np.ndarray) -> None:
    d = E.unpack_smallest_three(E.pack_smallest_three(q))
    assert (quat_distance(d, q) <= E.Q13_ROTATION_ERROR).all()
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-5)
    # the rotation angle bound of PROTOCOL.md: 0.32 degrees
    cos_half = np.clip(np.abs((d.astype(np.float64) * q).sum(1)), 0, 1)
    assert (np.degrees(2 * np.arccos(cos_half)) <= 0.32).all()


def test_smallest_three_worst_case_region() -> None:
    """All four components near 0.5 maximise the error of the reconstructed component."""
    rng = np.random.default_rng(2)
    q = 0.5 + rng.normal(0, 0.01, (20000, 4))
    q *= rng.choice([-1, 1], size=q.shape)
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    d = E.unpack_smallest_three(E.pack_smallest_three(q))
    assert quat_distance(d, q).max() <= E.Q13_ROTATION_ERROR


def test_smallest_three_special_cases() -> None:
    s = math.sqrt(0.5)
    q = np.array([[0, 0, 0, 1], [0, 0, 0, -1], [1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [-0.5, 0.5, 0.5, 0.5],
                  [s, -s, 0, 0], [0, 0, 0, 0], [np.nan, 0, 0, 1], [0, 2, 0, 0]], np.float32)
    v = E.pack_smallest_three(q)
    assert (v >> 30).tolist() == [3, 3, 0, 0, 0, 0, 3, 3, 1]  # lowest index wins ties
    d = E.unpack_smallest_three(v)
    assert d[0].tolist() == [0, 0, 0, 1] and d[1].tolist() == [0, 0, 0, 1]  # identity is exact
    assert d[2].tolist() == [1, 0, 0, 0] and d[8].tolist() == [0, 1, 0, 0]
    assert d[4][0] > 0  # negated so the dropped component is positive
    np.testing.assert_allclose(d[5], [s, -s, 0, 0], atol=1e-6)
    assert d[6].tolist() == [0, 0, 0, 1] and d[7].tolist() == [0, 0, 0, 1]  # unsendable -> identity
    # field value -512 decodes like -511 (SNORM), i.e. -1/sqrt2
    word = (3 << 30) | (512 << 20) | (513 << 10) | 0
    # (the dropped component is sqrt of a float32 rounding residue here: 2.4e-4, not 0)
    np.testing.assert_allclose(E.unpack_smallest_three(np.array([word], np.uint32))[0], [-s, -s, 0, 0], atol=3e-4)


# ============================================================================= coordinates


def _rotmat(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _sh_basis(d: np.ndarray) -> np.ndarray:
    """Real SH basis of degree 3 in the 3DGS (graphdeco) order and sign convention, without constants
    that do not depend on the direction's sign."""
    x, y, z = d
    xx, yy, zz = x * x, y * y, z * z
    return np.array([1, -y, z, -x, x * y, y * z, 2 * zz - xx - yy, x * z, xx - yy, y * (3 * xx - yy), x * y * z,
                     y * (4 * zz - xx - yy), z * (2 * zz - 3 * xx - 3 * yy), x * (4 * zz - xx - yy), z * (xx - yy),
                     x * (xx - 3 * yy)])


@FAST
@given(unit_quats(8))
def test_unity_mirror_is_reflection_conjugation(q: np.ndarray) -> None:
    m = np.diag([-1.0, 1.0, 1.0])
    p = q[:, :3].astype(np.float64)
    p2, q2 = to_coords(p, q, "unity")
    assert np.allclose(p2, p @ m)
    for a, b in zip(q, q2, strict=True):
        assert np.allclose(_rotmat(b.astype(np.float64)), m @ _rotmat(a.astype(np.float64)) @ m, atol=1e-6)
    assert np.array_equal(mirror_x_position(mirror_x_position(p)), p.astype(np.float32))
    assert np.array_equal(mirror_x_rotation(mirror_x_rotation(q)), q)
    assert to_coords(p, q, "flame") == (p, q)
    with pytest.raises(ValueError):
        to_coords(p, q, "unreal")


def test_sh_mirror_matches_mirrored_view_directions() -> None:
    rng = np.random.default_rng(4)
    sh = rng.normal(size=(1, 16, 3)).astype(np.float32)
    sh_m = mirror_x_sh(sh)
    for _ in range(20):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        colour = _sh_basis(d) @ sh[0]
        colour_m = _sh_basis(d * [-1, 1, 1]) @ sh_m[0]
        assert np.allclose(colour, colour_m, atol=1e-5)
    assert set(SH_ODD_IN_X) == {3, 4, 7, 10, 13, 15}
    assert np.array_equal(mirror_x_sh(sh[:, :1]), sh[:, :1])  # degree 0 is unchanged


# ============================================================================= avatar chunks and state


def _avatar(n: int, deg: int = 2) -> Avatar:
    rng = np.random.default_rng(n)
    k = (deg + 1) ** 2
    return Avatar(opacity=rng.uniform(0, 1, n).astype(np.float32), sh=rng.normal(size=(n, k, 3)).astype(np.float32),
                  position=rng.normal(size=(n, 3)).astype(np.float32),
                  rotation=np.tile(np.float32([0, 0, 0, 1]), (n, 1)), scale=np.full((n, 3), 0.01, np.float32))


@pytest.mark.parametrize("n,max_bytes", [(0, 1000), (1, 1), (10, 1000), (100, 5000), (7, 10**9)])
def test_split_and_assemble(n: int, max_bytes: int) -> None:
    av = _avatar(n)
    chunks = split_avatar(av, max_bytes)
    per = avatar_bytes_per_gaussian(2)
    assert all(c.n * per <= max(max_bytes, per) for c in chunks)
    asm = AvatarAssembler(n, 2)
    done = [asm.add(c) for c in chunks]
    assert done == [False] * (len(chunks) - 1) + [True]
    assert asm.result() == av
    with pytest.raises(ProtocolError):
        asm.add(chunks[0])


def test_assembler_rejects_bad_sequences() -> None:
    chunks = split_avatar(_avatar(10), 3 * avatar_bytes_per_gaussian(2))
    for bad_order in ([chunks[1]], [chunks[0], chunks[2]]):
        asm = AvatarAssembler(10, 2)
        with pytest.raises(ProtocolError) as ei:
            for c in bad_order:
                asm.add(c)
        assert ei.value.code == "bad_field"
    with pytest.raises(ProtocolError, match="count"):
        AvatarAssembler(11, 2).add(chunks[0])
    with pytest.raises(ProtocolError, match="sh_degree"):
        AvatarAssembler(10, 1).add(chunks[0])
    with pytest.raises(RuntimeError):
        AvatarAssembler(10, 2).result()


def test_avatar_shape_checks() -> None:
    av = _avatar(3)
    with pytest.raises(ValueError):
        Avatar(av.opacity, av.sh[:, :5], av.position, av.rotation, av.scale)
    with pytest.raises(ValueError):
        Avatar(av.opacity, av.sh, av.position[:2], av.rotation, av.scale)
    assert Avatar(av.opacity.astype(np.float64), av.sh, av.position, av.rotation, av.scale).opacity.dtype == np.float32


def test_gaussian_state_dense_and_sparse() -> None:
    av = _avatar(5)
    st_ = GaussianState.from_avatar(av)
    z = np.zeros((2, 3), np.float32)
    st_.apply(Frame(1, 0, z + 1, np.zeros((2, 4), np.float32), z + 2, index=np.array([1, 4], np.uint32)))
    assert st_.position[[1, 4]].tolist() == [[1, 1, 1]] * 2
    assert np.array_equal(st_.position[[0, 2, 3]], av.position[[0, 2, 3]])
    assert st_.scale[4].tolist() == [2, 2, 2] and st_.scale[0].tolist() == av.scale[0].tolist()
    full = np.full((5, 3), 7, np.float32)
    st_.apply(Frame(2, 0, full, np.zeros((5, 4), np.float32), full))
    assert (st_.position == 7).all()
    assert np.array_equal(av.position, _avatar(5).position)  # the avatar itself is untouched
