"""The blendshape layouts of `hello.layout` and `bs.w` (PROTOCOL.md section 4.1): each layout's names in wire order.

The one source of the layout tables: `constants.LAYOUTS` (name -> length), the server's `ofera.mapping.layouts`
(adapters and conversions), PROTOCOL.md's layout table and `vectors/tables.json` (what the C# and JavaScript
clients check their own tables against) are all made from `LAYOUT_NAMES` and `LAYOUT_ORDER` here.
"""

from __future__ import annotations

ARKIT52_NAMES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
    "eyeSquintLeft", "eyeWideLeft",
    "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight",
    "jawForward", "jawLeft", "jawRight", "jawOpen",
    "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
    "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft",
    "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight",
    "mouthUpperUpLeft", "mouthUpperUpRight",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
    "noseSneerLeft", "noseSneerRight",
    "tongueOut",
)  # fmt: skip
"""Apple's ARKit order (also Epic's EARFaceBlendShape and the Live Link UDP order)."""

ARKIT51_NAMES: tuple[str, ...] = ARKIT52_NAMES[:51]
"""The canonical model input: ARKit without tongueOut."""

MEDIAPIPE52_NAMES: tuple[str, ...] = ("_neutral", *sorted(ARKIT51_NAMES))
"""MediaPipe FaceLandmarker: `_neutral`, then the 51 ARKit names in alphabetical order."""

OVR63_NAMES: tuple[str, ...] = (
    "BROW_LOWERER_L", "BROW_LOWERER_R", "CHEEK_PUFF_L", "CHEEK_PUFF_R", "CHEEK_RAISER_L",
    "CHEEK_RAISER_R", "CHEEK_SUCK_L", "CHEEK_SUCK_R", "CHIN_RAISER_B", "CHIN_RAISER_T",
    "DIMPLER_L", "DIMPLER_R",
    "EYES_CLOSED_L", "EYES_CLOSED_R", "EYES_LOOK_DOWN_L", "EYES_LOOK_DOWN_R", "EYES_LOOK_LEFT_L",
    "EYES_LOOK_LEFT_R", "EYES_LOOK_RIGHT_L", "EYES_LOOK_RIGHT_R", "EYES_LOOK_UP_L", "EYES_LOOK_UP_R",
    "INNER_BROW_RAISER_L", "INNER_BROW_RAISER_R", "JAW_DROP", "JAW_SIDEWAYS_LEFT",
    "JAW_SIDEWAYS_RIGHT", "JAW_THRUST", "LID_TIGHTENER_L", "LID_TIGHTENER_R",
    "LIP_CORNER_DEPRESSOR_L", "LIP_CORNER_DEPRESSOR_R", "LIP_CORNER_PULLER_L", "LIP_CORNER_PULLER_R",
    "LIP_FUNNELER_LB", "LIP_FUNNELER_LT", "LIP_FUNNELER_RB", "LIP_FUNNELER_RT",
    "LIP_PRESSOR_L", "LIP_PRESSOR_R", "LIP_PUCKER_L", "LIP_PUCKER_R", "LIP_STRETCHER_L",
    "LIP_STRETCHER_R", "LIP_SUCK_LB", "LIP_SUCK_LT", "LIP_SUCK_RB", "LIP_SUCK_RT",
    "LIP_TIGHTENER_L", "LIP_TIGHTENER_R",
    "LIPS_TOWARD", "LOWER_LIP_DEPRESSOR_L", "LOWER_LIP_DEPRESSOR_R", "MOUTH_LEFT", "MOUTH_RIGHT",
    "NOSE_WRINKLER_L", "NOSE_WRINKLER_R", "OUTER_BROW_RAISER_L", "OUTER_BROW_RAISER_R",
    "UPPER_LID_RAISER_L", "UPPER_LID_RAISER_R", "UPPER_LIP_RAISER_L", "UPPER_LIP_RAISER_R",
)  # fmt: skip
"""OpenXR XR_FB_face_tracking (v1) order; Unity's OVRFaceExpressions uses it in PascalCase."""

OVR70_NAMES: tuple[str, ...] = (
    *OVR63_NAMES,
    "TONGUE_TIP_INTERDENTAL", "TONGUE_TIP_ALVEOLAR", "TONGUE_FRONT_DORSAL_PALATE",
    "TONGUE_MID_DORSAL_PALATE", "TONGUE_BACK_DORSAL_VELAR", "TONGUE_OUT", "TONGUE_RETREAT",
)  # fmt: skip
"""XR_FB_face_tracking2 (v2): v1 plus seven tongue shapes."""

LIVELINK61_NAMES: tuple[str, ...] = (
    *(n[0].upper() + n[1:] for n in ARKIT52_NAMES),
    "HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
    "RightEyeYaw", "RightEyePitch", "RightEyeRoll",
)  # fmt: skip
"""Live Link Face: the 52 ARKit shapes (PascalCase, Apple order), then head and eye angles (radians)."""


LAYOUT_NAMES: dict[str, tuple[str, ...]] = {
    "arkit52": ARKIT52_NAMES,
    "arkit51": ARKIT51_NAMES,
    "mediapipe52": MEDIAPIPE52_NAMES,
    "ovr63": OVR63_NAMES,
    "ovr70": OVR70_NAMES,
    "livelink61": LIVELINK61_NAMES,
}
"""Layout name -> its blendshape names in the order of `bs.w`."""

LAYOUT_ORDER: dict[str, str] = {
    "arkit52": "Apple ARKit `ARFaceAnchor.BlendShapeLocation` documentation order, eyeBlinkLeft ... tongueOut (also "
               "Epic's EARFaceBlendShape)",
    "arkit51": "`arkit52` without tongueOut (the mapper's input)",
    "mediapipe52": "MediaPipe FaceLandmarker categories: `_neutral`, then the 51 ARKit names (no tongueOut) in "
                   "alphabetical order",
    "ovr63": "OpenXR `XR_FB_face_tracking` (`XR_FACE_EXPRESSION_*_FB`, BROW_LOWERER_L ... UPPER_LIP_RAISER_R); Unity "
             "`OVRFaceExpressions`",
    "ovr70": "OpenXR `XR_FB_face_tracking2`: `ovr63`, then the 7 tongue weights",
    "livelink61": "Live Link Face: the 52 ARKit shapes in Apple order, then head yaw, pitch, roll and left/right eye "
                  "yaw, pitch, roll (radians)",
}
"""Layout name -> where its order comes from (PROTOCOL.md's layout table)."""
