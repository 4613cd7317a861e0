"""`dpmhw mock natnet` / `dpmhw mock serial`: the standalone emulators behind the CLI."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import sys

from typer.testing import CliRunner

from dpmhw.cli import _register, app
from dpmhw.session.testing import wait_for
from drivers.natnet import NatNetClient

from .conftest import free_udp_port

WAIT_S = 30  # for what must happen eventually: generous, as only broken code waits this long

_register()
runner = CliRunner()


def test_natnet_help_lists_the_documented_options():
    result = runner.invoke(app, ["mock", "natnet", "--help"])
    assert result.exit_code == 0
    for option in ("--rate", "--version", "--unicast", "--interface", "--latency-ms", "--trajectory"):
        assert option in result.output


def test_natnet_rejects_an_unsupported_version():
    result = runner.invoke(app, ["mock", "natnet", "--version", "2.9", "--command-port", "0", "--duration", "0"])
    assert result.exit_code == 2
    assert "Invalid value for '--version'" in result.output and "'2.9' is not one of" in result.output


def test_natnet_command_serves_a_real_client():
    # run until interrupted, not for a fixed `--duration`: a loaded machine may spend most of a
    # second or two starting the mock and connecting, so a fixed lifetime was a wall-clock window
    port = free_udp_port()
    with natnet_mock_process("--version", "4.2", "--rate", "200", "--command-port", str(port), "--trajectory",
                             "circular", "--bodies", "2", "--truncate-prob", "0.2", "--seed", "3") as proc:
        client = NatNetClient(command_port=port, connect_timeout_s=0.5, backoff_initial_s=0.05)
        with client:
            assert wait_for(lambda: client.status().frames >= 20, WAIT_S), client.status()
            assert client.version == (4, 2)
            assert client.rigid_body_names() == {1: "circular_1", 2: "circular_2"}
            assert wait_for(lambda: client.status().malformed >= 3, WAIT_S)  # the injected truncations
    assert proc.returncode == 0, proc.output
    assert "NatNet 4.2 mock on 127.0.0.1" in proc.output and "stopped after" in proc.output


def test_serial_command_prints_its_port():
    result = runner.invoke(app, ["mock", "serial", "--model", "PA", "--duration", "0.2"])
    assert result.exit_code == 0
    assert "PA serial tracker on /dev/pts/" in result.output


@contextlib.contextmanager
def natnet_mock_process(*args: str):
    """`dpmhw mock natnet --unicast --status-every 0 ARGS` in its own process, stopped by Ctrl-C
    (SIGINT) on leaving; its output is `proc.output` afterwards."""
    # Ctrl-C as in a terminal: a child of a background job without job control starts with SIGINT
    # ignored (POSIX shells), and Python then installs no KeyboardInterrupt handler (a hog run did that)
    child = "import signal; signal.signal(signal.SIGINT, signal.default_int_handler); from dpmhw.cli import main; main()"
    proc = subprocess.Popen([sys.executable, "-c", child, "mock", "natnet", "--unicast", "--status-every", "0", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        yield proc
        proc.send_signal(signal.SIGINT)
        proc.output, _ = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.output, _ = proc.communicate()


def test_natnet_command_runs_until_interrupted():
    port = free_udp_port()
    with natnet_mock_process("--command-port", str(port)) as proc:
        client = NatNetClient(command_port=port, connect_timeout_s=0.5, backoff_initial_s=0.1)
        with client:
            assert wait_for(lambda: client.status().frames >= 20, WAIT_S), client.status()
    assert proc.returncode == 0, proc.output
    assert "interrupted, stopping" in proc.output and "stopped after" in proc.output


def test_natnet_command_reports_a_busy_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        result = runner.invoke(app, ["mock", "natnet", "--command-port", str(port), "--duration", "0"])
    assert result.exit_code == 2 and "Address already in use" in result.output
