"""`dpmhw bench render`: where the time of a 1-spp frame goes, against raw ray-query throughput.

Frame time is measured on consecutive frames of the scene's timeline (frame k: t = k / fps,
seed k), as the projection loop renders them, with the projector fixed (`frame_ms_*`: its
camera hits on static objects are cached) and moved (`*_cold_camera_*`: panned by up to
±1° about the vertical, a different angle each frame, so camera rays and static hits are made
anew every frame, not only the hit cache's key dropped). With the
Embree C API one compiled call per render thread runs shading and every ray query of the image
segments that thread takes. Inside that
call nothing can be timed per stage, so the split is measured on the same frames rendered
staged (Python between the stages, the same kernels and queries, the same image): time inside
the ray queries (`inside_embree_ms_median`) and in the shading kernels (`shade_kernel_ms_median`:
kernels.first_surface, sample_first and shade; with the camera fixed the first vertices' surfaces
are kept, so first_surface runs in the first frame only), each as thread CPU-seconds / threads,
and the shading kernels' CPU-ns per path vertex (`shade_ns_per_vertex`); `main_thread_cpu_ms_median` is the calling
thread's CPU time per fixed frame, the part no render thread can share. Raw throughput replays
this scene's own ray batches of one frame
(camera, continuation and shadow rays, each query type alone) on the same thread count, in
Mrays per second of wall time and per CPU-second.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dpmhw.machine import machine_info
from dpmhw.render import kernels
from dpmhw.render.embree.accel import empty_hits
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene
from dpmhw.transforms import Pose, rotation_about_axis

QUERIES = ("intersect_range", "occluded_range", "intersect_static")
SHADING = ("first_surface", "sample_first", "shade")  # the shading kernels: the first vertex's two, then the others
PAN_DEG = 1.0  # the "camera moved" frames pan by up to this angle, a different one each frame


def panned_pose(pose: Pose, k: int) -> Pose:
    """Frame k's projector pose for the camera-moved frames: `pose` panned about the world's
    vertical axis by a different angle in ±PAN_DEG each frame (a real pose change: new camera
    rays and new static hits, as when a tracked projector moves)."""
    angle = np.radians(PAN_DEG * np.sin(1.0 + 2.3 * k))
    return Pose(rotation_about_axis((0.0, 1.0, 0.0), angle) @ pose.R, pose.t.copy())


class _Timed:
    """Wraps a query method or kernel and adds up the CPU-seconds its calling thread spends in
    it, per thread (thread CPU time: on a quiet machine the same as wall time, and on a shared
    one not inflated by waiting for a core)."""

    def __init__(self, fn, clock: dict):
        self._fn, self._clock = fn, clock

    def __call__(self, *args, **kwargs):
        start = time.thread_time()
        try:
            return self._fn(*args, **kwargs)
        finally:
            ident = threading.get_ident()
            self._clock[ident] = self._clock.get(ident, 0.0) + time.thread_time() - start


def bench_render(scene_name: str = "paper-static", frames: int = 9, threads: int = 2, mesh=None) -> dict:
    scene = load_scene(scene_name, mesh_override=mesh)
    integrator = PathIntegrator(scene, threads=threads)
    accel = integrator.geometry.accel
    fps = scene.render.fps
    try:
        for k in range(2):  # JIT compilation, caches
            integrator.render(time=k / fps, seed=k)
        rows = []
        for k in range(frames):
            start, start_cpu, start_main = time.perf_counter(), time.process_time(), time.thread_time()
            integrator.render(time=k / fps, seed=k)
            elapsed, cpu, main = time.perf_counter() - start, time.process_time() - start_cpu, time.thread_time() - start_main
            c = integrator.counts
            rows.append(dict(ms=elapsed * 1e3, cpu_ms=cpu * 1e3, main_cpu_ms=main * 1e3, camera=c.primary, static_camera_traced=c.primary_static_traced,
                             continuation=c.intersect, shadow=c.occluded))
        cold, cold_cpu = [], []
        for k in range(max(3, frames // 3)):  # camera moved every frame: new camera rays, static hits re-traced
            pose = panned_pose(integrator.camera.pose, k)
            start, start_cpu = time.perf_counter(), time.process_time()
            integrator.render(time=k / fps, seed=k, camera_pose=pose)
            cold.append((time.perf_counter() - start) * 1e3)
            cold_cpu.append((time.process_time() - start_cpu) * 1e3)
        split = _staged_split(integrator, frames, fps)
        raw = _raw_throughput(integrator, threads)
    finally:
        integrator.close()
    med = {key: float(np.median([r[key] for r in rows])) for key in rows[0]}
    rays = med["camera"] + med["continuation"] + med["shadow"]
    traced_closest = med["static_camera_traced"] + med["continuation"]
    embree_only_ms = (traced_closest / raw["closest_hit_rays_per_s"] + med["shadow"] / raw["occlusion_rays_per_s"]) * 1e3
    result = {
        "scene": scene_name, "width": scene.render.width, "height": scene.render.height,
        "max_bounces": scene.render.max_bounces, "triangles": integrator.geometry.triangle_count,
        "mis_last": integrator.mis_last, "threads": threads, "frames": frames,
        "backend": type(accel).__name__, "fused": bool(integrator.fused), "packets": list(integrator.packets),
        "frame_ms_median": med["ms"], "frame_ms_min": min(r["ms"] for r in rows), "frame_ms_max": max(r["ms"] for r in rows),
        "frame_ms_cold_camera_median": float(np.median(cold)),
        # CPU-seconds of all threads per frame: steadier than wall time on a shared machine
        "frame_cpu_ms_median": med["cpu_ms"], "frame_cpu_ms_cold_camera_median": float(np.median(cold_cpu)),
        # the calling thread's CPU time per frame: the serial part (the render threads do the rest)
        "main_thread_cpu_ms_median": med["main_cpu_ms"],
        "inside_embree_ms_median": split["embree_ms"], "inside_embree_fraction": split["embree_ms"] / split["ms"],
        "shade_kernel_ms_median": split["shade_ms"], "staged_frame_ms_median": split["ms"],
        "shade_ns_per_vertex": split["shade_ns_per_vertex"],
        "rays_per_frame": {"camera": int(med["camera"]), "continuation": int(med["continuation"]), "shadow": int(med["shadow"]), "total": int(rays)},
        "raw_embree": raw, "raw_embree_ms_for_frame_rays": embree_only_ms,
        "machine": machine_info(),
        "per_frame": rows,
    }
    for q in ("camera", "continuation", "shadow"):  # flat per-query rates
        result[f"{q}_mrays_per_s"] = raw[f"{q}_rays_per_s"] / 1e6
        result[f"{q}_mrays_per_cpu_s"] = raw[f"{q}_rays_per_cpu_s"] / 1e6
    return result


def _staged_split(integrator: PathIntegrator, frames: int, fps: float) -> dict:
    """Median ms per frame in the ray queries and in the shading kernel (thread-seconds /
    threads), from the same frames rendered with Python between the stages."""
    accel = integrator.geometry.accel
    clock: dict[int, float] = {}
    shade_clock: dict[int, float] = {}
    fused = integrator.fused
    shading = {name: getattr(kernels, name) for name in SHADING}
    originals = {name: getattr(accel, name) for name in QUERIES}
    rows = []
    try:
        integrator.fused = False
        for name, fn in shading.items():
            setattr(kernels, name, _Timed(fn, shade_clock))
        for name in QUERIES:
            setattr(accel, name, _Timed(originals[name], clock))
        for k in range(frames):
            clock.clear()
            shade_clock.clear()
            start = time.perf_counter()
            integrator.render(time=k / fps, seed=k)
            rows.append(((time.perf_counter() - start) * 1e3, sum(clock.values()) / integrator.threads * 1e3,
                         sum(shade_clock.values()) / integrator.threads * 1e3))
    finally:
        integrator.fused = fused
        for name, fn in shading.items():
            setattr(kernels, name, fn)
        for name in QUERIES:
            setattr(accel, name, originals[name])
    ms, embree_ms, shade_ms = (float(np.median(col)) for col in zip(*rows))
    c = integrator.counts
    vertices = c.primary + c.intersect  # shaded path vertices: one per camera ray and per continuation ray
    return {"ms": ms, "embree_ms": embree_ms, "shade_ms": shade_ms, "shade_ns_per_vertex": shade_ms * integrator.threads * 1e6 / vertices}


def _replay(fn, batch, threads: int, repeats: int = 5) -> tuple[float, float]:
    """Median rays per second of wall time and per CPU-second of fn(first, end) over a batch of
    n rays, split into a few chunks per thread (fn(0, n) once when it splits the batch itself:
    threads = 0)."""
    n = len(batch[0])
    bounds = np.linspace(0, n, 4 * max(threads, 1) + 1).astype(int) if threads else np.array([0, n])
    wall, cpu = [], []
    with ThreadPoolExecutor(max(threads, 1)) as pool:
        for _ in range(repeats):
            start, start_cpu = time.perf_counter(), time.process_time()
            for job in [pool.submit(fn, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]:
                job.result()
            wall.append(n / (time.perf_counter() - start))
            cpu.append(n / max(time.process_time() - start_cpu, 1e-9))
    return float(np.median(wall)), float(np.median(cpu))


def _raw_throughput(integrator: PathIntegrator, threads: int) -> dict:
    """Replay one frame's camera (static BVH), continuation and shadow rays, each alone."""
    accel = integrator.geometry.accel
    o, d = integrator.camera.generate_rays()
    R, T = integrator.geometry.poses(integrator.scene.object_poses(0.0))
    captured = {"INTERSECT": [], "OCCLUDED": []}
    intersect, occluded = accel.intersect_range, accel.occluded_range

    def cap_intersect(o, d, first, end, R, T, hits, static_done=False, packets=False):
        if not static_done:  # (camera rays against the moving objects only: not a separate batch)
            captured["INTERSECT"].append((o[first:end].copy(), d[first:end].copy()))
        return intersect(o, d, first, end, R, T, hits, static_done, packets=packets)

    def cap_occluded(o, d, tmax, first, end, R, T, blocked, packets=False):
        captured["OCCLUDED"].append((o[first:end].copy(), d[first:end].copy(), tmax[first:end].copy()))
        return occluded(o, d, tmax, first, end, R, T, blocked, packets=packets)

    fused = integrator.fused
    accel.intersect_range, accel.occluded_range, integrator.fused = cap_intersect, cap_occluded, False
    try:
        integrator.render(time=0.0, seed=12345)
    finally:
        accel.intersect_range, accel.occluded_range, integrator.fused = intersect, occluded, fused
    # one batch per query type (the frame traces them in per-segment pieces, on both threads at once)
    cont = tuple(np.concatenate(a) for a in zip(*captured["INTERSECT"])) if captured["INTERSECT"] else (np.zeros((0, 3), np.float32),) * 2
    shadow = tuple(np.concatenate(a) for a in zip(*captured["OCCLUDED"])) if captured["OCCLUDED"] else (np.zeros((0, 3), np.float32),) * 2 + (np.zeros(0, np.float32),)
    hits = empty_hits(max(len(o), len(cont[0])))
    blocked = np.zeros(len(shadow[0]), bool)
    pk_next, pk_shadow = integrator.packets
    cam = _replay(lambda a, e: accel.intersect_static(o, d), (o,), 0)  # (on the accel's own threads)
    nxt = _replay(lambda a, e: intersect(cont[0], cont[1], a, e, R, T, hits, packets=pk_next), cont, threads) if len(cont[0]) else (np.nan, np.nan)
    occ = _replay(lambda a, e: occluded(shadow[0], shadow[1], shadow[2], a, e, R, T, blocked, packets=pk_shadow), shadow, threads) if len(shadow[0]) else (np.nan, np.nan)
    closest_rate = (len(o) + len(cont[0])) / (len(o) / cam[0] + (len(cont[0]) / nxt[0] if len(cont[0]) else 0.0))
    return {
        "camera_rays_per_s": cam[0], "camera_rays_per_cpu_s": cam[1],
        "continuation_rays_per_s": nxt[0], "continuation_rays_per_cpu_s": nxt[1],
        "shadow_rays_per_s": occ[0], "shadow_rays_per_cpu_s": occ[1],
        "closest_hit_rays_per_s": closest_rate, "occlusion_rays_per_s": occ[0],
        "replayed_rays": {"INTERSECT": int(len(o) + len(cont[0])), "OCCLUDED": int(len(shadow[0]))},
    }


def format_table(r: dict) -> str:
    rays = r["rays_per_frame"]
    raw = r["raw_embree"]
    lines = [
        f"scene {r['scene']}  {r['width']}×{r['height']}  {r['triangles']:,} triangles  max_bounces {r['max_bounces']}  "
        f"mis_last {r['mis_last']}  threads {r['threads']}  frames {r['frames']}  {r['backend']}  packets {r['packets']}",
        "",
        f"{'1-spp frame, camera fixed (median)':44s} {r['frame_ms_median']:8.1f} ms   (min {r['frame_ms_min']:.1f}, max {r['frame_ms_max']:.1f})",
        f"{'1-spp frame, camera moved every frame':44s} {r['frame_ms_cold_camera_median']:8.1f} ms",
        f"{'  CPU time, camera fixed / moved':44s} {r['frame_cpu_ms_median']:8.1f} / {r['frame_cpu_ms_cold_camera_median']:.1f} CPU-ms",
        f"{'  of which the calling thread (serial)':44s} {r['main_thread_cpu_ms_median']:8.1f} CPU-ms",
        f"{'  inside Embree (staged frames, query CPU time)':44s} {r['inside_embree_ms_median']:8.1f} ms   ({100 * r['inside_embree_fraction']:.0f} % of the frame)",
        f"{'  shading kernel (thread CPU-s / threads)':44s} {r['shade_kernel_ms_median']:8.1f} ms   (staged frame {r['staged_frame_ms_median']:.1f} ms, "
        f"{r['shade_ns_per_vertex']:.0f} ns per vertex)",
        f"{'rays per frame: camera / continuation / shadow':44s} {rays['camera']:,} / {rays['continuation']:,} / {rays['shadow']:,}",
        f"{'raw queries, camera rays (static BVH)':44s} {raw['camera_rays_per_s'] / 1e6:8.1f} Mrays/s   ({raw['camera_rays_per_cpu_s'] / 1e6:.1f} per CPU-s)",
        f"{'raw queries, continuation rays':44s} {raw['continuation_rays_per_s'] / 1e6:8.1f} Mrays/s   ({raw['continuation_rays_per_cpu_s'] / 1e6:.1f} per CPU-s)",
        f"{'raw queries, shadow rays':44s} {raw['shadow_rays_per_s'] / 1e6:8.1f} Mrays/s   ({raw['shadow_rays_per_cpu_s'] / 1e6:.1f} per CPU-s)",
        f"{'raw Embree time for this frame’s traced rays':44s} {r['raw_embree_ms_for_frame_rays']:8.1f} ms   "
        f"({100 * r['raw_embree_ms_for_frame_rays'] / r['frame_ms_median']:.0f} % of the frame)",
    ]
    return "\n".join(lines)
