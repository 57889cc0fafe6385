"""The fast per-frame path (ofera.head.lbs_fast, ofera.avatar.fast/kernels) against the numpy reference
(lbs + Deformer), for both binding types, on random expressions, jaw and eye rotations."""

from __future__ import annotations

import gc
from types import SimpleNamespace

import numpy as np
import pytest
from ofera.avatar import BarycentricBinding, GaussianAvatar, TriangleBinding
from ofera.avatar.fast import FastAvatar, StatePool, affected_vertices, reference_frame
from ofera.avatar.frames import face_scales
from ofera.head.lbs import HeadSubject, pose_rotations
from ofera.head.lbs_fast import SubsetLBS, subset_lbs_reference
from ofera.head.rotations import axis_angle_to_matrix
from ofera.mapping.flame_values import neutral_flame_values, split_flame_values
from ofera.thread_choice import Activity

POS_ATOL = 2e-7  # metres: float32 output of positions ~0.1 m (ulp 7e-9) plus the float32 blend basis
ROT_ATOL = 3e-5  # quaternion components (float32 face frames of small triangles; f16 itself is ~5e-4)
SCALE_RTOL = 1e-5


def random_avatar(head, kind: str, rng, n: int = 4000, sorted_faces: bool = False) -> GaussianAvatar:
    """Random Gaussians of `kind`; half on the face region (where expressions act), half anywhere.
    sorted_faces: consecutive Gaussians share faces (as generated avatars are laid out: long runs)."""
    moving = np.flatnonzero(affected_vertices(head)[head.faces].any(axis=1))
    face = np.concatenate([rng.choice(moving, n // 2), rng.integers(0, head.num_faces, n - n // 2)])
    face = np.sort(face) if sorted_faces else rng.permutation(face)
    rot = rng.normal(size=(n, 4)).astype(np.float32)
    rot[:3] = 0  # zero local rotations: the identity in both paths
    if kind == "triangle":
        binding = TriangleBinding(face=face, position=rng.normal(scale=0.5, size=(n, 3)).astype(np.float32),
                                  rotation=rot, log_scale=rng.normal(-1.0, 0.5, size=(n, 3)).astype(np.float32))
    else:
        binding = BarycentricBinding(
            face=face, bary=rng.dirichlet(np.ones(3), n).astype(np.float32),
            offset=rng.normal(size=n).astype(np.float32), rotation=rot,
            log_scale=rng.normal(-6.0, 0.5, size=(n, 3)).astype(np.float32),
            face_scale_canonical=face_scales(head.v_template, head.faces).astype(np.float32) * 1.1)
    return GaussianAvatar(head, binding, rng.random(n).astype(np.float32),
                          rng.normal(size=(n, 1, 3)).astype(np.float32), name=f"random-{kind}")


def random_flame(rng, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(expr (50,), rotations (5, 3, 3)) float32 from random FLAME values: jaw and eyes up to ~0.4 rad."""
    y = neutral_flame_values(1)[0]
    y[:50] = rng.normal(0, scale, 50)
    y[50:] += rng.normal(0, 0.15 * scale, 18).astype(np.float32)
    return split_flame_values(y)


def assert_same_state(fast, ref, rows=None) -> None:
    rows = slice(None) if rows is None else rows
    np.testing.assert_allclose(fast.position[rows], ref.position[rows], rtol=0, atol=POS_ATOL)
    # quaternions: q and -q are the same rotation
    dot = np.abs(np.sum(fast.rotation[rows].astype(np.float64) * ref.rotation[rows], axis=1))
    assert np.all(np.abs(dot - 1) < ROT_ATOL), float(np.abs(dot - 1).max())
    sign = np.sign(np.sum(fast.rotation[rows] * ref.rotation[rows], axis=1))[:, None]
    np.testing.assert_allclose(fast.rotation[rows] * sign, ref.rotation[rows], rtol=0, atol=ROT_ATOL)
    np.testing.assert_allclose(fast.scale[rows], ref.scale[rows], rtol=SCALE_RTOL, atol=0)


@pytest.fixture(scope="module")
def subject(head):
    return HeadSubject.create(head)


def test_subset_lbs_matches_reference(head, subject) -> None:
    rng = np.random.default_rng(0)
    ids = np.sort(rng.choice(head.num_vertices, 1500, replace=False))
    sub = SubsetLBS(subject, ids)
    for _ in range(5):
        expr, rot = random_flame(rng, 2.0)
        ref = subset_lbs_reference(subject, expr, rot, ids)
        np.testing.assert_allclose(sub.forward(expr, rot), ref, rtol=0, atol=1e-8)
    # Any rotations (root and neck included) and fewer expression coefficients: still the reference.
    rot = pose_rotations(1, jaw=rng.normal(0, 0.3, 3), neck=rng.normal(0, 0.3, 3), root=rng.normal(0, 0.3, 3))[0]
    expr = rng.normal(0, 1, 20)
    np.testing.assert_allclose(sub.forward(expr, rot), subset_lbs_reference(subject, expr, rot, ids), atol=1e-8)
    with pytest.raises(ValueError):
        sub.forward(np.zeros(head.expr_dims + 1), rot)


def test_subset_lbs_on_threads_gives_the_same_bits(head, subject) -> None:
    """forward / forward_flame with ``parallel``: the vertices in blocks the threads claim (1501 vertices: three blocks,
    the last partial), bit for bit."""
    rng = np.random.default_rng(1)
    sub = SubsetLBS(subject, np.sort(rng.choice(head.num_vertices, 1501, replace=False)))
    for _ in range(3):
        expr, rot = random_flame(rng, 2.0)
        want = sub.forward(expr, rot).copy()
        np.testing.assert_array_equal(sub.forward(expr, rot, parallel=True), want)
        y = random_flame_values(rng, 0.3)
        e, r = np.zeros(50, np.float32), np.zeros((5, 3, 3), np.float32)
        want = sub.forward_flame(y, e, r).copy()
        np.testing.assert_array_equal(sub.forward_flame(y, e, r, parallel=True), want)


def test_subset_lbs_clone_shares_arrays_not_buffers(head, subject) -> None:
    sub = SubsetLBS(subject, np.arange(100))
    other = sub.clone()
    assert other.basis_t is sub.basis_t and other.out is not sub.out


@pytest.mark.parametrize("kind", ["triangle", "barycentric"])
@pytest.mark.parametrize("sorted_faces", [False, True])
def test_fast_frame_matches_reference(head, subject, kind, sorted_faces) -> None:
    rng = np.random.default_rng(3)
    avatar = random_avatar(head, kind, rng, sorted_faces=sorted_faces)
    fast = FastAvatar(avatar, subject)
    assert 0 < fast.moving < avatar.count
    session = fast.session()
    for scale in (0.0, 1.0, 2.5):
        expr, rot = random_flame(rng, scale)
        state = session.run(expr, rot)
        assert state.position.dtype == np.float32 and state.rotation.shape == (avatar.count, 4)
        assert_same_state(state, reference_frame(avatar, subject, expr, rot))


@pytest.mark.parametrize("kind", ["triangle", "barycentric"])
def test_deform_kernels_on_arbitrary_vertices(head, subject, kind) -> None:
    """Every Gaussian deformed ("all") on randomly perturbed vertices, not only LBS output."""
    rng = np.random.default_rng(4)
    avatar = random_avatar(head, kind, rng, n=3000)
    fast = FastAvatar(avatar, subject, gaussians="all")
    verts = head.v_template + rng.normal(0, 1e-3, head.v_template.shape)
    state = fast.session().deform(verts[fast.lbs.vertex_ids])
    assert_same_state(state, avatar.deformer().deform(verts))


def test_default_avatar_fast_path(subject) -> None:
    from ofera.avatar import load_avatar

    avatar = load_avatar("default")
    fast = FastAvatar(avatar, HeadSubject.create(avatar.head))
    assert fast.runs < fast.moving / 3  # its Gaussians are laid out face by face
    rng = np.random.default_rng(5)
    session = fast.session()
    for _ in range(2):
        expr, rot = random_flame(rng)
        assert_same_state(session.run(expr, rot), reference_frame(avatar, fast.subject, expr, rot))


@pytest.mark.parametrize("coords", ["flame", "unity"])
def test_states_carry_their_varying_rows_and_encode_to_the_codecs_bytes(head, subject, coords) -> None:
    """Every state of a fast session carries the avatar's VaryingRows; outside them every state equals the neutral
    one, so a FrameWriter that re-encodes only those rows into its pooled buffers gives the codec's bytes."""
    from ofera.streaming.encode_fast import frame_writer
    from ofera_protocol import Frame, FrameFormat, encode_frame, to_coords

    rng = np.random.default_rng(12)
    avatar = random_avatar(head, "triangle", rng, sorted_faces=True)
    fast = FastAvatar(avatar, subject)
    assert np.array_equal(fast.varying.indices, np.flatnonzero(fast.selected))
    others = ~fast.selected
    fmt = FrameFormat("f16", avatar.count, False, None)
    writer = frame_writer(fmt, coords, pool=2)
    sessions = [fast.session(pool_size=2), fast.session(pool_size=2)]  # two pools, one VaryingRows
    for i in range(6):
        expr, rot = random_flame(rng, 1.5)
        state = sessions[i % 2].run(expr, rot)
        assert state.varying is fast.varying
        for got, neutral in zip((state.position, state.rotation, state.scale),
                                (fast.neutral.position, fast.neutral.rotation, fast.neutral.scale)):
            assert np.array_equal(got[others], neutral[others])
        data = writer.encode(i, i, {"total": i}, state.position, state.rotation, state.scale, varying=state.varying)
        p, r = to_coords(state.position, state.rotation, coords)
        assert bytes(data) == encode_frame(Frame(seq=i, t=i, timing={"total": i}, position=p, rotation=r,
                                                 scale=state.scale), fmt)
    assert writer.partial >= 4


def test_movable_set_is_close_and_exact_set_is_exact(head, subject) -> None:
    rng = np.random.default_rng(6)
    avatar = random_avatar(head, "triangle", rng)
    expr, rot = random_flame(rng, 2.0)
    ref = reference_frame(avatar, subject, expr, rot)
    movable = FastAvatar(avatar, subject, gaussians="movable")
    assert movable.moving == int(avatar.movable.sum())
    state = movable.session().run(expr, rot)
    assert_same_state(state, ref, rows=avatar.movable)
    # The rest differ from the reference by at most the tolerance's motion (0.1 um per unit coefficient).
    assert np.abs(state.position - ref.position).max() < 1e-6


def test_root_or_neck_rotation_is_refused(head, subject) -> None:
    rng = np.random.default_rng(7)
    session = FastAvatar(random_avatar(head, "triangle", rng, n=200), subject).session()
    rot = pose_rotations(1, neck=np.array([0.0, 0.2, 0.0]))[0]
    with pytest.raises(ValueError, match="root and neck"):
        session.head(np.zeros(10), rot)
    root = pose_rotations(1)[0].copy()
    root[0, 0, 0] = np.nextafter(1.0, 2.0)  # one ulp off the identity: refused too
    for bad in (root, root[:4], np.full((5, 3, 3), np.nan)):  # and a wrong shape, and NaN
        with pytest.raises(ValueError, match="root and neck"):
            session.head(np.zeros(10), bad)
    ok = pose_rotations(1, jaw=np.array([0.3, 0.0, 0.0]))[0]  # (float64; its float32 rounding gives others)
    want = session.head(np.zeros(10), ok).copy()  # (head's output buffer is reused by the next call)
    for same in (ok[None], ok.tolist()):  # another shape and type of the same rotations
        np.testing.assert_array_equal(session.head(np.zeros(10), same), want)
    assert not np.array_equal(session.head(np.zeros(10), ok.astype(np.float32)), want)  # really another input


def test_pool_never_rewrites_a_state_in_use(head, subject) -> None:
    rng = np.random.default_rng(8)
    session = FastAvatar(random_avatar(head, "triangle", rng, n=500), subject).session(pool_size=3)
    e1, r1 = random_flame(rng)
    kept = session.run(e1, r1)
    snapshot = kept.position.copy()
    view = kept.rotation[:10]  # a view keeps its array busy too
    rot_snapshot = view.copy()
    del kept
    for _ in range(5):  # more frames than the pool holds
        session.run(*random_flame(rng))
    np.testing.assert_array_equal(view, rot_snapshot)
    assert not view.flags.writeable
    gc.collect()
    # Dropped states are recycled: a steady stream keeps using the same few buffers. At most two states are
    # referenced at once (the kept view's and the newest frame's) and the pool holds 3: none is ever unpooled.
    before = session.pool.created
    for _ in range(10):
        s = session.run(*random_flame(rng))
        del s
    assert session.pool.created == before <= 3 and session.pool.unpooled == 0
    assert snapshot.shape == (500, 3)


def test_state_pool_reuses_only_idle_states() -> None:
    from ofera.avatar import GaussianState

    n = 4
    template = GaussianState(np.zeros((n, 3), np.float32), np.tile(np.float32([0, 0, 0, 1]), (n, 1)),
                             np.ones((n, 3), np.float32))
    pool = StatePool(template, size=2)
    a, pa, _, _ = pool.acquire()
    pa[0] = 7
    b, _, _, _ = pool.acquire()
    c, _, _, _ = pool.acquire()  # both pooled ones busy: an unpooled one
    assert pool.unpooled == 1 and a is not b and c is not a and c is not b
    assert a.position[0, 0] == 7 and not a.position.flags.writeable
    del a, pa
    d, _, _, _ = pool.acquire()
    assert d.position[0, 0] == 7  # the first entry again (its values are the last frame's)


def test_rotation_matrices_from_axis_angle_match(head, subject) -> None:
    """float64 rotations (not only FLAME values' float32) go through the same kernel."""
    rng = np.random.default_rng(9)
    avatar = random_avatar(head, "barycentric", rng, n=1000)
    fast = FastAvatar(avatar, subject)
    rot = np.stack([np.eye(3), np.eye(3), *axis_angle_to_matrix(rng.normal(0, 0.2, (3, 3)))])
    expr = rng.normal(0, 1, 50)
    assert_same_state(fast.session().run(expr, rot), reference_frame(avatar, subject, expr, rot))


def random_flame_values(rng, pose_sd: float) -> np.ndarray:
    """(68,) float32 FLAME values: normal expression, 6D rotations near the neutral ones (sd ``pose_sd``)."""
    y = neutral_flame_values(1)[0]
    y[:50] = rng.normal(0, 1, 50)
    y[50:] += rng.normal(0, pose_sd, 18).astype(np.float32)
    return y


def test_flame_values_split_matches_reference(head, subject) -> None:
    rng = np.random.default_rng(10)
    session = FastAvatar(random_avatar(head, "triangle", rng, n=100), subject).session()
    for _ in range(20):
        y = random_flame_values(rng, 0.5)
        expr, rot = session.flame(y)
        ref_expr, ref_rot = split_flame_values(y)
        np.testing.assert_array_equal(expr, ref_expr)
        np.testing.assert_allclose(rot, ref_rot, rtol=0, atol=1e-6)


@pytest.mark.parametrize("kind", ["triangle", "barycentric"])
def test_parallel_kernels_match_serial(head, subject, kind) -> None:
    rng = np.random.default_rng(11)
    fast = FastAvatar(random_avatar(head, kind, rng, sorted_faces=True), subject)
    expr, rot = random_flame(rng)
    a = fast.session(parallel=True).run(expr, rot)
    b = fast.session(parallel=False).run(expr, rot)
    np.testing.assert_array_equal(a.position, b.position)
    np.testing.assert_array_equal(a.rotation, b.rotation)
    np.testing.assert_array_equal(a.scale, b.scale)


class _ThreadsAsked:
    """What FastSession.flame_delta asks of a DirectDelta, answering with the thread choice it was given."""

    def head_select(self, y: np.ndarray, parallel: bool) -> SimpleNamespace:
        return SimpleNamespace(counts=(0, parallel))


def test_auto_sessions_thread_while_alone_and_faster(head, subject, monkeypatch: pytest.MonkeyPatch) -> None:
    """Automatic sessions: a frame's kernels (dense or a delta frame's select) on threads while the session is alone
    and its threaded frames were faster, the same bits; two sessions computing: one thread each; a session whose
    serial frames were faster: one thread."""
    import ofera.avatar.fast as fast_module

    monkeypatch.setattr(fast_module, "load_average", lambda: 0.0)  # the test machine's load is not the subject
    monkeypatch.setattr(fast_module.numba, "get_num_threads", lambda: 2)
    rng = np.random.default_rng(12)
    fast = FastAvatar(random_avatar(head, "triangle", rng, sorted_faces=True), subject)
    activity = Activity(window_s=60.0)
    assert fast.session().parallel is False  # single-threaded unless asked (avatar.fast says why)
    a, b = (fast.session(parallel=None) for _ in range(2))
    a.activity = b.activity = activity
    for _ in range(3):
        a.choice.record(True, 1)
        a.choice.record(False, 10)
    expr, rot = random_flame(rng)
    ref = fast.session(parallel=False).run(expr, rot)
    state = a.run(expr, rot)
    np.testing.assert_array_equal(state.position, ref.position)
    assert a.threaded  # alone, threads faster: a dense frame on threads, the same bits
    y = np.zeros(68, np.float32)
    y[50:] = [1, 0, 0, 0, 1, 0] * 3
    assert a.flame_delta(y, _ThreadsAsked()).counts[1] and a.threaded  # and a delta frame's kernel
    state = b.run(expr, rot)
    np.testing.assert_array_equal(state.position, ref.position)
    assert not b.threaded
    assert not a.flame_delta(y, _ThreadsAsked()).counts[1]  # b computed a frame within the window: one thread
    c = fast.session(parallel=None)
    c.activity = Activity(window_s=60.0)
    for _ in range(3):
        c.choice.record(True, 10)
        c.choice.record(False, 1)
    state = c.run(expr, rot)
    np.testing.assert_array_equal(state.position, ref.position)
    assert not c.threaded  # alone, but its serial frames were faster
    c._start()
    c._end(0)  # a frame with no work (an avatar nothing moves) is recorded too
    assert len(c.choice.times[False]) == 5
    later: list = []  # the server's Source: recorded once the frame is delivered
    c.defer = later.append
    c._start()
    c._end(7)
    assert len(c.choice.times[False]) == 5 and len(later) == 1
    fn, args = later.pop()
    fn(*args)
    assert len(c.choice.times[False]) == 6


def test_the_kernel_threads_setting_reaches_every_session(monkeypatch: pytest.MonkeyPatch) -> None:
    """OFERA_KERNEL_THREADS -> Settings.kernel_threads -> the avatar's assets -> each pipeline's fast session."""
    from ofera.streaming.config import Settings
    from ofera.streaming.registry import AvatarRegistry

    assert Settings().kernel_threads == "auto"
    assert AvatarRegistry(Settings()).get("default").pipeline("arkit52").fast.parallel is None
    monkeypatch.setenv("OFERA_KERNEL_THREADS", "serial")
    settings = Settings()
    assert settings.kernel_threads == "serial"
    assets = AvatarRegistry(settings).get("default")
    assert assets.parallel is False and assets.pipeline("arkit52").fast.parallel is False
    with pytest.raises(ValueError, match="kernel_threads"):
        Settings(kernel_threads="two")


def test_flame_head_is_head_of_flame(head, subject) -> None:
    """The fused call (FLAME split + subset LBS, one numba call) gives head(flame(y)) bit for bit, and its split."""
    rng = np.random.default_rng(13)
    session = FastAvatar(random_avatar(head, "triangle", rng, n=300), subject).session()
    for _ in range(5):
        y = random_flame_values(rng, 0.3)
        expr, rot = (a.copy() for a in session.flame(y))
        want = session.head(expr, rot).copy()
        np.testing.assert_array_equal(session.flame_head(y), want)
        np.testing.assert_array_equal(session._expr, expr)
        np.testing.assert_array_equal(session._rot, rot)
    with pytest.raises(ValueError, match="68 entries"):
        session.flame_head(np.zeros(67, np.float32))
    # read-only values (a remote room member's, from the bus) take the kernels compiled for writable ones
    from ofera.head.lbs_fast import flame_subset_lbs

    y = random_flame_values(rng, 0.3)
    want = session.flame_head(y).copy()
    compiled = len(flame_subset_lbs.signatures)
    frozen = y.copy()
    frozen.flags.writeable = False
    np.testing.assert_array_equal(session.flame_head(frozen), want)
    assert len(flame_subset_lbs.signatures) == compiled
