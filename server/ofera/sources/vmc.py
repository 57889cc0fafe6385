"""VMC protocol (OSC over UDP, port 39539) blendshape messages accumulated into ARKit frames."""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import numpy as np
from pythonosc.osc_packet import OscPacket, ParseError

from ofera.mapping.layouts import Layout, get_layout

VAL_ADDRESS = "/VMC/Ext/Blend/Val"
APPLY_ADDRESS = "/VMC/Ext/Blend/Apply"


class VmcBlendshapeAccumulator:
    """Collects `/VMC/Ext/Blend/Val (name, value)` and yields a frame on `/VMC/Ext/Blend/Apply`.

    Names match the layout case-insensitively (PascalCase and camelCase both work); values persist
    until overwritten. Unknown names and malformed messages are counted and ignored; other VMC
    addresses (bones, root, status) are ignored.
    """

    def __init__(self, layout: str | Layout = "arkit52") -> None:
        self.layout = get_layout(layout)
        self.values = np.zeros(self.layout.length, dtype=np.float32)
        self.unknown_count = 0
        self.malformed_count = 0
        self.unknown_names: set[str] = set()

    def feed(self, address: str, args: Sequence[object]) -> np.ndarray | None:
        """Apply one OSC message; returns a copy (K,) float32 of the frame on Apply, else None."""
        if address == APPLY_ADDRESS:
            return self.values.copy()
        if address != VAL_ADDRESS:
            return None
        if len(args) != 2 or not isinstance(args[0], str) or not isinstance(args[1], numbers.Real):
            self.malformed_count += 1
            return None
        name, value = args
        if name not in self.layout:
            self.unknown_count += 1
            if len(self.unknown_names) < 256:
                self.unknown_names.add(name)
            return None
        if not np.isfinite(value):
            self.malformed_count += 1
            return None
        self.values[self.layout.index(name)] = value
        return None

    def feed_datagram(self, data: bytes) -> list[np.ndarray]:
        """Decode one OSC datagram (message or bundle) and return the frames it applied."""
        try:
            messages = OscPacket(data).messages
        except ParseError:
            self.malformed_count += 1
            return []
        frames = (self.feed(m.message.address, m.message.params) for m in messages)
        return [frame for frame in frames if frame is not None]
