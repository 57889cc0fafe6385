"""`LogReport`: what a face-log reader found, kept and dropped (`read_facelog_report`, `ofera replay inspect`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def median_rate(t: np.ndarray) -> float | None:
    """1 / the median positive step of `t` (seconds), robust to gaps; None with fewer than two times."""
    steps = np.diff(np.asarray(t, np.float64))
    steps = steps[steps > 0]
    return float(1.0 / np.median(steps)) if steps.size else None


@dataclass
class LogReport:
    """What the reader found and did. Counts are data rows (comment and blank lines excluded). Readers that
    keep every row (face-log, Live Link, .gesichter) report no drops."""

    path: str
    format: str
    """`quest-v1` (63 names), `quest-v2` (70 names), `quest-headerless`, `facelog`, `csv`, `livelink-csv` or
    `gesichter`."""
    layout: str
    rows: int = 0
    samples: int = 0
    duplicates: int = 0
    invalid: int = 0
    """Rows dropped as not faces (status false, or no tracker time: `Face_Time` <= 0)."""
    malformed: int = 0
    """Rows dropped as unreadable (wrong field count, bad number or status)."""
    time_source: str = ""
    duration_s: float = 0.0
    rate_hz: float | None = None
    """Samples per second (1 / the median step, robust to gaps)."""
    row_rate_hz: float | None = None
    """Rows per second of the logger (when a time column gives it)."""
    columns_ignored: list[str] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)
    """Ignored columns holding text (e.g. `Emotion`)."""
    confidence: bool = False
    status_column: str | None = None
    problems: list[str] = field(default_factory=list)
    """The first few malformed rows, each `line N: why`; and notes on what the reader decided (an ignored
    --fps, a tracker time not used, a long gap in the time, a header column without values)."""

    MAX_PROBLEMS = 5

    def to_dict(self) -> dict[str, object]:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["duration_s"] = round(self.duration_s, 6)
        for k in ("rate_hz", "row_rate_hz"):
            d[k] = None if d[k] is None else round(float(d[k]), 3)
        return d

    def text(self) -> str:
        """Human-readable lines, as `ofera replay inspect` prints them."""
        rate = f"{self.rate_hz:.2f} Hz" if self.rate_hz else "-"
        rows = f"{self.row_rate_hz:.2f} Hz" if self.row_rate_hz else "-"
        lines = [
            f"file          {self.path}",
            f"format        {self.format}",
            f"layout        {self.layout}",
            f"rows          {self.rows}",
            f"samples kept  {self.samples}",
            f"duplicates    {self.duplicates} dropped (repeated samples)",
            f"invalid       {self.invalid} dropped (not a face: status false or no tracker time)"
            + (f", {self.malformed} malformed" if self.malformed else ""),
            f"time source   {self.time_source}",
            f"rate          {rate} samples" + (f", rows at {rows}" if self.row_rate_hz else ""),
            f"duration      {self.duration_s:.3f} s",
            f"confidence    {'lower/upper' if self.confidence else 'none'}",
            "ignored       " + (", ".join(self.columns_ignored) or "none")
            + (f" (labels: {', '.join(self.labels)})" if self.labels else ""),
        ]
        lines += [f"note          {p}" for p in self.problems]
        return "\n".join(lines)
