"""The HTTP service in its own process, so that no request can take the session's interpreter lock.

    api = ApiProcess(host="127.0.0.1", port=8765, token="…")    # binds (a busy port fails here)
    with api.start(loop):
        print(api.url)                                           # serving until the block ends

The session process (this one) owns the devices and the loop. A publisher thread here copies the
loop's status (every `publish_period_s`, and at once after a command) and its latest frame into
two shared-memory slots (`shared_slot.py`); the API process answers reads from those slots alone,
and sends the few mutating requests (settings, resume, reset-history) over a pipe to a command
thread here, which applies them exactly as an in-process request would; the operator's blank has
a pipe and a thread of its own, so no other command is ever queued ahead of it. The work this
process does for the service is therefore bounded whatever the request load: one publish per
period, plus one per blank or resume (whose reply reports the new state). A settings change is
published with the next period (the API process answers its sender's own reads from the
accepted settings meanwhile). A settings patch that changes no value is
answered by the API process without a command; the other commands but blank are limited to
`commands_per_s` (bursts of `command_burst`; beyond: 429 with Retry-After), so a command storm
cannot make the loop publish more; the blank is never limited. What each client can hold in the
API process (connections, time, header size) is bounded by `server.guard` (`limits`). The API
process runs at a lower CPU priority (by default Linux's SCHED_IDLE: it gets the CPU time the
loop leaves idle, so requests wait for the loop rather than the other way round).

The operator's reserved port (`server.operator_port`, `operator_port`/`operator_sock`) is served
by threads of this process, not the API process: its blank is executed as the blank pipe's is, on
its own thread, and its status is the last one published. So blank and status stay reachable
whatever the API process's load, priority or state (restarting, stopped).

If the session process stops publishing (wedged, or gone), the API process keeps answering and
reports `fault` with the age of the last snapshot; it exits by itself when this process dies.

If the API process dies (killed, crashed), a keeper thread here starts a new one on the same
listening socket (still bound: clients queue rather than being refused) after a backoff
(`restart_backoff_s`, doubling up to `restart_backoff_max_s`; back to the start once the last
crash is `stable_after_s` old: `dpmhw.child_process.RestartPolicy`). The loop never notices: an
API crash costs the show no frame. The status says how often this happened and why
(`status["api"]`).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import socket
import threading
import time
from typing import Any

import numpy as np

from dpmhw.child_process import RestartPolicy, describe_exit, stop_process
from dpmhw.session.config import LiveSettings
from dpmhw.session.loop import LatestFrame, SettingsError
from server.app import trusted_hosts_for
from server.deps import Runtime, RuntimeBusy, RuntimeUnavailable
from server.guard import ConnectionLimits, TokenBucket
from server.operator_port import OperatorListener
from server.routers.status import public_status
from server.shared_slot import SharedSlot, SlotTornError

__all__ = ["ApiProcess", "RemoteRuntime", "bind_api_socket", "lower_priority"]

_MISSING = object()  # a field the settings lack (never equal to a value)

log = logging.getLogger(__name__)

_COMMANDS = ("update_settings", "blank", "resume", "reset_history")
_PUBLISH_AT_ONCE = ("blank", "resume")  # their replies say the state they led to
_PRIORITIES = ("idle", "low", "normal")


def lower_priority(priority: str) -> str:
    """Lower this process's CPU priority; returns what was applied (SCHED_IDLE needs Linux)."""
    if priority == "idle" and hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            return "SCHED_IDLE"
        except OSError:
            priority = "low"
    if priority in ("idle", "low"):
        os.nice(19 if priority == "idle" else 10)
        return f"nice {os.nice(0)}"
    return "normal"


class ApiProcess:
    """Serve a runtime (a started `SessionLoop`) over HTTP from a child process; see module doc."""

    def __init__(self, *, host: str = "127.0.0.1", port: int = 8765, token: str = "", priority: str = "idle",
                 publish_period_s: float = 0.05, stale_after_s: float = 1.0, status_capacity: int = 1 << 20,
                 start_timeout_s: float = 60.0, restart_backoff_s: float = 0.5, restart_backoff_max_s: float = 8.0,
                 stable_after_s: float = 30.0, sock: socket.socket | None = None,
                 limits: ConnectionLimits | None = None, commands_per_s: float = 20.0, command_burst: int = 10,
                 operator_port: int | None = 0, operator_sock: socket.socket | None = None):
        self.runtime: Runtime | None = None
        self.token = token
        if priority not in _PRIORITIES:
            raise ValueError(f"API process priority must be one of {', '.join(_PRIORITIES)}, not {priority!r}")
        self.priority = priority
        self.publish_period_s = publish_period_s
        self.stale_after_s = stale_after_s
        self.start_timeout_s = start_timeout_s
        self.restart_backoff_s, self.restart_backoff_max_s = restart_backoff_s, restart_backoff_max_s
        self.stable_after_s = stable_after_s
        self.limits = limits or ConnectionLimits()
        self.command_rate = (commands_per_s, command_burst)
        # bound here (or by the caller, who keeps it across sessions): a busy port fails in the
        # caller with the OS's message, and port 0 is resolved
        self.sock = sock if sock is not None else bind_api_socket(host, port)
        self.host, self.port = self.sock.getsockname()[:2]
        # the Host names clients may use: the bound address too, so a lab-network bind works as is
        self.trusted_hosts = trusted_hosts_for(self.host)
        # the operator's reserved listener (`server.operator_port`), on the API's address; None: none
        if operator_sock is None and operator_port is not None:
            operator_sock = bind_api_socket(self.host, operator_port)
        self.operator_sock = operator_sock
        self.operator: OperatorListener | None = None
        self._published: tuple[int, dict] | None = None  # (read ns, status) of the last publish
        self._operator_cache: tuple[int, bytes] | None = None  # that status as the operator port answers it
        self.status_capacity = status_capacity
        self.status_slot: SharedSlot | None = None
        self.frame_slot: SharedSlot | None = None
        self._write_lock = threading.Lock()  # one writer per slot: publisher and command threads
        self._frame_key: tuple | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._conn = self._blank_conn = None  # commands; the operator's blank alone
        self.process = None
        self.restarts = 0
        self.last_exit = ""  # why the previous API process ended ("" if none did)
        self._state = "starting"

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    # ---- lifecycle -------------------------------------------------------------------------
    def start(self, runtime: Runtime) -> "ApiProcess":
        self.runtime = runtime
        status = runtime.status()
        width, height = status.get("output_size", status["render_size"])  # frames reach the sink at the output size
        self.status_slot = SharedSlot.create(self.status_capacity)
        self.frame_slot = SharedSlot.create(width * height * 3)
        self.publish()
        if self.operator_sock is not None:  # first: it serves while the API process starts or restarts
            self.operator = OperatorListener(self.operator_sock, blank=self.operator_blank,
                                             status=self.operator_status, token=self.token,
                                             trusted_hosts=self.trusted_hosts, page_port=self.port).start()
        try:
            self._spawn()
        except BaseException:
            self.close()
            raise
        for name, target, args in (("api-publisher", self._publish_loop, ()),
                                   ("api-commands", self._serve_commands, ("_conn",)),
                                   ("api-blank", self._serve_commands, ("_blank_conn",)),
                                   ("api-keeper", self._keep, ())):
            t = threading.Thread(target=target, args=args, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def _spawn(self) -> None:
        """Start one API process on the bound socket and wait until it serves."""
        ctx = multiprocessing.get_context("spawn")  # never fork a process running native threads
        conn, child_conn = ctx.Pipe(duplex=True)
        blank_conn, child_blank_conn = ctx.Pipe(duplex=True)
        process = ctx.Process(
            target=_serve_child, name="dpmhw-api", daemon=True,
            args=(self.sock, child_conn, child_blank_conn, self.status_slot.name, self.frame_slot.name, self.token,
                  self.priority, self.stale_after_s, self.trusted_hosts, self.limits, self.command_rate,
                  None if self.operator is None else self.operator.port))
        process.start()
        child_conn.close()
        child_blank_conn.close()
        self.process = process
        try:
            self._wait_ready(conn)  # before the command threads may read these pipes
        except BaseException:
            conn.close()
            blank_conn.close()
            raise
        old = (self._conn, self._blank_conn)
        self._conn, self._blank_conn = conn, blank_conn
        for c in old:
            if c is not None:
                c.close()
        self._state = "serving"

    def _wait_ready(self, conn) -> None:
        deadline = time.monotonic() + self.start_timeout_s
        while time.monotonic() < deadline and not self._stop.is_set():
            try:
                if conn.poll(0.1) and conn.recv() == ("ready",):
                    return
            except EOFError:
                self.process.join(5)
            if not self.process.is_alive():
                raise RuntimeError(f"the API process exited during start-up (exit code {self.process.exitcode}); "
                                   "its error is printed above")
        raise RuntimeError(f"the API process did not start within {self.start_timeout_s:g} s")

    def _keep(self) -> None:
        """Restart the API process whenever it dies (not when we close it), with backoff."""
        policy = RestartPolicy(None, self.stable_after_s, self.restart_backoff_s, self.restart_backoff_max_s)
        while not self._stop.is_set():
            process = self.process
            while not self._stop.is_set() and process.is_alive():
                multiprocessing.connection.wait([process.sentinel], timeout=0.5)
            if self._stop.is_set():
                return
            process.join(1)
            backoff = policy.crashed(time.monotonic())
            self.last_exit = describe_exit(process.exitcode)
            self.restarts += 1
            self._state = "restarting"
            log.warning("the API process (pid %s) %s; restart %d in %.1f s", process.pid, self.last_exit,
                        self.restarts, backoff)
            with contextlib.suppress(Exception):
                self.publish()
            while not self._stop.wait(backoff):
                try:
                    self._spawn()
                    log.warning("API process restarted (pid %s) on %s", self.process.pid, self.url)
                    break
                except Exception as exc:  # e.g. it died again while starting: try later
                    self.last_exit = f"restart failed: {exc}"
                    log.warning("restarting the API process failed: %s", exc)
                    backoff = policy.crashed(time.monotonic())
            with contextlib.suppress(Exception):
                self.publish()

    def health(self) -> dict:
        """The service's own state, part of the published status."""
        return {"state": self._state, "pid": None if self.process is None else self.process.pid,
                "restarts": self.restarts, "last_exit": self.last_exit, "url": self.url,
                "operator": None if self.operator is None else self.operator.stats()}

    def close(self) -> None:
        """Stop the API process (graceful, then killed), the threads, and remove the slots."""
        self._stop.set()
        if self.operator is not None:
            self.operator.close()
        for t in self._threads:  # first, so that the keeper starts nothing new
            t.join(5)
        self._threads.clear()
        self._state = "closed"
        if self.process is not None:
            stop_process(self.process, grace_s=5.0)  # SIGTERM: uvicorn finishes open requests and exits
        for conn in (self._conn, self._blank_conn):
            if conn is not None:
                conn.close()
        self.sock.close()
        if self.operator_sock is not None:
            self.operator_sock.close()
        for slot in (self.status_slot, self.frame_slot):
            if slot is not None:
                slot.close()
        self.status_slot = self.frame_slot = None

    def __enter__(self) -> "ApiProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- this process's side ---------------------------------------------------------------
    def publish(self) -> None:
        """Copy the runtime's status (and a new latest frame) into the shared slots."""
        t_read = time.monotonic_ns()
        status = {**self.runtime.status(), "api": self.health()}
        payload = {"status": status, "ready": self.runtime.ready(),
                   "settings": self.runtime.settings().model_dump(), "t_read_ns": t_read}
        data = json.dumps(payload, separators=(",", ":")).encode()
        frame = self.runtime.latest_frame()
        with self._write_lock:
            self.status_slot.write(data)
            if self._published is None or t_read > self._published[0]:
                self._published = (t_read, status)
            if frame is not None:
                key = (frame.number, frame.t_present_ns, bool(frame.blank))
                if key != self._frame_key and frame.image.size <= self.frame_slot.capacity:
                    h, w = frame.image.shape[:2]
                    self.frame_slot.write(frame.image, (frame.number, frame.t_present_ns, int(frame.blank), h, w))
                    self._frame_key = key

    def operator_status(self) -> bytes:
        """The last published status as `GET /status` answers it, with its age (JSON; serialised
        once per publish, whatever the request rate)."""
        t_read, status = self._published
        cached = self._operator_cache
        if cached is None or cached[0] != t_read:
            cached = self._operator_cache = (t_read, json.dumps(public_status(status), separators=(",", ":")).encode())
        age_s = (time.monotonic_ns() - t_read) / 1e9
        return cached[1][:-1] + b',"snapshot_age_s":%.3f}' % age_s

    def operator_blank(self) -> tuple[bool, str, str]:
        """The operator port's blank: as the API process's (on the caller's thread), then published,
        so the answer and the next status say the state it led to."""
        (outcome, value), changed = self._execute("blank", ())
        if changed:
            try:
                self.publish()
            except Exception:
                log.exception("publishing the session status for the API failed")
        state = str(self._published[1].get("state", ""))
        if outcome != "ok":
            return False, str(value), state
        return True, "blanked: dark until resume", state

    def _publish_loop(self) -> None:
        while not self._stop.wait(self.publish_period_s):
            try:
                self.publish()
            except Exception:  # never let the service take the session down
                log.exception("publishing the session status for the API failed")

    def _serve_commands(self, pipe: str) -> None:
        """Execute the commands arriving on the pipe named `pipe` (the attribute: a restarted API
        process gets new pipes), one at a time, in order."""
        while not self._stop.is_set():
            conn = getattr(self, pipe)
            try:
                if not conn.poll(0.2):
                    continue
                request_id, name, args = conn.recv()
            except (EOFError, OSError):  # that API process is gone; the keeper starts another
                self._stop.wait(0.1)
                continue
            reply, changed = self._execute(name, args)
            try:
                if changed and name in _PUBLISH_AT_ONCE:
                    self.publish()  # the reply's sender reads its own write in the next status
            except Exception:
                log.exception("publishing the session status for the API failed")
            try:
                conn.send((request_id, *reply))
            except OSError:
                continue

    def _execute(self, name: str, args: tuple) -> tuple[tuple[str, Any], bool]:
        """The reply, and whether the command may have changed what the status says."""
        if name not in _COMMANDS:
            return ("error", f"unknown command {name!r}"), False
        try:
            if name == "update_settings":
                before = self.runtime.settings()
                new = self.runtime.update_settings(dict(args[0]))
                return ("ok", (new.model_dump(), time.monotonic_ns())), new != before
            result = getattr(self.runtime, name)()
            return ("ok", None if result is None else list(result)), True
        except ValueError as exc:  # SettingsError: the loop refused the value
            return ("refused", str(exc)), False
        except Exception as exc:
            log.exception("API command %s failed", name)
            return ("error", f"{type(exc).__name__}: {exc}"), True


def bind_api_socket(host: str, port: int) -> socket.socket:
    """The API's listening socket (port 0: a free one); whoever binds it may hand it on."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    return socket.create_server((host, port), family=family, backlog=128)


class RemoteRuntime:
    """The `Runtime` the API process serves: reads from the shared slots, commands over the pipe."""

    def __init__(self, status_slot: SharedSlot, frame_slot: SharedSlot, conn, blank_conn=None, *,
                 stale_after_s: float = 1.0, command_timeout_s: float = 2.0, session_alive=None,
                 command_rate: tuple[float, int] = (20.0, 10), connection_stats=None):
        self.status_slot = status_slot
        # whether the session process still exists, asked per request (None: assumed so). Its last
        # snapshot stays fresh for stale_after_s after it dies; without this, a crashed session
        # would read as ready until then, and longer while this process is slow to exit
        self.session_alive = session_alive
        self.frame_slot = frame_slot
        self.stale_after_s = stale_after_s
        self.command_timeout_s = command_timeout_s
        # the operator's blank has a pipe (and a session thread) of its own, so that no other
        # command is ever ahead of it; each pipe carries one command at a time
        commands = (conn, threading.Lock())
        self._pipes = {"commands": commands, "blank": commands if blank_conn is None else (blank_conn, threading.Lock())}
        self._ids = itertools.count(1)
        self._cache_lock = threading.Lock()
        self._payload: tuple[int, int, dict] | None = None  # (sequence, published ns, decoded)
        self._frame: tuple[int, LatestFrame] | None = None
        self._own_settings: tuple[int, LiveSettings] | None = None  # from our last accepted PATCH
        self._bucket = TokenBucket(*command_rate)  # every command but blank
        self.connection_stats = connection_stats  # this process's connections (`server.guard`), or None

    def _read(self) -> tuple[dict, float]:
        """The latest published payload (decoded once per publish) and seconds since it was published."""
        seq = self.status_slot.sequence()
        with self._cache_lock:
            if self._payload is None or self._payload[0] != seq:
                try:
                    got = self.status_slot.read()
                except SlotTornError:  # its writer stalled mid-publish: serve the snapshot before (it ages)
                    if self._payload is None:
                        raise RuntimeUnavailable("the session's first status is still being written") from None
                    got = None
                if got is None and self._payload is None:
                    raise RuntimeUnavailable("the session has not published a status yet")
                if got is not None:
                    seq, published, _, data = got
                    self._payload = (seq, published, json.loads(data))
            _, published, payload = self._payload
        return payload, (time.monotonic_ns() - published) / 1e9

    def _gone(self) -> bool:
        return self.session_alive is not None and not self.session_alive()

    def status(self) -> dict:
        payload, silent_s = self._read()
        last = payload["status"]
        out = dict(last, snapshot_age_s=round(silent_s, 3))
        own = self._own_settings
        if own is not None and own[0] > payload["t_read_ns"] and "settings" in out:
            out["settings"] = own[1].model_dump()  # accepted after that snapshot was taken
        if self.connection_stats is not None:
            out["api"] = {**out.get("api", {}), "connections": self.connection_stats()}
        if self._gone() and last.get("state") != "stopped":
            out.update(state="fault", output_on=False,
                       reason=f"the session process is gone; last state {last.get('state')}: {last.get('reason', '')}")
        elif silent_s > self.stale_after_s and last.get("state") != "stopped":
            out.update(state="fault", output_on=False,
                       reason=f"the session process has not published for {silent_s:.1f} s (stuck or gone); "
                              f"last state {last.get('state')}: {last.get('reason', '')}")
        return out

    def ready(self) -> bool:
        payload, silent_s = self._read()
        return bool(payload["ready"]) and silent_s <= self.stale_after_s and not self._gone()

    def settings(self) -> LiveSettings:
        payload, _ = self._read()
        own = self._own_settings
        if own is not None and own[0] > payload["t_read_ns"]:
            return own[1]  # our change was accepted after that snapshot was taken
        return LiveSettings.model_validate(payload["settings"])

    def update_settings(self, patch: dict) -> LiveSettings:
        if any(getattr(self.settings(), k, _MISSING) != v for k, v in patch.items()):
            self._admit("update_settings")  # only a change counts against the command rate: one that only pins
            # fields (the operator's, against the governor) costs the loop a comparison (`routers.settings`)
        settings, accepted_ns = self._call("update_settings", dict(patch))
        new = LiveSettings.model_validate(settings)
        self._own_settings = (accepted_ns, new)
        return new

    def blank(self) -> None:
        self._call("blank", pipe="blank")

    def resume(self) -> tuple[bool, str]:
        self._admit("resume")
        ok, message = self._call("resume")
        return bool(ok), str(message)

    def reset_history(self) -> None:
        self._admit("reset_history")
        self._call("reset_history")

    def _admit(self, name: str) -> None:
        wait_s = self._bucket.take()
        if wait_s > 0:
            rate, burst = self._bucket.rate, self._bucket.burst
            raise RuntimeBusy(f"too many commands ({name}): at most {rate:g} per second, in bursts of {burst}; "
                              f"retry in {wait_s:.2f} s", retry_after_s=max(1, math.ceil(wait_s)))

    def latest_frame(self) -> LatestFrame | None:
        seq = self.frame_slot.sequence()
        if seq == 0:
            return None
        cached = self._frame
        if cached is not None and cached[0] == seq:
            return cached[1]
        try:
            seq, _, (number, t_present, blank, h, w), data = self.frame_slot.read()
        except SlotTornError:  # its writer stalled mid-publish: the frame before, if any
            return cached[1] if cached is not None else None
        frame = LatestFrame(number, t_present, np.frombuffer(data, np.uint8).reshape(h, w, 3), self.settings(),
                            bool(blank))
        self._frame = (seq, frame)  # one reference swap: readers see the old or the new pair
        return frame

    def _call(self, name: str, *args, pipe: str = "commands") -> Any:
        """Send one command and wait for its reply (bounded: a stuck session → 503, not a hang)."""
        conn, lock = self._pipes[pipe]
        with lock:
            request_id = next(self._ids)
            try:
                conn.send((request_id, name, args))
                deadline = time.monotonic() + self.command_timeout_s
                while True:
                    left = deadline - time.monotonic()
                    if left <= 0 or not conn.poll(left):
                        raise RuntimeUnavailable(f"the session did not answer {name!r} within "
                                                 f"{self.command_timeout_s:g} s (stuck?)")
                    reply_id, outcome, value = conn.recv()
                    if reply_id == request_id:
                        break  # older replies belong to requests that already timed out
            except (EOFError, OSError) as exc:
                raise RuntimeUnavailable(f"the session process is gone ({type(exc).__name__})") from None
        if outcome == "refused":
            raise SettingsError(value)
        if outcome != "ok":
            raise RuntimeError(f"the session failed to {name}: {value}")
        return value


def _serve_child(sock: socket.socket, conn, blank_conn, status_name: str, frame_name: str, token: str, priority: str,
                 stale_after_s: float, trusted_hosts: list[str], limits: ConnectionLimits,
                 command_rate: tuple[float, int], operator_port: int | None) -> None:
    """The API process: uvicorn on the inherited socket, serving a `RemoteRuntime`."""
    import uvicorn

    from server.app import build_app

    lower_priority(priority)
    parent = multiprocessing.parent_process()
    options = limits.uvicorn_options()
    runtime = RemoteRuntime(SharedSlot.attach(status_name), SharedSlot.attach(frame_name), conn, blank_conn,
                            stale_after_s=stale_after_s, session_alive=parent.is_alive if parent is not None else None,
                            command_rate=command_rate, connection_stats=options["http"].guard.stats)
    app = build_app(runtime=runtime, token=token, trusted_hosts=trusted_hosts, max_headers=limits.max_headers,
                    max_header_bytes=limits.max_header_bytes, operator_port=operator_port)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on", timeout_graceful_shutdown=2,
                                           **options))

    def watch_parent() -> None:
        if parent is not None:
            parent.join()  # returns when the session process dies: then so do we
            server.should_exit = True

    threading.Thread(target=watch_parent, name="api-parent-watch", daemon=True).start()
    conn.send(("ready",))  # before any request can use the pipe (the socket already queues them)
    server.run(sockets=[sock])
