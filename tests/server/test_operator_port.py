"""The operator's reserved listener (`server.operator_port`): blank and status whatever happens on
the main API port, one-line refusals of what is malformed or too big, and no client that can hold it.

The listener is checked on its own over test doubles (real sockets, real HTTP), then in the
session process behind `ApiProcess` over a fake session, with the main port flooded and its API
process stopped outright. Bounds: WAIT_S only for what must happen eventually (a loaded 2-core
machine may hold a thread off for seconds); no speed is asserted.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import threading

import httpx
import pytest

from dpmhw.session.testing import fake_session, wait_for
from server.guard import ConnectionLimits
from server.operator_port import OperatorListener
from server.process import ApiProcess
from tests.server.conftest import closed_by_server, open_with

WAIT_S = 60
TOKEN = "operator-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class _Doubles:
    """What the listener calls, counted."""

    def __init__(self):
        self.blanks = 0
        self.failure = ""  # set: the blank fails with this

    def blank(self) -> tuple[bool, str, str]:
        self.blanks += 1
        return (False, self.failure, "fault") if self.failure else (True, "blanked", "blanked")

    def status(self) -> bytes:
        return json.dumps({"state": "running", "blanks": self.blanks}).encode()


class _Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@contextlib.contextmanager
def _listener(**kw):
    doubles = _Doubles()
    sock = socket.create_server(("127.0.0.1", 0))
    listener = OperatorListener(sock, blank=doubles.blank, status=doubles.status, token=TOKEN,
                                trusted_hosts=["127.0.0.1", "localhost"], **kw)
    try:
        with listener:
            yield listener, doubles
    finally:
        sock.close()


def _raw(listener: OperatorListener, data: bytes) -> tuple[int, dict, dict]:
    """Send `data` on a fresh connection; (status code, headers, JSON body) of the answer."""
    with socket.create_connection((listener.host, listener.port), timeout=WAIT_S) as s:
        with contextlib.suppress(OSError):  # the server may answer (and close) before it has read it all
            s.sendall(data)
        got = b""
        while chunk := s.recv(65536):
            got += chunk
    head, _, body = got.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    assert int(headers["content-length"]) == len(body) and headers["connection"] == "close"
    return int(lines[0].split()[1]), headers, json.loads(body) if body else None


def test_blank_and_status_over_plain_http():
    with _listener() as (listener, doubles):
        with httpx.Client(base_url=listener.url, timeout=WAIT_S) as client:
            r = client.get("/status")
            assert r.status_code == 200 and r.json() == {"state": "running", "blanks": 0}
            assert r.headers["content-type"] == "application/json" and r.headers["x-frame-options"] == "DENY"
            r = client.post("/session/blank", headers=AUTH)
            assert r.status_code == 200 and r.json() == {"ok": True, "message": "blanked", "state": "blanked"}
            assert client.post("/session/blank", headers=AUTH, content=b"{}").status_code == 200  # a small body is fine
            assert doubles.blanks == 2
        # HTTP/1.0 with a Host is answered too
        code, _, body = _raw(listener, b"GET /status HTTP/1.0\r\nHost: localhost:1\r\n\r\n")
        assert code == 200 and body["blanks"] == 2
        assert listener.stats()["served"] == 4


@pytest.mark.parametrize("request_bytes, code, words", [
    (b"GARBAGE\r\n\r\n", 400, "malformed request"),
    (b"GET /status HTTP/1.1\r\n\r\n", 400, "Host"),
    (b"GET /status HTTP/1.1\r\nHost: evil.example\r\n\r\n", 400, "'evil.example' is not one"),
    (b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nX: " + b"a" * 20_000 + b"\r\n\r\n", 431, "exceeds 8192 bytes"),
    (b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n" + b"".join(b"X-%d: 1\r\n" % i for i in range(70)) + b"\r\n",
     431, "71 headers; the limit is 64"),
    (b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 5000\r\n\r\n", 401, "missing bearer token"),
    (b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer nope\r\n\r\n", 401, "wrong bearer token"),
    (b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer " + TOKEN.encode()
     + b"\r\nContent-Length: 5000\r\n\r\n", 413, "5000 bytes exceeds the limit of 1024 bytes"),
    (b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer " + TOKEN.encode()
     + b"\r\nTransfer-Encoding: chunked\r\n\r\n" + b"400\r\n" + b"a" * 1024 + b"\r\n" + b"10\r\n" + b"b" * 16 + b"\r\n",
     413, "request body exceeds the limit of 1024 bytes"),
    (b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: x\r\n\r\n", 400, "malformed request"),
    (b"GET /settings HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", 404, "it answers POST /session/blank and GET /status"),
    (b"GET /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", 405, "answers only POST here"),
])
def test_malformed_and_oversized_requests_get_one_line_naming_the_problem(request_bytes, code, words):
    with _listener() as (listener, doubles):
        got, headers, body = _raw(listener, request_bytes)
        assert (got, doubles.blanks) == (code, 0), body
        assert list(body) == ["detail"] and words in body["detail"] and "\n" not in body["detail"]
        assert len(body["detail"]) < 200  # names the problem without echoing the input
        if code == 405:
            assert headers["allow"] == "POST"
        # and the listener goes on answering
        assert _raw(listener, b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")[0] == 200


def test_idle_and_half_sent_connections_time_out_and_never_hold_it():
    with _listener(request_timeout_s=0.3, max_connections=4) as (listener, _):
        sends = (b"", b"GET /sta", b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n",
                 b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer " + TOKEN.encode()
                 + b"\r\nContent-Length: 10\r\n\r\n{")
        socks = open_with(listener.host, listener.port, sends, WAIT_S)
        try:
            answers = [s.recv(4096) for s in socks]  # each gets its 408, then the end
            assert all(a.startswith(b"HTTP/1.1 408 ") and b"no whole request within 0.3 s" in a for a in answers), answers
            assert wait_for(lambda: listener.stats()["open"] == 0, WAIT_S)
            assert listener.stats()["timed_out"] == 4
        finally:
            for s in socks:
                s.close()


def test_at_its_cap_a_new_connection_evicts_the_longest_waiting():
    # requests never time out here: the cap and eviction alone must keep the port reachable
    with _listener(request_timeout_s=600, max_connections=3) as (listener, doubles):
        idle = [socket.create_connection((listener.host, listener.port), timeout=WAIT_S) for _ in range(10)]
        try:
            assert wait_for(lambda: sum(not closed_by_server(s) for s in idle) <= 3, WAIT_S)
            assert not any(closed_by_server(s) for s in idle[-2:])  # the newest kept their places
            code, _, body = _raw(listener, b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer "
                                 + TOKEN.encode() + b"\r\n\r\n")
            assert code == 200 and doubles.blanks == 1
            stats = listener.stats()
            assert stats["evicted"] >= 8 and stats["open"] <= 3
        finally:
            for s in idle:
                s.close()


def test_status_requests_are_rate_limited_and_the_blank_never():
    clock = _Clock()
    with _listener(status_per_s=2.0, clock=clock) as (listener, doubles):
        get = b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
        assert [_raw(listener, get)[0] for _ in range(3)] == [200, 200, 429]
        code, headers, body = _raw(listener, get)
        assert code == 429 and headers["retry-after"] == "1" and "at most 2 per second" in body["detail"]
        blank = b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer " + TOKEN.encode() + b"\r\n\r\n"
        assert [_raw(listener, blank)[0] for _ in range(5)] == [200] * 5
        clock.t += 1.0  # refilled
        assert _raw(listener, get)[0] == 200


def test_a_failed_blank_is_a_500_naming_why():
    with _listener() as (listener, doubles):
        doubles.failure = "RuntimeError: blank read-back failed"
        code, _, body = _raw(listener, b"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer "
                             + TOKEN.encode() + b"\r\n\r\n")
        assert code == 500 and body["detail"] == "the session failed to blank: RuntimeError: blank read-back failed"


def test_blank_and_status_on_the_operator_port_while_the_main_port_is_flooded_and_its_process_stopped():
    """The session's own listener: the main port's connection cap held by idle and half-sent
    connections, and then its API process stopped (SIGSTOP: it answers nothing at all); the
    operator port still answers, and its blank reaches the projector before the answer."""
    loop = fake_session(["governor.enabled=false"]).start()
    limits = ConnectionLimits(request_timeout_s=600, keep_alive_s=600, max_connections=16)
    api = ApiProcess(port=0, token=TOKEN, publish_period_s=0.02, priority="low", limits=limits)
    socks: list[socket.socket] = []
    stopped = False
    try:
        api.start(loop)
        assert api.operator is not None and api.operator.port != api.port
        assert wait_for(lambda: loop.status()["state"] == "running" and not loop.parts.projector.dark, WAIT_S)
        partial = (b"", b"GET /sta", b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        for i in range(64):  # four times the main port's cap
            s = socket.create_connection((api.host, api.port), timeout=WAIT_S)
            with contextlib.suppress(OSError):
                s.sendall(partial[i % 3])
            socks.append(s)
        os.kill(api.process.pid, signal.SIGSTOP)
        stopped = True
        with pytest.raises(httpx.TimeoutException):  # the main port answers nothing now
            httpx.get(f"{api.url}/status", timeout=0.5)
        with httpx.Client(base_url=api.operator.url, timeout=WAIT_S) as operator:
            status = operator.get("/status")
            assert status.status_code == 200 and status.json()["state"] == "running"
            assert status.json()["api"]["operator"]["url"] == api.operator.url and "histograms" not in status.json()
            assert status.json()["snapshot_age_s"] >= 0
            r = operator.post("/session/blank", headers=AUTH)
            assert r.status_code == 200 and r.json()["state"] == "blanked", r.text
            assert loop.parts.projector.dark  # read back before the answer: no waiting for the loop
            assert operator.get("/status").json()["state"] == "blanked"
        assert loop.status()["state"] == "blanked"
        os.kill(api.process.pid, signal.SIGCONT)
        stopped = False
        with httpx.Client(base_url=api.url, timeout=WAIT_S) as main:  # the main API as before
            assert main.get("/status").json()["api"]["operator"]["url"] == api.operator.url
            assert main.post("/session/resume", headers=AUTH).status_code == 200
    finally:
        if stopped:
            os.kill(api.process.pid, signal.SIGCONT)
        for s in socks:
            s.close()
        api.close()
        loop.stop()


def test_blanks_from_several_operators_at_once_are_each_answered():
    """Blanks from several operators at once are each answered (one thread per connection)."""
    loop = fake_session(["governor.enabled=false"]).start()
    api = ApiProcess(port=0, token=TOKEN, publish_period_s=0.02, priority="low")
    try:
        api.start(loop)
        assert wait_for(lambda: not loop.parts.projector.dark, WAIT_S)
        codes: list[int] = []

        def blank() -> None:
            codes.append(httpx.post(f"{api.operator.url}/session/blank", headers=AUTH, timeout=WAIT_S).status_code)

        threads = [threading.Thread(target=blank) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert codes == [200] * 4 and loop.parts.projector.dark and loop.safety.active("operator")
    finally:
        api.close()
        loop.stop()


def test_the_operator_page_alone_may_send_its_blank_here_across_origins():
    """A browser's preflight from the operator page (the API's port at a trusted name) is allowed,
    and its blank's answer is readable there; any other origin is refused and gets no CORS
    header, and a request without an Origin (curl, the CLI) is answered as before."""
    with _listener(page_port=8765) as (listener, doubles):
        def preflight(origin: str) -> tuple[int, dict]:
            code, headers, _ = _raw(listener, (
                "OPTIONS /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nOrigin: " + origin + "\r\n"
                "Access-Control-Request-Method: POST\r\nAccess-Control-Request-Headers: authorization\r\n\r\n"
            ).encode())
            return code, headers

        for origin in ("http://127.0.0.1:8765", "http://localhost:8765"):
            code, headers = preflight(origin)
            assert code == 204 and headers["access-control-allow-origin"] == origin
            assert headers["access-control-allow-methods"] == "POST"
            assert headers["access-control-allow-headers"] == "Authorization"
        for origin in ("http://evil.example:8765", "http://127.0.0.1:9999", "https://127.0.0.1:8765",
                       "http://127.0.0.1:8765/x", "null"):
            code, headers = preflight(origin)
            assert code == 403 and "access-control-allow-origin" not in headers, origin
        assert doubles.blanks == 0  # a preflight never blanks
        code, headers, body = _raw(listener, (
            f"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nOrigin: http://127.0.0.1:8765\r\n"
            f"Authorization: Bearer {TOKEN}\r\nContent-Length: 0\r\n\r\n").encode())
        assert code == 200 and body["ok"] and headers["access-control-allow-origin"] == "http://127.0.0.1:8765"
        code, headers, body = _raw(listener, (
            f"POST /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}\r\n"
            "Content-Length: 0\r\n\r\n").encode())
        assert code == 200 and "access-control-allow-origin" not in headers
        assert doubles.blanks == 2 and listener.stats()["blanks"] == 2
        code, _, body = _raw(listener, b"OPTIONS /status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert code == 405 and "GET" in body["detail"]
    with _listener() as (listener, _):  # no page port given: no origin is the page's
        code, _, _ = _raw(listener, b"OPTIONS /session/blank HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                                    b"Origin: http://127.0.0.1:8765\r\n\r\n")
        assert code == 403
