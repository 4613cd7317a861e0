"""The operator's reserved listener: `POST /session/blank` and `GET /status` on a port of their own,
served by threads of the session process at its own (normal) priority.

    listener = OperatorListener(sock, blank=api.operator_blank, status=api.operator_status,
                                token="…", trusted_hosts=["127.0.0.1", "localhost"]).start()
    listener.url                # what the status reports (`status["api"]["operator"]`)
    listener.close()

Why here. The main API process runs below the loop (SCHED_IDLE by default) and serves every
client from one event loop: under a request storm its CPU share goes to the storm, and a blank or
a status waits behind it however few places it may take. A listener inside that process would
wait the same (its threads share the interpreter lock with the starved event loop), and the
supervisor has no hold on the projector while a loop process runs. The session process owns the
projector and publishes the status: a blank here calls the loop directly (dark, read back, before
the answer), and a status is the one last published (`snapshot_age_s` says how old). Nothing on
the main port reaches this one.

Bounds, so that no client here can hold it either: at most `max_connections` at once, each on a
thread of its own; at the cap a new connection evicts the one that has waited longest for its
request (or, when all are being answered, is closed). A request must arrive whole within
`request_timeout_s` of its connection (408; trickled bytes do not extend it); its head is at
most `max_head_bytes` and `max_headers` (431), its body `max_body_bytes` (413). One request per
connection (`Connection: close`). Status requests are limited to `status_per_s` (429 with
Retry-After); the blank never. Requests are parsed by h11 (as the main API's are): a malformed one
gets 400 naming the problem. As on the main port, the Host header must be one the API accepts
(400) and the blank needs the API's bearer token (401). Every refusal is one line of JSON,
`{"detail": "…"}`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import selectors
import socket
import threading
import time
from http import HTTPStatus
from typing import Callable

import h11

from server.deps import bearer_problem
from server.guard import TokenBucket

__all__ = ["OperatorListener"]

log = logging.getLogger(__name__)

ROUTES = {"/session/blank": "POST", "/status": "GET"}  # and OPTIONS /session/blank: the operator page's preflight
# JSON only here, so nothing may load, sniff or frame it (the main API's pages have their own policy)
_HEADERS = ((b"Content-Type", b"application/json"), (b"Cache-Control", b"no-store"), (b"Connection", b"close"),
            (b"X-Content-Type-Options", b"nosniff"), (b"X-Frame-Options", b"DENY"),
            (b"Content-Security-Policy", b"default-src 'none'; frame-ancestors 'none'"))


class _Refused(Exception):
    """A request answered with `status` and the one-line `detail`."""

    def __init__(self, status: int, detail: str, headers: tuple = ()):
        super().__init__(detail)
        self.status, self.detail, self.headers = status, detail, headers


class _Evicted(Exception):
    """The connection gave its place to a newer one."""


class OperatorListener:
    """Blank and status on `sock` (bound and listening; never closed here: it may outlive this
    listener, as the API's does); see module doc. `blank()` returns (ok, message, state) once the
    projector is dark or the attempt failed; `status()` returns the status, a JSON object's bytes."""

    def __init__(self, sock: socket.socket, *, blank: Callable[[], tuple[bool, str, str]],
                 status: Callable[[], bytes], token: str, trusted_hosts: list[str] | tuple[str, ...],
                 max_connections: int = 8, request_timeout_s: float = 2.0, max_head_bytes: int = 8 * 1024,
                 max_headers: int = 64, max_body_bytes: int = 1024, status_per_s: float = 50.0,
                 page_port: int | None = None, clock: Callable[[], float] = time.monotonic):
        self.sock = sock
        self.host, self.port = sock.getsockname()[:2]
        self._blank, self._status, self.token = blank, status, token
        self.trusted_hosts = frozenset(h.strip("[]").lower() for h in trusted_hosts)
        self.max_connections, self.request_timeout_s = max_connections, request_timeout_s
        self.max_head_bytes, self.max_headers, self.max_body_bytes = max_head_bytes, max_headers, max_body_bytes
        self.page_port = page_port  # the operator page's (the main API's) port: its blank may come here (CORS)
        self.clock = clock
        self._status_rate = TokenBucket(status_per_s, max(1, int(status_per_s)), clock)
        self._lock = threading.Lock()
        self._waiting: dict[socket.socket, None] = {}  # insertion order: the longest waiting first
        self._serving: set[socket.socket] = set()
        self.counts = {"served": 0, "refused": 0, "evicted": 0, "timed_out": 0, "blanks": 0}
        self._wake_r, self._wake_w = socket.socketpair()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    def stats(self) -> dict:
        """What the status reports (`status["api"]["operator"]`)."""
        with self._lock:
            return {"url": self.url, "cap": self.max_connections, "open": len(self._waiting) + len(self._serving),
                    **self.counts}

    def start(self) -> "OperatorListener":
        # non-blocking: a supervisor's fault responder may share the socket, and a connection it
        # took first is then no wait here
        self.sock.setblocking(False)
        self._thread = threading.Thread(target=self._accept_loop, name="operator-listener", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop accepting and cut the open connections (the socket stays open)."""
        self._stop.set()
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        if self._thread is not None:
            self._thread.join(5)
        with self._lock:
            for conn in [*self._waiting, *self._serving]:
                with contextlib.suppress(OSError):
                    conn.shutdown(socket.SHUT_RDWR)
        self._wake_r.close()
        self._wake_w.close()

    def __enter__(self) -> "OperatorListener":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- connections -------------------------------------------------------------------------
    def _accept_loop(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self.sock, selectors.EVENT_READ)
            selector.register(self._wake_r, selectors.EVENT_READ)
            while not self._stop.is_set():
                for key, _ in selector.select():
                    if key.fileobj is self.sock:
                        self._accept()

    def _accept(self) -> None:
        try:
            conn, _ = self.sock.accept()
        except (BlockingIOError, InterruptedError):  # another server on the socket took it first
            return
        except OSError as exc:  # out of descriptors: the client's connection stays queued
            log.warning("operator port: accept failed: %s", exc)
            time.sleep(0.05)
            return
        conn.setblocking(True)
        with self._lock:
            if len(self._waiting) + len(self._serving) >= self.max_connections:
                victim = next(iter(self._waiting), None)
                if victim is None:  # every place is answering a request: this one waits for none
                    self.counts["refused"] += 1
                    conn.close()
                    return
                del self._waiting[victim]
                self.counts["evicted"] += 1
                with contextlib.suppress(OSError):
                    victim.shutdown(socket.SHUT_RDWR)  # its thread sees the end and closes it
            self._waiting[conn] = None
        threading.Thread(target=self._serve, args=(conn,), name="operator-connection", daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            try:
                status, body, headers = self._handle(conn)
            except _Refused as refusal:
                status, body, headers = refusal.status, _detail(refusal.detail), refusal.headers
                with self._lock:
                    self.counts["timed_out" if status == 408 else "refused"] += 1
            except (ConnectionError, _Evicted):
                return  # the client left, or was evicted: nothing to answer
            self._send(conn, status, body, headers)
        except Exception:  # never let a client take a thread of the session process down
            log.exception("operator port: answering a request failed")
        finally:
            with self._lock:
                self._waiting.pop(conn, None)
                self._serving.discard(conn)
            conn.close()

    def _handle(self, conn: socket.socket) -> tuple[int, bytes, tuple]:
        """Read one request whole and answer it: (status code, body, extra headers)."""
        deadline = self.clock() + self.request_timeout_s
        parser = h11.Connection(h11.SERVER, max_incomplete_event_size=self.max_head_bytes)
        request, body_bytes = None, 0
        while True:
            try:
                event = parser.next_event()
            except h11.RemoteProtocolError as exc:
                if exc.error_status_hint == 431:
                    raise _Refused(431, f"the request head exceeds {self.max_head_bytes} bytes") from None
                raise _Refused(400, f"malformed request: {str(exc)[:120]}") from None  # it may quote the input
            if event is h11.NEED_DATA:
                parser.receive_data(self._recv(conn, deadline))
            elif isinstance(event, h11.Request):
                request = event
                origin = self._admit(request)
            elif isinstance(event, h11.Data):
                body_bytes += len(event.data)
                if body_bytes > self.max_body_bytes:
                    raise _Refused(413, f"request body exceeds the limit of {self.max_body_bytes} bytes")
            elif isinstance(event, h11.EndOfMessage):
                break
            elif isinstance(event, h11.ConnectionClosed):
                raise ConnectionResetError
        with self._lock:
            if self._waiting.pop(conn, _Evicted) is _Evicted:
                raise _Evicted
            self._serving.add(conn)
        path = request.target.decode("latin-1").split("?", 1)[0]
        cors = ((b"Access-Control-Allow-Origin", origin.encode()), (b"Vary", b"Origin")) if origin else ()
        if request.method == b"OPTIONS":  # the operator page's preflight for its blank
            return 204, b"", cors + ((b"Access-Control-Allow-Methods", b"POST"),
                                     (b"Access-Control-Allow-Headers", b"Authorization"),
                                     (b"Access-Control-Max-Age", b"600"))
        if path == "/status":
            return 200, self._status(), cors
        ok, message, state = self._blank()
        if not ok:
            return 500, _detail(f"the session failed to blank: {message}"), cors
        with self._lock:
            self.counts["blanks"] += 1
        return 200, json.dumps({"ok": True, "message": message, "state": state}).encode(), cors

    def _recv(self, conn: socket.socket, deadline: float) -> bytes:
        left = deadline - self.clock()
        if left <= 0:
            raise _Refused(408, f"no whole request within {self.request_timeout_s:g} s")
        conn.settimeout(left)
        try:
            data = conn.recv(4096)
        except TimeoutError:
            raise _Refused(408, f"no whole request within {self.request_timeout_s:g} s") from None
        except OSError:
            raise ConnectionResetError from None
        if not data:
            with self._lock:
                if conn not in self._waiting:
                    raise _Evicted
        return data  # b"": the client closed its side (h11 then sees the end)

    def _admit(self, request: h11.Request) -> str | None:
        """Refuse a request head at once, cheapest check first (before its body is read); returns
        its Origin when that is the operator page's (`_page_origin`), else None."""
        if len(request.headers) > self.max_headers:
            raise _Refused(431, f"the request has {len(request.headers)} headers; the limit is {self.max_headers}")
        path = request.target.decode("latin-1").split("?", 1)[0]
        method = request.method.decode("latin-1")
        if path not in ROUTES:
            raise _Refused(404, f"no {path[:80]!r} on the operator port: it answers POST /session/blank and GET /status")
        preflight = method == "OPTIONS" and path == "/session/blank"
        if method != ROUTES[path] and not preflight:
            raise _Refused(405, f"{method[:16]} {path}: the operator port answers only {ROUTES[path]} here",
                           ((b"Allow", ROUTES[path].encode()),))
        headers = {}
        for name, value in request.headers:
            headers.setdefault(name.decode("latin-1"), value.decode("latin-1"))
        host = headers.get("host", "")
        if _host_name(host) not in self.trusted_hosts:
            raise _Refused(400, f"Host header {host[:80]!r} is not one this service answers to")
        origin = self._page_origin(headers.get("origin"))
        if preflight:
            if origin is None:
                raise _Refused(403, f"Origin {headers.get('origin', '')[:80]!r}: only the operator page may ask "
                                    "its way here")
            return origin
        if path == "/session/blank":
            problem = bearer_problem(headers.get("authorization"), self.token)
            if problem is not None:
                raise _Refused(401, problem, ((b"WWW-Authenticate", b"Bearer"),))
        declared = headers.get("content-length", "0")
        if int(declared) > self.max_body_bytes:  # h11 has checked that it is a number
            raise _Refused(413, f"request body of {declared} bytes exceeds the limit of {self.max_body_bytes} bytes")
        if path == "/status":
            wait_s = self._status_rate.take()
            if wait_s > 0:
                raise _Refused(429, f"too many status requests: at most {self._status_rate.rate:g} per second",
                               ((b"Retry-After", str(max(1, math.ceil(wait_s))).encode()),))
        return origin

    def _page_origin(self, origin: str | None) -> str | None:
        """`origin` if it is the operator page's, http://<a host this service answers to>:<the
        page's port>: a browser then lets that page read the answers here (CORS)."""
        if origin is None or self.page_port is None or not origin.startswith("http://"):
            return None
        authority = origin[len("http://"):]
        name, _, port = authority.rpartition(":")
        if "/" in authority or port != str(self.page_port) or _host_name(authority) not in self.trusted_hosts:
            return None
        return origin if name else None

    def _send(self, conn: socket.socket, status: int, body: bytes, headers: tuple) -> None:
        """The answer, then an orderly close: the client's unread bytes are drained briefly, so that
        closing does not reset the connection under the answer before the client has read it."""
        head = [f"HTTP/1.1 {status} {HTTPStatus(status).phrase}".encode(), b"Content-Length: %d" % len(body)]
        head += [k + b": " + v for k, v in (*_HEADERS, *headers)]
        conn.settimeout(self.request_timeout_s)
        try:
            conn.sendall(b"\r\n".join(head) + b"\r\n\r\n" + body)
            with self._lock:
                self.counts["served"] += int(status < 400)
            conn.shutdown(socket.SHUT_WR)
            conn.settimeout(0.2)
            for _ in range(16):
                if not conn.recv(4096):
                    break
        except OSError:
            pass


def _host_name(host: str) -> str:
    """The name in a Host header, without its port: "127.0.0.1:8766" → "127.0.0.1", "[::1]:8766" → "::1"."""
    if host.startswith("["):
        return host[1:host.find("]")].lower()
    return (host.rsplit(":", 1)[0] if host.count(":") == 1 else host).lower()


def _detail(text: str) -> bytes:
    return json.dumps({"detail": text}).encode()
