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


@bench_app.command("quality")
def bench_quality(
    quick: Annotated[bool, typer.Option("--quick", help="Quarter resolution (256×192), fewer frames, 256-spp dynamic references: a few minutes.")] = False,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Write the results as JSON here.")] = None,
    out_dir: Annotated[Path, typer.Option(help="Plots (PNG) and image strips go here.")] = Path("bench-quality"),
    cache_dir: Annotated[Optional[Path], typer.Option(help="Reference cache [default: $DPMHW_CACHE/references or ~/.cache/dpmhw/references].")] = None,
    part: Annotated[str, typer.Option(help="static | dynamic | all")] = "all",
    scale: Annotated[Optional[float], typer.Option(min=0.01, max=1.0, help="Override the resolution scale.")] = None,
    ref_spp: Annotated[Optional[int], typer.Option(min=1, help="Override the static reference spp.")] = None,
    dynamic_ref_spp: Annotated[Optional[int], typer.Option(min=1, help="Override the dynamic references' spp.")] = None,
    dynamic_times: Annotated[Optional[str], typer.Option(help="Override the dynamic eval times, comma-separated seconds, e.g. 0.2,0.5.")] = None,
    threads: Annotated[int, typer.Option(min=1)] = 2,
) -> None:
    """Speed against error: PSNR/SSIM against converged references for plain path tracing and
    temporal reuse (static table vs the paper's Table 1, dynamic per-frame error), with costs."""
    import dataclasses

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn, TimeRemainingColumn

    from dpmhw.benchmarks.quality import QualityConfig, format_table, run_quality

    if part not in ("static", "dynamic", "all"):
        raise typer.BadParameter(f"--part must be static, dynamic or all, got {part!r}")
    cfg = QualityConfig.quick() if quick else QualityConfig()
    changes = dict(threads=threads, parts=("static", "dynamic") if part == "all" else (part,))
    if scale is not None:
        changes["scale"] = scale
    if ref_spp is not None:
        changes["ref_spp"] = ref_spp
    if dynamic_ref_spp is not None:
        changes["dynamic_ref_spp"] = dynamic_ref_spp
    if dynamic_times is not None:
        try:
            times = tuple(float(x) for x in dynamic_times.split(","))
        except ValueError:
            raise typer.BadParameter(f"--dynamic-times: expected comma-separated seconds, got {dynamic_times!r}") from None
        if not times or any(not (t >= 0) for t in times):
            raise typer.BadParameter(f"--dynamic-times: expected times ≥ 0, got {dynamic_times!r}")
        changes["dynamic_eval_times"] = times
    cfg = dataclasses.replace(cfg, **changes)
    with Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), transient=True) as bar:
        tasks: dict[str, int] = {}

        def progress(desc: str, done: int, total: int) -> None:
            if desc not in tasks:
                tasks[desc] = bar.add_task(desc, total=total)
            bar.update(tasks[desc], completed=done)

        result = run_quality(cfg, cache_dir=cache_dir, out_dir=out_dir, progress=progress)
    typer.echo(format_table(result))
    for f in result.get("files", []):
        typer.echo(f"wrote {f}")
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=2))
        typer.echo(f"wrote {json_path}")


@bench_app.command("soak")
def bench_soak(
    minutes: Annotated[float, typer.Option(min=0.05, help="How long to run.")] = 30.0,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the results (per fault and per kind) here.")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the fault schedule.")] = 0,
    kinds: Annotated[Optional[str], typer.Option(help="Comma-separated fault kinds [default: all].")] = None,
) -> None:
    """Mock session with random faults (tracker stall/restart, corrupt and foreign datagrams,
    implausible poses, USB stall and unplug, API load): time to dark and to resume per fault kind,
    lit frames while a cause was active, recording rows against frames presented, memory."""
    from dpmhw.benchmarks.soak import FAULT_KINDS, format_table, plot_soak, run_soak

    chosen = tuple(k.strip() for k in kinds.split(",")) if kinds else FAULT_KINDS
    result = run_soak(minutes, seed=seed, kinds=chosen, progress=typer.echo)
    typer.echo(format_table(result))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=2))
        plot_soak(result, json_path.with_suffix(".png"))
        typer.echo(f"wrote {json_path} and {json_path.with_suffix('.png')}")
