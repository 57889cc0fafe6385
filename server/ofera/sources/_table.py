"""Comma-separated tables with `#` comment lines, keeping file line numbers for error messages."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from operator import itemgetter
from pathlib import Path

import numpy as np

from ofera.sources.facelog import SourceFormatError


class Table:
    """A CSV file read as strings: header, rows (lists of str), and the file line of each row.

    Blank lines are skipped; lines starting with `#` are comments, and `# key: value` comments are
    collected into `metadata` (keys lowercased).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self.metadata: dict[str, str] = {}
        kept: list[tuple[int, str]] = []
        try:
            with open(path, encoding="utf-8-sig", newline="") as f:
                for number, line in enumerate(f, 1):
                    text = line.strip()
                    if text.startswith("#"):
                        key, sep, value = text[1:].partition(":")
                        if sep and key.strip():
                            self.metadata[key.strip().lower()] = value.strip()
                    elif text:
                        kept.append((number, line))
        except UnicodeDecodeError as exc:
            raise SourceFormatError(f"not a UTF-8 text table ({exc.reason})", path) from None
        if not kept:
            raise SourceFormatError("no header line", path)
        records = list(csv.reader(line for _, line in kept))
        self.header = [name.strip() for name in records[0]]
        self.header_line = kept[0][0]
        self.lines = [number for number, _ in kept[1:]]
        for record, number in zip(records[1:], self.lines, strict=True):
            if len(record) != len(self.header):
                raise SourceFormatError(
                    f"expected {len(self.header)} fields as in the header, got {len(record)}", path, number
                )
        self.rows = records[1:]

    def find(self, *names: str) -> int | None:
        """Index of the first header column whose lowercased name is in `names`, else None."""
        lowered = [h.lower() for h in self.header]
        return next((lowered.index(n) for n in names if n in lowered), None)

    def texts(self, column: int) -> list[str]:
        """The cells of one column, as written."""
        return [row[column] for row in self.rows]

    def floats(self, columns: Sequence[int]) -> np.ndarray:
        """(T, len(columns)) float64 of those columns; errors name the line and column."""
        pick = itemgetter(*columns)
        cells = [pick(row) for row in self.rows]
        try:
            values = np.array(cells, dtype=np.float64).reshape(len(self.rows), len(columns))
        except ValueError:
            values = None
        if values is not None and np.isfinite(values).all():
            return values
        row, col = next(
            (r, c) for r, c in np.ndindex(len(self.rows), len(columns)) if not _finite(self.rows[r][columns[c]])
        )
        raise SourceFormatError(
            f"column {self.header[columns[col]]!r}: {self.rows[row][columns[col]]!r} is not a finite number",
            self.path,
            self.lines[row],
        )

    def relative_times(self, times: np.ndarray) -> np.ndarray:
        """(T,) seconds made relative to the first row; an error names the first line going back."""
        back = np.flatnonzero(np.diff(times) < 0)
        if len(back):
            i = int(back[0]) + 1
            raise SourceFormatError(
                f"time goes backwards ({times[i - 1]:.6f} s -> {times[i]:.6f} s)", self.path, self.lines[i]
            )
        return times - times[0] if len(times) else times


def _finite(text: str) -> bool:
    try:
        return bool(np.isfinite(float(text)))
    except ValueError:
        return False
