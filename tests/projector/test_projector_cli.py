"""`dpmhw projector …` and `dpmhw devices` against the emulated controller."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from dpmhw.cli import _register, app


def _run(*args):
    _register()
    return CliRunner().invoke(app, list(args))


def test_devices_lists_the_mocked_projector_with_firmware_and_status():
    result = _run("devices", "--mock")
    assert result.exit_code == 0, result.output
    assert "serial=EMU0001" in result.output and "firmware=5.3.0" in result.output
    assert "dmd=DLP6500" in result.output and "faults=none" in result.output


def test_projector_list_json_and_status():
    result = _run("projector", "list", "--mock", "--json")
    assert result.exit_code == 0, result.output
    (row,) = json.loads(result.output)
    assert row["serial"] == "EMU0001" and row["display_mode"] == "VIDEO" and row["idle"] is False
    result = _run("projector", "status", "--mock")
    assert result.exit_code == 0 and json.loads(result.output)["firmware"] == "5.3.0"


def test_projector_blank_and_missing_serial():
    result = _run("projector", "blank", "--mock")
    assert result.exit_code == 0 and "dark (idle)" in result.output
    result = _run("projector", "status", "--mock", "--serial", "NOPE")
    assert result.exit_code == 1 and "NOPE" in result.output


def test_projector_status_read_failure_is_an_error_not_a_traceback(monkeypatch):
    from drivers.dlpc900 import DLPC900, DLPC900Timeout

    def times_out(self):
        raise DLPC900Timeout("DLPC900: read timed out")

    monkeypatch.setattr(DLPC900, "status", times_out)
    result = _run("projector", "status", "--mock")
    assert result.exit_code == 1 and "error: DLPC900: read timed out" in result.output
    assert not isinstance(result.exception, DLPC900Timeout)
