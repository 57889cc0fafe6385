"""`ofera ingest vmc`: VMC (OSC) blendshape bundles built with python-osc drive a real server; malformed
datagrams are counted and skipped."""

from __future__ import annotations

import asyncio
import socket

import numpy as np
import pytest
from ofera.ingest import VmcDecoder, run_ingest
from ofera.mapping.layouts import ARKIT52_NAMES
from pythonosc import osc_bundle_builder, osc_message_builder

pytestmark = pytest.mark.timeout(120)

VAL, APPLY = "/VMC/Ext/Blend/Val", "/VMC/Ext/Blend/Apply"


def message(address: str, *args) -> osc_message_builder.OscMessageBuilder:
    m = osc_message_builder.OscMessageBuilder(address=address)
    for a in args:
        m.add_arg(a)
    return m


def frame_bundle(i: int, pascal: bool = True) -> bytes:
    """All 52 ARKit shapes then Apply, as VMagicMirror's perfect sync sends them (PascalCase) or camelCase."""
    b = osc_bundle_builder.OscBundleBuilder(osc_bundle_builder.IMMEDIATELY)
    for k, name in enumerate(ARKIT52_NAMES):
        value = 0.5 + 0.5 * np.sin(i / 6 + k)
        b.add_content(message(VAL, name[0].upper() + name[1:] if pascal else name, float(value)).build())
    b.add_content(message("/VMC/Ext/Root/Pos", "root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0).build())  # ignored
    b.add_content(message(APPLY).build())
    return b.build().dgram


def malformed() -> list[bytes]:
    good = frame_bundle(0)
    wrong_args = osc_bundle_builder.OscBundleBuilder(osc_bundle_builder.IMMEDIATELY)
    wrong_args.add_content(message(VAL, "JawOpen").build())  # value missing
    wrong_args.add_content(message(VAL, 0.5, "JawOpen").build())  # arguments swapped
    return [
        b"",
        b"not osc at all",
        b"#bundle\x00" + b"\x00" * 8 + b"\x00\x00\x01\x00",  # element size past the end
        good[:37],  # truncated bundle
        b"#bundle\x00" + bytes(range(200, 256)),  # garbage after the bundle tag
        b"/VMC/Ext/Blend/Val\x00\x00,sf\x00" + b"\xff\xfe\x00\x00",  # bad string argument
        wrong_args.build().dgram,
    ]


def test_decoder_frames_on_apply_and_counts_malformed():
    dec = VmcDecoder()
    frames, problem = dec(frame_bundle(1, pascal=False))
    assert problem is None and len(frames) == 1 and frames[0].shape == (52,)
    expected = [0.5 + 0.5 * np.sin(1 / 6 + k) for k in range(52)]
    np.testing.assert_allclose(frames[0], expected, atol=1e-6)
    for data in malformed():
        frames, problem = dec(data)
        assert problem, data[:20]
    # fuzz: random bytes and corrupted bundles are never fatal
    rng = np.random.default_rng(0)
    good = bytearray(frame_bundle(2))
    for i in range(300):
        data = rng.bytes(int(rng.integers(0, 120))) if i % 2 else bytes(
            b ^ (0xFF if rng.random() < 0.01 else 0) for b in good)
        frames, problem = dec(data)
        assert isinstance(frames, list) and (problem is None or isinstance(problem, str))
    # values persist: an Apply alone sends the last frame again
    frames, problem = dec(message(APPLY).build().dgram)
    assert problem is None and len(frames) == 1


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from replay_support import small_server

    with small_server(tmp_path_factory.getbasetemp() / "small-avatar") as s:
        yield s


def test_vmc_ingest_over_loopback(server):
    good, bad = 80, malformed()

    async def main():
        ready: asyncio.Future = asyncio.get_running_loop().create_future()
        stop = asyncio.Event()
        decoder = VmcDecoder()
        task = asyncio.create_task(run_ingest(decoder, "arkit52", "127.0.0.1", 0, server.url, seconds=20, stop=stop,
                                              status_every=0.25, on_listening=ready.set_result))
        addr = await asyncio.wait_for(ready, 60)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for i in range(good):
                s.sendto(frame_bundle(i, pascal=i % 2 == 0), addr)
                if i % 10 == 5:
                    s.sendto(bad[(i // 10) % len(bad)], addr)
                await asyncio.sleep(1 / 60)
            for data in bad:
                s.sendto(data, addr)
            s.sendto(frame_bundle(good), addr)
        await asyncio.sleep(0.5)
        stop.set()
        return await task

    result = asyncio.run(main())
    n_bad = sum(1 for i in range(good) if i % 10 == 5) + len(bad)
    assert result.packets.bad == n_bad
    assert result.packets.ok == good + 1
    assert result.stats.fatal_error is None and result.stats.errors == 0, result.stats.error_messages
    assert result.stats.sent >= 0.5 * good
    assert result.stats.received >= 1
    assert result.stats.last_seq_answered == result.stats.last_seq_sent == result.stats.sent - 1


def test_cli_ingest_vmc(server, tmp_path):
    from replay_support import run_ingest_cli

    code, output, s = run_ingest_cli("vmc", server.url, tmp_path / "vmc.json", frame_bundle, b"#bundle\x00junk")
    assert code == 0, output
    assert "VMC on udp 127.0.0.1" in output
    assert s["layout"] == "arkit52" and s["packets_ok"] > 30 and s["packets_bad"] > 3
    assert s["sent"] > 20 and s["received"] >= 1 and s["errors"] == 0 and s["fatal_error"] is None
    assert s["last_seq_answered"] == s["last_seq_sent"]
