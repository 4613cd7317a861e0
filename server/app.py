"""The FastAPI app: assembled here, routes in `routers/`, shared dependencies in `deps.py`.

    app = build_app(runtime=loop, token="…")        # in the session's process (tests, embedding)
    ApiProcess(token="…").start(loop)               # what `dpmhw session start` runs: server/process.py

The service only reads the session's published snapshots and queues validated setting changes.
Bind it to 127.0.0.1 unless the lab network needs more (then list the name clients use in
`trusted_hosts` or DPMHW_API_HOSTS).

Hostile input is refused where it enters, cheapest check first: more than `max_headers` headers
or `max_header_bytes` of them (431; the HTTP server bounds a head that arrives in pieces the same,
`server.guard`), a foreign `Host` header (400), then, on every mutating request, a bad token
(401) before a byte of the body is read, then a body over `max_body_bytes` (413) before it is
parsed; validation errors (422) name the field without
echoing the input (which may be huge, or NaN that JSON cannot carry).

At most `MAX_CONCURRENT_REQUESTS` requests are served at once; the rest wait their turn, except
the operator's `POST /session/blank`, which is served at once (`_OperatorFirst`).

Every response says how a browser may use it (`_SecurityHeaders`): never inside a frame
(X-Frame-Options DENY, CSP frame-ancestors), never sniffed as another type (nosniff), and a
Content-Security-Policy that lets a page run and load only this server's own files
(`server.pages` gives the docs pages theirs).
"""

from __future__ import annotations

import asyncio
import os
import socket

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from dpmhw import __version__
from server.deps import Runtime, RuntimeBusy, RuntimeUnavailable, bearer_problem
from server.pages import PAGE_CSP, add_pages, page_csp
from server.routers import session, settings, status

__all__ = [
    "DEFAULT_TRUSTED_HOSTS",
    "MAX_BODY_BYTES",
    "MAX_HEADERS",
    "MAX_HEADER_BYTES",
    "build_app",
    "trusted_hosts_for",
]

# The largest body any route takes is a settings patch of a few hundred bytes.
MAX_BODY_BYTES = 16 * 1024
MAX_HEADERS = 64  # a browser sends about 20
MAX_HEADER_BYTES = 8 * 1024  # request line and headers together
DEFAULT_TRUSTED_HOSTS = ("127.0.0.1", "localhost")
_SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
MAX_CONCURRENT_REQUESTS = 16  # served at once (`_OperatorFirst`); a browser opens about 6 connections
_NEVER_WAIT = frozenset({"/session/blank", "/status/stream"})


def trusted_hosts_for(bind_host: str) -> list[str]:
    """The Host names a service bound to `bind_host` accepts: DPMHW_API_HOSTS (comma-separated)
    if set, else the loopback names plus the bound address itself, or, for a wildcard bind
    (0.0.0.0, ::), this machine's name and the addresses it resolves to. A client that reaches
    the service through another name (a DNS alias, a NAT address) needs DPMHW_API_HOSTS."""
    env = [h.strip() for h in os.environ.get("DPMHW_API_HOSTS", "").split(",") if h.strip()]
    if env:
        return env
    hosts = list(DEFAULT_TRUSTED_HOSTS)
    if bind_host in ("0.0.0.0", "::", ""):
        names = {socket.gethostname(), socket.getfqdn()}
        for name in sorted(names):
            try:
                addresses = {info[4][0] for info in socket.getaddrinfo(name, None, proto=socket.IPPROTO_TCP)}
            except OSError:
                addresses = set()
            names |= addresses
        hosts += sorted(names)
    else:
        hosts.append(bind_host)
    return list(dict.fromkeys(hosts))


class _GuardMutations:
    """ASGI middleware for every request that may change something (not GET/HEAD/OPTIONS):
    401 on a missing or wrong token without reading the body, then 413 when the declared or the
    streamed body exceeds `max_body_bytes` (counted as it arrives, so a chunked body without a
    length is cut off at the cap, never buffered beyond it)."""

    def __init__(self, app: ASGIApp, max_body_bytes: int):
        self.app = app
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in _SAFE_METHODS:
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        problem = bearer_problem(headers.get("authorization"), scope["app"].state.token)
        if problem is not None:
            await _reply(send, 401, problem, {"WWW-Authenticate": "Bearer"})
            return
        limit = self.max_body_bytes
        declared = headers.get("content-length", "")
        if declared and (not declared.isdigit() or int(declared) > limit):
            await _reply(send, 413, f"request body of {declared} bytes exceeds the limit of {limit} bytes")
            return
        # Read the (at most `limit`-byte) body here, so the route sees it whole or not at all.
        body = bytearray()
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away
            body += message.get("body", b"")
            if len(body) > limit:
                await _reply(send, 413, f"request body exceeds the limit of {limit} bytes")
                return
            if not message.get("more_body", False):
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": bytes(body), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class _LimitHeaders:
    """ASGI middleware: 431 for a request with more than `max_headers` headers or more than
    `max_bytes` of names and values."""

    def __init__(self, app: ASGIApp, max_headers: int, max_bytes: int):
        self.app = app
        self.max_headers, self.max_bytes = max_headers, max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            headers = scope["headers"]
            size = sum(len(k) + len(v) for k, v in headers)
            problem = (f"the request has {len(headers)} headers; the limit is {self.max_headers}"
                       if len(headers) > self.max_headers else
                       f"the request's headers have {size} bytes; the limit is {self.max_bytes}"
                       if size > self.max_bytes else None)
            if problem is not None:
                await _reply(send, 431, problem, {"Connection": "close"})
                return
        await self.app(scope, receive, send)


class _OperatorFirst:
    """ASGI middleware: at most `limit` requests are worked on at once (until their answer starts);
    the others wait, costing the event loop nothing, for a place. The operator's blank never waits (nor does a status stream,
    which would hold a place for its whole life), so under a storm of requests the work ahead of
    a blank in the event loop is at most `limit` requests, however many are queued."""

    def __init__(self, app: ASGIApp, limit: int):
        self.app, self.limit = app, limit
        self._places: tuple[asyncio.AbstractEventLoop, asyncio.Semaphore] | None = None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in _NEVER_WAIT:
            await self.app(scope, receive, send)
            return
        loop = asyncio.get_running_loop()
        if self._places is None or self._places[0] is not loop:  # a semaphore belongs to one event loop
            self._places = (loop, asyncio.Semaphore(self.limit))
        places = self._places[1]
        await places.acquire()
        held = True

        def release() -> None:
            nonlocal held
            if held:
                held = False
                places.release()

        async def sending(message: Message) -> None:
            if message["type"] == "http.response.start":
                release()  # the work is done; a client slow to read its answer holds no place
            await send(message)

        try:
            await self.app(scope, receive, sending)
        finally:
            release()


class _SecurityHeaders:
    """ASGI middleware: the security headers on every response (a route's own CSP is kept)."""

    HEADERS = ((b"x-frame-options", b"DENY"), (b"x-content-type-options", b"nosniff"),
               (b"referrer-policy", b"no-referrer"))

    def __init__(self, app: ASGIApp, csp: str = PAGE_CSP):
        self.app = app
        self.csp = csp.encode()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {k.lower() for k, _ in headers}
                headers += [(k, v) for k, v in self.HEADERS if k not in present]
                if b"content-security-policy" not in present:
                    headers.append((b"content-security-policy", self.csp))
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, with_headers)


async def _reply(send: Send, status_code: int, detail: str, headers: dict | None = None) -> None:
    response = JSONResponse({"detail": detail}, status_code=status_code, headers=headers)
    body = response.body
    await send({"type": "http.response.start", "status": status_code, "headers": response.raw_headers})
    await send({"type": "http.response.body", "body": body})


def _validation_errors(exc: RequestValidationError) -> list[dict]:
    """Each error's location, message and type; the offending input only as a short repr, so a
    NaN, an infinity or a 10 MB string never reaches the JSON encoder."""
    out = []
    for err in exc.errors():
        item = {"loc": [str(p) for p in err.get("loc", ())], "msg": str(err.get("msg", "")), "type": str(err.get("type", ""))}
        if "input" in err:
            text = repr(err["input"])
            item["input"] = text if len(text) <= 80 else text[:77] + "..."
        out.append(item)
    return out


def build_app(runtime: Runtime, *, token: str | None = None, trusted_hosts: list[str] | tuple[str, ...] | None = None,
              max_body_bytes: int = MAX_BODY_BYTES, max_headers: int = MAX_HEADERS,
              max_header_bytes: int = MAX_HEADER_BYTES,
              max_concurrent_requests: int = MAX_CONCURRENT_REQUESTS, operator_port: int | None = None) -> FastAPI:
    """The service over `runtime`; `token` guards the mutating routes (None reads DPMHW_API_TOKEN;
    no token at all: they all answer 401). `trusted_hosts` are the Host names clients may use
    (None: DPMHW_API_HOSTS, comma-separated, else loopback names only). The caller owns the
    runtime's lifetime."""
    app = FastAPI(title="dpmhw session", version=__version__,
                  description="Status, settings and control of a dynamic projection mapping session.",
                  docs_url=None, redoc_url=None)  # served from local files by add_pages
    app.state.runtime = runtime
    app.state.png_cache = status.PngCache()  # per app: a frame is encoded once, a few per second at most
    app.state.token = token if token is not None else os.environ.get("DPMHW_API_TOKEN", "")
    if trusted_hosts is None:
        env = os.environ.get("DPMHW_API_HOSTS", "")
        trusted_hosts = [h.strip() for h in env.split(",") if h.strip()] or list(DEFAULT_TRUSTED_HOSTS)
    # Starlette runs the middleware added last first: the headers (on every answer, refusals too),
    # header count and size, Host, then token and body size (a body arrives whole before), a
    # place among the requests worked on at once.
    app.add_middleware(_OperatorFirst, limit=max_concurrent_requests)
    app.add_middleware(_GuardMutations, max_body_bytes=max_body_bytes)
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=list(trusted_hosts))
    app.add_middleware(_LimitHeaders, max_headers=max_headers, max_bytes=max_header_bytes)
    app.add_middleware(_SecurityHeaders, csp=page_csp(trusted_hosts, operator_port))

    @app.exception_handler(RuntimeUnavailable)
    async def unavailable(request: Request, exc: RuntimeUnavailable) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=503)

    @app.exception_handler(RuntimeBusy)
    async def busy(request: Request, exc: RuntimeBusy) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=429, headers={"Retry-After": str(exc.retry_after_s)})

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": _validation_errors(exc)}, status_code=422)

    app.include_router(status.router)
    app.include_router(settings.router)
    app.include_router(session.router)
    add_pages(app)  # the operator page at / and offline /docs, /redoc
    return app
