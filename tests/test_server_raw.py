"""A client written only from the design card's wire skeleton (the user's DESIGN.md, not in this repository;
PROTOCOL.md extends it): raw `websockets` + `msgpack`, no OFERA code.

Acceptance: hello (protocol 1, arkit52, avatar default, f32) -> welcome with avatar.count -> the avatar
data -> for 200 bs sent at 72 Hz, frames in increasing seq order, each with count x 3 finite float32
positions; bad bs (not msgpack, wrong length, NaN) get non-fatal errors and the session goes on.
"""

from __future__ import annotations

import asyncio
import time

import msgpack
import numpy as np
from test_server_support import main_server, run
from websockets.asyncio.client import connect

N_WEIGHTS = 52  # arkit52


def pack(obj: dict) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def unpack(data: bytes) -> dict:
    return msgpack.unpackb(data, raw=False)


def bs(seq: int, w: np.ndarray) -> bytes:
    return pack({"type": "bs", "seq": seq, "t": time.monotonic_ns() // 1000,
                 "w": np.asarray(w, "<f4").tobytes()})


async def open_session(url: str) -> tuple:
    """hello -> welcome -> every avatar chunk. Returns (ws, welcome, avatar arrays)."""
    ws = await connect(url, compression=None, max_size=64 * 2**20)
    await ws.send(pack({"type": "hello", "protocol": 1, "layout": "arkit52", "avatar": "default",
                        "encoding": "f32"}))
    welcome = unpack(await ws.recv())
    assert welcome["type"] == "welcome", welcome
    count = welcome["avatar"]["count"]
    k = (welcome["avatar"]["sh_degree"] + 1) ** 2
    parts: dict[str, list[np.ndarray]] = {"opacity": [], "sh": [], "position": [], "rotation": [], "scale": []}
    received, chunks = 0, None
    while chunks is None or len(parts["opacity"]) < chunks:
        m = unpack(await ws.recv())
        assert m["type"] == "avatar", m["type"]
        assert m["count"] == count and m["offset"] == received
        chunks = m["chunks"]
        n = m["n"]
        for name, width in (("opacity", 1), ("sh", k * 3), ("position", 3), ("rotation", 4), ("scale", 3)):
            a = np.frombuffer(m[name], "<f4")
            assert a.size == n * width, (name, a.size, n * width)
            parts[name].append(a.reshape(n, width))
        received += n
    assert received == count
    avatar = {name: np.concatenate(v) for name, v in parts.items()}
    return ws, welcome, avatar


def test_raw_client_200_bs_at_72hz() -> None:
    server = main_server()

    async def main() -> None:
        ws, welcome, avatar = await open_session(server.url)
        count = welcome["avatar"]["count"]
        assert count > 0 and welcome["protocol"] == 1 and welcome["encoding"] == "f32"
        assert welcome["layout"] == "arkit52" and isinstance(welcome["session"], str)
        assert avatar["position"].shape == (count, 3) and np.isfinite(avatar["position"]).all()
        assert ((avatar["opacity"] >= 0) & (avatar["opacity"] <= 1)).all()
        np.testing.assert_allclose(np.linalg.norm(avatar["rotation"], axis=1), 1.0, atol=1e-5)

        frames: list[dict] = []
        rng = np.random.default_rng(0)

        async def sender() -> None:
            start = time.monotonic()
            for seq in range(200):
                delay = start + seq / 72.0 - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                await ws.send(bs(seq, rng.uniform(0, 1, N_WEIGHTS)))

        async def receiver() -> None:
            while True:
                m = unpack(await ws.recv())
                assert m["type"] == "frame", m
                frames.append(m)
                if m["seq"] == 199:
                    return

        await asyncio.wait_for(asyncio.gather(sender(), receiver()), 60)
        await ws.send(pack({"type": "bye"}))
        await ws.close()

        seqs = [f["seq"] for f in frames]
        assert seqs == sorted(set(seqs)), "frames must come in strictly increasing seq order"
        assert seqs[-1] == 199
        assert len(frames) >= 100, f"only {len(frames)} of 200 bs answered at 72 Hz"
        for f in frames:
            assert f["n"] == count
            pos = np.frombuffer(f["position"], "<f4")
            assert pos.size == count * 3 and np.isfinite(pos).all()
            assert len(f["rotation"]) == count * 16 and len(f["scale"]) == count * 12
            assert isinstance(f["t"], int) and all(isinstance(v, int) and v >= 0 for v in f["timing"].values())
        assert {"epm", "head", "deform", "total"} <= set(frames[-1]["timing"])

    run(main())


def test_raw_bad_bs_is_non_fatal() -> None:
    server = main_server()

    async def main() -> None:
        ws, welcome, _ = await open_session(server.url)
        count = welcome["avatar"]["count"]
        bad = [
            (b"\xc1 definitely not msgpack", "malformed"),
            (pack({"type": "bs", "seq": 1, "t": 0, "w": np.zeros(51, "<f4").tobytes()}), "bad_length"),
            (pack({"type": "bs", "seq": 2, "t": 0, "w": np.full(52, np.nan, "<f4").tobytes()}), "non_finite"),
        ]
        for data, code in bad:
            await ws.send(data)
            m = unpack(await asyncio.wait_for(ws.recv(), 10))
            assert m["type"] == "error" and m["code"] == code and m["fatal"] is False, m
            await ws.send(bs(10, np.full(52, 0.3)))  # the next good bs gets its frame
            m = unpack(await asyncio.wait_for(ws.recv(), 10))
            assert m["type"] == "frame" and m["seq"] == 10, m
            assert np.isfinite(np.frombuffer(m["position"], "<f4")).all() and m["n"] == count
        await ws.close()

    run(main())
