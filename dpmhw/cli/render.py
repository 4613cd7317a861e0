"""`dpmhw render`: render one frame of a scene to .npy (float32 linear) or .png (sRGB), or, with
`--frames K`, K frames of its timeline at 1 spp each through temporal reuse."""

from __future__ import annotations

import json
import signal
import time as _time
from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import app, fail
from dpmhw.cli.choices import PixelSampling, ReuseMode, Tonemap
from dpmhw.cli.optional_value import optional_values
from dpmhw.progress import Progress


@app.command(cls=optional_values({"--ray": "local"}))
def render(
    scene: Annotated[str, typer.Argument(help="Scene file (TOML) or built-in name: paper-static, paper-dynamic, dpm-bunny.")] = "paper-static",
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help=".npy = float32 (H, W, 3) linear radiance; .png = sRGB; the parameters go to FILE.png.json (FILE.npy.json) beside it [default: frame.png; with --frames and --out-dir: none, the frames go to DIR only].")] = None,
    spp: Annotated[Optional[int], typer.Option(min=1, help="Samples (passes) per pixel [default: 16; 1 per frame with --frames].")] = None,
    seed: Annotated[int, typer.Option(min=0, help="Same seed, same image, bit for bit.")] = 0,
    frame: Annotated[Optional[int], typer.Option(min=0, help="Frame index on the scene's timeline (t = frame / fps).")] = None,
    time: Annotated[Optional[float], typer.Option(help="Time in seconds on the scene's timeline.")] = None,
    exposure: Annotated[float, typer.Option(min=0.0, help="Exposure multiplier for .png output.")] = 1.0,
    mesh: Annotated[Optional[Path], typer.Option(help="Mesh to use for built-in scenes' bunny.")] = None,
    threads: Annotated[int, typer.Option(min=1, help="Threads for Embree queries.")] = 2,
    frames: Annotated[Optional[int], typer.Option(min=1, help="Render K frames of the timeline (frame k: seed S+k, t = (F+k)/fps) through temporal reuse.")] = None,
    reuse: Annotated[ReuseMode, typer.Option(help="With --frames: off, same-pixel (paper's method 2) or motion (method 1).")] = ReuseMode("same-pixel"),
    alpha: Annotated[float, typer.Option(help="With --frames: EMA weight of the new frame, in (0, 1].")] = 0.2,
    warmup: Annotated[bool, typer.Option("--warmup", help="With --frames: α_eff = max(α, 1/n) after each reset.")] = False,
    split_screen: Annotated[bool, typer.Option("--split-screen", help="With --frames: left half plain, right half reused.")] = False,
    out_dir: Annotated[Optional[Path], typer.Option(help="With --frames: write every frame here as frame_00000.png (or the suffix of --out), and the parameters as frames.json.")] = None,
    tonemap: Annotated[Tonemap, typer.Option(help="Tone-mapping operator for .png output.")] = Tonemap("clip"),
    pixel_sampling: Annotated[PixelSampling, typer.Option(help="Single frame: jitter (converges to the pixel integral) or centre (pixel centres).")] = PixelSampling("jitter"),
    ray: Annotated[Optional[str], typer.Option(metavar="[ADDRESS]", help="Render the passes as Ray tasks (same image, bit for bit): no address or 'local' = a Ray instance on this machine, or a cluster's ray://HOST:10001 / HOST:6379 / auto (docs/cluster.md). A bare --ray goes last or before another option.")] = None,
) -> None:
    """Render one frame, or K frames through temporal reuse. Ctrl-C stops after the current pass
    (or frame) and still writes what is finished."""
    from dpmhw.cluster.passes import PASSES_PER_BLOCK, render_local
    from dpmhw.cluster.ray_pool import connect
    from dpmhw.errors import DpmhwError
    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.scene_file import load_scene

    if frame is not None and time is not None:
        raise typer.BadParameter("give --frame or --time, not both")
    if out is None and not (frames is not None and out_dir is not None):
        out = Path("frame.png")
    if out is not None and out.suffix.lower() not in (".npy", ".png"):
        raise typer.BadParameter(f"--out must end in .npy or .png, got {out.name}")
    tonemap = tonemap.value
    if frames is not None:
        from dpmhw.reconstruct.reuse import ReuseError, ReuseSettings

        try:
            settings = ReuseSettings(alpha, reuse.value, warmup, split_screen)
        except ReuseError as exc:  # alpha out of range: name the option, not the library's field
            raise typer.BadParameter(str(exc).removeprefix("alpha: "), param_hint="--alpha") from None
    elif out_dir is not None or split_screen or warmup:
        raise typer.BadParameter("--out-dir, --split-screen and --warmup need --frames")
    if frames is not None and ray is not None:
        raise typer.BadParameter("--ray renders one frame's passes; a --frames sequence is sequential (temporal reuse)")
    spp = spp if spp is not None else (1 if frames is not None else 16)
    try:
        sc = load_scene(scene, mesh_override=mesh)
    except DpmhwError as exc:
        typer.secho(str(exc), fg="red", err=True)
        raise typer.Exit(2)
    for note in sc.notes:
        typer.secho(f"note: {note}", fg="yellow", err=True)
    t = time if time is not None else (frame or 0) / sc.render.fps
    if frames is not None:
        _render_sequence(scene, sc, out, out_dir, t * sc.render.fps, frames, spp, seed, settings, exposure, tonemap, threads)
        return
    try:
        pool = connect(ray)
    except DpmhwError as exc:
        fail(exc)
    stop = {"requested": False}

    def on_sigint(signum, _frame):
        if stop["requested"]:
            raise KeyboardInterrupt
        stop["requested"] = True
        typer.secho("\nstopping after this pass (Ctrl-C again to abort)…", fg="yellow", err=True)

    previous = signal.signal(signal.SIGINT, on_sigint)
    started = _time.perf_counter()
    try:
        with Progress() as bar:
            where = "" if pool is None else f" on Ray ({pool.cpus} CPUs)"
            task = bar.task(f"rendering {sc.render.width}×{sc.render.height}{where}, passes", total=spp)
            on_pass = lambda done, total: task.update(done, total)  # noqa: E731
            options = {"pixel_sampling": pixel_sampling.value}  # PathIntegrator keyword arguments: the same here and on every worker
            if pool is None:
                with PathIntegrator(sc, threads=threads, **options) as integrator:
                    result = render_local(integrator, t, seed, spp, progress=on_pass, should_stop=lambda: stop["requested"])
            else:
                from dpmhw.cluster.ray_pool import render_on_ray

                result = render_on_ray(pool, sc, t, seed, spp, threads=threads, progress=on_pass,
                                       should_stop=lambda: stop["requested"], integrator_options=options)
    finally:
        signal.signal(signal.SIGINT, previous)
        if pool is not None:
            pool.close()
    elapsed = _time.perf_counter() - started
    _write(out, result.radiance, exposure, tonemap)
    meta = {
        "scene": str(scene), "spp": result.spp, "spp_requested": spp, "seed": seed, "time": t,
        "width": sc.render.width, "height": sc.render.height, "max_bounces": sc.render.max_bounces,
        "nonfinite_samples": result.nonfinite_samples, "seconds": round(elapsed, 3), "notes": sc.notes,
        "passes_per_block": PASSES_PER_BLOCK, "ray": ray,
    }
    out.with_name(out.name + ".json").write_text(json.dumps(meta, indent=2))
    typer.echo(f"wrote {out} ({result.spp}/{spp} spp, t = {t:.6f} s, {elapsed:.1f} s)")
    if result.nonfinite_samples:
        typer.secho(f"warning: {result.nonfinite_samples} non-finite samples were dropped (a renderer bug; please report)", fg="red", err=True)


def _write(out: Path, radiance, exposure: float, tonemap: str = "clip") -> None:
    import numpy as np

    from dpmhw.postprocess import postprocess, write_png

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".partial" + out.suffix)
    if out.suffix.lower() == ".npy":
        np.save(tmp, radiance.astype(np.float32))
    else:
        write_png(tmp, postprocess(radiance, exposure, tonemap))
    tmp.replace(out)  # never leave a half-written reference behind


def _render_sequence(scene_arg, sc, out: Path | None, out_dir, start_frame: float, frames: int, spp: int, seed: int, settings,
                     exposure: float, tonemap: str, threads: int) -> None:
    """K frames at `spp` each (seed S+k) through one TemporalReuse; the last output goes to
    `out` if given, every output to `out_dir` if given. Ctrl-C stops after the current frame."""
    import numpy as np

    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.reconstruct.reuse import TemporalReuse

    suffix = (out or Path("frame.png")).suffix.lower()
    from dpmhw.sequence import run_sequence

    stop = {"requested": False}

    def on_sigint(signum, _frame):
        if stop["requested"]:
            raise KeyboardInterrupt
        stop["requested"] = True
        typer.secho("\nstopping after this frame (Ctrl-C again to abort)…", fg="yellow", err=True)

    reuser = TemporalReuse(sc.render.width, sc.render.height, settings.alpha, settings.mode, settings.warmup, settings.split_screen)
    previous = signal.signal(signal.SIGINT, on_sigint)
    started = _time.perf_counter()
    render_ms, reuse_ms, nonfinite, last = [], [], 0, None
    try:
        with PathIntegrator(sc, threads=threads) as integrator, Progress() as bar:
            task = bar.task(f"{sc.render.width}×{sc.render.height} frames, reuse {settings.label}", total=frames)
            for step in run_sequence(integrator, sc, frames, [reuser], seed=seed, start_frame=start_frame, spp=spp,
                                     should_stop=lambda: stop["requested"]):
                last = step
                render_ms.append(step.render_ms)
                reuse_ms.append(step.reuse_ms[0])
                nonfinite += step.frame.nonfinite_samples
                if out_dir is not None:
                    _write(Path(out_dir) / f"frame_{step.index:05d}{suffix}", step.outputs[0], exposure, tonemap)
                task.update(step.index + 1)
    finally:
        signal.signal(signal.SIGINT, previous)
    elapsed = _time.perf_counter() - started
    if out is not None:
        _write(out, last.outputs[0], exposure, tonemap)
    meta = {
        "scene": str(scene_arg), "frames": len(render_ms), "frames_requested": frames, "spp_per_frame": spp, "seed": seed,
        "seeds": [seed, seed + len(render_ms) - 1], "start_frame": start_frame, "time": last.time, "fps": sc.render.fps,
        "reuse": settings.mode, "alpha": settings.alpha, "warmup": settings.warmup, "split_screen": settings.split_screen,
        "width": sc.render.width, "height": sc.render.height, "max_bounces": sc.render.max_bounces,
        "render_ms_median": float(np.median(render_ms)), "reuse_ms_median": float(np.median(reuse_ms)),
        "nonfinite_samples": nonfinite, "nonfinite_reuse_inputs": reuser.nonfinite_total,
        "seconds": round(elapsed, 3), "notes": sc.notes, "out_dir": None if out_dir is None else str(out_dir),
    }
    sidecar = out.with_name(out.name + ".json") if out is not None else Path(out_dir) / "frames.json"
    sidecar.write_text(json.dumps(meta, indent=2))
    wrote = f"{out}" if out is not None else f"{len(render_ms)} frames to {out_dir}"
    typer.echo(f"wrote {wrote} (frame {len(render_ms)}/{frames}, reuse {settings.label}, t = {last.time:.6f} s, "
               f"render {meta['render_ms_median']:.1f} ms + reuse {meta['reuse_ms_median']:.1f} ms per frame, {elapsed:.1f} s)")
    if nonfinite:
        typer.secho(f"warning: {nonfinite} non-finite samples were dropped (a renderer bug; please report)", fg="red", err=True)
