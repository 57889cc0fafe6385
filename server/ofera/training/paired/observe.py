"""What the trackers report: camera-style blendshape estimates and a simulated headset (OVR63) stream.

Camera estimates (the ``bs`` of paired data, like MediaPipe's blendshapes next to a FLAME tracker):
the true rig weights through an estimator with per-source bias, gain, a nonlinear response curve per
shape (dead zone + power), cross-talk between shapes of a region, per-subject deviations, estimation
lag, temporal jitter (noise and frame slips), dropouts (held or zeroed frames) and occasional saturation,
clipped to [0, 1].

Headset stream: Meta's face tracking (OpenXR XR_FB_face_tracking, 63 weights). The true weights are
turned into OVR weights by inverting Meta's coarse v10 retargeting channel by channel
(:func:`ovr_from_arkit`, the right inverse of ``layouts.to_arkit51("ovr63", .)`` where nothing clamps),
then distorted per channel as a device does (gain, offset, response exponent, left/right leak, noise).
Meta's mapping applied to the stream then gives a distorted arkit51: what BDA must correct.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import lfilter

from ofera.mapping.layouts import ARKIT_REGIONS, OVR63_NAMES
from ofera.training.paired.rig import IDX, N_SHAPES

_OVR = {name: i for i, name in enumerate(OVR63_NAMES)}


@dataclass(frozen=True)
class EstimatorNoise:
    """A camera blendshape estimator (one per source): noise levels."""

    gain: float = 0.15  # log-sd of the per-shape gain
    bias: float = 0.03  # sd of the per-shape bias
    crosstalk: float = 0.06  # scale of leaks between shapes of one face region
    subject: float = 0.5  # per-subject deviation, as a fraction of gain/bias sd
    lag: float = 0.35  # EMA coefficient of the estimator's smoothing (0 = none)
    jitter: float = 0.02  # sd of per-frame noise
    slips: float = 0.04  # probability that a frame shows its neighbour
    dropouts: float = 2.0  # dropout episodes per minute (2-10 frames each)
    saturation: float = 2.0  # saturation episodes per minute (one shape pushed to 1 for 0.3-1.5 s)
    response: float = 0.20  # log-sd of the per-shape response exponent (regressors compress or inflate)
    knee: float = 0.08  # largest per-shape dead zone: weights below it read as 0


def _region_groups() -> list[np.ndarray]:
    return [np.array([IDX[n] for n in names if n in IDX]) for names in ARKIT_REGIONS.values()]


def estimator_params(rng: np.random.Generator, noise: EstimatorNoise) -> dict[str, np.ndarray]:
    """Per-source estimator: gain (51,), bias (51,), mixing matrix (51, 51)."""
    mix = np.eye(N_SHAPES)
    for group in _region_groups():
        leak = np.abs(rng.normal(0.0, noise.crosstalk, (len(group), len(group))))
        leak *= rng.random(leak.shape) < 0.3
        np.fill_diagonal(leak, 0.0)
        mix[np.ix_(group, group)] += leak
    return {"gain": np.exp(rng.normal(0.0, noise.gain, N_SHAPES)), "bias": rng.normal(0.0, noise.bias, N_SHAPES),
            "mix": mix, "gamma": np.exp(rng.normal(0.0, noise.response, N_SHAPES)),
            "knee": rng.uniform(0.0, noise.knee, N_SHAPES)}


def response_curve(u: np.ndarray, gamma: np.ndarray, knee: np.ndarray) -> np.ndarray:
    """A regressor's monotonic, nonlinear response per shape: a dead zone below ``knee``, then a power
    curve (gamma < 1 inflates small activations, > 1 compresses them), as camera blendshape estimators
    do. u (T, 51) in [0, 1] -> (T, 51) in [0, 1]."""
    return np.clip((np.clip(u, 0.0, 1.0) - knee) / (1.0 - knee), 0.0, 1.0) ** gamma


def _episodes(rng: np.random.Generator, frames: int, fps: float, per_minute: float, lo: int, hi: int):
    n = rng.poisson(per_minute * frames / fps / 60.0)
    starts = rng.integers(0, max(frames, 1), n)
    lengths = rng.integers(lo, hi + 1, n)
    return [(s, min(frames, s + length)) for s, length in zip(starts, lengths)]


def observe_camera(rng: np.random.Generator, w: np.ndarray, fps: float, noise: EstimatorNoise,
                   source: dict[str, np.ndarray]) -> np.ndarray:
    """Camera-estimated weights (T, 51) float64 in [0, 1] for true weights w (T, 51)."""
    t = len(w)
    gain = source["gain"] * np.exp(rng.normal(0.0, noise.gain * noise.subject, N_SHAPES))
    bias = source["bias"] + rng.normal(0.0, noise.bias * noise.subject, N_SHAPES)
    x = response_curve(w @ source["mix"].T, source["gamma"], source["knee"]) * gain + bias
    if noise.lag > 0:
        x = lfilter([1.0 - noise.lag], [1.0, -noise.lag], x - x[:1], axis=0) + x[:1]
    slip = rng.random(t) < noise.slips
    idx = np.arange(t)
    idx[slip] += rng.choice([-1, 1], slip.sum())
    x = x[np.clip(idx, 0, t - 1)]
    x = x + rng.normal(0.0, noise.jitter, x.shape) + gaussian_filter1d(
        rng.normal(0.0, noise.jitter, x.shape), 2.0, axis=0)
    for start, stop in _episodes(rng, t, fps, noise.saturation, int(0.3 * fps), int(1.5 * fps)):
        k = rng.integers(0, N_SHAPES)
        x[start:stop, k] = np.where(x[start:stop, k] > 0.25, 1.0, x[start:stop, k] * 1.5)
    x = np.clip(x, 0.0, 1.0)
    for start, stop in _episodes(rng, t, fps, noise.dropouts, 2, 10):
        x[start:stop] = x[start - 1] if (start > 0 and rng.random() < 0.6) else 0.0  # held, or lost
    return x


# ----- the headset -----------------------------------------------------------------------------------


def ovr_from_arkit(w: np.ndarray) -> np.ndarray:
    """OVR63 weights (T, 63) whose Meta v10 mapping (layouts.to_arkit51) gives back w (T, 51).

    Channels that several ARKit shapes share are split (browInnerUp = inner L + inner R, cheekSquint =
    cheek raiser + lip corner puller, ...). The exact right inverse where Meta's clamp is inactive.
    Channels the mapping ignores (CHEEK_SUCK, LIP_TIGHTENER) get plausible co-activations.
    """
    w = np.atleast_2d(np.asarray(w, np.float64))
    o = np.zeros((len(w), len(OVR63_NAMES)))

    def put(ovr: str, value: np.ndarray) -> None:
        o[:, _OVR[ovr]] = value

    a = {name: w[:, i] for name, i in IDX.items()}
    for side, s in (("Left", "L"), ("Right", "R")):
        smile = a[f"mouthSmile{side}"]
        put(f"BROW_LOWERER_{s}", a[f"browDown{side}"])
        put(f"OUTER_BROW_RAISER_{s}", a[f"browOuterUp{side}"] / 1.5)
        put(f"INNER_BROW_RAISER_{s}", a["browInnerUp"] / 2)
        put(f"CHEEK_PUFF_{s}", a["cheekPuff"] / 2)
        put(f"LIP_CORNER_PULLER_{s}", smile)
        put(f"CHEEK_RAISER_{s}", np.maximum(a[f"cheekSquint{side}"] - smile, 0.0))
        put(f"LID_TIGHTENER_{s}", np.maximum(a[f"eyeSquint{side}"] - 0.25 * smile, 0.0))
        put(f"EYES_CLOSED_{s}", a[f"eyeBlink{side}"])
        put(f"UPPER_LID_RAISER_{s}", a[f"eyeWide{side}"])
        put(f"LIP_PUCKER_{s}", a["mouthPucker"] / 1.5)
        put(f"LIP_CORNER_DEPRESSOR_{s}", a[f"mouthFrown{side}"])
        put(f"DIMPLER_{s}", a[f"mouthDimple{side}"])
        put(f"LIP_STRETCHER_{s}", a[f"mouthStretch{side}"])
        put(f"LIP_PRESSOR_{s}", a[f"mouthPress{side}"])
        put(f"LOWER_LIP_DEPRESSOR_{s}", a[f"mouthLowerDown{side}"])
        put(f"UPPER_LIP_RAISER_{s}", a[f"mouthUpperUp{side}"])
        put(f"NOSE_WRINKLER_{s}", a[f"noseSneer{side}"])
        put(f"EYES_LOOK_UP_{s}", a[f"eyeLookUp{side}"])
        put(f"EYES_LOOK_DOWN_{s}", a[f"eyeLookDown{side}"])
        put(f"CHEEK_SUCK_{s}", 0.3 * a["mouthPucker"])
        put(f"LIP_TIGHTENER_{s}", 0.6 * a[f"mouthPress{side}"])
        for lip in ("B", "T"):
            put(f"LIP_FUNNELER_{s}{lip}", np.maximum(a["mouthFunnel"] - a["mouthPucker"], 0.0) / 3)
        put(f"LIP_SUCK_{s}B", a["mouthRollLower"])
        put(f"LIP_SUCK_{s}T", a["mouthRollUpper"])
    # Meta's eye channels are by direction: "in" for the left eye is looking right, and vice versa.
    put("EYES_LOOK_RIGHT_L", a["eyeLookInLeft"])
    put("EYES_LOOK_LEFT_L", a["eyeLookOutLeft"])
    put("EYES_LOOK_LEFT_R", a["eyeLookInRight"])
    put("EYES_LOOK_RIGHT_R", a["eyeLookOutRight"])
    put("JAW_DROP", a["jawOpen"])
    put("JAW_THRUST", a["jawForward"])
    put("JAW_SIDEWAYS_LEFT", a["jawLeft"])
    put("JAW_SIDEWAYS_RIGHT", a["jawRight"])
    put("LIPS_TOWARD", a["mouthClose"])
    put("CHIN_RAISER_B", a["mouthShrugLower"])
    put("CHIN_RAISER_T", a["mouthShrugUpper"])
    put("MOUTH_LEFT", a["mouthLeft"])
    put("MOUTH_RIGHT", a["mouthRight"])
    return o


@dataclass(frozen=True)
class HeadsetDevice:
    """A headset's per-channel response: ovr_reported = clip(gain * ovr^gamma + offset + leak + noise)."""

    gain: np.ndarray  # (63,)
    offset: np.ndarray  # (63,)
    gamma: np.ndarray  # (63,)
    leak: np.ndarray  # (63,) share of the other side's channel (L <-> R)
    noise: float = 0.015

    @classmethod
    def random(cls, rng: np.random.Generator) -> HeadsetDevice:
        n = len(OVR63_NAMES)
        return cls(gain=np.exp(rng.normal(0.0, 0.3, n)), offset=rng.normal(0.0, 0.04, n),
                   gamma=np.exp(rng.normal(0.0, 0.15, n)), leak=np.abs(rng.normal(0.0, 0.08, n)))


def _other_side() -> np.ndarray:
    """Index of each OVR channel's other-side twin (itself when it has none)."""
    twin = np.arange(len(OVR63_NAMES))
    for name, i in _OVR.items():
        for a, b in (("_L", "_R"), ("_R", "_L"), ("_LB", "_RB"), ("_LT", "_RT"), ("_RB", "_LB"), ("_RT", "_LT")):
            if name.endswith(a) and name[: -len(a)] + b in _OVR:
                twin[i] = _OVR[name[: -len(a)] + b]
    return twin


_TWIN = _other_side()


def headset_stream(rng: np.random.Generator, w: np.ndarray, device: HeadsetDevice) -> np.ndarray:
    """The headset's OVR63 weights (T, 63) float64 in [0, 1] for true weights w (T, 51)."""
    ovr = np.clip(ovr_from_arkit(w), 0.0, 1.0)
    gain = device.gain * np.exp(rng.normal(0.0, 0.05, len(device.gain)))  # fit of the headset on this face
    x = gain * ovr**device.gamma + device.offset + device.leak * ovr[:, _TWIN]
    x = x + rng.normal(0.0, device.noise, x.shape)
    return np.clip(x, 0.0, 1.0)
