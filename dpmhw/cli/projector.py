"""`dpmhw projector …` (and `dpmhw devices`): find, inspect and blank DLPC900 projectors.

`--mock` runs the same commands against the emulated controller (firmware_mocks), which is how
CI and a laptop without a projector exercise them. Drivers are imported inside the commands.
"""

from __future__ import annotations

import contextlib
import json
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import app

projector_app = typer.Typer(no_args_is_help=True, help="DLPC900 projector over USB: list, status, blank.")
app.add_typer(projector_app, name="projector")

MockOpt = Annotated[bool, typer.Option("--mock", help="Use an emulated DLPC900 instead of the USB bus.")]
SerialOpt = Annotated[Optional[str], typer.Option("--serial", help="Serial number, when several are attached.")]


def _bus(mock: bool):
    if not mock:
        return contextlib.nullcontext()
    from firmware_mocks.dlpc900_usb import usb_emulation

    return usb_emulation()


def _describe_all() -> list[dict]:
    from drivers.dlpc900 import DLPC900, DLPC900Error, list_devices

    rows = []
    for info in list_devices():
        row = {"serial": info.serial, "bus": info.bus, "address": info.address}
        try:
            dlp = DLPC900.open(info.serial, settle_s=0)
            try:
                row.update(dlp.status())
            finally:
                dlp.close()  # only looks: no blanking, no state change
        except DLPC900Error as exc:
            row["error"] = str(exc)
        rows.append(row)
    return rows


def _print_rows(rows: list[dict], as_json: bool) -> None:
    if as_json:
        typer.echo(json.dumps(rows, indent=2))
        return
    if not rows:
        typer.echo("no DLPC900 projectors found (USB 0451:c900)")
        return
    for r in rows:
        if "error" in r:
            typer.echo(f"DLPC900 serial={r['serial']} bus={r['bus']} address={r['address']}: {r['error']}")
            continue
        faults = ",".join(r["hardware_faults"]) or "none"
        typer.echo(f"DLPC900 serial={r['serial']} bus={r['bus']} address={r['address']} firmware={r['firmware']} "
                   f"dmd={r['dmd']} mode={r['display_mode']} sequencer={'running' if r['sequencer_running'] else 'stopped'} "
                   f"idle={r['idle']} standby={r['standby']} parked={r['parked']} faults={faults}")


def _require_usb_backend() -> None:
    """Exit 1 naming the cause when pyusb has no backend: an empty list would read as "no projector"."""
    import usb.core

    try:
        usb.core.find(idVendor=0xFFFF, idProduct=0xFFFF)  # any query raises NoBackendError without libusb
    except usb.core.NoBackendError:
        typer.echo("error: cannot look for projectors: pyusb found no USB backend; install libusb-1.0 "
                   "(apt install libusb-1.0-0)", err=True)
        raise typer.Exit(1) from None


@projector_app.command("list")
def list_cmd(mock: MockOpt = False, as_json: Annotated[bool, typer.Option("--json", help="Print JSON rows.")] = False) -> None:
    """Attached projectors with firmware version and status."""
    with _bus(mock):
        if not mock:
            _require_usb_backend()
        _print_rows(_describe_all(), as_json)


@projector_app.command()
def status(serial: SerialOpt = None, mock: MockOpt = False) -> None:
    """Full status of one projector as JSON."""
    from drivers.dlpc900 import DLPC900, DLPC900Error

    with _bus(mock):
        try:
            dlp = DLPC900.open(serial, settle_s=0)
            try:
                typer.echo(json.dumps(dlp.status(), indent=2))
            finally:
                dlp.close()
        except DLPC900Error as exc:  # opening or reading (a timeout, an unplug): no traceback
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1)


@projector_app.command()
def blank(serial: SerialOpt = None, mock: MockOpt = False) -> None:
    """Stop the sequence and make the projector dark, confirmed by read-back."""
    from drivers.dlpc900 import DLPC900, DLPC900Error

    with _bus(mock):
        try:
            dlp = DLPC900.open(serial, settle_s=0)
            try:
                report = dlp.blank()
            finally:
                dlp.close()
        except DLPC900Error as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1)
        typer.echo(f"dark ({report.method}), confirmed by read-back")


def _register_devices() -> None:
    """`dpmhw devices`: the projector part of the device listing (unless another group owns it)."""
    if any(c.name == "devices" for c in app.registered_commands):
        return

    @app.command("devices")
    def devices(mock: MockOpt = False, as_json: Annotated[bool, typer.Option("--json", help="Print JSON rows.")] = False) -> None:
        """Attached devices (projectors: firmware version and status)."""
        list_cmd(mock=mock, as_json=as_json)


_register_devices()
