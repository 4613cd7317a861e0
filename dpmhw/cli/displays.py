"""`dpmhw displays`: the attached displays and which one can carry the projector's image.

The window sink needs the display that feeds the projector (`sink.display`) to run at the
projector's native size, the session's output size (`session.factory.output_size`: the
calibration's or the scene camera's size, or render.width × height).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import app


def describe_displays(found, native: tuple[int, int], configured: int) -> list[str]:
    """The lines `dpmhw displays` prints for `found` (a `drivers.displays.DisplayList`), given
    the projector's native size and the configured `sink.display`."""
    if not found.displays:
        return [found.problem]
    lines = []
    for d in found.displays:
        hz = f" @ {d.refresh_hz[0]} Hz" if d.refresh_hz else " (refresh rate not reported)"
        more = f" (also {', '.join(map(str, d.refresh_hz[1:]))} Hz)" if len(d.refresh_hz) > 1 else ""
        marks = [m for m, on in (("projector's native size", d.size == native),
                                 ("sink.display", d.index == configured)) if on]
        name = f" {d.name!r}" if d.name else ""
        lines.append(f"display {d.index}:{name} {d.size[0]}×{d.size[1]}{hz}{more}"
                     + (f"  <- {', '.join(marks)}" if marks else ""))
    if configured >= len(found.displays):
        lines.append(f"sink.display = {configured}: no such display ({len(found.displays)} attached)")
    size = f"{native[0]}×{native[1]}"
    matching = [d.index for d in found.displays if d.size == native]
    if not matching:
        lines.append(f"no display runs at the projector's native {size}: set the projector's display to that mode "
                     "(or calibrate/configure the projector's real size)")
    elif configured in matching:
        lines.append(f"sink.display = {configured} runs at the projector's native {size}")
    else:
        lines.append(f"sink.display = {configured} is not at the projector's native {size}; "
                     f"display {' or '.join(map(str, matching))} is: set sink.display = {matching[0]}")
    return lines


@app.command("displays")
def displays(
    config: Annotated[Optional[Path], typer.Option("--config", "-c", envvar="DPMHW_SESSION_CONFIG",
                                                   help="Session TOML file whose projector size to match (default: built-in defaults).")] = None,
    sets: Annotated[Optional[list[str]], typer.Option("--set", help="Override a field: section.field=value (repeatable).")] = None,
) -> None:
    """List the attached displays (index, name, desktop size, refresh rates) and say which runs at
    the projector's native size, the session's output size."""
    from drivers.displays import attached_displays
    from dpmhw.errors import DpmhwError
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import output_size

    try:
        cfg = load_session_config(config, list(sets or []))
        native = output_size(cfg)
    except (DpmhwError, ValueError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2)
    for line in describe_displays(attached_displays(), native, cfg.sink.display):
        typer.echo(line)
