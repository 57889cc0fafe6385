"""Live Link `.gesichter` captures (the LLV tool's format).

Layout: the whole file is gzip; uint8 container version; big-endian uint32 frame count; then per
frame a big-endian uint32 packet size followed by one raw Live Link Face UDP packet.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ofera.mapping.layouts import get_layout
from ofera.sources.facelog import FaceLog, SourceFormatError
from ofera.sources.livelink_packet import VALUE_COUNT, LiveLinkPacketError, parse_livelink_packet

CONTAINER_VERSION = 6


def read_gesichter(path: str | Path) -> FaceLog:
    """Read a capture as a livelink61 `FaceLog`; times from frame numbers and each packet's fps."""
    raw = Path(path).read_bytes()
    try:
        data = gzip.decompress(raw)
    except (OSError, EOFError, zlib.error) as exc:
        raise SourceFormatError(f"not a gzip .gesichter capture ({exc})", path) from None
    if len(data) < 5:
        raise SourceFormatError(f"capture header needs 5 bytes, file has {len(data)}", path)
    version, count = struct.unpack_from(">BI", data)
    pos, packets = 5, []
    for frame in range(count):
        if len(data) - pos < 4:
            raise SourceFormatError(f"truncated: {count} frames announced, file ends", path, frame=frame)
        (size,) = struct.unpack_from(">I", data, pos)
        if size > len(data) - pos - 4:
            raise SourceFormatError(f"truncated: packet of {size} bytes, {len(data) - pos - 4} left", path, frame=frame)
        try:
            packets.append(parse_livelink_packet(data[pos + 4 : pos + 4 + size]))
        except LiveLinkPacketError as exc:
            raise SourceFormatError(exc.problem, path, frame=frame) from None
        pos += 4 + size
    if pos != len(data):
        raise SourceFormatError(f"{len(data) - pos} unexpected bytes after {count} frames", path)
    times = np.array([p.time for p in packets], dtype=np.float64)
    back = np.flatnonzero(np.diff(times) < 0)
    if len(back):
        raise SourceFormatError("frame number goes backwards", path, frame=int(back[0]) + 1)
    metadata = {"container_version": str(version)}
    source = f"Live Link .gesichter {path}"
    if packets:
        first = packets[0]
        metadata |= {
            "device_id": first.device_id,
            "subject": first.subject,
            "fps": f"{first.fps_num}/{first.fps_den}",
        }
        source += f" from {first.subject!r} ({first.device_id})"
        times -= times[0]
    return FaceLog(
        times=times,
        weights=np.array([p.values for p in packets], dtype=np.float32).reshape(count, VALUE_COUNT),
        layout=get_layout("livelink61"),
        source=source,
        metadata=metadata,
    )


def write_gesichter(path: str | Path, packets: Iterable[bytes]) -> None:
    """Write raw Live Link packets as a `.gesichter` capture."""
    packets = list(packets)
    body = [struct.pack(">BI", CONTAINER_VERSION, len(packets))]
    for packet in packets:
        body += [struct.pack(">I", len(packet)), packet]
    Path(path).write_bytes(gzip.compress(b"".join(body)))
