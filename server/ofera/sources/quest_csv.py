"""Quest Pro face-tracking logs written by Unity loggers (protocol/FACELOG.md, "Quest Pro logs").

What the reader takes:

- Blendshape columns named by Meta's enums: `OVRFaceExpressions.FaceExpression` (v1, 63, `BrowLowererL`)
  or `OVRPlugin.FaceExpression2` (v2, 70, `Brow_Lowerer_L` ... `Tongue_Retreat`), or the OpenXR spelling,
  in any order; names match case- and separator-insensitively (`_`, `-`, `.`, spaces), and an enum prefix
  (`FaceExpression.JawDrop`) is dropped unless the whole name is a time/status/confidence column
  (`FaceState.Time` is the tracker time). `Max`/`Invalid`/`Count` (from `Enum.GetNames`) are ignored; a
  logger that writes them in the header but no value for them in the rows (rows short by exactly that
  many) gets them left out of the header, with a note.
- Time: the tracker's own sample time `Face_Time` (device seconds), a Unity clock (`timeSinceStartup`,
  `realtimeSinceStartup`, `TimeFromStart`, `time`, `Timestamp`; seconds), or none (then `fps` paces the
  rows). The best present is used: tracker time > Unity clock > `fps`. A tracker time of 0 (or below) is
  not a sample: loggers write 0 before tracking starts, and those rows are invalid like status-false rows.
  Steps over `LONG_GAP_S` in the file's time are kept (the replay waits through them) and noted.
- `Face_Status` (`true`/`false`, `1`/`0`): rows that are not valid faces are dropped.
- `FaceRegionConfidence_Lower`/`_Upper` (or `confidence_lower`/`_upper`): kept as `FaceLog.confidence`.
- `Face_DataSource`/`data_source` (`visual`/`audio`): kept as `FaceLog.data_source`.
- Anything else (labels such as `Emotion`, head pose, frame counters) is ignored and reported.
- C# `ToString()` floats (`1.401298E-45`), a UTF-8 BOM, `#` comment lines (`# key: value` is metadata),
  `,`, `;` or tab separators (with `;` or tab, a decimal comma is accepted), and headerless files in enum
  order (`layout` says ovr63 or ovr70).

Repeated rows. Loggers in `Update`/`FixedUpdate` write faster than the tracker samples (rows at 83 Hz,
samples at 36 Hz). With a tracker time, a sample is a row with a new tracker time; the other rows are
repeats. Without one, a row whose weights equal the previous kept row's exactly is a repeat (a tracker
does not produce two bit-identical 63-float samples in a row); each sample keeps the time of its first
row. A tracker time too coarse to tell samples apart (a float `Face_Time` at a large device uptime: rows
with the same tracker time but different weights) is not used: samples are then found by weight changes
and timed by the Unity clock (or `fps`), with a note.

Malformed rows (wrong field count, a cell that is not a finite number, an unknown status) are
dropped and counted; more than `MAX_MALFORMED_SHARE` of them is an error (a wrong format, not a glitch).
"""

from __future__ import annotations

import csv
import io
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ofera.mapping.layouts import OVR63_NAMES, OVR70_NAMES, Layout, LayoutError, get_layout
from ofera.sources.facelog import DATA_SOURCES, FaceLog, SourceFormatError
from ofera.sources.report import LogReport, median_rate

TRACKER_TIME_KEYS: tuple[str, ...] = ("facetime", "trackertime", "facestatetime")
"""Tracker sample time columns (matching keys), device seconds."""

CLOCK_KEYS: tuple[str, ...] = ("timesincestartup", "realtimesincestartup", "timefromstart", "time", "timestamp")
"""Unity clock columns (matching keys), seconds; the first present wins."""

STATUS_KEYS: tuple[str, ...] = ("facestatus", "facevalid", "isvalid")
CONFIDENCE_KEYS: tuple[tuple[str, ...], tuple[str, ...]] = (
    ("faceregionconfidencelower", "confidencelower", "lowerfaceconfidence"),
    ("faceregionconfidenceupper", "confidenceupper", "upperfaceconfidence"),
)
DATA_SOURCE_KEYS: tuple[str, ...] = ("facedatasource", "datasource")
ENUM_EXTRA_KEYS: tuple[str, ...] = ("max", "invalid", "count")
"""Enum members that `Enum.GetNames` adds and that are not expressions."""
_SPECIAL_KEYS = frozenset(TRACKER_TIME_KEYS + CLOCK_KEYS + STATUS_KEYS + CONFIDENCE_KEYS[0] + CONFIDENCE_KEYS[1]
                          + DATA_SOURCE_KEYS)

LONG_GAP_S = 3.0
"""A step in the file's time longer than this (seconds: tracking lost, the app paused) is noted in the report."""

MAX_MALFORMED_SHARE = 0.05
"""Largest share of malformed rows tolerated (dropped and reported); above it the file is refused."""

FACELOG_MAGIC = "ofera facelog"
"""First words of the project's own face-log CSV (protocol/FACELOG.md), read by the strict reader."""

_STATUS_VALUES = {"true": True, "1": True, "valid": True, "yes": True,
                  "false": False, "0": False, "invalid": False, "no": False}
_DATA_SOURCE_CODES = {"visual": 0, "audio": 1, "0": 0, "1": 1}
_SEPARATORS = re.compile(r"[\s_\-.]+")
_OVR_KEYS: dict[str, int] = {n.replace("_", "").lower(): i for i, n in enumerate(OVR70_NAMES)}
_STRICT_KEYS = frozenset({"time", "timems", "timestampms", "timestampus", "frame", "frameindex", "framenumber",
                          "confidencelower", "confidenceupper", "datasource"})


def column_key(name: str) -> str:
    """Matching key of a column name: quotes and an enum prefix (`FaceExpression.`) dropped, separators
    (`_ - . space`) removed, lowercase. `Brow_Lowerer_L`, `BrowLowererL`, `BROW_LOWERER_L` -> `browlowererl`.
    The whole name is tried first against the time, status, confidence and data-source keys, so that
    `FaceState.Time` stays the tracker time (`facestatetime`) instead of becoming a Unity clock (`time`)."""
    name = name.strip().strip("\"'")
    full = _SEPARATORS.sub("", name).lower()
    if full in _SPECIAL_KEYS or "." not in name or _is_number(name):
        return full
    return _SEPARATORS.sub("", name.rsplit(".", 1)[1]).lower()


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


@dataclass
class _Rows:
    """The data lines of a delimited text file, split into cells."""

    header: list[str] | None
    header_line: int | None
    cells: list[list[str]]
    lines: list[int]
    delimiter: str
    metadata: dict[str, str]
    magic: bool


def _read_rows(path: Path) -> _Rows:
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SourceFormatError(f"not a UTF-8 text table ({exc.reason})", path) from None
    metadata: dict[str, str] = {}
    kept: list[tuple[int, str]] = []
    magic = False
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip().lstrip("\ufeff")
        if stripped.startswith("#"):
            body = stripped[1:].strip()
            if not kept and body.lower().startswith(FACELOG_MAGIC):
                magic = True
            key, sep, value = body.partition(":")
            if sep and key.strip():
                metadata[key.strip().lower()] = value.strip()
        elif stripped:
            kept.append((number, stripped))
    if not kept:
        raise SourceFormatError("no data lines", path)
    first = kept[0][1]
    delimiter = max((",", ";", "\t"), key=first.count)
    if first.count(delimiter) == 0:
        delimiter = ","
    records = list(csv.reader(io.StringIO("\n".join(line for _, line in kept)), delimiter=delimiter))
    if len(records) != len(kept):  # a quoted cell spanning lines: not something loggers write
        raise SourceFormatError("unbalanced quotes in the table", path)
    cells = [[c.strip() for c in r] for r in records]
    numbers = [n for n, _ in kept]
    head = [c for c in cells[0] if c]
    if head and all(_is_number(c.replace(",", ".")) or c.lower() in _STATUS_VALUES for c in head):
        return _Rows(None, None, cells, numbers, delimiter, metadata, magic)
    return _Rows(cells[0], numbers[0], cells[1:], numbers[1:], delimiter, metadata, magic)


def sniff_quest_log(path: str | Path) -> bool:
    """True if `read_facelog` should read `path` with this reader: a headerless numeric table, or a header
    with at least half of Meta's v1 names, unless it is the project's own strict face log (`# ofera facelog`
    first, only face-log columns). Reads only up to the first data line."""
    magic, first = False, None
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            for line in f:
                stripped = line.strip().lstrip("\ufeff")
                if stripped.startswith("#"):
                    magic = magic or stripped[1:].strip().lower().startswith(FACELOG_MAGIC)
                elif stripped:
                    first = stripped
                    break
    except OSError:
        return False
    if first is None:
        return False
    delimiter = max((",", ";", "\t"), key=first.count)
    cells = [c.strip() for c in next(csv.reader([first], delimiter=delimiter))]
    values = [c for c in cells if c]
    if values and all(_is_number(c.replace(",", ".")) or c.lower() in _STATUS_VALUES for c in values):
        return True
    keys = [column_key(c) for c in cells]
    if sum(k in _OVR_KEYS for k in keys) < len(OVR63_NAMES) // 2:
        return False
    strict = all(k in _OVR_KEYS or k in _STRICT_KEYS for k in keys)
    return not (magic and strict)


def read_quest_csv(path: str | Path, layout: str | Layout = "auto", fps: float | None = None) -> FaceLog:
    """Read a Quest Pro Unity log (module docstring) into ovr63/ovr70 samples, one per tracker sample."""
    return read_quest_csv_report(path, layout, fps)[0]


def read_quest_csv_report(
    path: str | Path, layout: str | Layout = "auto", fps: float | None = None
) -> tuple[FaceLog, LogReport]:
    """`read_quest_csv` and the report of what was found, kept and dropped.

    Returns a FaceLog (times (T,) s from 0, weights (T, 63|70) float32, confidence (T, 2) lower/upper in
    [0, 1] or None) and a `LogReport`. Raises SourceFormatError naming the file, line and problem.
    """
    path = Path(path)
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise SourceFormatError(f"--fps must be a positive number, got {fps}", path)
    rows = _read_rows(path)
    if not rows.cells:
        raise SourceFormatError("no data rows after the header", path, rows.header_line)
    if isinstance(layout, str) and layout.strip().lower() == "auto":
        layout = rows.metadata.get("layout", "auto")  # a `# layout:` comment, as in the project's face log
    try:
        wanted = None if isinstance(layout, str) and layout.strip().lower() == "auto" else get_layout(layout)
    except LayoutError as exc:
        raise SourceFormatError(str(exc), path) from None
    if wanted is not None and wanted.family != "ovr":
        raise SourceFormatError(f"a Quest Pro log holds ovr63 or ovr70 weights, not {wanted.name!r}", path)
    cols = _columns(rows, wanted, path)
    lay, names = cols.layout, cols.names
    report = LogReport(path=str(path), format=cols.format, layout=lay.name, rows=len(rows.cells),
                       columns_ignored=cols.ignored, confidence=cols.conf is not None,
                       status_column=None if cols.status is None else names[cols.status],
                       problems=list(cols.notes))
    parsed = _parse(rows, cols, path, report)
    keep = parsed.status.copy()
    report.invalid = int((~keep).sum())
    report.labels = [names[i] for i in cols.ignored_index if _texty(rows.cells, i)] if rows.header else []
    tr = parsed.tracker
    tracker_name = names[cols.tracker] if cols.tracker is not None else ""
    clock_name = names[cols.clock] if cols.clock is not None else ""
    if tr is not None:
        timed = keep & (tr > 0)
        distinct = np.unique(tr[timed]).size
        if distinct == 0 or (distinct == 1 and keep.sum() > 1):
            report.problems.append(f"{tracker_name} never changes"
                                   + (" (never above 0)" if distinct == 0 else "")
                                   + ": not used as the time source")
            tr = None
        else:
            untimed = int((keep & ~timed).sum())
            if untimed:  # tracker time 0: the logger wrote rows before tracking started (or while it was lost)
                report.invalid += untimed
                report.problems.append(f"{untimed} rows with {tracker_name} <= 0 (no tracker sample: before "
                                       "tracking started, or while lost) dropped as invalid")
            keep = timed
    if not keep.any():
        raise SourceFormatError(f"no valid face rows ({report.invalid} rows have status false"
                                + (f", {report.malformed} are malformed" if report.malformed else "") + ")", path)
    w, lines_kept = parsed.weights[keep], np.asarray(rows.lines)[parsed.index][keep]
    ck = parsed.clock[keep] if parsed.clock is not None else None
    positions = parsed.index[keep]
    if tr is not None:
        tr = tr[keep]
        _check_order(tr, lines_kept, tracker_name, path)
        clash = (tr[1:] == tr[:-1]) & np.any(w[1:] != w[:-1], axis=1)
        if clash.any():  # one tracker time, two faces: the time is too coarse to tell samples apart
            line = int(lines_kept[int(np.flatnonzero(clash)[0]) + 1])
            instead = (f"the Unity clock ({clock_name})" if ck is not None
                       else f"--fps {fps:g}" if fps is not None else None)
            what = (f"{tracker_name} is too coarse to tell samples apart: {int(clash.sum())} rows have the "
                    f"tracker time of the row before but a different face (first at line {line})")
            if instead is None:
                raise SourceFormatError(f"{what}, and the file has no Unity clock: give --fps (rows per second)",
                                        path)
            report.problems.append(f"{what}; samples found by weight changes and timed by {instead} instead")
            tr = None
    if tr is not None:
        first = np.ones(len(tr), bool)
        first[1:] = tr[1:] != tr[:-1]
        times = tr[first]
        report.time_source = f"tracker ({tracker_name}, device seconds)"
    else:
        first = np.ones(len(w), bool)
        first[1:] = np.any(w[1:] != w[:-1], axis=1)
        if ck is not None:
            _check_order(ck, lines_kept, clock_name, path)
            times = ck[first]
            report.time_source = f"unity clock ({clock_name}, seconds)"
        elif fps is not None:
            times = positions[first] / float(fps)
            report.time_source = f"--fps {fps:g} (rows paced at 1/{fps:g} s)"
        else:
            raise SourceFormatError("no time column: give --fps (rows per second; the file has no Face_Time, "
                                    "timeSinceStartup, realtimeSinceStartup, TimeFromStart, time or Timestamp "
                                    "column)", path)
    if fps is not None and (tr is not None or ck is not None):
        report.problems.append(f"--fps {fps:g} ignored: the file has its own time")
    if tr is not None or ck is not None:
        _note_gaps(times, lines_kept[first], report)
    report.samples = int(first.sum())
    report.duplicates = len(w) - report.samples
    times = times - times[0]
    report.duration_s = float(times[-1])
    report.rate_hz = median_rate(times)
    report.row_rate_hz = None if parsed.clock is None else median_rate(parsed.clock)
    metadata = dict(rows.metadata)
    metadata.update({"format": report.format, "time_source": report.time_source})
    log = FaceLog(
        times=times,
        weights=w[first].astype(np.float32),
        layout=lay,
        confidence=None if parsed.conf is None else np.clip(parsed.conf[keep][first], 0.0, 1.0).astype(np.float32),
        data_source=None if parsed.source is None else parsed.source[keep][first],
        source=metadata.pop("source", f"Quest Pro log {path}"),
        metadata=metadata,
    )
    return log, report


def _note_gaps(times: np.ndarray, lines: np.ndarray, report: LogReport) -> None:
    """Note steps over LONG_GAP_S in the samples' times (kept: the replay waits through them)."""
    steps = np.diff(times)
    long = np.flatnonzero(steps > LONG_GAP_S)
    if long.size:
        j = int(long[np.argmax(steps[long])])
        report.problems.append(f"{long.size} step(s) over {LONG_GAP_S:g} s in the time (tracking lost or the app "
                               f"paused?); the longest, {steps[j]:.3f} s, ends at line {int(lines[j + 1])}: kept, "
                               "the replay waits through it")


def _check_order(t: np.ndarray, lines: np.ndarray, name: str, path: Path) -> None:
    back = np.flatnonzero(np.diff(t) < 0)
    if len(back):
        i = int(back[0]) + 1
        raise SourceFormatError(f"{name} goes backwards ({t[i - 1]:.6f} s -> {t[i]:.6f} s)", path, int(lines[i]))


@dataclass
class _Columns:
    layout: Layout
    format: str
    width: int
    """Cells a row holds (the header's columns, less trailing separators and value-less enum extras)."""
    shapes: np.ndarray
    """(K,) column of each expression, in layout order."""
    names: list[str]
    """Name of each of the `width` columns (`value N` in a headerless file)."""
    tracker: int | None = None
    clock: int | None = None
    status: int | None = None
    conf: tuple[int, int] | None = None
    source: int | None = None
    ignored: list[str] = field(default_factory=list)
    ignored_index: list[int] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _columns(rows: _Rows, wanted: Layout | None, path: Path) -> _Columns:
    if rows.header is None:
        width = len(rows.cells[0])
        while width and all(len(r) >= width and not r[width - 1] for r in rows.cells[:50]):
            width -= 1  # trailing separators
        if wanted is None:
            guess = {63: " (63 values a row: ovr63?)", 70: " (70 values a row: ovr70?)"}.get(width, "")
            raise SourceFormatError(f"headerless file: give --layout ovr63 or ovr70 to say what its {width} "
                                    f"values a row are{guess}", path, rows.lines[0])
        if width != wanted.length:
            raise SourceFormatError(f"headerless rows have {width} values; layout {wanted.name} needs "
                                    f"{wanted.length} in enum order", path, rows.lines[0])
        return _Columns(wanted, "quest-headerless", width, np.arange(wanted.length),
                        [f"value {j + 1}" for j in range(width)])
    header = list(rows.header)
    keys = [column_key(h) for h in header]
    width = len(keys)
    while width and not keys[width - 1] and all(len(r) < width or not r[width - 1] for r in rows.cells[:50]):
        width -= 1  # a trailing separator on the header (and rows)
    header, keys = header[:width], keys[:width]
    dropped: list[str] = []
    extras = [i for i, k in enumerate(keys) if k in ENUM_EXTRA_KEYS]
    if extras:
        usual = Counter(len(r) for r in rows.cells).most_common(1)[0][0]
        if usual == width - len(extras):  # `Enum.GetNames` in the header, no value for `Max` in the rows
            dropped = [header[i] for i in extras]
            header = [h for i, h in enumerate(header) if i not in extras]
            keys = [k for i, k in enumerate(keys) if i not in extras]
            width -= len(extras)
    shapes: dict[int, int] = {}
    out = _Columns(get_layout("ovr63"), "", width, np.zeros(0, np.int64), header)
    if dropped:
        out.ignored += dropped
        out.notes.append(f"header column{'s' if len(dropped) > 1 else ''} {', '.join(dropped)} (from Enum.GetNames, "
                         f"not expressions) ha{'ve' if len(dropped) > 1 else 's'} no value in the rows: left out "
                         f"of the header")
    lower: int | None = None
    upper: int | None = None
    for i, k in enumerate(keys):
        if k in _OVR_KEYS and _OVR_KEYS[k] not in shapes:
            shapes[_OVR_KEYS[k]] = i
        elif k in _OVR_KEYS:
            raise SourceFormatError(f"duplicate column {header[i]!r} (also column {shapes[_OVR_KEYS[k]] + 1})",
                                    path, rows.header_line)
        elif k in TRACKER_TIME_KEYS and out.tracker is None:
            out.tracker = i
        elif k in CLOCK_KEYS and (out.clock is None or CLOCK_KEYS.index(k) < CLOCK_KEYS.index(keys[out.clock])):
            if out.clock is not None:
                out.ignored.append(header[out.clock])
                out.ignored_index.append(out.clock)
            out.clock = i
        elif k in STATUS_KEYS and out.status is None:
            out.status = i
        elif k in CONFIDENCE_KEYS[0] and lower is None:
            lower = i
        elif k in CONFIDENCE_KEYS[1] and upper is None:
            upper = i
        elif k in DATA_SOURCE_KEYS and out.source is None:
            out.source = i
        else:
            out.ignored.append(header[i] or f"(column {i + 1}, unnamed)")
            out.ignored_index.append(i)
    if lower is not None and upper is not None:
        out.conf = (lower, upper)
    else:  # one confidence alone is not the lower/upper pair: ignored
        for lone in (lower, upper):
            if lone is not None:
                out.ignored.append(header[lone])
                out.ignored_index.append(lone)
    found = set(shapes)
    tongue = found - set(range(len(OVR63_NAMES)))
    lay = get_layout("ovr70" if tongue or (wanted is not None and wanted.name == "ovr70") else "ovr63")
    missing = [OVR70_NAMES[j] for j in range(lay.length) if j not in found]
    if missing:
        shown = ", ".join(missing[:12]) + (f" and {len(missing) - 12} more" if len(missing) > 12 else "")
        hint = f"; columns not understood: {', '.join(out.ignored[:12])}" if out.ignored else ""
        raise SourceFormatError(f"not a complete Meta {lay.name} log: missing {shown}{hint}", path, rows.header_line)
    if wanted is not None and wanted != lay:
        raise SourceFormatError(f"holds layout {lay.name!r}, not {wanted.name!r}", path, rows.header_line)
    out.layout = lay
    out.format = "quest-v2" if lay.name == "ovr70" else "quest-v1"
    out.shapes = np.array([shapes[j] for j in range(lay.length)], dtype=np.int64)
    return out


def _texty(cells: list[list[str]], column: int) -> bool:
    """True if the column holds text somewhere in its first 200 rows (a label, not a number)."""
    return any(column < len(r) and r[column] and not _is_number(r[column]) for r in cells[:200])


class _Parsed(NamedTuple):
    """The rows `_parse` could read (malformed ones dropped), R of them."""

    weights: np.ndarray
    """(R, K) float64, in layout order."""
    tracker: np.ndarray | None
    """(R,) tracker time, device seconds."""
    clock: np.ndarray | None
    """(R,) Unity clock, seconds."""
    conf: np.ndarray | None
    """(R, 2) lower/upper confidence, as written."""
    source: np.ndarray | None
    """(R,) uint8 data source codes (DATA_SOURCES)."""
    status: np.ndarray
    """(R,) bool: a valid face (status true, or no status column)."""
    index: np.ndarray
    """(R,) int64 positions of the rows in `rows.cells`."""


def _parse(rows: _Rows, cols: _Columns, path: Path, report: LogReport) -> _Parsed:
    numeric = [*cols.shapes.tolist()]
    extra = {}
    for name, col in (("tracker", cols.tracker), ("clock", cols.clock)):
        if col is not None:
            extra[name] = len(numeric)
            numeric.append(col)
    if cols.conf is not None:
        extra["conf"] = len(numeric)
        numeric += list(cols.conf)
    comma = rows.delimiter != ","
    names = cols.names
    values: list[list[float]] = []
    status: list[bool] = []
    sources: list[int] = []
    index: list[int] = []
    first_problem: tuple[int, str] | None = None
    for r, cells in enumerate(rows.cells):
        problem = None
        if len(cells) < cols.width or any(c for c in cells[cols.width:]):
            problem = f"{len(cells)} fields, the header has {cols.width}"
        else:
            try:
                v = [float(cells[c].replace(",", ".") if comma else cells[c]) for c in numeric]
            except ValueError:
                bad = next(c for c in numeric if not _is_number(cells[c].replace(",", ".") if comma else cells[c]))
                problem = f"column {names[bad]!r}: {cells[bad]!r} is not a number"
            else:
                if not np.all(np.isfinite(v)):
                    bad = numeric[int(np.flatnonzero(~np.isfinite(v))[0])]
                    problem = f"column {names[bad]!r}: {cells[bad]!r} is not a finite number"
            ok = True
            if problem is None and cols.status is not None:
                s = _STATUS_VALUES.get(cells[cols.status].lower())
                if s is None:
                    problem = f"column {names[cols.status]!r}: {cells[cols.status]!r} is not true or false"
                ok = bool(s)
            code = 0
            if problem is None and cols.source is not None:
                found = _DATA_SOURCE_CODES.get(cells[cols.source].lower())
                if found is None:
                    problem = f"column {names[cols.source]!r}: {cells[cols.source]!r} is not one of {DATA_SOURCES}"
                code = found or 0
        if problem is not None:
            report.malformed += 1
            if len(report.problems) < report.MAX_PROBLEMS:
                report.problems.append(f"line {rows.lines[r]}: {problem} (row dropped)")
            first_problem = first_problem or (rows.lines[r], problem)
            continue
        values.append(v)
        status.append(ok)
        sources.append(code)
        index.append(r)
    if report.malformed and (not values or report.malformed > MAX_MALFORMED_SHARE * len(rows.cells)):
        assert first_problem is not None
        line, problem = first_problem
        raise SourceFormatError(f"{problem} ({report.malformed} of {len(rows.cells)} rows malformed)", path, line)
    a = np.array(values, dtype=np.float64).reshape(len(values), len(numeric))
    k = len(cols.shapes)
    return _Parsed(
        weights=a[:, :k],
        tracker=a[:, extra["tracker"]] if "tracker" in extra else None,
        clock=a[:, extra["clock"]] if "clock" in extra else None,
        conf=a[:, extra["conf"]: extra["conf"] + 2] if "conf" in extra else None,
        source=np.array(sources, np.uint8) if cols.source is not None else None,
        status=np.array(status, bool),
        index=np.array(index, np.int64),
    )
