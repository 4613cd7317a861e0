"""`dpmhw bench …`: benchmarks that print a table and can save it as JSON."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import bench_app, fail, report, write_json
from dpmhw.cli.choices import BenchTrajectory, QualityPart
from dpmhw.cli.optional_value import optional_values
from dpmhw.cli.session import SetOpt
from dpmhw.progress import Progress


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
    report(format_table(result), result, json_path)


@bench_app.command("quality", cls=optional_values({"--ray": "local"}))
def bench_quality(
    quick: Annotated[bool, typer.Option("--quick", help="Quarter resolution (256×192), fewer frames, 256-spp dynamic references: a few minutes.")] = False,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Write the results as JSON here.")] = None,
    out_dir: Annotated[Path, typer.Option(help="Plots (PNG) and image strips go here.")] = Path("bench-quality"),
    cache_dir: Annotated[Optional[Path], typer.Option(help="Reference cache [default: $DPMHW_CACHE/references or ~/.cache/dpmhw/references].")] = None,
    part: Annotated[QualityPart, typer.Option(help="Which half of the benchmark to run.")] = QualityPart("all"),
    scale: Annotated[Optional[float], typer.Option(min=0.01, max=1.0, help="Override the resolution scale.")] = None,
    ref_spp: Annotated[Optional[int], typer.Option(min=1, help="Override the static reference spp.")] = None,
    dynamic_ref_spp: Annotated[Optional[int], typer.Option(min=1, help="Override the dynamic references' spp.")] = None,
    dynamic_times: Annotated[Optional[str], typer.Option(help="Override the dynamic eval times, comma-separated seconds, e.g. 0.2,0.5.")] = None,
    threads: Annotated[int, typer.Option(min=1)] = 2,
    ray: Annotated[Optional[str], typer.Option(metavar="[ADDRESS]", help="References and sweep units as Ray tasks: no address or 'local' = a Ray instance on this machine, or a cluster's address (docs/cluster.md).")] = None,
) -> None:
    """Speed against error: PSNR/SSIM against converged references for plain path tracing and
    temporal reuse (static table vs the paper's Table 1, dynamic per-frame error), and native
    reconstruction rows (filters, shading scales; PSNR/SSIM/FLIP), with costs."""
    import dataclasses
    import functools

    from dpmhw.benchmarks.quality import QualityConfig, format_table, run_quality
    from dpmhw.benchmarks.quality_ray import run_units_on_ray
    from dpmhw.cluster.ray_pool import connect
    from dpmhw.errors import DpmhwError

    cfg = QualityConfig.quick() if quick else QualityConfig()
    changes = dict(threads=threads, parts=("static", "dynamic", "native") if part.value == "all" else (part.value,))
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
    try:
        pool = connect(ray)
    except DpmhwError as exc:
        fail(exc)
    try:
        with Progress() as bar:
            result = run_quality(cfg, cache_dir=cache_dir, out_dir=out_dir, progress=bar.callback, pool=pool,
                                 run_units=None if pool is None else functools.partial(run_units_on_ray, pool))
    finally:
        if pool is not None:
            pool.close()
    typer.echo(format_table(result))
    for f in result.get("files", []):
        typer.echo(f"wrote {f}")
    if json_path is not None:
        typer.echo(f"wrote {write_json(result, json_path)}")


@bench_app.command("lod")
def bench_lod(
    quick: Annotated[bool, typer.Option("--quick", help="Half resolution (512×384), 32-spp references.")] = False,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Write the rows as JSON here.")] = None,
    out_dir: Annotated[Path, typer.Option(help="Visibility-map and ms-vs-error figures (PNG) go here.")] = Path("bench-lod"),
    cache_dir: Annotated[Optional[Path], typer.Option(help="Reference cache [default: $DPMHW_CACHE/references or ~/.cache/dpmhw/references].")] = None,
    scenes: Annotated[Optional[str], typer.Option(help="Comma-separated scenes [default: paper-dynamic,dpm-bunny].")] = None,
    eval_times: Annotated[Optional[str], typer.Option(help="Comma-separated timeline seconds compared with references [default: 0.3,0.5].")] = None,
    history_frames: Annotated[Optional[int], typer.Option(min=1, help="60 fps frames before the first eval time.")] = None,
    ref_spp: Annotated[Optional[int], typer.Option(min=1, help="Reference spp.")] = None,
    rays: Annotated[Optional[int], typer.Option(min=1, help="Native rays per frame of the refining methods [default: the session's lod.rays].")] = None,
    viewer_distance: Annotated[float, typer.Option(help="Audience distance from the surface, metres.")] = 1.5,
    alpha_v: Annotated[float, typer.Option(help="α_v added to the visibility (1/contrast units).")] = 0.0,
    threads: Annotated[int, typer.Option(min=1)] = 2,
    methods: Annotated[Optional[str], typer.Option(help="Comma-separated methods, none first; NAME-plain: NAME without the analytic demodulation [default: none,quarter,moving,shading-rate,spp,mesh-LOD,all].")] = None,
    analytic_floors: Annotated[Optional[str], typer.Option(help="Diffuse,specular floor fractions of the analytic-direct demodulation [default: the session's render.analytic_floor, render.analytic_specular_floor].")] = None,
    moving_every: Annotated[Optional[int], typer.Option(help="lod.moving_every of the refining methods: 1, 2 or 4 [default: the session's].")] = None,
) -> None:
    """Contrast-driven LOD through the loop's pipeline, speed against error: rows {scene, method,
    frame_ms, rays_per_frame, triangles, psnr_db, ssim, flip, psnr_db_object, ...} for none /
    quarter / moving / shading-rate / spp / mesh-LOD / all against converged references."""
    import dataclasses

    from dpmhw.benchmarks.lod import LodBenchConfig, format_table, run_lod
    from dpmhw.lod.visibility import LodSettingsError, VisibilitySettings

    cfg = LodBenchConfig.quick() if quick else LodBenchConfig()
    try:
        changes = dict(threads=threads, visibility=VisibilitySettings(viewer_distance_m=viewer_distance, alpha_v=alpha_v))
        if eval_times is not None:
            changes["eval_times"] = tuple(float(v) for v in eval_times.split(",") if v.strip())
            if not changes["eval_times"] or min(changes["eval_times"]) < 0:
                raise ValueError
    except LodSettingsError as e:
        raise typer.BadParameter(str(e)) from None
    except ValueError:
        raise typer.BadParameter(f"--eval-times: expected comma-separated seconds ≥ 0, got {eval_times!r}") from None
    if scenes is not None:
        changes["scenes"] = tuple(s.strip() for s in scenes.split(",") if s.strip())
    if methods is not None:
        from dpmhw.benchmarks.lod import check_methods

        try:
            changes["methods"] = check_methods(m.strip() for m in methods.split(",") if m.strip())
        except ValueError as e:
            raise typer.BadParameter(f"--{e}") from None
    if moving_every is not None and moving_every not in (1, 2, 4):
        raise typer.BadParameter(f"--moving-every: expected 1, 2 or 4, got {moving_every}")
    if analytic_floors is not None:
        try:
            changes["analytic_floors"] = tuple(float(v) for v in analytic_floors.split(","))
            if len(changes["analytic_floors"]) != 2 or not all(0 < v < float("inf") for v in changes["analytic_floors"]):
                raise ValueError
        except ValueError:
            raise typer.BadParameter(f"--analytic-floors: expected two numbers > 0 (diffuse,specular), got {analytic_floors!r}") from None
    for key, value in (("history_frames", history_frames), ("ref_spp", ref_spp), ("rays", rays), ("moving_every", moving_every)):
        if value is not None:
            changes[key] = value
    cfg = dataclasses.replace(cfg, **changes)
    with Progress() as bar:
        result = run_lod(cfg, cache_dir=cache_dir, out_dir=out_dir, progress=bar.callback)
    typer.echo(format_table(result))
    for f in result["files"]:
        typer.echo(f"wrote {f}")
    if json_path is not None:
        typer.echo(f"wrote {write_json(result['rows'], json_path)}")


@bench_app.command("ray-scaling")
def bench_ray_scaling(
    scene: Annotated[str, typer.Argument(help="Scene file or built-in name.")] = "paper-static",
    scale: Annotated[float, typer.Option(min=0.01, max=1.0, help="Resolution scale of the scene.")] = 0.5,
    spp: Annotated[int, typer.Option(min=1)] = 64,
    workers: Annotated[str, typer.Option(help="Comma-separated worker counts (local Ray CPUs) and thread counts.")] = "1,2",
    repeats: Annotated[int, typer.Option(min=1)] = 3,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the results as JSON here.")] = None,
    plot: Annotated[Optional[Path], typer.Option(help="Passes per second against workers, as PNG.")] = Path("ray-scaling.png"),
) -> None:
    """Wall time of one render in process and on local Ray at 1, 2, … workers (docs/cluster.md)."""
    from dpmhw.cluster.ray_pool import import_ray
    from dpmhw.benchmarks.ray_scaling import format_table, plot as plot_png, run_scaling
    from dpmhw.errors import DpmhwError

    try:
        counts = tuple(int(w) for w in workers.split(","))
        import_ray()
    except ValueError:
        raise typer.BadParameter(f"--workers: expected comma-separated integers, got {workers!r}") from None
    except DpmhwError as exc:
        fail(exc)
    if any(w < 1 for w in counts):
        raise typer.BadParameter(f"--workers: expected counts ≥ 1, got {workers!r}")
    result = run_scaling(scene, scale=scale, spp=spp, workers=counts, repeats=repeats,
                         progress=lambda desc, done, total: typer.echo(f"[{done}/{total}] {desc}", err=True))
    typer.echo(format_table(result))
    if plot is not None:
        typer.echo(f"wrote {plot_png(result, plot)}")
    if json_path is not None:
        typer.echo(f"wrote {write_json(result, json_path)}")


@bench_app.command("soak")
def bench_soak(
    minutes: Annotated[float, typer.Option(min=0.05, help="How long to run.")] = 30.0,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the results (per fault and per kind) here.")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the fault schedule.")] = 0,
    kinds: Annotated[Optional[str], typer.Option(help="Comma-separated fault kinds [default: all of the tracker's].")] = None,
    tracker: Annotated[str, typer.Option(help="natnet (emulated Motive) or serial (emulated Polhemus).")] = "natnet",
    size: Annotated[str, typer.Option(help="Projector native size WxH (the loop renders at its shading scale).")] = "128x96",
) -> None:
    """Mock session with random faults (tracker stall/restart, corrupt and foreign datagrams, serial
    stall/noise/unplug, implausible poses, USB stall and unplug, API load): time to dark and to
    resume per fault kind against the goal, lit frames while a cause was active, recording rows
    against frames presented, memory."""
    from dpmhw.benchmarks.soak import format_table, plot_soak, run_soak

    chosen = tuple(k.strip() for k in kinds.split(",")) if kinds else None
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"--size: expected WxH such as 1024x768, got {size!r}") from None
    try:
        result = run_soak(minutes, seed=seed, tracker=tracker, kinds=chosen, width=width, height=height,
                          progress=typer.echo)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    typer.echo(format_table(result))
    if json_path is not None:
        write_json(result, json_path)
        plot_soak(result, json_path.with_suffix(".png"))
        typer.echo(f"wrote {json_path} and {json_path.with_suffix('.png')}")


@bench_app.command("mitsuba")
def bench_mitsuba(
    scene: Annotated[str, typer.Argument(help="Scene file or built-in name (no lens distortion, no separate viewer).")] = "paper-static",
    frames: Annotated[int, typer.Option(min=3, help="Timed frames per camera mode (the median is reported).")] = 9,
    threads: Annotated[int, typer.Option(min=1, help="Threads for both renderers (drjit's pool, dpmhw's segments).")] = 2,
    variant: Annotated[str, typer.Option(help="Mitsuba variant; llvm_ad_rgb is the fair CPU comparison.")] = "llvm_ad_rgb",
    dpmhw: Annotated[bool, typer.Option("--dpmhw/--no-dpmhw", help="Alternate dpmhw frames with Mitsuba's and report the ratios.")] = True,
    compare_spp: Annotated[int, typer.Option(min=0, help="Also render both converged at this spp and compare region means (0: skip).")] = 0,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the rows as JSON here (a list of flat rows).")] = None,
    plot_path: Annotated[Optional[Path], typer.Option("--plot", help="Also save a labelled PNG plot here.")] = None,
    mesh: Annotated[Optional[Path], typer.Option(help="Mesh for the built-in scenes' bunny.")] = None,
) -> None:
    """Mitsuba 3 (LLVM) on the same scene: ms per 1-spp frame with the camera fixed and moved,
    alternated with dpmhw's frames, and optionally converged images compared (docs/mitsuba.md)."""
    from dpmhw.benchmarks import mitsuba as mb
    from dpmhw.errors import DpmhwError

    try:
        with Progress() as bar:
            rows = mb.bench_mitsuba(scene, frames=frames, threads=threads, variant=variant, with_dpmhw=dpmhw, mesh=mesh,
                                    progress=bar.callback)
            if compare_spp:
                rows += mb.compare(scene, spp=compare_spp, threads=threads, variant=variant, mesh=mesh, progress=bar.callback)
    except DpmhwError as exc:
        fail(exc)
    report(mb.format_table(rows), rows, json_path)
    if plot_path is not None:
        plot_path.parent.mkdir(parents=True, exist_ok=True)
        mb.plot(rows, plot_path)
        typer.echo(f"wrote {plot_path}")


@bench_app.command("reproject")
def bench_reproject(
    scene: Annotated[str, typer.Argument(help="Scene file or built-in name.")] = "dpm-bunny",
    size: Annotated[Optional[str], typer.Option(help="Native size WxH [default: the scene's].")] = None,
    spp: Annotated[int, typer.Option(min=1, help="Samples per pixel of the captured frames and the fresh renders.")] = 32,
    starts: Annotated[str, typer.Option(help="Comma-separated trajectory times (s) the captures are rendered at.")] = "0.3,0.8,1.4",
    horizons: Annotated[str, typer.Option(help="Comma-separated horizons (ms) the captures are moved by.")] = "5,10,20,40",
    trajectory: Annotated[BenchTrajectory, typer.Option(help="The mock world's trajectory.")] = BenchTrajectory("rotate-oscillate"),
    repeats: Annotated[int, typer.Option(min=1, help="Timed reprojections per row (the median is reported).")] = 30,
    threads: Annotated[int, typer.Option(min=1, help="Render threads.")] = 2,
    present_threads: Annotated[int, typer.Option(min=1, max=2, help="The reprojection's threads (2: a helper thread "
                                                 "shares a pattern present's splats).")] = 1,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the rows as JSON here (a list of flat rows).")] = None,
) -> None:
    """Late reprojection: CPU-ms per reprojection and per pattern-mode present (three channels),
    lit pixels, holes, and PSNR/SSIM inside the moving objects against fresh renders, per
    horizon, beside the stale frame and the renders' own noise (docs/reprojection.md)."""
    from dpmhw.benchmarks.reproject import ReprojectBenchConfig, format_table, run_reproject

    try:
        dims = None if size is None else tuple(int(v) for v in size.lower().split("x"))
        if dims is not None and (len(dims) != 2 or min(dims) < 1):
            raise ValueError
    except ValueError:
        raise typer.BadParameter(f"--size: expected WxH such as 1024x768, got {size!r}") from None
    try:
        times = tuple(float(v) for v in starts.split(","))
    except ValueError:
        raise typer.BadParameter(f"--starts: expected comma-separated seconds, got {starts!r}") from None
    try:
        ms = tuple(float(v) for v in horizons.split(","))
    except ValueError:
        raise typer.BadParameter(f"--horizons: expected comma-separated milliseconds, got {horizons!r}") from None
    try:
        cfg = ReprojectBenchConfig(scene=scene, size=dims, spp=spp, starts_s=times, horizons_ms=ms, trajectory=trajectory.value,
                                   repeats=repeats, threads=threads, present_threads=present_threads)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    with Progress() as bar:
        rows = run_reproject(cfg, progress=bar.callback)
    report(format_table(rows), rows, json_path)


@bench_app.command("prediction")
def bench_prediction(
    horizon_ms: Annotated[float, typer.Option(min=0.001, max=1000.0, help="How far ahead each prediction reaches.")] = 35.0,
    noise_mm: Annotated[str, typer.Option(help="Comma-separated marker-noise standard deviations (mm).")] = "0,0.1,0.2,0.5",
    trajectory: Annotated[BenchTrajectory, typer.Option(help="The mock's trajectory.")] = BenchTrajectory("rotate-oscillate"),
    seconds: Annotated[float, typer.Option(min=1.0, max=3600.0, help="Trajectory seconds sampled at the tracker's rate.")] = 20.0,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the rows as JSON here.")] = None,
) -> None:
    """The pose predictor's position error at a horizon, per model and history, with marker noise (offline)."""
    from dpmhw.benchmarks.prediction import PredictionBenchConfig, format_table, run_prediction

    try:
        cfg = PredictionBenchConfig(trajectory=trajectory.value, horizon_ms=horizon_ms, seconds=seconds,
                                    noise_mm=tuple(float(v) for v in noise_mm.split(",")))
    except ValueError as exc:
        raise typer.BadParameter(f"--noise-mm: {exc}") from None
    with Progress() as bar:
        rows = run_prediction(cfg, progress=bar.callback)
    report(format_table(rows), rows, json_path)


@bench_app.command("stages")
def bench_stages(
    scene: Annotated[str, typer.Argument(help="Scene file or built-in name.")] = "dpm-bunny",
    frames: Annotated[int, typer.Option(min=1, help="Timed frames (after the warm-up ones).")] = 60,
    warmup: Annotated[int, typer.Option(min=0, help="Frames run first and not counted (history fill, cache loads).")] = 8,
    trajectory: Annotated[BenchTrajectory, typer.Option(help="The mock's trajectory of the bound objects.")] = BenchTrajectory("rotate-oscillate"),
    digest: Annotated[bool, typer.Option("--digest", help="Also hash the outputs (images, histories, G-buffer) and the rendered inputs.")] = False,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the per-frame rows as JSON here.")] = None,
) -> None:
    """The session's reconstruction stage alone: median wall and CPU ms per frame and ms per
    sub-stage (gbuffer, reuse, filter, upsample, adaptive, post) on a moving pose sequence."""
    from dpmhw.benchmarks.stages import format_table, run_stages
    from dpmhw.errors import DpmhwError

    try:
        result = run_stages(scene, frames=frames, warmup=warmup, trajectory=trajectory.value, digest=digest)
    except DpmhwError as exc:  # e.g. a scene without a bound (moving) object
        fail(exc)
    typer.echo(format_table(result))
    if json_path is not None:
        keep = {k: result[k] for k in ("scene", "size", "shading", "trajectory", "digest_out", "digest_in") if k in result}
        typer.echo(f"wrote {write_json([{**keep, **r} for r in result['rows']], json_path)}")


@bench_app.command("governor")
def bench_governor(
    seconds: Annotated[float, typer.Option(min=3.0, max=3600.0, help="Measured seconds (after the warm-up).")] = 25.0,
    hog_after: Annotated[float, typer.Option(min=1.0, help="Seconds into the measurement the CPU hog starts (it runs to the end).")] = 10.0,
    hog_processes: Annotated[Optional[int], typer.Option(min=1, max=64, help="Busy processes of the hog, at this command's priority [default: one per core].")] = None,
    trajectory: Annotated[BenchTrajectory, typer.Option(help="The mock's trajectory.")] = BenchTrajectory("rotate-oscillate"),
    quality: Annotated[bool, typer.Option("--quality/--no-quality", help="Afterwards, PSNR inside the objects of the configurations the governor held, beside the configured one (offline, a few frames).")] = True,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the rows (per second, summary, quality) as JSON here.")] = None,
    plot: Annotated[Path, typer.Option(help="Plot of the rates over time, the hog's start and the governor's level (PNG).")] = Path("bench-governor/bench-governor.png"),
    sets: SetOpt = None,
) -> None:
    """The quality governor against a real CPU hog: a --mock session, busy processes started
    mid-run; present and render rates per second, the governor's level, the time until the rate
    is back above target (docs/session.md)."""
    from dpmhw.benchmarks.governor_hog import format_table, run_governor_hog
    from dpmhw.benchmarks.governor_hog import plot as plot_hog
    from dpmhw.errors import DpmhwError
    from dpmhw.machine import machine_line

    if hog_after >= seconds:
        raise typer.BadParameter(f"--hog-after {hog_after:g} must be less than --seconds {seconds:g}")
    try:
        result = run_governor_hog(seconds=seconds, hog_after=hog_after, hog_processes=hog_processes, trajectory=trajectory.value,
                                  overrides=tuple(sets or ()), quality=quality, progress=typer.echo)
    except DpmhwError as exc:  # e.g. a --set the config refuses
        fail(exc)
    typer.echo(format_table(result["rows"]))
    typer.echo(f"wrote {plot_hog(result, plot, title=f'dpmhw bench governor ({machine_line()})')}")
    if json_path is not None:
        typer.echo(f"wrote {write_json(result['rows'], json_path)}")
