"""`dpmhw render`: render one frame of a scene to .npy (float32 linear) or .png (sRGB)."""

from __future__ import annotations

import json
import signal
import time as _time
from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli import app


@app.command()
def render(
    scene: Annotated[str, typer.Argument(help="Scene file (TOML) or built-in name: paper-static, paper-dynamic, dpm-bunny.")] = "paper-static",
    out: Annotated[Path, typer.Option("--out", "-o", help=".npy = float32 (H, W, 3) linear radiance; .png = sRGB.")] = Path("frame.png"),
    spp: Annotated[int, typer.Option(min=1, help="Samples (passes) per pixel.")] = 16,
    seed: Annotated[int, typer.Option(min=0, help="Same seed, same image, bit for bit.")] = 0,
    frame: Annotated[Optional[int], typer.Option(min=0, help="Frame index on the scene's timeline (t = frame / fps).")] = None,
    time: Annotated[Optional[float], typer.Option(help="Time in seconds on the scene's timeline.")] = None,
    exposure: Annotated[float, typer.Option(min=0.0, help="Exposure multiplier for .png output.")] = 1.0,
    mesh: Annotated[Optional[Path], typer.Option(help="Mesh to use for built-in scenes' bunny.")] = None,
    threads: Annotated[int, typer.Option(min=1, help="Threads for Embree queries.")] = 2,
) -> None:
    """Render one frame. Ctrl-C stops after the current pass and still writes the finished passes."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn, TimeRemainingColumn

    from dpmhw.errors import DpmhwError
    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.scene_file import load_scene

    if frame is not None and time is not None:
        raise typer.BadParameter("give --frame or --time, not both")
    if out.suffix.lower() not in (".npy", ".png"):
        raise typer.BadParameter(f"--out must end in .npy or .png, got {out.name}")
    try:
        sc = load_scene(scene, mesh_override=mesh)
    except DpmhwError as exc:
        typer.secho(str(exc), fg="red", err=True)
        raise typer.Exit(2)
    for note in sc.notes:
        typer.secho(f"note: {note}", fg="yellow", err=True)
    t = time if time is not None else (frame or 0) / sc.render.fps
    stop = {"requested": False}

    def on_sigint(signum, _frame):
        if stop["requested"]:
            raise KeyboardInterrupt
        stop["requested"] = True
        typer.secho("\nstopping after this pass (Ctrl-C again to abort)…", fg="yellow", err=True)

    previous = signal.signal(signal.SIGINT, on_sigint)
    started = _time.perf_counter()
    try:
        with PathIntegrator(sc, threads=threads) as integrator, Progress(
            "[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            TimeRemainingColumn(), transient=True,
        ) as bar:
            task = bar.add_task(f"rendering {sc.render.width}×{sc.render.height}", total=spp)
            result = integrator.render(
                time=t, seed=seed, spp=spp,
                progress=lambda done, total: bar.update(task, completed=done),
                should_stop=lambda: stop["requested"],
            )
    finally:
        signal.signal(signal.SIGINT, previous)
    elapsed = _time.perf_counter() - started
    _write(out, result, exposure)
    meta = {
        "scene": str(scene), "spp": result.spp, "spp_requested": spp, "seed": seed, "time": t,
        "width": sc.render.width, "height": sc.render.height, "max_bounces": sc.render.max_bounces,
        "nonfinite_samples": result.nonfinite_samples, "seconds": round(elapsed, 3), "notes": sc.notes,
    }
    out.with_name(out.name + ".json").write_text(json.dumps(meta, indent=2))
    typer.echo(f"wrote {out} ({result.spp}/{spp} spp, t = {t:.6f} s, {elapsed:.1f} s)")
    if result.nonfinite_samples:
        typer.secho(f"warning: {result.nonfinite_samples} non-finite samples were dropped (a renderer bug; please report)", fg="red", err=True)


def _write(out: Path, frame, exposure: float) -> None:
    import numpy as np

    from dpmhw.postprocess import to_srgb8, write_png

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".partial" + out.suffix)
    if out.suffix.lower() == ".npy":
        np.save(tmp, frame.radiance.astype(np.float32))
    else:
        write_png(tmp, to_srgb8(frame.radiance, exposure))
    tmp.replace(out)  # never leave a half-written reference behind
