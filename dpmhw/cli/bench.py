"""`dpmhw bench …`: benchmarks that print a table and can save it as JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli import bench_app


@bench_app.command("render")
def bench_render(
    scene: Annotated[str, typer.Argument(help="Scene file or built-in name.")] = "paper-static",
    frames: Annotated[int, typer.Option(min=3, help="Timed frames (the median is reported).")] = 9,
    threads: Annotated[int, typer.Option(min=1)] = 2,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the results as JSON here.")] = None,
    mesh: Annotated[Optional[Path], typer.Option(help="Mesh for the built-in scenes' bunny.")] = None,
) -> None:
    """Median ms per 1-spp frame, rays per frame, and raw Embree throughput on the same scene."""
    from dpmhw.benchmarks.render import bench_render as run, format_table

    result = run(scene, frames=frames, threads=threads, mesh=mesh)
    typer.echo(format_table(result))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=2))
        typer.echo(f"wrote {json_path}")
