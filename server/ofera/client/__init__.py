"""asyncio Python client of the OFERA stream (tests, benchmarks, replay): `connect(url, ...) -> Client`."""

from .client import Client, ServerError, connect, now_us, stream_url
from .stats import LatencyStats

__all__ = ["Client", "LatencyStats", "ServerError", "connect", "now_us", "stream_url"]
