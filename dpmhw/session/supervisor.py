"""A thin supervising parent for a session: the loop runs in a child process, so that no way of
ending that process (SIGKILL, a segfault in native code, the OOM killer, an exception escaping a
thread) and no way of hanging it (SIGSTOP, a deadlock) leaves the projector lit.

    Supervisor(config, mock=True, echo=print).run()     # what `dpmhw session start` does

The parent imports little and does little: it binds the API port, starts the loop process
(`run_child`), and watches it. While the output is lit, the loop's frame thread states in shared
memory when its next present is due (`dpmhw.session.heartbeat`: `safety.stale_after_ms` plus
twice its frame time plus 50 ms; a frame on a moving object older than that is as misregistered
as a stale pose). A loop process that misses it is hung: it is SIGKILLed at once (the kernel
releases its USB claim only when it is gone; a real device cannot be claimed by a second process
before) and handled like one that died. When the loop process ends without being asked to, the
parent

- idles the projector over USB itself and confirms it by read-back (`factory.idle_projector`),
  each attempt on a thread of its own with a deadline (`idle_timeout_s`): a device or emulator
  that does not answer gives "NOT confirmed dark", and the attempts go on while staying dark;
- puts a black full-screen window on the projector's display if the session used one;
- logs the exit status or the signal;
- answers `/status` with `fault` and the reason on the API port and the operator port
  (`FaultResponder`) while no loop process serves them;
- restarts the loop process if `safety.restart = "on-crash"` (`RestartPolicy`: backoff, and at
  most `restart_limit` restarts within `restart_window_s`), else stays dark until stopped.

Nothing from outside can hold the main thread: the loop process's messages are read on a relay
thread (a message half-sent by a process that was then stopped blocks only that thread), and
every HTTP connection to the fault responder is served on a thread of its own with a timeout.

Who holds the API port and the operator's reserved port: the parent binds them once (`dpmhw
session start` does) and keeps them for the whole show; each loop process receives copies, serves
the full API from its own API process (server/process.py, which also restarts that one if it dies)
and blank and status on the operator port from its own threads (server/operator_port.py). So the port is never free for another program to take
between restarts, clients queue instead of being refused, the full API sits next to the state
it reports, and the parent stays small (no web framework, no render code: little to crash).

Stops are reported with their real reason: the `--duration` elapsed, SIGTERM, Ctrl-C, or the
supervisor itself gone (the loop process stops dark when its parent dies). A stop while the loop
process is still starting (opening devices, compiling kernels) ends it at once and idles the
projector, rather than waiting for a start-up that cannot see the request.

Shared-memory slots left by a loop process that was killed are removed after its end, and those
of any dead owner when the supervisor starts (`dpmhw.child_process.SHARED_SLOTS`).
"""

from __future__ import annotations

import contextlib
import html
import json
import logging
import multiprocessing
import multiprocessing.connection
import os
import queue
import selectors
import signal
import socket
import socketserver
import sys
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, HTTPServer
from typing import Any, Callable

import numpy as np

from dpmhw.child_process import EXIT_THREAD_EXCEPTION, SHARED_SLOTS, RestartPolicy, describe_exit
from dpmhw.session.config import SessionConfig
from dpmhw.session.heartbeat import Heartbeat

__all__ = ["ChildArgs", "FaultResponder", "Supervisor", "run_child", "status_line"]

log = logging.getLogger(__name__)

EXIT_START_FAILED = 2
KILL_WAIT_S = 5.0  # after SIGKILL, for the process to be gone (it is, unless stuck in the kernel)
# --mock: use this already running DLPC900 emulator ("address" and hex key) instead of starting one
# (tests read the device back themselves; see firmware_mocks/dlpc900_socket.py)
EMULATOR_ENV = ("DPMHW_MOCK_DLPC900_ADDRESS", "DPMHW_MOCK_DLPC900_KEY")


def status_line(status: dict) -> str:
    """One line of a session's status, as `session start` prints it every few seconds."""
    lat = status.get("latency_ms", {})
    line = (f"[{status.get('state')}] frames={status.get('frame_number')} fps={status.get('fps', 0):.1f} "
            f"(rendered {status.get('render_fps', 0):.1f}/s) "
            f"latency p50/p95/p99={lat.get('p50')}/{lat.get('p95')}/{lat.get('p99')} ms")
    api = status.get("api") or {}
    if api.get("restarts"):
        line += f" api-restarts={api['restarts']} ({api['last_exit']})"
    return line + (f" — {status['reason']}" if status.get("reason") else "")


# ---- what answers the API port while no loop process does ----------------------------------------
class _Server(socketserver.ThreadingMixIn, HTTPServer):
    """Each connection on a thread of its own (at most `max_connections`; more are closed unread),
    never waited for on shutdown."""

    daemon_threads = True
    block_on_close = False

    def __init__(self, *args, max_connections: int, **kw):
        super().__init__(*args, **kw)
        self._slots = threading.BoundedSemaphore(max_connections)

    def process_request(self, request, client_address) -> None:
        if not self._slots.acquire(blocking=False):
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def handle_error(self, request, client_address) -> None:
        if not isinstance(sys.exc_info()[1], (ConnectionError, TimeoutError)):  # a client that left or stalled
            super().handle_error(request, client_address)


# as the API's (server/app.py): JSON only here, so nothing may load or frame it
_HEADERS = (("X-Content-Type-Options", "nosniff"), ("X-Frame-Options", "DENY"),
            ("Content-Security-Policy", "default-src 'none'; frame-ancestors 'none'"))


def _down_page(status: dict) -> bytes:
    """What the operator page's address shows while no loop process serves it (compiling,
    restarting, a fault): the state and reason as text, reloaded every 2 s until the page is back."""
    state, reason = (html.escape(str(status.get(k, ""))) for k in ("state", "reason"))
    return (f'<!doctype html><html><head><meta charset="utf-8"><meta http-equiv="refresh" content="2">'
            f"<title>dpmhw: {state}</title></head><body><h1>Projector dark: {state}</h1><p>{reason}</p>"
            f"<p>This page reloads by itself; the operator page comes back when the session is up.</p>"
            f"</body></html>").encode()


class FaultResponder:
    """Minimal HTTP on the supervisor's listening socket: `/status` says `fault` (or `compiling`)
    and why, `/readyz` 503, `/livez` 200, `/` a page saying so in words, anything else 503. Serves only between `start()` and `stop()`.
    A client has `timeout_s` for each read; neither a slow client nor many of them can hold up
    `stop()` or another client (up to `max_connections` at once)."""

    def __init__(self, sock: socket.socket, *, timeout_s: float = 2.0, max_connections: int = 32):
        self.sock = sock
        self.timeout_s, self.max_connections = timeout_s, max_connections
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()
        self._lock = threading.Lock()
        self._status: dict = {}

    def set_status(self, status: dict) -> None:
        with self._lock:
            self._status = dict(status)

    def status(self) -> dict:
        with self._lock:
            return dict(self._status)

    def start(self) -> None:
        if self._thread is not None:
            return
        responder = self

        class Handler(BaseHTTPRequestHandler):
            timeout = self.timeout_s  # per read: a half-sent request times out, its thread ends

            def _answer(self) -> None:
                status = responder.status()
                path = self.path.split("?", 1)[0]
                if path == "/status" and self.command == "GET":
                    code, body = 200, status
                elif path == "/livez":
                    code, body = 200, {"live": True}
                elif path == "/readyz":
                    code, body = 503, {"ready": False, "state": status.get("state"), "reason": status.get("reason")}
                else:
                    code, body = 503, {"detail": f"the session is down: {status.get('reason', '')}"}
                kind = "application/json"
                data = json.dumps(body).encode()
                if path == "/" and self.command == "GET":  # the operator page's address: say why in words
                    kind, data = "text/html; charset=utf-8", _down_page(status)
                self.send_response(code)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(data)))
                for name, value in _HEADERS:
                    self.send_header(name, value)
                self.end_headers()
                self.wfile.write(data)

            do_GET = do_POST = do_PATCH = do_PUT = do_DELETE = do_HEAD = _answer

            def log_message(self, *args) -> None:  # quiet: the supervisor reports the fault itself
                pass

        server = _Server(self.sock.getsockname()[:2], Handler, bind_and_activate=False,
                         max_connections=self.max_connections)
        server.socket.close()  # the unbound one it made: we serve the supervisor's bound socket
        server.socket = self.sock  # (never closed here)
        # non-blocking, as the API process's server makes it anyway (the two share it): a connection
        # the other took first is no wait here
        self.sock.setblocking(False)
        halt = self._halt = threading.Event()

        def serve() -> None:
            with selectors.DefaultSelector() as selector:
                selector.register(self.sock, selectors.EVENT_READ)
                while not halt.is_set():
                    if selector.select(0.05):  # 50 ms: how often `_halt` is looked at
                        server._handle_request_noblock()  # accept (or nothing: the other took it), hand on

        self._thread = threading.Thread(target=serve, name="supervisor-fault-responder", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop answering (the socket stays open for the next loop process); never waits for a client."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._halt.set()
            thread.join(1.0)  # one poll interval; requests run on their own threads


# ---- the loop process ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ChildArgs:
    config: dict
    mock: bool
    usb: tuple[str, bytes] | None  # the out-of-process DLPC900 emulator (mock sessions)
    sock: socket.socket | None  # the API's listening socket (None: no API)
    operator_sock: socket.socket | None  # the operator's reserved one (`server.operator_port`)
    token: str
    status_every: float
    supervisor: dict  # what the status reports about the supervision (pid, starts, last crash)
    heartbeat: Heartbeat
    # called with the started loop, in the loop process (a module-level function: it is pickled by name)
    on_started: Callable[[Any], None] | None = None


class _SupervisedRuntime:
    """The loop as the API sees it, plus what the supervisor knows (restarts, last crash)."""

    def __init__(self, loop, supervisor: dict):
        self._loop, self._supervisor = loop, supervisor

    def status(self) -> dict:
        return {**self._loop.status(), "supervisor": {**self._supervisor, "loop_pid": os.getpid()}}

    def __getattr__(self, name: str) -> Any:
        return getattr(self._loop, name)


class _Relay(logging.Handler):
    """The loop process's warnings ("projection dark: …", "projection resumed") to the supervisor."""

    def __init__(self, echo: Callable[[str], None]):
        super().__init__(logging.WARNING)
        self.echo = echo

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.echo(self.format(record))
        except Exception:
            self.handleError(record)


def _fatal_thread_exception(args: threading.ExceptHookArgs) -> None:
    """An exception escaped a thread: this process can no longer be trusted to run the show.
    Exit at once; the supervisor idles the projector and decides about a restart."""
    name = args.thread.name if args.thread else "?"
    sys.stderr.write(f"fatal: exception escaped thread {name}: {args.exc_type.__name__}: {args.exc_value}\n")
    import traceback

    traceback.print_exception(args.exc_type, args.exc_value, args.exc_traceback, file=sys.stderr)
    sys.stderr.flush()
    os._exit(EXIT_THREAD_EXCEPTION)


def run_child(args: ChildArgs, conn) -> None:
    """The loop process: open devices, run the loop and the API until the supervisor says stop."""
    os.setpgrp()  # a terminal's Ctrl-C reaches the supervisor only, which stops us in order
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.excepthook = _fatal_thread_exception
    from dpmhw.errors import DpmhwError
    from dpmhw.session.factory import build_session

    stop = threading.Event()
    reason: list[str] = []

    def request(why: str) -> None:
        reason.append(why)
        stop.set()

    signal.signal(signal.SIGTERM, lambda *a: request("SIGTERM received by the loop process"))

    def listen() -> None:
        try:
            while True:
                message = conn.recv()
                if message[0] == "stop":
                    request(message[1])
                    return
        except (EOFError, OSError):
            request("the supervisor process is gone")

    config = SessionConfig.model_validate(args.config)
    send_lock = threading.Lock()

    def send(*message) -> None:
        with send_lock, contextlib.suppress(OSError):
            conn.send(message)

    def echo(text: str) -> None:
        send("line", text)

    logging.getLogger().addHandler(_Relay(echo))
    loop = api = None
    try:
        echo("opening devices, loading the scene and the render kernels …")
        loop = build_session(config, mock=args.mock, usb=args.usb, heartbeat=args.heartbeat).start()

        threading.Thread(target=lambda: loop.first_lit.wait() and send("lit", loop.first_lit_at),
                         name="first-light", daemon=True).start()
        echo(f"session started ({'mock devices' if args.mock else 'hardware'}); scene {config.scene.source}, "
             f"render {loop.parts.renderer.width}×{loop.parts.renderer.height}")
        threading.Thread(target=listen, name="supervisor-link", daemon=True).start()
        runtime = _SupervisedRuntime(loop, args.supervisor)
        if args.sock is not None:
            from server.process import ApiProcess

            api = ApiProcess(sock=args.sock, operator_sock=args.operator_sock, operator_port=None, token=args.token,
                             priority=config.api.priority).start(runtime)
            echo(f"API on {api.url} (docs at {api.url}/docs); API process pid {api.process.pid}"
                 + (f"; operator port {api.operator.url}" if api.operator is not None else ""))
        send("started", {"pid": os.getpid(), "api_pid": api.process.pid if api else None})
        if args.on_started is not None:
            args.on_started(loop)
        while not stop.wait(args.status_every or None):
            echo(status_line(runtime.status()))
    except (DpmhwError, OSError, RuntimeError) as exc:
        echo(f"error: {exc}")
        request(f"start-up failed: {exc}")
        if loop is None:
            send("failed", str(exc))
            os._exit(EXIT_START_FAILED)
    finally:
        if loop is not None:
            how = loop.stop(reason[0] if reason else "stopped")
            if api is not None:
                api.publish()  # the last status (stopped, dark) for anyone still asking
            echo(status_line(loop.status()))
            echo(f"projector dark ({how or 'no projector'})")
        if api is not None:
            api.close()


class _Link:
    """The loop process's messages, and then its end, as events on a queue. Read on a thread of
    its own: a message half-sent by a process that was stopped mid-write holds only that thread."""

    def __init__(self, child, conn, heartbeat: Heartbeat):
        self.child, self.conn, self.heartbeat = child, conn, heartbeat
        self.events: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        threading.Thread(target=self._read, name="supervisor-relay", daemon=True).start()

    def _read(self) -> None:
        try:
            watched = [self.child.sentinel, self.conn]
            while watched:
                ready = multiprocessing.connection.wait(watched)
                if self.conn in ready:
                    try:
                        self.events.put(self.conn.recv())
                        continue
                    except (EOFError, OSError):  # it closed its end: it is ending
                        watched = [self.child.sentinel]
                        continue
                if self.child.sentinel in ready:  # gone: what it sent before is all in the pipe
                    with contextlib.suppress(EOFError, OSError):
                        while self.conn in watched and self.conn.poll(0):
                            self.events.put(self.conn.recv())
                    break
        finally:  # (the pipe is closed with the link: the main thread may still send "stop" on it)
            self.events.put(("exited", None))

    def get(self, timeout_s: float) -> tuple[str | None, Any]:
        try:
            return self.events.get(timeout=max(0.0, timeout_s))
        except queue.Empty:
            return None, None


# ---- the supervising parent ---------------------------------------------------------------------
def _process_age_s() -> float:
    """Seconds since this process started (its imports included), 0 where /proc cannot tell."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return 0.0


class Supervisor:
    """Runs the session in a child process and keeps the projector dark whenever it is down or hung.
    `on_loop_started` (a module-level function, called in the loop process with the started loop)
    lets a caller add to the loop process, e.g. the tests' injected faults."""

    def __init__(self, config: SessionConfig, *, mock: bool = False, token: str = "",
                 sock: socket.socket | None = None, operator_sock: socket.socket | None = None,
                 duration: float | None = None, status_every: float = 2.0,
                 echo: Callable[[str], None] = print, stop_timeout_s: float = 30.0,
                 idle_timeout_s: float = 10.0, on_loop_started: Callable[[Any], None] | None = None):
        self.config, self.mock, self.token, self.sock = config, mock, token, sock
        self.duration, self.status_every, self.echo = duration, status_every, echo
        self.stop_timeout_s, self.idle_timeout_s = stop_timeout_s, idle_timeout_s
        self.on_loop_started = on_loop_started
        s = config.safety
        self.policy = RestartPolicy(s.restart_limit if s.restart == "on-crash" else 0, s.restart_window_s,
                                    s.restart_backoff_s)
        # what answers the API port and the operator's while no loop process does
        self.responders = [FaultResponder(s) for s in (sock, operator_sock) if s is not None]
        self.operator_sock = operator_sock
        self.emulator = None
        self.usb: tuple[str, bytes] | None = None
        self.starts = 0
        self.crashes = 0
        self.last_crash = ""
        self._stop = threading.Event()
        self._stop_reason = ""
        self._deadline: float | None = None
        self._window = None
        self._idle_job: Future | None = None  # the idle attempt in flight (at most one)
        self._unconfirmed = ""  # what left the projector without a confirmed dark (retried)
        self._t_start = time.monotonic() - _process_age_s()  # when the command started
        self._loop_started: float | None = None
        self._first_lit: float | None = None
        self.compile_s = 0.0

    def request_stop(self, reason: str) -> None:
        if not self._stop.is_set():
            self._stop_reason = reason
            self._stop.set()

    # ---- the whole show ------------------------------------------------------------------------
    def run(self) -> int:
        """Until stopped (duration, SIGTERM, Ctrl-C) or a start-up failure; returns the exit code."""
        from dpmhw.session import factory

        previous = {sig: signal.signal(sig, handler) for sig, handler in (
            (signal.SIGTERM, lambda *a: self.request_stop("SIGTERM received")),
            (signal.SIGINT, lambda *a: self.request_stop("interrupted (Ctrl-C)")))}
        code = 0
        try:
            SHARED_SLOTS.sweep()  # what loop processes of an earlier show left when they were killed
            if self.mock and self.config.projector.kind == "dlpc900":
                address, key = (os.environ.get(name, "") for name in EMULATOR_ENV)
                if address:
                    self.usb = (address, bytes.fromhex(key))
                else:
                    self.emulator = factory.start_usb_emulator(self.config)
                    self.usb = (self.emulator.address, self.emulator.authkey)
            try:  # pre-flight: our own way to the projector works (and its code is loaded) before the show
                self._idle_attempt(self.idle_timeout_s)
            except Exception as exc:
                self.echo(f"supervisor: warning: cannot reach the projector to idle it ({exc or type(exc).__name__}); "
                          "after a crash of the loop process it may not be made dark")
            if not self._ready_kernels():
                return 0
            while True:
                child, link = self._start_child()
                outcome, what = self._watch(child, link)
                SHARED_SLOTS.sweep()  # the slots of a loop process that could not close them
                if outcome == "stopped":
                    break
                if outcome == "failed" and self.starts == 1:  # it printed why (a config or device error)
                    if child.exitcode != EXIT_START_FAILED:  # died while opening the devices: make sure
                        self.echo(f"supervisor: the loop process {describe_exit(child.exitcode)} while starting; "
                                  f"projector {self._make_dark('a failed start')}")
                    return EXIT_START_FAILED
                wait_s = self._after_crash(what)
                if wait_s is None or self._stop.wait(wait_s) or self._deadline_passed():
                    code = 1  # the show ended dark after a crash
                    self._stay_dark()
                    break
                self.echo(f"restarting the loop process (restart {self.starts} of at most "
                          f"{self.policy.limit} within {self.policy.window_s:g} s)")
            return code
        finally:
            if self._stop_reason:
                self.echo(f"supervisor: stopped ({self._stop_reason})")
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            self._close_window()
            for responder in self.responders:
                responder.stop()
            if self.emulator is not None:
                self.emulator.close()

    def _ready_kernels(self) -> bool:
        """Compile the session's kernels in worker processes before the loop process starts (a
        first run on this machine), with progress on the console and `/status`; False if stopped
        meanwhile. The loop process then loads them from the cache in seconds."""
        from dpmhw.session.warmup import compile_kernels

        self._serve_status("starting", "the session is starting")  # the port says why it is dark from the start
        printed = -1e9

        def show(p) -> None:
            nonlocal printed
            if p.warm:
                return
            now = time.monotonic()
            if now - printed >= 5.0 or not p.groups_left:  # a line every 5 s, and the last
                printed = now
                self.echo(p.line())
            self._serve_status("compiling", p.line(), compile=p.as_status())

        result = compile_kernels(self.config, progress=show, should_stop=self._stop.is_set)
        for group, why in result.failed.items():
            self.echo(f"supervisor: compiling the {group} kernels ahead failed ({why}); the loop process compiles them")
        self.compile_s = 0.0 if result.warm else result.elapsed_s
        return not result.stopped

    def _deadline_passed(self) -> bool:
        """The --duration counts from the first lit frame; a show that never lights ends
        `duration` after its loop process started."""
        if self._deadline is not None and time.monotonic() >= self._deadline:
            self.request_stop(f"the --duration of {self.duration:g} s elapsed")
        return self._stop.is_set()

    def _start_child(self):
        self.starts += 1
        ctx = multiprocessing.get_context("spawn")
        ours, theirs = ctx.Pipe()
        args = ChildArgs(self.config.model_dump(), self.mock, self.usb, self.sock, self.operator_sock, self.token,
                         self.status_every,
                         {"pid": os.getpid(), "starts": self.starts, "crashes": self.crashes,
                          "last_crash": self.last_crash, "restart": self.config.safety.restart},
                         Heartbeat(), self.on_loop_started)
        child = ctx.Process(target=run_child, args=(args, theirs), name="dpmhw-loop")
        child.start()
        theirs.close()
        self._close_window()
        if self.starts > 1 and self.responders:
            self._report_fault(f"{self.last_crash}; restarting: loop process pid {child.pid} is starting")
        self.echo(f"loop process pid {child.pid} (start {self.starts})")
        return child, _Link(child, ours, args.heartbeat)

    def _receive(self, kind: str, payload: Any) -> None:
        """Handle one message of the loop process."""
        if kind == "line":  # its output: relayed, so that one process writes the session's lines
            self.echo(payload)
        elif kind == "started":
            if self._loop_started is None:
                self._loop_started = time.monotonic()
                self._set_deadline()
            for responder in self.responders:
                responder.stop()  # the loop process's own API serves the ports now
        elif kind == "lit" and self._first_lit is None:
            self._first_lit = payload
            compiled = f", {self.compile_s:.1f} s of it compiling the render kernels" if self.compile_s else ""
            self.echo(f"first lit frame {payload - self._t_start:.1f} s after the command started{compiled}"
                      + (f"; showing for {self.duration:g} s" if self.duration is not None else ""))
            self._set_deadline()

    def _set_deadline(self) -> None:
        """The --duration counts from the first lit frame, or from the loop's start while none came."""
        start = self._first_lit if self._first_lit is not None else self._loop_started
        if self.duration is not None and start is not None:
            self._deadline = start + self.duration

    def _until_exit(self, child, link: _Link, timeout_s: float) -> bool:
        """Relay its messages until the loop process has exited (True) or `timeout_s` passed."""
        deadline = time.monotonic() + timeout_s
        while True:
            kind, payload = link.get(deadline - time.monotonic())
            if kind == "exited":
                child.join(KILL_WAIT_S)  # it is gone: reaped at once
                return True
            if kind is None:
                return False
            self._receive(kind, payload)

    def _watch(self, child, link: _Link) -> tuple[str, str]:
        """Until the child ends, hangs or a stop is asked for; returns ("stopped" | "failed" |
        "crashed", what happened to it)."""
        started = False
        while True:
            timeout_s = 0.1  # how often a stop and the --duration are looked at
            if started:
                hung, due_ns = link.heartbeat.overdue(time.monotonic_ns())
                if hung:
                    return "crashed", self._kill_hung(child, link, hung)
                timeout_s = min(timeout_s, due_ns / 1e9 + 0.001)
            kind, payload = link.get(timeout_s)
            if kind == "exited":
                child.join(KILL_WAIT_S)
                if child.exitcode == 0 and self._stop.is_set():
                    return "stopped", ""
                return ("crashed" if started else "failed"), f"the loop process (pid {child.pid}) {describe_exit(child.exitcode)}"
            if kind is not None:
                started = started or kind in ("started", "lit")  # lit: its link listens and its heartbeat runs
                self._receive(kind, payload)
            if self._deadline_passed():
                return self._stop_child(child, link, started), ""

    def _kill_hung(self, child, link: _Link, why: str) -> str:
        """A hung loop process may still drive the projector: SIGKILL it (its USB claim goes with it)."""
        t0 = time.monotonic()
        self.echo(f"supervisor: the loop process (pid {child.pid}) is hung: {why}; killing it")
        child.kill()
        if not self._until_exit(child, link, KILL_WAIT_S):
            self.echo(f"supervisor: the loop process (pid {child.pid}) outlived SIGKILL by {KILL_WAIT_S:g} s")
        self.echo(f"supervisor: the hung loop process was gone {(time.monotonic() - t0) * 1e3:.0f} ms after the kill")
        return f"the loop process (pid {child.pid}) hung ({why}) and was {describe_exit(child.exitcode)}"

    def _stop_child(self, child, link: _Link, started: bool) -> str:
        if not started:  # it cannot see a request before its start-up returns: end it now
            self.echo(f"supervisor: stopping ({self._stop_reason}) while the loop process is still starting "
                      "(opening devices, loading the scene, compiling kernels): ending it")
            child.kill()
            self._until_exit(child, link, KILL_WAIT_S)
            self.echo(f"supervisor: projector {self._make_dark('a stop during start-up')}")
            return "stopped"
        self.echo(f"supervisor: stopping ({self._stop_reason}): asking the loop process to stop dark")
        with contextlib.suppress(OSError):
            link.conn.send(("stop", self._stop_reason))
        if not self._until_exit(child, link, self.stop_timeout_s):
            self.echo(f"supervisor: the loop process did not stop within {self.stop_timeout_s:g} s; killing it")
            child.kill()
            self._until_exit(child, link, KILL_WAIT_S)
        if child.exitcode != 0:
            what = f"the loop process {describe_exit(child.exitcode)} while stopping"
            self.echo(f"supervisor: {what}; projector {self._make_dark(what)}")
        return "stopped"

    # ---- a crash -------------------------------------------------------------------------------
    def _after_crash(self, what: str) -> float | None:
        """Dark first, then report; returns the wait before a restart, or None to stay dark."""
        t_seen = time.monotonic()
        self.crashes += 1
        self.last_crash = what
        self.echo(f"supervisor: {what}")
        how = self._make_dark(what)
        dark_ms = (time.monotonic() - t_seen) * 1e3
        self.echo(f"supervisor: projector {how} {dark_ms:.0f} ms after the loop process was seen gone")
        wait_s = self.policy.crashed(time.monotonic())
        if wait_s is None:
            plan = ("staying dark (safety.restart = \"never\")" if self.config.safety.restart == "never" else
                    f"staying dark: {self.policy.limit} restart(s) within {self.policy.window_s:g} s used up")
        else:
            plan = f"restarting in {wait_s:g} s"
        self.echo(f"supervisor: {plan}")
        self._report_fault(f"{what}; projector {how}; {plan}")
        if self.config.sink.kind == "window" and not self.mock:
            from dpmhw.session import factory

            try:
                self._window = factory.open_black_window(self.config, self.mock)
            except Exception as exc:
                self.echo(f"supervisor: cannot open a black window on display {self.config.sink.display}: {exc}")
        return wait_s

    def _make_dark(self, what: str) -> str:
        """Idle the projector and confirm by read-back, retrying until `idle_timeout_s`; returns
        "dark (idle, read back)" or "NOT confirmed dark (why)" (then `_stay_dark` keeps trying).
        Each attempt runs on a thread of its own: a device that never answers costs the deadline."""
        deadline = time.monotonic() + self.idle_timeout_s
        while True:
            try:
                how = f"dark ({self._idle_attempt(deadline - time.monotonic())}, read back)"
                self._unconfirmed = ""
                return how
            except Exception as exc:
                why = (f"no answer within {self.idle_timeout_s:g} s" if isinstance(exc, TimeoutError)
                       else str(exc) or type(exc).__name__)
                if time.monotonic() >= deadline:
                    self.echo(f"supervisor: CANNOT CONFIRM THE PROJECTOR IS DARK after {what}: {why}")
                    self._unconfirmed = what
                    return f"NOT confirmed dark ({why})"
                time.sleep(min(0.1, max(0.0, deadline - time.monotonic())))

    def _idle_attempt(self, timeout_s: float) -> str:
        """`factory.idle_projector` on a daemon thread, waited for `timeout_s` (TimeoutError). An
        attempt still blocked is waited for again rather than joined by a second one."""
        from dpmhw.session import factory

        job = self._idle_job
        if job is None or job.done():
            job = self._idle_job = Future()

            def attempt() -> None:
                try:
                    job.set_result(factory.idle_projector(self.config, self.usb))
                except BaseException as exc:
                    job.set_exception(exc)

            threading.Thread(target=attempt, name="supervisor-idle", daemon=True).start()
        return job.result(timeout=max(0.0, timeout_s))

    def _report_fault(self, reason: str) -> None:
        self._serve_status("fault", reason)

    def _serve_status(self, state: str, reason: str, **extra) -> None:
        """What the API and operator ports answer while no loop process serves them (starting, compiling, a fault)."""
        status = {"state": state, "reason": reason, "output_on": False, **extra,
                  "supervisor": {"pid": os.getpid(), "starts": self.starts, "crashes": self.crashes,
                                 "last_crash": self.last_crash, "restart": self.config.safety.restart, "loop_pid": None}}
        for responder in self.responders:
            responder.set_status(status)
            responder.start()

    def _stay_dark(self) -> None:
        """No more restarts: keep reporting the fault (and the black window) until stopped."""
        while not self._stop.wait(0.5) and not self._deadline_passed():
            if self._unconfirmed:
                how = self._make_dark(self._unconfirmed)
                self._report_fault(f"{self.last_crash}; projector {how}; staying dark")
            if self._window is not None:  # redraw: keeps the window on top and answering its manager
                with contextlib.suppress(Exception):
                    self._window.present(np.zeros((*self._window.shape, 3), np.uint8), time.monotonic_ns())

    def _close_window(self) -> None:
        window, self._window = self._window, None
        if window is not None:
            with contextlib.suppress(Exception):
                window.close()
