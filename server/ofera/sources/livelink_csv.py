"""Live Link Face CSV recordings: `Timecode,BlendshapeCount,<61 PascalCase names>`, parsed by name."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ofera.mapping.layouts import LayoutError, layout_from_names
from ofera.sources._table import Table
from ofera.sources.facelog import FaceLog, SourceFormatError

_TIMECODE = re.compile(r"(\d{1,2}):(\d{2}):(\d{2})[:;](\d+(?:\.\d*)?)")
_DAY = 86400.0


def parse_timecode(text: str, fps: float = 60.0) -> float:
    """`HH:MM:SS:FF.fff` (FF.fff = frame within the second at `fps`) -> seconds since midnight."""
    match = _TIMECODE.fullmatch(text.strip())
    if match is None:
        raise ValueError(f"timecode {text!r} is not HH:MM:SS:FF.fff")
    hours, minutes, seconds = (int(g) for g in match.group(1, 2, 3))
    frame = float(match.group(4))
    if hours >= 24 or minutes >= 60 or seconds >= 60:
        raise ValueError(f"timecode {text!r} is out of range")
    if frame >= fps:
        raise ValueError(f"timecode {text!r}: frame {frame:g} is not below {fps:g} fps (wrong fps?)")
    return hours * 3600.0 + minutes * 60.0 + seconds + frame / fps


def read_livelink_csv(path: str | Path, fps: float = 60.0) -> FaceLog:
    """Read a Live Link Face CSV into livelink61 order; times relative to the first row.

    Timecodes crossing midnight keep counting up; any other step back is an error.
    """
    table = Table(path)
    tc_col = table.find("timecode")
    if tc_col is None:
        raise SourceFormatError("no 'Timecode' column", path, table.header_line)
    special = {tc_col, table.find("blendshapecount")}
    columns = [i for i in range(len(table.header)) if i not in special]
    try:
        layout, index = layout_from_names([table.header[i] for i in columns])
    except LayoutError as exc:
        raise SourceFormatError(str(exc), path, table.header_line) from None
    times = np.empty(len(table.lines), dtype=np.float64)
    day = 0.0
    for row, text in enumerate(table.texts(tc_col)):
        try:
            t = parse_timecode(text, fps) + day
        except ValueError as exc:
            raise SourceFormatError(str(exc), path, table.lines[row]) from None
        if row and t < times[row - 1] - _DAY / 2:
            day += _DAY
            t += _DAY
        times[row] = t
    return FaceLog(
        times=table.relative_times(times),
        weights=table.floats([columns[i] for i in index]).astype(np.float32),
        layout=layout,
        source=f"Live Link Face CSV {path}",
        metadata=table.metadata,
    )
