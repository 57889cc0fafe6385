"""The FLAME fitter (the paired data's ground truth) and the evaluation geometry."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.head import HeadSubject, lbs, pose_rotations
from ofera.head.rotations import axis_angle_to_matrix, euler_xy_to_matrix
from ofera.mapping.flame_values import join_flame_values, split_flame_values
from ofera.training.paired import FlameFitter, fit_vertices, region_masks, vertices_from_flame
from ofera.training.paired.fit import pose_blend, unpose_blend


@pytest.fixture(scope="module")
def ids(head):
    return fit_vertices(head)


def _head_meshes(head, rng, t, shape, ids, expr_scale=1.0, jaw_open=(0.0, 0.45)):
    expr = rng.normal(0.0, expr_scale, (t, 50))
    jaw = axis_angle_to_matrix(np.stack([rng.uniform(*jaw_open, t), rng.normal(0, 0.08, t),
                                         rng.normal(0, 0.03, t)], 1))
    left = euler_xy_to_matrix(rng.normal(0, 0.3, t), rng.normal(0, 0.2, t))
    right = euler_xy_to_matrix(rng.normal(0, 0.3, t), rng.normal(0, 0.2, t))
    verts, _ = lbs(HeadSubject.create(head, shape), expr, pose_rotations(t, jaw=jaw, left_eye=left, right_eye=right))
    return verts[:, ids], join_flame_values(expr, jaw, left, right)


def test_fitter_recovers_the_head_models_own_parameters(head, ids):
    """With the rig replaced by the head model itself, the fit is exact (sanity of the fitter)."""
    rng = np.random.default_rng(0)
    shape = rng.normal(size=head.shape_dims)
    points, truth = _head_meshes(head, rng, 60, shape, ids)
    res = FlameFitter(head, shape, ids, ridge=0.0).fit(points)
    e_fit, r_fit = split_flame_values(res.flame)
    e_true, r_true = split_flame_values(truth)
    np.testing.assert_allclose(e_fit, e_true, atol=1e-5)
    np.testing.assert_allclose(r_fit, r_true, atol=1e-7)
    assert res.rms.max() < 1e-8


def test_jaw_fit_recovers_a_known_rotation(head, ids):
    rng = np.random.default_rng(1)
    aa = np.array([[0.0, 0.0, 0.0], [0.35, 0.0, 0.0], [0.2, 0.1, 0.0], [0.42, -0.08, 0.03], [0.05, 0.0, -0.04]])
    jaw = axis_angle_to_matrix(aa)
    verts, _ = lbs(HeadSubject.create(head), np.zeros((5, 50)), pose_rotations(5, jaw=jaw))
    fitter = FlameFitter(head, None, ids)  # default ridge: as the benchmark uses it
    res = fitter.fit(verts[:, ids] + rng.normal(0.0, 2e-5, (5, len(ids), 3)))  # 20 micrometres of noise
    np.testing.assert_allclose(res.jaw_axis_angle, aa, atol=2e-3)
    expr, rot = split_flame_values(res.flame)
    np.testing.assert_allclose(rot[:, 2], jaw, atol=2e-3)
    assert np.abs(expr).max() < 0.05


def test_with_identity_equals_a_fresh_fitter(head, ids):
    rng = np.random.default_rng(2)
    shape = rng.normal(size=head.shape_dims)
    points, _ = _head_meshes(head, rng, 8, shape, ids)
    a = FlameFitter(head, None, ids).with_identity(shape).fit(points)
    b = FlameFitter(head, shape, ids).fit(points)
    np.testing.assert_allclose(a.flame, b.flame, atol=1e-10)


def test_any_vertex_order_fits_the_same(head, ids):
    rng = np.random.default_rng(3)
    points, _ = _head_meshes(head, rng, 6, None, ids)
    perm = rng.permutation(len(ids))
    a = FlameFitter(head, None, ids).fit(points)
    b = FlameFitter(head, None, ids[perm]).fit(points[:, perm])
    np.testing.assert_allclose(a.flame, b.flame, atol=1e-8)


def test_fitter_rejects_bad_vertex_sets(head, ids):
    with pytest.raises(ValueError, match="eyeball"):
        FlameFitter(head, None, ids[: len(ids) // 2])
    with pytest.raises(ValueError, match="points must be"):
        FlameFitter(head, None, ids).fit(np.zeros((2, 5, 3)))


def test_unpose_inverts_the_blended_jaw_transform():
    rng = np.random.default_rng(4)
    u = rng.normal(size=(6, 40, 3))
    omega = rng.normal(0, 0.5, (6, 3))
    omega[0] = 0.0
    share = rng.uniform(0, 1, 40)
    share[:5] = (0.0, 1.0, 0.5, 1.0, 0.0)
    y = pose_blend(u, omega, share)
    rot = axis_angle_to_matrix(omega)
    reference = np.stack([  # plain reference: ((1 - a) I + a R) u, vertex by vertex
        np.stack([((1 - a) * np.eye(3) + a * rot[t]) @ v for a, v in zip(share, u[t])]) for t in range(6)
    ])
    np.testing.assert_allclose(y, reference, atol=1e-12)
    np.testing.assert_allclose(unpose_blend(y, omega, share), u, atol=1e-10)


def test_vertices_from_flame_matches_the_reference_lbs(head):
    rng = np.random.default_rng(5)
    shape = rng.normal(size=head.shape_dims)
    t = 4
    expr = rng.normal(size=(t, 50))
    jaw, left, right = (axis_angle_to_matrix(rng.normal(0, 0.2, (t, 3))) for _ in range(3))
    rotations = pose_rotations(t, jaw=jaw, left_eye=left, right_eye=right)
    reference, _ = lbs(HeadSubject.create(head, shape), expr, rotations)
    flame = join_flame_values(expr, jaw, left, right)
    fast = vertices_from_flame(head, flame, shape, chunk=3, dtype=np.float64)
    np.testing.assert_allclose(fast, reference, atol=1e-12)
    some = np.array([5, 100, 4000, head.num_vertices - 1])
    np.testing.assert_allclose(vertices_from_flame(head, flame, shape, vertex_ids=some), reference[:, some], atol=1e-6)


def test_region_masks(head):
    masks = region_masks(head)
    assert set(masks) == {"eyes", "brows", "mouth_and_jaw", "face"}
    for name in ("eyes", "brows", "mouth_and_jaw"):
        assert 100 < masks[name].sum() < head.num_vertices // 2, name
    assert not (masks["eyes"] & masks["brows"]).any()
    assert not (masks["eyes"] & masks["mouth_and_jaw"]).any()
    assert masks["eyes"][head.vertex_labels["eyeball_left"]].all()
    assert masks["mouth_and_jaw"][head.vertex_labels["lips"]].all()
    lm = head.landmarks
    ys = head.v_template[:, 1]
    assert ys[masks["brows"]].mean() > lm["eye_left"][1] > ys[masks["mouth_and_jaw"]].mean()
