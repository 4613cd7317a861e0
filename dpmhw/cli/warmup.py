"""`dpmhw warmup`: compile the session's kernels for this machine ahead of the first show."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Annotated, Optional

import typer

from dpmhw.cli.apps import app, write_json
from dpmhw.cli.apps import fail
from dpmhw.cli.session import ConfigOpt, SetOpt, _load


@app.command("warmup")
def warmup(
    config: ConfigOpt = None,
    sets: SetOpt = None,
    workers: Annotated[int, typer.Option(min=0, max=64, help="Worker processes (0: one per core, at most one per kernel group).")] = 0,
    profile: Annotated[bool, typer.Option("--profile", help="Compile into an empty temporary cache and print each kernel's cold compile time (the cache is left as it was).")] = False,
    json_path: Annotated[Optional[Path], typer.Option("--json", help="With --profile: write the per-kernel rows here (keys: kernel, group, seconds, llvm_seconds, signatures).")] = None,
) -> None:
    """Compile every kernel a session with this config runs (NUMBA_CACHE_DIR is respected), so
    that the first `session start` on this machine, a lab PC or a container image starts in
    seconds. Run it again after installing a new version or moving to another CPU."""
    from dpmhw.errors import DpmhwError
    from dpmhw.progress import Progress

    try:
        cfg = _load(config, sets, [])
    except DpmhwError as exc:
        fail(exc)
    if json_path is not None and not profile:
        raise typer.BadParameter("--json needs --profile")
    scratch = tempfile.TemporaryDirectory(prefix="dpmhw-profile-cache-") if profile else None
    if scratch is not None:
        os.environ["NUMBA_CACHE_DIR"] = scratch.name  # before numba is imported here or in the workers
    from dpmhw.session.warmup import compile_kernels, cache_dir

    try:
        with Progress() as bar:
            task = bar.task("compiling the render kernels", total=None)

            def show(p) -> None:
                task.update(p.done, p.expected or None)

            result = compile_kernels(cfg, progress=show, workers=workers or None, force=profile)
        for group, why in result.failed.items():
            typer.echo(f"error: the {group} kernels: {why}", err=True)
        if result.warm:
            typer.echo(f"already compiled for this machine; cache: {cache_dir()}")
        else:
            typer.echo(f"compiled {len(result.kernels)} functions in {result.elapsed_s:.1f} s with "
                       f"{result.workers} worker process(es); cache: {cache_dir() if scratch is None else scratch.name + ' (temporary)'}")
        if profile:
            rows = sorted(({"kernel": k, **v} for k, v in result.kernels.items()), key=lambda r: -r["seconds"])
            typer.echo(f"{'seconds':>8} {'LLVM s':>7} {'sigs':>4}  group / kernel")
            for r in rows:
                typer.echo(f"{r['seconds']:8.1f} {r['llvm_seconds']:7.1f} {r['signatures']:4d}  {r['group']} / {r['kernel']}")
            if json_path is not None:
                typer.echo(f"wrote {write_json(rows, json_path)}")
        if result.failed:
            raise typer.Exit(code=1)
    finally:
        if scratch is not None:
            scratch.cleanup()
