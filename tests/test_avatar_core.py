"""Bindings and deformation: face frames, rigid motion, neutral pose, movable Gaussians (both binding types)."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.avatar import AvatarError, BarycentricBinding, GaussianAvatar, TriangleBinding
from ofera.avatar.frames import face_frames, face_scales
from ofera.avatar.movable import movable_vertices
from ofera.head.lbs import forward
from ofera.head.rotations import axis_angle_to_matrix, matrix_to_quaternion, quaternion_multiply


def random_rotations(rng, n):
    return axis_angle_to_matrix(rng.normal(size=(n, 3)))


def random_triangle_avatar(head, rng, n=3000) -> GaussianAvatar:
    face = rng.integers(0, head.num_faces, n)
    binding = TriangleBinding(
        face=face,
        position=rng.normal(scale=0.5, size=(n, 3)).astype(np.float32),
        rotation=rng.normal(size=(n, 4)).astype(np.float32),
        log_scale=rng.normal(-1.0, 0.5, size=(n, 3)).astype(np.float32),
    )
    return GaussianAvatar(head, binding, rng.random(n).astype(np.float32),
                          rng.normal(size=(n, 16, 3)).astype(np.float32), name="random-triangle")


def random_barycentric_avatar(head, rng, n=3000) -> GaussianAvatar:
    face = rng.integers(0, head.num_faces, n)
    binding = BarycentricBinding(
        face=face,
        bary=rng.dirichlet(np.ones(3), n).astype(np.float32),
        offset=rng.normal(size=n).astype(np.float32),
        rotation=rng.normal(size=(n, 4)).astype(np.float32),
        log_scale=rng.normal(-6.0, 0.5, size=(n, 3)).astype(np.float32),
        face_scale_canonical=face_scales(head.v_template, head.faces).astype(np.float32),
    )
    return GaussianAvatar(head, binding, rng.random(n).astype(np.float32),
                          rng.normal(size=(n, 1, 3)).astype(np.float32), name="random-barycentric")


@pytest.fixture(scope="module")
def avatars(head):
    rng = np.random.default_rng(1)
    return {"triangle": random_triangle_avatar(head, rng), "barycentric": random_barycentric_avatar(head, rng)}


def same_rotation(q1_xyzw, q2_xyzw, atol):
    return np.all(np.abs(np.abs(np.sum(q1_xyzw * q2_xyzw, axis=1)) - 1.0) < atol)


def test_face_frames_orthonormal_det_plus_one(head):
    jaw = axis_angle_to_matrix(np.array([0.3, 0.0, 0.0]))
    for verts in (head.v_template, forward(head, np.full((1, 10), 1.5), jaw=jaw)[0]):
        rot, scale, centre = face_frames(verts, head.faces)
        assert np.allclose(rot.transpose(0, 2, 1) @ rot, np.eye(3), atol=1e-9)
        assert np.allclose(np.linalg.det(rot), 1.0, atol=1e-9)
        assert np.all(scale > 0) and np.allclose(centre, verts[head.faces].mean(axis=1))
        # a1 is the normal of the face, a0 along the first edge
        e1 = verts[head.faces[:, 1]] - verts[head.faces[:, 0]]
        e2 = verts[head.faces[:, 2]] - verts[head.faces[:, 0]]
        assert np.allclose(np.sum(rot[:, :, 1] * e1, axis=1), 0, atol=1e-12)
        assert np.allclose(np.sum(rot[:, :, 1] * e2, axis=1), 0, atol=1e-12)


@pytest.mark.parametrize("kind", ["triangle", "barycentric"])
def test_rigid_motion_moves_every_gaussian_rigidly(avatars, head, kind):
    avatar = avatars[kind]
    rng = np.random.default_rng(7)
    rot, shift = random_rotations(rng, 1)[0], rng.normal(scale=0.2, size=3)
    deformer = avatar.deformer()
    verts = forward(head, rng.normal(size=(1, 20)))[0]
    before = deformer.deform(verts)
    after = deformer.deform(verts @ rot.T + shift)
    assert np.allclose(after.position, before.position @ rot.T + shift, atol=2e-6)
    assert np.allclose(after.scale, before.scale, rtol=1e-5)
    q = matrix_to_quaternion(rot)  # (w, x, y, z)
    composed = quaternion_multiply(q, before.rotation_wxyz().astype(np.float64))
    assert same_rotation(after.rotation_wxyz(), composed, 1e-5)


@pytest.mark.parametrize("kind", ["triangle", "barycentric"])
def test_state_contract(avatars, kind):
    state = avatars[kind].neutral()
    n = avatars[kind].count
    for arr, width in ((state.position, 3), (state.rotation, 4), (state.scale, 3)):
        assert arr.shape == (n, width) and arr.dtype == np.float32 and np.all(np.isfinite(arr))
    assert np.allclose(np.linalg.norm(state.rotation, axis=1), 1.0, atol=1e-6)
    assert np.all(state.scale > 0)


def test_neutral_reproduces_world_attributes_triangle(head):
    rng = np.random.default_rng(3)
    n = 2000
    face = rng.integers(0, head.num_faces, n)
    pos = head.v_template[head.faces[face]].mean(axis=1) + rng.normal(scale=0.002, size=(n, 3))
    rot = matrix_to_quaternion(random_rotations(rng, n))
    scale = rng.uniform(1e-4, 3e-3, (n, 3))
    binding = TriangleBinding.from_world(face, pos, rot, scale, head.v_template, head.faces)
    avatar = GaussianAvatar(head, binding, np.ones(n, np.float32), np.zeros((n, 1, 3), np.float32))
    state = avatar.neutral()
    assert np.allclose(state.position, pos, atol=1e-6)
    assert np.allclose(state.scale, scale, rtol=1e-5)
    assert same_rotation(state.rotation_wxyz(), rot, 1e-5)


def test_neutral_reproduces_canonical_attributes_barycentric(avatars, head):
    avatar = avatars["barycentric"]
    b = avatar.binding
    state = avatar.neutral()
    # canonical face scales equal the neutral ones, so the scale is exactly exp(local log scale)
    assert np.allclose(state.scale, np.exp(b.log_scale), rtol=1e-5)
    corners = head.v_template[head.faces[b.face]]
    v0, v1, v2 = corners[:, 0], corners[:, 1], corners[:, 2]
    expected = np.einsum("nk,nkc->nc", b.bary, corners) + np.cross(v1 - v0, v2 - v0) * 0.05 * np.tanh(b.offset)[:, None]
    assert np.allclose(state.position, expected, atol=1e-7)
    rot_f = face_frames(head.v_template, head.faces[b.face])[0]
    local = b.rotation / np.linalg.norm(b.rotation, axis=1, keepdims=True)
    assert same_rotation(state.rotation_wxyz(), quaternion_multiply(matrix_to_quaternion(rot_f), local), 1e-5)


def test_triangle_matches_upstream_formula(avatars, head):
    avatar = avatars["triangle"]
    b = avatar.binding
    verts = forward(head, np.ones((1, 5)) * 0.8)[0]
    state = avatar.deformer().deform(verts)
    rot_f, s_f, c_f = face_frames(verts, head.faces[b.face])
    expected = np.einsum("nij,nj->ni", rot_f, b.position) * s_f[:, None] + c_f
    assert np.allclose(state.position, expected, atol=1e-6)
    assert np.allclose(state.scale, np.exp(b.log_scale) * s_f[:, None], rtol=1e-5)


@pytest.mark.parametrize("kind", ["triangle", "barycentric"])
def test_non_movable_gaussians_stay_put(avatars, head, kind):
    avatar = avatars[kind]
    assert avatar.movable.dtype == bool and 0 < avatar.movable.sum() < avatar.count
    rng = np.random.default_rng(5)
    jaw = axis_angle_to_matrix(np.array([0.35, 0, 0]))
    eye = axis_angle_to_matrix(np.array([0.1, 0.3, 0]))
    verts = forward(head, rng.normal(size=(1, head.expr_dims)) * 2, jaw=jaw, left_eye=eye, right_eye=eye)[0]
    moved, rest = avatar.deformer().deform(verts), avatar.neutral()
    static = ~avatar.movable
    assert np.allclose(moved.position[static], rest.position[static], atol=1e-6)
    assert np.abs(moved.position[avatar.movable] - rest.position[avatar.movable]).max() > 1e-3


def test_movable_vertices_cover_face_joints_and_expressions(head):
    mv = movable_vertices(head)
    assert mv[head.weights[:, 2] > 0.01].all() and mv[head.vertex_labels["eyeball_left"]].all()
    assert not mv[head.vertex_labels["neck"] & (head.v_template[:, 1] < -0.14)].any()


def test_invalid_bindings_are_refused(head):
    rng = np.random.default_rng(0)
    good = random_triangle_avatar(head, rng, 10)
    bad = TriangleBinding(np.full(10, head.num_faces), good.binding.position, good.binding.rotation,
                          good.binding.log_scale)
    with pytest.raises(AvatarError, match="faces"):
        GaussianAvatar(head, bad, good.opacity, good.sh)
    with pytest.raises(AvatarError, match="SH"):
        GaussianAvatar(head, good.binding, good.opacity, np.zeros((10, 5, 3), np.float32))
    with pytest.raises(ValueError, match="vertices"):
        good.deformer().deform(np.zeros((3, 3)))
