"""The browser preview: a page at `/` that is a plain protocol client of `/v1/stream`.

The page (``static/index.html``) and its JavaScript modules are static files, served as they are: no
build step, no CDN, nothing fetched from outside at run time. ``static/msgpack.js`` and
``static/protocol.js`` are the client side of PROTOCOL.md (hello, bs, ping, bye; welcome, avatar chunks,
frames in f32/f16/q13, dense or sparse), ``static/splat-worker.js`` keeps the session's Gaussians and prepares
each view's splats off the main thread (decoding, projected 2D covariance, culling, depth sort),
``static/renderer.js`` draws them with WebGL2 (instanced quads, back-to-front premultiplied blending),
``static/facelog.js`` reads dropped face-log and Live Link CSV files,
``static/bsdata.js`` LAM / OpenAvatarChat ``bsData.json`` expression tracks, and
``static/app.js`` ties it together (sliders, presets, playback, orbit camera, statistics, reduced stream
when the browser is slow).

``/static/layouts.json`` is generated here from :mod:`ofera.mapping.layouts`, so that the page's slider
names, face regions and the CSV layouts' conversion to ARKit come from the same table as the server's.

Mounted by the streaming app: ``app.include_router(web.router)``.
"""

from __future__ import annotations

import functools
from pathlib import Path

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse, JSONResponse

STATIC = Path(__file__).resolve().parent / "static"
"""The page's files."""

_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".json": "application/json",
    ".png": "image/png",
    ".svg": "image/svg+xml",
}

router = APIRouter(tags=["browser preview"])


@functools.cache
def layouts_table() -> dict:
    """Layouts for the page: arkit52 names, face regions, and each layout's sparse map to arkit52."""
    import numpy as np

    from ..mapping.layouts import ARKIT52_NAMES, ARKIT_REGIONS, LAYOUTS, conversion_matrix, get_layout

    layouts = {}
    for name in LAYOUTS:
        m = conversion_matrix(name, "arkit52")
        dst, src = np.nonzero(m)
        layouts[name] = {
            "names": list(get_layout(name).names),
            "to_arkit52": [[int(d), int(s), round(float(m[d, s]), 6)] for d, s in zip(dst, src)],
        }
    return {"arkit52": list(ARKIT52_NAMES), "regions": {k: list(v) for k, v in ARKIT_REGIONS.items()},
            "layouts": layouts}


@router.api_route("/", methods=["GET", "HEAD"], include_in_schema=False)
async def index() -> FileResponse:
    """The preview page."""
    return FileResponse(STATIC / "index.html", media_type=_TYPES[".html"], headers={"Cache-Control": "no-cache"})


@router.api_route("/static/layouts.json", methods=["GET", "HEAD"], include_in_schema=False)
async def layouts_json() -> JSONResponse:
    return JSONResponse(layouts_table(), headers={"Cache-Control": "no-cache"})


@router.api_route("/static/{name:path}", methods=["GET", "HEAD"], include_in_schema=False)
async def static(name: str) -> FileResponse:
    """A file of the page (only files inside ``static/``, with a known type)."""
    try:
        path = (STATIC / name).resolve()
    except (ValueError, OSError):  # e.g. a NUL byte in the name
        raise HTTPException(404, "no such file") from None
    kind = _TYPES.get(path.suffix)
    if kind is None or not path.is_relative_to(STATIC) or not path.is_file():
        raise HTTPException(404, f"no such file: /static/{name}")
    return FileResponse(path, media_type=kind, headers={"Cache-Control": "no-cache"})


__all__ = ["STATIC", "layouts_table", "router"]
