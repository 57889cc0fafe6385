"""Rotation utilities: round trips and agreement between forms (property-based)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from ofera.head import rotations as rt

vec3 = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0))
quat = arrays(np.float64, 4, elements=st.floats(-1.0, 1.0)).filter(lambda q: np.linalg.norm(q) > 1e-3)


def is_rotation(r):
    return np.allclose(r @ r.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(r), 1.0)


@given(vec3)
@settings(max_examples=200)
def test_axis_angle_round_trip(aa):
    r = rt.axis_angle_to_matrix(aa)
    assert is_rotation(r)
    np.testing.assert_allclose(rt.axis_angle_to_matrix(rt.matrix_to_axis_angle(r)), r, atol=1e-9)


@given(quat)
@settings(max_examples=300)
def test_quaternion_round_trip_every_branch(q):
    r = rt.quaternion_to_matrix(q)
    assert is_rotation(r)
    q2 = rt.matrix_to_quaternion(r)
    qn = q / np.linalg.norm(q)
    assert np.isclose(abs(np.dot(q2, qn)), 1.0, atol=1e-9)
    assert q2[0] >= 0


def test_quaternion_180_degree_turns():
    for axis in np.eye(3):
        r = rt.axis_angle_to_matrix(axis * np.pi)
        q = rt.matrix_to_quaternion(r)
        np.testing.assert_allclose(np.abs(q[1:]), axis, atol=1e-12)


@given(vec3)
def test_rot6d_round_trip_pytorch3d_rows(aa):
    r = rt.axis_angle_to_matrix(aa)
    d6 = rt.matrix_to_rot6d(r)
    np.testing.assert_allclose(d6, r[:2].reshape(-1))  # rows convention
    np.testing.assert_allclose(rt.rot6d_to_matrix(d6), r, atol=1e-9)


def test_rot6d_identity_and_gram_schmidt():
    np.testing.assert_allclose(rt.rot6d_to_matrix(np.array([1.0, 0, 0, 0, 1, 0])), np.eye(3))
    r = rt.rot6d_to_matrix(np.array([2.0, 0.1, 0, 0.5, 3, 0.2]))
    assert is_rotation(r)


@given(quat, quat)
def test_quaternion_product_composes_rotations(a, b):
    ra, rb = rt.quaternion_to_matrix(a), rt.quaternion_to_matrix(b)
    np.testing.assert_allclose(rt.quaternion_to_matrix(rt.quaternion_multiply(a, b)), ra @ rb, atol=1e-9)


def test_wire_order():
    np.testing.assert_array_equal(rt.wxyz_to_xyzw(np.array([1.0, 2, 3, 4])), [2.0, 3, 4, 1])
