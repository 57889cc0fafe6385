"""Measure end-to-end latency against a running server: `python -m ofera.client.probe [URL]`.

Sends random blendshapes at a fixed rate (absolute schedule, 72 Hz by default) for some seconds while
reading frames, then prints one JSON object: round-trip latency percentiles (bs sent -> frame decoded,
from the echoed `t`), frames received versus bs sent, and the median of each server stage.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time

import numpy as np
from ofera_protocol import LAYOUTS

from .client import Client, connect, now_us
from .stats import LatencyStats


async def probe(url: str, seconds: float = 10.0, rate: float = 72.0, layout: str = "arkit52",
                avatar: str = "default", encoding: str = "f32", token: str | None = None,
                warmup: float = 1.0, seed: int = 0, sparse: bool = False) -> dict:
    client: Client = await connect(url, layout=layout, avatar=avatar, encoding=encoding, token=token, sparse=sparse)
    rng = np.random.default_rng(seed)
    n = LAYOUTS[layout]
    total = int(round((seconds + warmup) * rate))
    warm = int(round(warmup * rate))
    timings: dict[str, list[int]] = {}
    frames = 0
    frame_bytes = 0
    latency = LatencyStats()  # measured frames only (after the warm-up)

    async def sender() -> None:
        start = time.monotonic()
        for seq in range(total):
            delay = start + seq / rate - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            await client.send_bs(rng.uniform(0, 1, n).astype(np.float32), seq=seq)
        await asyncio.sleep(2.0)  # time for the last frame

    async def receiver() -> None:
        nonlocal frames, frame_bytes
        while True:
            f = await client.recv_frame()
            frame_bytes = client.conn.format.payload_bytes(None if f.index is None else f.n)
            if f.seq >= warm:
                latency.add(now_us() - f.t)
                frames += 1
                for k, v in f.timing.items():
                    timings.setdefault(k, []).append(v)
            if f.seq == total - 1:
                return

    recv_task = asyncio.create_task(receiver())
    await sender()
    if not recv_task.done():
        recv_task.cancel()
    await asyncio.gather(recv_task, return_exceptions=True)
    await client.close()
    lat = latency.summary()
    return {
        "url": url, "avatar": client.welcome.avatar.id, "count": client.count, "encoding": encoding,
        "sparse": sparse, "frame_bytes": frame_bytes,
        "rate_hz": rate, "seconds": seconds, "bs_sent": total - warm, "frames_received": frames,
        "latency_ms": lat,
        "server_stage_median_us": {k: int(np.median(v)) for k, v in timings.items()},
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("url", nargs="?", default="ws://127.0.0.1:8000/v1/stream")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rate", type=float, default=72.0)
    p.add_argument("--layout", default="arkit52")
    p.add_argument("--avatar", default="default")
    p.add_argument("--encoding", default="f32")
    p.add_argument("--token", default=None)
    p.add_argument("--sparse", action="store_true", help="ask for sparse frames (only the movable Gaussians)")
    a = p.parse_args(argv)
    result = asyncio.run(probe(a.url, a.seconds, a.rate, a.layout, a.avatar, a.encoding, a.token, sparse=a.sparse))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
