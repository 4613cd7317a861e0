"""Wavefront path tracer: Embree for every ray query, fused numba kernels for everything else.

Per pass (1 sample per pixel): primary hits; the first vertex in two kernels,
`first_surface` (what does not depend on the pass's random numbers: hit point, facing normals,
material, emission seen, G-buffer; kept per camera pose while nothing moves) and
`sample_first` (NEE shadow ray and BSDF sample, vectorised over the pixels); then per further
bounce: `shade` (emission with MIS, one NEE shadow ray, BSDF sampling, Russian roulette,
compaction of the shadow rays and surviving paths); each followed by the occlusion query for
its shadow rays and the closest-hit query for its continuation rays. The wavefront runs per image
segment, one thread taking a segment through all its bounces; with Embree's C API the whole
chain of a segment is compiled code (`kernels.trace_segment`, queries from inside), and each render
thread makes one call per pass that takes segments until none is left (`kernels.trace_segments`).
Pixel sampling: "centre" traces the pixel centres (static hits cached per camera pose, reused by
every pass); "jitter" traces a random point of each pixel on every pass (deterministic from
seed, pass and pixel), so the passes converge to the pixel integral under a box filter.
With `max_bounces` = B a path has B + 1 vertices; the last one is lit by NEE alone, unless the
scene has glossy lobes, where one more ray is traced from it so emitters it finds get MIS weights
(`mis_last`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np

from dpmhw.errors import RenderError
from dpmhw.limits import render_memory_problem
from dpmhw.parallel_kernels import kernel_threads
from dpmhw.render import kernels
from dpmhw.render.cameras import PinholeCamera
from dpmhw.render.embree.accel import Hits, RtcAccel, empty_hits
from dpmhw.render.frame import Frame
from dpmhw.render.geometry import SceneGeometry
from dpmhw.render.static_raster import CameraHits
from dpmhw.scene_file import Scene
from dpmhw.transforms import Pose

f32 = np.float32
GLOSSY_ROUGHNESS = 0.5  # below this, a specular lobe is sharp enough that NEE alone is noisy
# Image segments, each traced independently by one thread. Their number follows the image size
# (never the thread count): big enough that the Python between native calls is small next to
# them (a 256×192 frame rendered 2× faster in 8 segments than in 64), many enough to balance the
# threads. Random numbers hash the pixel, so segmentation never changes the image.
SEGMENT_PIXELS = 6144
MAX_SEGMENTS = 64
PIXEL_SAMPLING = ("centre", "jitter")
_NO_CORNERS = np.zeros((1, 1, 2), np.float32)
SUBSET_SALT = 0xBB67AE8584CAA73B  # render_pixels' random stream: independent of render's
PACKETS = (True, True)  # measured: packets beat single rays for every query type here (README)


@dataclass
class RayCounts:
    """Rays traced in one render call, by query type (for the benchmark)."""

    primary: int = 0  # camera rays (hits on static objects are reused while the camera stays put)
    primary_static_traced: int = 0  # camera rays traced against the static BVH in this call
    intersect: int = 0  # continuation rays (closest hit)
    occluded: int = 0  # shadow rays
    primary_traced: int = 0  # camera rays traced in full (pixel jitter: every pass)
    primary_static_rasterised: int = 0  # camera hits on static objects rasterised in this call (instead of traced)


class PathIntegrator:
    """Renders a Scene from its camera on `threads` threads (image segments, each taken through
    shading and its Embree queries by one thread)."""

    def __init__(self, scene: Scene, threads: int = 2, mis_last: bool | None = None, pixel_sampling: str = "centre"):
        if pixel_sampling not in PIXEL_SAMPLING:
            raise ValueError(f"pixel_sampling: expected one of {', '.join(PIXEL_SAMPLING)}, got {pixel_sampling!r}")
        problem = render_memory_problem(scene.render.width, scene.render.height)  # before any allocation
        if problem is not None:
            raise RenderError(problem)
        # "centre": one ray through each pixel centre (camera hits on static objects cached per
        # camera pose); "jitter": through a random point of the pixel on every pass, so the
        # passes converge to the pixel's integral (box filter); camera rays traced every pass
        self.pixel_sampling = pixel_sampling
        self.scene = scene
        self.geometry = SceneGeometry(scene, threads=threads)
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="render") if self.threads > 1 else None
        r = scene.render
        self.width, self.height, self.max_bounces = r.width, r.height, r.max_bounces
        self.camera = PinholeCamera(scene.camera.K, scene.camera.dist, r.width, r.height, scene.camera.pose)
        if mis_last is None:
            mis_last = any(np.any(o.specular > 0) and o.roughness < GLOSSY_ROUGHNESS for o in scene.objects)
        self.mis_last = bool(mis_last)
        # diffuse/specular split of the film only where some object has a specular lobe
        self.split = bool(any(np.any(o.specular > 0) for o in scene.objects))
        self.use_viewer = not np.allclose(scene.viewer_position, scene.camera.pose.t)
        self.counts = RayCounts()
        self._static_primary_key = None
        self._static_primary_hits = None
        self._pending_key = None  # the pose whose static hits the next pass traces
        self._rays = None  # camera rays (origins, directions), rewritten in place for a new pose
        self._rays_key = None
        self._work: list[_Work] = []  # most recently used first
        # (pose key, work buffers, G-buffer): the first vertices' surfaces in those buffers and the
        # G-buffer are this pose's, for as long as nothing moves (then frames share the G-buffer).
        # Kept from a pose's second frame on: a moving camera keeps nothing (a G-buffer held past
        # its frame made the allocator hand every moved frame fresh, page-faulting memory)
        self._surface: tuple | None = None
        self._last_pose_key = None
        # (continuation, shadow) rays as 16-wide packets of consecutive paths, or single rays
        self.packets = PACKETS
        # one compiled call per thread and pass (with the C API); False: Python between the stages (the
        # embreex fallback, and the benchmark's per-stage timing)
        self.fused = True
        # a new camera pose's hits on static objects by rasterisation (static_raster.CameraHits: 15 against
        # 35 CPU-ms for paper-static's, the same triangles but at shared edges); not with lens
        # distortion, whose pixel rays are traced. False: traced (for comparisons)
        self.raster_camera = True
        self._raster = None if np.any(self.camera.dist != 0) else CameraHits(scene.objects, self.geometry.tri_offsets)
        r = self._raster
        # its tables as trace_segment takes them (empty without a rasteriser)
        self._raster_tables = ((r.vertices, r.faces, r.tri_obj, r.tri_prim) if r is not None else
                               (np.zeros((0, 3), f32), np.zeros((0, 3), np.int32), _NO_TRI, _NO_TRI))
        self._raster_tri = _NO_TRI  # each pixel's rasterised triangle for the pose the next pass resolves (none: traced)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        self.geometry.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def render(
        self,
        time: float = 0.0,
        seed: int = 0,
        spp: int = 1,
        poses: list[Pose] | None = None,
        camera_pose: Pose | None = None,
        progress: Callable[[int, int], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> Frame:
        """Render `spp` passes of the scene at `time` (poses override the scripted ones, e.g. from
        a tracker). `should_stop` is polled between passes: the frame then holds the finished ones."""
        if spp < 1:
            raise ValueError(f"spp must be ≥ 1, got {spp}")
        poses = poses if poses is not None else self.scene.object_poses(time)
        if len(poses) != len(self.scene.objects):
            raise ValueError(f"expected {len(self.scene.objects)} poses, got {len(poses)}")
        camera = self.camera if camera_pose is None else self.camera.with_pose(camera_pose)
        R, T = self.geometry.poses(poses)
        self.counts = RayCounts()
        npix = self.width * self.height
        jitter = self.pixel_sampling == "jitter"
        moving = bool(self.geometry.accel.dynamic_objects)
        # The first vertices' surfaces depend on the camera hits alone: computed by the first pass
        # (every pass with jitter), and kept with the G-buffer while the camera and all objects stay put
        pose_key = (camera.pose.R.tobytes(), camera.pose.t.tobytes())
        w = self._work_buffers(npix)
        kept = (not jitter and not moving and self._surface is not None and self._surface[0] == pose_key
                and self._surface[1] is w and self._static_primary_key == pose_key)
        if not kept:
            self._surface = None
        same_pose, self._last_pose_key = self._last_pose_key == pose_key, pose_key
        # allocated empty: each segment clears its own rows in its thread (kernels.clear_rows)
        film = {k: np.empty((npix, 3), f32) for k in ("emit", "diff", "spec")}
        gbuf = self._surface[2] if kept else _GBuffer(npix)
        nonfinite = np.empty(npix, np.int32)
        # at 1 spp with the compiled path, the segments also write the radiance sum
        radiance = np.empty((npix, 3), f32) if spp == 1 and self._fused_native() else None
        o, d = self._camera_rays(camera)
        if jitter:  # every pass traces its own camera rays in full, into the work buffers
            static_hits, primary, trace_static = None, w.primary, False
        else:
            # with the C API a new pose's static hits are traced by the first pass's segments
            static_hits, trace_static = self._static_primary(camera, pose_key, o, d, defer=self._fused_native())
            # without moving objects the cached hits are the primary hits; with them, the first
            # pass completes them per segment (in its thread) into a work buffer later passes reuse
            primary = w.primary if moving else static_hits
        self.counts.primary = npix
        done = 0
        for p in range(spp):
            if should_stop is not None and done > 0 and should_stop():
                break
            surface_ready = kept or (p > 0 and not jitter)
            self._trace_pass(kernels.pass_key(seed, p), o, d, static_hits if moving and p == 0 else None, primary,
                             R, T, camera, film, _NO_GBUFFER if kept else gbuf, nonfinite, p == 0 and not kept,
                             kernels.jitter_key(seed, p) if jitter else None,
                             trace_static=trace_static and p == 0, clear=p == 0, radiance=radiance, surface_ready=surface_ready)
            if trace_static and p == 0:  # the cache is valid only once a pass has filled all of it
                self._static_primary_key = self._pending_key
            if jitter:
                self.counts.primary_traced += npix
            done += 1
            if progress is not None:
                progress(done, spp)
        if not kept and same_pose and not jitter and not moving and done:
            # this pose's surfaces and G-buffer, kept (read-only from now on: later frames share it)
            for a in vars(gbuf).values():
                a.flags.writeable = False
            self._surface = (pose_key, w, gbuf)
        H, W = self.height, self.width
        # x / 1 == x exactly: at 1 spp hand over the film arrays (fresh each frame) without copies
        emit, diff, spec = (film[k].reshape(H, W, 3) / f32(done) if done > 1 else film[k].reshape(H, W, 3) for k in ("emit", "diff", "spec"))
        return Frame(
            radiance=radiance.reshape(H, W, 3) if radiance is not None else emit + diff + spec, diffuse=diff, specular=spec,
            object_id=gbuf.id.reshape(H, W), model_position=gbuf.model.reshape(H, W, 3),
            position=gbuf.pos.reshape(H, W, 3), normal=gbuf.normal.reshape(H, W, 3),
            depth=gbuf.depth.reshape(H, W), albedo=gbuf.alb.reshape(H, W, 3),
            specular_albedo=gbuf.spec.reshape(H, W, 3), roughness=gbuf.rough.reshape(H, W),
            spp=done, time=float(time), seed=int(seed), nonfinite_samples=int(nonfinite.sum()),
        )

    def render_pixels(self, camera: PinholeCamera, pixels: np.ndarray, poses: list[Pose], seed: int, spp: int = 1,
                      static_hits: Hits | None = None) -> np.ndarray:
        """Radiance (n, 3) of `spp` paths through the centres of `camera`'s pixels `pixels` (flat
        row-major indices; any camera, e.g. the projector's native one while the integrator
        shades at a lower resolution). `static_hits`: the camera's cached hits on static
        objects for every pixel (else traced here). Deterministic per (seed, pixels): the random
        numbers hash the pixel's position in `pixels` and a key of the seed independent of
        `render`'s. `counts` then holds this call's rays.

        Per path this costs what the same path costs inside `render` (the kernels are the same);
        what is per call is kept small: the working arrays are views of one buffer that only
        grows (callers ask for a different n every frame; fresh arrays would cost page faults
        and evict `render`'s), and no G-buffer is allocated (none is written)."""
        if spp < 1:
            raise ValueError(f"spp must be ≥ 1, got {spp}")
        pixels = np.asarray(pixels, np.int64)
        n = len(pixels)
        R, T = self.geometry.poses(poses)
        self.counts = RayCounts(primary=n)
        film = {k: np.zeros((n, 3), f32) for k in ("emit", "diff", "spec")}
        if n == 0:
            return film["emit"]
        if pixels.min() < 0 or pixels.max() >= camera.width * camera.height:
            raise ValueError(f"pixels: indices must lie in [0, {camera.width * camera.height}) for a "
                             f"{camera.width}×{camera.height} camera")
        work, o, d = self._pixel_work(n)
        o_all, d_all = camera.generate_rays()
        np.take(o_all, pixels, axis=0, out=o)
        np.take(d_all, pixels, axis=0, out=d)
        moving = bool(self.geometry.accel.dynamic_objects)
        primary = work.primary  # camera hits of the subset: the static ones gathered (completed in pass 0 when objects move)
        if static_hits is None:
            sh = self.geometry.accel.intersect_static(o, d)
            for name in ("t", "obj", "prim", "u", "v"):
                getattr(primary, name)[:] = getattr(sh, name)
            self.counts.primary_static_traced = n
        else:
            for name in ("t", "obj", "prim", "u", "v"):
                np.take(getattr(static_hits, name), pixels, out=getattr(primary, name))
        nonfinite = np.zeros(n, np.int32)
        for p in range(spp):
            key = np.uint64(int(kernels.pass_key(seed, p)) ^ SUBSET_SALT)
            self._trace_pass(key, o, d, primary if moving and p == 0 else None, primary, R, T, camera, film, _NO_GBUFFER,
                             nonfinite, False, work=work)
        return (film["emit"] + film["diff"] + film["spec"]) / f32(spp)

    def _pixel_work(self, n: int) -> tuple["_Work", np.ndarray, np.ndarray]:
        """`render_pixels`' working arrays for n paths in ≥ `threads` segments, and its camera
        rays' origins and directions: views of buffers kept apart from `render`'s, grown by a
        quarter when too small."""
        pool = getattr(self, "_pixel_pool", None)
        if pool is None or pool[0].n < n:
            cap = max(n, n + n // 4, 1024)
            pool = self._pixel_pool = (_Work(cap, self.threads), np.empty((cap, 3), f32), np.empty((cap, 3), f32))
        full, o, d = pool
        return full.prefix(n), o[:n], d[:n]

    def _camera_rays(self, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
        """`camera.generate_rays()`, the same rays, in two arrays kept between frames: a new pose
        rewrites them in place, split by segments between the render threads (compiled, no
        numpy temporaries, no fresh 9 MB arrays and their page faults every moved frame)."""
        key = (camera.pose.R.tobytes(), camera.pose.t.tobytes())
        if self._rays_key is not None and self._rays_key[0] is camera._dirs_cam and self._rays_key[1] == key:
            return self._rays
        n = camera.width * camera.height
        if self._rays is None or len(self._rays[0]) != n:
            self._rays = (np.empty((n, 3), f32), np.empty((n, 3), f32))
        self._rays_key = None
        o, d = self._rays
        w = self._work_buffers(n)
        segments = [(int(a), int(a + c)) for a, c in zip(w.starts, w.full_counts) if c > 0]
        if self._pool is not None:
            list(self._pool.map(lambda s: camera.rays_into(o, d, *s), segments))
        else:
            for s in segments:
                camera.rays_into(o, d, *s)
        self._rays_key = (camera._dirs_cam, key)
        return self._rays

    def _fused_native(self) -> bool:
        """Compiled calls that take whole segments, Embree queried from inside (the C API is loaded)."""
        return self.fused and isinstance(self.geometry.accel, RtcAccel)

    def _static_primary(self, camera: PinholeCamera, key, o, d, defer: bool = False) -> tuple[Hits, bool]:
        """Primary hits on static objects depend only on the camera pose: made once per pose
        (rasterised, or traced with lens distortion or `raster_camera` off). Returns (hits,
        whether they are still to be made). `defer`: for a new pose, return the cache's arrays
        (reused in place, not 16 MB allocated per moved frame) for the first pass's segments to
        fill (resolving their pixels on the rasterised triangles, or tracing their camera rays);
        the pose is recorded once that pass is done. `key`: the pose's (render's pose_key)."""
        if self._static_primary_key == key:
            return self._static_primary_hits, False
        self._raster_tri = _NO_TRI
        if self._raster is not None and self.raster_camera:
            self.counts.primary_static_rasterised = len(o)
            with kernel_threads(self.threads):  # numba's pool, on this integrator's thread count
                if not defer:
                    self._static_primary_hits = self._raster.hits(camera, d, out=self._cache_hits(len(o)))
                    self._static_primary_key = key
                    return self._static_primary_hits, False
                # each pixel's triangle now; the first pass's segments resolve their pixels' hits
                self._raster_tri = self._raster.triangles(camera)
        else:
            self.counts.primary_static_traced = len(o)
        if not defer:
            self._static_primary_hits = self.geometry.accel.intersect_static(o, d, width=self.width)
            self._static_primary_key = key
            return self._static_primary_hits, False
        self._static_primary_hits = self._cache_hits(len(o))
        self._static_primary_key, self._pending_key = None, key
        return self._static_primary_hits, True

    def _cache_hits(self, n: int) -> Hits:
        """The static-hit cache's arrays for n pixels, reused in place (not 16 MB allocated per moved frame)."""
        if self._static_primary_hits is None or len(self._static_primary_hits.t) != n:
            self._static_primary_hits = empty_hits(n)
        return self._static_primary_hits

    def _trace_pass(self, key, camera_o, primary_dirs, static_hits: Hits | None, primary: Hits, R, T, camera, film, gbuf,
                    nonfinite, write_gbuffer, jitter_key=None, work: "_Work | None" = None, trace_static: bool = False,
                    clear: bool = False, radiance: np.ndarray | None = None, surface_ready: bool = False):
        """One sample per pixel. The image is cut into row ranges (segments); each is traced to the
        end of its paths by one thread (shade → shadow rays → continuation rays → shade …), so a
        segment's rays and hits are still in cache when the next stage reads them, and the
        threads never wait for each other between stages. Segments write disjoint pixels.
        `trace_static` (fused path only): the camera rays' static hits (`static_hits`, or `primary`
        when nothing moves) are still to be traced, by each segment for its own rows. `clear`:
        each segment first zeros its rows of the film. `surface_ready`: the work buffers'
        first-vertex surfaces (`kernels.first_surface`) are already those of `primary` (else each
        segment computes its rows of them, writing the G-buffer when `write_gbuffer`).
        `radiance` (fused path only): each segment writes its rows of emit + diff + spec there."""
        w = work if work is not None else self._work_buffers(len(primary.t))
        cam_fwd = camera.pose.R[:, 2].astype(f32)
        viewer = self.scene.viewer_position.astype(f32)
        accel = self.geometry.accel
        corners = camera.pixel_corners() if jitter_key is not None else _NO_CORNERS  # centre sampling reads none
        cam_R = camera.pose.R.astype(f32)
        light_world = self.geometry.light_rows(R, T)
        if jitter_key is not None:  # camera rays through random points of the pixels, into the work buffer
            primary_dirs = w.cam_d
        # the kernels' tuples (kernels.trace_segment)
        g = self.geometry
        scn = (g.tri, R, T, g.obj_albedo, g.textures, g.obj_specular, g.obj_alpha, g.obj_emission, g.obj_pdf_area, light_world, g.light_obj,
               g.light_cdf, g.p_env, g.background, viewer, self.use_viewer, cam_fwd)
        films = (film["emit"], film["diff"], film["spec"], nonfinite)
        gb = (gbuf.id, gbuf.model, gbuf.pos, gbuf.normal, gbuf.depth, gbuf.alb, gbuf.spec, gbuf.rough, write_gbuffer)
        work = (w.pixel, w.beta, w.kd, w.prev_pdf, w.prev_env, w.sh_o, w.sh_d, w.sh_tmax, w.sh_c, w.sh_pix, w.blocked,
                w.ray_o[0], w.ray_d[0], w.ray_o[1], w.ray_d[1], w.hits.t, w.hits.obj, w.hits.prim, w.hits.u, w.hits.v)
        prim = (primary.t, primary.obj, primary.prim, primary.u, primary.v)
        if self._fused_native():  # queries from inside the kernel: one native call per thread
            # the static camera hits: traced per segment for a new pose, copied into `primary`'s
            # rows and completed with the moving objects (static_hits given), or primary itself
            cache = static_hits if static_hits is not None else primary
            static = (trace_static, cache.t, cache.obj, cache.prim, cache.u, cache.v, self._raster_tri if trace_static else _NO_TRI,
                      *self._raster_tables, camera.pose.t.astype(f32))
            depth_limit = self.max_bounces + (1 if self.mis_last else 0)
            jitter = (jitter_key is not None, np.uint64(jitter_key or 0), corners, cam_R, self.width, w.cam_d)
            surface = (surface_ready, w.surf)

            counter = np.zeros(1, np.int64)  # the next segment, taken by the threads as they get free
            no_radiance = np.empty((0, 3), f32)

            def run(_):
                traced = kernels.trace_segments(counter, w.starts, w.full_counts, clear, no_radiance if radiance is None else radiance,
                                                accel.acc, accel.acc_moving, accel.acc_static, self.packets, self.split, depth_limit,
                                                self.max_bounces, self.mis_last, key, primary_dirs, prim,
                                                static_hits is not None, static, camera_o, scn, films, gb, surface, work, jitter)
                if traced[0] < 0:
                    raise RenderError("path depth exceeded 4096: Russian roulette failed to terminate")
                return traced

            jobs = range(self.threads)  # one call per thread; the kernel hands out the segments
        else:
            if trace_static or radiance is not None:
                raise ValueError("trace_static and radiance need the fused path")

            def run(segment):
                first, count = segment
                if clear:
                    kernels.clear_rows(films, first, first + count)
                if jitter_key is not None:
                    kernels.jittered_directions(corners, cam_R, self.width, jitter_key, first, first + count, primary_dirs)
                    accel.intersect_range(camera_o, primary_dirs, first, first + count, R, T, primary, packets=self.packets[0])
                return self._trace_segment(first, count, key, camera_o, primary_dirs, static_hits, primary, prim, R, T, scn, films, gb, work,
                                           surface_ready, w)

            jobs = [(int(a), int(c)) for a, c in zip(w.starts, w.full_counts) if c > 0]
        results = list(self._pool.map(run, jobs)) if self._pool is not None else [run(j) for j in jobs]
        self.counts.occluded += sum(r[0] for r in results)
        self.counts.intersect += sum(r[1] for r in results)

    def _trace_segment(self, first, count, key, camera_o, primary_dirs, static_hits, primary, prim, R, T, scn, films, gb, work,
                       surface_ready, w: "_Work") -> tuple[int, int]:
        """All bounces of the paths through pixels [first, first + count), with Python between
        the stages (the same kernels and queries as kernels.trace_segment, so the same image);
        their rows in the work buffers are the same range. `static_hits`: the camera rays'
        cached hits on static objects, to complete with the moving objects into `primary` first
        (None: `primary` is ready); `prim`, `scn`, `films`, `gb`, `work`: the kernels' tuples of
        `primary` and `w`. Returns (shadow rays, continuation rays) traced."""
        g = self.geometry
        end = first + count
        if static_hits is not None:
            for name in ("t", "obj", "prim", "u", "v"):
                getattr(primary, name)[first:end] = getattr(static_hits, name)[first:end]
            g.accel.intersect_range(camera_o, primary_dirs, first, end, R, T, primary, static_done=True, packets=self.packets[0])
        last_depth = self.max_bounces + (1 if self.mis_last else 0)
        traced_shadow = traced_next = 0
        depth, rays = 0, 0  # which of the two ray buffers this depth's continuation rays go to
        while True:
            if depth == 0:  # the first vertex: its surface (unless kept), then this pass's samples
                if not surface_ready:
                    kernels.first_surface(first, end, primary_dirs, prim, scn, w.surf, gb, self.split)
                n_shadow, n_next = kernels.sample_first(first, end, key, w.surf, w.ray_o[rays], w.ray_d[rays], scn, films, work,
                                                        self.max_bounces > 0 or self.mis_last, self.split, kernels.block_scratch())
            else:
                n_shadow, n_next = kernels.shade(depth, self.max_bounces, self.mis_last, key, first, count, w.ray_d[1 - rays],
                                                 w.ray_o[rays], w.ray_d[rays], scn, films, work, self.split)
            if n_shadow:
                g.accel.occluded_range(w.sh_o, w.sh_d, w.sh_tmax, first, first + n_shadow, R, T, w.blocked, packets=self.packets[1])
                kernels.add_unoccluded(first, n_shadow, w.sh_pix, w.sh_c, w.blocked, films[1], films[2], self.split)
                traced_shadow += n_shadow
            if depth >= last_depth or n_next == 0:
                return traced_shadow, traced_next
            g.accel.intersect_range(w.ray_o[rays], w.ray_d[rays], first, first + n_next, R, T, w.hits, packets=self.packets[0])
            traced_next += n_next
            rays, count = 1 - rays, n_next
            depth += 1
            if depth > 4096:
                raise RenderError("path depth exceeded 4096: Russian roulette failed to terminate")

    def _work_buffers(self, n: int, min_segments: int = 1) -> "_Work":
        """The working arrays for n paths in at least `min_segments` segments (of ≥ 64 paths);
        the two last sizes are kept (`render_pixels` has its own, `_pixel_work`)."""
        for w in self._work:
            if w.n == n and w.min_segments == min_segments:
                self._work = [w] + [x for x in self._work if x is not w]
                return w
        w = _Work(n, min_segments)
        self._work = [w] + self._work[:1]
        return w


class _Work:
    """Per-path working arrays, kept between frames (fresh multi-MB arrays cost page faults every
    frame). Segment s owns rows [starts[s], starts[s] + full_counts[s]) of every array."""

    def __init__(self, n: int, min_segments: int = 1):
        self.n, self.min_segments = n, min_segments
        self.starts, self.full_counts = _segments(n, min_segments)
        self.pixel = np.empty(n, np.int32)
        self.beta = np.empty((n, 3), f32)
        self.kd = np.empty((n, 3), f32)
        self.prev_pdf = np.empty(n, f32)
        self.prev_env = np.empty(n, f32)  # environment-light pdf of the path's ray (MIS)
        self.ray_o = (np.empty((n, 3), f32), np.empty((n, 3), f32))  # ping-pong: a kernel reads one, writes the other
        self.ray_d = (np.empty((n, 3), f32), np.empty((n, 3), f32))
        self.hits = empty_hits(n)
        self.cam_d = np.empty((n, 3), f32)  # jittered camera rays of the current pass
        self.primary = empty_hits(n)  # camera hits, when objects move (the static ones are cached)
        # the first vertices' surfaces (kernels.first_surface), a column per quantity. Padded: at
        # 1024×768 columns n floats apart would all fall in the same cache set (n · 4 bytes is a
        # multiple of 4 KiB), and writing or reading 24 of them at once ran 10× slower
        self.surf = np.zeros((kernels.SURF_COLS, n + 16), f32)  # zeros: a lane that reflects nothing reads finite values
        self.sh_o = np.empty((n, 3), f32)
        self.sh_d = np.empty((n, 3), f32)
        self.sh_tmax = np.empty(n, f32)
        self.sh_c = np.empty((n, 6), f32)
        self.sh_pix = np.empty(n, np.int32)
        self.blocked = np.empty(n, np.bool_)

    def prefix(self, n: int) -> "_Work":
        """The first n rows of every array (views), segmented for n paths (`render_pixels`)."""
        w = object.__new__(_Work)
        for k, a in vars(self).items():
            if k == "surf":  # (columns, paths): kept whole (C-contiguous); rows ≥ n are not read
                pass
            elif isinstance(a, np.ndarray):
                a = a[:n]
            elif isinstance(a, tuple):
                a = tuple(x[:n] for x in a)
            elif isinstance(a, Hits):
                a = Hits(a.t[:n], a.obj[:n], a.prim[:n], a.u[:n], a.v[:n])
            setattr(w, k, a)
        w.n = n
        w.starts, w.full_counts = _segments(n, self.min_segments)
        return w


def _segments(n: int, min_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """First row and row count of each segment of n paths (at least `min_segments` of ≥ 64 paths)."""
    segments = min(MAX_SEGMENTS, max(1, min(min_segments, n // 64), -(-n // SEGMENT_PIXELS)))
    size = -(-n // segments)
    starts = np.minimum(np.arange(segments, dtype=np.int64) * size, n)
    return starts, np.minimum(starts + size, n) - starts


class _GBuffer:
    """A frame's G-buffer arrays, allocated empty: the render segments write every row
    (kernels.first_surface)."""

    def __init__(self, npix: int):
        self.id = np.empty(npix, np.int32)
        self.model, self.pos, self.normal, self.alb, self.spec = (np.empty((npix, 3), f32) for _ in range(5))
        self.depth = np.empty(npix, f32)
        self.rough = np.empty(npix, f32)


_NO_GBUFFER = _GBuffer(0)  # render_pixels writes no G-buffer: the kernels take empty arrays of the right types
_NO_TRI = np.zeros(0, np.int32)  # trace_segment: no rasterised triangles (its camera hits are traced)
