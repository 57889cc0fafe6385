"""asyncio Python client of the OFERA stream (tests, benchmarks, replay): `connect(url, ...) -> Client`;
rooms: `connect(url, room=...)` publishes, `watch(url, room)` watches."""

from .client import Client, ServerError, connect, now_us, stream_url, watch
from .stats import LatencyStats

__all__ = ["Client", "LatencyStats", "ServerError", "connect", "now_us", "stream_url", "watch"]
