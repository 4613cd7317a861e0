"""Shared dependencies: the runtime the routes read, and bearer-token auth for mutating routes."""

from __future__ import annotations

import secrets
from typing import Annotated, Any, Protocol

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

__all__ = ["Runtime", "RuntimeBusy", "RuntimeUnavailable", "bearer_problem", "get_runtime", "require_token"]


class RuntimeUnavailable(RuntimeError):
    """The session cannot be reached right now (answered as 503 with this message)."""


class RuntimeBusy(RuntimeError):
    """Too many commands in a short time (answered as 429, Retry-After whole seconds)."""

    def __init__(self, message: str, retry_after_s: int):
        super().__init__(message)
        self.retry_after_s = retry_after_s


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


def bearer_problem(authorization: str | None, expected: str) -> str | None:
    """Why `authorization` (the raw header) does not carry the expected token; None when it does.

    Shared by `require_token` and the body-cap middleware in `server/app.py`, which refuses a
    bad token before the body is read."""
    if not expected:
        return "no API token is configured: set api.token in the session config or DPMHW_API_TOKEN"
    scheme, _, credentials = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not credentials:
        return "missing bearer token (Authorization: Bearer <token>)"
    if not secrets.compare_digest(credentials.strip().encode(), expected.encode()):
        return "wrong bearer token"
    return None


async def require_token(request: Request,
                  credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """401 unless the request carries `Authorization: Bearer <token>` with the configured token.
    (`credentials` is declared so that the OpenAPI schema shows the bearer scheme.)"""
    problem = bearer_problem(request.headers.get("authorization"), getattr(request.app.state, "token", "") or "")
    if problem is not None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, problem, headers={"WWW-Authenticate": "Bearer"})


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
