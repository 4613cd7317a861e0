"""What a client can hold in the API process, and what a flood can take from the operator and the
loop: real HTTP on loopback against an API process over a fake session.

Bounds: WAIT_S is for what must happen eventually; the API processes run at "low" priority (nice 10,
see test_api_process.py) and a loaded 2-core machine may hold them off for seconds, so only broken
code waits that long. The limits themselves (cap, timeouts) are what is checked, never a speed.
"""

from __future__ import annotations

import contextlib
import os
import resource
import socket
import threading
import time

import httpx
import pytest

from dpmhw.session.testing import fake_session, wait_for
from server.guard import ConnectionLimits
from server.process import ApiProcess
from tests.server.conftest import closed_by_server, open_with

WAIT_S = 60
TOKEN = "flood-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
FD_LIMIT = 256  # the API process's descriptor limit here: the flood is 2,000 connections, far beyond it
FLOOD = 2000


@contextlib.contextmanager
def _session_and_api(fd_limit: int | None = None, **kw):
    """A started fake session and its API process, spawned with soft RLIMIT_NOFILE `fd_limit`
    (a spawned child inherits the limit; this process's own is put back at once)."""
    loop = fake_session(["governor.enabled=false"]).start()  # what changes the settings here is the clients alone
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    api = ApiProcess(port=0, token=TOKEN, publish_period_s=0.02, priority="low", **kw)
    try:
        if fd_limit is not None:
            resource.setrlimit(resource.RLIMIT_NOFILE, (fd_limit, hard))
        try:
            api.start(loop)
        finally:
            resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
        with httpx.Client(base_url=api.url, timeout=WAIT_S) as client:
            assert wait_for(lambda: client.get("/status").json()["state"] == "running", WAIT_S)
            yield loop, api, client
    finally:
        api.close()
        loop.stop()


def _flood(api: ApiProcess, n: int) -> list[socket.socket]:
    """`n` connections that never finish a request: a third send nothing, a third half a request
    line, a third a request head without its end."""
    partial = (b"", b"GET /sta", b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
    socks = []
    for i in range(n):
        s = socket.create_connection((api.host, api.port), timeout=WAIT_S)
        if partial[i % 3]:
            with contextlib.suppress(OSError):  # the server may already have evicted it
                s.sendall(partial[i % 3])
        socks.append(s)
    return socks


def test_blank_and_status_answer_through_a_flood_beyond_the_descriptor_limit():
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if min(soft, hard) < FLOOD + 256:  # this process holds the flood's client ends
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, FLOOD + 1024), hard))
        if resource.getrlimit(resource.RLIMIT_NOFILE)[0] < FLOOD + 256:
            pytest.skip(f"needs {FLOOD + 256} descriptors for the flood's client ends; the hard limit is {hard}")
    # requests never time out here: the connection cap alone must keep the port reachable
    limits = ConnectionLimits(request_timeout_s=600, keep_alive_s=600)
    with _session_and_api(FD_LIMIT, limits=limits) as (loop, api, _client):
        socks = _flood(api, FLOOD)
        try:
            # the cap is below the API process's descriptor limit: it never ran out of them
            cap = FD_LIMIT - limits.reserved_fds
            assert wait_for(lambda: sum(not closed_by_server(s) for s in socks) <= cap, WAIT_S)
            assert len(os.listdir(f"/proc/{api.process.pid}/fd")) < FD_LIMIT
            with httpx.Client(base_url=api.url, timeout=WAIT_S) as fresh:  # a new connection, as an operator's
                assert fresh.get("/status").status_code == 200
                assert loop.parts.projector.dark is False
                r = fresh.post("/session/blank", headers=AUTH)
                assert r.status_code == 200 and r.json()["state"] == "blanked"
                assert wait_for(lambda: loop.parts.projector.dark, WAIT_S)  # read back from the projector
                status = fresh.get("/status")
                assert status.status_code == 200 and status.json()["state"] == "blanked"
                connections = status.json()["api"]["connections"]
                assert connections["cap"] == cap and connections["evicted"] >= FLOOD - cap
            assert api.process.is_alive() and loop.status()["state"] == "blanked"
        finally:
            for s in socks:
                s.close()


def test_idle_half_sent_streaming_and_oversized_requests_are_cut_off():
    limits = ConnectionLimits(request_timeout_s=0.5, keep_alive_s=0.5, max_header_bytes=4096, max_headers=32,
                              max_connections=8)
    with _session_and_api(limits=limits) as (loop, api, client):
        sends = (b"", b"GET /sta", b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n",
                 b"PATCH /settings HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer " + TOKEN.encode()
                 + b"\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{\"alpha\": ")
        socks = open_with(api.host, api.port, sends, WAIT_S)
        keep_alive = socket.create_connection((api.host, api.port), timeout=WAIT_S)  # idle after one answer
        keep_alive.sendall(b"GET /livez HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert b"200 OK" in keep_alive.recv(4096)
        socks.append(keep_alive)
        trickle = socket.create_connection((api.host, api.port), timeout=WAIT_S)  # bytes do not extend the deadline
        socks.append(trickle)
        try:
            deadline = time.monotonic() + WAIT_S
            while time.monotonic() < deadline and not all(closed_by_server(s) for s in socks):
                with contextlib.suppress(OSError):
                    trickle.send(b"G")
                time.sleep(0.1)
            assert [closed_by_server(s) for s in socks] == [True] * len(socks)
            assert client.get("/status").json()["api"]["connections"]["timed_out"] >= 4  # keep-alive: uvicorn's own
            assert loop.settings().alpha != 100  # the half-sent body was never applied
        finally:
            for s in socks:
                s.close()
        # streams whose requests have all arrived: at the cap the longest-running one gives way
        streams = []
        try:
            for _ in range(12):  # each serving (its first event read) before the next connects
                s = socket.create_connection((api.host, api.port), timeout=WAIT_S)
                streams.append(s)
                s.sendall(b"GET /status/stream?interval=10 HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
                got = b""
                while b"event: status" not in got:
                    chunk = s.recv(65536)
                    assert chunk, "a stream was closed before its first event"
                    got += chunk
            with httpx.Client(base_url=api.url, timeout=WAIT_S) as fresh:
                assert fresh.get("/status").status_code == 200
            assert wait_for(lambda: all(closed_by_server(s) for s in streams[:4]), WAIT_S)
        finally:
            for s in streams:
                s.close()
        r = client.get("/status", headers={f"x-h{i}": "1" for i in range(40)})
        assert r.status_code == 431 and "the limit is 32" in r.json()["detail"] and r.headers["x-frame-options"] == "DENY"
        with httpx.Client(base_url=api.url, timeout=WAIT_S) as fresh:
            assert fresh.get("/status", headers={"x-big": "a" * 8000}).status_code == 431  # whole in one read
            big = socket.create_connection((api.host, api.port), timeout=WAIT_S)  # in pieces: h11's own bound
            with contextlib.suppress(OSError):
                big.sendall(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: ")
                for _ in range(10):
                    time.sleep(0.05)
                    big.sendall(b"a" * 1000)
            big.setblocking(True)
            assert big.recv(4096).startswith(b"HTTP/1.1 400")
            big.close()
            assert fresh.get("/status").status_code == 200


def test_commands_that_change_nothing_cost_the_loop_nothing_and_a_storm_is_limited():
    with _session_and_api(commands_per_s=5.0, command_burst=3) as (loop, api, client):
        def applied() -> int:
            return loop.status()["counters"].get("settings_changes_applied", 0)

        current = client.get("/settings").json()
        same = {"alpha": current["alpha"], "spp": current["spp"]}
        before = applied()
        codes: list[int] = []

        def storm() -> None:
            with httpx.Client(base_url=api.url, timeout=WAIT_S) as c:
                codes.extend(c.patch("/settings", json=same, headers=AUTH).status_code for _ in range(25))

        threads = [threading.Thread(target=storm) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert codes == [200] * 200  # answered, and never limited: they cost nothing
        assert loop.update_settings(same) == loop.settings()  # in the session too, a no-op queues nothing
        n = loop.status()["frame_number"]
        assert wait_for(lambda: loop.status()["frame_number"] > n + 3, WAIT_S)  # frames after the storm
        assert applied() == before

        # a real change is applied once; a storm of them is limited (429 with Retry-After), blank never is
        r = client.patch("/settings", json={"alpha": 0.31}, headers=AUTH)
        assert r.status_code == 200 and wait_for(lambda: applied() == before + 1, WAIT_S)
        t0 = time.monotonic()
        replies = [client.patch("/settings", json={"alpha": 0.1 + i * 1e-3}, headers=AUTH) for i in range(20)]
        elapsed = time.monotonic() - t0
        limited = [r for r in replies if r.status_code == 429]
        admitted = sum(r.status_code == 200 for r in replies)
        assert limited and admitted + len(limited) == 20 and int(limited[0].headers["retry-after"]) >= 1
        assert admitted <= 3 + 5.0 * elapsed  # the burst, then the rate
        assert client.post("/session/blank", headers=AUTH).status_code == 200
        assert client.post("/session/blank", headers=AUTH).status_code == 200


def _storm_keeps_blank_and_status_answering(clients: int, storm_s: float):
    """`clients` storm clients (status, frame, no-op and changing PATCH) for `storm_s`; meanwhile
    the operator's blank on a fresh connection darkens the projector and /status answers."""
    from server.storm import ENDPOINTS, Storm, summarise

    with _session_and_api(commands_per_s=5.0, command_burst=3) as (loop, api, client):
        applied0 = loop.status()["counters"].get("settings_changes_applied", 0)
        with Storm(api.port, clients, TOKEN, timeout_s=WAIT_S) as storm:
            storm.active.set()
            t0 = time.monotonic()
            time.sleep(storm_s / 2)
            with httpx.Client(base_url=api.url, timeout=WAIT_S) as operator:
                assert operator.get("/status").status_code == 200
                assert loop.parts.projector.dark is False
                assert operator.post("/session/blank", headers=AUTH).status_code == 200
                assert wait_for(lambda: loop.parts.projector.dark, WAIT_S)  # read back from the projector
                assert loop.status()["state"] == "blanked"
            time.sleep(storm_s / 2)
        elapsed = time.monotonic() - t0
        records = storm.results()
        assert storm.lost == 0
        got = summarise(records)
        assert all(got[name]["requests"] > 0 for name in ENDPOINTS), got
        for name in ("status", "frame", "patch_noop"):  # answered, never limited (no-op patches cost nothing)
            assert got[name]["codes"] == {"200": got[name]["requests"]}, (name, got[name])
        assert set(got["patch_change"]["codes"]) <= {"200", "429"}, got["patch_change"]
        applied = loop.status()["counters"].get("settings_changes_applied", 0) - applied0
        assert applied <= 3 + 5.0 * (elapsed + 1), (applied, elapsed)  # the burst, then the rate
        assert api.process.is_alive()


def test_blank_and_status_answer_through_a_mixed_request_storm():
    _storm_keeps_blank_and_status_answering(clients=16, storm_s=2.0)


@pytest.mark.slow
def test_blank_and_status_answer_through_a_200_client_mixed_storm():
    _storm_keeps_blank_and_status_answering(clients=200, storm_s=10.0)


def test_the_storm_tools_flood_holds_connections_and_the_probes_reach_both_ports():
    """`server.storm`'s flood keeps its connections up as the API evicts them, and its status
    probes report each port apart."""
    from server.storm import Flood, Probes

    limits = ConnectionLimits(request_timeout_s=600, keep_alive_s=600, max_connections=16)
    with _session_and_api(limits=limits) as (loop, api, client):
        with Flood(api.port, 40) as flood, Probes([api.url, api.operator.url], period_s=0.05) as probes:
            flood.active.set()
            # more than the cap were held at once: the API evicted some, and the flood reopened them
            # (this client's own idle connection may be among the evicted: a failed look is no answer)
            def evicted() -> int:
                try:
                    return client.get("/status").json()["api"]["connections"]["evicted"]
                except httpx.TransportError:
                    return 0

            assert wait_for(lambda: evicted() > 24, WAIT_S)
            probes.active.set()
            time.sleep(1.0)  # a second of probes under the flood
            probes.active.clear()
            flood.active.clear()
        assert flood.opened > 40
        got = probes.summary(["main", "operator"])
        for name in ("main", "operator"):
            assert got[name]["requests"] > 0 and set(got[name]["codes"]) == {"200"}, got
