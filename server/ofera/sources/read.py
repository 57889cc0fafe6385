"""`read_facelog` / `read_facelog_report`: open any supported face log, choosing the reader by content."""

from __future__ import annotations

from pathlib import Path

from ofera.mapping.layouts import Layout, get_layout
from ofera.sources.facelog import FaceLog, SourceFormatError
from ofera.sources.facelog_csv import read_facelog_csv
from ofera.sources.gesichter import read_gesichter
from ofera.sources.livelink_csv import read_livelink_csv
from ofera.sources.quest_csv import FACELOG_MAGIC, read_quest_csv_report, sniff_quest_log
from ofera.sources.report import LogReport, median_rate

_GZIP_MAGIC = b"\x1f\x8b"


def read_facelog(path: str | Path, layout: str | Layout = "auto", fps: float | None = None) -> FaceLog:
    """Read a face log: `.gesichter` (gzip), Live Link Face CSV (a Timecode column), a Quest Pro Unity log
    (Meta enum names with other columns, or headerless: `quest_csv`), else face-log / MediaPipe / ARKit CSV.
    `layout` forces or checks the layout (a headerless Quest log needs ovr63 or ovr70); `fps` is the Live
    Link timecode rate (default 60), the rate of a CSV frame column, or the row rate of a Quest log
    without a time column.
    """
    return read_facelog_report(path, layout, fps)[0]


def read_facelog_report(
    path: str | Path, layout: str | Layout = "auto", fps: float | None = None
) -> tuple[FaceLog, LogReport]:
    """`read_facelog` (the one place that chooses the reader) and a `LogReport` of what the file held, as
    `ofera replay inspect` shows it. Quest Pro logs get the Quest reader's full report (repeats and invalid
    rows dropped, time source, columns ignored, notes); the other readers keep every row, so their report
    has no drops."""
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(2)
    if path.suffix.lower() == ".gesichter" or magic == _GZIP_MAGIC:
        log = read_gesichter(path)
        fmt, source = "gesichter", "frame numbers at the packets' fps"
    elif "timecode" in _header(path):
        rate = 60.0 if fps is None else fps
        log = read_livelink_csv(path, rate)
        fmt, source = "livelink-csv", f"Timecode at {rate:g} fps"
    elif sniff_quest_log(path):
        return read_quest_csv_report(path, layout, fps)
    else:
        log = read_facelog_csv(path, layout, fps)  # checks `layout` itself
        fmt, source = ("facelog" if _has_magic(path) else "csv"), "time column"
    if fmt in ("gesichter", "livelink-csv") and layout != "auto" and log.layout != get_layout(layout):
        raise SourceFormatError(f"holds layout {log.layout.name!r}, not {get_layout(layout).name!r}", path)
    report = LogReport(path=str(path), format=fmt, layout=log.layout.name, rows=len(log), samples=len(log),
                       time_source=source, duration_s=log.duration, rate_hz=median_rate(log.times),
                       confidence=log.confidence is not None)
    return log, report


def _has_magic(path: Path) -> bool:
    """True if the first non-blank line is the project's face-log magic comment (`# ofera facelog`)."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            for line in f:
                if line.strip():
                    return line.strip().lstrip("#").strip().lower().startswith(FACELOG_MAGIC)
    except OSError:
        return False
    return False


def _header(path: Path) -> list[str]:
    """Lowercased fields of the first line that is neither blank nor a `#` comment."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            for line in f:
                if line.strip() and not line.lstrip().startswith("#"):
                    return [field.strip().strip('"').lower() for field in line.split(",")]
    except UnicodeDecodeError:
        raise SourceFormatError("neither a gzip capture nor a UTF-8 CSV", path) from None
    raise SourceFormatError("no header line", path)
