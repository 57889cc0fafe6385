"""The FastAPI application: WebSocket `/v1/stream`, `GET /healthz`, `GET /metrics`, `GET /v1/avatars`; the rooms'
cross-server bus (Redis, `make_bus`) is started and closed with it."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, WebSocket
from fastapi.responses import JSONResponse, Response
from ofera_protocol import COORDS, ENCODINGS, ENDPOINT, LAYOUTS, PROTOCOL_VERSION
from ofera_protocol.constants import PARAMS
from starlette.websockets import WebSocketDisconnect

from .. import __version__, web
from .affinity import cpus_in_use, usable_cpus
from .bus import RoomBus
from .compute_pool import ComputePool
from .config import Settings, normalize_origin
from .metrics import CONTENT_TYPE, Metrics
from .registry import registry_for
from .session import ConnectionGone, Hub, Session, Transport

log = logging.getLogger("ofera.streaming")


class WebSocketTransport(Transport):
    """Transport over Starlette's WebSocket (binary messages; text is reported to the session)."""

    def __init__(self, ws: WebSocket) -> None:
        self.ws = ws
        self.gone = False

    async def receive(self) -> bytes | str | None:
        if self.gone:
            return None
        msg = await self.ws.receive()
        if msg["type"] == "websocket.disconnect":
            self.gone = True
            return None
        data = msg.get("bytes")
        if data is not None:
            return data
        text = msg.get("text")
        return text if text is not None else b""

    async def send(self, data: bytes) -> None:
        if self.gone:
            raise ConnectionGone()
        try:
            await self.ws.send_bytes(data)
        except (WebSocketDisconnect, OSError, RuntimeError) as exc:
            self.gone = True
            raise ConnectionGone() from exc

    async def close(self, code: int, reason: str = "") -> None:
        if self.gone:
            return
        self.gone = True
        try:
            await self.ws.close(code, reason)
        except Exception:  # noqa: BLE001 - already closing or gone: nothing left to do
            pass


def warm_up(hub: Hub) -> None:
    """Load the default avatar and run its pipeline a few times (blocking; before accepting clients).
    Raises what loading raises (AvatarError, MapperError, FileNotFoundError...)."""
    if hub.warm:
        return
    assets = hub.registry.get(hub.settings.default_avatar)
    assets.pipeline("arkit52").warm_up()
    assets.wire_avatar("flame")
    assets.selection(sparse=True, max_gaussians=None)
    if hub.settings.fast:
        from .encode_fast import numba_kernels

        numba_kernels(warm=True)  # compiles (or loads cached) frame-encoding kernels
        if getattr(assets.fast, "binding_type", None) == "triangle":  # a delta session's frames (direct_delta)
            from .direct_delta import warm_up as warm_direct_delta

            warm_direct_delta(assets.fast, threads=assets.parallel is not False)
    hub.warm = True


def make_bus(settings: Settings, hub: Hub) -> RoomBus | None:
    """The rooms' cross-server bus: None (rooms in-process) unless `settings.redis_url` is set."""
    if not getattr(settings, "redis_url", None):
        return None
    from .redis_bus import RedisBus

    return RedisBus(settings.redis_url, metrics=hub.metrics)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    registry = registry_for(settings)
    threads = settings.compute_threads or usable_cpus()
    hub = Hub(settings, registry, ComputePool(threads), Metrics())

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if settings.warmup:
            await asyncio.get_running_loop().run_in_executor(hub.executor, warm_up, hub)
        bus = make_bus(settings, hub)
        if bus is not None:
            assert hub.rooms is not None
            await bus.start(hub.rooms)  # BusUnavailable (naming the URL) if Redis cannot be reached
            hub.bus = hub.rooms.bus = bus
        try:
            yield
        finally:
            if bus is not None:
                await bus.close()
            hub.executor.shutdown(wait=False, cancel_futures=True)

    app = FastAPI(title="OFERA server", version=__version__, lifespan=lifespan)
    app.state.hub = hub

    origins = settings.origins

    @app.websocket(ENDPOINT)
    async def stream(ws: WebSocket) -> None:
        origin = ws.headers.get("origin")
        if origins is not None and origin is not None and normalize_origin(origin) not in origins:
            # A page from a site not in allowed_origins (cross-site WebSocket hijacking). Closing before accept
            # makes uvicorn answer the handshake with HTTP 403.
            log.info("refused a WebSocket handshake from origin %r (not in allowed_origins)", origin[:256])
            await ws.close(1008)
            return
        await ws.accept()
        await Session(WebSocketTransport(ws), hub).run()

    @app.get("/healthz")
    async def healthz() -> JSONResponse:
        loop = type(asyncio.get_running_loop())  # event_loop: e.g. "uvloop.Loop" (the event_loop setting's choice)
        return JSONResponse({"status": "ok", "version": __version__, "protocol": PROTOCOL_VERSION,
                             "sessions": hub.active, "max_sessions": settings.max_sessions,
                             "rooms": len(hub.rooms.rooms) if hub.rooms is not None else 0,
                             "tasks": len(asyncio.all_tasks()), "event_loop": f"{loop.__module__}.{loop.__qualname__}",
                             "cpus": cpus_in_use()})

    @app.get("/metrics")
    async def metrics() -> Response:
        return Response(hub.metrics.render(), media_type=CONTENT_TYPE)

    @app.get("/v1/avatars")
    async def avatars() -> JSONResponse:
        return JSONResponse({"default": registry.default_id, "avatars": registry.describe(),
                             "devices": sorted(registry.devices), "layouts": list(LAYOUTS),
                             "encodings": [*ENCODINGS, PARAMS], "coords": list(COORDS),
                             "auth": settings.token is not None})

    app.include_router(web.router)  # the browser preview: / and /static/
    return app
