"""The head model's forward pass against an independent loop-based computation."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.head import HeadSubject, forward, lbs
from ofera.head.rotations import axis_angle_to_matrix


def slow_lbs(model, expr, rots):
    """Per-vertex, per-joint loops straight from the FLAME formulas (one frame)."""
    v = model.v_template + np.einsum("vce,e->vc", model.exprdirs[:, :, : len(expr)], expr)
    joints = np.array([sum(model.j_regressor[k, i] * v[i] for i in range(len(v))) for k in range(5)])
    feat = np.concatenate([(rots[k] - np.eye(3)).reshape(-1) for k in range(1, 5)])
    v_po = v + (feat @ model.posedirs).reshape(-1, 3)
    world = []
    for k in range(5):
        local = np.eye(4)
        local[:3, :3] = rots[k]
        p = model.parents[k]
        local[:3, 3] = joints[k] - (joints[p] if p >= 0 else 0)
        world.append(local if p < 0 else world[p] @ local)
    a = []
    for k in range(5):
        m = world[k].copy()
        m[:3, 3] = world[k][:3, 3] - world[k][:3, :3] @ joints[k]
        a.append(m)
    out = np.zeros_like(v)
    for i in range(len(v)):
        t = sum(model.weights[i, k] * a[k] for k in range(5))
        out[i] = t[:3, :3] @ v_po[i] + t[:3, 3]
    return out


def random_pose(rng, scale=0.3):
    return axis_angle_to_matrix(rng.normal(size=(5, 3)) * scale)


def test_forward_matches_slow_reference(head):
    rng = np.random.default_rng(0)
    expr = rng.normal(size=20)
    rots = random_pose(rng)
    fast, _ = lbs(HeadSubject.create(head), expr[None], rots[None])
    np.testing.assert_allclose(fast[0], slow_lbs(head, expr, rots), atol=1e-10)


def test_zero_parameters_reproduce_template(head):
    np.testing.assert_allclose(forward(head)[0], head.v_template, atol=1e-12)


def test_jaw_moves_only_jaw_weighted_vertices(head):
    v = forward(head, jaw=[0.3, 0.0, 0.0])[0]
    moved = np.linalg.norm(v - head.v_template, axis=1) > 1e-9
    jaw_weighted = head.weights[:, 2] > 0
    posed_corrective = np.abs(head.posedirs[9:18]).reshape(9, -1, 3).sum(axis=(0, 2)) > 0
    assert moved.any()
    assert not (moved & ~jaw_weighted & ~posed_corrective).any()
    assert (moved[jaw_weighted]).all()


def test_eyes_rotate_rigidly_about_their_centre(head):
    r = axis_angle_to_matrix(np.array([0.1, 0.4, 0.0]))
    v = forward(head, left_eye=r)[0]
    eye = head.vertex_labels["eyeball_left"]
    centre = head.j_regressor[3] @ head.v_template
    np.testing.assert_allclose(v[eye], (head.v_template[eye] - centre) @ r.T + centre, atol=1e-12)
    np.testing.assert_allclose(v[~eye], head.v_template[~eye], atol=1e-12)


def test_batched_equals_single(head):
    rng = np.random.default_rng(1)
    expr = rng.normal(size=(3, 50))
    rots = np.stack([random_pose(rng) for _ in range(3)])
    subj = HeadSubject.create(head, rng.normal(size=10))
    batch, _ = lbs(subj, expr, rots)
    for i in range(3):
        np.testing.assert_allclose(batch[i], lbs(subj, expr[i : i + 1], rots[i : i + 1])[0][0], atol=1e-12)


def test_rotation_forms_agree(head):
    from ofera.head.rotations import matrix_to_rot6d

    r = axis_angle_to_matrix(np.array([0.2, 0.0, 0.05]))
    a = forward(head, jaw=r)
    np.testing.assert_allclose(forward(head, jaw=[0.2, 0.0, 0.05]), a, atol=1e-12)
    np.testing.assert_allclose(forward(head, jaw=matrix_to_rot6d(r)), a, atol=1e-12)


def test_torch_matches_numpy(head):
    torch = pytest.importorskip("torch")
    from ofera.head.lbs_torch import TorchHead

    rng = np.random.default_rng(2)
    expr = rng.normal(size=(2, 50))
    rots = np.stack([random_pose(rng) for _ in range(2)])
    shape = rng.normal(size=20)
    ref, _ = lbs(HeadSubject.create(head, shape), expr, rots)
    th = TorchHead(head, torch.tensor(shape), dtype=torch.float64)
    out = th(torch.tensor(expr), torch.tensor(rots)).numpy()
    np.testing.assert_allclose(out, ref, atol=1e-10)


def test_procedural_head_is_deterministic_and_head_sized(head):
    from ofera.head.procedural import make_procedural_head

    again = make_procedural_head()
    np.testing.assert_array_equal(again.v_template, head.v_template)
    np.testing.assert_array_equal(again.exprdirs, head.exprdirs)
    extent = head.v_template.max(0) - head.v_template.min(0)
    assert 0.14 < extent[0] < 0.22 and 0.2 < extent[1] < 0.35 and 0.15 < extent[2] < 0.26
    assert head.expr_dims >= 50 and head.num_joints == 5
    np.testing.assert_allclose(head.weights.sum(1), 1.0, atol=1e-12)
    # The face looks +z: the nose tip is the front-most point of the face.
    assert head.landmarks["nose_tip"][2] > head.landmarks["eye_left"][2]
    assert head.landmarks["eye_left"][0] > 0  # FLAME: the left eye is on +x


def test_basis_signs_do_not_follow_rounding():
    """The SVD's sign of each column is LAPACK's (it differed between two CPUs for 8 of the head's 50 expression
    columns, and so did the FLAME values an EPM trained on one machine meant): _orthogonalise fixes it by a rule
    rounding cannot flip, even where a column's largest entries are mirrored pairs of equal size."""
    from ofera.head.procedural import _orthogonalise

    rng = np.random.default_rng(3)
    half = rng.standard_normal((200, 3, 6))
    fields = np.concatenate([half, half * np.array([-1.0, 1.0, 1.0])[None, :, None]])  # mirrored in x: tied sizes
    basis = _orthogonalise(fields, 6, 1.0)
    for noise in (1e-13, -1e-13):
        again = _orthogonalise(fields + noise * rng.standard_normal(fields.shape), 6, 1.0)
        np.testing.assert_allclose(again, basis, atol=1e-9)
    flipped = _orthogonalise(-fields, 6, 1.0)  # any sign of the input columns: the same basis
    np.testing.assert_allclose(flipped, basis, atol=1e-9)


def test_expression_basis_is_local_and_spares_eyeballs(head):
    eyes = head.vertex_labels["eyeball_left"] | head.vertex_labels["eyeball_right"]
    assert np.abs(head.exprdirs[eyes]).max() == 0.0
    back = head.v_template[:, 2] < -0.05
    assert np.abs(head.exprdirs[back]).max() < 1e-6
    mags = np.linalg.norm(head.exprdirs, axis=1).max(axis=0)
    assert (mags > 1e-4).all() and (mags < 0.02).all()  # each unit coefficient moves 0.1..20 mm
