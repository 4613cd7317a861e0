"""`dpmhw mock natnet …` / `dpmhw mock serial …`: run an emulated tracker standalone.

Useful for testing any NatNet client (ours or a third party's) or a serial tracker client
without hardware. The firmware mocks are imported inside the commands.
"""

from __future__ import annotations

import time
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import mock_app
from dpmhw.cli.choices import NatNetVersion, SerialModel, Trajectory


def _run_until(duration_s: Optional[float], report, every_s: float) -> None:
    """Sleep until interrupted (or `duration_s` elapses), calling `report()` every `every_s`."""
    start = time.monotonic()
    next_report = start + every_s
    try:
        while duration_s is None or time.monotonic() - start < duration_s:
            time.sleep(0.05)
            if every_s > 0 and time.monotonic() >= next_report:
                report()
                next_report += every_s
    except KeyboardInterrupt:
        typer.echo("interrupted, stopping")


@mock_app.command("natnet")
def natnet(
    rate: Annotated[float, typer.Option(min=0.1, max=10000.0, help="Frames per second.")] = 360.0,
    version: Annotated[NatNetVersion, typer.Option(help="NatNet bitstream version.")] = NatNetVersion("4.1"),
    unicast: Annotated[bool, typer.Option("--unicast", help="Send frames to connected clients instead of the multicast group.")] = False,
    interface: Annotated[str, typer.Option(help="Address to serve on (and multicast interface).")] = "127.0.0.1",
    latency_ms: Annotated[float, typer.Option(min=0.0, help="Camera mid-exposure to transmit, milliseconds.")] = 4.5,
    jitter_ms: Annotated[float, typer.Option(min=0.0, help="Extra random send delay, uniform in [0, jitter).")] = 0.0,
    trajectory: Annotated[Trajectory, typer.Option(help="Motion of the simulated bodies.")] = Trajectory("rotate-oscillate"),
    bodies: Annotated[int, typer.Option(min=1, max=1000, help="Number of rigid bodies (ids 1..N).")] = 1,
    command_port: Annotated[int, typer.Option(min=0, max=65535, help="Command port (0: any free port).")] = 1510,
    data_port: Annotated[int, typer.Option(min=1, max=65535, help="Multicast data port (clients join the group on this port, so it must be fixed).")] = 1511,
    group: Annotated[str, typer.Option(help="Multicast group.")] = "239.255.42.99",
    dropout: Annotated[float, typer.Option(min=0.0, max=1.0, help="Probability per body per frame of a tracking dropout.")] = 0.0,
    marker_noise_mm: Annotated[float, typer.Option(min=0.0, help="Std dev of marker noise, millimetres.")] = 0.0,
    truncate_prob: Annotated[float, typer.Option(min=0.0, max=1.0, help="Fault injection: probability per frame of a truncated datagram.")] = 0.0,
    corrupt_prob: Annotated[float, typer.Option(min=0.0, max=1.0, help="Fault injection: probability per frame of a corrupted datagram.")] = 0.0,
    clock_drift_ppm: Annotated[float, typer.Option(help="The server clock runs this many ppm fast.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Seed of every random choice.")] = 0,
    duration: Annotated[Optional[float], typer.Option(min=0.0, help="Stop after this many seconds (default: until Ctrl-C).")] = None,
    status_every: Annotated[float, typer.Option(min=0.0, help="Print a status line every N seconds (0: never).")] = 5.0,
) -> None:
    """Emulated OptiTrack Motive streaming a simulated world over NatNet."""
    from firmware_mocks.natnet_server import NatNetServer, NatNetServerConfig
    from firmware_mocks.world import World

    try:
        world = World.demo(trajectory.value, epoch_s=time.monotonic(), count=bodies)
        cfg = NatNetServerConfig(
            version=version.value, rate_hz=rate, latency_ms=latency_ms, jitter_ms=jitter_ms, unicast=unicast,
            interface=interface, command_port=command_port, data_port=data_port, multicast_group=group,
            dropout_prob=dropout, marker_noise_m=marker_noise_mm / 1000, seed=seed,
            truncate_prob=truncate_prob, corrupt_prob=corrupt_prob, clock_drift_ppm=clock_drift_ppm,
            software_latency_ms=min(0.9, latency_ms),
        )
        server = NatNetServer(world, cfg)
    except (ValueError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from None
    mode = "unicast" if unicast else f"multicast {group}:{data_port}"
    typer.echo(
        f"NatNet {version.value} mock on {interface}:{server.command_port} ({mode}), {rate:g} Hz, "
        f"latency {latency_ms:g} ms, {bodies} rigid bod{'y' if bodies == 1 else 'ies'} on '{trajectory.value}'"
    )
    with server:
        _run_until(
            duration,
            lambda: typer.echo(
                f"frames sent {server.frames_sent}, skipped {server.frames_skipped}, "
                f"faults {dict(server.faults) or 0}, clients {len(server.clients)}"
            ),
            status_every,
        )
    typer.echo(f"stopped after {server.frames_sent} frames")


@mock_app.command("serial")
def serial(
    model: Annotated[SerialModel, typer.Option(help="Record preamble: LY (Liberty), PA (Patriot) or LU (Latus).")] = SerialModel("LY"),
    rate: Annotated[float, typer.Option(min=0.1, max=10000.0, help="Records per second per station in continuous mode.")] = 240.0,
    trajectory: Annotated[Trajectory, typer.Option(help="Motion of the simulated sensors.")] = Trajectory("rotate-oscillate"),
    stations: Annotated[int, typer.Option(min=1, max=16, help="Number of sensors (stations 1..N).")] = 1,
    duration: Annotated[Optional[float], typer.Option(min=0.0, help="Stop after this many seconds (default: until Ctrl-C).")] = None,
) -> None:
    """Emulated Polhemus-style serial tracker on a pseudo-terminal; prints the port path."""
    from firmware_mocks.serial_tracker import PolhemusEmulator
    from firmware_mocks.world import World

    try:
        world = World.demo(trajectory.value, epoch_s=time.monotonic(), count=stations)
        emulator = PolhemusEmulator(world, model=model.value, rate_hz=rate)
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from None
    with emulator:
        typer.echo(f"{model.value} serial tracker on {emulator.pty} (also {emulator.port}; {stations} station(s), "
                   f"{rate:g} Hz)")
        _run_until(duration, lambda: None, 0)
    typer.echo(f"stopped after {emulator.records_sent} records")
