"""The rig's displacement fields, as a table (read by :mod:`.rig`): where each ARKit shape moves the face, which
way and how far.

A row is one Gaussian bump on the skin, ``amp * unit(direction) * exp(-|(p - centre) / squash|^2 / (2 radius^2))``:

- ``target``: the arkit51 shape it belongs to, or ``"a*b"``, a corrective driven by the product of the effective
  weights of shapes a and b (one of ``rig.CORRECTIVES``);
- ``term``: ``"linear"`` (per unit of effective weight), ``"quadratic"`` (per unit of its square: the "arcs")
  or ``"corrective"``;
- ``at``: the landmark(s) of the procedural head the bump is centred on (several: their mean), plus ``offset``;
- ``direction``: a vector, or ``"towards_mid"`` (towards the mouth's mid line, 0 at the centre, 1.2 at most) or
  ``"towards_eye"`` (towards the eye centre, in the image plane);
- ``mask``: ``"lower"`` / ``"upper"`` (the lower / upper lip side of the mouth seam), ``"ring"`` (outside the lids),
  ``"orbit"`` (around the eye, not on it);
- ``power``: the bump's exponent (2: a narrower, squared bump); ``of_close_lift``: ``amp`` is a fraction of the
  lip gap a 0.36 rad jaw opening makes.

Sided blocks are evaluated once per side (Left, then Right): ``{side}`` becomes ``Left`` / ``Right`` in targets and
``left`` / ``right`` in landmark names, and the x components of ``offset`` and ``direction`` take the side's sign
(the subject's left is +x). Blocks run in order; within a block, rows run in order.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Bump:
    target: str
    at: str | tuple[str, ...]
    radius: float
    direction: tuple[float, float, float] | str
    amp: float
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    squash: tuple[float, float, float] = (1.0, 1.0, 1.0)
    mask: str = ""
    term: str = "linear"
    power: int = 1
    of_close_lift: bool = False


_BELOW_EYE = dict(at="eye_{side}", offset=(0, -0.0075, 0.004), radius=0.0045, squash=(1.9, 1, 1))
_RING = dict(at="eye_{side}", offset=(0, 0, 0.006), radius=0.011, squash=(1.4, 1, 1), mask="ring")
_PUFF = dict(at="cheek_{side}", offset=(0, -0.028, -0.004), radius=0.013, squash=(1.0, 1.2, 1.0))
_ALA = (0.012, 0.004, -0.014)  # the nose wing, from the nose tip
_CORNER = dict(at="mouth_corner_{side}", radius=0.0085)
_LIPS = dict(at="mouth_centre", radius=0.009, squash=(1.5, 1, 1))
_LIP_ZONE = dict(at="mouth_centre", radius=0.011, squash=(1.7, 1, 1))
_BROW = ("brow_inner_{side}", "brow_outer_{side}")

SIDED_FIELDS: tuple[Bump, ...] = (
    # --- eyes (the lids themselves rotate: rig.py) ------------------------------------------------------
    Bump("eyeBlink{side}", direction=(0, 1, 0.2), amp=0.0010, **_BELOW_EYE),
    Bump("eyeLookDown{side}", direction=(0, -1, 0), amp=0.0008, **_BELOW_EYE),
    Bump("eyeLookUp{side}", direction=(0, 1, 0.1), amp=0.0006, **_BELOW_EYE),
    Bump("eyeLookIn{side}", direction=(-1, 0, 0), amp=0.0005, **_RING),
    Bump("eyeLookOut{side}", direction=(1, 0, 0), amp=0.0005, **_RING),
    Bump("eyeSquint{side}", direction=(0, 1, 0.3), amp=0.0022, **_BELOW_EYE),
    Bump("eyeSquint{side}", at="eye_{side}", offset=(0, 0, 0.004), radius=0.013, squash=(1.3, 1, 1), mask="orbit",
         direction="towards_eye", amp=0.0012),
    Bump("eyeWide{side}", at=_BROW, radius=0.012, squash=(1.6, 1, 1), direction=(0, 1, 0), amp=0.0012),
    # --- brows --------------------------------------------------------------------------------------------
    Bump("browDown{side}", at=_BROW, offset=(-0.006, 0, 0), radius=0.011, squash=(1.8, 1, 1),
         direction=(-0.4, -1, 0.15), amp=0.0050),
    Bump("browDown{side}", at=("brow_inner_left", "brow_inner_right"), radius=0.006, direction=(0, -1, 0.2),
         amp=0.0012),
    Bump("browInnerUp", at="brow_inner_{side}", radius=0.009, squash=(1.2, 1, 1), direction=(0.1, 1, 0.1),
         amp=0.0065),
    Bump("browInnerUp", at="brow_inner_{side}", offset=(0, 0.012, 0), radius=0.010, direction=(0, 1, 0),
         amp=0.0015, term="quadratic"),
    Bump("browOuterUp{side}", at="brow_outer_{side}", radius=0.011, squash=(1.3, 1, 1), direction=(0.1, 1, -0.05),
         amp=0.0060),
    # --- cheeks and nose ----------------------------------------------------------------------------------
    Bump("cheekPuff", direction=(0.85, 0, 0.5), amp=0.0085, **_PUFF),
    Bump("cheekPuff", direction=(0.7, -0.2, 0.7), amp=0.0030, power=2, term="quadratic", **_PUFF),
    Bump("cheekSquint{side}", at="cheek_{side}", offset=(0, -0.004, 0), radius=0.011, direction=(0, 0.8, 0.45),
         amp=0.0040),
    Bump("cheekSquint{side}", direction=(0, 1, 0.2), amp=0.0010, **_BELOW_EYE),
    Bump("noseSneer{side}", at="nose_tip", offset=(0.011, 0.013, -0.013), radius=0.007, direction=(0, 1, 0.25),
         amp=0.0040),
    Bump("noseSneer{side}", at="nose_tip", offset=_ALA, radius=0.006, direction=(0, 0.6, 0.2), amp=0.0020),
    Bump("noseSneer{side}", at="brow_inner_{side}", offset=(-0.004, 0, 0), radius=0.006, direction=(0, -1, 0),
         amp=0.0010),
    # --- mouth corner shapes ------------------------------------------------------------------------------
    Bump("mouthSmile{side}", direction=(0.55, 1, -0.35), amp=0.0080, **_CORNER),
    Bump("mouthSmile{side}", at="cheek_{side}", offset=(0, -0.02, -0.002), radius=0.010, direction=(0.3, 0.5, 0.5),
         amp=0.0020),
    Bump("mouthSmile{side}", direction=(0.2, 0.3, -0.6), amp=0.0060, term="quadratic", **_CORNER),
    Bump("mouthFrown{side}", direction=(0.15, -1, -0.1), amp=0.0060, **_CORNER),
    Bump("mouthFrown{side}", at="mouth_corner_{side}", offset=(0, -0.012, -0.004), radius=0.008,
         direction=(0, -1, 0), amp=0.0020),
    Bump("mouthFrown{side}", direction=(0, -0.3, -0.4), amp=0.0040, term="quadratic", **_CORNER),
    Bump("mouthDimple{side}", at="mouth_corner_{side}", radius=0.007, direction=(0.3, 0.1, -1), amp=0.0050),
    Bump("mouthStretch{side}", at="mouth_corner_{side}", radius=0.010, direction=(1, -0.35, -0.25), amp=0.0060),
    Bump("mouthStretch{side}", at="lower_lip", offset=(0.012, 0, 0), radius=0.007, mask="lower",
         direction=(1, -0.3, 0), amp=0.0015),
    Bump("mouthStretch{side}", direction=(0.3, -0.2, -0.5), amp=0.0040, term="quadratic", **_CORNER),
    # --- one-sided lip shapes -----------------------------------------------------------------------------
    Bump("mouthPress{side}", at="lower_lip", offset=(0.010, 0.001, 0), radius=0.007, squash=(1.4, 1, 1),
         mask="lower", direction=(0, 0.8, -0.3), amp=0.0030),
    Bump("mouthPress{side}", at="upper_lip", offset=(0.010, -0.001, 0), radius=0.007, squash=(1.4, 1, 1),
         mask="upper", direction=(0, -0.5, -0.3), amp=0.0015),
    Bump("mouthLowerDown{side}", at="lower_lip", offset=(0.011, -0.002, 0), radius=0.008, mask="lower",
         direction=(0, -1, 0.25), amp=0.0060),
    Bump("mouthUpperUp{side}", at="upper_lip", offset=(0.010, 0.001, 0), radius=0.007, mask="upper",
         direction=(0, 1, 0.3), amp=0.0050),
    Bump("mouthUpperUp{side}", at="nose_tip", offset=(0.012, -0.002, -0.010), radius=0.006,  # below the ala
         direction=(0, 1, 0.3), amp=0.0015),
    # --- correctives that have a side -----------------------------------------------------------------------
    Bump("mouthSmile{side}*jawOpen", term="corrective", direction=(0.45, -0.6, -0.3), amp=0.0130,  # the open
         **_CORNER),  # jaw pulls the corner down and out
    Bump("eyeBlink{side}*eyeSquint{side}", term="corrective", at="eye_{side}", offset=(0, -0.011, 0.002),
         radius=0.005, squash=(1.8, 1, 1), direction=(0, -0.6, 0.8), amp=0.0060),
    Bump("browDown{side}*browInnerUp", term="corrective", at="brow_inner_{side}", radius=0.007,
         direction=(-1, 0.8, 0.2), amp=0.0050),  # grief brows: the inner ends up and in
    Bump("mouthSmile{side}*cheekSquint{side}", term="corrective", at="cheek_{side}", offset=(0, -0.012, 0.002),
         radius=0.009, direction=(0.2, 0.6, 0.8), amp=0.0045),
)

MOUTH_FIELDS: tuple[Bump, ...] = (
    Bump("mouthPucker", direction=(0, 0, 1), amp=0.0060, **_LIPS),
    Bump("mouthPucker", direction="towards_mid", amp=0.0050, **_LIPS),
    Bump("mouthPucker", mask="upper", direction=(0, -1, 0), amp=0.0010, **_LIPS),
    Bump("mouthPucker", mask="lower", direction=(0, 1, 0), amp=0.0010, **_LIPS),
    Bump("mouthPucker", direction=(0, 0, 1), amp=0.0020, term="quadratic", **_LIPS),
    Bump("mouthFunnel", mask="upper", direction=(0, 0.7, 1), amp=0.0040, **_LIP_ZONE),
    Bump("mouthFunnel", mask="lower", direction=(0, -0.7, 1), amp=0.0040, **_LIP_ZONE),
    Bump("mouthFunnel", direction="towards_mid", amp=0.0030, **_LIP_ZONE),
    Bump("mouthFunnel", direction=(0, 0, 1), amp=0.0020, term="quadratic", **_LIPS),
    Bump("mouthLeft", at="mouth_centre", radius=0.012, squash=(1.8, 1, 1), direction=(1, 0, 0.05), amp=0.0050),
    Bump("mouthRight", at="mouth_centre", radius=0.012, squash=(1.8, 1, 1), direction=(-1, 0, 0.05), amp=0.0050),
    Bump("mouthShrugLower", at="lower_lip", radius=0.008, squash=(2, 1, 1), mask="lower", direction=(0, 0.6, 0.8),
         amp=0.0040),
    Bump("mouthShrugLower", at="chin", offset=(0, 0.006, 0), radius=0.012, direction=(0, 0.5, 0.6), amp=0.0040),
    Bump("mouthShrugUpper", at="upper_lip", radius=0.008, squash=(2, 1, 1), mask="upper", direction=(0, 0.4, 0.9),
         amp=0.0030),
    Bump("mouthRollLower", at="lower_lip", radius=0.007, squash=(2, 1, 1), mask="lower", direction=(0, 0.3, -1),
         amp=0.0010),
    Bump("mouthRollUpper", at="upper_lip", radius=0.007, squash=(2, 1, 1), mask="upper", direction=(0, -0.3, -1),
         amp=0.0010),
    Bump("jawOpen", at="lower_lip", radius=0.009, squash=(2, 1, 1), mask="lower", direction=(0, -1, 0.1),
         amp=0.0015),
)

JAW_SIDE_FIELDS: tuple[Bump, ...] = (  # sided: the jaw pulls the cheeks behind the mouth corners in
    Bump("jawOpen", at="mouth_corner_{side}", offset=(0.012, 0.004, -0.01), radius=0.010, direction=(-1, 0, -0.3),
         amp=0.0020),
)

MOUTH_CORRECTIVES: tuple[Bump, ...] = (
    # Lips together while the jaw is open: in the rest pose the lower lip rises by the gap that the jaw opens at
    # the lips (the rotation then carries it), the upper lip comes down a little.
    Bump("jawOpen*mouthClose", term="corrective", at="lower_lip", radius=0.010, squash=(2.2, 1.4, 1.0), mask="lower",
         direction=(0, 1, -0.15), amp=0.9, of_close_lift=True),
    Bump("jawOpen*mouthClose", term="corrective", at="upper_lip", radius=0.009, squash=(2.2, 1.2, 1.0), mask="upper",
         direction=(0, -1, 0), amp=0.20, of_close_lift=True),
    Bump("mouthPucker*mouthFunnel", term="corrective", direction=(0, 0, 1), amp=0.0090, **_LIPS),
    Bump("jawOpen*mouthFunnel", term="corrective", direction="towards_mid", amp=0.0090, **_LIP_ZONE),
    Bump("jawOpen*mouthFunnel", term="corrective", mask="upper", direction=(0, 1, 0.5), amp=0.0065, **_LIP_ZONE),
)

FIELD_BLOCKS: tuple[tuple[bool, tuple[Bump, ...]], ...] = (
    (True, SIDED_FIELDS), (False, MOUTH_FIELDS), (True, JAW_SIDE_FIELDS), (False, MOUTH_CORRECTIVES))
"""(sided, rows) in the order :func:`rig._build_basis` adds them."""
