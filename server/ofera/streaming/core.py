"""The sans-I/O core of one session (in the style of h11 and python-websockets): it takes received WebSocket
messages and clock readings and returns actions for its driver to carry out (`Send`, `Close`, `Start`, `Compute`,
`KeyFrame`). No sockets, no asyncio, no pipeline: `session.Session` drives it over a Transport, tests drive it in
memory.

It owns the protocol state machine (`ServerConnection`), the hello checks that need no avatar (server token, room
token), the hello timeout, the bs/ping rate limit and the clamping of huge weights.
"""

from __future__ import annotations

import hashlib
import hmac
from dataclasses import dataclass, replace

import numpy as np
from ofera_protocol import Blendshapes, Bye, Hello, Ping, ProtocolError, ServerConnection, ServerState
from ofera_protocol import errors as E
from ofera_protocol.messages import Resync

from .config import Settings

WEIGHT_LIMIT = 1000.0
"""bs weights are limited to +-WEIGHT_LIMIT before the pipeline (PROTOCOL.md 4.2: the server clamps them).
The layout adapter clamps the arkit weights it computes to [0, 1], but an arkit weight of an ovr layout is a
sum of several ovr weights: finite inputs near float32's limit (+-3.4e38) overflow there to inf - inf = NaN."""


class TokenBucket:
    """`rate` events per second with bursts of up to `burst`; time in seconds, given by the caller."""

    def __init__(self, rate: float, burst: float, now: float) -> None:
        self.rate, self.burst = rate, burst
        self.tokens = burst
        self.stamp = now

    def take(self, now: float) -> bool:
        self.tokens = min(self.burst, self.tokens + max(0.0, now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass(frozen=True)
class Send:
    """Send these bytes; `error`: the code of an error message (for metrics)."""

    data: bytes
    error: str | None = None


@dataclass(frozen=True)
class Close:
    """Close the WebSocket with this code and reason; the session is over."""

    code: int
    reason: str


@dataclass(frozen=True)
class Start:
    """The hello passed every check the core can make: load its avatar, then `conn.accept` (or `fail`)."""

    hello: Hello


@dataclass(frozen=True)
class Compute:
    """A bs to hand to the session's Source (newest wins there). `received_ns`: when it arrived (monotonic)."""

    bs: Blendshapes
    received_ns: int


@dataclass(frozen=True)
class KeyFrame:
    """A delta-session client asked for a key frame (`resync`)."""


@dataclass(frozen=True)
class Count:
    """Count one event in the metrics: "bs_in" (a bs received, valid or not), "bs_conf" (one carrying conf)."""

    metric: str


Action = Send | Close | Start | Compute | KeyFrame | Count


def room_token(secret: str, room: str) -> str:
    """The token of `room` (PROTOCOL.md 12.1): lowercase hex HMAC-SHA256(secret, room name in UTF-8)."""
    return hmac.new(secret.encode(), room.encode(), hashlib.sha256).hexdigest()


class SessionCore:
    """One session's protocol logic. Call `receive` with each WebSocket message and `tick` when a timer fires;
    carry out the returned actions in order. Times are monotonic nanoseconds."""

    def __init__(self, settings: Settings, now_ns: int) -> None:
        self.settings = settings
        self.conn = ServerConnection(max_message_size=settings.max_message_bytes)
        self.bucket = TokenBucket(settings.bs_rate, settings.burst, now_ns * 1e-9)
        self.hello_deadline_ns = now_ns + int(settings.hello_timeout * 1e9)
        self._last_rate_error: float | None = None
        self.closed = False

    # ------------------------------------------------------------------ inputs

    def tick(self, now_ns: int) -> list[Action]:
        """Timers: a connection that sent no hello by the deadline is closed (1008)."""
        if self.conn.state is ServerState.AWAITING_HELLO and now_ns >= self.hello_deadline_ns and not self.closed:
            return self._close(1008, f"no hello within {self.settings.hello_timeout:g} s")
        return []

    def receive(self, data: bytes | bytearray | memoryview | str, now_ns: int) -> list[Action]:
        """One received WebSocket message (str: a text message, always fatal)."""
        if self.closed:
            return []
        streaming = self.conn.state is ServerState.STREAMING
        try:
            if isinstance(data, str):
                self.conn.receive_text(data)
            msg = self.conn.receive(data)
        except ProtocolError as e:
            if e.fatal or not streaming:
                return self.fail(e.as_fatal())
            if self._allow(now_ns):  # a flood of bad messages shares the bs/ping budget
                return self.fail(e)
            return self._rate_error(now_ns, None)
        if isinstance(msg, Hello):
            refusal = self.check_hello(msg)
            return self.fail(refusal) if refusal is not None else [Start(msg)]
        if isinstance(msg, Bye):
            return self._close(E.CLOSE_NORMAL, "bye")
        if isinstance(msg, Ping):
            if not streaming or self._allow(now_ns):
                return [Send(self.conn.pong(msg.t))]
            return self._rate_error(now_ns, None)
        if isinstance(msg, Blendshapes):
            return self._bs(msg, now_ns)
        if isinstance(msg, Resync):
            return [KeyFrame()]
        return []  # pragma: no cover - the connection returns only the messages above

    def fail(self, err: ProtocolError, seq: int | None = None) -> list[Action]:
        """Report `err` to the client (and close after it if it is fatal)."""
        out: list[Action] = [Send(self.conn.error(err, seq=seq), error=err.code)]
        if err.fatal:
            out += self._close(err.close_code, err.code)
        return out

    # ------------------------------------------------------------------ checks

    def check_hello(self, hello: Hello) -> ProtocolError | None:
        """The server token and the room token (PROTOCOL.md 4.1, 12.1); None if the hello may go on."""
        s = self.settings
        if s.token is not None and not hmac.compare_digest((hello.token or "").encode(), s.token.encode()):
            return ProtocolError(E.UNAUTHORIZED, "missing or wrong token: send the server's token in hello.token",
                                 True)
        if hello.room is not None and s.room_secret is not None:
            want = room_token(s.room_secret, hello.room)
            if not hmac.compare_digest((hello.room_token or "").encode(), want.encode()):
                return ProtocolError(E.UNAUTHORIZED, f"missing or wrong room_token for room {hello.room!r}: this "
                                     "server's rooms need hello.room_token = hex HMAC-SHA256 of the room name "
                                     "(ask the app that sent you here)", True)
        return None

    # ------------------------------------------------------------------ internals

    def _bs(self, msg: Blendshapes, now_ns: int) -> list[Action]:
        counts: list[Action] = [Count("bs_in")] + ([Count("bs_conf")] if msg.conf is not None else [])
        if not self._allow(now_ns):
            return counts + self._rate_error(now_ns, msg.seq)
        hello = self.conn.hello
        if hello is not None and hello.room is not None and not hello.publish:
            return counts + self.fail(ProtocolError(E.NOT_READY, "bs in a watch-only room session (hello.publish "
                                                    "false) is ignored", False), seq=msg.seq)
        w = msg.w.tolist()  # a few Python builtins: cheaper than numpy calls on a cold CPU (_fields.SMALL_ARRAY)
        if w and (max(w) > WEIGHT_LIMIT or min(w) < -WEIGHT_LIMIT):  # finite but huge: see WEIGHT_LIMIT
            msg = replace(msg, w=np.clip(msg.w, -WEIGHT_LIMIT, WEIGHT_LIMIT))
        return [Compute(msg, now_ns), *counts]  # to the source first, then the counters

    def _allow(self, now_ns: int) -> bool:
        return self.bucket.take(now_ns * 1e-9)

    def _rate_error(self, now_ns: int, seq: int | None) -> list[Action]:
        """A dropped message: one non-fatal `rate_limited` error per second at most."""
        now = now_ns * 1e-9
        if self._last_rate_error is not None and now - self._last_rate_error < 1.0:
            return []
        self._last_rate_error = now
        return self.fail(ProtocolError(
            E.RATE_LIMITED, f"more than {self.settings.bs_rate:g} messages (bs, ping or invalid ones) per second; "
            "the excess is dropped", False), seq=seq)

    def _close(self, code: int, reason: str) -> list[Action]:
        self.closed = True
        return [Close(code, reason)]
