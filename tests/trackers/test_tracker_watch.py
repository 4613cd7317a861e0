"""`dpmhw tracker watch` against the NatNet mock on loopback (and its bad-input paths)."""

from __future__ import annotations

import re
import time

from typer.testing import CliRunner

from dpmhw.cli import _register, app
from firmware_mocks.natnet_server import NatNetServer, NatNetServerConfig
from firmware_mocks.world import World

runner = CliRunner()


def flat(output: str) -> str:
    """The output without rich's error box and line wrapping."""
    return " ".join(re.sub("[│╭╮╰╯─]", " ", output).split())


def test_watch_reports_bodies_rate_latency_and_invalid_samples():
    _register()
    world = World.demo("circular", epoch_s=time.monotonic(), count=2)
    cfg = NatNetServerConfig(unicast=True, command_port=0, rate_hz=200.0, latency_ms=4.0, dropout_prob=0.2, seed=3)
    with NatNetServer(world, cfg) as server:
        result = runner.invoke(app, ["tracker", "watch", "--natnet", "127.0.0.1", "--command-port", str(server.command_port),
                                     "--seconds", "2.5", "--every", "0.5"])
    assert result.exit_code == 0, result.output
    blocks = result.output.strip().split("link ")[1:]
    assert any(b.startswith("streaming") for b in blocks)  # the last may read stale on a loaded machine
    last = blocks[-1]
    assert "malformed 0" in last and "clock offset host−device" in last
    bodies = {int(m.group(1)): m for m in re.finditer(
        r"body (\d+): (\d+) samples \((\d+) invalid\), ([\d.]+|–) Hz, latency p50 ([\d.]+|–)", last)}
    assert set(bodies) == {1, 2}
    for m in bodies.values():
        samples, invalid = int(m.group(2)), int(m.group(3))
        assert samples > 50 and 0 < invalid < samples  # dropout 0.2 → some occluded samples, not all
        if m.group(4) != "–":
            assert float(m.group(4)) <= 260  # the mock sends 200 Hz: never counted twice
        if m.group(5) != "–":
            assert float(m.group(5)) >= 4.0  # never below the mock's exposure-to-transmit latency


def test_watch_without_a_server_exits_1_with_the_reason():
    _register()
    result = runner.invoke(app, ["tracker", "watch", "--natnet", "127.0.0.1", "--command-port", "9", "--seconds", "1.5"])
    assert result.exit_code == 1
    assert "no frame from NatNet 127.0.0.1:9" in result.output and "no server info" in result.output


def test_watch_needs_exactly_one_source():
    _register()
    for args in ([], ["--natnet", "a", "--serial", "b"]):
        result = runner.invoke(app, ["tracker", "watch", *args])
        assert result.exit_code == 2 and "--natnet SERVER or --serial PORT" in flat(result.output)
