"""Adaptive sampling: native-resolution paths where the upsampled frame has too little support.

The joint bilateral upsampling (`upsample`) returns, per native pixel, the sum of its diffuse
weights and whether any shading sample supports it at all (*unresolved*: a thin feature or a
silhouette the shading resolution missed). Those pixels, and the ones whose weight sum is below
`WEIGHT_THRESHOLD` (few neighbours share their guides), get one extra path each through their
own centre, traced by the renderer at the native resolution (`PathIntegrator.render_pixels`
with the native G-buffer's camera and cached static hits), within a per-frame ray budget:

    pixels = budget_rays // rays_per_sample_bound      (the most rays one path can trace)

so the budget holds whatever the paths do. Unresolved pixels come first, then the smallest
weight sums (ties: the lower pixel index; the choice is deterministic). A chosen pixel becomes

    L = a·L_upsampled + (1 − a)·L_path,   a = weight_sum / WEIGHT_THRESHOLD  (0 if unresolved)

A pixel sampled in the previous frame too, showing the same object, averages its new path with
its last estimate as the temporal reuse does (weight α of the new one; "same-pixel" reuse at
the native resolution, history reset by an object change or a frame without a path there):
without it the silhouettes would flicker with 1-path noise while the rest of the frame is
reused. The blend is continuous at the threshold, and a filled pixel stops counting as unresolved.
A non-finite path sample keeps L_upsampled (and an unresolved pixel stays unresolved).

The session's threshold (`render.adaptive_threshold`) is 0 by default: only unresolved pixels
are sampled. On dpm-bunny and the paper scenes at ¼ shading there are none, and sampling the
weak band (threshold `WEIGHT_THRESHOLD`) bought ≤ 0.1 dB for ~1.8 CPU-ms a frame
(docs/temporal-reuse.md), a tenth of the frame; thin features the shading resolution misses
entirely still get their paths.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from dpmhw.lod.policy import rays_per_sample_bound

WEIGHT_THRESHOLD = 0.05  # diffuse weight sum below which a pixel asks for a native path
DEFAULT_BUDGET_RAYS = 2048  # per frame: ≈ 340 paths at ≤ 6 rays, the pixels with (almost) no 2×2 support at ¼ (docs)


@nb.njit(cache=True, nogil=True)
def _candidates(gid, wsum, unresolved, W, y0, y1, x0, x1, threshold):
    """Pixels of the box that show an object and are unresolved or under-supported, and their
    priority (−1 unresolved, else the weight sum)."""
    n = 0
    pix = np.empty((y1 - y0) * (x1 - x0), np.int64)
    key = np.empty((y1 - y0) * (x1 - x0), np.float32)
    for y in range(y0, y1):
        for x in range(x0, x1):
            i = y * W + x
            if gid[i] >= 0 and (unresolved[i] or wsum[i] < threshold):
                pix[n] = i
                key[n] = -1.0 if unresolved[i] else wsum[i]
                n += 1
    return pix[:n], key[:n]


@nb.njit(cache=True, nogil=True)
def _merge(pixels, samples, wsum, unresolved, threshold, radiance, gid, alpha, h_rad, h_id, h_frame, frame):
    for k in range(pixels.shape[0]):
        i = pixels[k]
        s0, s1, s2 = samples[k, 0], samples[k, 1], samples[k, 2]
        if not (np.isfinite(s0) and np.isfinite(s1) and np.isfinite(s2)):
            continue
        if h_frame[i] == frame - 1 and h_id[i] == gid[i]:  # sampled in the last frame too: its history
            s0 = alpha * s0 + (1.0 - alpha) * h_rad[i, 0]
            s1 = alpha * s1 + (1.0 - alpha) * h_rad[i, 1]
            s2 = alpha * s2 + (1.0 - alpha) * h_rad[i, 2]
        h_rad[i, 0], h_rad[i, 1], h_rad[i, 2] = s0, s1, s2
        h_id[i], h_frame[i] = gid[i], frame
        a = 0.0 if unresolved[i] or threshold <= 0.0 else min(max(wsum[i] / threshold, 0.0), 1.0)
        unresolved[i] = False
        radiance[i, 0] = a * radiance[i, 0] + (1.0 - a) * s0
        radiance[i, 1] = a * radiance[i, 1] + (1.0 - a) * s1
        radiance[i, 2] = a * radiance[i, 2] + (1.0 - a) * s2


def select(gid, wsum, unresolved, width: int, box, limit: int, threshold: float = WEIGHT_THRESHOLD) -> np.ndarray:
    """Up to `limit` pixels (ascending flat indices) of `box` to sample: unresolved first, then
    the smallest weight sums."""
    if limit <= 0 or box[1] <= box[0] or box[3] <= box[2]:
        return np.zeros(0, np.int64)
    pix, key = _candidates(gid, wsum, unresolved, int(width), *(int(v) for v in box), np.float32(threshold))
    if len(pix) > limit:
        pix = pix[np.lexsort((pix, key))[:limit]]
    return np.sort(pix)


class AdaptiveSampler:
    """Extra native paths for one session: `renderer` a `PathIntegrator` (any shading size),
    `gbuffer` the `NativeGBuffer` (its camera and cached static hits), `budget_rays` per frame."""

    def __init__(self, renderer, gbuffer, budget_rays: int = DEFAULT_BUDGET_RAYS, threshold: float = WEIGHT_THRESHOLD):
        if budget_rays < 0:
            raise ValueError(f"adaptive budget_rays: expected ≥ 0, got {budget_rays}")
        self.renderer, self.gbuffer = renderer, gbuffer
        self.threshold = float(threshold)
        self.budget_rays = int(budget_rays)
        self.rays_per_path = rays_per_sample_bound(renderer.max_bounces, renderer.mis_last)
        self.last_pixels = 0  # paths traced in the last frame
        self.last_rays = 0  # rays they traced (≤ budget_rays)
        n = gbuffer.width * gbuffer.height
        self._h_rad = np.zeros((n, 3), np.float32)  # per native pixel: its last adaptive estimate,
        self._h_id = np.full(n, -1, np.int32)  # the object it showed,
        self._h_frame = np.full(n, -2, np.int64)  # and the refine call it was made in
        self._frame = 0

    @property
    def max_pixels(self) -> int:
        return self.budget_rays // self.rays_per_path

    def reset(self) -> None:
        self._h_frame[:] = -2

    def refine(self, radiance, wsum, unresolved, box, poses, seed: int, alpha: float = 1.0, object_id=None) -> np.ndarray:
        """Sample the chosen pixels and blend them into `radiance` (W*H, 3) in place; returns
        them. `alpha`: the temporal reuse's weight of the new sample (1: no history).
        `object_id`: the frame's native ids (default the G-buffer's; the stage passes its native
        guides' ids, which stay this frame's while the G-buffer moves on to the next one)."""
        g = self.gbuffer
        gid = g.id if object_id is None else object_id
        self._frame += 1
        if self.max_pixels == 0:  # budget 0 (a live setting): nothing to choose
            self.last_pixels = self.last_rays = 0
            return np.empty(0, np.int64)
        pixels = select(gid, wsum, unresolved, g.width, box, self.max_pixels, self.threshold)
        self.last_pixels, self.last_rays = len(pixels), 0
        if len(pixels) == 0:
            return pixels
        samples = self.renderer.render_pixels(g.camera, pixels, poses, seed, static_hits=g.static_hits)
        c = self.renderer.counts
        self.last_rays = c.primary + c.intersect + c.occluded
        _merge(pixels, samples, wsum, unresolved, np.float32(self.threshold), radiance, gid, np.float32(alpha),
               self._h_rad, self._h_id, self._h_frame, self._frame)
        return pixels
