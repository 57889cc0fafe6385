"""`inspect_facelog`: read a face log as `read_facelog` does and say what it held (`ofera replay inspect`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ofera.mapping.layouts import Layout
from ofera.sources.facelog import FaceLog
from ofera.sources.quest_csv import FACELOG_MAGIC, QuestLogReport, read_quest_csv_report, sniff_quest_log
from ofera.sources.read import _GZIP_MAGIC, _header, read_facelog


def inspect_facelog(
    path: str | Path, layout: str | Layout = "auto", fps: float | None = None
) -> tuple[FaceLog, QuestLogReport]:
    """The log `read_facelog(path, layout, fps)` returns, and a report of what the file held.

    Quest Pro logs get the Quest reader's full report (repeats and invalid rows dropped, time source,
    columns ignored); other formats keep every row, so their report has no drops.
    """
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(2)
    gz = path.suffix.lower() == ".gesichter" or magic == _GZIP_MAGIC
    if not gz and sniff_quest_log(path):
        return read_quest_csv_report(path, layout, fps)
    log = read_facelog(path, layout, fps)
    if gz:
        fmt, source = "gesichter", "frame numbers at the packets' fps"
    elif "timecode" in _header(path):
        fmt, source = "livelink-csv", f"Timecode at {60.0 if fps is None else fps:g} fps"
    else:
        fmt = "facelog" if _has_magic(path) else "csv"
        source = "time column"
    steps = np.diff(log.times)
    steps = steps[steps > 0]
    report = QuestLogReport(
        path=str(path), format=fmt, layout=log.layout.name, rows=len(log), samples=len(log), time_source=source,
        duration_s=log.duration, rate_hz=float(1.0 / np.median(steps)) if steps.size else None,
        confidence=log.confidence is not None,
    )
    return log, report


def _has_magic(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            for line in f:
                if line.strip():
                    return line.strip().lstrip("#").strip().lower().startswith(FACELOG_MAGIC)
    except OSError:
        return False
    return False
