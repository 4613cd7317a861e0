"""The supervisor's parts, fast: the restart policy, the fault answer on the API port, exit
descriptions, stop reasons in `resume` (the whole supervised session: test_supervisor.py, slow)."""

from __future__ import annotations

import signal
import socket

import httpx
import pytest

from dpmhw.session.safety import SafetyMonitor
from dpmhw.session.supervisor import FaultResponder, RestartPolicy, describe_exit
from server.process import bind_api_socket


def test_restart_policy_backs_off_and_gives_up_after_the_limit_within_the_window():
    p = RestartPolicy(limit=2, window_s=100.0, backoff_s=1.0)
    assert p.crashed(0.0) == 1.0
    assert p.crashed(10.0) == 2.0  # doubles while the first crash is still in the window
    assert p.crashed(20.0) is None  # a third crash within 100 s: stay dark
    late = RestartPolicy(limit=2, window_s=100.0, backoff_s=1.0)
    assert late.crashed(0.0) == 1.0 and late.crashed(10.0) == 2.0
    assert late.crashed(500.0) == 1.0  # the old crashes fell out of the window
    assert RestartPolicy(limit=0, window_s=100.0, backoff_s=1.0).crashed(0.0) is None  # restart = never


def test_exit_descriptions_name_the_signal_or_the_code():
    assert describe_exit(-signal.SIGKILL) == "killed by SIGKILL"
    assert describe_exit(-signal.SIGABRT) == "killed by SIGABRT"
    assert describe_exit(3) == "exited with code 3"
    assert "exception escaped" in describe_exit(70)
    assert describe_exit(None) == "still running"


def test_fault_responder_answers_only_while_started_and_keeps_the_socket():
    sock = bind_api_socket("127.0.0.1", 0)
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    responder = FaultResponder(sock)
    try:
        responder.set_status({"state": "fault", "reason": "the loop process (pid 7) killed by SIGKILL"})
        responder.start()
        with httpx.Client(base_url=url, timeout=10.0) as client:
            st = client.get("/status")
            assert st.status_code == 200 and st.json()["state"] == "fault" and "SIGKILL" in st.json()["reason"]
            assert client.get("/readyz").status_code == 503 and client.get("/livez").json() == {"live": True}
            r = client.post("/session/resume")
            assert r.status_code == 503 and "the session is down" in r.json()["detail"]
        responder.stop()
        assert sock.fileno() != -1  # still bound, for the next loop process
        with socket.create_connection(sock.getsockname()[:2], timeout=10) as raw:  # queued by the kernel …
            raw.settimeout(0.5)
            raw.sendall(b"GET /status HTTP/1.0\r\n\r\n")
            with pytest.raises(TimeoutError):  # … and answered by nobody
                raw.recv(1)
        responder.start()  # a second down spell
        assert httpx.get(f"{url}/status", timeout=10.0).json()["state"] == "fault"
    finally:
        responder.stop()
        sock.close()


def test_resume_while_projecting_does_not_promise_a_hold_off():
    clock = [0]
    safety = SafetyMonitor(holdoff_s=0.5, clock=lambda: clock[0])
    safety.mark_started()
    ok, message = safety.request_resume()
    assert ok and "nothing to resume" in message and "hold-off" not in message
    safety.operator_blank()
    ok, message = safety.request_resume()
    assert ok and message == "resuming after the 0.5 s hold-off"


def test_black_window_on_the_projector_display_only_when_the_session_used_one(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import open_black_window

    assert open_black_window(load_session_config(None, ["sink.kind=\"recording\""]), mock=False) is None
    assert open_black_window(load_session_config(None, ["sink.kind=\"window\""]), mock=True) is None  # mock: no display
    window = open_black_window(load_session_config(None, ["sink.kind=\"window\"", "sink.display=0"]), mock=False)
    try:
        shot = window.snapshot()
        assert shot.shape[:2] == window.shape and shot.size > 0 and not shot.any()  # full size, all black
    finally:
        window.close()
