"""`dpmhw bench render`: where the time of a 1-spp frame goes, against raw Embree throughput.

Frame time is measured on consecutive frames of the scene's timeline (frame k: t = k / fps,
seed k), as the projection loop renders them. Time inside Embree is measured in the same frames
by timing every `EmbreeScene.run` call; raw throughput replays this scene's own ray batches
(camera, continuation and shadow rays of one frame) straight through `run` on the same thread
count, so "fraction inside Embree" compares like with like.
"""

from __future__ import annotations

import os
import platform
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dpmhw.render import kernels
from dpmhw.render.accel import empty_hits
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene


class _TimedScene:
    """Wraps an accel query method and adds up the seconds spent in it, per thread."""

    def __init__(self, fn, clock: dict):
        self._fn, self._clock = fn, clock

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self._fn(*args, **kwargs)
        finally:
            ident = threading.get_ident()
            self._clock[ident] = self._clock.get(ident, 0.0) + time.perf_counter() - start


def _replay(accel, R, T, batches, query: str, threads: int, repeats: int = 5) -> float:
    """Median rays/s of the accel's queries over the given (origins, directions, tmax) batches."""
    total = sum(len(b[0]) for b in batches)
    rates = []
    with ThreadPoolExecutor(threads) as pool:
        for _ in range(repeats):
            start = time.perf_counter()
            for o, d, tm in batches:
                bounds = np.linspace(0, len(o), 4 * threads + 1).astype(int)  # a few chunks per thread
                hits, blocked = empty_hits(len(o)), np.zeros(len(o), bool)
                jobs = [
                    pool.submit(accel.intersect_range, o, d, a, b, R, T, hits) if query == "INTERSECT"
                    else pool.submit(accel.occluded_range, o, d, tm, a, b, R, T, blocked)
                    for a, b in zip(bounds[:-1], bounds[1:])
                ]
                for job in jobs:
                    job.result()
            rates.append(total / (time.perf_counter() - start))
    return float(np.median(rates))


def bench_render(scene_name: str = "paper-static", frames: int = 9, threads: int = 2, mesh=None) -> dict:
    scene = load_scene(scene_name, mesh_override=mesh)
    integrator = PathIntegrator(scene, threads=threads)
    accel = integrator.geometry.accel
    clock: dict[int, float] = {}
    for name in ("intersect_range", "occluded_range", "intersect_static"):
        setattr(accel, name, _TimedScene(getattr(accel, name), clock))
    shade_seconds = [0.0]  # summed over the threads that run it
    shade = kernels.shade

    def timed_shade(*args):
        start = time.perf_counter()
        try:
            return shade(*args)
        finally:
            shade_seconds[0] += time.perf_counter() - start

    fps = scene.render.fps
    try:
        kernels.shade = timed_shade
        for k in range(2):  # JIT compilation, caches
            integrator.render(time=k / fps, seed=k)
        rows = []
        for k in range(frames):
            clock.clear()
            shade_seconds[0] = 0.0
            start = time.perf_counter()
            integrator.render(time=k / fps, seed=k)
            elapsed = time.perf_counter() - start
            c = integrator.counts
            rows.append(dict(ms=elapsed * 1e3, embree_ms=sum(clock.values()) / threads * 1e3, shade_ms=shade_seconds[0] / threads * 1e3,
                             camera=c.primary, static_camera_traced=c.primary_static_traced, continuation=c.intersect, shadow=c.occluded))
        cold = []
        for k in range(max(3, frames // 3)):  # camera moved every frame: static camera hits re-traced
            integrator._static_primary_key = None
            start = time.perf_counter()
            integrator.render(time=k / fps, seed=k)
            cold.append((time.perf_counter() - start) * 1e3)
        raw = _raw_throughput(integrator, threads)
    finally:
        kernels.shade = shade
        integrator.close()
    med = {key: float(np.median([r[key] for r in rows])) for key in rows[0]}
    rays = med["camera"] + med["continuation"] + med["shadow"]
    traced_closest = med["static_camera_traced"] + med["continuation"]
    embree_only_ms = (traced_closest / raw["closest_hit_rays_per_s"] + med["shadow"] / raw["occlusion_rays_per_s"]) * 1e3
    return {
        "scene": scene_name, "width": scene.render.width, "height": scene.render.height,
        "max_bounces": scene.render.max_bounces, "triangles": integrator.geometry.triangle_count,
        "mis_last": integrator.mis_last, "threads": threads, "frames": frames,
        "frame_ms_median": med["ms"], "frame_ms_min": min(r["ms"] for r in rows), "frame_ms_max": max(r["ms"] for r in rows),
        "frame_ms_cold_camera_median": float(np.median(cold)),
        "inside_embree_ms_median": med["embree_ms"], "inside_embree_fraction": med["embree_ms"] / med["ms"],
        "shade_kernel_ms_median": med["shade_ms"],
        "rays_per_frame": {"camera": int(med["camera"]), "continuation": int(med["continuation"]), "shadow": int(med["shadow"]), "total": int(rays)},
        "raw_embree": raw, "raw_embree_ms_for_frame_rays": embree_only_ms,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "per_frame": rows,
    }


def _raw_throughput(integrator: PathIntegrator, threads: int) -> dict:
    """Replay one frame's camera, continuation and shadow rays through the static BVH."""
    accel = integrator.geometry.accel
    for name in ("intersect_range", "occluded_range", "intersect_static"):
        if isinstance(getattr(accel, name), _TimedScene):
            setattr(accel, name, getattr(accel, name)._fn)
    o, d = integrator.camera.generate_rays()
    R, T = integrator.geometry.poses(integrator.scene.object_poses(0.0))
    captured = {"INTERSECT": [(o, d, np.full(len(o), np.inf, np.float32))], "OCCLUDED": []}
    intersect, occluded = accel.intersect_range, accel.occluded_range

    def cap_intersect(o, d, first, end, R, T, hits, static_done=False):
        if not static_done:  # (camera rays against the moving objects only: captured above)
            captured["INTERSECT"].append((o[first:end].copy(), d[first:end].copy(), np.full(end - first, np.inf, np.float32)))
        return intersect(o, d, first, end, R, T, hits, static_done)

    def cap_occluded(o, d, tmax, first, end, R, T, blocked):
        captured["OCCLUDED"].append((o[first:end].copy(), d[first:end].copy(), tmax[first:end].copy()))
        return occluded(o, d, tmax, first, end, R, T, blocked)

    accel.intersect_range, accel.occluded_range = cap_intersect, cap_occluded
    try:
        integrator.render(time=0.0, seed=12345)
    finally:
        accel.intersect_range, accel.occluded_range = intersect, occluded
    # one batch per query type (the frame traces them in per-segment pieces, on both threads at once)
    batches = {q: [tuple(np.concatenate(a) for a in zip(*v))] if v else [] for q, v in captured.items()}
    return {
        "closest_hit_rays_per_s": _replay(accel, R, T, batches["INTERSECT"], "INTERSECT", threads),
        "occlusion_rays_per_s": _replay(accel, R, T, batches["OCCLUDED"], "OCCLUDED", threads),
        "replayed_rays": {q: int(sum(len(b[0]) for b in v)) for q, v in captured.items()},
    }


def format_table(r: dict) -> str:
    rays = r["rays_per_frame"]
    raw = r["raw_embree"]
    lines = [
        f"scene {r['scene']}  {r['width']}×{r['height']}  {r['triangles']:,} triangles  max_bounces {r['max_bounces']}  "
        f"mis_last {r['mis_last']}  threads {r['threads']}  frames {r['frames']}",
        "",
        f"{'1-spp frame, camera fixed (median)':44s} {r['frame_ms_median']:8.1f} ms   (min {r['frame_ms_min']:.1f}, max {r['frame_ms_max']:.1f})",
        f"{'1-spp frame, camera moved every frame':44s} {r['frame_ms_cold_camera_median']:8.1f} ms",
        f"{'  inside Embree (timed run() calls)':44s} {r['inside_embree_ms_median']:8.1f} ms   ({100 * r['inside_embree_fraction']:.0f} % of the frame)",
        f"{'  shading kernel (thread-seconds / threads)':44s} {r['shade_kernel_ms_median']:8.1f} ms",
        f"{'rays per frame: camera / continuation / shadow':44s} {rays['camera']:,} / {rays['continuation']:,} / {rays['shadow']:,}",
        f"{'raw Embree, this scene, closest hit':44s} {raw['closest_hit_rays_per_s'] / 1e6:8.1f} Mrays/s",
        f"{'raw Embree, this scene, occlusion':44s} {raw['occlusion_rays_per_s'] / 1e6:8.1f} Mrays/s",
        f"{'raw Embree time for this frame’s traced rays':44s} {r['raw_embree_ms_for_frame_rays']:8.1f} ms   "
        f"({100 * r['raw_embree_ms_for_frame_rays'] / r['frame_ms_median']:.0f} % of the frame)",
    ]
    return "\n".join(lines)
