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
        loop = build_session(cfg, mock=mock).start()
        typer.echo(f"session started ({'mock devices' if mock else 'hardware'}); scene {cfg.scene.source}, "
                   f"render {loop.parts.renderer.width}×{loop.parts.renderer.height}")
        return loop

    try:
        if cfg.api.enabled:
            _serve(cfg, make_loop, duration, status_every)
        else:
            _run_plain(make_loop, duration, status_every)
    except (DpmhwError, OSError) as exc:
        _fail(exc)


def _run_plain(make_loop, duration: Optional[float], status_every: float) -> None:
    loop = make_loop()
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *a: stop.set())
    reporter = _Reporter(loop.status, status_every) if status_every > 0 else None
    if reporter:
        reporter.thread.start()
    try:
        deadline = None if duration is None else time.monotonic() + duration
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            stop.wait(0.1)
    except KeyboardInterrupt:
        typer.echo("interrupted")
    finally:
        if reporter:
            reporter.stop.set()
        signal.signal(signal.SIGTERM, previous)
        how = loop.stop("stopped by the operator")
        typer.echo(_status_line(loop.status()))
        typer.echo(f"projector dark ({how or 'no projector'})")


def _serve(cfg, make_loop, duration: Optional[float], status_every: float) -> None:
    """uvicorn owns SIGINT/SIGTERM; its shutdown runs the app's lifespan, which stops the loop."""
    import uvicorn

    from server.app import build_app

    token = cfg.api_token()
    if not token:
        token = secrets.token_urlsafe(18)
        typer.echo(f"no api.token / DPMHW_API_TOKEN set; this session's token: {token}")
    holder: dict = {}

    def start():
        holder["loop"] = make_loop()
        return holder["loop"]

    def stopped(loop) -> None:
        if reporter:
            reporter.stop.set()
        typer.echo(_status_line(loop.status()))
        typer.echo(f"projector dark ({loop.final_blank or 'no projector'})")

    app_ = build_app(start=start, token=token, stopped=stopped)
    server = uvicorn.Server(uvicorn.Config(app_, host=cfg.api.host, port=cfg.api.port, log_level="warning"))
    reporter = _Reporter(lambda: holder["loop"].status(), status_every) if status_every > 0 else None
    timer = threading.Timer(duration, lambda: setattr(server, "should_exit", True)) if duration else None

    def announce():
        if wait_started(server):
            bound = [s.getsockname() for srv in server.servers for s in srv.sockets]
            typer.echo(f"API on http://{bound[0][0]}:{bound[0][1]} (docs at /docs)")
        if reporter:
            reporter.thread.start()

    threading.Thread(target=announce, daemon=True).start()
    if timer:
        timer.start()
    try:
        server.run()
    finally:
        if timer:
            timer.cancel()
        if reporter:
            reporter.stop.set()


def wait_started(server, timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.started:
            return True
        time.sleep(0.05)
    return False


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
    width: Annotated[int, typer.Option(min=8, help="Render width (the projector is 1024 wide; errors are in its pixels).")] = 256,
    height: Annotated[int, typer.Option(min=6)] = 192,
    spp: Annotated[int, typer.Option(min=1, max=64)] = 1,
    api_clients: Annotated[int, typer.Option(min=0, max=64, help="Concurrent API clients for the load case (0: skip it).")] = 4,
    api_rate: Annotated[float, typer.Option(min=0.0, max=1000.0, help="Requests per second per API client (0: as fast as possible).")] = 10.0,
    trajectory: Annotated[Optional[list[str]], typer.Option(help="linear, rotate-oscillate (repeatable; default both).")] = None,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write the results as JSON here.")] = None,
    sets: SetOpt = None,
) -> None:
    """Registration error vs ground truth with/without prediction, fps, latency, frame time under API load."""
    from dpmhw.session.bench import format_table, run_bench

    trajectories = tuple(trajectory or ("linear", "rotate-oscillate"))
    for t in trajectories:
        if t not in ("linear", "rotate-oscillate", "static"):
            raise typer.BadParameter(f"--trajectory: expected linear, rotate-oscillate or static, got {t!r}")
    results = run_bench(trajectories, api_clients=api_clients, api_rate_hz=api_rate, seconds=seconds, width=width, height=height, spp=spp,
                        overrides=tuple(sets or ()), progress=lambda label: typer.echo(f"running {label} …"))
    typer.echo(format_table(results))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(results, indent=2))
        typer.echo(f"wrote {json_path}")
