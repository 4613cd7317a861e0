"""The Typer apps the command modules attach their commands to, and what they share; apart
from the package so that a command module never imports the package that imports it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import NoReturn

import typer

from dpmhw import __version__

app = typer.Typer(no_args_is_help=True, add_completion=False, help="Dynamic projection mapping: render, bench, mock devices.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks that print and save their tables.")
mock_app = typer.Typer(no_args_is_help=True, help="Run emulated devices (firmware mocks) standalone.")
app.add_typer(bench_app, name="bench")
app.add_typer(mock_app, name="mock")


def write_json(data, path: Path) -> Path:
    """Write a benchmark's result as indented JSON (making the folder); returns the path. Every
    result records its machine (`dpmhw.machine.machine_info`): a dict under "machine", flat rows
    each with its keys prefixed `machine_`."""
    from dpmhw.machine import machine_info

    m = machine_info()
    if isinstance(data, dict):
        data = {**data, "machine": m}
    elif isinstance(data, list):
        data = [{**row, **{f"machine_{k}": v for k, v in m.items()}} if isinstance(row, dict) else row for row in data]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2))
    return path


def report(table: str, data, json_path: Path | None) -> None:
    """A benchmark's table on stdout, and its result as JSON at `json_path` when given."""
    typer.echo(table)
    if json_path is not None:
        typer.echo(f"wrote {write_json(data, json_path)}")


def fail(exc: Exception) -> NoReturn:
    """A refused input or an unusable setup (a `DpmhwError`): its one line, exit status 2."""
    typer.secho(f"error: {exc}", fg="red", err=True)
    raise typer.Exit(2)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"dpmhw {__version__}")
        raise typer.Exit()


@bench_app.callback()
def _bench() -> None:
    """Benchmarks that print and save their tables, each with the machine it ran on."""
    from dpmhw.machine import machine_line

    typer.echo(machine_line())


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """dpmhw command line."""
