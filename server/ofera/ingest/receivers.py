"""UDP receivers for live face tracking: Live Link Face packets and VMC (OSC) blendshape bundles.

Each datagram is decoded into zero or more weight frames that go into a `LatestSlot` (newest wins:
a sender that is slower than the tracker sends only the newest frame). A datagram that cannot be
decoded is counted as bad and skipped; nothing a sender puts on the wire can stop the receiver.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ofera.mapping.layouts import get_layout
from ofera.sources.livelink_packet import parse_livelink_packet
from ofera.sources.vmc import VmcBlendshapeAccumulator

Decoded = tuple[list[np.ndarray], "str | None"]
"""(frames decoded from one datagram, problem or None). A datagram with a problem counts as bad."""


class LatestSlot:
    """A one-frame mailbox: `put` replaces whatever was not taken yet; `get` waits for a frame."""

    def __init__(self) -> None:
        self._value: np.ndarray | None = None
        self._event = asyncio.Event()
        self.put_count = 0
        self.replaced = 0
        """Frames overwritten before they were taken (the sender was slower than the source)."""

    def put(self, frame: np.ndarray) -> None:
        if self._value is not None:
            self.replaced += 1
        self._value = frame
        self.put_count += 1
        self._event.set()

    def take_nowait(self) -> np.ndarray | None:
        value, self._value = self._value, None
        self._event.clear()
        return value

    async def get(self) -> np.ndarray:
        while self._value is None:
            self._event.clear()
            await self._event.wait()
        value = self.take_nowait()
        assert value is not None
        return value


@dataclass
class PacketCounters:
    ok: int = 0
    bad: int = 0
    frames: int = 0
    last_problem: str | None = None


class LiveLinkDecoder:
    """Live Link Face UDP packet -> one livelink61 frame (61 values; the last nine are radians)."""

    layout = get_layout("livelink61")
    name = "Live Link Face"

    def __call__(self, data: bytes) -> Decoded:
        try:
            packet = parse_livelink_packet(data)
        except ValueError as exc:
            return [], str(exc)
        if not np.all(np.isfinite(packet.values)):
            return [], "Live Link packet holds NaN or infinite values"
        return [packet.values], None


class VmcDecoder:
    """VMC OSC datagram (message or bundle) -> one arkit52 frame per `/VMC/Ext/Blend/Apply`.

    Values persist between datagrams (a sender may send only the shapes that changed). A datagram that
    is not OSC, or holds malformed blendshape messages, counts as bad; its well-formed messages still
    apply. Unknown blendshape names are counted in `accumulator.unknown_count`, not as bad.
    """

    name = "VMC"

    def __init__(self, layout: str = "arkit52") -> None:
        self.accumulator = VmcBlendshapeAccumulator(layout)
        self.layout = self.accumulator.layout

    def __call__(self, data: bytes) -> Decoded:
        # Not OSC at all (an OSC packet starts with an address '/' or '#bundle'): skip it before
        # python-osc, which logs a warning for every such datagram.
        problem = osc_structure_problem(data)
        if problem is not None:
            return [], problem
        before = self.accumulator.malformed_count
        try:
            frames = self.accumulator.feed_datagram(data)
        except Exception as exc:  # python-osc raises more than ParseError on hostile input
            return [], f"undecodable OSC packet: {type(exc).__name__}: {exc}"
        if self.accumulator.malformed_count > before:
            return frames, "malformed OSC packet or /VMC/Ext/Blend/Val message"
        return frames, None


_BUNDLE = b"#bundle\x00"


def osc_structure_problem(data: bytes, depth: int = 0) -> str | None:
    """Why `data` is not a structurally valid OSC packet (None if it is): a message starts with '/', a
    bundle is '#bundle', a time tag, then (int32 size, element) pairs that fill it exactly. Checked
    before python-osc, which silently accepts bundles whose sizes run past the end (and logs a warning
    for every non-OSC datagram)."""
    if data[:1] == b"/":
        return None
    if data[:8] != _BUNDLE:
        return f"not an OSC packet ({len(data)} bytes)"
    if depth > 8:
        return "OSC bundles nested too deeply"
    pos = 16
    if len(data) < pos:
        return "truncated OSC bundle header"
    while pos < len(data):
        if len(data) - pos < 4:
            return "truncated OSC bundle element size"
        size = int.from_bytes(data[pos : pos + 4], "big", signed=True)
        pos += 4
        if size <= 0 or size % 4 or size > len(data) - pos:
            return f"OSC bundle element size {size} does not fit the {len(data) - pos} bytes left"
        problem = osc_structure_problem(data[pos : pos + size], depth + 1)
        if problem is not None:
            return problem
        pos += size
    return None


class DatagramReceiver(asyncio.DatagramProtocol):
    """asyncio UDP protocol: decode each datagram, count it, put its frames into `slot`."""

    def __init__(self, decode: Callable[[bytes], Decoded], slot: LatestSlot,
                 counters: PacketCounters | None = None) -> None:
        self.decode = decode
        self.slot = slot
        self.counters = counters or PacketCounters()
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str | object, ...]) -> None:
        c = self.counters
        try:
            frames, problem = self.decode(data)
        except Exception as exc:  # a decoder bug must not stop the receiver
            frames, problem = [], f"{type(exc).__name__}: {exc}"
        if problem is None:
            c.ok += 1
        else:
            c.bad += 1
            c.last_problem = problem
        for frame in frames:
            c.frames += 1
            self.slot.put(frame)

    def error_received(self, exc: Exception) -> None:
        self.counters.last_problem = f"socket error: {exc}"


def parse_listen(text: str, default_port: int) -> tuple[str, int]:
    """`HOST:PORT`, `:PORT`, `PORT` or `HOST` -> (host, port); IPv6 as `[::1]:PORT`."""
    text = text.strip()
    host, port = text, str(default_port)
    if text.startswith("["):
        end = text.find("]")
        if end < 0:
            raise ValueError(f"--listen {text!r}: missing ']' in an IPv6 address")
        host, rest = text[1:end], text[end + 1 :]
        if rest:
            if not rest.startswith(":"):
                raise ValueError(f"--listen {text!r}: expected ':PORT' after ']'")
            port = rest[1:]
    elif text.isdigit():
        host, port = "0.0.0.0", text
    elif text.count(":") == 1:
        host, port = text.split(":")
    host = host or "0.0.0.0"
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--listen {text!r}: port {port!r} is not a number in 0..65535")
    return host, int(port)
