"""Readying the numba kernels before the loop needs them.

A first run on a machine compiles every kernel a session calls (numba type inference, then LLVM);
about half of it goes to the path tracer's `trace_segments`, whose callees (`shade`,
`sample_first`, the Embree queries) are compiled while it is typed. numba keeps compiled code on disk (in
`NUMBA_CACHE_DIR` when set, else in `__pycache__` beside the sources, or a per-user cache when
those are read-only), so later runs load it in a second or two. The cache is per CPU, numba
version and source file: a new machine, an update or a new install compiles again.

Two passes, so that no frame ever waits for a compile:

1. `compile_kernels`: independent groups compiled at once in worker processes that fill the
   cache, with progress (kernels done out of those expected, elapsed time, ETA). Nothing of the
   session is open yet, so a stop just ends the workers.
2. `SessionLoop.warm`: the session's own renderer and reconstruction stage run every per-frame
   path once (every reuse mode and filter an operator can switch to, an object moving between two
   frames) before the loop goes live: loaded from the cache, compiled where it lacks something.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)

@dataclass
class CompileProgress:
    """What `compile_kernels` reports while it works (and returns at the end)."""

    done: int = 0  # kernels of `GROUPS` compiled so far (cache loads are not counted: they take no time)
    expected: int = 0  # the kernels in `GROUPS`
    elapsed_s: float = 0.0
    eta_s: float | None = None  # None until something is done
    groups_left: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)  # group -> why (the loop then compiles it itself)
    stopped: bool = False
    workers: int = 0  # processes used
    warm: bool = False  # the cache already held everything: nothing was started
    # every function compiled: name -> group, seconds and LLVM seconds (exclusive of its callees), signatures
    kernels: dict[str, dict] = field(default_factory=dict)

    def line(self) -> str:
        if self.warm:
            return "render kernels: loaded from the cache"
        eta = "" if self.eta_s is None or not self.groups_left else f", about {self.eta_s:.0f} s left"
        head = f"compiling the render kernels (first run on this machine): {self.done}/{self.expected} kernels, {self.elapsed_s:.0f} s"
        return head + (eta if self.groups_left else ", done")

    def as_status(self) -> dict:
        return {"done": self.done, "expected": self.expected, "elapsed_s": round(self.elapsed_s, 1),
                "eta_s": None if self.eta_s is None else round(self.eta_s, 1), "groups_left": list(self.groups_left)}


def cache_dir() -> str:
    """Where this machine's compiled kernels live (the path tracer's, the others sit beside theirs)."""
    from dpmhw.render import kernels

    return kernels.trace_segments._cache._cache_path


def cache_is_warm() -> bool:
    """Whether the path tracer, the longest compile by far, is cached for this CPU and its
    source. A new install, numba version or CPU misses it with everything else; a kernel whose
    source alone was edited since is compiled by the loop process's warm-up instead (a slower
    start, never a late frame). Checking every kernel would import them all here, about a
    second of every start."""
    from dpmhw.render import kernels

    try:
        dispatcher = kernels.trace_segments
        index = dispatcher._cache._cache_file._load_index()  # {} when the source changed since
        magic = dispatcher.targetctx.codegen().magic_tuple()
        return any(key[1] == magic for key in index)
    except Exception:  # numba's private cache layout moved: assume cold, the workers find out
        return False


# ---- the groups: each runs in its own process, on the session's scene and sizes --------------------
def _build(config_data: dict, gbuffer: bool = True):
    from dpmhw.session.config import SessionConfig
    from dpmhw.session.factory import build_renderer, prepare_scene

    config = SessionConfig.model_validate(config_data)
    scene = prepare_scene(config)
    return (config, scene, *build_renderer(config, scene, gbuffer=gbuffer))


def _path_tracing(config_data: dict) -> None:
    """The renderer: a frame at two poses (camera hits traced, then kept) and a pixel subset; and
    the late reprojection (here rather than in the other group, to even out the two)."""
    from dpmhw.reconstruct.reproject import Reprojector
    from dpmhw.render.cameras import PinholeCamera
    from dpmhw.session.loop import exercise_reprojection

    config, scene, renderer, _ = _build(config_data, gbuffer=False)
    for k, t in enumerate((0.0, 0.0, 0.25)):
        renderer.render(time=t, seed=k, spp=1, poses=scene.object_poses(t))
    renderer.render_pixels(renderer.camera, np.arange(64), scene.object_poses(0.0), seed=1)
    if config.prediction.late_reprojection:  # at the output size, as the G-buffer's camera
        size = (scene.render.width, scene.render.height)
        camera = PinholeCamera(scene.camera.K, scene.camera.dist, *size, scene.camera.pose)
        exercise_reprojection(Reprojector(camera, [o.is_dynamic for o in scene.objects]), scene, size)


class _NoPaths:
    """The renderer as the reconstruction group sees it: subsets of pixels come back black. Its
    kernels (the path tracer's) are the other group's work; the reconstruction's own kernels
    are typed the same either way."""

    def __init__(self, renderer):
        self._renderer = renderer

    def render_pixels(self, camera, pixels, poses, seed, spp=1, static_hits=None):
        return np.zeros((len(pixels), 3), np.float32)

    def __getattr__(self, name):
        return getattr(self._renderer, name)


def _synthetic_frame(renderer, t: float):
    """A shading-size `Frame` with the renderer's types: zero light on object 0 everywhere."""
    from dpmhw.render.frame import Frame

    h, w = renderer.height, renderer.width
    rgb = lambda: np.zeros((h, w, 3), np.float32)  # noqa: E731
    return Frame(radiance=rgb(), diffuse=rgb(), specular=rgb(), object_id=np.zeros((h, w), np.int32),
                 model_position=rgb(), position=rgb(), normal=rgb(), depth=np.ones((h, w), np.float32), albedo=rgb(),
                 specular_albedo=rgb(), roughness=np.ones((h, w), np.float32), spp=1, time=t, seed=0)


def _reconstruction(config_data: dict) -> None:
    """The native G-buffer, reuse, filter, upsampling, LOD and post on synthetic frames."""
    from dpmhw.session.loop import exercise_stage, reconstruct_stage

    config, scene, renderer, gbuffer = _build(config_data)
    stage = reconstruct_stage(config, scene, _NoPaths(renderer), gbuffer, time.monotonic_ns)
    frames = [(scene.object_poses(t), _synthetic_frame(renderer, t)) for t in (0.0, 0.25)]
    exercise_stage(stage, frames, renderer.camera)


# Each group's kernels and their cold compile time in seconds (exclusive of the callees listed
# beside them), from `dpmhw warmup --profile --workers 1` with an empty cache on the machine of
# docs/first-run.md. They weigh the progress and its ETA (a kernel not listed is not counted).
EXPECTED_S: dict[str, dict[str, float]] = {
    "path tracing": {
        "render.kernels.shade": 7.7, "render.kernels.trace_segments": 5.3, "render.embree.traversal._closest_rows": 3.8,
        "render.kernels._sample_block_glossy": 3.5, "render.kernels._sample_block_lambert": 3.0,
        "render.kernels.first_surface": 2.8, "render.kernels.sample_first": 2.2, "render.static_raster._raster": 2.2,
        "reconstruct.reproject._splat": 1.8, "render.embree.traversal.occluded_range": 1.7,
        "reconstruct.reproject._reproject_windows": 1.6, "render.static_raster._setup": 1.6,
        "render.embree.traversal.closest_rows": 1.3,
    },
    "G-buffer and reconstruction": {
        "reconstruct.upsample._upsample_kernel": 6.9, "reconstruct.analytic._products_kernel": 3.3,
        "reconstruct.filter._filter_kernel": 3.2, "render.gbuffer._classify": 2.8, "render.gbuffer._attributes_py": 2.1,
        "reconstruct.guides._guides_kernel": 1.9, "reconstruct.reuse._same_pixel_py": 1.8,
        "reconstruct.reuse._motion_span": 1.7, "reconstruct.reuse._motion_py": 1.1,
        "reconstruct.analytic._row_counts": 0.8, "render.gbuffer._trace_pixels": 0.8,
        "reconstruct.analytic._prepare_span": 0.7, "reconstruct.analytic._irradiance_span": 0.7,
        "render.kernels.hit_point_ieee": 0.7, "reconstruct.analytic._specular_span": 0.7,
        "postprocess._encode_kernel": 0.7, "reconstruct.reuse._reproject_py": 0.7,
        "reconstruct.analytic._evaluate_block": 0.7, "reconstruct.analytic._clipped_edge": 0.6,
    },
}


@dataclass(frozen=True)
class KernelGroup:
    """Kernels compiled together in one worker: `run(config data)` calls them, `expected_s`
    weighs the progress."""

    run: Callable[[dict], None]
    expected_s: dict[str, float]


GROUPS: dict[str, KernelGroup] = {name: KernelGroup(run, EXPECTED_S[name]) for name, run in
                                  (("path tracing", _path_tracing), ("G-buffer and reconstruction", _reconstruction))}


def _qualname(dispatcher) -> str:
    f = dispatcher.py_func
    return f"{f.__module__.removeprefix('dpmhw.')}.{f.__qualname__}"


def _worker(group: str, run: Callable[[dict], None], config_data: dict, out) -> None:
    """One group in a worker process. Each finished compile goes to `out` as ("kernel", group,
    name, seconds, LLVM seconds), both exclusive of the callees compiled inside it; then
    ("done" | "failed", group, why)."""
    from numba.core import event

    stack: list[list] = []  # [start, seconds of nested compiles, LLVM seconds] per open compile

    class Compiles(event.Listener):
        def on_start(self, ev):
            stack.append([time.perf_counter(), 0.0, 0.0])

        def on_end(self, ev):
            start, nested, llvm = stack.pop()
            took = time.perf_counter() - start
            if stack:
                stack[-1][1] += took
            dispatcher = ev.data.get("dispatcher")
            if dispatcher is not None:
                out.put(("kernel", group, _qualname(dispatcher), took - nested, llvm))

    class Llvm(event.Listener):  # LLVM optimisation and code generation, inside a compile
        def on_start(self, ev):
            self.t = time.perf_counter()

        def on_end(self, ev):
            if stack:
                stack[-1][2] += time.perf_counter() - self.t

    event.register("numba:compile", Compiles())
    event.register("numba:llvm_lock", Llvm())
    try:
        run(config_data)
    except BaseException as exc:  # reported; the loop process compiles what is missing itself
        out.put(("failed", group, f"{type(exc).__name__}: {exc}"))
    else:
        out.put(("done", group, ""))


TRUST_PACE_AT = 0.1  # the fraction of the table's work done from which the observed pace alone sets the ETA


def eta_s(elapsed_s: float, frac: float, wall_s: float) -> float:
    """Seconds left when `frac` of the table's work (by its seconds) is done after `elapsed_s`,
    the table predicting `wall_s` for the whole. The table was measured on one CPU; on another
    the whole compile is slower or faster by about one factor, so it is estimated from the
    observed pace (elapsed / frac), blended with the table's `wall_s` until `TRUST_PACE_AT` of
    the work is done and alone from then on. A kernel counts when it ends, after the start-up
    and its callees: early on the estimate errs long, not short."""
    frac = min(frac, 0.99)
    if frac <= 0.0:
        return max(0.0, wall_s - elapsed_s)
    w = min(1.0, frac / TRUST_PACE_AT)
    return max(0.0, (1 - w) * wall_s + w * elapsed_s / frac - elapsed_s)


def compile_kernels(config, *, progress: Callable[[CompileProgress], None] | None = None,
                    should_stop: Callable[[], bool] = lambda: False, workers: int | None = None,
                    every_s: float = 1.0, force: bool = False, groups: dict[str, KernelGroup] | None = None,
                    clock: Callable[[], float] = time.monotonic) -> CompileProgress:
    """Fill the kernel cache for `config`'s session, its groups in parallel worker processes
    (`workers`, default one per core up to the number of groups). Returns at once when the cache
    is already warm (unless `force`). `progress` is called every `every_s` seconds and at each
    group's end; `should_stop` is polled as often (true: the workers are ended, `stopped` set)."""
    groups = GROUPS if groups is None else groups
    state = CompileProgress(groups_left=list(groups))
    if not force and cache_is_warm():
        state.warm, state.groups_left = True, []
        if progress is not None:
            progress(state)
        return state
    weights = {name: s for group in groups.values() for name, s in group.expected_s.items()}
    total_s = sum(weights.values())
    state.expected = len(weights)
    n = state.workers = max(1, min(len(groups), workers or os.cpu_count() or 1))
    group_s = sorted((sum(g.expected_s.values()) for g in groups.values()), reverse=True)
    wall_s = max(sum(group_s[i::n]) for i in range(n))  # the longest worker's share, by the table
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    config_data = config.model_dump() if hasattr(config, "model_dump") else dict(config)
    pending = list(groups)
    running: dict[str, multiprocessing.Process] = {}
    t0, done_s, last = clock(), 0.0, -every_s
    try:
        while pending or running:
            while pending and len(running) < n:
                group = pending.pop(0)
                running[group] = ctx.Process(target=_worker, args=(group, groups[group].run, config_data, out), daemon=True,
                                             name=f"dpmhw-compile ({group})")
                running[group].start()
            try:
                kind, group, what, *times = out.get(timeout=0.1)
            except queue.Empty:
                kind = ""
                for group, proc in list(running.items()):
                    if not proc.is_alive() and out.empty():  # died without a word (killed, out of memory)
                        del running[group]
                        state.failed[group] = f"worker exited with code {proc.exitcode}"
                        state.groups_left.remove(group)
            if kind == "kernel":
                took = state.kernels.setdefault(what, {"group": group, "seconds": 0.0, "llvm_seconds": 0.0, "signatures": 0})
                took["seconds"] += times[0]
                took["llvm_seconds"] += times[1]
                took["signatures"] += 1
                if what in weights and took["signatures"] == 1:  # a listed kernel, counted once
                    state.done += 1
                    done_s += weights[what]
            elif kind in ("done", "failed"):
                running.pop(group).join(5)
                state.groups_left.remove(group)
                if kind == "failed":
                    state.failed[group] = what
                    log.warning("compiling the %s kernels failed (the loop compiles them itself): %s", group, what)
            now = clock()
            state.elapsed_s = now - t0
            state.eta_s = eta_s(state.elapsed_s, done_s / total_s if total_s else 0.0, wall_s)
            if should_stop():
                state.stopped = True
                break
            if progress is not None and state.groups_left and (kind in ("done", "failed") or now - last >= every_s):
                last = now  # (the last report comes after the loop)
                progress(state)
    finally:
        for proc in running.values():
            proc.kill()
            proc.join(5)
        out.close()
    state.elapsed_s = clock() - t0
    if progress is not None and not state.stopped:
        progress(state)
    return state
