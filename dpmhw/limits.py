"""Size limits where outside input enters dpmhw, so nothing allocates without bound.

A scene file, a mesh and a render size come from a hand-edited file or a command line. Past
these limits a typo (a width of 163840) or a wrong file (a 2 GB scan) would run for minutes and
take the machine's memory before failing, so each is refused up front with an error naming the
limit and the environment variable that raises it:

- scene files: `DPMHW_MAX_SCENE_KB` (default 1024: hand-written scenes are a few kilobytes);
- mesh files: `DPMHW_MAX_MESH_MB` (default 512: the Stanford bunny's OBJ is 3 MB, a 10-million-
  triangle scan about 500 MB), for the file as stored and for what a compressed one expands to;
  what a mesh decodes to is charged to the render memory limit (`mesh_limits`);
- render buffers: `DPMHW_RENDER_MEMORY_MB` (default 4608). A render allocates per pixel its
  rays, path state, film lobes, G-buffer, the first vertices' surfaces, the rasterised camera
  hits and work arrays: measured here as 506 bytes per pixel (peak RSS of two 1-spp renders of
  paper-static at 2048×1536 minus 512×384), taken as 520. The default admits 4K (3840×2160 ≈ 4.3 GB).
- a session: `DPMHW_SESSION_MEMORY_MB` (default 8192). At its output (native) size a session
  holds the shading render and the native G-buffer, the reconstruction's guides, histories and
  output, the frame rendered ahead (pipelining) and the sink's frames. Measured as whole: the
  peak RSS of `dpmhw session start --mock --duration 3 --no-api` (dpm-bunny, the loop's child
  included) at two to four output sizes from 640×480 to 2560×1920 per shading scale, the
  difference over the difference in pixels: 890–910 bytes per output pixel at shading scale 1
  and ½, 530–690 at ¼ (less render, the same native buffers), taken as
  `SESSION_BYTES_PER_PIXEL`; the part that does not grow with the size (interpreter, compiled
  kernels, the bunny's BVH, the mocks) was 300–350 MiB, taken as `SESSION_BASE_BYTES`. The
  default admits 4K at ¼.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["RENDER_BYTES_PER_PIXEL", "SESSION_BASE_BYTES", "SESSION_BYTES_PER_PIXEL", "check_file_size", "max_mesh_bytes",
           "max_scene_bytes", "render_memory_limit", "render_memory_problem", "session_memory", "session_memory_problem"]

RENDER_BYTES_PER_PIXEL = 520
SESSION_BYTES_PER_PIXEL = {1.0: 960, 0.5: 960, 0.25: 740}  # per output pixel, by shading scale
SESSION_BASE_BYTES = 384 * 2**20


def _limit(env: str, default: int, unit: int) -> int:
    raw = os.environ.get(env, "")
    try:
        value = int(raw) if raw else default
    except ValueError:
        raise ValueError(f"{env}={raw!r}: expected a whole number") from None
    if value <= 0:
        raise ValueError(f"{env}={raw!r}: expected a positive number")
    return value * unit


def max_scene_bytes() -> int:
    return _limit("DPMHW_MAX_SCENE_KB", 1024, 1024)


def max_mesh_bytes() -> int:
    return _limit("DPMHW_MAX_MESH_MB", 512, 1024 * 1024)


def check_file_size(path: Path, limit: int, what: str, env: str) -> None:
    """Raise ValueError when `path` is larger than `limit` bytes (before anything reads it)."""
    size = Path(path).stat().st_size
    if size > limit:
        raise ValueError(f"{what} {path} is {size / 2**20:.1f} MiB, over the limit of {limit / 2**20:.3g} MiB "
                         f"(raise it with {env})")


def render_memory_limit() -> int:
    """Bytes a render may hold: its pixel buffers (`render_memory_problem`), and a mesh's arrays and BVH (`mesh_limits`)."""
    return _limit("DPMHW_RENDER_MEMORY_MB", 4608, 1024 * 1024)


def render_memory_problem(width: int, height: int) -> str | None:
    """Why a `width`×`height` render would allocate too much memory, or None when it fits."""
    limit = render_memory_limit()
    need = int(width) * int(height) * RENDER_BYTES_PER_PIXEL
    if need <= limit:
        return None
    return (f"a {width}×{height} render needs about {need / 2**20:.0f} MiB of pixel and ray buffers "
            f"({RENDER_BYTES_PER_PIXEL} bytes per pixel), over the limit of {limit / 2**20:.0f} MiB: lower the size, "
            f"or raise the limit with DPMHW_RENDER_MEMORY_MB")


def session_memory(width: int, height: int, shading_scale: float) -> tuple[int, int]:
    """(bytes a session at a `width`×`height` output needs, the limit)."""
    need = SESSION_BASE_BYTES + int(width) * int(height) * SESSION_BYTES_PER_PIXEL[shading_scale]
    return need, _limit("DPMHW_SESSION_MEMORY_MB", 8192, 1024 * 1024)


def session_memory_problem(width: int, height: int, shading_scale: float) -> str | None:
    """Why a session at a `width`×`height` output would allocate too much memory, or None when it fits."""
    need, limit = session_memory(width, height, shading_scale)
    if need <= limit:
        return None
    return (f"a session at a {width}×{height} output (shading_scale {shading_scale:g}) needs about "
            f"{need / 2**20:.0f} MiB ({SESSION_BYTES_PER_PIXEL[shading_scale]} bytes per output pixel for the render, "
            f"the native G-buffer, the reconstruction's histories and the frames in flight), over the limit of "
            f"{limit / 2**20:.0f} MiB: lower the size, or raise the limit with DPMHW_SESSION_MEMORY_MB")
