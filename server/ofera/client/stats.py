"""Latency statistics of a client session (from the `t` each frame echoes)."""

from __future__ import annotations

import numpy as np


class LatencyStats:
    """End-to-end latencies in microseconds: bs sent (its `t`) -> frame decoded."""

    def __init__(self) -> None:
        self.samples: list[int] = []

    def add(self, us: int) -> None:
        self.samples.append(int(us))

    def clear(self) -> None:
        self.samples.clear()

    def __len__(self) -> int:
        return len(self.samples)

    def percentile_ms(self, q: float) -> float | None:
        if not self.samples:
            return None
        return float(np.percentile(np.asarray(self.samples, np.float64), q)) / 1000.0

    @property
    def p50(self) -> float | None:
        """Median latency, milliseconds."""
        return self.percentile_ms(50)

    @property
    def p99(self) -> float | None:
        """99th percentile latency, milliseconds."""
        return self.percentile_ms(99)

    def summary(self) -> dict[str, float | int | None]:
        a = np.asarray(self.samples, np.float64) / 1000.0
        if a.size == 0:
            return {"n": 0, "p50_ms": None, "p90_ms": None, "p99_ms": None, "mean_ms": None, "max_ms": None}
        p50, p90, p99 = np.percentile(a, [50, 90, 99])
        return {"n": int(a.size), "p50_ms": round(float(p50), 3), "p90_ms": round(float(p90), 3),
                "p99_ms": round(float(p99), 3), "mean_ms": round(float(a.mean()), 3),
                "max_ms": round(float(a.max()), 3)}
