"""The project's face-log CSV (protocol/FACELOG.md), which also reads MediaPipe and ARKit CSVs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ofera.mapping.layouts import Layout, LayoutError, layout_from_names
from ofera.sources._table import Table
from ofera.sources.facelog import DATA_SOURCES, FaceLog, SourceFormatError

TIME_COLUMNS: dict[str, float] = {"time": 1.0, "time_ms": 1e-3, "timestamp_ms": 1e-3, "timestamp_us": 1e-6}
"""Accepted time columns (lowercase) and their unit in seconds; `time` is the canonical one."""

FRAME_COLUMNS: tuple[str, ...] = ("frame", "frame_index", "frame_number")
"""Frame-index columns, used when there is no time column (needs a frame rate)."""

CONFIDENCE_COLUMNS: tuple[str, str] = ("confidence_lower", "confidence_upper")
DATA_SOURCE_COLUMN = "data_source"
_DATA_SOURCE_CODES = {"visual": 0, "audio": 1, "0": 0, "1": 1}


def read_facelog_csv(path: str | Path, layout: str | Layout = "auto", fps: float | None = None) -> FaceLog:
    """Read a face-log CSV, or a MediaPipe/ARKit blendshape CSV (time or frame column + names).

    The layout is `layout` unless "auto", else the `# layout:` comment, else detected from the names.
    A frame column needs `fps` or a `# fps:` comment. Times are returned relative to the first row.
    """
    table = Table(path)
    times = _times(table, fps)
    lower, upper = (table.find(c) for c in CONFIDENCE_COLUMNS)
    if (lower is None) != (upper is None):
        missing = CONFIDENCE_COLUMNS[0] if lower is None else CONFIDENCE_COLUMNS[1]
        raise SourceFormatError(f"column {missing!r} is missing (confidences come in pairs)", path)
    source_col = table.find(DATA_SOURCE_COLUMN)
    special = {table.find(*TIME_COLUMNS), table.find(*FRAME_COLUMNS), lower, upper, source_col}
    columns = [i for i in range(len(table.header)) if i not in special]
    hint = table.metadata.get("layout") if layout == "auto" else layout
    try:
        lay, index = layout_from_names([table.header[i] for i in columns], hint or None)
    except LayoutError as exc:
        raise SourceFormatError(str(exc), path, table.header_line) from None
    return FaceLog(
        times=times,
        weights=table.floats([columns[i] for i in index]).astype(np.float32),
        layout=lay,
        confidence=None if lower is None else table.floats([lower, upper]).astype(np.float32),
        data_source=None if source_col is None else _data_source(table, source_col),
        source=table.metadata.pop("source", f"CSV {path}"),
        metadata=table.metadata,
    )


def _times(table: Table, fps: float | None) -> np.ndarray:
    time_col = table.find(*TIME_COLUMNS)
    if time_col is not None:
        scale = TIME_COLUMNS[table.header[time_col].lower()]
        return table.relative_times(table.floats([time_col])[:, 0] * scale)
    frame_col = table.find(*FRAME_COLUMNS)
    if frame_col is None:
        raise SourceFormatError(
            f"no time column (one of {', '.join((*TIME_COLUMNS, *FRAME_COLUMNS))})",
            table.path,
            table.header_line,
        )
    rate = fps if fps is not None else table.metadata.get("fps")
    if rate is None:
        raise SourceFormatError("a frame column needs a frame rate: pass fps or add '# fps: N'", table.path)
    try:
        rate = float(rate)
    except ValueError:
        raise SourceFormatError(f"frame rate {rate!r} is not a number", table.path) from None
    if not rate > 0:
        raise SourceFormatError(f"frame rate must be positive, got {rate}", table.path)
    return table.relative_times(table.floats([frame_col])[:, 0] / rate)


def _data_source(table: Table, column: int) -> np.ndarray:
    codes = np.empty(len(table.rows), dtype=np.uint8)
    for row, text in enumerate(table.texts(column)):
        code = _DATA_SOURCE_CODES.get(text.strip().lower())
        if code is None:
            raise SourceFormatError(f"data_source {text!r} is not one of {DATA_SOURCES}", table.path, table.lines[row])
        codes[row] = code
    return codes


def write_facelog(path: str | Path, log: FaceLog) -> None:
    """Write `log` as a face-log CSV: times %.6f s, weights and confidences %.6g, layout order."""
    header = ["time", *log.layout.names]
    blocks = [log.times[:, None], log.weights]
    if log.confidence is not None:
        if log.confidence.shape[1] != len(CONFIDENCE_COLUMNS):
            raise ValueError(f"face-log CSV confidence must be (T, 2) lower/upper, got {log.confidence.shape}")
        header += CONFIDENCE_COLUMNS
        blocks.append(log.confidence)
    numbers = np.hstack([b.astype(np.float64) for b in blocks])
    fmt = ",".join(["%.6f"] + ["%.6g"] * (numbers.shape[1] - 1))
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(f"# ofera facelog 1\n# layout: {log.layout.name}\n")
        for key, value in {"source": log.source, **log.metadata}.items():
            if key != "layout" and value:
                f.write(f"# {key}: {' '.join(str(value).split())}\n")
        if log.data_source is None:
            f.write(",".join(header) + "\n")
            f.writelines(fmt % tuple(row) + "\n" for row in numbers)
        else:
            f.write(",".join([*header, DATA_SOURCE_COLUMN]) + "\n")
            f.writelines(
                fmt % tuple(row) + f",{DATA_SOURCES[code]}\n"
                for row, code in zip(numbers, log.data_source, strict=True)
            )
