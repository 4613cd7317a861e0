"""Per-tile decisions from a visibility map: shading rate and samples per pixel, under a ray budget.

Levels come from V (`visibility.py`, units 1/contrast) through ascending thresholds:

    shading rate   V ≤ t0: history only (0)   t0 < V ≤ t1: 1/4   t1 < V ≤ t2: 1/2   V > t2: full
    spp            V ≤ t0: 0                  t0 < V ≤ t1: 1     t1 < V ≤ t2: 2     V > t2: 4

`rate` is the pixel pitch of shading per axis (1 full, 2 half, 4 quarter, 0 none: the tile keeps
its history, to be upsampled/reused by the reconstruction stage). Safeguards, all stateful and
I/O-free like `session/safety.py`:

- dilation: a tile takes the max V of its neighbours within `dilate` tiles, because the map is a
  frame old and objects move into tiles that were empty;
- hysteresis: a tile drops a level only when V + `hysteresis` no longer reaches it, so V jittering
  around a threshold (noise in the previous frame) does not flicker between rates;
- refresh: a tile that kept its history for `refresh_frames` frames is shaded once at the lowest
  level (1/4, 1 spp), staggered over tiles, so lighting changes in "invisible" tiles still arrive.

Ray budget: a sample costs at most `rays_per_sample` rays (camera + one shadow ray per vertex +
continuations; `rays_per_sample_bound`). Samples are granted in priority order (every tile's
first sample before anyone's second; within a step the tile unshaded longest first, then by V)
while the running total stays within `ray_budget`: the bound Σ spp · shaded pixels ·
rays_per_sample ≤ ray_budget holds by construction, so the traced rays never exceed it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dpmhw.lod.visibility import LodSettingsError, VisibilityMap, check_number

RATES = np.array([0, 4, 2, 1], np.uint8)  # level → pixel pitch per axis (0: history only)
SPPS = np.array([0, 1, 2, 4], np.uint8)  # level → samples per shaded pixel
BOOST_PRIORITY = 1.0e15  # added to a boosted tile's priority (age · 1e5 + V stays far below it)
BOOST_V = 1.0e4  # V given to boosted tiles: above any threshold (V itself never exceeds α_v + S_peak − 1)


def rays_per_sample_bound(max_bounces: int, mis_last: bool) -> int:
    """Most rays one camera sample can trace in dpmhw's path tracer: 1 camera ray, one NEE shadow
    ray at each of the L + 1 vertices and L continuation rays (L = max_bounces, +1 with mis_last)."""
    last = int(max_bounces) + (1 if mis_last else 0)
    return 1 + (last + 1) + last


@dataclass(frozen=True)
class PolicySettings:
    thresholds: tuple[float, float, float] = (0.0, 20.0, 50.0)  # V above which level 1, 2, 3 starts
    hysteresis: float = 5.0
    dilate: int = 1
    refresh_frames: int = 8
    shading_rate: bool = True  # off: every shaded tile at full rate
    adaptive_spp: bool = True  # off: every shaded tile at 1 spp
    ray_budget: int | None = None  # rays per frame; None: unlimited
    rays_per_sample: int = 4  # rays_per_sample_bound(1, False)
    free_rate: int = 0  # tiles at this pitch cost no rays of the budget (4: a ¼ base frame shades them anyway)
    keep: float | None = None  # None: longest-unshaded first (tiles take turns); a number: most visible first, and
    # a tile granted last frame counts `keep` more (its native history continues instead of lapsing between turns)

    def __post_init__(self):
        t = tuple(check_number(f"thresholds[{i}]", x, -1e4, 1e4) for i, x in enumerate(self.thresholds))
        if len(t) != 3 or not (t[0] <= t[1] <= t[2]):
            raise LodSettingsError(f"thresholds: expected three ascending values, got {self.thresholds!r}")
        object.__setattr__(self, "thresholds", t)
        object.__setattr__(self, "hysteresis", check_number("hysteresis", self.hysteresis, 0.0, 1e4))
        object.__setattr__(self, "dilate", check_number("dilate", self.dilate, 0, 16, integer=True))
        object.__setattr__(self, "refresh_frames", check_number("refresh_frames", self.refresh_frames, 1, 1e6, integer=True))
        object.__setattr__(self, "rays_per_sample", check_number("rays_per_sample", self.rays_per_sample, 1, 1e3, integer=True))
        if self.free_rate not in (0, 1, 2, 4):
            raise LodSettingsError(f"free_rate: expected 0 (none), 1, 2 or 4, got {self.free_rate!r}")
        if self.keep is not None:
            object.__setattr__(self, "keep", check_number("keep", self.keep, 0.0, 1e4))
        if self.ray_budget is not None:
            object.__setattr__(self, "ray_budget", check_number("ray_budget", self.ray_budget, 0, 1e15, integer=True))


@dataclass
class TileDecisions:
    """Per tile (TY, TX): rate (uint8 pitch: 0 history, 1, 2, 4), spp (uint8 0/1/2/4, 0 exactly
    where rate is 0), shaded_pixels (int64 pixels shaded once per sample at that rate),
    refreshed (bool: forced refresh of a history tile); ray_bound: the most rays this frame can
    trace, ≤ the budget."""

    rate: np.ndarray
    spp: np.ndarray
    shaded_pixels: np.ndarray
    refreshed: np.ndarray
    ray_bound: int
    tile: int

    def pixel_spp(self, height: int, width: int) -> np.ndarray:
        """(H, W) uint8 samples per pixel at full resolution (rate ignored: for full-rate tiles)."""
        t = self.tile
        return np.repeat(np.repeat(self.spp, t, 0), t, 1)[:height, :width]

    def pixel_rate(self, height: int, width: int) -> np.ndarray:
        t = self.tile
        return np.repeat(np.repeat(self.rate, t, 0), t, 1)[:height, :width]


def _tile_sides(height: int, width: int, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of each tile row and columns of each tile column (edge tiles may be partial)."""
    return (np.minimum(tile, height - np.arange(0, height, tile)).astype(np.int64),
            np.minimum(tile, width - np.arange(0, width, tile)).astype(np.int64))


def tile_pixel_counts(height: int, width: int, tile: int) -> np.ndarray:
    """(TY, TX) pixels in each tile (edge tiles may be partial)."""
    ys, xs = _tile_sides(height, width, tile)
    return np.outer(ys, xs)


def shaded_counts(rate: np.ndarray, height: int, width: int, tile: int) -> np.ndarray:
    """(TY, TX) pixels shaded per sample at each tile's pitch: ⌈rows/rate⌉ · ⌈cols/rate⌉ (0 where
    rate is 0). Every pixel whose row and column are both ≡ (phase) mod rate, counted from the
    tile's origin (a multiple of the tile, so of every rate dividing it), is within this bound
    whatever the phase."""
    ys, xs = _tile_sides(height, width, tile)
    r = np.maximum(rate, 1).astype(np.int64)
    return np.where(rate > 0, -(-ys[:, None] // r) * -(-xs[None, :] // r), 0)


def dilate_max(v: np.ndarray, r: int) -> np.ndarray:
    """Each tile takes the max of its neighbours within r tiles (the map is a frame old: objects move in)."""
    if r == 0:
        return v
    p = np.pad(v, r, mode="edge")
    out = v.copy()
    for dy in range(-r, r + 1):  # (2r + 1)² shifted views: per-tile work stays in numpy
        for dx in range(-r, r + 1):
            np.maximum(out, p[r + dy : r + dy + v.shape[0], r + dx : r + dx + v.shape[1]], out=out)
    return out


def allocate(levels: np.ndarray, priority: np.ndarray, shaded: np.ndarray, budget: int | None, rays_per_sample: int) -> np.ndarray:
    """Grant each tile at most its level (spp 0/1/2/4) in priority order within the ray budget.

    Steps: level 1 (1 spp), 2 (+1), 3 (+2); all tiles' step k before any step k + 1, within a step
    higher `priority` first. The granted prefix is the longest whose cost fits. Returns levels."""
    levels = levels.reshape(-1).astype(np.int64)
    if budget is None:
        return levels.reshape(shaded.shape)
    n = levels.size
    step = np.repeat(np.arange(1, 4), n)
    tile = np.tile(np.arange(n), 3)
    want = step <= levels[tile]
    step, tile = step[want], tile[want]
    cost = (SPPS[step].astype(np.int64) - SPPS[step - 1]) * shaded.reshape(-1)[tile] * rays_per_sample
    order = np.lexsort((-priority.reshape(-1)[tile], step))
    fits = np.cumsum(cost[order]) <= budget
    granted = np.zeros(n, np.int64)
    np.maximum.at(granted, tile[order][fits], step[order][fits])
    return granted.reshape(shaded.shape)


class TilePolicy:
    """Turns each frame's visibility map into TileDecisions; keeps the per-tile state."""

    def __init__(self, height: int, width: int, settings: PolicySettings = PolicySettings()):
        self.height, self.width, self.settings = int(height), int(width), settings
        self._level: np.ndarray | None = None
        self._age: np.ndarray | None = None  # frames since each tile was last shaded
        self.frame = 0

    def reset(self) -> None:
        self._level = self._age = None
        self.frame = 0

    def levels(self, v: np.ndarray) -> np.ndarray:
        """Level (0–3) of each visibility value by the thresholds, before dilation, hysteresis and budget."""
        return np.searchsorted(np.asarray(self.settings.thresholds), v, side="left").astype(np.int64)  # V > t_k ⇒ level ≥ k+1

    def decide(self, vmap: VisibilityMap, boost: np.ndarray | None = None, traceable: np.ndarray | None = None) -> TileDecisions:
        """`boost`: optional (TY, TX) bool, tiles to treat as the most visible (e.g. a moving
        object covers them now: its shading changes under the viewer's eye). `traceable`:
        optional (TY, TX) count of pixels per tile that can take a path at all (e.g. those that
        show a surface); a tile's shaded pixels are at most that many."""
        s = self.settings
        tile = vmap.tile
        v = seen = dilate_max(np.asarray(vmap.visibility, np.float64), s.dilate)
        if boost is not None:  # from the current frame's G-buffer: no lag to cover, not dilated
            v = np.where(boost, BOOST_V, v)
        pixels = tile_pixel_counts(self.height, self.width, tile)
        if v.shape != pixels.shape:
            raise LodSettingsError(f"visibility: expected tiles {pixels.shape} for {self.width}×{self.height}, got {v.shape}")
        up = self.levels(v)
        if self._level is None or self._level.shape != v.shape:
            self._level, self._age = up.copy(), np.zeros(v.shape, np.int64)
        prev, age = self._level, self._age
        level = np.where(up >= prev, up, np.minimum(prev, self.levels(v + s.hysteresis)))
        self._level = level
        index = np.arange(level.size).reshape(level.shape)
        refresh = (level == 0) & (age >= s.refresh_frames) & ((index + self.frame) % s.refresh_frames == 0)
        self.frame += 1
        render_level = np.where(refresh, 1, level)
        rate = RATES[render_level] if s.shading_rate else np.where(render_level > 0, 1, 0).astype(np.uint8)
        shaded = shaded_counts(rate, self.height, self.width, tile)
        if traceable is not None:
            shaded = np.minimum(shaded, traceable)
        if s.free_rate:
            shaded = np.where(rate == s.free_rate, 0, shaded)
        if boost is not None:  # a boosted tile's samples per pixel still follow what the map saw there (≥ 1)
            render_level = np.where(boost, np.maximum(self.levels(seen), 1), render_level)
        spp_level = render_level if s.adaptive_spp else np.minimum(render_level, 1)
        if s.keep is None:  # longest-unshaded first (V is bounded by 1e4, so age dominates): under a tight
            priority = age * 1e5 + v  # budget every wanted tile takes its turn instead of the most visible ones starving the rest
        else:  # most visible first, the last frame's grants kept: with a base that shades every tile anyway a
            priority = seen + s.keep * (age == 0)  # tile left out keeps the base, and one refined in turns would lose its
            # history; boosted tiles too are ordered by what the map saw there
        if boost is not None:  # boosted tiles first: what they show changes now, whatever waited longest
            priority = np.where(boost, priority + BOOST_PRIORITY, priority)
        granted = allocate(spp_level, priority, shaded, s.ray_budget, s.rays_per_sample)
        spp = SPPS[granted]
        rate = np.where(spp > 0, rate, 0).astype(np.uint8)
        self._age = np.where(spp > 0, 0, age + 1)
        ray_bound = int((spp.astype(np.int64) * shaded).sum() * s.rays_per_sample)
        return TileDecisions(rate, spp, shaded, refresh & (spp > 0), ray_bound, tile)
