"""`ofera ingest livelink`: Live Link Face UDP packets over loopback drive a real server; bad packets are
counted and skipped."""

from __future__ import annotations

import asyncio
import socket
import struct

import numpy as np
import pytest
from ofera.ingest import LatestSlot, LiveLinkDecoder, parse_listen, run_ingest
from ofera.sources import build_livelink_packet

pytestmark = pytest.mark.timeout(120)


def good_packet(i: int) -> bytes:
    v = np.zeros(61, np.float32)
    v[17] = 0.5 + 0.5 * np.sin(i / 5)  # JawOpen
    v[0] = v[7] = float(i % 30 == 0)  # a blink now and then
    v[52] = 0.1  # head yaw, radians
    return build_livelink_packet(v, device_id="TEST-IPHONE", subject="test", frame_number=1000 + i)


def bad_packets() -> list[bytes]:
    """Malformed per the byte layout: each must be counted as bad, none may stop the receiver."""
    good = good_packet(0)
    v = np.zeros(61, np.float32)
    v[3] = np.nan
    return [
        b"",  # empty datagram
        b"hello live link",  # text
        good[:40],  # truncated inside the frame time
        good[:-4],  # one value short
        good + b"\x00",  # trailing byte
        bytes([5]) + good[1:],  # packet version 5
        good[:1] + struct.pack(">i", -3) + good[5:],  # negative device id length
        good[:1] + struct.pack(">i", 10**6) + good[5:],  # absurd device id length
        good[:-245] + struct.pack(">B", 60) + good[-244:-4],  # 60 values
        build_livelink_packet(v),  # NaN value
        build_livelink_packet(np.zeros(61), fps_num=0),  # zero frame rate
    ]


def test_decoder_accepts_good_and_rejects_bad():
    dec = LiveLinkDecoder()
    frames, problem = dec(good_packet(3))
    assert problem is None and len(frames) == 1 and frames[0].shape == (61,)
    for data in bad_packets():
        frames, problem = dec(data)
        assert frames == [] and problem, data[:16]


def test_latest_slot_newest_wins():
    async def main():
        slot = LatestSlot()
        for i in range(5):
            slot.put(np.full(3, i, np.float32))
        got = await slot.get()
        assert got[0] == 4 and slot.replaced == 4 and slot.take_nowait() is None

    asyncio.run(main())


def test_parse_listen():
    assert parse_listen("0.0.0.0:11111", 1) == ("0.0.0.0", 11111)
    assert parse_listen(":9000", 1) == ("0.0.0.0", 9000)
    assert parse_listen("127.0.0.1", 11111) == ("127.0.0.1", 11111)
    assert parse_listen("[::1]:5", 1) == ("::1", 5)
    with pytest.raises(ValueError, match="port"):
        parse_listen("host:http", 1)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from replay_support import small_server

    with small_server(tmp_path_factory.getbasetemp() / "small-avatar") as s:
        yield s


def test_udp_ingest_over_loopback(server):
    good, bad = 90, bad_packets()

    async def main():
        ready: asyncio.Future = asyncio.get_running_loop().create_future()
        stop = asyncio.Event()
        statuses: list[str] = []
        task = asyncio.create_task(run_ingest(
            LiveLinkDecoder(), "livelink61", "127.0.0.1", 0, server.url, seconds=20, stop=stop,
            status_every=0.25, on_status=lambda r: statuses.append(r.status_line()), on_listening=ready.set_result))
        addr = await asyncio.wait_for(ready, 60)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for i in range(good):
                s.sendto(good_packet(i), addr)
                if i % 8 == 4:
                    s.sendto(bad[(i // 8) % len(bad)], addr)
                await asyncio.sleep(1 / 60)
            for data in bad:
                s.sendto(data, addr)
            s.sendto(good_packet(good), addr)  # the receiver survived all of them
        await asyncio.sleep(0.5)
        stop.set()
        return await task, statuses

    result, statuses = asyncio.run(main())
    n_bad = sum(1 for i in range(good) if i % 8 == 4) + len(bad)
    assert result.packets.ok == good + 1
    assert result.packets.bad == n_bad
    assert result.stats.fatal_error is None and result.stats.errors == 0, result.stats.error_messages
    assert result.stats.sent + result.replaced == good + 1  # newest wins: every good frame sent or replaced
    assert result.stats.sent >= 0.5 * good
    # frames come back; the server computes only the newest bs when it falls behind, so the last is answered
    assert result.stats.received >= 1
    assert result.stats.last_seq_answered == result.stats.last_seq_sent == result.stats.sent - 1
    assert statuses and "packets ok" in statuses[-1] and "latency p50" in statuses[-1]
    s = result.summary()
    assert s["packets_bad"] == n_bad and s["latency_ms"]["p50"] is not None


def test_cli_ingest_livelink(server, tmp_path):
    from replay_support import run_ingest_cli

    code, output, s = run_ingest_cli("livelink", server.url, tmp_path / "ingest.json", good_packet, b"\x06garbage")
    assert code == 0, output
    assert "Live Link Face on udp 127.0.0.1" in output and "packets ok" in output
    assert s["packets_ok"] > 30 and s["packets_bad"] > 3
    assert s["sent"] > 20 and s["received"] >= 1 and s["errors"] == 0 and s["fatal_error"] is None
    assert s["last_seq_answered"] == s["last_seq_sent"]


def test_cli_ingest_port_in_use(server):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        from ofera.cli.main import app
        from typer.testing import CliRunner

        result = CliRunner().invoke(app, ["ingest", "livelink", "--listen", f"127.0.0.1:{port}", "--url", server.url,
                                          "--seconds", "1"])
    assert result.exit_code == 2 and "cannot listen on udp" in result.output
