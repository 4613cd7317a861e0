"""`dpmhw session …` (run a projection session) and `dpmhw bench session`.

`dpmhw session start --mock` runs the whole system on a fresh machine: firmware mocks on
loopback, the real drivers, the loop and the HTTP service, the loop in a supervised child
process (`dpmhw.session.supervisor`). The loop, drivers, mocks and server are imported inside
the commands.
"""

from __future__ import annotations

import json
import secrets
from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import app, bench_app, fail, write_json
from dpmhw.cli.choices import ApiMode, BenchTrajectory, ClientPriority, DisplayModeChoice

session_app = typer.Typer(no_args_is_help=True, help="Projection sessions: tracker → prediction → render → projector.")
app.add_typer(session_app, name="session")

ConfigOpt = Annotated[Optional[Path], typer.Option("--config", "-c", envvar="DPMHW_SESSION_CONFIG",
                                                   help="Session TOML file (default: built-in defaults).")]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override a field: section.field=value (repeatable), e.g. render.spp=2.")]
MockOpt = Annotated[bool, typer.Option("--mock", help="Run against the firmware mocks and the simulated world (no hardware).")]


def _load(config: Optional[Path], sets: Optional[list[str]], extra: list[str]):
    from dpmhw.session.config import load_session_config

    return load_session_config(config, [*(sets or []), *extra])


def _vet(cfg) -> None:
    """On stderr, the memory the output size needs and what costly values cost; refuses a session
    over the memory limit (before anything allocates at that size)."""
    from dpmhw.errors import DpmhwError
    from dpmhw.limits import session_memory
    from dpmhw.session.factory import memory_problem, output_size

    try:
        size = output_size(cfg)
    except DpmhwError as exc:
        fail(exc)
    problem = memory_problem(cfg, size)
    if problem is not None:
        fail(ValueError(problem))
    need, limit = session_memory(*size, cfg.render.shading_scale)
    typer.echo(f"memory: about {need / 2**20:.0f} MiB for a {size[0]}×{size[1]} output at shading_scale "
               f"{cfg.render.shading_scale:g} (limit {limit / 2**20:.0f} MiB: DPMHW_SESSION_MEMORY_MB)", err=True)
    for warning in cfg.warnings():
        typer.echo(f"warning: {warning}", err=True)


@session_app.command("start")
def start(
    config: ConfigOpt = None,
    sets: SetOpt = None,
    mock: MockOpt = False,
    host: Annotated[Optional[str], typer.Option(help="API bind address (default 127.0.0.1; api.host).")] = None,
    port: Annotated[Optional[int], typer.Option(help="API port (api.port; 0 picks a free one, and a free operator port too).")] = None,
    operator_port: Annotated[Optional[int], typer.Option(help="The operator's reserved port for blank and status (api.operator_port; 0 picks a free one).")] = None,
    no_api: Annotated[bool, typer.Option("--no-api", help="Run the loop without the HTTP service.")] = False,
    record: Annotated[bool, typer.Option("--record", help="Record poses, timings and some frames (recording.*).")] = False,
    duration: Annotated[Optional[float], typer.Option(min=0.1, help="Stop after this many seconds (default: Ctrl-C / SIGTERM).")] = None,
    status_every: Annotated[float, typer.Option(min=0.0, help="Print a status line every N seconds (0: never).")] = 2.0,
) -> None:
    """Connect tracker and projector, load scene and calibration, run the loop and the API.

    This process supervises: the loop runs in a child process, and if that one dies by any means
    this one idles the projector (read back), reports `fault` on the API port and restarts it
    when `safety.restart = "on-crash"` (see docs/session.md, "Supervisor")."""
    from dpmhw.errors import DpmhwError

    extra = [f"api.host={json.dumps(host)}"] if host else []
    extra += [f"api.port={port}"] if port is not None else []
    if operator_port is not None or port == 0:
        extra.append(f"api.operator_port={operator_port or 0}")
    extra += ["api.enabled=false"] if no_api else []
    extra += ["recording.enabled=true"] if record else []
    from dpmhw.session.instance import SessionLock

    try:
        cfg = _load(config, sets, extra)
        lock = SessionLock.claim(cfg, mock)  # held until this process ends
    except (DpmhwError, OSError) as exc:
        fail(exc)
    _vet(cfg)
    if lock.warning:
        typer.echo(lock.warning)
    from dpmhw.session.supervisor import Supervisor

    sock = operator_sock = token = None
    if cfg.api.enabled:
        from server.process import bind_api_socket

        token = cfg.api_token()
        if not token:
            token = secrets.token_urlsafe(18)
            typer.echo(f"no api.token / DPMHW_API_TOKEN set; this session's token: {token}")
        bound = []  # both held here for the whole show
        for field in ("port", "operator_port"):
            try:
                bound.append(bind_api_socket(cfg.api.host, getattr(cfg.api, field)))
            except OSError as exc:
                for s in bound:
                    s.close()
                fail(OSError(f"api.{field}: cannot listen on {cfg.api.host}:{getattr(cfg.api, field)}: "
                              f"{exc.strerror or exc}"))
        sock, operator_sock = bound
        host = f"[{cfg.api.host}]" if ":" in cfg.api.host else cfg.api.host
        typer.echo(f"operator page: http://{host}:{sock.getsockname()[1]}/ (it says why while the session is not up yet)")
        typer.echo(f"operator port (blank and status, whatever the load on the page's port): "
                   f"http://{host}:{operator_sock.getsockname()[1]}")
    try:
        code = Supervisor(cfg, mock=mock, token=token or "", sock=sock, operator_sock=operator_sock,
                          duration=duration, status_every=status_every, echo=typer.echo).run()
    except (DpmhwError, OSError, RuntimeError) as exc:
        fail(exc)
    finally:
        for s in (sock, operator_sock):
            if s is not None:
                s.close()
        lock.release()
    raise typer.Exit(code=code)


@session_app.command("config")
def show_config(
    config: ConfigOpt = None,
    sets: SetOpt = None,
    offline: Annotated[bool, typer.Option("--offline", help="Skip the device checks (projector, tracker port or address, display).")] = False,
) -> None:
    """Validate a session config (with overrides) as a start would, and print it resolved, as JSON;
    the memory its output size needs and what costly values cost go to stderr.

    Loads the scene, its meshes and the calibration files, resolves the bindings, and (unless
    --offline) reaches the devices without changing them."""
    from dpmhw.errors import DpmhwError
    from dpmhw.session.factory import check_devices, prepare_scene, resolve_bindings

    try:
        cfg = _load(config, sets, [])
    except DpmhwError as exc:
        fail(exc)
    _vet(cfg)  # from the sizes alone: a session over the memory limit is refused before its scene loads
    try:
        scene = prepare_scene(cfg)
        resolve_bindings(cfg, scene)
        if not offline:
            check_devices(cfg, scene)
    except DpmhwError as exc:
        fail(exc)
    data = cfg.model_dump()
    data["api"]["token"] = "***" if data["api"]["token"] else ""
    typer.echo(json.dumps(data, indent=2))


@bench_app.command("session")
def bench_session(
    seconds: Annotated[float, typer.Option(min=0.5, help="Measured seconds per case (after warm-up).")] = 4.0,
    width: Annotated[int, typer.Option(min=0, help="Output width; 0: the projector's native size (errors are in its pixels). Shading resolution: --set render.shading_scale=…")] = 0,
    height: Annotated[int, typer.Option(min=0)] = 0,
    spp: Annotated[int, typer.Option(min=1, max=64)] = 1,
    api_clients: Annotated[int, typer.Option(min=0, max=64, help="Concurrent API clients for the load case (0: skip it).")] = 4,
    api_rate: Annotated[float, typer.Option(min=0.0, max=1000.0, help="Requests per second per API client (0: as fast as possible).")] = 10.0,
    api_mode: Annotated[Optional[list[ApiMode]], typer.Option(help="How the API is served in the load case: process (as `session start` does), thread (inside the session process; for comparison). Repeatable; default both.")] = None,
    api_windows: Annotated[int, typer.Option(min=1, max=100, help="Unloaded/loaded window pairs per API mode.")] = 6,
    api_window_s: Annotated[float, typer.Option(min=0.5, max=60.0, help="Seconds per load window.")] = 3.0,
    client_priority: Annotated[ClientPriority, typer.Option(help="CPU priority of the load-client process: normal (the strict test: it competes with the loop like any local program), low, idle (as if the clients were on another machine).")] = ClientPriority("normal"),
    api_only: Annotated[bool, typer.Option("--api-only", help="Only the API-load case (skip the registration cases).")] = False,
    mitsuba: Annotated[bool, typer.Option("--mitsuba/--no-mitsuba", help="Time Mitsuba 3's 1-spp frame of the same scene after the cases and give each case's CPU-ms per rendered frame as a ratio to it (skipped, with a note, without the mitsuba extra).")] = True,
    trajectory: Annotated[Optional[list[BenchTrajectory]], typer.Option(help="Repeatable; default: linear and rotate-oscillate.")] = None,
    display: Annotated[DisplayModeChoice, typer.Option(help="The projector's display mode: video (one 24-bit frame per refresh) or pattern-8bit (three 8-bit sub-frames per refresh, one per colour channel).")] = DisplayModeChoice("video"),
    present_cpu_factor: Annotated[float, typer.Option(min=1.0, max=20.0, help="Every kernel call of a present, on the present thread or its helper, spends this many times its CPU time there (the extra without the GIL, as the kernel): how the present path holds on a CPU this much slower. The renders keep this machine's speed.")] = 1.0,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the results as JSON here.")] = None,
    plot: Annotated[Path, typer.Option(help="Plot of registration error and latency over time and the frame-time histogram (PNG).")] = Path("bench-session/bench-session.png"),
    sets: SetOpt = None,
) -> None:
    """Registration at photon time vs ground truth with/without late reprojection and prediction, fps, latency, frame time under API load."""
    from dpmhw.benchmarks.session import CASES, format_table, run_bench

    trajectories = tuple(t.value for t in trajectory) if trajectory else ("linear", "rotate-oscillate")
    modes = tuple(m.value for m in api_mode) if api_mode else ("process", "thread")
    if api_only and not api_clients:
        raise typer.BadParameter("--api-only needs --api-clients ≥ 1")
    from dpmhw.progress import Progress

    steps = (0 if api_only else len(CASES) * len(trajectories) + int(mitsuba)) + (1 if api_clients else 0)  # run_bench's progress() calls
    with Progress() as bar:
        task = bar.task("bench session", total=steps)
        started: list[str] = []

        def on_step(label: str) -> None:
            task.update(len(started), description=f"bench session: {label}")
            started.append(label)

        def on_note(text: str) -> None:
            task.update(max(len(started) - 1, 0), description=f"bench session: {text}")

        results = run_bench(trajectories, api_clients=api_clients, api_rate_hz=api_rate, api_modes=modes,
                            api_windows=api_windows, api_window_s=api_window_s, api_client_priority=client_priority.value,
                            cases=not api_only, mitsuba=mitsuba, seconds=seconds,
                            width=width, height=height, spp=spp, overrides=(f"display.mode={display.value}", *(sets or ())),
                            present_cpu_factor=present_cpu_factor,
                            progress=on_step, note=on_note)
        task.update(steps, description="bench session")
    series = {c["case"]: c.pop("series") for c in results["cases"] if "series" in c}
    typer.echo(format_table(results))
    if series:
        from dpmhw.benchmarks.session_plots import plot_bench_session

        typer.echo(f"wrote {plot_bench_session(results['cases'], series, plot)}")
    if json_path is not None:
        typer.echo(f"wrote {write_json(results, json_path)}")
