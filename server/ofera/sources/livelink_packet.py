"""Epic Live Link Face UDP packets (port 11111): parse and build.

Layout, big-endian: uint8 version (6); int32 length + UTF-8 device id; int32 length + UTF-8 subject;
int32 frame number, float32 sub-frame, int32 fps numerator, int32 fps denominator; uint8 count (61);
count float32 values in `livelink61` order (52 ARKit shapes, then head/eye yaw, pitch, roll in radians).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from ofera.sources.facelog import SourceFormatError

PACKET_VERSION = 6
VALUE_COUNT = 61
_FRAME_TIME = struct.Struct(">ifii")
_MAX_NAME_BYTES = 1024


class LiveLinkPacketError(SourceFormatError):
    """A malformed or truncated Live Link packet."""


@dataclass(frozen=True)
class LiveLinkPacket:
    """One decoded Live Link Face packet; `values` is (61,) float32 in livelink61 order."""

    device_id: str
    subject: str
    frame_number: int
    subframe: float
    fps_num: int
    fps_den: int
    values: np.ndarray

    @property
    def time(self) -> float:
        """Seconds of this frame on the sender's timecode clock: (frame + subframe) * den / num."""
        return (self.frame_number + self.subframe) * self.fps_den / self.fps_num


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data, self.pos = memoryview(data), 0

    def take(self, n: int, what: str) -> memoryview:
        if n > len(self.data) - self.pos:
            raise LiveLinkPacketError(
                f"Live Link packet truncated: {what} needs {n} bytes at offset {self.pos}, "
                f"{len(self.data) - self.pos} left"
            )
        self.pos += n
        return self.data[self.pos - n : self.pos]

    def text(self, what: str) -> str:
        (n,) = struct.unpack(">i", self.take(4, f"{what} length"))
        if not 0 <= n <= _MAX_NAME_BYTES:
            raise LiveLinkPacketError(f"Live Link packet: {what} length {n} is not in 0..{_MAX_NAME_BYTES}")
        try:
            return bytes(self.take(n, what)).decode("utf-8")
        except UnicodeDecodeError:
            raise LiveLinkPacketError(f"Live Link packet: {what} is not UTF-8") from None


def parse_livelink_packet(data: bytes) -> LiveLinkPacket:
    """Decode one Live Link Face packet; raises `LiveLinkPacketError` (a ValueError) if malformed."""
    reader = _Reader(data)
    (version,) = reader.take(1, "version")
    if version != PACKET_VERSION:
        raise LiveLinkPacketError(f"Live Link packet version {version} is not supported (expected {PACKET_VERSION})")
    device_id = reader.text("device id")
    subject = reader.text("subject name")
    frame, subframe, fps_num, fps_den = _FRAME_TIME.unpack(reader.take(_FRAME_TIME.size, "frame time"))
    if fps_num <= 0 or fps_den <= 0:
        raise LiveLinkPacketError(f"Live Link packet: frame rate {fps_num}/{fps_den} is not positive")
    (count,) = reader.take(1, "value count")
    if count != VALUE_COUNT:
        raise LiveLinkPacketError(f"Live Link packet: {count} values, expected {VALUE_COUNT}")
    values = np.frombuffer(reader.take(4 * count, f"{count} values"), dtype=">f4").astype(np.float32)
    if reader.pos != len(data):
        raise LiveLinkPacketError(f"Live Link packet: {len(data) - reader.pos} unexpected trailing bytes")
    return LiveLinkPacket(device_id, subject, frame, subframe, fps_num, fps_den, values)


def build_livelink_packet(
    values: np.ndarray,
    device_id: str = "OFERA-TEST-DEVICE",
    subject: str = "OFERA",
    frame_number: int = 0,
    subframe: float = 0.0,
    fps_num: int = 60,
    fps_den: int = 1,
) -> bytes:
    """Encode a Live Link Face packet from (61,) values in livelink61 order."""
    values = np.asarray(values, dtype=">f4")
    if values.shape != (VALUE_COUNT,):
        raise ValueError(f"a Live Link packet carries {VALUE_COUNT} values, got shape {values.shape}")
    device, name = device_id.encode("utf-8"), subject.encode("utf-8")
    return b"".join(
        (
            struct.pack(">Bi", PACKET_VERSION, len(device)),
            device,
            struct.pack(">i", len(name)),
            name,
            _FRAME_TIME.pack(frame_number, subframe, fps_num, fps_den),
            struct.pack(">B", VALUE_COUNT),
            values.tobytes(),
        )
    )
