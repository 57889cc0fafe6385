"""Blendshape layouts, name matching, layout detection and the conversions to ARKit."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from ofera.mapping.layouts import (
    ARKIT51_NAMES,
    ARKIT52_NAMES,
    ARKIT_REGIONS,
    LAYOUTS,
    OVR_TO_ARKIT,
    LayoutAdapter,
    LayoutError,
    conversion_matrix,
    convert,
    convert_reference,
    get_layout,
    layout_from_names,
    normalize_name,
    region_indices,
    to_arkit51,
)

# MediaPipe's face_blendshapes_graph.cc order after `_neutral`, copied from REFERENCE.md.
MEDIAPIPE_51 = """browDownLeft browDownRight browInnerUp browOuterUpLeft browOuterUpRight cheekPuff
cheekSquintLeft cheekSquintRight eyeBlinkLeft eyeBlinkRight eyeLookDownLeft eyeLookDownRight eyeLookInLeft
eyeLookInRight eyeLookOutLeft eyeLookOutRight eyeLookUpLeft eyeLookUpRight eyeSquintLeft eyeSquintRight
eyeWideLeft eyeWideRight jawForward jawLeft jawOpen jawRight mouthClose mouthDimpleLeft mouthDimpleRight
mouthFrownLeft mouthFrownRight mouthFunnel mouthLeft mouthLowerDownLeft mouthLowerDownRight mouthPressLeft
mouthPressRight mouthPucker mouthRight mouthRollLower mouthRollUpper mouthShrugLower mouthShrugUpper
mouthSmileLeft mouthSmileRight mouthStretchLeft mouthStretchRight mouthUpperUpLeft mouthUpperUpRight
noseSneerLeft noseSneerRight""".split()


def ovr_vector(layout: str, **values: float) -> np.ndarray:
    """OVR weights with the named entries set (any spelling) and the rest zero."""
    lay = get_layout(layout)
    w = np.zeros(lay.length, dtype=np.float32)
    for name, value in values.items():
        w[lay.index(name)] = value
    return w


def test_registry_lengths_and_spot_names():
    lengths = {name: lay.length for name, lay in LAYOUTS.items()}
    assert lengths == {
        "arkit52": 52,
        "arkit51": 51,
        "mediapipe52": 52,
        "ovr63": 63,
        "ovr70": 70,
        "livelink61": 61,
    }
    assert ARKIT52_NAMES[17] == "jawOpen" and ARKIT52_NAMES[41] == "browDownLeft"
    assert ARKIT51_NAMES == ARKIT52_NAMES[:51] and "tongueOut" not in get_layout("arkit51")
    ovr = get_layout("ovr63").names
    assert (ovr[0], ovr[12], ovr[24], ovr[50], ovr[62]) == (
        "BROW_LOWERER_L",
        "EYES_CLOSED_L",
        "JAW_DROP",
        "LIPS_TOWARD",
        "UPPER_LIP_RAISER_R",
    )
    ovr70 = get_layout("ovr70").names
    assert ovr70[:63] == ovr and ovr70[63] == "TONGUE_TIP_INTERDENTAL" and ovr70[68] == "TONGUE_OUT"
    ll = get_layout("livelink61").names
    assert [normalize_name(n) for n in ll[:52]] == [normalize_name(n) for n in ARKIT52_NAMES]
    assert ll[52:] == (
        "HeadYaw",
        "HeadPitch",
        "HeadRoll",
        "LeftEyeYaw",
        "LeftEyePitch",
        "LeftEyeRoll",
        "RightEyeYaw",
        "RightEyePitch",
        "RightEyeRoll",
    )
    assert get_layout("OVR63") is LAYOUTS["ovr63"]


def test_mediapipe_order_matches_reference():
    names = get_layout("mediapipe52").names
    assert names[0] == "_neutral" and list(names[1:]) == MEDIAPIPE_51


def test_unknown_layout_lists_valid_names():
    with pytest.raises(LayoutError, match="unknown layout 'arkit53'.*arkit52.*ovr70.*livelink61"):
        get_layout("arkit53")
    with pytest.raises(LayoutError, match="cannot convert to 'ovr63'"):
        conversion_matrix("arkit52", "ovr63")


@pytest.mark.parametrize(
    ("a", "b"),
    [
        ("BrowLowererL", "BROW_LOWERER_L"),
        ("LipFunnelerLB", "lip_funneler_lb"),
        ("EyeBlinkLeft", "eyeBlinkLeft"),
        ("_neutral", "Neutral"),
        (" jawOpen ", "JAWOPEN"),
    ],
)
def test_normalize_name(a, b):
    assert normalize_name(a) == normalize_name(b)
    assert normalize_name("mouthLeft") != normalize_name("mouthRight")


@pytest.mark.parametrize("name", ["arkit52", "arkit51", "mediapipe52", "livelink61"])
def test_arkit_family_selects_by_name(name):
    lay = get_layout(name)
    w = np.random.default_rng(1).uniform(0.0, 1.0, lay.length).astype(np.float32)
    got = to_arkit51(name, w)
    assert got.shape == (51,) and got.dtype == np.float32
    for i, target in enumerate(ARKIT51_NAMES):
        assert got[i] == w[lay.index(target)]


def test_mediapipe_reorder_and_arkit52_from_arkit51():
    mp = np.zeros(52, dtype=np.float32)
    mp[0] = 0.9  # _neutral is ignored
    mp[1] = 0.25  # browDownLeft
    mp[25] = 0.5  # jawOpen
    out = to_arkit51("mediapipe52", mp)
    assert out[41] == 0.25 and out[17] == 0.5 and np.count_nonzero(out) == 2
    a51 = np.linspace(0, 1, 51, dtype=np.float32)
    a52 = convert("arkit51", a51, "arkit52")
    assert a52.shape == (52,) and np.array_equal(a52[:51], a51) and a52[51] == 0.0
    assert np.array_equal(convert("arkit52", a52, "arkit51"), a51)


META_ROWS = [
    ({"LIP_FUNNELER_LB": 1.0}, {"mouthFunnel": 0.75}),
    (
        {"CHEEK_RAISER_L": 0.6, "LIP_CORNER_PULLER_L": 0.7},
        {"cheekSquintLeft": 1.0, "mouthSmileLeft": 0.7, "eyeSquintLeft": 0.175},
    ),
    ({"CheekRaiserR": 0.2, "LipCornerPullerR": 0.3}, {"cheekSquintRight": 0.5, "mouthSmileRight": 0.3,
                                                      "eyeSquintRight": 0.075}),
    ({"EYES_LOOK_RIGHT_L": 0.5}, {"eyeLookInLeft": 0.5}),
    ({"EYES_LOOK_LEFT_L": 0.5, "EYES_LOOK_LEFT_R": 0.4}, {"eyeLookOutLeft": 0.5, "eyeLookInRight": 0.4}),
    ({"EYES_LOOK_RIGHT_R": 0.3, "EYES_LOOK_UP_L": 0.2, "EYES_LOOK_DOWN_R": 0.1},
     {"eyeLookOutRight": 0.3, "eyeLookUpLeft": 0.2, "eyeLookDownRight": 0.1}),
    ({"OUTER_BROW_RAISER_R": 0.4, "BROW_LOWERER_L": 0.3}, {"browOuterUpRight": 0.6, "browDownLeft": 0.3}),
    ({"INNER_BROW_RAISER_L": 0.3, "INNER_BROW_RAISER_R": 0.3}, {"browInnerUp": 0.6}),
    ({"LIP_PUCKER_L": 0.4, "LIP_PUCKER_R": 0.4}, {"mouthPucker": 0.6, "mouthFunnel": 0.6}),
    ({"LIP_SUCK_LB": 1.0, "LIP_SUCK_RT": 0.4}, {"mouthRollLower": 0.5, "mouthRollUpper": 0.2}),
    ({"JAW_DROP": 0.8, "JAW_SIDEWAYS_LEFT": 0.2, "JAW_THRUST": 0.1, "LIPS_TOWARD": 0.3, "CHIN_RAISER_T": 0.5},
     {"jawOpen": 0.8, "jawLeft": 0.2, "jawForward": 0.1, "mouthClose": 0.3, "mouthShrugUpper": 0.5}),
    ({"MOUTH_LEFT": 0.5, "NOSE_WRINKLER_R": 0.25, "EYES_CLOSED_R": 1.0, "UPPER_LID_RAISER_L": 0.3},
     {"mouthLeft": 0.5, "noseSneerRight": 0.25, "eyeBlinkRight": 1.0, "eyeWideLeft": 0.3}),
    ({"CHEEK_PUFF_L": 0.7, "CHEEK_PUFF_R": 0.7, "LIP_STRETCHER_R": 0.2, "LOWER_LIP_DEPRESSOR_L": 0.1},
     {"cheekPuff": 1.0, "mouthStretchRight": 0.2, "mouthLowerDownLeft": 0.1}),
    ({"CHEEK_SUCK_L": 1.0, "LIP_TIGHTENER_R": 1.0, "BROW_LOWERER_R": -0.5}, {}),
]  # fmt: skip


@pytest.mark.parametrize("layout", ["ovr63", "ovr70"])
@pytest.mark.parametrize(("inputs", "expected"), META_ROWS)
def test_meta_mapping_hand_checked(layout, inputs, expected):
    w = ovr_vector(layout, **inputs)
    want = np.zeros(51, dtype=np.float32)
    for name, value in expected.items():
        want[ARKIT51_NAMES.index(name)] = value
    np.testing.assert_allclose(to_arkit51(layout, w), want, atol=1e-6)
    np.testing.assert_allclose(convert_reference(layout, w), want, atol=1e-6)


def test_tongue_out_only_from_v2():
    w70 = ovr_vector("ovr70", TONGUE_OUT=0.6, TONGUE_RETREAT=1.0)
    assert convert("ovr70", w70, "arkit52")[51] == pytest.approx(0.6)
    assert np.count_nonzero(convert("ovr70", w70, "arkit52")) == 1
    assert convert("ovr63", np.ones(63), "arkit52")[51] == 0.0


def test_meta_table_covers_arkit_with_real_ovr_names():
    assert set(OVR_TO_ARKIT) == set(ARKIT52_NAMES)
    ovr70 = get_layout("ovr70")
    for drivers in OVR_TO_ARKIT.values():
        assert drivers and all(d in ovr70.names for d, _ in drivers)


def test_conversion_matrix_is_cached_and_read_only():
    m = conversion_matrix("ovr63")
    assert m.shape == (51, 63) and m.dtype == np.float32 and not m.flags.writeable
    assert conversion_matrix(get_layout("ovr63"), "arkit51") is m
    perm = conversion_matrix("mediapipe52")
    assert np.array_equal(perm.sum(axis=1), np.ones(51)) and perm[:, 0].sum() == 0


@pytest.mark.parametrize("dst", ["arkit51", "arkit52"])
@pytest.mark.parametrize("src", list(LAYOUTS))
def test_fast_paths_match_reference(src, dst):
    lay = get_layout(src)
    w = np.random.default_rng(7).uniform(-0.3, 1.3, (16, lay.length)).astype(np.float32)
    want = convert_reference(src, w, dst)
    np.testing.assert_allclose(convert(src, w, dst), want, atol=1e-6)
    adapter = LayoutAdapter(src, dst)
    batch_out = np.empty((16, get_layout(dst).length), dtype=np.float32)
    assert adapter(w, out=batch_out) is batch_out
    np.testing.assert_allclose(batch_out, want, atol=1e-6)
    for row, expect in zip(w, want, strict=True):
        assert adapter(row) is adapter.out
        np.testing.assert_allclose(adapter.out, expect, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(arrays(np.float32, 70, elements=st.floats(-2, 2, width=32)))
def test_ovr70_adapter_matches_reference_property(w):
    np.testing.assert_allclose(LayoutAdapter("ovr70")(w), convert_reference("ovr70", w), atol=1e-6)


def test_wrong_shapes_are_rejected():
    with pytest.raises(ValueError, match=r"\(63,\) or \(B, 63\).*'ovr63'"):
        to_arkit51("ovr63", np.zeros(52))
    with pytest.raises(ValueError, match="expected 52 values"):
        LayoutAdapter("arkit52")(np.zeros(51))


def test_layout_from_names_permuted_and_spelled_differently():
    rng = np.random.default_rng(3)
    ovr = get_layout("ovr63")
    # Unity's OVRFaceExpressions spelling: PascalCase words, side suffix kept (LipFunnelerLB, EyesLookUpL).
    unity = []
    for name in ovr.names:
        *words, last = name.split("_")
        unity.append("".join(w.capitalize() for w in words) + (last if len(last) <= 2 else last.capitalize()))
    assert (unity[0], unity[20], unity[25], unity[34]) == (
        "BrowLowererL",
        "EyesLookUpL",
        "JawSidewaysLeft",
        "LipFunnelerLB",
    )
    order = rng.permutation(63)
    shuffled = [unity[i] for i in order]
    lay, index = layout_from_names(shuffled)
    assert lay is ovr
    table = rng.uniform(size=(5, 63))
    assert np.array_equal(table[:, index], table[:, np.argsort(order)])
    assert [shuffled[i] for i in index] == unity


@pytest.mark.parametrize(
    ("names", "expected"),
    [
        (list(ARKIT51_NAMES), "arkit51"),
        (list(ARKIT52_NAMES), "arkit52"),
        (MEDIAPIPE_51, "arkit51"),
        (["_neutral", *MEDIAPIPE_51], "mediapipe52"),
        ([n.upper() for n in get_layout("livelink61").names], "livelink61"),
        (list(get_layout("ovr70").names), "ovr70"),
    ],
)
def test_layout_detection(names, expected):
    assert layout_from_names(names)[0].name == expected


def test_detection_errors_name_the_names():
    names = [*ARKIT51_NAMES[:-1], "mouthSmileCenter"]
    with pytest.raises(LayoutError, match="closest is 'arkit51'.*unknown names: mouthSmileCenter.*"
                                          "missing names: noseSneerRight"):  # fmt: skip
        layout_from_names(names)
    with pytest.raises(LayoutError, match="do not match layout 'ovr63'.*unknown names: eyeBlinkLeft"):
        layout_from_names(ARKIT52_NAMES, "ovr63")
    with pytest.raises(LayoutError, match="duplicate column 'EyeBlinkLeft' \\(also column 1\\)"):
        layout_from_names(["eyeBlinkLeft", "EyeBlinkLeft"])


def test_regions_partition_arkit():
    sizes = {region: len(names) for region, names in ARKIT_REGIONS.items()}
    assert sizes == {"eyes": 14, "brows": 5, "mouth_jaw": 28, "cheeks_nose": 5}
    assert sorted(sum(ARKIT_REGIONS.values(), ())) == sorted(ARKIT52_NAMES)
    assert "tongueOut" in ARKIT_REGIONS["mouth_jaw"]
    assert len(region_indices("mouth_jaw")) == 27
    mp = get_layout("mediapipe52")
    assert [mp.names[i] for i in region_indices("brows", mp)] == list(ARKIT_REGIONS["brows"])
    with pytest.raises(LayoutError, match="regions: eyes, brows"):
        region_indices("ears")
