"""The FastAPI app: assembled here, routes in `routers/`, shared dependencies in `deps.py`.

    app = build_app(runtime=loop, token="…")        # in the session's process (tests, embedding)
    ApiProcess(token="…").start(loop)               # what `dpmhw session start` runs: server/process.py

The service only reads the session's published snapshots and queues validated setting changes.
Bind it to 127.0.0.1 unless the lab network needs more.
"""

from __future__ import annotations

import os

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from dpmhw import __version__
from server.deps import Runtime, RuntimeUnavailable
from server.pages import add_pages
from server.routers import session, settings, status

__all__ = ["build_app"]


def build_app(runtime: Runtime, *, token: str | None = None) -> FastAPI:
    """The service over `runtime`; `token` guards the mutating routes (None reads DPMHW_API_TOKEN;
    no token at all: they all answer 401). The caller owns the runtime's lifetime."""
    app = FastAPI(title="dpmhw session", version=__version__,
                  description="Status, settings and control of a dynamic projection mapping session.",
                  docs_url=None, redoc_url=None)  # served from local files by add_pages
    app.state.runtime = runtime
    app.state.png_cache = status.PngCache()  # per app: each presented frame is encoded once
    app.state.token = token if token is not None else os.environ.get("DPMHW_API_TOKEN", "")

    @app.exception_handler(RuntimeUnavailable)
    async def unavailable(request: Request, exc: RuntimeUnavailable) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=503)

    app.include_router(status.router)
    app.include_router(settings.router)
    app.include_router(session.router)
    add_pages(app)  # the operator page at / and offline /docs, /redoc
    return app
