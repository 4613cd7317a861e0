"""What one client can hold in the API process: a bounded share of its connections, time and memory.

    limits = ConnectionLimits()
    uvicorn.Config(app, **limits.uvicorn_options(), ...)

The API is served with uvicorn's h11 protocol, not httptools: h11 bounds the part of a request
head it buffers (`h11_max_incomplete_event_size`: a head still incomplete beyond it is answered 400
and closed; a head that arrives whole in one read is bounded by that read, then by the app), and
its protocol class can be extended. uvicorn's own `timeout_keep_alive` closes a connection left idle after a response.
What uvicorn lacks, `GuardedH11Protocol` adds:

- a request deadline: from the moment a connection opens (or its last response ends) its next
  request must have arrived whole, head and body, within `request_timeout_s`, or the connection
  is closed. A connection that sends nothing, half a request line or half a body holds its
  descriptor for that long at most (trickling bytes does not extend it);
- a connection cap below the process's descriptor limit (RLIMIT_NOFILE less `reserved_fds` for the
  process's own files), so accepting never fails for want of a descriptor. At the cap, a new
  connection evicts the one that has waited longest without a whole request, or, when every
  connection has one in progress, the longest-running request (a status stream: the others end
  within a command's timeout). So no flood of connections, idle, half-sent or streaming, can
  keep out a client that sends its request promptly: the operator's `POST /session/blank` and
  `GET /status` are answered on the same port and page as ever. (uvicorn's `limit_concurrency`
  does not help here: it answers 503 but still accepts, and keeps, every connection.)

The app bounds the headers it is handed (`server.app`: count and size, 431).
"""

from __future__ import annotations

import resource
import threading
import time
from dataclasses import dataclass

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from server.app import MAX_HEADER_BYTES, MAX_HEADERS

__all__ = ["ConnectionGuard", "ConnectionLimits", "GuardedH11Protocol", "TokenBucket"]

_WAITING = (h11.IDLE, h11.SEND_BODY)  # the client's side of a request that has not arrived whole


@dataclass(frozen=True)
class ConnectionLimits:
    """The bounds on each client; `max_connections` is lowered to fit the descriptor limit."""

    request_timeout_s: float = 10.0  # head and body of one request, from the connection's open or last response
    keep_alive_s: float = 5.0  # idle after a response (uvicorn's timeout_keep_alive)
    max_connections: int = 1000
    reserved_fds: int = 64  # for the process's own files: slots, pipes, the listening socket, imports
    max_header_bytes: int = MAX_HEADER_BYTES
    max_headers: int = MAX_HEADERS

    def connection_cap(self) -> int:
        """`max_connections`, lowered to the soft RLIMIT_NOFILE less `reserved_fds` (at least 1)."""
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft == resource.RLIM_INFINITY:
            return self.max_connections
        return max(1, min(self.max_connections, soft - self.reserved_fds))

    def uvicorn_options(self) -> dict:
        """uvicorn.Config's own settings for these limits, and the guarded protocol."""
        return {"http": type("GuardedH11Protocol", (GuardedH11Protocol,), {"guard": ConnectionGuard(self)}),
                "timeout_keep_alive": self.keep_alive_s, "h11_max_incomplete_event_size": self.max_header_bytes}


class ConnectionGuard:
    """The connections of one server, those waiting for a request and those serving one (each
    longest first), and what was cut."""

    def __init__(self, limits: ConnectionLimits):
        self.limits = limits
        self.cap = limits.connection_cap()
        self.waiting: dict[GuardedH11Protocol, None] = {}  # insertion order: the longest waiting first
        self.busy: dict[GuardedH11Protocol, None] = {}  # request arrived, response not yet complete
        self.evicted = self.refused = self.timed_out = 0

    def stats(self) -> dict:
        """What the status reports (`status["api"]["connections"]`)."""
        return {"cap": self.cap, "waiting": len(self.waiting), "busy": len(self.busy), "evicted": self.evicted,
                "timed_out": self.timed_out, "refused": self.refused}


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a request deadline and a connection cap (see module doc)."""

    guard: ConnectionGuard  # set on the per-server subclass (`ConnectionLimits.uvicorn_options`)
    _deadline = None

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        guard = self.guard
        if len(self.connections) > guard.cap:
            victim = next(iter(guard.waiting), None) or next(iter(guard.busy), None)
            if victim is None:  # none that is ours (an upgraded one): this one waits for none of them
                guard.refused += 1
                self.connections.discard(self)
                transport.abort()
                return
            guard.evicted += 1
            victim._close()
        self._wait()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._track()

    def on_response_complete(self) -> None:
        self._forget()  # each request gets a fresh deadline, from the end of the response before
        super().on_response_complete()
        if not self.transport.is_closing():
            self._track()

    def connection_lost(self, exc: Exception | None) -> None:
        self._forget()
        super().connection_lost(exc)

    def _track(self) -> None:
        if self.conn.their_state in _WAITING:
            self._wait()
        else:
            self._arrived()

    def _wait(self) -> None:
        self.guard.busy.pop(self, None)
        if self._deadline is None:
            self._deadline = self.loop.call_later(self.guard.limits.request_timeout_s, self._expire)
            self.guard.waiting[self] = None

    def _arrived(self) -> None:
        if self not in self.guard.busy:  # its place is kept while it is served, whatever it sends
            self._forget()
            self.guard.busy[self] = None

    def _forget(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        self.guard.waiting.pop(self, None)
        self.guard.busy.pop(self, None)

    def _expire(self) -> None:
        self._deadline = None
        self.guard.timed_out += 1
        self._close()

    def _close(self) -> None:
        """Drop the connection (its request, if begun, sees a disconnect)."""
        self._forget()
        self.transport.abort()


class TokenBucket:
    """At most `burst` at once, refilled at `rate` per second; `take()` returns 0 when admitted,
    else the seconds until the next would be."""

    def __init__(self, rate: float, burst: int, clock=time.monotonic):
        self.rate, self.burst, self.clock = rate, burst, clock
        self._tokens, self._t = float(burst), clock()
        self._lock = threading.Lock()

    def take(self) -> float:
        with self._lock:
            now = self.clock()
            self._tokens = min(self.burst, self._tokens + (now - self._t) * self.rate)
            self._t = now
            if self._tokens >= 1:
                self._tokens -= 1
                return 0.0
            return (1 - self._tokens) / self.rate
