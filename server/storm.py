"""A mixed request storm, or a connection flood, against a session's API, and what it costs the
operator and the loop.

    with Storm(api.port, clients=200, token="…") as storm:     # a separate process of clients
        storm.active.set()                                     # they send while this is set
        ...
    storm.results()                                            # per endpoint: codes and latencies

    python -m server.storm --clients 200                       # the measurement on the mocks
    python -m server.storm --flood 2000                        # the same under a connection flood

Each storm client is one keep-alive connection sending, in turn, `GET /status`, `GET /frame.png`
and `PATCH /settings` (every other one to the current `spp`, which changes nothing, the others
toggling `alpha` between two values: those are the commands the API limits), as fast as they are
answered. A flood (`Flood`) holds that many connections to the main port that never finish a
request (nothing, half a request line, a head without its end), reopening each one the server
closes. Clients, flood and probes run in processes of their own with the standard library, never
in the session's.

`measure` runs a `--mock` session with its API in its own process (`server.process.ApiProcess`,
as `dpmhw session start` serves it, with the operator's reserved port), then alternates quiet and
loud windows of equal length, so that frame rates with and without traffic come from the same
session under the same machine conditions; each window's rate is frames presented over its
length, and the windows' medians are compared. During the loud windows an operator's probe
(`Probes`) asks `GET /status` on a fresh connection every 0.1 s, by turns on the main port and
the operator port. During a last loud phase, while the projector is lit, it sends
`POST /session/blank` on a fresh connection, by turns to each port, and times it from the request
to the emulated projector's own state going dark with the operator's blank in force (read back
from the DLPC900 model the driver talks to), then resumes in-process and repeats.
"""
from __future__ import annotations

import argparse
import json
import queue
import threading
import time

import numpy as np

from dpmhw.benchmarks.load_process import LoadProcess, run_threads

__all__ = ["ENDPOINTS", "Flood", "Probes", "Storm", "measure", "summarise"]

ENDPOINTS = ("status", "frame", "patch_noop", "patch_change")


def _clients(port: int, clients: int, token: str, timeout_s: float, priority: str, active, stop, ready,
             out) -> None:
    """The storm's process: `clients` threads, each on one keep-alive connection; every response's
    endpoint, status code (0: timed out or failed) and seconds go to `out` when they stop."""
    import http.client

    from server.process import lower_priority

    lower_priority(priority)
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}

    def client(i: int) -> None:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout_s)
        got: list[tuple[int, int, float]] = []
        spp = None
        k = i  # clients start at different points of the mix
        idle = False
        while not stop.is_set():
            if not active.wait(0.05):
                idle = True
                continue
            if idle:  # the server closes a connection idle past its keep-alive: start afresh
                conn.close()
                idle = False
            kind = k % 4
            k += 1
            t0 = time.monotonic()
            try:
                if kind == 0:
                    conn.request("GET", "/status")
                elif kind == 1:
                    conn.request("GET", "/frame.png")
                else:
                    if spp is None:  # the accepted value, which no client changes: a patch to it changes nothing
                        conn.request("GET", "/settings")
                        r = conn.getresponse()
                        spp = json.loads(r.read())["spp"] if r.status == 200 else 1
                        t0 = time.monotonic()
                    patch = {"alpha": 0.21 if k % 8 < 4 else 0.22} if kind == 3 else {"spp": spp}
                    conn.request("PATCH", "/settings", body=json.dumps(patch), headers=headers)
                response = conn.getresponse()
                response.read()
                code = response.status
            except (OSError, http.client.HTTPException):
                conn.close()  # reconnects on the next request
                code = 0
            got.append((min(kind, 3), code, time.monotonic() - t0))
        conn.close()
        out.put(got)

    run_threads(clients, client, ready)


class Storm(LoadProcess):
    """`clients` storm clients in a spawned process; they send only while `active` is set."""

    def __init__(self, port: int, clients: int, token: str, timeout_s: float = 10.0, priority: str = "normal"):
        super().__init__("api-storm", _clients, (port, clients, token, timeout_s, priority))
        self.clients = clients
        self._records: list[tuple[int, int, float]] = []
        self.lost = 0  # clients whose records never arrived (stuck past the stop)

    def _collect(self, wait_s: float = 30.0) -> None:
        """Each client finishes or times out its request, then sends its records."""
        deadline = time.monotonic() + wait_s
        for _ in range(self.clients):
            try:
                self._records += self._out.get(timeout=max(0.1, deadline - time.monotonic()))
            except queue.Empty:
                self.lost += 1

    def results(self) -> np.ndarray:
        """One row per response: endpoint index (`ENDPOINTS`), status code (0: failed), seconds."""
        return np.array(self._records, dtype=float).reshape(-1, 3)


def _flood(host: str, port: int, connections: int, active, stop, ready, out) -> None:
    """The flood's process: while `active` is set, `connections` connections to the API that
    never finish a request (a third send nothing, a third half a request line, a third a head
    without its end), each reopened as soon as the server closes it; none while it is clear.
    Puts how many it opened in all on `out` when stopped."""
    import contextlib
    import resource
    import selectors
    import socket

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, connections + 256)), hard))
    partial = (b"", b"GET /sta", b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
    selector = selectors.DefaultSelector()
    opened = 0

    def open_one(i: int) -> None:
        nonlocal opened
        try:
            sock = socket.create_connection((host, port), timeout=5)
        except OSError:
            return  # refused: tried again on the next round
        try:
            if partial[i % 3]:
                sock.sendall(partial[i % 3])
        except OSError:  # reset at once: tried again on the next round
            sock.close()
            return
        sock.setblocking(False)
        selector.register(sock, selectors.EVENT_READ, i)
        opened += 1

    def close_all() -> None:
        for key in list(selector.get_map().values()):
            selector.unregister(key.fileobj)
            key.fileobj.close()

    ready.set()
    while not stop.is_set():
        if not active.wait(0.05):
            close_all()
            continue
        held = {key.data for key in selector.get_map().values()}
        for i in range(connections):
            if i not in held:
                open_one(i)
        for key, _ in selector.select(0.05):  # the server closed it (or answered it): reopen next round
            with contextlib.suppress(OSError):
                if key.fileobj.recv(65536):
                    continue
            selector.unregister(key.fileobj)
            key.fileobj.close()
    close_all()
    out.put(opened)


class Flood(LoadProcess):
    """`connections` idle and half-sent connections to the API, held from a spawned process while
    `active` is set (see `_flood`)."""

    def __init__(self, port: int, connections: int, host: str = "127.0.0.1"):
        super().__init__("api-flood", _flood, (host, port, connections))
        self.opened = 0

    def _collect(self) -> None:
        try:
            self.opened = self._out.get(timeout=30)
        except queue.Empty:
            pass


def _probe(urls: list[str], period_s: float, timeout_s: float, active, stop, ready, out) -> None:
    """The probes' process: while `active` is set, `GET /status` on a fresh connection to each
    of `urls` in turn, one every `period_s`; (url index, status code (0: failed), seconds) of each
    go to `out` when stopped."""
    import http.client

    got: list[tuple[int, int, float]] = []
    ready.set()
    k = 0
    while not stop.is_set():
        if not active.wait(0.05):
            continue
        i = k % len(urls)
        k += 1
        host, port = urls[i].rsplit("/", 1)[-1].rsplit(":", 1)
        conn = http.client.HTTPConnection(host, int(port), timeout=timeout_s)
        t0 = time.monotonic()
        try:
            conn.request("GET", "/status")
            response = conn.getresponse()
            response.read()
            code = response.status
        except (OSError, http.client.HTTPException):
            code = 0
        got.append((i, code, time.monotonic() - t0))
        conn.close()
        stop.wait(max(0.0, period_s - (time.monotonic() - t0)))
    out.put(got)


class Probes(LoadProcess):
    """`GET /status` probes (an operator's, on fresh connections) to each of `urls`, from a
    spawned process, while `active` is set."""

    def __init__(self, urls: list[str], period_s: float = 0.1, timeout_s: float = 10.0):
        super().__init__("api-probes", _probe, (urls, period_s, timeout_s))
        self.urls = urls
        self._records: list[tuple[int, int, float]] = []

    def _collect(self) -> None:
        try:
            self._records += self._out.get(timeout=30)
        except queue.Empty:
            pass

    def summary(self, names: list[str]) -> dict:
        """Per url (named by `names`): requests, codes, p50/p99/max latency (ms)."""
        records = np.array(self._records, dtype=float).reshape(-1, 3)
        out = {}
        for i, name in enumerate(names):
            rows = records[records[:, 0] == i]
            out[name] = _latencies(rows)
        return out


def _latencies(rows: np.ndarray) -> dict:
    """Count, status codes and latency percentiles (ms) of (index, code, seconds) rows."""
    codes, counts = np.unique(rows[:, 1].astype(int), return_counts=True)
    ms = rows[:, 2] * 1e3
    return {"requests": len(rows), "codes": {str(c): int(n) for c, n in zip(codes, counts)},
            **({f"p{q}_ms": round(float(np.percentile(ms, q)), 1) for q in (50, 99)} if len(rows) else {}),
            **({"max_ms": round(float(ms.max()), 1)} if len(rows) else {})}


def summarise(records: np.ndarray) -> dict:
    """Per endpoint: count, status codes and latency percentiles (ms)."""
    return {name: _latencies(records[records[:, 0] == i]) for i, name in enumerate(ENDPOINTS)}


def _blank_probe(api_url: str, token: str, dark, timeout_s: float = 10.0) -> tuple[int, float | None, float | None]:
    """POST /session/blank on a fresh connection: (status code, 0 if none within `timeout_s`;
    seconds from sending it to the response, and to `dark()` turning true; None if not within
    `timeout_s`)."""
    import http.client

    host, port = api_url.rsplit("/", 1)[-1].rsplit(":", 1)
    dark_at: list[float] = []
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            if dark():
                dark_at.append(time.monotonic())
                return
            time.sleep(0.0005)

    conn = http.client.HTTPConnection(host, int(port), timeout=timeout_s)
    watcher = threading.Thread(target=watch, daemon=True)
    code, answered_s = 0, None
    watcher.start()
    t0 = time.monotonic()  # the operator's connection is part of the request
    try:
        conn.connect()
        conn.request("POST", "/session/blank", headers={"Authorization": f"Bearer {token}"})
        code = conn.getresponse().status
        answered_s = time.monotonic() - t0
        watcher.join(max(0.0, t0 + timeout_s - time.monotonic()))
    except (OSError, http.client.HTTPException):
        watcher.join(max(0.0, t0 + timeout_s - time.monotonic()))
    finally:
        done.set()
        conn.close()
    return code, answered_s, (dark_at[0] - t0) if dark_at else None


def measure(clients: int = 200, windows: int = 4, window_s: float = 5.0, blanks: int = 10,
            client_priority: str = "normal", overrides: tuple[str, ...] = (), flood: int = 0,
            api_fd_limit: int | None = 1024) -> dict:
    """The storm (or, with `flood` > 0, that many idle and half-sent connections) on a `--mock`
    session (see the module doc): frame rates per window, the API's answers per endpoint, status
    probes and the blank's time to a dark projector on the main port and the operator port. The
    API process gets the soft descriptor limit `api_fd_limit` (None: this process's)."""
    import resource

    from dpmhw.benchmarks.session import _cpu_seconds
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import build_session
    from dpmhw.session.testing import wait_for
    from server.process import ApiProcess

    token = "storm"
    cfg = load_session_config(overrides=["sink.kind=recording", "api.enabled=false", *overrides])
    loop = build_session(cfg, mock=True, frame_log=100_000)
    spans: dict[bool, list[tuple[int, int]]] = {False: [], True: []}
    session_cpu = {False: 0.0, True: 0.0}  # this process's CPU seconds in quiet and loud windows
    blank: dict[str, list] = {"main": [], "operator": []}
    records, lost, opened = np.zeros((0, 3)), 0, 0
    try:
        loop.start()
        if not wait_for(lambda: loop.status()["state"] == "running", 600):
            raise RuntimeError(f"the session did not start: {loop.status()['reason']}")
        projector = loop.parts.mock.projector.model
        with ApiProcess(host="127.0.0.1", port=0, token=token, priority=cfg.api.priority) as api:
            soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
            try:
                if api_fd_limit is not None:  # inherited by the spawned API process
                    resource.setrlimit(resource.RLIMIT_NOFILE, (min(api_fd_limit, hard), hard))
                api.start(loop)
            finally:
                resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
            urls = {"main": api.url, "operator": api.operator.url}
            cpu0 = {"session": time.process_time(), "api": _cpu_seconds(api.process.pid)}
            load = Flood(api.port, flood) if flood else Storm(api.port, clients, token, priority=client_priority)
            with load, Probes(list(urls.values())) as probes:
                cpu0["clients"] = _cpu_seconds(load.process.pid)
                time.sleep(window_s)  # settle
                for w in range(2 * windows):
                    loud = w % 2 == 1
                    for event in (load.active, probes.active):
                        (event.set if loud else event.clear)()
                    t0, c0 = time.monotonic_ns(), time.process_time()
                    time.sleep(window_s)
                    spans[loud].append((t0, time.monotonic_ns()))
                    session_cpu[loud] += time.process_time() - c0
                load.active.set()
                probes.active.set()
                for k in range(2 * blanks):  # by turns on the main port and the operator's
                    path = ("main", "operator")[k % 2]
                    time.sleep(1.0)
                    if not wait_for(lambda: not projector.dark, 10):  # dark for another reason (a hold-off)
                        continue
                    blank[path].append(_blank_probe(urls[path], token,
                                                    lambda: projector.dark and loop.safety.active("operator")))
                    loop.resume()
                cpu = {"session": time.process_time() - cpu0["session"],
                       "api": _cpu_seconds(api.process.pid) - cpu0["api"],
                       "clients": _cpu_seconds(load.process.pid) - cpu0["clients"]}
            if isinstance(load, Storm):
                records, lost = load.results(), load.lost
            else:
                opened = load.opened
            status_probes = probes.summary(list(urls))
            connections = api.health()  # the operator listener's counts
        log = list(loop.frame_log)
    finally:
        loop.stop()
    presented = np.array([r.t_present_ns for r in log], dtype=np.int64)

    def fps(a: int, b: int) -> float:
        return float(np.count_nonzero((presented >= a) & (presented < b)) / ((b - a) / 1e9))

    quiet = [fps(*s) for s in spans[False]]
    loud = [fps(*s) for s in spans[True]]

    def ms(seconds: list[float | None]) -> list[float | None]:
        return [None if x is None else round(x * 1e3, 1) for x in seconds]

    load_info = ({"flood_connections": flood, "flood_opened": opened} if flood else
                 {"clients": clients, "client_priority": client_priority, "api": summarise(records),
                  "clients_lost": lost})
    return {**load_info, "api_fd_limit": api_fd_limit, "windows": windows, "window_s": window_s,
            "quiet_fps": [round(x, 2) for x in quiet], "loud_fps": [round(x, 2) for x in loud],
            "fps_ratio_median": round(float(np.median(loud) / np.median(quiet)), 3),
            # GET /status on a fresh connection every 0.1 s, by turns on each port, while loud
            "status_probes": status_probes,
            "blank": {path: {"codes": [c for c, _, _ in got], "answered_ms": ms([a for _, a, _ in got]),
                             "to_dark_ms": ms([d for _, _, d in got])} for path, got in blank.items()},
            "operator_listener": connections["operator"],
            "cpu_s": {k: round(v, 1) for k, v in cpu.items()},
            # the session process's CPU use (cores) in each kind of window: more under load is
            # work the API costs it (publishes, commands); less is CPU the load took from it
            "session_cores": {"quiet": round(session_cpu[False] / (windows * window_s), 2),
                              "loud": round(session_cpu[True] / (windows * window_s), 2)}}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m server.storm", description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=200)
    parser.add_argument("--windows", type=int, default=4, help="quiet and storm windows, each")
    parser.add_argument("--window-s", type=float, default=5.0)
    parser.add_argument("--blanks", type=int, default=10)
    parser.add_argument("--client-priority", choices=("idle", "low", "normal"), default="normal",
                        help="the clients' CPU priority: below the session's stands for clients on other machines")
    parser.add_argument("--flood", type=int, default=0, metavar="N",
                        help="instead of the request storm, hold N idle and half-sent connections to the main port")
    parser.add_argument("--api-fd-limit", type=int, default=1024,
                        help="the API process's soft descriptor limit (a common default; 0: this process's)")
    parser.add_argument("--set", action="append", default=[], help="session config override, e.g. render.spp=1")
    args = parser.parse_args(argv)
    print(json.dumps(measure(args.clients, args.windows, args.window_s, args.blanks, args.client_priority,
                             tuple(args.set), args.flood, args.api_fd_limit or None), indent=1))


if __name__ == "__main__":
    main()
