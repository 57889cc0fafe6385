"""Prometheus metrics of one server instance (its own registry, so several apps can share a process)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

# Microsecond-scale stages and whole-frame latencies, in seconds.
_STAGE_BUCKETS = (2e-5, 5e-5, 1e-4, 2e-4, 5e-4, 1e-3, 2e-3, 5e-3, 1e-2, 2e-2, 5e-2, 0.1, 0.25, 1.0)

CONTENT_TYPE = CONTENT_TYPE_LATEST

FRAME_STAGES = ("decode", "queue", "layout", "bda", "epm", "map", "head", "deform", "total", "encode", "send", "drain")
"""The `ofera_stage_seconds` stages of a frame, in order: bs decode, queue (received -> computation starts), the
pipeline's stages (map = layout + bda), total (received -> computed), encode (the frame message written), send (the
writes' time on the event loop: bytes into the kernel) and drain (until the kernel took them: streaming.server)."""


class Metrics:
    """Sessions, message counts, skipped work, errors by code, per-stage latency histograms."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.sessions = Gauge("ofera_sessions", "Open WebSocket sessions by role.", ["role"], registry=r)
        self.bs_in = Counter("ofera_bs_received", "bs messages received (valid or not).", registry=r)
        self.frames_computed = Counter("ofera_frames_computed", "Pipeline runs (one per computed bs).",
                                       registry=r)
        self.frames_out = Counter("ofera_frames_sent", "frame messages sent to viewers.", registry=r)
        self.skipped = Counter("ofera_frames_skipped", "Work dropped by newest-wins backpressure: 'bs' "
                               "(a bs replaced before it was computed), 'frame' (a computed frame replaced "
                               "before it was sent).", ["stage"], registry=r)
        self.errors = Counter("ofera_errors", "error messages sent, by code.", ["code"], registry=r)
        self.stage = Histogram("ofera_stage_seconds", "Duration of each server stage.", ["stage"],
                               buckets=_STAGE_BUCKETS, registry=r)
        self.server_latency = Histogram("ofera_server_latency_seconds", "From a bs arriving to its frame "
                                        "being handed to the socket.", buckets=_STAGE_BUCKETS, registry=r)
        self.bytes_out = Counter("ofera_bytes_sent", "Bytes of frame and avatar messages sent.", registry=r)
        self.bs_conf = Counter("ofera_bs_conf", "bs messages received that carried a face confidence (bs.conf).",
                               registry=r)
        self.conf_held = Counter("ofera_bs_conf_held", "Computed bs in which a face region was held (its bs.conf "
                                 "below the confidence threshold: streaming.confidence).", registry=r)
        # Rooms (streaming.rooms).
        self.rooms = Gauge("ofera_rooms", "Rooms with at least one member on this server.", registry=r)
        self.room_members = Gauge("ofera_room_members", "Members of this server's rooms: 'local' (connected here) "
                                  "or 'remote' (on another server, through the bus).", ["where"], registry=r)
        self.room_unresolved = Counter("ofera_room_unresolved", "Remote members whose avatar id this server does not "
                                       "have (invisible to its viewers: PROTOCOL.md 12.5).", registry=r)
        self.room_events = Counter("ofera_room_events", "Room events: 'join', 'leave', 'refused' (room_full, "
                                   "too_many_rooms), 'stale' (remote members dropped when the bus was lost), "
                                   "'bad_frame' (a member's frame that failed to encode: dropped), 'over_limit' (a "
                                   "remote member beyond room_members: waits unseen), 'overflow' (a viewer's control "
                                   "queue over room_control_bytes: its session ends).",
                                   ["event"], registry=r)
        for where in ("local", "remote"):
            self.room_members.labels(where)
        # Rooms across servers (streaming.redis_bus; they stay at zero without --redis).
        self.bus_connected = Gauge("ofera_bus_connected", "1 while the rooms bus (Redis) is connected.", registry=r)
        self.bus_published = Counter("ofera_bus_published", "Messages published to the rooms bus, by kind "
                                     "('v': expression values, 'join', 'leave').", ["kind"], registry=r)
        self.bus_received = Counter("ofera_bus_received", "Valid messages received from other servers, by kind.",
                                    ["kind"], registry=r)
        self.bus_dropped = Counter("ofera_bus_dropped", "Expression values not sent or not delivered: 'down' (bus "
                                   "lost), 'superseded' (newest wins before sending), 'unknown_member' (from a "
                                   "member not (yet) in the room).", ["reason"], registry=r)
        self.bus_malformed = Counter("ofera_bus_malformed", "Bus messages or member entries that failed "
                                     "validation (dropped).", registry=r)
        self.bus_reconnects = Counter("ofera_bus_reconnects", "Times the rooms bus reconnected after losing Redis.",
                                      registry=r)
        self.bus_remote_members = Gauge("ofera_bus_remote_members", "Members of other servers in this server's "
                                        "rooms.", registry=r)
        self.bus_hop = Histogram("ofera_bus_hop_seconds", "Expression values: publish() on the sending server to "
                                 "receipt here (wall clocks: meaningful when the servers' clocks agree).",
                                 buckets=_STAGE_BUCKETS, registry=r)
        for role in ("source", "viewer"):
            self.sessions.labels(role)
        # Labelled children looked up once (`labels()` costs about as much as the observation, several per frame)
        self.skipped_bs, self.skipped_frame = self.skipped.labels("bs"), self.skipped.labels("frame")
        self._stages = {stage: self.stage.labels(stage) for stage in FRAME_STAGES}  # listed (at zero) from the start

    def stage_of(self, name: str) -> Histogram:
        """The `ofera_stage_seconds` child of stage `name` (cached)."""
        child = self._stages.get(name)
        if child is None:
            child = self._stages[name] = self.stage.labels(name)
        return child

    def observe_timings(self, timings: dict[str, int]) -> None:
        """Record a frame's stage durations (microseconds)."""
        for name, us in timings.items():
            self.stage_of(name).observe(us * 1e-6)

    def render(self) -> bytes:
        return generate_latest(self.registry)
