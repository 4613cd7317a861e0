"""SIGTERM ends a running `dpmhw session start --mock` with the projector dark (read back)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading

import pytest

from dpmhw.tracking import wait_for


@pytest.mark.parametrize("api", [False, True], ids=["loop-only", "with-api"])
def test_sigterm_shuts_down_dark(api):
    args = ["session", "start", "--mock", "--status-every", "0", "--set", "render.width=32", "--set", "render.height=24"]
    args += ["--port", "0"] if api else ["--no-api"]
    env = {**os.environ, "DPMHW_API_TOKEN": "t"}
    proc = subprocess.Popen([sys.executable, "-c", "from dpmhw.cli import main; main()", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        ready = "API on http://127.0.0.1:" if api else "session started"
        assert wait_for(lambda: any(ready in line for line in lines), 60), "".join(lines)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        reader.join(timeout=10)
        proc.stdout.close()
    out = "".join(lines)
    assert "projector dark (idle)" in out and "[stopped]" in out, out
    assert proc.returncode in (0, -signal.SIGTERM)  # uvicorn re-raises SIGTERM after its shutdown
