"""The synthetic paired benchmark: a fair stand-in for the paper's paired captures.

Per subject: a rig style and identity (:mod:`.rig`), a capture-like expression sequence
(:mod:`.sequences`), the rig's meshes, FLAME values fitted to them as a tracker does (:mod:`.fit`),
camera-style blendshape estimates of the same frames and a simulated headset stream (:mod:`.observe`).

Three training sources of ten subjects (they differ in what is recorded, in estimator noise and in the
headset that records them, like different capture sets), each split 8/1/1 subject-disjoint into
train/val/test, and one held-out source (``HOLDOUT``: its own sequence style, estimator and headset)
whose five subjects are all test: the held-out-source split, which no training or validation frame
shares anything with. ``make_benchmark`` is deterministic in ``seed``; every subject draws from its own
generator, so subjects do not depend on each other or on the frame count of others.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass

import numpy as np

from ofera.head.io import default_head
from ofera.head.model import HeadModel
from ofera.training.paired._threads import single_blas_thread
from ofera.training.paired.data import SPLITS, PairedData
from ofera.training.paired.fit import FlameFitter, fit_vertices
from ofera.training.paired.observe import (
    EstimatorNoise,
    HeadsetDevice,
    estimator_params,
    headset_stream,
    observe_camera,
)
from ofera.training.paired.rig import Rig, RigBasis, RigStyle
from ofera.training.paired.sequences import SequenceStyle, generate_weights

Progress = Callable[[int, int, str], None]


@dataclass(frozen=True)
class Source:
    """A capture set: what it records and how noisy its blendshape estimator is."""

    name: str
    sequence: SequenceStyle
    noise: EstimatorNoise


SOURCES: tuple[Source, ...] = (
    Source("studio", SequenceStyle(emotion=1.0, speech=0.3, idle=1.0, expressiveness=1.0, blink_rate=15.0,
                                   gaze_spread=10.0),
           EstimatorNoise(gain=0.10, bias=0.02, crosstalk=0.04, lag=0.25, jitter=0.012, slips=0.02, dropouts=1.0,
                          saturation=1.0)),
    Source("conversation", SequenceStyle(emotion=0.5, speech=0.75, idle=0.8, expressiveness=0.9, blink_rate=18.0,
                                         gaze_spread=8.0),
           EstimatorNoise(gain=0.20, bias=0.04, crosstalk=0.08, lag=0.45, jitter=0.03, slips=0.06, dropouts=3.0,
                          saturation=3.0)),
    Source("expressive", SequenceStyle(emotion=0.9, speech=0.4, idle=1.8, expressiveness=1.15, blink_rate=13.0,
                                       gaze_spread=14.0),
           EstimatorNoise(gain=0.15, bias=0.03, crosstalk=0.06, lag=0.35, jitter=0.022, slips=0.04, dropouts=2.0,
                          saturation=2.0)),
)

HOLDOUT: tuple[Source, ...] = (
    # A webcam-style estimator on casual, talkative footage: never seen in training or validation.
    Source("handheld", SequenceStyle(emotion=0.7, speech=0.6, idle=1.2, expressiveness=1.05, blink_rate=16.0,
                                     gaze_spread=11.0),
           EstimatorNoise(gain=0.18, bias=0.035, crosstalk=0.07, lag=0.4, jitter=0.026, slips=0.05, dropouts=2.5,
                          saturation=2.5)),
)
HOLDOUT_SUBJECTS = 5

TINY = {"subjects_per_source": 2, "frames_per_subject": 100, "holdout_subjects": 2}


@dataclass(frozen=True)
class PlannedSubject:
    """Where one subject of the benchmark comes from: its id, source (index into sources + holdout), split."""

    subject: int
    source: int
    split: int


def plan_subjects(seed: int, subjects_per_source: int, n_sources: int, n_holdout: int,
                  holdout_subjects: int) -> list[PlannedSubject]:
    """Every subject of the benchmark in generation order (training sources first, then held-out ones)."""
    plan = []
    for s in range(n_sources):
        splits = assign_splits(subjects_per_source, s, np.random.default_rng([seed, 0x5B1, s]))
        plan += [PlannedSubject(s * subjects_per_source + k, s, int(splits[k])) for k in range(subjects_per_source)]
    first = n_sources * subjects_per_source
    for h in range(n_holdout):
        plan += [PlannedSubject(first + h * holdout_subjects + k, n_sources + h, SPLITS.index("test"))
                 for k in range(holdout_subjects)]
    return plan


def source_models(seed: int, index: int, source: Source) -> tuple[dict[str, np.ndarray], HeadsetDevice]:
    """The camera estimator and the headset of source number ``index`` (each source has its own)."""
    estimator = estimator_params(np.random.default_rng([seed, 0x50C, index]), source.noise)
    return estimator, HeadsetDevice.random(np.random.default_rng([seed, 0x0DE7, index]))


def assign_splits(n: int, source_index: int, rng: np.random.Generator) -> np.ndarray:
    """Split codes for the n subjects of one source: 8/1/1 for ten (10% val, 10% test, at least one each
    from three subjects up); with two subjects, one train and one val or test (alternating by source)."""
    codes = np.zeros(n, np.int8)
    order = rng.permutation(n)
    if n >= 3:
        k = max(1, int(round(0.1 * n)))
        codes[order[:k]] = SPLITS.index("val")
        codes[order[k:2 * k]] = SPLITS.index("test")
    elif n == 2:
        codes[order[0]] = SPLITS.index("val") if source_index % 2 == 0 else SPLITS.index("test")
    return codes


def _rich_progress() -> tuple[Progress, Callable[[], None]]:
    from rich.progress import BarColumn, TextColumn, TimeElapsedColumn
    from rich.progress import Progress as RichProgress

    bar = RichProgress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                       TimeElapsedColumn())
    bar.start()
    task = bar.add_task("paired data", total=1)

    def update(done: int, total: int, message: str) -> None:
        bar.update(task, completed=done, total=total, description=message)

    return update, bar.stop


def make_subject(head: HeadModel, basis: RigBasis, fitter: FlameFitter, seed: int, subject: int,
                 source: Source, frames: int, fps: float, estimator: dict, device: HeadsetDevice,
                 chunk: int = 200) -> dict[str, np.ndarray]:
    """One subject's frames: rig weights, FLAME fit, camera bs, headset stream, identity."""
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence([seed, subject]).spawn(4)]
    style = RigStyle.random(rngs[0], head.shape_dims)
    seq = source.sequence
    seq = SequenceStyle(emotion=seq.emotion, speech=seq.speech, idle=seq.idle,
                        expressiveness=seq.expressiveness * rngs[0].uniform(0.85, 1.15),
                        blink_rate=seq.blink_rate * rngs[0].uniform(0.7, 1.4), gaze_spread=seq.gaze_spread)
    w = generate_weights(rngs[1], frames, fps, seq)
    rig = Rig(head, style, fitter.vertex_ids, basis)
    fitter = fitter.with_identity(style.shape)
    flame, rms = np.empty((frames, 68)), np.empty(frames)
    for start in range(0, frames, chunk):
        res = fitter.fit(rig.mesh(w[start:start + chunk]))
        flame[start:start + chunk], rms[start:start + chunk] = res.flame, res.rms
    return {"rig_weights": w, "flame": flame, "fit_rms": rms, "bs": observe_camera(rngs[2], w, fps, source.noise,
                                                                                     estimator),
            "headset": headset_stream(rngs[3], w, device), "shape": style.shape}


def make_benchmark(frames_per_subject: int = 1500, seed: int = 0, tiny: bool = False,
                   progress: Progress | bool | None = None, head: HeadModel | None = None,
                   subjects_per_source: int = 10, fps: float = 30.0,
                   sources: tuple[Source, ...] = SOURCES, holdout: tuple[Source, ...] = HOLDOUT,
                   holdout_subjects: int = HOLDOUT_SUBJECTS) -> PairedData:
    """Generate the synthetic paired benchmark (deterministic in ``seed``).

    Full size: 3 sources x 10 subjects x ``frames_per_subject`` frames at ``fps``, plus
    ``holdout_subjects`` test subjects of each held-out source. ``tiny``: 3 x 2 subjects + 2 held-out x
    100 frames (tests). ``progress``: a callback ``(done, total, message)``, True for a rich progress bar,
    or None. ``head``: the procedural head (default); the rig needs its landmarks and labels.
    """
    if tiny:
        subjects_per_source, frames_per_subject = TINY["subjects_per_source"], TINY["frames_per_subject"]
        holdout_subjects = TINY["holdout_subjects"]
    if frames_per_subject < 1 or subjects_per_source < 1:
        raise ValueError("frames_per_subject and subjects_per_source must be positive")
    head = default_head() if head is None else head
    basis = RigBasis.build(head)
    fitter = FlameFitter(head, None, fit_vertices(head))
    every = sources + holdout
    models = [source_models(seed, i, src) for i, src in enumerate(every)]
    plan = plan_subjects(seed, subjects_per_source, len(sources), len(holdout) if holdout_subjects else 0,
                         holdout_subjects)
    parts: list[dict[str, np.ndarray]] = []
    with ExitStack() as stack:
        stack.enter_context(single_blas_thread())
        if progress is True:
            update, stop = _rich_progress()
            stack.callback(stop)
            progress = update
        report = progress if callable(progress) else (lambda done, total, message: None)
        for n, p in enumerate(plan):
            report(n, len(plan), f"subject {p.subject + 1}/{len(plan)} ({every[p.source].name})")
            estimator, device = models[p.source]
            part = make_subject(head, basis, fitter, seed, p.subject, every[p.source], frames_per_subject, fps,
                                estimator, device)
            part |= {"subject": np.full(frames_per_subject, p.subject), "source": np.full(frames_per_subject, p.source),
                     "split": np.full(frames_per_subject, p.split), "frame": np.arange(frames_per_subject)}
            parts.append(part)
        report(len(plan), len(plan), "paired data done")
    keys = ("bs", "flame", "subject", "source", "split", "frame", "headset", "rig_weights", "fit_rms")
    data = {k: np.concatenate([p[k] for p in parts]) for k in keys}
    meta = {"generator": "ofera.training.paired.make_benchmark", "seed": seed, "tiny": tiny,
            "frames_per_subject": frames_per_subject, "subjects_per_source": subjects_per_source,
            "holdout_sources": [src.name for src in holdout] if holdout_subjects else [],
            "holdout_subjects": holdout_subjects, "head": head.name}
    return PairedData(**data, fps=fps, shape=np.stack([p["shape"] for p in parts]),
                      source_names=tuple(src.name for src in every), meta=meta)


# ----- provenance: a small regenerated sample that any change to the generator changes -----------------------

SAMPLE_FRAMES = 60
SAMPLE_STEP = 1e-3  # rounding step of the sample's values before hashing (BLAS and CPU differences are ~1e-10)


def validation_sample(seed: int = 0, frames: int = SAMPLE_FRAMES, head: HeadModel | None = None) -> dict:
    """The first validation subject of the full benchmark, regenerated at ``frames`` frames through the same
    code path -> {"subject", "source", "frames", "bs" (frames, 51), "flame" (frames, 68)}."""
    head = default_head() if head is None else head
    plan = plan_subjects(seed, 10, len(SOURCES), len(HOLDOUT), HOLDOUT_SUBJECTS)
    first = next(p for p in plan if p.split == SPLITS.index("val"))
    estimator, device = source_models(seed, first.source, SOURCES[first.source])
    with single_blas_thread():
        part = make_subject(head, RigBasis.build(head), FlameFitter(head, None, fit_vertices(head)), seed,
                            first.subject, SOURCES[first.source], frames, 30.0, estimator, device)
    return {"subject": first.subject, "source": SOURCES[first.source].name, "frames": frames,
            "bs": part["bs"], "flame": part["flame"]}


def sample_digest(sample: dict) -> str:
    """SHA-256 of the sample's ``bs`` and ``flame`` rounded to ``SAMPLE_STEP`` (as int32, little-endian)."""
    import hashlib

    digest = hashlib.sha256()
    for key in ("bs", "flame"):
        q = np.rint(np.asarray(sample[key], np.float64) / SAMPLE_STEP).astype("<i4")
        digest.update(key.encode())
        digest.update(q.tobytes())
    return digest.hexdigest()
