"""The ARKit-style rig on the procedural head: shapes placed by meaning, nonlinear, per-subject style."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.training.paired.rig import CORRECTIVES, IDX, Rig, RigBasis, RigStyle, saturate


@pytest.fixture(scope="module")
def basis(head):
    return RigBasis.build(head)


@pytest.fixture(scope="module")
def rig(head, basis):
    return Rig(head, RigStyle.neutral(head.shape_dims), basis=basis)


def weights(**values: float) -> np.ndarray:
    w = np.zeros(51)
    for name, value in values.items():
        w[IDX[name]] = value
    return w


def nearest(head, point, label="skin"):
    d = np.linalg.norm(head.v_template - point, axis=1)
    d[~head.vertex_labels[label]] = np.inf
    return int(np.argmin(d))


def test_neutral_is_the_identity_shape(head, basis):
    rng = np.random.default_rng(0)
    style = RigStyle.random(rng, head.shape_dims)
    rig = Rig(head, style, basis=basis)
    np.testing.assert_allclose(rig.mesh(np.zeros(51))[0], rig.subject.v_id, atol=1e-12)


def test_blink_closes_the_upper_lid_and_saturates(head, rig):
    eye = head.landmarks["eye_left"]
    lid = nearest(head, eye + [0.0, 0.0056, 0.013])
    m = rig.mesh(np.stack([weights(eyeBlinkLeft=v) for v in (0.0, 0.2, 0.8, 1.0)]))
    drop = m[0, lid, 1] - m[:, lid, 1]
    assert drop[3] > 0.006  # the lid margin comes down over the eyeball (the opening is ~10 mm high)
    assert drop[1] - drop[0] > drop[3] - drop[2]  # saturating: the last 0.2 adds less than the first 0.2
    centre = rig._eye_centre[0]  # the lid slides on the eyeball: its distance to the centre barely changes
    assert abs(np.linalg.norm(m[3, lid] - centre) - np.linalg.norm(m[0, lid] - centre)) < 0.0015
    right_lid = nearest(head, head.landmarks["eye_right"] + [0.0, 0.0056, 0.013])
    assert abs(m[3, right_lid, 1] - m[0, right_lid, 1]) < 1e-9  # one side only
    assert saturate(np.array([1.0]))[0] == pytest.approx(1.0)


def test_jaw_open_is_a_rotation_of_the_jaw(head, rig):
    chin = nearest(head, head.landmarks["chin"])
    m = rig.mesh(np.stack([weights(), weights(jawOpen=1.0)]))
    move = m[1, chin] - m[0, chin]
    assert move[1] < -0.015  # the chin drops by centimetres
    pivot = rig._pivot
    assert abs(np.linalg.norm(m[1, chin] - pivot) - np.linalg.norm(m[0, chin] - pivot)) < 1e-5  # rotation


def test_smile_lifts_the_corner_and_gaze_rotates_the_eyeball(head, rig):
    corner = nearest(head, head.landmarks["mouth_corner_left"])
    m = rig.mesh(np.stack([weights(), weights(mouthSmileLeft=1.0), weights(mouthFrownLeft=1.0)]))
    assert m[1, corner, 1] - m[0, corner, 1] > 0.005 and m[1, corner, 0] > m[0, corner, 0]
    assert m[2, corner, 1] - m[0, corner, 1] < -0.004
    ball = head.vertex_labels["eyeball_left"]
    pupil = head.vertex_labels["pupil_left"]
    m = rig.mesh(np.stack([weights(), weights(eyeLookOutLeft=1.0), weights(eyeLookUpLeft=1.0),
                           weights(eyeLookInLeft=1.0)]))
    shift = m[:, pupil].mean(axis=1) - m[0, pupil].mean(axis=0)
    assert shift[1, 0] > 0.004 and shift[2, 1] > 0.003 and shift[3, 0] < -0.004  # out = +x for the left eye
    centre = rig._eye_centre[0]
    np.testing.assert_allclose(np.linalg.norm(m[:, ball] - centre, axis=-1),
                               np.broadcast_to(np.linalg.norm(m[0, ball] - centre, axis=-1), (4, ball.sum())),
                               atol=1e-12)


def test_mouth_close_closes_the_lips_only_while_the_jaw_is_open(head, rig):
    v = head.v_template
    skin = np.nonzero(head.vertex_labels["skin"])[0]
    pair = skin[np.linalg.norm(v[skin] - head.landmarks["mouth_centre"], axis=1) < 1e-9]  # the seam's two sides
    assert len(pair) == 2
    m = rig.mesh(np.stack([weights(), weights(mouthClose=1.0), weights(jawOpen=0.5),
                           weights(jawOpen=0.5, mouthClose=0.5)]))
    gap = np.linalg.norm(m[:, pair[0]] - m[:, pair[1]], axis=-1)
    np.testing.assert_allclose(m[1], m[0], atol=1e-12)  # mouthClose alone: nothing
    assert gap[2] > 0.01 and gap[3] < 0.5 * gap[2]


@pytest.mark.parametrize("pair", [("jawOpen", "mouthClose"), ("mouthSmileLeft", "jawOpen"),
                                  ("eyeBlinkLeft", "eyeSquintLeft"), ("browDownLeft", "browInnerUp")])
def test_rig_is_nonlinear_for_common_combinations(rig, pair):
    a, b = pair
    m = rig.mesh(np.stack([weights(), weights(**{a: 0.7}), weights(**{b: 0.7}), weights(**{a: 0.7, b: 0.7})]))
    interaction = m[3] - m[1] - m[2] + m[0]  # rig(w1 + w2) - rig(w1) - rig(w2) + rig(0)
    assert np.abs(interaction).max() > 5e-4


def test_correctives_cover_the_documented_combinations():
    assert ("jawOpen", "mouthClose") in CORRECTIVES
    assert ("mouthSmileLeft", "jawOpen") in CORRECTIVES and ("eyeBlinkRight", "eyeSquintRight") in CORRECTIVES


def test_subjects_differ_in_style_and_identity(head, basis):
    a = Rig(head, RigStyle.random(np.random.default_rng(1), head.shape_dims), vertex_ids=np.arange(0, 8000, 7),
            basis=basis)
    b = Rig(head, RigStyle.random(np.random.default_rng(2), head.shape_dims), vertex_ids=np.arange(0, 8000, 7),
            basis=basis)
    w = weights(mouthSmileLeft=0.6, jawOpen=0.3, browInnerUp=0.5)
    da = a.mesh(w)[0] - a.rest
    db = b.mesh(w)[0] - b.rest
    assert np.abs(da - db).max() > 5e-4  # the same weights move two faces differently
    assert np.abs(a.rest - b.rest).max() > 1e-3  # and the faces differ
    full = Rig(head, a.style, basis=basis)
    np.testing.assert_allclose(full.mesh(w)[0, a.vertex_ids], a.mesh(w)[0], atol=1e-12)  # subsets agree
