"""`--record OUT`: the frames a replay received, saved as one `.npz`.

Arrays (F = frames received, in arrival order; S = timing stages):

- `seq` (F,) int64: the `bs` each frame answers; `t_us` (F,) int64: that `bs`'s send time (replay
  clock, microseconds, echoed by the server); `recv_us` (F,) int64: arrival time, same clock;
  `latency_ms` (F,) float32 = (recv_us - t_us) / 1000.
- `timing_stages` (S,) str and `timing_us` (F, S) int64: the server's stage durations (-1 = absent).
- A face-log-like view of what was answered: `layout` (str), `log_time` (F,) float64 seconds in the
  log of the answered frame, `weights` (F, K) float32 in `layout` order.
- `count` (F,) int64: Gaussians carried by each frame.
- With positions recorded (`--record-positions`): `position` (F, N, 3) float32, every Gaussian's position
  as the client reconstructs it after each frame (a dense frame's own values; after a delta frame of
  `--delta`, the client's state: key frame plus the deltas applied since). At 100k Gaussians that is
  1.2 MB a frame: use a small avatar or a short log.
- `key` (F,) int8: 1 key frame, 0 delta frame, -1 not a delta session.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from ofera_protocol import Frame, FrameHeader


class FrameRecorder:
    """Collects received frames; `save(path)` writes the npz described in the module docstring."""

    def __init__(self, layout: str, weights: np.ndarray, times: np.ndarray, positions: bool = False) -> None:
        self.layout = layout
        self.log_weights = np.asarray(weights, dtype=np.float32)
        self.log_times = np.asarray(times, dtype=np.float64)
        self.positions = positions
        self.seq: list[int] = []
        self.t_us: list[int] = []
        self.recv_us: list[int] = []
        self.count: list[int] = []
        self.timing: list[dict[str, int]] = []
        self.position: list[np.ndarray] = []
        self.key: list[int] = []

    def __len__(self) -> int:
        return len(self.seq)

    def add(self, frame: Frame | FrameHeader, recv_us: int, state: object | None = None) -> None:
        """One received frame (a FrameHeader is enough without `positions`); `state` (a GaussianState: the client's
        reconstruction) is what `position` records for frames that carry only some Gaussians (sparse and delta
        frames)."""
        if self.positions and isinstance(frame, FrameHeader):
            raise ValueError("recording positions needs decoded frames, not headers (LinkOptions.header_only)")
        self.seq.append(int(frame.seq))
        self.key.append(-1 if frame.key is None else int(frame.key))
        self.t_us.append(int(frame.t))
        self.recv_us.append(int(recv_us))
        self.count.append(frame.n)
        self.timing.append(dict(frame.timing))
        if self.positions:
            if frame.index is None:
                self.position.append(np.array(frame.position, dtype=np.float32, copy=True))
            elif state is not None:
                self.position.append(np.array(state.position, dtype=np.float32, copy=True))  # type: ignore[attr-defined]
            else:
                raise ValueError("recording positions of sparse or delta frames needs the client's state")

    def arrays(self) -> dict[str, np.ndarray]:
        stages = sorted({k for t in self.timing for k in t})
        timing = np.full((len(self), len(stages)), -1, dtype=np.int64)
        for row, t in enumerate(self.timing):
            for col, name in enumerate(stages):
                timing[row, col] = t.get(name, -1)
        seq = np.asarray(self.seq, dtype=np.int64)
        n = len(self.log_times)
        index = seq % n if n else seq
        t_us = np.asarray(self.t_us, dtype=np.int64)
        recv_us = np.asarray(self.recv_us, dtype=np.int64)
        out = {
            "seq": seq,
            "t_us": t_us,
            "recv_us": recv_us,
            "latency_ms": ((recv_us - t_us) / 1e3).astype(np.float32),
            "timing_stages": np.asarray(stages, dtype=str),
            "timing_us": timing,
            "layout": np.asarray(self.layout),
            "log_time": self.log_times[index] if n else np.zeros(0),
            "weights": self.log_weights[index] if n else np.zeros((0, 0), np.float32),
            "count": np.asarray(self.count, dtype=np.int64),
            "key": np.asarray(self.key, dtype=np.int8),
        }
        if self.positions:
            out["position"] = (np.stack(self.position) if self.position else np.zeros((0, 0, 3), np.float32))
        return out

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **self.arrays())
        return path
