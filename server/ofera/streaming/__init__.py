"""The streaming server: FastAPI + uvicorn, one WebSocket session per client.

Modules, one job each: `config` (settings), `registry` (avatars and device BDA profiles on disk; the offline
pipeline), `pipeline` (layout -> BDA -> EPM -> FLAME -> LBS -> Gaussians), `session`
(source/viewer roles, newest-wins backpressure), `metrics` (Prometheus), `app` (routes), `server`
(uvicorn with TCP_NODELAY and draining sends; background-thread runner), `affinity` (the server's CPUs).
"""

from .config import Settings
from .pipeline import STAGES, AvatarAssets, Pipeline
from .registry import offline_pipeline

__all__ = ["STAGES", "AvatarAssets", "Pipeline", "Settings", "ServerThread", "create_app", "offline_pipeline",
           "serve"]


def __getattr__(name: str):  # the web stack is imported only when a server is wanted
    if name == "create_app":
        from .app import create_app

        return create_app
    if name in ("serve", "ServerThread"):
        from . import server

        return getattr(server, name)
    raise AttributeError(name)
