"""Temporal delta streams (PROTOCOL.md 7.1) through a real server: the client reconstructs every frame within
the tolerance of the exact (f32) frame, key frames come on join, every N frames and on resync, and frames that
are computed but never handed to the socket (a forced drop pattern) never corrupt the client's state."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from ofera.client import connect
from ofera.streaming import offline_pipeline
from ofera.streaming import roles as R
from ofera.streaming.server import ServerThread
from ofera_protocol import LAYOUTS, to_coords
from ofera_protocol.delta import DeltaEncoder
from test_server_eager_encode import mark_compute
from test_server_support import SMALL, main_server, run, settings


def sweep(frames: int, seed: int = 0) -> np.ndarray:
    """A smooth arkit52 expression sweep (frames, 52): every weight oscillates, some hold still."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None] / 30.0
    f, ph = rng.uniform(0.3, 2.0, 52), rng.uniform(0, 6.3, 52)
    w = 0.5 + 0.5 * np.sin(2 * np.pi * f * t + ph)
    w[:, rng.random(52) < 0.3] = 0.0
    return w.astype(np.float32)


def errors(state, exact, coords: str) -> tuple[float, float]:
    """Max position error (m) and rotation error (degrees) of the client's state against the exact frame."""
    p, r = to_coords(exact.position, exact.rotation, coords)
    perr = float(np.linalg.norm(state.position.astype(np.float64) - p, axis=1).max())
    a = state.rotation.astype(np.float64)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = r.astype(np.float64) / np.linalg.norm(r, axis=1, keepdims=True)
    sign = np.where(np.sum(a * b, axis=1) < 0, -1.0, 1.0)[:, None]
    rerr = float(np.degrees(4 * np.arcsin(np.minimum(np.linalg.norm(a - sign * b, axis=1) / 2, 1))).max())
    return perr, rerr


async def stream(url: str, w: np.ndarray, coords: str = "flame", resync_at: int | None = None, **hello):
    """Send the sweep one bs at a time (waiting for each answer) and collect (frame, copy of client state)."""
    out = []
    async with await connect(url, encoding=hello.pop("encoding", "q13"), coords=coords, delta=True, track=True,
                             **hello) as c:
        assert c.welcome.delta and not c.welcome.sparse
        for seq, x in enumerate(w):
            if seq == resync_at:
                await c.resync()
            await c.send_bs(x, seq=seq)
            f = await c.recv_frame(timeout=30)
            g = c.gaussians
            out.append((f, g.position.copy(), g.rotation.copy()))
    return out


@pytest.mark.parametrize("encoding,coords", [("q13", "flame"), ("q13", "unity"), ("f16", "flame")])
def test_delta_client_reconstructs_every_frame(encoding: str, coords: str) -> None:
    server = main_server()
    w = sweep(30)
    frames = run(stream(server.url, w, coords, resync_at=17, encoding=encoding))
    s = settings()
    keys = [f.seq for f, _, _ in frames if f.key]
    assert keys == [0, 17]  # join and resync (key_interval 720)
    assert all(f.key is False and f.index is not None for f, _, _ in frames if f.seq not in keys)
    for f, pos, rot in frames:
        exact, _ = offline_pipeline(SMALL, "arkit52", w[f.seq], settings=s)
        perr, rerr = errors(type("S", (), {"position": pos, "rotation": rot})(), exact, coords)
        pos_bound = s.delta_position_mm * 1e-3 if encoding == "q13" else 0.25 * 2.0**-11 * math.sqrt(3)
        assert perr <= max(pos_bound, s.delta_position_mm * 1e-3) + 1e-6, (f.seq, perr)
        assert rerr <= max(s.delta_rotation_deg, 0.33) + 1e-3, (f.seq, rerr)


def test_delta_frames_encoded_in_the_compute_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """A delta session encodes in the thread that computes its frame, inside ``Source._compute`` (Source.eager; the
    pool's thread, or the loop's for a lone session): its source computes only while the viewer's slot is empty, so no
    frame it encodes is replaced before the socket. Its frames' timing carries "encode"."""
    inside: list[bool] = []
    computing = mark_compute(monkeypatch)
    encode = DeltaEncoder.encode

    def spy(self, *args, **kwargs):
        inside.append(getattr(computing, "on", False))
        return encode(self, *args, **kwargs)

    monkeypatch.setattr(DeltaEncoder, "encode", spy)
    frames = run(stream(main_server().url, sweep(6)))
    assert [f.seq for f, _, _ in frames] == list(range(6))
    assert inside and all(inside), inside
    assert all(f.timing["encode"] >= 0 and f.timing["queue"] >= 0 for f, _, _ in frames)  # whole-frame timing


def test_replaced_delta_frames_never_corrupt_the_client(monkeypatch: pytest.MonkeyPatch) -> None:
    """Frames encoded and then replaced before reaching the socket (forced here: the source computes whatever the
    viewer's slot holds, and the viewer's socket is slow): each replacement makes the next frame sent a key
    frame, so the client stays within the tolerance of every frame it gets."""
    monkeypatch.setattr(R.LatestSlot, "full", property(lambda self: False))  # demand: compute every bs
    init = R.Viewer.__init__

    def slow_socket(self, send, *args, **kwargs):
        async def slow_send(data) -> None:  # 50 ms a frame: slower than any computation here, under load too
            await asyncio.sleep(0.05)
            await send(data)

        init(self, slow_send, *args, **kwargs)

    monkeypatch.setattr(R.Viewer, "__init__", slow_socket)
    s = settings(key_interval=0)  # key frames only on join and after a replacement
    server = ServerThread(s).start()
    try:
        w = sweep(40, seed=3)

        async def main():
            got = []
            async with await connect(server.url, encoding="q13", delta=True, track=True) as c:
                for seq, x in enumerate(w):  # a bs every 5 ms: frames are replaced in the slow viewer's slot
                    await c.send_bs(x, seq=seq)
                    await asyncio.sleep(0.005)
                while not got or got[-1][0].seq < len(w) - 1:
                    f = await c.recv_frame(timeout=30)
                    got.append((f, c.gaussians.position.copy(), c.gaussians.rotation.copy()))
            return got

        frames = run(main())
    finally:
        server.stop()
    seqs = [f.seq for f, _, _ in frames]
    assert seqs == sorted(seqs) and len(seqs) < len(w)  # some frames were replaced
    keys = [f.seq for f, _, _ in frames if f.key]
    # the first frame the client gets is a key frame (the join's, or, where the join's was replaced before it was
    # sent, the replacement's), and so is one after each replacement
    assert keys[0] == seqs[0] and len(keys) > 1, (seqs, keys)
    for f, pos, rot in frames:
        exact, _ = offline_pipeline(SMALL, "arkit52", w[f.seq], settings=s)
        perr, rerr = errors(type("S", (), {"position": pos, "rotation": rot})(), exact, "flame")
        assert perr <= s.delta_position_mm * 1e-3 + 1e-6 and rerr <= s.delta_rotation_deg + 1e-3, (f.seq, perr, rerr)


def test_f32_delta_is_declined_and_resync_outside_delta_is_harmless() -> None:
    server = main_server()

    async def main():
        async with await connect(server.url, encoding="f32", delta=True) as c:
            assert not c.welcome.delta
            await c.send_raw(c.conn.resync())
            await c.send_bs(np.zeros(LAYOUTS["arkit52"], np.float32))
            f = await c.recv_frame(timeout=30)
            assert f.key is None and f.index is None
            return [e.code for e in c.errors]

    assert run(main()) == ["not_ready"]


def test_replay_delta_records_the_reconstructed_positions(tmp_path) -> None:
    """`ofera replay --encoding q13 --delta --record OUT --record-positions`: every recorded frame is the client's
    reconstruction (key + deltas), within the tolerance of the exact frame of the bs it answers."""
    import json

    from ofera.cli.main import app
    from ofera.mapping.layouts import get_layout
    from ofera.sources import FaceLog, write_facelog
    from typer.testing import CliRunner

    server = main_server()
    n = 40
    w = sweep(n, seed=5)
    log = tmp_path / "sweep.csv"
    write_facelog(log, FaceLog(times=np.arange(n) / 30.0, weights=w, layout=get_layout("arkit52")))
    rec, out = tmp_path / "rec.npz", tmp_path / "summary.json"
    result = CliRunner().invoke(app, ["replay", str(log), "--url", server.url, "--encoding", "q13", "--delta",
                                      "--record", str(rec), "--record-positions", "--json", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    assert json.loads(out.read_text())["errors"] == 0
    z = np.load(rec)
    assert z["key"][0] == 1 and (z["key"][1:] == 0).all() and z["position"].shape[1:] == (z["count"][0], 3)
    s = settings()
    for seq, pos in zip(z["seq"], z["position"], strict=True):
        exact, _ = offline_pipeline(SMALL, "arkit52", w[seq], settings=s)
        err = np.linalg.norm(pos.astype(np.float64) - exact.position, axis=1).max()
        assert err <= s.delta_position_mm * 1e-3 + 1e-6, (seq, err)


def test_replay_delta_needs_a_compact_encoding(tmp_path) -> None:
    from ofera.cli.main import app
    from typer.testing import CliRunner

    result = CliRunner().invoke(app, ["replay", str(tmp_path / "x.csv"), "--encoding", "f32", "--delta"])
    assert result.exit_code == 2 and "--delta needs --encoding f16 or q13" in result.output
