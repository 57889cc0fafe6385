"""Expression sequences that resemble real face captures, as arkit51 weights (T, 51) in [0, 1].

A sequence is the sum of independent layers, each built vectorised with numpy:

- emotions: Ekman's six basic emotions as ARKit prototypes (from the usual EMFACS action units:
  happiness AU6+12, sadness AU1+4+15, surprise AU1+2+5+26, fear AU1+2+4+5+7+20+26, anger AU4+5+7+23,
  disgust AU9+15+16) in segments of a few seconds with smooth onsets and offsets, varying intensity,
  left/right asymmetry, and neutral stretches;
- speech: talk turns of syllables (consonant then vowel visemes, about 4-6 per second) smoothed into
  one another (coarticulation), with brow emphasis on stressed syllables;
- blinks: a Poisson process (about 15 a minute) of 100-150 ms blinks, fast close and slower open;
- gaze: fixations and saccades (fast ramps of 20-100 ms), small drift and vergence, lids following a
  downward gaze;
- idle activity: sparse smooth bumps on every shape (one- or two-sided), so that all 51 shapes occur;
- co-activations seen in real captures (a smile raises the cheeks and narrows the eyes, an open jaw
  lowers the lower lip, a sneer raises the upper lip, mouthClose never exceeds jawOpen).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from ofera.training.paired.rig import IDX, N_SHAPES


def _vector(values: dict[str, float]) -> np.ndarray:
    """ARKit vector from {name: value}; a name without Left/Right applies to both sides if sided."""
    out = np.zeros(N_SHAPES)
    for name, value in values.items():
        if name in IDX:
            out[IDX[name]] = value
        else:
            out[IDX[name + "Left"]] = value
            out[IDX[name + "Right"]] = value
    return out


EMOTIONS: dict[str, np.ndarray] = {
    "happiness": _vector({"mouthSmile": 0.8, "cheekSquint": 0.55, "eyeSquint": 0.35, "mouthUpperUp": 0.1,
                          "mouthDimple": 0.2, "jawOpen": 0.08}),
    "sadness": _vector({"browInnerUp": 0.7, "browDown": 0.35, "mouthFrown": 0.6, "mouthShrugLower": 0.3,
                        "mouthPress": 0.15, "eyeLookDown": 0.2, "eyeBlink": 0.15}),
    "surprise": _vector({"browInnerUp": 0.8, "browOuterUp": 0.8, "eyeWide": 0.7, "jawOpen": 0.45,
                         "mouthFunnel": 0.15}),
    "fear": _vector({"browInnerUp": 0.8, "browOuterUp": 0.4, "browDown": 0.3, "eyeWide": 0.7, "eyeSquint": 0.25,
                     "mouthStretch": 0.6, "jawOpen": 0.25, "mouthLowerDown": 0.2}),
    "anger": _vector({"browDown": 0.85, "eyeWide": 0.25, "eyeSquint": 0.45, "mouthPress": 0.55,
                      "mouthRollLower": 0.2, "mouthShrugLower": 0.2, "noseSneer": 0.2, "jawForward": 0.1}),
    "disgust": _vector({"noseSneer": 0.75, "mouthFrown": 0.35, "mouthLowerDown": 0.3, "mouthUpperUp": 0.55,
                        "cheekSquint": 0.35, "browDown": 0.35, "eyeSquint": 0.3}),
}
"""ARKit prototypes of Ekman's six basic emotions at full intensity."""

CONSONANTS: dict[str, np.ndarray] = {
    "PBM": _vector({"jawOpen": 0.12, "mouthClose": 0.12, "mouthPress": 0.35, "mouthRollLower": 0.15,
                    "mouthRollUpper": 0.1}),
    "FV": _vector({"jawOpen": 0.1, "mouthRollLower": 0.45, "mouthUpperUp": 0.2, "mouthShrugUpper": 0.1}),
    "TDN": _vector({"jawOpen": 0.18, "mouthUpperUp": 0.1, "mouthStretch": 0.1}),
    "SZ": _vector({"jawOpen": 0.08, "mouthStretch": 0.25, "mouthSmile": 0.1, "mouthClose": 0.05}),
    "SHCH": _vector({"jawOpen": 0.15, "mouthFunnel": 0.4, "mouthPucker": 0.2, "mouthShrugUpper": 0.2,
                     "mouthShrugLower": 0.15}),
    "KG": _vector({"jawOpen": 0.25, "mouthStretch": 0.1, "mouthLowerDown": 0.1}),
    "R": _vector({"jawOpen": 0.12, "mouthPucker": 0.35, "mouthFunnel": 0.2}),
    "W": _vector({"jawOpen": 0.08, "mouthPucker": 0.7, "mouthFunnel": 0.2}),
}
VOWELS: dict[str, np.ndarray] = {
    "AA": _vector({"jawOpen": 0.55, "mouthLowerDown": 0.3, "mouthUpperUp": 0.1, "mouthStretch": 0.1}),
    "EH": _vector({"jawOpen": 0.35, "mouthStretch": 0.3, "mouthSmile": 0.15, "mouthLowerDown": 0.25}),
    "IY": _vector({"jawOpen": 0.15, "mouthStretch": 0.35, "mouthSmile": 0.25, "mouthUpperUp": 0.1}),
    "OW": _vector({"jawOpen": 0.4, "mouthFunnel": 0.5, "mouthPucker": 0.15}),
    "UW": _vector({"jawOpen": 0.15, "mouthPucker": 0.65, "mouthFunnel": 0.35}),
    "ER": _vector({"jawOpen": 0.2, "mouthFunnel": 0.25, "mouthPucker": 0.2, "mouthShrugUpper": 0.1}),
}
VISEMES = {**CONSONANTS, **VOWELS}
_CONSONANT_P = np.array([0.18, 0.1, 0.22, 0.16, 0.07, 0.12, 0.08, 0.07])
_VOWEL_P = np.array([0.24, 0.24, 0.2, 0.13, 0.1, 0.09])
_IDLE_CAP = np.ones(N_SHAPES)  # idle activity is milder on shapes that real captures rarely push far
for _name, _cap in (("mouthClose", 0.3), ("jawForward", 0.6), ("jawLeft", 0.6), ("jawRight", 0.6),
                    ("cheekPuff", 0.8), ("mouthRollUpper", 0.7), ("mouthRollLower", 0.7)):
    _IDLE_CAP[IDX[_name]] = _cap
_PAIRS = np.array([[IDX[n], IDX[n[:-4] + "Right"]] for n in IDX if n.endswith("Left")])


@dataclass(frozen=True)
class SequenceStyle:
    """What a capture set records (sources differ in it)."""

    emotion: float = 1.0  # share of emotional segments (vs neutral)
    speech: float = 0.4  # share of time talking
    idle: float = 1.0  # rate scale of idle activity on all shapes
    expressiveness: float = 1.0  # overall intensity
    blink_rate: float = 15.0  # per minute
    gaze_spread: float = 10.0  # degrees (standard deviation of fixation targets)


def _segments(rng: np.random.Generator, frames: int, fps: float, lo: float, hi: float) -> np.ndarray:
    """Frame -> segment index for consecutive segments of uniform random length in [lo, hi] seconds."""
    n = int(frames / (lo * fps)) + 2
    bounds = np.cumsum(rng.uniform(lo, hi, n) * fps)
    return np.searchsorted(bounds, np.arange(frames), side="right")


def _smooth(x: np.ndarray, sigma_frames: float) -> np.ndarray:
    return gaussian_filter1d(x, max(sigma_frames, 1e-3), axis=0, mode="nearest") if sigma_frames > 0.05 else x


def _asymmetric(rng: np.random.Generator, proto: np.ndarray, spread: float) -> np.ndarray:
    """Prototype rows (n, 51) with per-shape jitter and left/right asymmetry."""
    out = proto * rng.uniform(0.7, 1.2, proto.shape)
    a = rng.normal(0.0, spread, (len(proto), len(_PAIRS)))
    out[:, _PAIRS[:, 0]] *= 1 + a
    out[:, _PAIRS[:, 1]] *= 1 - a
    return out


def emotion_layer(rng: np.random.Generator, frames: int, fps: float, style: SequenceStyle) -> np.ndarray:
    seg = _segments(rng, frames, fps, 1.5, 5.0)
    n = seg.max() + 1
    protos = np.stack(list(EMOTIONS.values()))
    which = rng.integers(0, len(protos), n)
    emotional = rng.random(n) < 0.75 * style.emotion
    rows = _asymmetric(rng, protos[which], 0.12) * (rng.uniform(0.3, 1.0, n) * emotional)[:, None]
    steps = rows[seg]
    onset = rng.uniform(0.12, 0.25) * fps  # onset/offset speed of this subject
    envelope = 0.8 + 0.2 * np.tanh(_smooth(rng.normal(0, 1, frames), fps * 0.8) * 3)
    return _smooth(steps, onset) * envelope[:, None]


def speech_layer(rng: np.random.Generator, frames: int, fps: float, style: SequenceStyle) -> np.ndarray:
    # Talk turns and pauses.
    turns = _segments(rng, frames, fps, 1.0, 6.0)
    talking = (rng.random(turns.max() + 1) < style.speech)[turns].astype(float)
    # Syllables: consonant third then vowel, 4-6 per second.
    n = int(frames / fps * 7) + 4
    lengths = rng.uniform(0.16, 0.26, n) * fps
    starts = np.concatenate([[0.0], np.cumsum(lengths)])
    pos = np.arange(frames)
    syl = np.searchsorted(starts, pos, side="right") - 1
    vowel_part = (pos - starts[syl]) > lengths[syl] * rng.uniform(0.25, 0.4)
    cons = np.stack(list(CONSONANTS.values()))[rng.choice(len(CONSONANTS), n, p=_CONSONANT_P)]
    vows = np.stack(list(VOWELS.values()))[rng.choice(len(VOWELS), n, p=_VOWEL_P)]
    gain = rng.uniform(0.6, 1.15, n)[:, None]
    cons, vows = _asymmetric(rng, cons, 0.06) * gain, _asymmetric(rng, vows, 0.06) * gain
    steps = np.where(vowel_part[:, None], vows[syl], cons[syl])
    mouth = _smooth(steps, 0.045 * fps)  # coarticulation
    # Emphasis: brows rise on stressed syllables.
    stressed = (rng.random(n) < 0.15)[syl] * vowel_part
    emph = _smooth(stressed.astype(float), 0.12 * fps) * rng.uniform(0.2, 0.5)
    mouth[:, IDX["browInnerUp"]] += emph
    mouth[:, IDX["browOuterUpLeft"]] += 0.7 * emph
    mouth[:, IDX["browOuterUpRight"]] += 0.7 * emph
    return mouth * _smooth(talking, 0.1 * fps)[:, None]


def blink_layer(rng: np.random.Generator, frames: int, fps: float, style: SequenceStyle) -> np.ndarray:
    out = np.zeros((frames, N_SHAPES))
    mean_gap = 60.0 / max(style.blink_rate, 1e-3)
    n = int(frames / fps / mean_gap * 3) + 3
    starts = np.cumsum(np.maximum(rng.exponential(mean_gap, n), 0.4)) - rng.uniform(0, mean_gap)
    starts = starts[(starts > -0.2) & (starts < frames / fps)]
    if len(starts) == 0:
        return out
    dur = rng.uniform(0.10, 0.15, len(starts))
    peak = rng.uniform(0.85, 1.0, len(starts))
    t = np.arange(frames) / fps
    tau = (t[None, :] - starts[:, None]) / dur[:, None]  # (n, T)
    close = 0.35
    shape = np.where(tau < close, np.sin(0.5 * np.pi * np.clip(tau / close, 0, 1)),
                     np.cos(0.5 * np.pi * np.clip((tau - close) / (1 - close), 0, 1)))
    shape *= (tau >= 0) & (tau <= 1)
    side = rng.normal(1.0, 0.04, (len(starts), 2))
    wink = rng.random(len(starts)) < 0.02
    side[wink, rng.integers(0, 2, wink.sum())] = 0.1
    out[:, IDX["eyeBlinkLeft"]] = np.max(shape * (peak * side[:, 0])[:, None], axis=0)
    out[:, IDX["eyeBlinkRight"]] = np.max(shape * (peak * side[:, 1])[:, None], axis=0)
    return out


def gaze_layer(rng: np.random.Generator, frames: int, fps: float, style: SequenceStyle,
               full_scale_deg: float = 32.0) -> np.ndarray:
    """eyeLook* weights from fixations and saccades (degrees; weight 1 at ``full_scale_deg``)."""
    n = int(frames / fps / 0.3) + 3
    fix = rng.gamma(2.0, 0.35, n) + 0.15  # fixation durations (s)
    yaw = np.clip(rng.normal(0.0, style.gaze_spread, n), -40, 40)
    pitch = np.clip(rng.normal(-2.0, 0.6 * style.gaze_spread, n), -30, 30)
    yaw[0], pitch[0] = 0.0, 0.0
    amp = np.hypot(np.diff(yaw, prepend=0), np.diff(pitch, prepend=0))
    sacc = 0.02 + 0.0022 * amp  # saccade durations (s), main sequence
    starts = np.concatenate([[0.0], np.cumsum(fix + sacc)])[:n]
    t = np.arange(frames) / fps
    k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, n - 1)
    prev = np.maximum(k - 1, 0)
    ramp = np.clip((t - starts[k]) / sacc[k], 0.0, 1.0)
    ramp = ramp * ramp * (3 - 2 * ramp)
    gy = yaw[prev] + (yaw[k] - yaw[prev]) * ramp + _smooth(rng.normal(0, 1.5, frames), 0.3 * fps)
    gp = pitch[prev] + (pitch[k] - pitch[prev]) * ramp + _smooth(rng.normal(0, 1.5, frames), 0.3 * fps)
    verg = rng.uniform(0.5, 2.0)
    out = np.zeros((frames, N_SHAPES))
    for side, s in (("Left", 1.0), ("Right", -1.0)):
        y = (gy - s * verg) / full_scale_deg  # + = towards the subject's left
        p = gp / full_scale_deg  # + = up
        outward = s * y
        out[:, IDX[f"eyeLookOut{side}"]] = np.clip(outward, 0, 1)
        out[:, IDX[f"eyeLookIn{side}"]] = np.clip(-outward, 0, 1)
        out[:, IDX[f"eyeLookUp{side}"]] = np.clip(p, 0, 1)
        out[:, IDX[f"eyeLookDown{side}"]] = np.clip(-p, 0, 1)
        out[:, IDX[f"eyeBlink{side}"]] += 0.3 * np.clip(-p, 0, 1)  # lids follow a downward gaze
    return out


def idle_layer(rng: np.random.Generator, frames: int, fps: float, style: SequenceStyle) -> np.ndarray:
    minutes = frames / fps / 60.0
    n = rng.poisson(1.6 * style.idle * minutes * N_SHAPES)
    out = np.zeros((frames, N_SHAPES))
    if n:
        shape = rng.integers(0, N_SHAPES, n)
        start = rng.uniform(-1.0, frames / fps, n)
        dur = rng.uniform(0.4, 2.5, n)
        amp = rng.uniform(0.1, 0.7, n) * style.expressiveness * _IDLE_CAP[shape]
        t = np.arange(frames) / fps
        tau = (t[None, :] - start[:, None]) / dur[:, None]
        bump = np.where((tau > 0) & (tau < 1), 0.5 - 0.5 * np.cos(2 * np.pi * np.clip(tau, 0, 1)), 0.0) * amp[:, None]
        np.add.at(out.T, shape, bump)
        # Most sided events are two-sided: copy to the other side with some asymmetry.
        both = out.copy()
        left, right = _PAIRS[:, 0], _PAIRS[:, 1]
        mirror = rng.uniform(0.5, 0.9, len(_PAIRS))
        both[:, left] += mirror * out[:, right]
        both[:, right] += mirror * out[:, left]
        out = both
    tonus = (rng.random(N_SHAPES) < 0.3) * rng.uniform(0.0, 0.06, N_SHAPES)
    return out + tonus + np.abs(_smooth(rng.normal(0, 0.02, (frames, N_SHAPES)), 0.5 * fps))


def coactivate(w: np.ndarray) -> np.ndarray:
    """Co-activations of real captures, then clip to [0, 1] and mouthClose <= jawOpen."""
    w = w.copy()
    for side in ("Left", "Right"):
        smile = w[:, IDX[f"mouthSmile{side}"]]
        w[:, IDX[f"cheekSquint{side}"]] += 0.45 * smile
        w[:, IDX[f"eyeSquint{side}"]] += 0.25 * smile
        w[:, IDX[f"mouthUpperUp{side}"]] += 0.3 * w[:, IDX[f"noseSneer{side}"]]
        w[:, IDX[f"mouthLowerDown{side}"]] += 0.25 * w[:, IDX["jawOpen"]]
        w[:, IDX[f"eyeSquint{side}"]] += 0.2 * w[:, IDX[f"browDown{side}"]]
    w = np.clip(w, 0.0, 1.0)
    w[:, IDX["mouthClose"]] = np.minimum(w[:, IDX["mouthClose"]], w[:, IDX["jawOpen"]])
    return w


def generate_weights(rng: np.random.Generator, frames: int, fps: float = 30.0,
                     style: SequenceStyle | None = None) -> np.ndarray:
    """One subject's capture: arkit51 weights (frames, 51) float64 in [0, 1]."""
    style = SequenceStyle() if style is None else style
    layers = (emotion_layer, speech_layer, blink_layer, gaze_layer, idle_layer)
    total = sum(layer(rng, frames, fps, style) for layer in layers)
    scale = np.ones(N_SHAPES) * style.expressiveness
    for k in ("eyeBlinkLeft", "eyeBlinkRight", "eyeLookDownLeft", "eyeLookDownRight", "eyeLookInLeft",
              "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight", "eyeLookUpLeft", "eyeLookUpRight"):
        scale[IDX[k]] = 1.0  # blinks and gaze do not scale with expressiveness
    return coactivate(total * scale)
