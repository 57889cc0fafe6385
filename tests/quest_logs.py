"""Quest Pro Unity logs as other people's loggers write them (REFERENCE.md 1, "Quest Pro recordings in
the wild"), for the reader and replay tests: `write_quest_log(path, ...) -> QuestTruth`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ofera.mapping.layouts import OVR63_NAMES, OVR70_NAMES

LABELS = ("Neutral", "Happy", "Sad", "Surprise", "Anger")


_SIDES = {"L", "R", "LB", "LT", "RB", "RT", "B", "T"}


def _parts(name: str) -> list[str]:
    """OpenXR name parts in Meta's C# casing: words capitalised, side suffixes (L, RB, ...) kept."""
    return [p if p in _SIDES else p.capitalize() for p in name.split("_")]


def v1_names() -> list[str]:
    """OVRFaceExpressions.FaceExpression spelling: BrowLowererL ... EyesLookUpL ... UpperLipRaiserR (63)."""
    return ["".join(_parts(n)) for n in OVR63_NAMES]


def v2_names() -> list[str]:
    """OVRPlugin.FaceExpression2 spelling: Brow_Lowerer_L ... Tongue_Retreat (70)."""
    return ["_".join(_parts(n)) for n in OVR70_NAMES]


def cs_float(x: float) -> str:
    """C# float.ToString() (7 significant digits, E notation for small numbers): 1.401298E-45, 7.413328E-07."""
    if x == 0:
        return "0"
    return f"{float(np.float32(x)):.7G}"


@dataclass
class QuestTruth:
    """What a correct reader finds: the kept samples' times (s, from 0) and weights, rows written."""

    times: np.ndarray
    weights: np.ndarray
    confidence: np.ndarray | None
    rows: int
    invalid: int


def write_quest_log(
    path: Path,
    *,
    version: int = 2,
    seconds: float = 4.0,
    tracker_hz: float = 36.0,
    row_hz: float = 83.0,
    tracker_time: bool = True,
    clock: str | None = "timeSinceStartup",
    status: bool = True,
    confidence: bool = True,
    label: bool = False,
    bom: bool = False,
    max_column: bool = False,
    shuffle: bool = False,
    invalid_window: tuple[float, float] | None = (1.0, 1.25),
    headerless: bool = False,
    seed: int = 0,
) -> QuestTruth:
    """A logger in FixedUpdate at `row_hz` over a tracker at `tracker_hz` (each row repeats the newest
    sample); rows in `invalid_window` (seconds) have status false and zeros. `row_hz` = `tracker_hz` with
    no time columns makes a snapshot log (one row per sample)."""
    rng = np.random.default_rng(seed)
    k = 70 if version == 2 else 63
    names = v2_names() if version == 2 else v1_names()
    n_samples = int(seconds * tracker_hz) + 1
    sample_w = rng.uniform(0, 1, (n_samples, k)).astype(np.float32)
    sample_w[:, 5] = 1.401298e-45  # C# denormal output
    sample_w[:, 7] = 7.413328e-07
    sample_w = np.array([[float(cs_float(v)) for v in row] for row in sample_w], np.float32)
    sample_conf = rng.uniform(0.85, 1.0, (n_samples, 2)).astype(np.float32)
    t_device = 5021.25 + np.arange(n_samples) / tracker_hz  # device clock
    snapshot = row_hz == tracker_hz
    n_rows = n_samples if snapshot else int(seconds * row_hz) + 1
    row_t = np.arange(n_rows) / row_hz
    sample_of_row = np.arange(n_rows) if snapshot else np.floor(row_t * tracker_hz + 1e-9).astype(int)
    sample_of_row = np.minimum(sample_of_row, n_samples - 1)
    valid = np.ones(n_rows, bool)
    if invalid_window is not None:
        valid &= ~((row_t >= invalid_window[0]) & (row_t < invalid_window[1]))
    header: list[str] = []
    if clock:
        header.append(clock)
    if tracker_time:
        header.append("Face_Time")
    if status:
        header.append("Face_Status")
    header += names
    if max_column:
        header.append("Max")
    if confidence:
        header += ["FaceRegionConfidence_Lower", "FaceRegionConfidence_Upper"]
    if label:
        header.append("Emotion")
    order = rng.permutation(len(header)) if shuffle else np.arange(len(header))
    lines = [] if headerless else [",".join(header[i] for i in order)]
    for r in range(n_rows):
        s = sample_of_row[r]
        ok = valid[r] or not status
        cells: list[str] = []
        if clock:
            cells.append(cs_float(17.5 + row_t[r]))
        if tracker_time:
            cells.append(repr(float(t_device[s])) if ok else "0")
        if status:
            cells.append("true" if valid[r] else "false")
        cells += [cs_float(v) if ok else "0" for v in sample_w[s]]
        if max_column:
            cells.append("")
        if confidence:
            cells += [cs_float(v) if ok else "0" for v in sample_conf[s]]
        if label:
            cells.append(LABELS[s % len(LABELS)])
        lines.append(",".join(cells[i] for i in order))
    text = "\n".join(lines) + "\n"
    path.write_bytes(("\ufeff" + text if bom else text).encode("utf-8"))
    kept_rows = np.flatnonzero(valid) if status else np.arange(n_rows)
    kept = []
    for r in kept_rows:
        if not kept or sample_of_row[r] != sample_of_row[kept[-1]]:
            kept.append(r)
    ids = sample_of_row[kept]
    if tracker_time:
        times = t_device[ids]
    elif clock:
        times = 17.5 + row_t[kept]
    else:
        times = np.asarray(kept, np.float64)  # row positions; the caller divides by its fps
    return QuestTruth(times=times - times[0], weights=sample_w[ids],
                      confidence=sample_conf[ids] if confidence else None, rows=n_rows,
                      invalid=int((~valid).sum()) if status else 0)
