"""Live face tracking into an avatar session without Unity (`ofera ingest livelink|vmc`).

`receivers` decodes UDP datagrams (Live Link Face packets, VMC/OSC bundles) into a newest-wins slot,
counting and skipping malformed ones; `run.run_ingest` sends the newest frame as `bs` and counts the
frames that come back.
"""

from ofera.ingest.receivers import (
    DatagramReceiver,
    LatestSlot,
    LiveLinkDecoder,
    PacketCounters,
    VmcDecoder,
    parse_listen,
)
from ofera.ingest.run import IngestResult, run_ingest

__all__ = [
    "DatagramReceiver",
    "IngestResult",
    "LatestSlot",
    "LiveLinkDecoder",
    "PacketCounters",
    "VmcDecoder",
    "parse_listen",
    "run_ingest",
]
