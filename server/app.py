"""The FastAPI app: assembled here, routes in `routers/`, shared dependencies in `deps.py`.

    app = build_app(runtime=loop, token="…")          # the caller owns the loop
    app = build_app(start=lambda: build_session(…))    # the app starts it, and stops it on shutdown

The service only reads the loop's immutable snapshots and queues validated setting changes, so
no request can hold up a frame. Bind it to 127.0.0.1 unless the lab network needs more.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import AsyncIterator, Callable

from fastapi import FastAPI

from dpmhw import __version__
from server.deps import Runtime
from server.routers import session, settings, status

__all__ = ["build_app"]


def build_app(runtime: Runtime | None = None, *, token: str | None = None,
              start: Callable[[], Runtime] | None = None,
              stopped: Callable[[Runtime], None] | None = None) -> FastAPI:
    """The service over `runtime`, or over the one `start()` returns at startup.

    token : bearer token for mutating routes; None reads DPMHW_API_TOKEN (no token: they all 401).
    stopped : called with the runtime after the app stopped it (e.g. to print the final status:
        uvicorn re-raises SIGTERM after shutdown, so code after `server.run()` may never run).
    """
    if (runtime is None) == (start is None):
        raise ValueError("build_app: pass exactly one of runtime= or start=")

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if start is not None:
            app.state.runtime = start()
        try:
            yield
        finally:
            if start is not None:
                owned, app.state.runtime = app.state.runtime, None
                owned.stop()
                if stopped is not None:
                    stopped(owned)

    app = FastAPI(title="dpmhw session", version=__version__, lifespan=lifespan,
                  description="Status, settings and control of a dynamic projection mapping session.")
    app.state.runtime = runtime
    app.state.png_cache = status.PngCache()  # per app: each presented frame is encoded once
    app.state.token = token if token is not None else os.environ.get("DPMHW_API_TOKEN", "")
    app.include_router(status.router)
    app.include_router(settings.router)
    app.include_router(session.router)
    return app
