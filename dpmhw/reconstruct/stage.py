"""The loop's image-space stage: shading-resolution frame → native uint8 projector frame.

    render (shading res) → temporal reuse (shading res) → cross-bilateral filter (shading res)
    → joint bilateral upsampling + re-modulation (native, lit region only)
    → adaptive sampling (native paths where the upsampling lacks support, optional) → sRGB (lit region only)

Two paths, chosen per frame from the live settings:

- *exact*: shading size = native size and filter ``off``: reuse of the radiance and
  `postprocess.encode_srgb8` over the whole frame, bit-identical to the pipeline before
  reconstruction existed (`TemporalReuse.update` → `to_srgb8`).
- *reconstruct*: diffuse and specular light are demodulated (divided by the shading G-buffer's
  albedos), each gets its own temporal history (same ids and motion, so the same resets), the
  filter runs on them (``off`` / ``normal`` / ``lobe``), then `upsample.upsample` re-modulates
  them with the native albedos inside the native G-buffer's lit box. The directly seen emission
  (radiance − diffuse − specular; exact at one sample through the pixel centre) needs no reuse.
  With `analytic` (the session's default) the albedos are multiplied by analytic direct-lighting
  terms plus a floor at both resolutions (`reconstruct.analytic`): the ratio is reused, filtered
  and upsampled, the native terms put back the detail of the native normals.

Why the history lives at the shading resolution: it costs (w·h) instead of (W·H) per frame
(16× less at scale ¼; measured in docs/temporal-reuse.md), and the native G-buffer of a moving
object is re-traced each frame anyway, so a native history would need a native reprojection of
every lit pixel as well. The price: reuse sees the shading resolution's edges (the upsampler
fixes them per frame against the native G-buffer).

Pixels outside the lit box show the background, encoded once (`base` frame): the frame copy
is the only full-frame work.

Overlap: the shading-resolution branch (guides, demodulation, reuse, filter) does not read the
native G-buffer, so it runs on a helper thread while this one brings the native G-buffer up
to date (every kernel of both releases the GIL; the helper runs its kernels on one thread). The
native G-buffer's work is mostly serial steps and small parallel ones that leave the second core
idle; the branch fills it. The sub-stage timings are each branch's own wall time (`gbuffer`
overlaps `reuse` + `filter`), so they no longer add up to the frame time.

Early G-buffer (`apply(next_frame=…)`, the loop's pipelining): once this frame's native guides
and analytic products are derived, nothing of this frame reads the G-buffer again, so it is
brought to the next frame on a thread of its own, as soon as that frame's render is done,
beside this frame's upsampling, adaptive sampling and encoding. The next `apply` then finds it
done: the loop thread's serial path loses the G-buffer update, its largest step.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from dpmhw.postprocess import encode_srgb8
from dpmhw.reconstruct.analytic import DEFAULT_FLOORS, AnalyticDirect, emitter_polygons, floor_from
from dpmhw.reconstruct.filter import cross_bilateral, mode_code
from dpmhw.reconstruct.guides import Guides
from dpmhw.reconstruct.reuse import ReuseSettings, TemporalReuse
from dpmhw.reconstruct.upsample import upsample
from dpmhw.stage_runner import Stage, run_timed

__all__ = ["ReconstructStage", "StageOutput"]


@dataclass
class _Ahead:
    frame: Future  # the next frame's render
    update: Future  # the G-buffer update for it: (lit box, seconds)


@dataclass
class _Work:
    """One `apply`: its inputs, its sub-stages' seconds and what its stages made."""

    frame: Any
    mode: str
    alpha: float
    filter: str
    exposure: float
    poses: Any
    camera: Any
    st: dict = field(default_factory=dict)  # seconds per sub-stage
    box: tuple[int, int, int, int] = (0, 0, 0, 0)  # the lit box
    radiance: np.ndarray | None = None  # the exact path's reused radiance
    d: np.ndarray | None = None  # the shading branch's diffuse and specular (reused, filtered) and emitted light
    s: np.ndarray | None = None
    emitted: np.ndarray | None = None
    image: Any = None  # the output frame, or the future of its background copy


@dataclass
class StageOutput:
    image: np.ndarray  # (H, W, 3) uint8, native
    stages_s: dict  # seconds per sub-stage: gbuffer, reuse, filter, upsample, [adaptive,] post
    lit_box: tuple[int, int, int, int]
    unresolved: int  # native pixels no shading sample supports (see upsample)
    background: np.ndarray | None = None  # the frame `image` equals outside `lit_box` (the same object while the exposure stays)


def _one_kernel_thread() -> None:
    """The helper runs its (small, shading-resolution) kernels on itself alone: a second team of
    kernel threads would only compete for the two cores with the native G-buffer's."""
    import numba

    numba.set_num_threads(1)


class ReconstructStage:
    """One per session.

    native_size, shading_size : (W, H) and (w, h)
    background : the scene's background colour (linear): what pixels without a hit show
    viewer : the eye position (lobe axes are reflections of the direction to it)
    gbuffer : a `render.gbuffer.NativeGBuffer` (needed when the sizes differ; at equal sizes the
        shading frame's own G-buffer is the native one)
    gbuffer_mode : "edges" (trace only near the shading frame's discontinuities), "trace"
        (every pixel of the moving objects' region) or "raster"; see `render.gbuffer`
    clock : monotonic nanoseconds, for the sub-stage timings
    adaptive : a `reconstruct.adaptive.AdaptiveSampler` (None: no adaptive sampling): extra
        native paths for unresolved and under-supported pixels, merged before post
    lod : a `lod.refine.TileRefiner` (None: off, and the stage is exactly what it is without
        it): per-tile native paths where the previous output is visible (docs/lod.md); planned
        before the upsampling, traced and blended after it, before adaptive sampling;
        its time is the sub-stage "lod"
    analytic : the (diffuse, specular) floor fractions of the analytic-direct demodulation
        (`reconstruct.analytic`; None: off, and the stage is exactly what it is without it): the
        diffuse light is divided by albedo·(E + F_d) and the specular by spec_albedo·(S + F_s) at
        the shading resolution, and re-multiplied by the native products. Needs the native
        G-buffer (its geometry gives the emitters); at equal sizes it is off
    """

    def __init__(self, native_size, shading_size, *, background=(0.0, 0.0, 0.0), viewer=(0.0, 0.0, 0.0),
                 warmup: bool = False, gbuffer=None, gbuffer_mode: str = "edges", clock=time.monotonic_ns,
                 adaptive=None, lod=None, analytic: tuple[float, float] | None = DEFAULT_FLOORS):
        self.W, self.H = (int(v) for v in native_size)
        self.w, self.h = (int(v) for v in shading_size)
        if (self.w, self.h) != (self.W, self.H) and gbuffer is None:
            raise ValueError("ReconstructStage: shading size differs from the native size but no native G-buffer was given")
        self.gbuffer = gbuffer
        self.adaptive = adaptive if gbuffer is not None else None
        self.lod = lod if gbuffer is not None else None  # per-tile refinement (lod.refine)
        self.clock = clock  # ns; the loop's injectable clock
        self.gbuffer_mode = gbuffer_mode
        self.background = np.asarray(background, np.float32).reshape(3)
        self.viewer = np.asarray(viewer, np.float32).reshape(3)
        self.warmup = warmup
        self.reuse = TemporalReuse(self.w, self.h, alpha=0.2, mode="same-pixel", warmup=warmup)
        self.reuse_d = TemporalReuse(self.w, self.h, alpha=0.2, mode="same-pixel", warmup=warmup)
        self.reuse_s = TemporalReuse(self.w, self.h, alpha=0.2, mode="same-pixel", warmup=warmup)
        self.low = Guides.empty(self.w, self.h)
        self.native = Guides.empty(self.W, self.H) if gbuffer is not None else self.low
        n = self.W * self.H
        self._radiance = np.zeros((n, 3), np.float32)
        self._wsum = np.zeros(n, np.float32)
        self._unresolved = np.zeros(n, np.bool_)
        self._base: tuple[float, np.ndarray] | None = None
        self._native_roi = "none yet"  # the moving objects' box this stage's native guides last followed
        self._gbuffer_updates = -1  # the native G-buffer's update count this stage's guides last followed
        self._exact: bool | None = None  # which path the last frame took
        self._helper: ThreadPoolExecutor | None = None  # runs the shading-resolution branch (see module doc)
        self._ahead_thread: ThreadPoolExecutor | None = None  # brings the native G-buffer to the next frame early
        self._ahead: _Ahead | None = None  # that update, while it runs or until the frame it was for arrives
        self.analytic = None  # (low, native) `AnalyticDirect` products when on
        if analytic is not None and gbuffer is not None:
            fractions = tuple(float(f) for f in analytic)
            if len(fractions) != 2 or not all(math.isfinite(f) and f > 0 for f in fractions):
                raise ValueError(f"analytic: expected two finite floor fractions > 0 (diffuse, specular), got {analytic!r}")
            self._analytic_fractions = fractions
            scene = gbuffer.scene
            self._dynamic_lights = any(o.is_emissive and o.is_dynamic for o in scene.objects)
            poly, lum = emitter_polygons(gbuffer.geometry, scene.object_poses(0.0))
            self.analytic = (AnalyticDirect(self.w, self.h, poly, lum, self.viewer),
                             AnalyticDirect(self.W, self.H, poly, lum, self.viewer))

    def close(self) -> None:
        self._drop_ahead()
        for pool in (self._helper, self._ahead_thread):
            if pool is not None:
                pool.shutdown(wait=True)
        self._helper = self._ahead_thread = None

    def set_budgets(self, adaptive_rays: int, lod_rays: int) -> None:
        """The live ray budgets of adaptive sampling and tile refinement (each only where that
        sampler exists: a refiner off at start stays off)."""
        if self.adaptive is not None:
            self.adaptive.budget_rays = int(adaptive_rays)
        if self.lod is not None:
            self.lod.set_rays(lod_rays)

    def reset(self) -> None:
        for r in (self.reuse, self.reuse_d, self.reuse_s):
            r.reset()
        if self.adaptive is not None:
            self.adaptive.reset()
        if self.lod is not None:
            self.lod.reset()

    def _settings(self, mode: str, alpha: float, split_screen: bool) -> None:
        wanted = ReuseSettings(alpha, mode, self.warmup, split_screen)
        for r in (self.reuse, self.reuse_d, self.reuse_s):
            if wanted != r.settings:
                if wanted.mode != r.settings.mode:
                    r.reset()
                r.settings = wanted

    def base_frame(self, exposure: float) -> np.ndarray:
        """(W*H, 3) uint8 background everywhere, encoded once per exposure."""
        if self._base is None or self._base[0] != exposure:
            bg = np.broadcast_to(self.background, (self.W * self.H, 3)).copy()
            self._base = (exposure, encode_srgb8(bg, self.W, exposure))
        return self._base[1]

    def _update_gbuffer(self, poses, frame) -> tuple[tuple[int, int, int, int], float]:
        """The native G-buffer brought to `poses` (moving objects' region re-traced): (lit box, seconds)."""
        t0 = self.clock()
        box = self.gbuffer.update(poses if poses is not None else [], shading=frame, mode=self.gbuffer_mode)
        return box, (self.clock() - t0) / 1e9

    def _update_native(self, box) -> None:
        """This stage's native guides (and analytic products) from the G-buffer's last update."""
        from dpmhw.render.gbuffer import box_minus  # loaded already (the G-buffer's module); kept out of
        # this module's imports so that importers of the stage (the API process) skip numba/Embree

        g = self.gbuffer
        # this stage's native guides: everything once, then the current region and the rest of its last
        if self._native_roi == "none yet":
            dirty = [(0, self.H, 0, self.W)]
        elif self._native_roi is None:
            dirty = [g.roi_box]
        else:  # the current region, and what of the last one lies outside it (each pixel once)
            dirty = [g.roi_box] + box_minus(self._native_roi, g.roi_box)
        # inside the current region only the pixels the G-buffer changed (most of it is background
        # that stays background), if this stage saw the update before (another user of the same
        # G-buffer, e.g. a benchmark's other stage, may have changed pixels since); the rest in full
        masked = self._native_roi != "none yet" and self._gbuffer_updates == g.updates - 1
        self._gbuffer_updates = g.updates
        self._native_roi = g.roi_box
        for k, b in enumerate(dirty):
            if b is not None and b[1] > b[0] and b[3] > b[2]:
                mask = g.changed if k == 0 and masked else None
                self.native.update(g.id, g.position, g.normal, g.depth, g.albedo, g.spec_albedo, g.roughness,
                                   self.viewer, b, mask)
                if self.analytic is not None:
                    self.analytic[1].update(g.id, g.position, g.normal, g.roughness, self.native.albedo,
                                            self.native.spec_albedo, b, mask)

    # ---- the next frame's G-buffer, early (pipelining) ---------------------------------------------
    def _start_ahead(self, next_frame) -> None:
        """Bring the G-buffer to the next frame on its own thread as soon as that frame's render is
        done, while this frame is upsampled, sampled and encoded. Safe because from here on this
        frame reads only what `_update_native` derived from the G-buffer (the native guides and
        analytic products; adaptive sampling takes the guides' ids), never the G-buffer itself."""
        poses, frame_future = next_frame
        if self._ahead_thread is None:
            self._ahead_thread = ThreadPoolExecutor(1, thread_name_prefix="gbuffer-ahead")

        def run():
            return self._update_gbuffer(poses, frame_future.result())

        self._ahead = _Ahead(frame_future, self._ahead_thread.submit(run))

    def _take_ahead(self, frame):
        """(box, seconds) of the early update if it was for `frame`; else None, once any early
        update has finished (it must not run beside this frame's own)."""
        ahead, self._ahead = self._ahead, None
        if ahead is None:
            return None
        try:
            for_this = ahead.frame.done() and ahead.frame.exception() is None and ahead.frame.result() is frame
        except CancelledError:
            for_this = False
        if for_this:
            return ahead.update.result()  # its own failure is this frame's
        try:
            ahead.update.result()
        except Exception:
            pass  # for a frame that was dropped: its fault, if any, shows again with the frame's own update
        return None

    def _drop_ahead(self) -> None:
        self._take_ahead(None)

    # ---- the stages (each a function of one `apply`'s `_Work`) -------------------------------------
    def _reuse_radiance(self, w: _Work) -> None:
        w.radiance = self.reuse.update_frame(w.frame, poses=w.poses, camera=w.camera)

    def _encode_frame(self, w: _Work) -> None:
        w.image = encode_srgb8(np.ascontiguousarray(w.radiance.reshape(-1, 3)), self.W, w.exposure)

    def _demodulate_and_reuse(self, w: _Work) -> None:
        """Shading-resolution guides, demodulation and reuse (reads nothing native)."""
        frame = w.frame
        low = self.low
        low.update(frame.object_id, frame.position, frame.normal, frame.depth, frame.albedo, frame.specular_albedo,
                   frame.roughness, self.viewer, (0, self.h, 0, self.w))
        diffuse = np.asarray(frame.diffuse, np.float32).reshape(-1, 3)
        specular = np.asarray(frame.specular, np.float32).reshape(-1, 3)
        w.emitted = np.asarray(frame.radiance, np.float32).reshape(-1, 3) - diffuse - specular
        if self.analytic is not None:  # the ratios to the analytic terms (+ floors)
            an = self.analytic[0]
            an.update(frame.object_id, frame.position, frame.normal, frame.roughness, low.albedo, low.spec_albedo,
                      (0, self.h, 0, self.w))
            d_in = (diffuse / an.diffuse_products).reshape(self.h, self.w, 3)
            s_in = (specular / an.specular_products).reshape(self.h, self.w, 3)
        else:
            d_in = (diffuse / low.albedo).reshape(self.h, self.w, 3)
            s_in = (specular / low.spec_albedo).reshape(self.h, self.w, 3)
        # both histories move in lockstep: one reprojection serves both
        shared = self.reuse_d.settings.mode == "motion" and self.reuse_s.follows_same_frames(self.reuse_d)
        rp = self.reuse_d.reprojection(frame.object_id, frame.model_position, w.camera) if shared else None
        w.d = self.reuse_d.update(d_in, frame.object_id, frame.model_position, w.poses, w.camera, rp)
        w.s = self.reuse_s.update(s_in, frame.object_id, frame.model_position, w.poses, w.camera, rp)

    def _filter(self, w: _Work) -> None:
        w.d, w.s, _ = cross_bilateral(w.d, w.s, self.low, w.filter)

    def _gbuffer_at_frame(self, w: _Work) -> None:
        """The native G-buffer at this frame: brought there beside the last frame, or now; its
        seconds are the update's own (on whichever thread it ran)."""
        early = self._take_ahead(w.frame)
        w.box, w.st["gbuffer"] = early if early is not None else self._update_gbuffer(w.poses, w.frame)

    def _upsample(self, w: _Work) -> None:
        native = self.native if self.analytic is None else replace(
            self.native, albedo=self.analytic[1].diffuse_products, spec_albedo=self.analytic[1].specular_products)
        upsample(self.low, w.d, w.s, w.emitted, native, w.filter, w.box, self.background, self._radiance, self._wsum,
                 self._unresolved)

    def _refine_tiles(self, w: _Work) -> None:
        """Native paths in the tiles planned before the upsampling."""
        self.lod.refine(self._radiance, self._wsum, self._unresolved, w.box, w.poses if w.poses is not None else [],
                        w.frame.seed, 1.0 if w.mode == "off" else w.alpha)

    def _sample_adaptively(self, w: _Work) -> None:
        self.adaptive.refine(self._radiance, self._wsum, self._unresolved, w.box, w.poses if w.poses is not None else [],
                             w.frame.seed, 1.0 if w.mode == "off" else w.alpha, self.native.id)

    def _encode_lit_box(self, w: _Work) -> None:
        """The background frame (copied on the helper thread, or now) with the lit box encoded into it."""
        w.image = self._background_copy(w.exposure) if w.image is None else w.image.result()
        y0, y1, x0, x1 = w.box
        if y1 > y0 and x1 > x0:
            encode_srgb8(self._radiance, self.W, w.exposure, w.box, w.image)

    def _analytic_setup(self, frame, poses) -> None:
        """The floors from the first frame's terms; moving emitters: new polygons, every native pixel again."""
        low, nat = self.analytic
        if self._dynamic_lights and poses is not None:
            poly, lum = emitter_polygons(self.gbuffer.geometry, poses)
            if poly.shape != low.poly.shape or not np.array_equal(poly, low.poly):
                for a in (low, nat):
                    a.poly, a.lum = poly, lum
                self._native_roi = "none yet"  # every native pixel again (guides and products)
        if low.floors is None:
            low.set_floors(1.0, 1.0)
            low.update(frame.object_id, frame.position, frame.normal, frame.roughness, frame.albedo,
                       frame.specular_albedo, (0, self.h, 0, self.w))  # this frame's (the guides are not updated yet)
            fd, fs = self._analytic_fractions
            floors = (floor_from(low.irradiance, frame.object_id, fd), floor_from(low.specular, frame.object_id, fs))
            low.set_floors(*floors)
            nat.set_floors(*floors)
            self._native_roi = "none yet"

    def _background_copy(self, exposure: float) -> np.ndarray:
        return self.base_frame(exposure).copy()

    def apply(self, frame, *, mode: str, alpha: float, filter: str = "lobe", split_screen: bool = False,
              exposure: float = 1.0, poses=None, camera=None, next_frame=None) -> StageOutput:
        """Reconstruct one native frame from a shading-resolution renderer `Frame`.

        next_frame : (poses, future of its `Frame`) of the frame that will follow, when the caller
            already renders it (the loop's pipelining): the native G-buffer is then brought to it
            beside this frame's upsampling, and the next call finds it done. Only without tile
            refinement, which reads the G-buffer after the upsampling."""
        code = mode_code(filter)
        if frame.shape != (self.h, self.w):
            raise ValueError(f"frame: expected the shading size {self.w}×{self.h}, got {frame.shape[1]}×{frame.shape[0]}")
        self._settings(mode, alpha, split_screen)
        exact = code == 0 and (self.w, self.h) == (self.W, self.H)
        if self._exact is not None and exact != self._exact:
            self.reset()  # the other path's history stopped being updated: it shows another moment
        self._exact = exact
        w = _Work(frame, mode, alpha, filter, exposure, poses, camera)
        if exact:
            w.st = dict.fromkeys(("gbuffer", "reuse", "filter", "upsample"), 0.0)
            run_timed((Stage("reuse", self._reuse_radiance), Stage("post", self._encode_frame)), w, self.clock, w.st)
            return StageOutput(w.image.reshape(self.H, self.W, 3), w.st, (0, self.H, 0, self.W), 0)

        if self.analytic is not None:
            self._analytic_setup(frame, poses)
        shading = (Stage("reuse", self._demodulate_and_reuse), Stage("filter", self._filter))
        if self.gbuffer is not None:
            # the shading-resolution branch on the helper thread while the native G-buffer updates here
            if self._helper is None:
                self._helper = ThreadPoolExecutor(1, thread_name_prefix="reconstruct", initializer=_one_kernel_thread)
            st_low: dict[str, float] = {}
            branch = self._helper.submit(run_timed, shading, w, self.clock, st_low)
            w.image = self._helper.submit(self._background_copy, exposure)  # the frame to draw into, after the branch
            try:
                run_timed((Stage("gbuffer", self._gbuffer_at_frame, timed=False),
                           Stage("gbuffer", lambda w: self._update_native(w.box)),
                           Stage("ahead", lambda w: self._start_ahead(next_frame), timed=False)
                           if next_frame is not None and self.lod is None else None), w, self.clock, w.st)
            finally:
                branch.result()  # never leave the branch running into the next frame
            w.st.update(st_low)
        else:
            w.box = (0, self.H, 0, self.W)
            w.st["gbuffer"] = 0.0
            run_timed(shading, w, self.clock, w.st)
        if self.adaptive is None:
            w.st["adaptive"] = 0.0
        lod = self.lod is not None
        # tile refinement plans from the last output before the upsampling overwrites it
        run_timed((Stage("lod", lambda w: self.lod.plan(self._radiance, w.box)) if lod else None,
                   Stage("upsample", self._upsample),
                   Stage("lod", self._refine_tiles) if lod else None,
                   Stage("adaptive", self._sample_adaptively) if self.adaptive is not None else None,
                   Stage("post", self._encode_lit_box)), w, self.clock, w.st)
        y0, y1, x0, x1 = w.box
        unresolved = int(self._unresolved.reshape(self.H, self.W)[y0:y1, x0:x1].sum())
        return StageOutput(w.image.reshape(self.H, self.W, 3), w.st, w.box, unresolved, self.base_frame(w.exposure))
