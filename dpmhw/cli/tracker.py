"""`dpmhw tracker watch`: a live table of what a NatNet or serial tracker is streaming.

On a terminal the table redraws in place (rich); otherwise one block of lines every `--every`
seconds, so it also works in a log. Drivers are imported inside the command.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import app

tracker_app = typer.Typer(no_args_is_help=True, help="Check a tracker before a session.")
app.add_typer(tracker_app, name="tracker")


def _f(v, digits: int = 1) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _table(watch, title: str):
    from rich.table import Table

    table = Table(title=title, caption=_link_text(watch.link()))
    for col in ("body", "samples", "invalid", "rate Hz", "latency p50 ms", "latency p99 ms", "position m", "age ms"):
        table.add_column(col, justify="right", no_wrap=col == "position m")
    for r in watch.rows():
        pos = "occluded" if r["position_m"] is None else " ".join(f"{v:+.3f}" for v in r["position_m"])
        table.add_row(str(r["body"]), str(r["samples"]), str(r["invalid"]), _f(r["rate_hz"]), _f(r["latency_p50_ms"], 2),
                      _f(r["latency_p99_ms"], 2), pos, _f(r["age_ms"]))
    return table


def _link_text(link: dict) -> str:
    offset = "–" if link["clock_offset_s"] is None else f"{link['clock_offset_s']:+.6f} s"
    return (f"link {link['state']}{' (' + link['reason'] + ')' if link['reason'] else ''}: frames {link['frames']}, "
            f"malformed {link['malformed']}, missed {link['frames_missed']}, out of order {link['out_of_order']}, "
            f"reconnects {link['reconnects']}, clock offset host−device {offset}")


def _lines(watch) -> list[str]:
    out = [_link_text(watch.link())]
    for r in watch.rows():
        pos = "occluded" if r["position_m"] is None else "(" + ", ".join(f"{v:+.3f}" for v in r["position_m"]) + ") m"
        out.append(f"  body {r['body']}: {r['samples']} samples ({r['invalid']} invalid), {_f(r['rate_hz'])} Hz, "
                   f"latency p50 {_f(r['latency_p50_ms'], 2)} / p99 {_f(r['latency_p99_ms'], 2)} ms, {pos}")
    if len(out) == 1:
        out.append("  no rigid bodies yet")
    return out


@tracker_app.command("watch")
def watch(
    natnet: Annotated[Optional[str], typer.Option("--natnet", metavar="SERVER", help="Motive (NatNet) server address.")] = None,
    serial: Annotated[Optional[str], typer.Option("--serial", metavar="PORT", help="Serial tracker port: a device path, pty or pyserial URL.")] = None,
    command_port: Annotated[int, typer.Option(min=1, max=65535, help="NatNet command port.")] = 1510,
    local_interface: Annotated[str, typer.Option(help="This host's address towards the NatNet server.")] = "127.0.0.1",
    baudrate: Annotated[int, typer.Option(min=1, help="Serial baud rate.")] = 115200,
    seconds: Annotated[Optional[float], typer.Option(min=0.1, help="Stop after this many seconds (default: until Ctrl-C).")] = None,
    every: Annotated[float, typer.Option(min=0.1, help="Seconds between updates.")] = 1.0,
    window: Annotated[float, typer.Option(min=0.1, help="Rate and latency cover the last this many seconds.")] = 2.0,
) -> None:
    """Bodies, rate, latency, invalid and dropped frames, and clock offset of a live tracker.
    Exits 1 if no frame arrived at all."""
    from dpmhw.tracker_watch import TrackerWatch

    if (natnet is None) == (serial is None):
        raise typer.BadParameter("give exactly one of --natnet SERVER or --serial PORT", param_hint="--natnet / --serial")
    if natnet is not None:
        from drivers.natnet import NatNetClient

        tracker, title = NatNetClient(natnet, command_port=command_port, local_interface=local_interface), f"NatNet {natnet}:{command_port}"
    else:
        from drivers.serial_tracker import SerialTracker

        tracker, title = SerialTracker(serial, baudrate=baudrate), f"serial {serial}"
    tracker.start()
    watcher = TrackerWatch(tracker, window_s=window)
    deadline = None if seconds is None else time.monotonic() + seconds
    live = None
    try:
        if sys.stdout.isatty():
            from rich.live import Live

            live = Live(_table(watcher, title), refresh_per_second=4, transient=False)
            live.start()
        while deadline is None or time.monotonic() < deadline:
            time.sleep(min(every, max(0.0, deadline - time.monotonic())) if deadline else every)
            watcher.update()
            if live is not None:
                live.update(_table(watcher, title))
            else:
                typer.echo("\n".join(_lines(watcher)))
    except KeyboardInterrupt:
        pass
    finally:
        if live is not None:
            live.stop()
        link = watcher.link()  # before stop(): its state would read "stopped by the user"
        watcher.close()
        tracker.stop()
    if not link["frames"]:
        typer.echo(f"error: no frame from {title}: {link['state']} ({link['reason']})", err=True)
        raise typer.Exit(1)
