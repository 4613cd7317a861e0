"""`dpmhw session …` (run a projection session) and `dpmhw bench session`.

`dpmhw session start --mock` runs the whole system on a fresh machine: firmware mocks on
loopback, the real drivers, the loop and the HTTP service. The loop, drivers, mocks and server
are imported inside the commands.
"""

from __future__ import annotations

import json
import secrets
import signal
import threading
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli import app, bench_app
from dpmhw.cli.choices import ApiMode, BenchTrajectory, ClientPriority

session_app = typer.Typer(no_args_is_help=True, help="Projection sessions: tracker → prediction → render → projector.")
app.add_typer(session_app, name="session")

ConfigOpt = Annotated[Optional[Path], typer.Option("--config", "-c", envvar="DPMHW_SESSION_CONFIG",
                                                   help="Session TOML file (default: built-in defaults).")]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override a field: section.field=value (repeatable), e.g. render.spp=2.")]
MockOpt = Annotated[bool, typer.Option("--mock", help="Run against the firmware mocks and the simulated world (no hardware).")]


def _load(config: Optional[Path], sets: Optional[list[str]], extra: list[str]):
    from dpmhw.session.config import load_session_config

    return load_session_config(config, [*(sets or []), *extra])


def _fail(exc: Exception) -> None:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(code=2)


def _status_line(status: dict) -> str:
    lat = status.get("latency_ms", {})
    line = (f"[{status.get('state')}] frames={status.get('frame_number')} fps={status.get('fps', 0):.1f} "
            f"latency p50/p95/p99={lat.get('p50')}/{lat.get('p95')}/{lat.get('p99')} ms")
    return line + (f" — {status['reason']}" if status.get("reason") else "")


class _Reporter:
    """Prints a status line every `every_s` seconds on its own thread (stopped with the session)."""

    def __init__(self, get_status, every_s: float):
        self.get_status, self.every_s = get_status, every_s
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.wait(self.every_s):
            try:
                typer.echo(_status_line(self.get_status()))
            except Exception:  # the session is going away
                return


@session_app.command("start")
def start(
    config: ConfigOpt = None,
    sets: SetOpt = None,
    mock: MockOpt = False,
    host: Annotated[Optional[str], typer.Option(help="API bind address (default 127.0.0.1; api.host).")] = None,
    port: Annotated[Optional[int], typer.Option(help="API port (api.port; 0 picks a free one).")] = None,
    no_api: Annotated[bool, typer.Option("--no-api", help="Run the loop without the HTTP service.")] = False,
    record: Annotated[bool, typer.Option("--record", help="Record poses, timings and some frames (recording.*).")] = False,
    duration: Annotated[Optional[float], typer.Option(min=0.1, help="Stop after this many seconds (default: Ctrl-C / SIGTERM).")] = None,
    status_every: Annotated[float, typer.Option(min=0.0, help="Print a status line every N seconds (0: never).")] = 2.0,
) -> None:
    """Connect tracker and projector, load scene and calibration, run the loop and the API."""
    from dpmhw.errors import DpmhwError

    extra = [f"api.host={json.dumps(host)}"] if host else []
    extra += [f"api.port={port}"] if port is not None else []
    extra += ["api.enabled=false"] if no_api else []
    extra += ["recording.enabled=true"] if record else []
    try:
        cfg = _load(config, sets, extra)
    except DpmhwError as exc:
        _fail(exc)
    from dpmhw.session.factory import build_session

    def make_loop():
        typer.echo("opening devices, loading the scene, readying the render kernels (a first run compiles them) …")
        loop = build_session(cfg, mock=mock).start()
        typer.echo(f"session started ({'mock devices' if mock else 'hardware'}); scene {cfg.scene.source}, "
                   f"render {loop.parts.renderer.width}×{loop.parts.renderer.height}")
        return loop

    api = None
    try:
        if cfg.api.enabled:
            from server.process import ApiProcess

            token = cfg.api_token()
            if not token:
                token = secrets.token_urlsafe(18)
                typer.echo(f"no api.token / DPMHW_API_TOKEN set; this session's token: {token}")
            api = ApiProcess(host=cfg.api.host, port=cfg.api.port, token=token, priority=cfg.api.priority)  # binds now
        _run(make_loop, api, duration, status_every)
    except (DpmhwError, OSError, RuntimeError) as exc:
        _fail(exc)


def _run(make_loop, api, duration: Optional[float], status_every: float) -> None:
    """Run until `duration`, Ctrl-C or SIGTERM; always end with the loop stopped and the projector dark."""
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *a: stop.set())
    loop = reporter = None
    try:
        loop = make_loop()
        if api is not None:
            api.start(loop)
            typer.echo(f"API on {api.url} (docs at {api.url}/docs)")
        if status_every > 0:
            reporter = _Reporter(loop.status, status_every)
            reporter.thread.start()
        deadline = None if duration is None else time.monotonic() + duration
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            stop.wait(0.1)
    except KeyboardInterrupt:
        typer.echo("interrupted")
    finally:
        signal.signal(signal.SIGTERM, previous)
        if reporter:
            reporter.stop.set()
        if loop is not None:
            how = loop.stop("stopped by the operator")
            if api is not None:
                api.publish()  # the last status (stopped, dark) for anyone still asking
            typer.echo(_status_line(loop.status()))
            typer.echo(f"projector dark ({how or 'no projector'})")
        if api is not None:
            api.close()


@session_app.command("config")
def show_config(config: ConfigOpt = None, sets: SetOpt = None) -> None:
    """Validate a session config (with overrides) and print it resolved, as JSON."""
    from dpmhw.errors import DpmhwError

    try:
        cfg = _load(config, sets, [])
    except DpmhwError as exc:
        _fail(exc)
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
    trajectory: Annotated[Optional[list[BenchTrajectory]], typer.Option(help="Repeatable; default: linear and rotate-oscillate.")] = None,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the results as JSON here.")] = None,
    plot: Annotated[Path, typer.Option(help="Plot of registration error and latency over time and the frame-time histogram (PNG).")] = Path("bench-session/bench-session.png"),
    sets: SetOpt = None,
) -> None:
    """Registration error vs ground truth with/without prediction, fps, latency, frame time under API load."""
    from dpmhw.session.bench import format_table, run_bench

    trajectories = tuple(t.value for t in trajectory) if trajectory else ("linear", "rotate-oscillate")
    modes = tuple(m.value for m in api_mode) if api_mode else ("process", "thread")
    if api_only and not api_clients:
        raise typer.BadParameter("--api-only needs --api-clients ≥ 1")
    from dpmhw.progress import Progress

    steps = (0 if api_only else 2 * len(trajectories)) + (1 if api_clients else 0)  # run_bench's progress() calls
    with Progress() as bar:
        task = bar.task("bench session", total=steps)
        started: list[str] = []

        def on_step(label: str) -> None:
            task.update(len(started), description=f"bench session: {label}")
            started.append(label)

        results = run_bench(trajectories, api_clients=api_clients, api_rate_hz=api_rate, api_modes=modes,
                            api_windows=api_windows, api_window_s=api_window_s, api_client_priority=client_priority.value,
                            cases=not api_only, seconds=seconds,
                            width=width, height=height, spp=spp, overrides=tuple(sets or ()), progress=on_step)
        task.update(steps, description="bench session")
    series = {c["case"]: c.pop("series") for c in results["cases"] if "series" in c}
    typer.echo(format_table(results))
    if series:
        from dpmhw.session.bench_plots import plot_bench_session

        typer.echo(f"wrote {plot_bench_session(results['cases'], series, plot)}")
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(results, indent=2))
        typer.echo(f"wrote {json_path}")
