"""The supervisor's parts, fast: the restart policy, the fault answer on the API port (slow
clients included), exit descriptions, the heartbeat's verdict, the bounded idle, pid-named
leftovers, stop reasons in `resume` (the whole supervised session: test_supervisor.py)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import pytest

from dpmhw.child_process import RestartPolicy, describe_exit
from dpmhw.session.safety import SafetyMonitor
from dpmhw.session.supervisor import FaultResponder
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
    api = RestartPolicy(limit=None, window_s=30.0, backoff_s=0.5, max_backoff_s=8.0)  # the API process's
    assert [api.crashed(float(t)) for t in range(7)] == [0.5, 1.0, 2.0, 4.0, 8.0, 8.0, 8.0]
    assert api.crashed(100.0) == 0.5  # served longer than the window: from the start


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
            assert st.headers["x-content-type-options"] == "nosniff" and st.headers["x-frame-options"] == "DENY"
            assert st.headers["content-security-policy"] == "default-src 'none'; frame-ancestors 'none'"
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


def test_heartbeat_says_hung_when_a_lit_loop_has_not_presented_by_its_deadline():
    from dpmhw.session.heartbeat import MARGIN_NS, Heartbeat

    beat, ms = Heartbeat(), 1_000_000
    assert beat.overdue(10_000 * ms)[0] is None  # never lit: nothing to judge
    beat.presented(0, 100 * ms)  # went live at 0: the first frame is due by 100 ms + the margin
    assert beat.overdue(60 * ms) == (None, 40 * ms + MARGIN_NS)
    why, _ = beat.overdue(101 * ms + MARGIN_NS)
    assert why == f"its frame thread has not presented for {101 + MARGIN_NS // ms} ms while lit " \
                  f"(due within {100 + MARGIN_NS // ms} ms)"
    beat.presented(90 * ms, 100 * ms)
    assert beat.overdue(101 * ms + MARGIN_NS)[0] is None
    beat.dark()  # confirmed dark: a hang is no longer judged
    assert beat.overdue(10_000 * ms)[0] is None


def test_slow_clients_hold_up_neither_the_fault_answer_nor_stop():
    sock = bind_api_socket("127.0.0.1", 0)
    address = sock.getsockname()[:2]
    responder = FaultResponder(sock, timeout_s=2.0, max_connections=16)
    slow = []
    try:
        responder.set_status({"state": "fault", "reason": "the loop process (pid 7) killed by SIGKILL"})
        responder.start()
        for i in range(8):  # half a request line, or nothing at all
            c = socket.create_connection(address, timeout=10)
            if i % 2:
                c.sendall(b"GET /sta")
            slow.append(c)
        with httpx.Client(base_url=f"http://{address[0]}:{address[1]}", timeout=10.0) as client:
            assert client.get("/status").json()["state"] == "fault"  # answered beside them
        t0 = time.monotonic()
        responder.stop()
        # bound: one poll of the serving thread (50 ms) on a quiet machine; 1 s of join at most by construction
        assert time.monotonic() - t0 < 1.5
        for c in slow:  # each is dropped after its read timeout (2 s), not held forever
            c.settimeout(30)
            assert c.recv(4096) == b""
    finally:
        responder.stop()
        for c in slow:
            c.close()
        sock.close()


def test_connections_beyond_the_cap_are_closed_at_once():
    sock = bind_api_socket("127.0.0.1", 0)
    responder = FaultResponder(sock, timeout_s=30.0, max_connections=2)
    held = []
    try:
        responder.set_status({"state": "fault", "reason": "x"})
        responder.start()
        held = [socket.create_connection(sock.getsockname()[:2], timeout=10) for _ in range(2)]
        extra = socket.create_connection(sock.getsockname()[:2], timeout=10)  # accepted after them, in order
        extra.settimeout(10)
        assert extra.recv(1) == b""  # closed unread: no third thread
        extra.close()
    finally:
        responder.stop()
        for c in held:
            c.close()
        sock.close()


def test_an_idle_that_never_answers_is_reported_unconfirmed_within_its_deadline(monkeypatch):
    from dpmhw.session import factory
    from dpmhw.session.config import load_session_config
    from dpmhw.session.supervisor import Supervisor

    release = threading.Event()
    calls = []

    def stuck(config, usb):  # a device or emulator that never answers
        calls.append(1)
        release.wait(60)
        return "idle"

    monkeypatch.setattr(factory, "idle_projector", stuck)
    lines: list[str] = []
    sup = Supervisor(load_session_config(None, ['projector.kind="dlpc900"']), echo=lines.append, idle_timeout_s=0.3)
    try:
        t0 = time.monotonic()
        how = sup._make_dark("a test crash")
        took = time.monotonic() - t0
        assert how == "NOT confirmed dark (no answer within 0.3 s)"
        assert lines == ["supervisor: CANNOT CONFIRM THE PROJECTOR IS DARK after a test crash: no answer within 0.3 s"]
        assert took < 5.0  # bound: the 0.3 s deadline, plus a loaded machine's scheduling
        assert sup._make_dark("again").startswith("NOT confirmed") and len(calls) == 1  # waits for the same attempt
        release.set()
        assert sup._make_dark("after") == "dark (idle, read back)"  # that attempt's answer, once it came
    finally:
        release.set()


def test_leftovers_of_dead_owners_are_swept_and_live_ones_kept(tmp_path):
    from dpmhw.child_process import SHARED_SLOTS, OwnedNames
    from server.shared_slot import SharedSlot

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # a pid nobody has now
    names = OwnedNames(str(tmp_path), "dpmhw-slot")
    dead, live, other = f"dpmhw-slot-{proc.pid}-abc", names.new_name(), "dpmhw-slot-notapid"
    for name in (dead, live, other):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / f"dpmhw-slot-{proc.pid}-dir").mkdir()
    assert sorted(names.sweep()) == sorted([dead, f"dpmhw-slot-{proc.pid}-dir"])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live, other])
    slot = SharedSlot.create(64)  # named for this process, so a later run can tell it
    try:
        assert SHARED_SLOTS.owner(slot.name.lstrip("/")) == os.getpid()
        assert os.path.exists(f"/dev/shm/{slot.name.lstrip('/')}") and slot.name.lstrip("/") not in SHARED_SLOTS.sweep()
    finally:
        slot.close()
    assert not os.path.exists(f"/dev/shm/{slot.name.lstrip('/')}")


def test_the_loop_keeps_its_heartbeat_lit_while_projecting_and_dark_once_blanked(make_loop):
    from dpmhw.session.heartbeat import Heartbeat
    from dpmhw.session.testing import wait_for

    loop = make_loop()  # stale 200 ms, watchdog 1 s
    beat = loop.heartbeat = Heartbeat()
    loop.start()
    later = 10_000_000_000  # 10 s on: past any deadline the loop could have set

    def lit() -> bool:
        return beat.overdue(time.monotonic_ns() + later)[0] is not None

    assert wait_for(lambda: loop.status()["state"] == "running" and lit(), 30)
    # each present moves the deadline: it stays ahead of now while frames come
    assert wait_for(lambda: beat.overdue(time.monotonic_ns())[0] is None, 30)
    due_ns = beat.overdue(time.monotonic_ns())[1]
    assert 0 < due_ns <= 1_050_000_000  # at most the 1 s watchdog + the 50 ms margin
    loop.blank()
    assert wait_for(lambda: loop.status()["state"] == "blanked" and not lit(), 30)  # confirmed dark
    assert loop.parts.projector.dark
