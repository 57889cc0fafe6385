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
    max_cell: bool = True,
    shuffle: bool = False,
    invalid_window: tuple[float, float] | None = (1.0, 1.25),
    lead_s: float = 0.0,
    tracker_name: str = "Face_Time",
    device_t0: float = 5021.25,
    tracker_csharp: bool = False,
    headerless: bool = False,
    seed: int = 0,
) -> QuestTruth:
    """A logger in FixedUpdate at `row_hz` over a tracker at `tracker_hz` (each row repeats the newest
    sample); rows in `invalid_window` (seconds of tracking) are not faces: zeros, status false, tracker time 0
    (with a tracker time and no status column, that 0 is all that says so). `row_hz` = `tracker_hz` with no
    time columns makes a snapshot log (one row per sample).

    `max_column` adds `Max` (Enum.GetNames) after the names: with `max_cell` False the rows hold no value for
    it (the header is one longer than the rows). `lead_s`: the logger runs that long before tracking starts
    (invalid rows first). `tracker_csharp` writes the tracker time as a C# float (7 significant digits: 0.1 s
    steps at a `device_t0` of 1e5 s, too coarse for 36 Hz; the truth then follows the Unity clock, as the
    reader must)."""
    assert not (shuffle and max_column and not max_cell), "a value-less Max only makes sense in enum order"
    rng = np.random.default_rng(seed)
    k = 70 if version == 2 else 63
    names = v2_names() if version == 2 else v1_names()
    n_samples = int(seconds * tracker_hz) + 1
    sample_w = rng.uniform(0, 1, (n_samples, k)).astype(np.float32)
    sample_w[:, 5] = 1.401298e-45  # C# denormal output
    sample_w[:, 7] = 7.413328e-07
    sample_w = np.array([[float(cs_float(v)) for v in row] for row in sample_w], np.float32)
    sample_conf = rng.uniform(0.85, 1.0, (n_samples, 2)).astype(np.float32)
    t_device = device_t0 + np.arange(n_samples) / tracker_hz  # device clock
    tracker_text = [cs_float(t) if tracker_csharp else repr(float(t)) for t in t_device]
    snapshot = row_hz == tracker_hz
    assert not (snapshot and lead_s), "a snapshot log has no rows before tracking"
    n_rows = n_samples if snapshot else int((seconds + lead_s) * row_hz) + 1
    row_t = np.arange(n_rows) / row_hz
    track_t = row_t - lead_s  # time since tracking started
    sample_of_row = np.arange(n_rows) if snapshot else np.floor(track_t * tracker_hz + 1e-9).astype(int)
    sample_of_row = np.clip(sample_of_row, 0, n_samples - 1)
    valid = track_t >= 0
    if invalid_window is not None:
        valid &= ~((track_t >= invalid_window[0]) & (track_t < invalid_window[1]))
    marked = status or tracker_time  # something in the file says which rows are not faces
    header: list[str] = []
    if clock:
        header.append(clock)
    if tracker_time:
        header.append(tracker_name)
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
        ok = valid[r] or not marked
        cells: list[str | None] = []
        if clock:
            cells.append(cs_float(17.5 + row_t[r]))
        if tracker_time:
            cells.append(tracker_text[s] if ok else "0")
        if status:
            cells.append("true" if valid[r] else "false")
        cells += [cs_float(v) if ok else "0" for v in sample_w[s]]
        if max_column:
            cells.append("" if max_cell else None)
        if confidence:
            cells += [cs_float(v) if ok else "0" for v in sample_conf[s]]
        if label:
            cells.append(LABELS[s % len(LABELS)])
        lines.append(",".join(c for c in (cells[i] for i in order) if c is not None))
    text = "\n".join(lines) + "\n"
    path.write_bytes(("\ufeff" + text if bom else text).encode("utf-8"))
    kept_rows = np.flatnonzero(valid) if marked else np.arange(n_rows)
    kept = []
    for r in kept_rows:
        if not kept or sample_of_row[r] != sample_of_row[kept[-1]]:
            kept.append(r)
    ids = sample_of_row[kept]
    written = np.array([float(tracker_text[i]) for i in ids])
    coarse = tracker_time and bool(np.any(written[1:] == written[:-1]))
    if tracker_time and not coarse:
        times = written
    elif clock:
        times = 17.5 + row_t[kept]
    else:
        times = np.asarray(kept, np.float64)  # row positions; the caller divides by its fps
    return QuestTruth(times=times - times[0], weights=sample_w[ids],
                      confidence=sample_conf[ids] if confidence else None, rows=n_rows,
                      invalid=int((~valid).sum()) if marked else 0)
