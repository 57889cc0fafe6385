"""The send path (ofera.streaming.server): binary messages written without the websockets library's copies (the
same bytes on the wire), frames whose timing carries every computed stage (`queue` included), /metrics histograms
of every stage of a frame (encode, send and drain included), and the event-loop setting."""

from __future__ import annotations

import importlib.util

import httpx
import numpy as np
import pytest
from ofera.client import connect
from ofera.streaming import Settings, offline_pipeline
from ofera.streaming.server import (
    SMALL_MESSAGE,
    ServerThread,
    StreamingWebSocketProtocol,
    uvicorn_config,
    ws_binary_header,
)
from pydantic import ValidationError
from test_server_support import run, settings
from websockets.frames import Frame, Opcode


@pytest.mark.parametrize("n", [0, 1, 125, 126, 127, 65535, 65536, 2_000_163])
def test_binary_header_is_the_websockets_framing(n: int) -> None:
    payload = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    assert ws_binary_header(n) + payload == Frame(Opcode.BINARY, payload).serialize(mask=False, extensions=[])


def stage_count(text: str, stage: str) -> float:
    key = f'ofera_stage_seconds_count{{stage="{stage}"}} '
    return next((float(line.split()[-1]) for line in text.splitlines() if line.startswith(key)), 0.0)


async def stream(url: str, w: np.ndarray, frames: int, **hello) -> list:
    out = []
    async with await connect(url, **hello) as c:
        for seq in range(frames):
            await c.send_bs(w, seq=seq)
            out.append(await c.recv_frame(timeout=30))
    return out


@pytest.mark.parametrize("event_loop", ["asyncio", "uvloop"])
def test_frames_are_exact_timed_and_counted_per_stage(event_loop: str, monkeypatch) -> None:
    if event_loop == "uvloop" and importlib.util.find_spec("uvloop") is None:
        pytest.skip("uvloop is not installed (the optional `uvloop` extra)")
    sizes: list[int] = []
    direct = StreamingWebSocketProtocol.write_binary

    def counted(self, data):
        sizes.append(memoryview(data).nbytes)
        return direct(self, data)

    monkeypatch.setattr(StreamingWebSocketProtocol, "write_binary", counted)
    w = np.random.default_rng(3).uniform(0, 1, 52).astype(np.float32)
    with ServerThread(settings(event_loop=event_loop)) as server:
        big = run(stream(server.url, w, 3, encoding="f32"))  # 2000 Gaussians x 40 B: the no-copy path
        small = run(stream(server.url, w, 2, encoding="q13", sparse=True, max_gaussians=200))  # joined to its header
        text = httpx.get(f"{server.http_url}/metrics", timeout=10).text
        loop = httpx.get(f"{server.http_url}/healthz", timeout=10).json()["event_loop"]
    assert loop.startswith("uvloop.") == (event_loop == "uvloop"), loop  # the server ran the loop asked for
    state, _ = offline_pipeline("default", "arkit52", w, settings=settings())
    assert sum(n > SMALL_MESSAGE for n in sizes) >= 3 and sum(n <= SMALL_MESSAGE for n in sizes) >= 2  # both ways
    for frame in big:
        assert frame.position.tobytes() == state.position.tobytes()
        assert frame.rotation.tobytes() == state.rotation.tobytes()
        assert frame.scale.tobytes() == state.scale.tobytes()
    for frame in big + small:
        assert {"decode", "queue", "layout", "bda", "epm", "head", "deform", "total"} <= set(frame.timing)
    for stage in ("decode", "queue", "layout", "bda", "epm", "head", "deform", "encode", "total", "send", "drain"):
        assert stage_count(text, stage) >= 5, stage


def test_event_loop_is_a_setting() -> None:
    assert uvicorn_config(Settings()).loop == "auto"  # uvloop when installed
    assert uvicorn_config(Settings(event_loop="asyncio")).loop == "asyncio"
    assert uvicorn_config(Settings(event_loop="uvloop")).loop == "uvloop"
    with pytest.raises(ValidationError, match="event_loop"):
        Settings(event_loop="trio")
