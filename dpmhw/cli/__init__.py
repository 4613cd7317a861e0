"""The `dpmhw` command. Each group lives in its own module; heavy imports happen inside commands."""

from __future__ import annotations

import typer

from dpmhw.cli.apps import app

__all__ = ["app", "main"]


def _register() -> None:
    # Importing the command modules attaches their commands to the apps above.
    from dpmhw.cli import render  # noqa: F401
    from dpmhw.cli import bench  # noqa: F401
    from dpmhw.cli import displays  # noqa: F401
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
