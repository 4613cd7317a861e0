"""While the kernels compile ahead of a first show, the API port (and the operator port) says so: `/status` gives the
state `compiling` with the progress, and the operator page's address a page that says it in words."""

from __future__ import annotations

import json
import socket
import urllib.error
import urllib.request

from dpmhw.session import warmup
from dpmhw.session.config import load_session_config
from dpmhw.session.supervisor import Supervisor
from dpmhw.session.warmup import CompileProgress


def _get(port: int, path: str) -> tuple[int, str, str]:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as r:
            return r.status, r.headers["Content-Type"], r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.headers["Content-Type"], e.read().decode()


def test_the_api_port_says_compiling_with_progress(monkeypatch):
    sock, operator_sock = socket.create_server(("127.0.0.1", 0)), socket.create_server(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    seen: dict = {}

    def compile_kernels(config, *, progress, should_stop, **kw):
        seen["before"] = json.loads(_get(port, "/status")[2])  # answered before any progress
        p = CompileProgress(done=3, expected=37, elapsed_s=4.2, eta_s=20.0, groups_left=["path tracing"])
        progress(p)
        seen["status"] = _get(port, "/status")
        seen["operator"] = _get(operator_sock.getsockname()[1], "/status")  # the operator's port says the same
        seen["page"] = _get(port, "/")
        p.groups_left, p.done, p.elapsed_s = [], 37, 30.0
        progress(p)
        return p

    monkeypatch.setattr(warmup, "compile_kernels", compile_kernels)
    lines: list[str] = []
    sup = Supervisor(load_session_config(None), sock=sock, operator_sock=operator_sock, echo=lines.append)
    try:
        assert sup._ready_kernels() and sup.compile_s == 30.0
    finally:
        for responder in sup.responders:
            responder.stop()
        sock.close()
        operator_sock.close()
    assert seen["operator"] == seen["status"]
    assert seen["before"]["state"] == "starting" and not seen["before"]["output_on"]
    code, kind, body = seen["status"]
    status = json.loads(body)
    assert code == 200 and status["state"] == "compiling" and not status["output_on"]
    assert status["compile"] == {"done": 3, "expected": 37, "elapsed_s": 4.2, "eta_s": 20.0, "groups_left": ["path tracing"]}
    assert "3/37 kernels" in status["reason"] and "about 20 s left" in status["reason"]
    code, kind, page = seen["page"]
    assert code == 503 and kind.startswith("text/html") and "compiling" in page and "3/37 kernels" in page
    assert lines[0].startswith("compiling the render kernels") and lines[-1].endswith("done")


def test_a_stop_while_compiling_starts_no_loop_process(monkeypatch):
    def compile_kernels(config, *, progress, should_stop, **kw):
        sup.request_stop("interrupted (Ctrl-C)")
        assert should_stop()
        return CompileProgress(stopped=True)

    monkeypatch.setattr(warmup, "compile_kernels", compile_kernels)
    lines: list[str] = []
    sup = Supervisor(load_session_config(None, ["projector.kind=none"]), mock=True, echo=lines.append)
    monkeypatch.setattr(sup, "_start_child", lambda: (_ for _ in ()).throw(AssertionError("a loop process was started")))
    assert sup.run() == 0
    assert lines[-1] == "supervisor: stopped (interrupted (Ctrl-C))"
