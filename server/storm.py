"""A mixed request storm against a session's API, and what it costs the operator and the loop.

    with Storm(api.port, clients=200, token="…") as storm:     # a separate process of clients
        storm.active.set()                                     # they send while this is set
        ...
    storm.results()                                            # per endpoint: codes and latencies

    python -m server.storm --clients 200                       # the measurement on the mocks

Each client is one keep-alive connection sending, in turn, `GET /status`, `GET /frame.png` and
`PATCH /settings` (every other one to the current `spp`, which changes nothing, the others
toggling `alpha` between two values: those are the commands the API limits), as fast as they are
answered. The clients run in their own process with the standard library's HTTP client, never in
the session's.

`measure` runs a `--mock` session with its API in its own process (`server.process.ApiProcess`,
as `dpmhw session start` serves it), then alternates quiet and storm windows of equal length, so
that frame rates with and without traffic come from the same session under the same machine
conditions; each window's rate is frames presented over its length, and the windows' medians are
compared. During a last storm phase, while the projector is lit, it sends `POST /session/blank`
on a fresh connection and times it from the request to the emulated projector's own state going
dark with the operator's blank in force (read back from the DLPC900 model the driver talks to),
then resumes in-process and repeats.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import queue
import threading
import time

import numpy as np

__all__ = ["ENDPOINTS", "Storm", "measure", "summarise"]

ENDPOINTS = ("status", "frame", "patch_noop", "patch_change")


def _clients(port: int, clients: int, token: str, timeout_s: float, priority: str, ready, active, stop,
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

    threads = [threading.Thread(target=client, args=(i,), daemon=True) for i in range(clients)]
    for t in threads:
        t.start()
    ready.set()
    for t in threads:
        t.join()


class Storm:
    """`clients` storm clients in a spawned process; they send only while `active` is set."""

    def __init__(self, port: int, clients: int, token: str, timeout_s: float = 10.0, priority: str = "normal"):
        ctx = multiprocessing.get_context("spawn")
        self.ready, self.active, self._stop = ctx.Event(), ctx.Event(), ctx.Event()
        self._out = ctx.Queue()
        self.clients = clients
        self.process = ctx.Process(target=_clients, name="api-storm", daemon=True,
                                   args=(port, clients, token, timeout_s, priority, self.ready, self.active,
                                         self._stop, self._out))
        self._records: list[tuple[int, int, float]] = []
        self.lost = 0  # clients whose records never arrived (stuck past the stop)

    def __enter__(self) -> "Storm":
        self.process.start()
        if not self.ready.wait(60):
            self.close()
            raise RuntimeError("the storm's client process did not start")
        return self

    def close(self, wait_s: float = 30.0) -> None:
        """Stop the clients (each finishes or times out its request) and collect their records."""
        self.active.clear()
        self._stop.set()
        deadline = time.monotonic() + wait_s
        for _ in range(self.clients if self.process.pid is not None else 0):
            try:
                self._records += self._out.get(timeout=max(0.1, deadline - time.monotonic()))
            except queue.Empty:
                self.lost += 1
        self.process.join(5)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5)

    def __exit__(self, *exc) -> None:
        self.close()

    def results(self) -> np.ndarray:
        """One row per response: endpoint index (`ENDPOINTS`), status code (0: failed), seconds."""
        return np.array(self._records, dtype=float).reshape(-1, 3)


def summarise(records: np.ndarray) -> dict:
    """Per endpoint: count, status codes and latency percentiles (ms)."""
    out = {}
    for i, name in enumerate(ENDPOINTS):
        rows = records[records[:, 0] == i]
        codes, counts = np.unique(rows[:, 1].astype(int), return_counts=True)
        ms = rows[:, 2] * 1e3
        out[name] = {"requests": len(rows), "codes": {str(c): int(n) for c, n in zip(codes, counts)},
                     **({f"p{q}_ms": round(float(np.percentile(ms, q)), 1) for q in (50, 99)} if len(rows) else {}),
                     **({"max_ms": round(float(ms.max()), 1)} if len(rows) else {})}
    return out


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
            client_priority: str = "normal", overrides: tuple[str, ...] = ()) -> dict:
    """The storm on a `--mock` session (see the module doc); frame rates per window, the API's
    answers per endpoint, and the blank's time to a dark projector."""
    from dpmhw.benchmarks.session import _cpu_seconds
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import build_session
    from dpmhw.session.testing import wait_for
    from server.process import ApiProcess

    token = "storm"
    cfg = load_session_config(overrides=["sink.kind=recording", "api.enabled=false", *overrides])
    loop = build_session(cfg, mock=True, frame_log=100_000)
    spans: dict[bool, list[tuple[int, int]]] = {False: [], True: []}
    session_cpu = {False: 0.0, True: 0.0}  # this process's CPU seconds in quiet and storm windows
    blank = []
    try:
        loop.start()
        if not wait_for(lambda: loop.status()["state"] == "running", 600):
            raise RuntimeError(f"the session did not start: {loop.status()['reason']}")
        projector = loop.parts.mock.projector.model
        with ApiProcess(host="127.0.0.1", port=0, token=token, priority=cfg.api.priority) as api:
            api.start(loop)
            cpu0 = {"session": time.process_time(), "api": _cpu_seconds(api.process.pid)}
            with Storm(api.port, clients, token, priority=client_priority) as storm:
                cpu0["clients"] = _cpu_seconds(storm.process.pid)
                time.sleep(window_s)  # settle
                for w in range(2 * windows):
                    loud = w % 2 == 1
                    (storm.active.set if loud else storm.active.clear)()
                    t0, c0 = time.monotonic_ns(), time.process_time()
                    time.sleep(window_s)
                    spans[loud].append((t0, time.monotonic_ns()))
                    session_cpu[loud] += time.process_time() - c0
                storm.active.set()
                for _ in range(blanks):
                    time.sleep(1.0)
                    if not wait_for(lambda: not projector.dark, 10):  # dark for another reason (a hold-off)
                        continue
                    blank.append(_blank_probe(api.url, token, lambda: projector.dark and loop.safety.active("operator")))
                    loop.resume()
                cpu = {"session": time.process_time() - cpu0["session"],
                       "api": _cpu_seconds(api.process.pid) - cpu0["api"],
                       "clients": _cpu_seconds(storm.process.pid) - cpu0["clients"]}
            records = storm.results()
            lost = storm.lost
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

    return {"clients": clients, "client_priority": client_priority, "windows": windows, "window_s": window_s,
            "quiet_fps": [round(x, 2) for x in quiet], "storm_fps": [round(x, 2) for x in loud],
            "fps_ratio_median": round(float(np.median(loud) / np.median(quiet)), 3),
            "api": summarise(records), "clients_lost": lost,
            "blank_codes": [c for c, _, _ in blank], "blank_answered_ms": ms([a for _, a, _ in blank]),
            "blank_to_dark_ms": ms([d for _, _, d in blank]),
            "cpu_s": {k: round(v, 1) for k, v in cpu.items()},
            # the session process's CPU use (cores) in each kind of window: more under the storm is
            # work the API costs it (publishes, commands); less is CPU the storm took from it
            "session_cores": {"quiet": round(session_cpu[False] / (windows * window_s), 2),
                              "storm": round(session_cpu[True] / (windows * window_s), 2)}}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m server.storm", description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=200)
    parser.add_argument("--windows", type=int, default=4, help="quiet and storm windows, each")
    parser.add_argument("--window-s", type=float, default=5.0)
    parser.add_argument("--blanks", type=int, default=10)
    parser.add_argument("--client-priority", choices=("idle", "low", "normal"), default="normal",
                        help="the clients' CPU priority: below the session's stands for clients on other machines")
    parser.add_argument("--set", action="append", default=[], help="session config override, e.g. render.spp=1")
    args = parser.parse_args(argv)
    print(json.dumps(measure(args.clients, args.windows, args.window_s, args.blanks, args.client_priority,
                             tuple(args.set)), indent=1))


if __name__ == "__main__":
    main()
