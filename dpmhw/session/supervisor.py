"""A thin supervising parent for a session: the loop runs in a child process, so that no way of
ending that process (SIGKILL, a segfault in native code, the OOM killer, an exception escaping a
thread) leaves the projector lit.

    Supervisor(config, mock=True, echo=print).run()     # what `dpmhw session start` does

The parent imports little and does little: it binds the API port, starts the loop process
(`run_child`), and waits. When the child ends without being asked to, the parent

- idles the projector over USB itself (the kernel freed the device with the child) and confirms
  it by read-back (`factory.idle_projector`), retrying until it is confirmed;
- puts a black full-screen window on the projector's display if the session used one;
- logs the exit status or the signal;
- answers `/status` with `fault` and the reason on the API port (`FaultResponder`) while no
  loop process serves it;
- restarts the loop process if `safety.restart = "on-crash"` (`RestartPolicy`: backoff, and at
  most `restart_limit` restarts within `restart_window_s`), else stays dark until stopped.

Who holds the API port: the parent binds it once and keeps it for the whole show; each loop
process receives a copy and serves the full API from its own API process (server/process.py,
which also restarts that one if it dies). So the port is never free for another program to take
between restarts, clients queue instead of being refused, the full API sits next to the state
it reports, and the parent stays small (no web framework, no render code: little to crash).

Stops are reported with their real reason: the `--duration` elapsed, SIGTERM, Ctrl-C, or the
supervisor itself gone (the loop process stops dark when its parent dies).
"""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import socket
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, HTTPServer
from typing import Any, Callable

import numpy as np

from dpmhw.session.config import SessionConfig

__all__ = ["FaultResponder", "RestartPolicy", "Supervisor", "describe_exit", "run_child", "status_line"]

log = logging.getLogger(__name__)

EXIT_THREAD_EXCEPTION = 70  # EX_SOFTWARE: an exception escaped a thread of the loop process
EXIT_START_FAILED = 2
FAULT_ENV = "DPMHW_TEST_FAULT"  # tests only: "loop-exception" or "abort" once a frame was shown
# --mock: use this already running DLPC900 emulator ("address" and hex key) instead of starting one
# (tests read the device back themselves; see firmware_mocks/dlpc900_socket.py)
EMULATOR_ENV = ("DPMHW_MOCK_DLPC900_ADDRESS", "DPMHW_MOCK_DLPC900_KEY")


def describe_exit(exitcode: int | None) -> str:
    """A process's end in words: `exited with code 70`, `killed by SIGKILL`."""
    if exitcode is None:
        return "still running"
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    if exitcode == EXIT_THREAD_EXCEPTION:
        return f"exited with code {exitcode} (an exception escaped one of its threads)"
    return f"exited with code {exitcode}"


def status_line(status: dict) -> str:
    """One line of a session's status, as `session start` prints it every few seconds."""
    lat = status.get("latency_ms", {})
    line = (f"[{status.get('state')}] frames={status.get('frame_number')} fps={status.get('fps', 0):.1f} "
            f"latency p50/p95/p99={lat.get('p50')}/{lat.get('p95')}/{lat.get('p99')} ms")
    api = status.get("api") or {}
    if api.get("restarts"):
        line += f" api-restarts={api['restarts']} ({api['last_exit']})"
    return line + (f" — {status['reason']}" if status.get("reason") else "")


def _process_age_s() -> float:
    """Seconds since this process started (its imports included), 0 where /proc cannot tell."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return 0.0


class RestartPolicy:
    """When to restart after a crash: at most `limit` restarts within `window_s`, each after a
    backoff that doubles with every crash still inside the window. Pure; the clock is given."""

    def __init__(self, limit: int, window_s: float, backoff_s: float):
        self.limit, self.window_s, self.backoff_s = limit, window_s, backoff_s
        self._crashes: deque[float] = deque()

    def crashed(self, now_s: float) -> float | None:
        """Record a crash at `now_s`; returns the seconds to wait before restarting, or None: give up."""
        self._crashes.append(now_s)
        while self._crashes and now_s - self._crashes[0] > self.window_s:
            self._crashes.popleft()
        restarts = len(self._crashes)  # the restart this crash would cost
        if restarts > self.limit:
            return None
        return self.backoff_s * 2 ** (restarts - 1)


# ---- what answers the API port while no loop process does ----------------------------------------
class _Server(HTTPServer):
    def handle_error(self, request, client_address) -> None:
        if not isinstance(sys.exc_info()[1], ConnectionError):  # a client that left is no error
            super().handle_error(request, client_address)


class FaultResponder:
    """Minimal HTTP on the supervisor's listening socket: `/status` says `fault` and why,
    `/readyz` 503, `/livez` 200, anything else 503. Serves only between `start()` and `stop()`."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self._server: HTTPServer | None = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._status: dict = {}

    def set_status(self, status: dict) -> None:
        with self._lock:
            self._status = dict(status)

    def status(self) -> dict:
        with self._lock:
            return dict(self._status)

    def start(self) -> None:
        if self._server is not None:
            return
        responder = self

        class Handler(BaseHTTPRequestHandler):
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
                data = json.dumps(body).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            do_GET = do_POST = do_PATCH = do_PUT = do_DELETE = do_HEAD = _answer

            def log_message(self, *args) -> None:  # quiet: the supervisor reports the fault itself
                pass

        server = _Server(self.sock.getsockname()[:2], Handler, bind_and_activate=False)
        server.socket.close()  # the unbound one it made: we serve the supervisor's bound socket
        server.socket = self.sock  # (never closed here)
        server.timeout = 2.0
        self._server = server
        self._thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05},
                                        name="supervisor-fault-responder", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop answering (the socket stays open for the next loop process)."""
        server, self._server = self._server, None
        if server is not None:
            server.shutdown()
            self._thread.join(5)


# ---- the loop process ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ChildArgs:
    config: dict
    mock: bool
    usb: tuple[str, bytes] | None  # the out-of-process DLPC900 emulator (mock sessions)
    sock: socket.socket | None  # the API's listening socket (None: no API)
    token: str
    status_every: float
    supervisor: dict  # what the status reports about the supervision (pid, starts, last crash)


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


def _inject_fault(loop, kind: str) -> None:
    """Tests: crash this process the way `kind` says once the loop has presented a frame."""
    def arm() -> None:
        while loop.status().get("frame_number", 0) < 1:
            time.sleep(0.01)
        # CLOCK_MONOTONIC is one clock for every process: the test measures time to dark from here
        sys.stderr.write(f"injected {kind} at monotonic_ns {time.monotonic_ns()}\n")
        sys.stderr.flush()
        if kind == "abort":
            os.abort()  # SIGABRT, as a native crash would end the process
        publish = loop._publish

        def failing(force: bool = False) -> None:
            loop._publish = publish
            raise RuntimeError("injected: an exception escaping the loop thread")

        loop._publish = failing  # called outside the loop's per-iteration try

    threading.Thread(target=arm, name="test-fault", daemon=True).start()


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
        loop = build_session(config, mock=args.mock, usb=args.usb).start()

        def first_light() -> None:
            while not stop.is_set():
                if loop.first_lit.wait(0.1):
                    send("lit", loop.first_lit_at)
                    return

        threading.Thread(target=first_light, name="first-light", daemon=True).start()
        echo(f"session started ({'mock devices' if args.mock else 'hardware'}); scene {config.scene.source}, "
             f"render {loop.parts.renderer.width}×{loop.parts.renderer.height}")
        threading.Thread(target=listen, name="supervisor-link", daemon=True).start()
        runtime = _SupervisedRuntime(loop, args.supervisor)
        if args.sock is not None:
            from server.process import ApiProcess

            api = ApiProcess(sock=args.sock, token=args.token, priority=config.api.priority).start(runtime)
            echo(f"API on {api.url} (docs at {api.url}/docs); API process pid {api.process.pid}")
        send("started", {"pid": os.getpid(), "api_pid": api.process.pid if api else None})
        if os.environ.get(FAULT_ENV):
            _inject_fault(loop, os.environ[FAULT_ENV])
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


# ---- the supervising parent ---------------------------------------------------------------------
class Supervisor:
    """Runs the session in a child process and keeps the projector dark whenever it is down."""

    def __init__(self, config: SessionConfig, *, mock: bool = False, token: str = "",
                 sock: socket.socket | None = None, duration: float | None = None, status_every: float = 2.0,
                 echo: Callable[[str], None] = print, stop_timeout_s: float = 30.0,
                 idle_timeout_s: float = 10.0):
        self.config, self.mock, self.token, self.sock = config, mock, token, sock
        self.duration, self.status_every, self.echo = duration, status_every, echo
        self.stop_timeout_s, self.idle_timeout_s = stop_timeout_s, idle_timeout_s
        s = config.safety
        self.policy = RestartPolicy(s.restart_limit if s.restart == "on-crash" else 0, s.restart_window_s,
                                    s.restart_backoff_s)
        self.responder = FaultResponder(sock) if sock is not None else None
        self.emulator = None
        self.usb: tuple[str, bytes] | None = None
        self.starts = 0
        self.crashes = 0
        self.last_crash = ""
        self._stop = threading.Event()
        self._stop_reason = ""
        self._deadline: float | None = None
        self._window = None
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
            if self.mock and self.config.projector.kind == "dlpc900":
                address, key = (os.environ.get(name, "") for name in EMULATOR_ENV)
                if address:
                    self.usb = (address, bytes.fromhex(key))
                else:
                    self.emulator = factory.start_usb_emulator(self.config)
                    self.usb = (self.emulator.address, self.emulator.authkey)
            try:  # pre-flight: our own way to the projector works (and its code is loaded) before the show
                factory.idle_projector(self.config, self.usb)
            except Exception as exc:
                self.echo(f"supervisor: warning: cannot reach the projector to idle it ({exc}); "
                          "after a crash of the loop process it may not be made dark")
            if not self._ready_kernels():
                return 0
            while True:
                child, conn = self._start_child()
                outcome = self._watch(child, conn)
                if outcome == "stopped":
                    break
                if outcome == "failed" and self.starts == 1:  # it printed why (a config or device error)
                    if child.exitcode != EXIT_START_FAILED:  # died while opening the devices: make sure
                        self.echo(f"supervisor: the loop process {describe_exit(child.exitcode)} while starting; "
                                  f"projector {self._make_dark('a failed start')}")
                    return EXIT_START_FAILED
                wait_s = self._after_crash(child)
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
            if self.responder is not None:
                self.responder.stop()
            if self.emulator is not None:
                self.emulator.close()

    def _ready_kernels(self) -> bool:
        """Compile the session's kernels in worker processes before the loop process starts (a
        first run on this machine), with progress on the console and `/status`; False if stopped
        meanwhile. The loop process then loads them from the cache in seconds."""
        from dpmhw.session.warmup import compile_kernels

        printed = [-1e9]

        def show(p) -> None:
            if p.warm:
                return
            now = time.monotonic()
            if now - printed[0] >= 5.0 or not p.groups_left:  # a line every 5 s, and the last
                printed[0] = now
                self.echo(p.line())
            if self.responder is not None:
                self.responder.set_status({"state": "compiling", "reason": p.line(), "output_on": False,
                                           "compile": p.as_status(), "supervisor": {"pid": os.getpid(), "starts": 0}})
                self.responder.start()

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
        args = ChildArgs(self.config.model_dump(), self.mock, self.usb, self.sock, self.token, self.status_every,
                         {"pid": os.getpid(), "starts": self.starts, "crashes": self.crashes,
                          "last_crash": self.last_crash, "restart": self.config.safety.restart})
        child = ctx.Process(target=run_child, args=(args, theirs), name="dpmhw-loop")
        child.start()
        theirs.close()
        self._close_window()
        if self.starts > 1 and self.responder is not None:
            self._report_fault(f"{self.last_crash}; restarting: loop process pid {child.pid} is starting")
        self.echo(f"loop process pid {child.pid} (start {self.starts})")
        return child, ours

    def _receive(self, conn) -> str | None:
        """Handle one message of the loop process; returns its kind (None: the pipe closed)."""
        try:
            kind, payload = conn.recv()
        except (EOFError, OSError):
            return None
        if kind == "line":  # its output: relayed, so that one process writes the session's lines
            self.echo(payload)
        elif kind == "started":
            if self._loop_started is None:
                self._loop_started = time.monotonic()
                self._set_deadline()
            if self.responder is not None:
                self.responder.stop()  # the loop process's own API serves the port now
        elif kind == "lit" and self._first_lit is None:
            self._first_lit = payload
            compiled = f", {self.compile_s:.1f} s of it compiling the render kernels" if self.compile_s else ""
            self.echo(f"first lit frame {payload - self._t_start:.1f} s after the command started{compiled}"
                      + (f"; showing for {self.duration:g} s" if self.duration is not None else ""))
            self._set_deadline()
        return kind

    def _set_deadline(self) -> None:
        """The --duration counts from the first lit frame, or from the loop's start while none came."""
        if self.duration is not None and self._loop_started is not None:
            self._deadline = (self._first_lit if self._first_lit is not None else self._loop_started) + self.duration

    def _relay_until_exit(self, child, conn, timeout_s: float) -> None:
        """Relay its messages until the loop process has exited (or `timeout_s`), then the rest."""
        deadline = time.monotonic() + timeout_s
        while child.is_alive() and time.monotonic() < deadline:
            if conn in multiprocessing.connection.wait([child.sentinel, conn], timeout=0.1):
                if self._receive(conn) is None:
                    child.join(max(0.0, deadline - time.monotonic()))
                    break
        while not child.is_alive() and conn.poll(0):
            if self._receive(conn) is None:
                break

    def _watch(self, child, conn) -> str:
        """Wait for the child to end or for a stop; returns "stopped", "failed" or "crashed"."""
        started = False
        while True:
            if conn in multiprocessing.connection.wait([child.sentinel, conn], timeout=0.1):
                kind = self._receive(conn)
                started = started or kind == "started"
                if kind is None:  # it is ending
                    child.join(self.stop_timeout_s)
            if not child.is_alive():
                self._relay_until_exit(child, conn, 0.0)
                child.join(5)
                conn.close()
                if child.exitcode == 0 and self._stop.is_set():
                    return "stopped"
                return "crashed" if started else "failed"
            if self._deadline_passed():
                return self._stop_child(child, conn)

    def _stop_child(self, child, conn) -> str:
        with contextlib.suppress(OSError):
            conn.send(("stop", self._stop_reason))
        self._relay_until_exit(child, conn, self.stop_timeout_s)
        if child.is_alive():
            self.echo(f"supervisor: the loop process did not stop within {self.stop_timeout_s:g} s; killing it")
            child.kill()
            child.join(5)
        conn.close()
        if child.exitcode != 0:
            what = f"the loop process {describe_exit(child.exitcode)} while stopping"
            self.echo(f"supervisor: {what}; projector {self._make_dark(what)}")
        return "stopped"

    # ---- a crash -------------------------------------------------------------------------------
    def _after_crash(self, child) -> float | None:
        """Dark first, then report; returns the wait before a restart, or None to stay dark."""
        t_seen = time.monotonic()
        self.crashes += 1
        what = f"the loop process (pid {child.pid}) {describe_exit(child.exitcode)}"
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
        "dark (idle, read back)" or "NOT confirmed dark (why)" (then `_stay_dark` keeps trying)."""
        from dpmhw.session import factory

        deadline = time.monotonic() + self.idle_timeout_s
        while True:
            try:
                how = f"dark ({factory.idle_projector(self.config, self.usb)}, read back)"
                self._unconfirmed = ""
                return how
            except Exception as exc:
                if time.monotonic() >= deadline:
                    self.echo(f"supervisor: CANNOT CONFIRM THE PROJECTOR IS DARK after {what}: {exc}")
                    self._unconfirmed = what
                    return f"NOT confirmed dark ({exc})"
                time.sleep(0.1)

    def _report_fault(self, reason: str) -> None:
        if self.responder is None:
            return
        self.responder.set_status({
            "state": "fault", "reason": reason, "output_on": False,
            "supervisor": {"pid": os.getpid(), "starts": self.starts, "crashes": self.crashes,
                           "last_crash": self.last_crash, "restart": self.config.safety.restart, "loop_pid": None},
        })
        self.responder.start()

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
