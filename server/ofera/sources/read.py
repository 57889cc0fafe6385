"""`read_facelog`: open any supported face log, choosing the reader by content."""

from __future__ import annotations

from pathlib import Path

from ofera.mapping.layouts import Layout, get_layout
from ofera.sources.facelog import FaceLog, SourceFormatError
from ofera.sources.facelog_csv import read_facelog_csv
from ofera.sources.gesichter import read_gesichter
from ofera.sources.livelink_csv import read_livelink_csv
from ofera.sources.quest_csv import read_quest_csv, sniff_quest_log

_GZIP_MAGIC = b"\x1f\x8b"


def read_facelog(path: str | Path, layout: str | Layout = "auto", fps: float | None = None) -> FaceLog:
    """Read a face log: `.gesichter` (gzip), Live Link Face CSV (a Timecode column), a Quest Pro Unity log
    (Meta enum names with other columns, or headerless: `quest_csv`), else face-log / MediaPipe / ARKit CSV.
    `layout` forces or checks the layout (a headerless Quest log needs ovr63 or ovr70); `fps` is the Live
    Link timecode rate (default 60), the rate of a CSV frame column, or the row rate of a Quest log
    without a time column.
    """
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(2)
    if path.suffix.lower() == ".gesichter" or magic == _GZIP_MAGIC:
        log = read_gesichter(path)
    elif "timecode" in _header(path):
        log = read_livelink_csv(path, 60.0 if fps is None else fps)
    elif sniff_quest_log(path):
        return read_quest_csv(path, layout, fps)
    else:
        return read_facelog_csv(path, layout, fps)
    if layout != "auto" and log.layout != get_layout(layout):
        raise SourceFormatError(f"holds layout {log.layout.name!r}, not {get_layout(layout).name!r}", path)
    return log


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
