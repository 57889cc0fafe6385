"""asyncio client of the OFERA stream, on the protocol codec and a zero-copy WebSocket transport (`transport.py`;
`transport="websockets"` uses the `websockets` library instead).

    client = await connect("ws://127.0.0.1:8000/v1/stream", layout="arkit52")
    await client.send_bs(weights)            # seq and t (microseconds, monotonic clock) filled in
    frame = await client.recv_frame()        # decoded float32 arrays, stage timings, seq, t
    print(client.latency.summary())          # p50/p99 of now - frame.t (ms)
    await client.close()

Rooms (PROTOCOL.md 12): `connect(url, room="lab", avatar="default")` joins a room and publishes;
`publish=False` watches only (`watch(url, "lab")`). Every member's frames come through `recv_frame` with
`frame.member`; `client.members` holds who is there (their join, avatar, Gaussians with `track=True`),
`client.member_latency` per-member latency, `client.joins` / `client.leaves` the membership events seen.

Load generators: `connect(url, header_only=True)` returns every frame as a FrameHeader (seq, t, timing, n, member,
size), its arrays neither decoded nor checked (`codec.read_frame_header`).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator

import numpy as np
from ofera_protocol import (
    ENDPOINT,
    MAX_SERVER_MESSAGE,
    Avatar,
    ClientConnection,
    ClientState,
    ConnectionUsageError,
    ErrorMessage,
    Frame,
    FrameHeader,
    Join,
    Leave,
    Pong,
    ProtocolError,
    ServerMessage,
    Welcome,
)
from ofera_protocol.messages import ParamsFrame
from websockets.asyncio.client import ClientConnection as WsConnection
from websockets.asyncio.client import connect as ws_connect
from websockets.exceptions import ConnectionClosed

from .stats import LatencyStats
from .transport import WebSocket, open_websocket

TRANSPORTS = ("fast", "websockets")


def now_us() -> int:
    """The client clock put in `bs.t`: monotonic, microseconds."""
    return time.monotonic_ns() // 1000


def stream_url(url: str) -> str:
    """`host:port`, `ws://host:port`, `http://host:port[/]` -> `ws://host:port/v1/stream` (paths kept)."""
    url = url.strip()
    for http, ws in (("http://", "ws://"), ("https://", "wss://")):
        if url.startswith(http):
            url = ws + url[len(http):]
    if "://" not in url:
        url = "ws://" + url
    scheme, rest = url.split("://", 1)
    if "/" not in rest.rstrip("/"):
        rest = rest.rstrip("/") + ENDPOINT
    return f"{scheme}://{rest}"


class ServerError(Exception):
    """The server refused or ended the session: `code` (protocol error code), `fatal`, `close_code`."""

    def __init__(self, code: str, message: str, fatal: bool = True, close_code: int | None = None) -> None:
        super().__init__(f"{code}: {message}" + (f" (close {close_code})" if close_code else ""))
        self.code, self.message, self.fatal, self.close_code = code, message, fatal, close_code


class Client:
    """One open session (use `connect`). Not safe for concurrent receivers: one task reads."""

    def __init__(self, ws: WebSocket | WsConnection, conn: ClientConnection, welcome: Welcome, avatar: Avatar | None,
                 header_only: bool = False) -> None:
        self.ws = ws
        self.conn = conn
        self.header_only = header_only  # frames come as FrameHeader (connect(header_only=True))
        self.welcome = welcome
        self.avatar = avatar  # None in a room session: every avatar comes with a join (`members`)
        self.latency = LatencyStats()
        self.member_latency: dict[str, LatencyStats] = {}  # rooms: per member
        self.joins: list[Join] = []  # rooms: every join seen, in order
        self.leaves: list[Leave] = []  # rooms: every leave seen, in order
        self.errors: list[ErrorMessage] = []  # non-fatal errors seen while reading frames
        self.pongs: list[int] = []  # ping round trips, microseconds
        self.seq = -1
        self.frames_received = 0
        self.last_bytes = 0  # size of the last message received (bandwidth measurements)
        self.rig_deformer = None  # params sessions (PROTOCOL.md 13): params.RigDeformer of the rig, with track=True
        self._member_deformers: dict = {}  # rooms: member -> its RigDeformer
        if conn.rig is not None and conn.gaussians is not None:
            from .params import RigDeformer

            self.rig_deformer = RigDeformer(conn.rig)

    @property
    def session(self) -> str:
        return self.welcome.session

    @property
    def count(self) -> int:
        """Gaussians of this client's own avatar (0 for a watch-only room member)."""
        return self.welcome.avatar.count if self.welcome.avatar is not None else 0

    @property
    def room(self) -> str | None:
        return self.welcome.room

    @property
    def member(self) -> str | None:
        """This client's member id in its room."""
        return self.welcome.member

    @property
    def members(self):  # noqa: ANN201 - dict[str, ofera_protocol.connection.RoomMember]
        """Rooms: the members present (joined and not left), by member id."""
        return self.conn.members

    # ------------------------------------------------------------------ sending

    async def send_bs(self, weights: np.ndarray, seq: int | None = None, t: int | None = None,
                      conf: np.ndarray | None = None) -> int:
        """Send one `bs` (weights in the session's layout; `conf` optional [lower, upper] face confidence
        in [0, 1]). Returns the seq used (default: last + 1)."""
        self.seq = self.seq + 1 if seq is None else seq
        await self.ws.send(self.conn.bs(self.seq, now_us() if t is None else t, weights, conf))
        return self.seq

    async def send_raw(self, data: bytes | str) -> None:
        """Send any bytes (tests of the server's error handling)."""
        await self.ws.send(data)

    async def ping(self) -> None:
        await self.ws.send(self.conn.ping(now_us()))

    async def resync(self) -> None:
        """Ask for a key frame (delta sessions; sent by `recv` itself when a delta frame could not be applied)."""
        await self.ws.send(self.conn.resync())

    @property
    def gaussians(self):  # noqa: ANN201 - ofera_protocol.GaussianState | None
        """The client's reconstructed state (position, rotation, scale of every Gaussian), with `track=True`."""
        return self.conn.gaussians

    # ------------------------------------------------------------------ receiving

    async def recv(self, timeout: float | None = None) -> ServerMessage | FrameHeader:
        """The next server message (Frame, ErrorMessage or Pong), decoded; with `header_only` a frame is its
        FrameHeader. Frames update `latency`. Raises ServerError when the connection closes, TimeoutError on
        timeout."""
        try:
            data = await asyncio.wait_for(self.ws.recv(), timeout)
        except ConnectionClosed as e:
            rcvd = e.rcvd
            raise ServerError("closed", rcvd.reason if rcvd else "connection closed without a close frame",
                              True, rcvd.code if rcvd else None) from None
        if isinstance(data, str):
            raise ServerError("text_frame", "the server sent a text message", True)
        self.last_bytes = len(data)
        try:
            msg = self.conn.receive_header(data) if self.header_only else self.conn.receive(data)
        except ProtocolError:
            if self.conn.resync_needed:  # a delta frame was lost: the server must send a key frame
                await self.resync()
            raise
        if isinstance(msg, (Frame, FrameHeader)):  # a header is never a params frame's (connect refuses those)
            self.frames_received += 1
            self.latency.add(now_us() - msg.t)
            if msg.member is not None:
                self.member_latency.setdefault(msg.member, LatencyStats()).add(now_us() - msg.t)
        elif isinstance(msg, Join):
            self.joins.append(msg)
        elif isinstance(msg, Leave):
            self.leaves.append(msg)
        elif isinstance(msg, ParamsFrame):  # params sessions: stamped frames carry t; the client deforms
            self.frames_received += 1
            if msg.t is not None:
                self.latency.add(now_us() - msg.t)
            self._deform(msg)
        elif isinstance(msg, Pong):
            self.pongs.append(now_us() - msg.t)
        return msg

    def _deform(self, msg: ParamsFrame) -> None:
        """Params sessions with `track`: deform the Gaussians the frame moves (one's own, or a room member's)."""
        if msg.member is None:
            if self.rig_deformer is not None:
                self.rig_deformer.apply(msg.params, self.conn.gaussians, self.welcome.coords)
            return
        m = self.conn.members.get(msg.member)
        if m is None or m.rig is None or m.gaussians is None:
            return
        deformer = self._member_deformers.get(msg.member)
        if deformer is None or deformer.rig is not m.rig:  # a new join brings a new rig
            from .params import RigDeformer

            deformer = self._member_deformers[msg.member] = RigDeformer(m.rig)
        deformer.apply(msg.params, m.gaussians, self.welcome.coords)

    async def recv_frame(self, timeout: float | None = None) -> Frame | ParamsFrame | FrameHeader:
        """The next frame (a params session's: a ParamsFrame; with `header_only`: a FrameHeader). Non-fatal errors
        are kept in `errors`; a fatal one raises ServerError. Rooms: joins, avatar chunks and leaves are taken in
        passing (`members`, `joins`, `leaves`); `timeout` applies to each message."""
        while True:
            msg = await self.recv(timeout)
            if isinstance(msg, (Frame, ParamsFrame, FrameHeader)):
                return msg
            if isinstance(msg, ErrorMessage):
                if msg.fatal:
                    raise ServerError(msg.code, msg.message, True, await self._close_code())
                self.errors.append(msg)

    async def frames(self, timeout: float | None = None) -> AsyncIterator[Frame]:
        """Frames until the server closes the connection (ends quietly on a normal close)."""
        while True:
            try:
                yield await self.recv_frame(timeout)
            except ServerError as e:
                if e.code == "closed" and e.close_code in (1000, 1001):
                    return
                raise

    async def _close_code(self) -> int | None:
        try:
            await asyncio.wait_for(self.ws.wait_closed(), 5)
        except asyncio.TimeoutError:
            return None
        return self.ws.close_code

    # ------------------------------------------------------------------ closing

    async def close(self, timeout: float = 5.0) -> None:
        """Say bye and close (idempotent). Messages still on their way (a room's other members keep streaming) are
        read and dropped until the server's close arrives, at most `timeout` seconds: unread, they would hold the
        close frame back until the library's close timeout."""
        async def drain() -> None:
            while True:
                await self.ws.recv()

        try:
            if self.conn.state.value != "closed":
                await self.ws.send(self.conn.bye())
            await asyncio.wait_for(drain(), timeout)  # (asyncio.timeout would need Python 3.11; we support 3.10)
        except (ConnectionClosed, asyncio.TimeoutError):
            pass
        await self.ws.close()

    async def __aenter__(self) -> Client:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


async def connect(url: str, layout: str = "arkit52", avatar: str = "default", encoding: str = "f32",
                  coords: str = "flame", token: str | None = None, *, device: str | None = None,
                  sparse: bool = False, max_gaussians: int | None = None, open_timeout: float = 60.0,
                  max_size: int = MAX_SERVER_MESSAGE, max_queue: int = 2, delta: bool = False,
                  track: bool = False, room: str | None = None, publish: bool = True, self_view: bool = False,
                  room_token: str | None = None, header_only: bool = False, transport: str = "fast") -> Client:
    """Open a session: hello -> welcome -> avatar (chunks assembled). Raises ServerError if refused.

    `delta`: ask for key/delta frames (f16, q13; PROTOCOL.md 7.1): delta frames are returned as sparse-like
    Frames of the changed Gaussians (absolute values). `track`: keep every Gaussian's latest value in
    `client.gaussians` (the avatar as the client reconstructs it). `encoding="params"` (PROTOCOL.md 13): frames are
    ParamsFrames; the rig is in `client.conn.rig`, and with `track` the client deforms every frame itself.

    `max_queue`: messages the websockets library may read ahead of the application. Kept small so that
    a client slower than the stream leaves frames to the server's newest-wins backpressure instead of
    queueing stale ones locally (which would only add latency).

    `room` joins that room (PROTOCOL.md 12): `publish` False watches only, `self_view` also receives one's own
    avatar, `room_token` answers a server with a room secret. The handshake ends at welcome (avatars follow with
    each join).

    `header_only` (load generators): frames come back as FrameHeader, their arrays neither decoded nor checked
    (`ClientConnection.receive_header`); with `track`, `delta` or `encoding="params"`, which need the arrays, it
    raises ConnectionUsageError before connecting.

    `transport`: "fast" (default: `transport.WebSocket`, each message received straight into its buffer) or
    "websockets" (the library's asyncio client: several copies of every message, about twice the round trip of a
    1-4 MB message at p50, benchmarks/transport.py)."""
    if transport not in TRANSPORTS:
        raise ValueError(f"unknown transport {transport!r}; expected one of {TRANSPORTS}")
    if header_only:
        for asked, what in ((track, "track=True"), (delta, "delta=True"), (encoding == "params", 'encoding="params"')):
            if asked:
                raise ConnectionUsageError(f"header_only=True leaves the arrays of frames undecoded: {what} needs "
                                           "them (use header_only=False)")
    if transport == "fast":
        ws: WebSocket | WsConnection = await open_websocket(stream_url(url), max_size=max_size, max_queue=max_queue,
                                                            open_timeout=open_timeout)
    else:
        ws = await ws_connect(stream_url(url), compression=None, max_size=max_size, open_timeout=open_timeout,
                              ping_interval=None, max_queue=max_queue)
    conn = ClientConnection(max_message_size=max_size, track_gaussians=track)
    try:
        await ws.send(conn.hello(layout, avatar, encoding=encoding, coords=coords, sparse=sparse, device=device,
                                 token=token, max_gaussians=max_gaussians, delta=delta, room=room, publish=publish,
                                 self_view=self_view, room_token=room_token))
        welcome = await asyncio.wait_for(_handshake(ws, conn), open_timeout)
    except BaseException:
        await ws.close()
        raise
    assert conn.avatar is not None or room is not None
    return Client(ws, conn, welcome, conn.avatar, header_only)


async def watch(url: str, room: str, **kwargs: object) -> Client:
    """Watch a room without publishing: `connect(url, room=room, publish=False, ...)`."""
    return await connect(url, room=room, publish=False, **kwargs)  # type: ignore[arg-type]


def _handshake_done(conn: ClientConnection) -> bool:
    """v1: the avatar (params: and the rig after it) is complete; rooms: welcome arrived."""
    if conn.welcome is not None and conn.welcome.room is not None:
        return True
    return conn.avatar is not None and conn.state is not ClientState.RECEIVING_RIG


async def _handshake(ws: WebSocket | WsConnection, conn: ClientConnection) -> Welcome:
    welcome: Welcome | None = None
    while not _handshake_done(conn):
        try:
            data = await ws.recv()
        except ConnectionClosed as e:
            rcvd = e.rcvd
            raise ServerError("closed", rcvd.reason if rcvd else "closed during the handshake", True,
                              rcvd.code if rcvd else None) from None
        if isinstance(data, str):
            raise ServerError("text_frame", "the server sent a text message", True)
        try:
            msg = conn.receive(data)
        except ProtocolError as e:
            raise ServerError(e.code, f"bad server message: {e.message}", True) from None
        if isinstance(msg, ErrorMessage):
            code = None
            if msg.fatal:
                try:
                    await asyncio.wait_for(ws.wait_closed(), 5)
                    code = ws.close_code
                except asyncio.TimeoutError:
                    pass
            raise ServerError(msg.code, msg.message, msg.fatal, code)
        if isinstance(msg, Welcome):
            welcome = msg
    assert welcome is not None
    return welcome
