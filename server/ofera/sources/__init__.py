"""Face-tracking inputs read into a common `FaceLog`: face-log CSV, Quest Pro Unity logs, Live Link
CSV/UDP/.gesichter, MediaPipe/ARKit CSV, and VMC (OSC) blendshape messages."""

from ofera.sources.facelog import DATA_SOURCES, FaceLog, SourceFormatError
from ofera.sources.facelog_csv import read_facelog_csv, write_facelog
from ofera.sources.gesichter import read_gesichter, write_gesichter
from ofera.sources.livelink_csv import parse_timecode, read_livelink_csv
from ofera.sources.livelink_packet import (
    LiveLinkPacket,
    LiveLinkPacketError,
    build_livelink_packet,
    parse_livelink_packet,
)
from ofera.sources.quest_csv import read_quest_csv, read_quest_csv_report
from ofera.sources.read import read_facelog, read_facelog_report
from ofera.sources.report import LogReport
from ofera.sources.vmc import VmcBlendshapeAccumulator

__all__ = [
    "DATA_SOURCES",
    "FaceLog",
    "LiveLinkPacket",
    "LiveLinkPacketError",
    "LogReport",
    "SourceFormatError",
    "VmcBlendshapeAccumulator",
    "build_livelink_packet",
    "parse_livelink_packet",
    "parse_timecode",
    "read_facelog",
    "read_facelog_report",
    "read_facelog_csv",
    "read_gesichter",
    "read_livelink_csv",
    "read_quest_csv",
    "read_quest_csv_report",
    "write_facelog",
    "write_gesichter",
]
