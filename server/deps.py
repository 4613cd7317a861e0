"""Shared dependencies: the runtime the routes read, and bearer-token auth for mutating routes."""

from __future__ import annotations

import secrets
from typing import Annotated, Any, Protocol

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

__all__ = ["Runtime", "RuntimeUnavailable", "get_runtime", "require_token"]


class RuntimeUnavailable(RuntimeError):
    """The session cannot be reached right now (answered as 503 with this message)."""


class Runtime(Protocol):
    """What the service needs from a running session (`dpmhw.session.loop.SessionLoop`).

    Every method returns at once: reads are snapshot swaps, writes are validated and queued.
    A runtime in another process (`server.process.RemoteRuntime`) raises `RuntimeUnavailable`
    when the session does not answer.
    """

    def status(self) -> dict: ...

    def settings(self) -> Any: ...

    def update_settings(self, patch: dict) -> Any: ...

    def blank(self) -> None: ...

    def resume(self) -> tuple[bool, str]: ...

    def reset_history(self) -> None: ...

    def latest_frame(self) -> Any: ...

    def ready(self) -> bool: ...


async def get_runtime(request: Request) -> Runtime:
    runtime = getattr(request.app.state, "runtime", None)
    if runtime is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, "the session is not running")
    return runtime


_bearer = HTTPBearer(auto_error=False, description="the session's API token (api.token or DPMHW_API_TOKEN)")


async def require_token(request: Request,
                  credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """401 unless the request carries `Authorization: Bearer <token>` with the configured token."""
    expected: str = getattr(request.app.state, "token", "") or ""
    challenge = {"WWW-Authenticate": "Bearer"}
    if not expected:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED,
                            "no API token is configured: set api.token in the session config or DPMHW_API_TOKEN",
                            headers=challenge)
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing bearer token (Authorization: Bearer <token>)",
                            headers=challenge)
    if not secrets.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "wrong bearer token", headers=challenge)


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
