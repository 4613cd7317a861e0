"""`dpmhw session start --mock` as an operator runs it: SIGTERM ends it with the projector dark
(read back) and the API process gone; a killed session process takes its API process with it."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading

import pytest

from dpmhw.session.testing import wait_for

WAIT_S = 30  # for what must happen eventually: generous, as only broken code waits this long


def _start(api: bool):
    # api.priority=low: a SCHED_IDLE API process gets next to no CPU beside a CPU hog
    args = ["session", "start", "--mock", "--status-every", "0", "--set", "render.width=32", "--set", "render.height=24",
            "--set", "api.priority=low"]
    args += ["--port", "0"] if api else ["--no-api"]
    env = {**os.environ, "DPMHW_API_TOKEN": "t"}
    proc = subprocess.Popen([sys.executable, "-c", "from dpmhw.cli import main; main()", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    ready = "API on http://127.0.0.1:" if api else "session started"
    if not wait_for(lambda: any(ready in line for line in lines), 120):  # start-up on a loaded machine (as test_supervisor)
        proc.kill()
        pytest.fail("".join(lines))
    port = next((int(m.group(1)) for line in lines if (m := re.search(r"API on http://127\.0\.0\.1:(\d+)", line))), None)
    return proc, lines, reader, port


def _finish(proc, reader) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait(timeout=10)
    reader.join(timeout=10)
    proc.stdout.close()


def _port_closed(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
    except OSError:
        return True
    return False


@pytest.mark.parametrize("api", [False, True], ids=["loop-only", "with-api"])
def test_sigterm_shuts_down_dark(api):
    proc, lines, reader, port = _start(api)
    try:
        if api:
            assert not _port_closed(port)
            assert f"operator page: http://127.0.0.1:{port}/ " in "".join(lines)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    finally:
        _finish(proc, reader)
    out = "".join(lines)
    assert "projector dark (idle)" in out and "[stopped]" in out, out
    assert proc.returncode == 0, out
    if api:
        assert wait_for(lambda: _port_closed(port), WAIT_S), "the API process outlived its session"


def test_killed_session_takes_its_api_process_along():
    proc, lines, reader, port = _start(True)
    try:
        assert not _port_closed(port)
        proc.kill()  # no shutdown code runs in the session process
        proc.wait(timeout=10)
        assert wait_for(lambda: _port_closed(port), WAIT_S), "the API process was orphaned"
    finally:
        _finish(proc, reader)
