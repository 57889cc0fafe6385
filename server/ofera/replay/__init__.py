"""Replay recorded face logs through a running OFERA server (`ofera replay`).

`core.Replayer` is the network-free absolute-time scheduler and `core.ReplayStats` the accounting;
`link.open_link` opens a session; `run.replay_through` ties them together; `record.FrameRecorder`
saves the received frames (`--record`).
"""

from ofera.replay.core import Replayer, ReplayStats, percentiles_ms
from ofera.replay.link import Link, LinkError, LinkOptions, open_link, stream_url
from ofera.replay.record import FrameRecorder
from ofera.replay.run import receive_loop, replay_through, watch_through

__all__ = [
    "FrameRecorder",
    "Link",
    "LinkError",
    "LinkOptions",
    "ReplayStats",
    "Replayer",
    "open_link",
    "percentiles_ms",
    "receive_loop",
    "replay_through",
    "stream_url",
    "watch_through",
]
