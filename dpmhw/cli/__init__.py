"""The `dpmhw` command. Each group lives in its own module; heavy imports happen inside commands."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from dpmhw import __version__

app = typer.Typer(no_args_is_help=True, add_completion=False, help="Dynamic projection mapping: render, bench, mock devices.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks that print and save their tables.")
mock_app = typer.Typer(no_args_is_help=True, help="Run emulated devices (firmware mocks) standalone.")
app.add_typer(bench_app, name="bench")
app.add_typer(mock_app, name="mock")


def write_json(data, path: Path) -> Path:
    """Write a benchmark's result as indented JSON (making the folder); returns the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2))
    return path


def _version(value: bool) -> None:
    if value:
        typer.echo(f"dpmhw {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """dpmhw command line."""


def _register() -> None:
    # Importing the command modules attaches their commands to the apps above.
    from dpmhw.cli import render  # noqa: F401
    from dpmhw.cli import bench  # noqa: F401
    import importlib

    for optional in ("dpmhw.cli.mock", "dpmhw.cli.calibrate", "dpmhw.cli.projector", "dpmhw.cli.session",
                     "dpmhw.cli.tracker", "dpmhw.cli.warmup"):
        try:
            importlib.import_module(optional)
        except ModuleNotFoundError as exc:  # a group another issue has not landed yet
            if exc.name != optional:
                raise
    _plain_help(app)


def _plain_help(typer_app: typer.Typer) -> None:
    """Help as plain text for every group: Rich markup would eat bracketed text such as
    "[default: …]" from help strings, and plain help reads the same in a terminal and a log."""
    typer_app.rich_markup_mode = None
    for group in typer_app.registered_groups:
        _plain_help(group.typer_instance)


def main() -> None:
    _register()
    app()
