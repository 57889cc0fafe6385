"""A session with an OFERA server as the replay and ingest tools use it, on `ofera.client`.

`open_link(url, options)` performs the handshake (hello -> welcome -> avatar) and returns a `Link`:
`send(seq, t_us, w)` sends one `bs`, `events()` yields every `Frame` (a `FrameHeader` with
`LinkOptions.header_only`) and `ErrorMessage` the server sends (a frame the codec cannot decode is
yielded as a non-fatal error), `close()` says bye. Anything that prevents the session (refused hello,
nothing listening, timeout) raises `LinkError` with a message that says what to do.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass

import numpy as np
from ofera_protocol import ConnectionUsageError, ErrorMessage, Frame, FrameHeader, ProtocolError

from ofera.client import Client, ServerError, connect, stream_url

__all__ = ["Link", "LinkError", "LinkOptions", "open_link", "stream_url"]


class LinkError(Exception):
    """The session could not be opened: `code` is the protocol error code when the server sent one."""

    def __init__(self, message: str, code: str | None = None) -> None:
        super().__init__(message)
        self.code = code


@dataclass
class LinkOptions:
    layout: str
    avatar: str = "default"
    encoding: str = "f32"
    token: str | None = None
    device: str | None = None
    open_timeout: float = 60.0
    delta: bool = False  # ask for key/delta frames (f16, q13; PROTOCOL.md 7.1)
    track: bool = False  # keep the client's reconstruction of every Gaussian (client.gaussians)
    room: str | None = None  # join this room (PROTOCOL.md 12); None: a v1 session
    publish: bool = True  # rooms: False watches only
    self_view: bool = False  # rooms: also receive one's own avatar
    room_token: str | None = None  # rooms: the room's token, if the server asks for one
    header_only: bool = False  # frames as FrameHeader, arrays undecoded (not with delta or track; client.connect)


class Link:
    """An open session (see `open_link`)."""

    def __init__(self, client: Client) -> None:
        self.client = client
        self.closed_reason: str | None = None
        self.closing = False

    @property
    def layout(self) -> str:
        return self.client.welcome.layout

    @property
    def count(self) -> int:
        return self.client.count

    @property
    def member(self) -> str | None:
        """Rooms: this client's member id."""
        return self.client.member

    async def send(self, seq: int, t_us: int, w: np.ndarray, conf: np.ndarray | None = None) -> None:
        """One `bs`; `conf`: optional (2,) [lower, upper] face confidence in [0, 1]."""
        await self.client.send_bs(w, seq=seq, t=t_us, conf=conf)

    async def events(self) -> AsyncIterator[Frame | FrameHeader | ErrorMessage]:
        """Frames and errors until the connection closes; a fatal error is yielded last."""
        while True:
            try:
                msg = await self.client.recv()
            except ProtocolError as e:
                yield ErrorMessage(e.code, f"undecodable server message: {e.message}", e.fatal)
                if e.fatal:
                    return
                continue
            except ServerError as e:  # the connection closed
                if e.code == "closed":
                    code = f"{e.close_code}" if e.close_code is not None else "no close code"
                    why = f": {e.message}" if e.message else ""
                    self.closed_reason = f"the server closed the connection ({code}{why})"
                else:
                    yield ErrorMessage(e.code, e.message, True)
                return
            if isinstance(msg, (Frame, FrameHeader, ErrorMessage)):
                yield msg
                if isinstance(msg, ErrorMessage) and msg.fatal:
                    return

    async def close(self) -> None:
        self.closing = True
        try:
            await self.client.close()
        except Exception:  # already gone: nothing left to close
            pass


async def open_link(url: str, options: LinkOptions) -> Link:
    """Connect and complete the handshake. Raises `LinkError`, e.g. `server rejected hello: unknown_layout: ...`."""
    target = stream_url(url)
    try:
        client = await connect(target, layout=options.layout, avatar=options.avatar, encoding=options.encoding,
                               token=options.token, device=options.device, open_timeout=options.open_timeout,
                               delta=options.delta, track=options.track, room=options.room,
                               publish=options.publish, self_view=options.self_view, room_token=options.room_token,
                               header_only=options.header_only)
    except ServerError as e:
        if e.code == "closed":
            raise LinkError(f"the server closed the connection during the handshake: {e}") from None
        raise LinkError(f"server rejected hello: {e.code}: {e.message}", e.code) from None
    except ConnectionUsageError as e:
        raise LinkError(f"cannot ask for that session: {e}") from None
    except (asyncio.TimeoutError, TimeoutError):
        raise LinkError(f"{target} did not complete the handshake within {options.open_timeout:g} s") from None
    except OSError as e:
        raise LinkError(f"cannot connect to {target}: {e.strerror or e} (is `ofera serve` running there?)") from None
    except Exception as e:  # websockets: invalid URI, HTTP status instead of a WebSocket upgrade, ...
        raise LinkError(f"cannot open a WebSocket session at {target}: {e}") from None
    return Link(client)
