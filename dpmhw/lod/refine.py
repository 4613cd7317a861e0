"""Per-tile shading rate and samples per pixel inside the loop's reconstruction (docs/lod.md).

The loop shades a ¼-per-axis frame everywhere, reuses, filters and upsamples it to the native
size (`reconstruct.stage`). That base is the cheapest level; on top of it `TileRefiner` spends a
per-frame ray budget on native-resolution paths where a viewer can see the difference:

1. **Plan** (before the upsampling): with `visible`, the visibility map of the *previous
   output* (the reused, filtered, upsampled and refined native radiance, so most 1-spp noise
   is averaged away, and the map's noise floor takes the rest; `visibility.py`) over the lit
   box, with the native G-buffer's depth. It is made at the end of the previous `refine`
   (`output_map`; before the adaptive sampler's few pixels), so the mesh levels can use the same
   map (`MeshLod.observe(visibility=…)`): one map per frame for all three uses. With `moving`,
   tiles a moving object covers now are boosted (full rate, budget first; samples per pixel
   still from the map's level there) and only the moving objects' own pixels are traced in
   them (their shading changes under the eye, and the ¼ base loses their detail: the
   inside-object PSNR). `TilePolicy` turns V into a level per tile under the budget (¼-rate
   tiles are free: the base shades them), the most visible tiles first, the last frame's
   grants counting `keep` more (the base shades every tile anyway, and a tile refined in
   turns would lose its native history between them).
2. **Refine** (after the upsampling): every lit pixel of a full-rate tile, and one pixel of
   each 2×2 block of a ½-rate tile (the block's phase cycles over four frames), gets `spp`
   native paths (`PathIntegrator.render_pixels`, one call per spp group, the native camera and
   cached static hits). Each refined pixel keeps a native history, reprojected through the
   object's motion like `reuse` mode "motion" (bilinear over the taps that showed the same
   object in the last frame, else the nearest, else none):

       traced, history:       L = a·x + (1 − a)·h,    a = 1 − (1 − α)^spp
       traced, no history:    L = a·x + (1 − a)·L_up  (the upsampled base seeds the history)
       not traced, history:   L = h                   (½ rate, between its turns)
       not traced, none:      L = L_up

   With `moving_every` = 2 or 4, boosted tiles trace each moving pixel every 2 frames (an
   alternating checkerboard) or 4 (each 2×2 block in turn); an untraced pixel there takes the
   mean of this frame's paths at its same-object 3×3 neighbours as its sample x (`_fill`;
   1/every of the paths, and every pixel still gets fresh light each frame: holding L = h
   instead lagged the moving shading, docs/lod.md).

   The output is (1 − `base_weight`)·L + `base_weight`·L_up: the base is filtered and L is
   not, so a share of it lowers the noise (0.3 measured best of 0 / 0.3 / 0.5, docs/lod.md).
   A non-finite path sample counts as not traced. Refined pixels are marked resolved (the
   adaptive sampler then skips them). Tiles at ¼ (and "history only", which in this pipeline
   is the base's own reuse) keep L_up, and their native history lapses.

Ray budget: `policy.allocate` grants samples while Σ spp · shaded pixels · rays_per_path ≤
`rays` (rays_per_path = `rays_per_sample_bound`, the most rays a path can trace), and the
pixels traced per tile are within `shaded_counts` (boosted tiles: within one phase of the
`moving_every` pattern), so the rays traced never exceed the budget.

Everything per pixel is a numba kernel over the refined tiles only; per-tile bookkeeping is
numpy over a (48 × 64)-tile grid.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numba as nb
import numpy as np

from dpmhw.lod.policy import PolicySettings, TileDecisions, TilePolicy, rays_per_sample_bound, shaded_counts
from dpmhw.lod.visibility import LodSettingsError, VisibilityMap, VisibilitySettings, check_number, visibility_map
from dpmhw.reconstruct.reuse import reproject


@dataclass(frozen=True)
class RefineSettings:
    """What the session config's `lod` section sets (`session/config.py`)."""

    rays: int = 0  # per-frame budget of native rays; 0: off
    moving: bool = True  # tiles a moving object covers get its pixels at full rate (highest priority)
    visible: bool = False  # tiles refined by the visibility map of the previous output (else no map is computed)
    shading_rate: bool = True  # visible tiles: levels → ¼ (free) / ½ / full rate; off: every level ≥ 1 at full rate
    adaptive_spp: bool = False  # visible tiles: levels → 1 / 2 / 4 spp; off: 1 spp
    viewer_distance_m: float = 1.5
    alpha_v: float = 0.0
    thresholds: tuple[float, float, float] = (0.0, 20.0, 50.0)
    base_weight: float = 0.3  # share of the upsampled base in a refined pixel's output (its history stays native)
    moving_every: int = 2  # a moving object's pixel is traced every 1, 2 or 4 frames
    keep: float = 20.0  # under a tight budget the most visible tiles first, last frame's grants counting this much more

    def __post_init__(self):
        object.__setattr__(self, "rays", check_number("rays", self.rays, 0, 1 << 40, integer=True))
        object.__setattr__(self, "base_weight", check_number("base_weight", self.base_weight, 0.0, 1.0))
        if self.moving_every not in (1, 2, 4):
            raise LodSettingsError(f"moving_every: expected 1, 2 or 4, got {self.moving_every!r}")


    @property
    def enabled(self) -> bool:
        return self.rays > 0 and (self.moving or self.visible)


@nb.njit(cache=True, nogil=True)
def _select(rate, spp, moving_only, gid, dynamic, W, y0, y1, x0, x1, tile, phase, frame, every):
    """Lit pixels of the box in tiles of rate 1 or 2 (only the moving objects' pixels where
    `moving_only`), in row-major order: flat index, spp if traced this frame (0: a pixel between
    its turns: `_fill` may give it its neighbours' paths, else it keeps its history). Rate-2 pixels are traced when (y, x) ≡ phase mod 2.
    Full-rate pixels of `moving_only` tiles are traced every `every` frames (1, 2: a
    checkerboard alternating per frame, 4: each 2×2 block's four pixels in turn), so a moving
    object costs 1/every of its paths. Visits only the refined tiles' pixels."""
    n = 0
    pix = np.empty((y1 - y0) * (x1 - x0), np.int64)
    s = np.empty((y1 - y0) * (x1 - x0), np.uint8)
    py, px = phase // 2, phase % 2
    for y in range(y0, y1):
        ty = y // tile
        for tx in range(x0 // tile, (x1 - 1) // tile + 1):
            r = rate[ty, tx]
            if r != 1 and r != 2:
                continue
            only = moving_only[ty, tx]
            for x in range(max(x0, tx * tile), min(x1, tx * tile + tile)):
                i = y * W + x
                if gid[i] < 0 or (only and not dynamic[gid[i]]):
                    continue
                pix[n] = i
                if r == 2:
                    on = y % 2 == py and x % 2 == px
                elif only and every == 2:
                    on = (x + y + frame) % 2 == 0
                elif only and every == 4:
                    on = (2 * ((x + y) % 2) + y % 2 + frame) % 4 == 0
                else:
                    on = True
                s[n] = spp[ty, tx] if on else 0
                n += 1
    return pix[:n], s[:n]


@nb.njit(cache=True, nogil=True)
def _fill(pixels, spp, samples, moving_only, tile, gid, normal, W, H, stamp, fresh, frame):
    """Untraced pixels of `moving_only` tiles (moving_every > 1) take the mean of this frame's
    samples at their 3×3 neighbours that show the same object with a normal within ~25°, and
    count as traced at 1 spp: every pixel of a moving object gets fresh light every frame (at
    the density of the traced ones) instead of holding its reprojected history, which lags
    and blurs (measured). A pixel with no such neighbour keeps its history."""
    for k in range(pixels.shape[0]):
        if spp[k] > 0 and np.isfinite(samples[k, 0]) and np.isfinite(samples[k, 1]) and np.isfinite(samples[k, 2]):
            i = pixels[k]
            fresh[i, 0], fresh[i, 1], fresh[i, 2] = samples[k, 0], samples[k, 1], samples[k, 2]
            stamp[i] = frame
    for k in range(pixels.shape[0]):
        if spp[k] != 0:
            continue
        i = pixels[k]
        y, x = i // W, i % W
        if not moving_only[y // tile, x // tile]:
            continue
        o = gid[i]
        s0 = s1 = s2 = 0.0
        m = 0
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                yy, xx = y + dy, x + dx
                if yy < 0 or xx < 0 or yy >= H or xx >= W:
                    continue
                j = yy * W + xx
                if stamp[j] != frame or gid[j] != o:
                    continue
                if normal[i, 0] * normal[j, 0] + normal[i, 1] * normal[j, 1] + normal[i, 2] * normal[j, 2] < 0.9:
                    continue
                s0 += fresh[j, 0]
                s1 += fresh[j, 1]
                s2 += fresh[j, 2]
                m += 1
        if m > 0:
            samples[k, 0], samples[k, 1], samples[k, 2] = s0 / m, s1 / m, s2 / m
            spp[k] = 1


@nb.njit(cache=True, nogil=True)
def _fetch(pixels, gid, xy, ok, W, H, h_rad, h_id, h_frame, frame, out, valid):
    """Reprojected native history of `pixels` from the last frame's refined pixels (bilinear
    over the matching taps, renormalised; else the nearest matching tap; else invalid)."""
    for k in range(pixels.shape[0]):
        valid[k] = False
        if not ok[k]:
            continue
        x, y = xy[k, 0], xy[k, 1]
        if not (x > -0.5 and x < W - 0.5 and y > -0.5 and y < H - 0.5):
            continue
        o = gid[pixels[k]]
        fx, fy = np.floor(x), np.floor(y)
        ax, ay = x - fx, y - fy
        s0 = s1 = s2 = wsum = 0.0
        best, bestd = -1, 1e30
        for dy in range(2):
            for dx in range(2):
                tx, ty = int(fx) + dx, int(fy) + dy
                if tx < 0 or ty < 0 or tx >= W or ty >= H:
                    continue
                j = ty * W + tx
                if h_frame[j] != frame - 1 or h_id[j] != o:
                    continue
                w = (ax if dx else 1.0 - ax) * (ay if dy else 1.0 - ay)
                s0 += w * h_rad[j, 0]
                s1 += w * h_rad[j, 1]
                s2 += w * h_rad[j, 2]
                wsum += w
                d = (tx - x) ** 2 + (ty - y) ** 2
                if d < bestd:
                    best, bestd = j, d
        if wsum >= 1e-6:
            out[k, 0], out[k, 1], out[k, 2] = s0 / wsum, s1 / wsum, s2 / wsum
            valid[k] = True
        elif best >= 0:
            out[k, 0], out[k, 1], out[k, 2] = h_rad[best, 0], h_rad[best, 1], h_rad[best, 2]
            valid[k] = True


@nb.njit(cache=True, nogil=True)
def _merge(pixels, spp, samples, hist, valid, alpha, base_weight, radiance, wsum, unresolved, gid, h_rad, h_id, h_frame, frame):
    """The blend of the module docstring; writes this frame's history and the output
    (1 − base_weight)·L + base_weight·L_up."""
    for k in range(pixels.shape[0]):
        i = pixels[k]
        s = spp[k]
        traced = s > 0 and np.isfinite(samples[k, 0]) and np.isfinite(samples[k, 1]) and np.isfinite(samples[k, 2])
        if not traced and not valid[k]:
            continue  # L_up stays, no history starts here
        a = 1.0 - (1.0 - alpha) ** s if traced else 0.0
        for c in range(3):
            up = radiance[i, c]
            prior = hist[k, c] if valid[k] else up
            est = a * samples[k, c] + (1.0 - a) * prior if traced else prior
            h_rad[i, c] = est
            radiance[i, c] = (1.0 - base_weight) * est + base_weight * up
        h_id[i], h_frame[i] = gid[i], frame
        unresolved[i] = False
        wsum[i] = np.inf  # resolved: the adaptive sampler leaves it alone


@nb.njit(cache=True, nogil=True)
def _lit_per_tile(gid, W, y0, y1, x0, x1, tile, out):
    """out[ty, tx] = pixels of the box showing a surface (the only ones the refiner traces)."""
    out[:] = 0
    for y in range(y0, y1):
        ty, row = y // tile, y * W
        for tx in range(x0 // tile, (x1 - 1) // tile + 1):  # one division per tile, not per pixel
            c = 0
            for x in range(max(x0, tx * tile), min(x1, tx * tile + tile)):
                c += gid[row + x] >= 0
            out[ty, tx] += c


def _tile_any(mask: np.ndarray, tile: int, shape: tuple[int, int], y0: int, x0: int) -> np.ndarray:
    """(TY, TX) bool: tiles holding a True pixel of `mask`, a tile-aligned region starting at (y0, x0)."""
    out = np.zeros(shape, np.bool_)
    h, w = mask.shape
    ph, pw = -(-h // tile) * tile, -(-w // tile) * tile
    padded = np.zeros((ph, pw), np.bool_)
    padded[:h, :w] = mask
    t = padded.reshape(ph // tile, tile, pw // tile, tile).any(axis=(1, 3))
    out[y0 // tile : y0 // tile + t.shape[0], x0 // tile : x0 // tile + t.shape[1]] = t
    return out


class TileRefiner:
    """Native paths per tile for one session. `renderer`: the session's `PathIntegrator` (any
    shading size); `gbuffer`: its `NativeGBuffer` (camera, cached static hits, ids, depth)."""

    def __init__(self, renderer, gbuffer, settings: RefineSettings = RefineSettings(), tile: int = 16):
        if not isinstance(settings, RefineSettings):
            raise LodSettingsError(f"settings: expected RefineSettings, got {type(settings).__name__}")
        self.renderer, self.gbuffer, self.settings = renderer, gbuffer, settings
        self.W, self.H = gbuffer.width, gbuffer.height
        self.visibility = VisibilitySettings(viewer_distance_m=settings.viewer_distance_m, alpha_v=settings.alpha_v, tile=tile)
        self.rays_per_path = rays_per_sample_bound(renderer.max_bounces, renderer.mis_last)
        self.policy = TilePolicy(self.H, self.W, PolicySettings(
            thresholds=settings.thresholds, shading_rate=settings.shading_rate, adaptive_spp=settings.adaptive_spp,
            ray_budget=settings.rays, rays_per_sample=self.rays_per_path, free_rate=4 if settings.shading_rate else 0,
            keep=settings.keep))
        self._dynamic = np.array([o.is_dynamic for o in gbuffer.scene.objects] + [False], np.bool_)  # [-1]: background
        n = self.W * self.H
        self._h = [(np.zeros((n, 3), np.float32), np.full(n, -1, np.int32), np.full(n, -2, np.int64)) for _ in range(2)]
        self._fresh = (np.full(n, -1, np.int64), np.zeros((n, 3), np.float32))  # this frame's samples by pixel (`_fill`)
        self._frame = 0
        self._prev_poses = None
        self._moving_only = np.zeros((-(-self.H // tile), -(-self.W // tile)), np.bool_)
        # most pixels of a tile one frame of the `moving_every` pattern traces (`_select`): a checkerboard
        # colour (every 2) or one pixel of each 2×2 block (every 4), edge tiles included
        full = shaded_counts(np.ones_like(self._moving_only, np.uint8), self.H, self.W, tile)
        self._phase_pixels = {1: full, 2: -(-full // 2),
                              4: shaded_counts(np.full_like(self._moving_only, 2, np.uint8), self.H, self.W, tile)}[settings.moving_every]
        self.decisions: TileDecisions | None = None
        self.vmap: VisibilityMap | None = None  # the map this frame's plan used
        self.output_map: VisibilityMap | None = None  # the map of the last refined output (the next plan's)
        self.last_rays = 0  # rays traced in the last frame (≤ settings.rays)
        self.last_pixels = 0  # paths traced in the last frame (pixels × spp)

    def set_rays(self, rays: int) -> None:
        """A new per-frame ray budget from the next plan on (a live setting; 0 traces nothing)."""
        self.settings = replace(self.settings, rays=rays)
        self.policy.settings = replace(self.policy.settings, ray_budget=self.settings.rays)

    def reset(self) -> None:
        for _, _, f in self._h:
            f[:] = -2
        self._prev_poses = None
        self.output_map = None
        self.policy.reset()

    def plan(self, previous: np.ndarray, box) -> TileDecisions:
        """Decide this frame's tiles from the previous output `previous` ((W*H, 3) linear
        radiance, valid inside the lit box) and the current native G-buffer."""
        g, t = self.gbuffer, self.visibility.tile
        TY, TX = -(-self.H // t), -(-self.W // t)
        if self.output_map is None:  # no map of the last output (first frame, reset): map `previous` now
            self.output_map = self._map(previous, box)
        self.vmap, self.output_map = self.output_map, None
        boost = None
        roi = g.roi_box
        if self.settings.moving and roi is not None and roi[1] > roi[0] and roi[3] > roi[2]:
            ry0, ry1, rx0, rx1 = roi
            ry0, rx0 = (ry0 // t) * t, (rx0 // t) * t
            ids = g.id.reshape(self.H, self.W)[ry0:ry1, rx0:rx1]
            boost = _tile_any(self._dynamic[ids], t, (TY, TX), ry0, rx0)
        lit = np.zeros((TY, TX), np.int64)
        if box[1] > box[0] and box[3] > box[2]:
            _lit_per_tile(g.id, self.W, *(int(v) for v in box), t, lit)
        # tiles a moving object covers: trace only its pixels, each every `moving_every` frames (so a
        # tile there costs at most one phase of that pattern; background pixels cost no budget at all)
        self._moving_only = boost if boost is not None else np.zeros((TY, TX), np.bool_)
        if boost is not None and self.settings.moving_every > 1:
            lit = np.where(boost, np.minimum(lit, self._phase_pixels), lit)
        self.decisions = self.policy.decide(self.vmap, boost, lit)
        return self.decisions

    def _map(self, radiance: np.ndarray, box) -> VisibilityMap:
        """The visibility map of `radiance` ((W*H, 3) linear, valid inside `box`) with the current
        G-buffer's depth; tiles outside the box (nothing lit) and every tile without `visible` at
        the lowest V. Only V is kept (frequency NaN, contrast 0 in the returned map)."""
        g, t = self.gbuffer, self.visibility.tile
        vis = np.full((-(-self.H // t), -(-self.W // t)), self.visibility.bounds[0], np.float32)
        y0, y1, x0, x1 = box
        if self.settings.visible and y1 > y0 and x1 > x0:
            y0, x0 = (y0 // t) * t, (x0 // t) * t  # tile-aligned, so the box's tiles are the map's
            rad = radiance.reshape(self.H, self.W, 3)[y0:y1, x0:x1]
            depth = g.depth.reshape(self.H, self.W)[y0:y1, x0:x1]
            m = visibility_map(rad, depth, g.camera.K, self.visibility)
            vis[y0 // t : y0 // t + m.visibility.shape[0], x0 // t : x0 // t + m.visibility.shape[1]] = m.visibility
        return VisibilityMap(vis, np.full_like(vis, np.nan), np.zeros_like(vis), t)

    def refine(self, radiance, wsum, unresolved, box, poses, seed: int, alpha: float = 1.0) -> int:
        """Trace and blend the planned tiles into `radiance` (W*H, 3) in place (after the
        upsampling); returns the rays traced. With `visible`, then maps the result (this
        frame's output but for the adaptive sampler's few pixels) into `output_map`: the next
        plan's map, and the mesh levels' (`MeshLod.observe(visibility=…)`): one map, three uses."""
        self._refine(radiance, wsum, unresolved, box, poses, seed, alpha)
        if self.settings.visible:
            self.output_map = self._map(radiance, box)
        return self.last_rays

    def _refine(self, radiance, wsum, unresolved, box, poses, seed: int, alpha: float) -> None:
        g, dec = self.gbuffer, self.decisions
        self._frame += 1
        self.last_rays = self.last_pixels = 0
        read, write = self._h[self._frame % 2], self._h[(self._frame + 1) % 2]
        if dec is None or box[1] <= box[0] or box[3] <= box[2]:
            self._prev_poses = list(poses)
            return
        pixels, spp = _select(dec.rate, dec.spp, self._moving_only, g.id, self._dynamic, self.W, *(int(v) for v in box), dec.tile,
                              self._frame % 4, self._frame, self.settings.moving_every)
        n = len(pixels)
        hist = np.zeros((n, 3), np.float32)
        valid = np.zeros(n, np.bool_)
        if n and self._prev_poses is not None and len(self._prev_poses) == len(poses):
            if len(poses):
                ids = g.id[pixels]
                xm = _model_position(g.position[pixels], ids, poses)
                xy, ok = reproject(ids.reshape(1, -1), xm.reshape(1, -1, 3), self._prev_poses, g.camera, g.camera)
            else:  # no poses given: nothing moves, each pixel is its own history
                xy = np.stack([pixels % self.W, pixels // self.W], axis=1).astype(np.float64)
                ok = np.ones(n, np.bool_)
            _fetch(pixels, g.id, xy, ok, self.W, self.H, read[0], read[1], read[2], self._frame, hist, valid)
        samples = np.full((n, 3), np.nan, np.float32)
        for s in (1, 2, 4):
            sel = np.flatnonzero(spp == s)
            if len(sel) == 0:
                continue
            samples[sel] = self.renderer.render_pixels(g.camera, pixels[sel], poses, seed * 8 + s, spp=s,
                                                       static_hits=g.static_hits)
            c = self.renderer.counts
            self.last_rays += c.primary + c.intersect + c.occluded
            self.last_pixels += len(sel) * s
        if self.settings.moving_every > 1:
            _fill(pixels, spp, samples, self._moving_only, dec.tile, g.id, g.normal, self.W, self.H, *self._fresh, self._frame)
        _merge(pixels, spp, samples, hist, valid, np.float32(alpha), np.float32(self.settings.base_weight), radiance, wsum, unresolved, g.id,
               write[0], write[1], write[2], self._frame)
        self._prev_poses = list(poses)


def _model_position(world: np.ndarray, ids: np.ndarray, poses) -> np.ndarray:
    """x_m = Rᵀ (x_w − t) with each pixel's object pose (the G-buffer stores world positions)."""
    R = np.stack([np.asarray(p.R, np.float64) for p in poses])
    T = np.stack([np.asarray(p.t, np.float64) for p in poses])
    out = np.empty((len(ids), 3), np.float32)
    _model_position_kernel(world, ids, R, T, out)
    return out


@nb.njit(cache=True, nogil=True)
def _model_position_kernel(world, ids, R, T, out):
    """Per pixel, in float64 (a gathered (n, 3, 3) einsum cost ~10 ms CPU for 60 000 pixels)."""
    for k in range(ids.shape[0]):
        o = max(ids[k], 0)
        d0, d1, d2 = world[k, 0] - T[o, 0], world[k, 1] - T[o, 1], world[k, 2] - T[o, 2]
        for i in range(3):
            out[k, i] = R[o, 0, i] * d0 + R[o, 1, i] * d1 + R[o, 2, i] * d2


def tile_refiner(renderer, gbuffer, section) -> TileRefiner | None:
    """The session's refiner from its config's `lod` section (None when off or without a native
    G-buffer, i.e. at shading_scale 1)."""
    settings = RefineSettings(rays=section.rays, moving=section.moving, visible=section.visible,
                              shading_rate=section.shading_rate, adaptive_spp=section.adaptive_spp,
                              base_weight=section.base_weight, moving_every=section.moving_every, viewer_distance_m=section.viewer_distance_m,
                              alpha_v=section.alpha_v)
    return TileRefiner(renderer, gbuffer, settings) if gbuffer is not None and settings.enabled else None
