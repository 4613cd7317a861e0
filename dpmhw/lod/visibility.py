"""Per-tile visibility map from the previous output frame (Miza & Saito, `methods.md` §3).

In the temporal loop the previous frame (after reuse) is a free pre-pass. For every screen tile
(default 16×16 projector pixels):

1. Luminance L = 0.2126 R + 0.7152 G + 0.0722 B of the linear radiance, averaged over `block`×
   `block` pixel blocks (the "samples"; averaging keeps single-sample noise of a 1-spp frame
   from reading as contrast). Non-finite pixels are skipped, negative ones count as 0.
2. Michelson contrast c = (L_max − L_min) / (L_max + L_min) of the brightest and darkest block;
   c = 0 when the tile is uniform, black, or has no finite sample. Noise-aware (`noise_k` > 0):
   the range first loses `noise_k` · σ̂, with σ̂ = 1.4826 · median|b_i − b_{i+1}| / √2 over
   horizontally adjacent block means b (the MAD of their differences: a step edge crosses few
   pairs, so σ̂ measures the noise, not the detail), c = max(0, L_max − L_min − k σ̂) / (L_max +
   L_min). Noise alone spans about 5σ over a tile's 64 blocks and rarely beyond 6σ, so k = 6
   keeps a noisy flat tile from reading as detail (k = 4 left a third of such tiles visible:
   at 1 % threshold contrast, what survives a 4σ floor still shows), while a clean edge, a
   single bright pixel or a uniform tile (σ̂ = 0) keep their contrast.
3. Spatial frequency: the brightest and darkest blocks are half a cycle apart. Their distance
   d (pixels) covers d · z / f_px metres on the surface (z: the tile's mean finite G-buffer depth,
   f_px = √(fx·fy): the projector pixel footprint, fronto-parallel approximation), which a viewer
   at `viewer_distance_m` sees under θ = atan(d z / (f_px D)) degrees, so f = 1 / (2θ) cycles per
   degree. Tiles with no surface (background only) have no frequency: S = 0.
4. V = S(f) − 1/c + α_v (`csf.py`: S in 1/contrast, peak `peak_sensitivity`); 1/c is capped at
   `INV_CONTRAST_MAX`, so V ∈ [α_v − INV_CONTRAST_MAX, α_v + peak_sensitivity − 1]: always finite.

V > 0: a viewer could see the tile's detail. One numba kernel, parallel over tiles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from dpmhw.errors import DpmhwError
from dpmhw.lod.csf import A_PEAK, sensitivity

INV_CONTRAST_MAX = 1.0e4  # contrasts below 0.01 % (100× below any threshold) count as 0.01 %


class LodSettingsError(DpmhwError, ValueError):
    """A level-of-detail setting is out of range; the message names the field."""


def check_number(name: str, value, lo: float, hi: float, lo_open: bool = False, integer: bool = False):
    """`value` as a float (or int) within [lo, hi] ((lo, hi] with lo_open), else LodSettingsError naming `name`."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise LodSettingsError(f"{name}: expected a number, got {value!r}") from None
    if not math.isfinite(x) or x < lo or x > hi or (lo_open and x == lo) or (integer and x != int(x)):
        kind = "an integer" if integer else "a finite number"
        raise LodSettingsError(f"{name}: expected {kind} in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {value!r}")
    return int(x) if integer else x


@dataclass(frozen=True)
class VisibilitySettings:
    """Defaults for a lab demo: the audience stands 1–2 m from the projected surface (1.5 m), α_v
    = 0 (the previous frame is the final image, not a cheaper pre-pass, so no pre-pass error to
    cover), peak sensitivity 100 (1 % threshold contrast, see csf.py)."""

    viewer_distance_m: float = 1.5
    alpha_v: float = 0.0
    peak_sensitivity: float = 100.0
    tile: int = 16
    block: int = 2
    noise_k: float = 6.0  # the noise floor in σ̂ (0: plain Michelson contrast)

    def __post_init__(self):
        object.__setattr__(self, "viewer_distance_m", check_number("viewer_distance_m", self.viewer_distance_m, 0.0, 1e4, lo_open=True))
        object.__setattr__(self, "alpha_v", check_number("alpha_v", self.alpha_v, -1e4, 1e4))
        object.__setattr__(self, "peak_sensitivity", check_number("peak_sensitivity", self.peak_sensitivity, 1.0, 1e4))
        object.__setattr__(self, "noise_k", check_number("noise_k", self.noise_k, 0.0, 100.0))
        tile = check_number("tile", self.tile, 2, 256, integer=True)
        block = check_number("block", self.block, 1, tile, integer=True)
        if tile % block:
            raise LodSettingsError(f"block: must divide tile ({tile}), got {block}")
        object.__setattr__(self, "tile", tile)
        object.__setattr__(self, "block", block)

    @property
    def bounds(self) -> tuple[float, float]:
        """The closed range every visibility value lies in."""
        return self.alpha_v - INV_CONTRAST_MAX, self.alpha_v + self.peak_sensitivity - 1.0


@dataclass
class VisibilityMap:
    """Per-tile arrays, shape (ceil(H / tile), ceil(W / tile)), float32: visibility V,
    frequency_cpd f (inf where the extremes coincide, nan without a surface), contrast c."""

    visibility: np.ndarray
    frequency_cpd: np.ndarray
    contrast: np.ndarray
    tile: int

    @property
    def visible(self) -> np.ndarray:
        return self.visibility > 0


@nb.njit(nogil=True, cache=True, parallel=True)
def _visibility_kernel(rad, depth, focal, dist_m, alpha, s_peak, a_peak, tile, block, noise_k, vis, freq, con):
    H, W = depth.shape
    TY, TX = vis.shape
    nb_side = -(-tile // block)
    for t in nb.prange(TY * TX):
        ty, tx = t // TX, t % TX
        y0, x0 = ty * tile, tx * tile
        y1, x1 = min(y0 + tile, H), min(x0 + tile, W)
        lmax, lmin = -1.0, np.inf
        ymax = xmax = ymin = xmin = 0.0
        zsum, zn = 0.0, 0
        diffs = np.empty(nb_side * nb_side, np.float64)
        nd = 0
        for by in range(y0, y1, block):
            left = np.nan
            for bx in range(x0, x1, block):
                s, n = 0.0, 0
                for y in range(by, min(by + block, y1)):
                    for x in range(bx, min(bx + block, x1)):
                        lum = 0.2126 * rad[y, x, 0] + 0.7152 * rad[y, x, 1] + 0.0722 * rad[y, x, 2]
                        if math.isfinite(lum):
                            s += max(lum, 0.0)
                            n += 1
                        z = depth[y, x]
                        if math.isfinite(z) and z > 0.0:
                            zsum += z
                            zn += 1
                if n == 0:
                    left = np.nan
                    continue
                m = s / n
                if noise_k > 0.0 and left == left:  # left is not NaN
                    diffs[nd] = abs(m - left)
                    nd += 1
                left = m
                cy, cx = by + 0.5 * (min(by + block, y1) - by), bx + 0.5 * (min(bx + block, x1) - bx)
                if m > lmax:
                    lmax, ymax, xmax = m, cy, cx
                if m < lmin:
                    lmin, ymin, xmin = m, cy, cx
        c = 0.0
        if lmax >= 0.0 and lmax + lmin > 0.0 and math.isfinite(lmax):
            floor = noise_k * 1.4826 * np.median(diffs[:nd]) / math.sqrt(2.0) if nd > 0 else 0.0
            c = max(lmax - lmin - floor, 0.0) / (lmax + lmin)
        f = np.nan
        if zn > 0:
            d_px = math.sqrt((ymax - ymin) ** 2 + (xmax - xmin) ** 2)
            theta = math.degrees(math.atan(d_px * (zsum / zn) / focal / dist_m))
            f = 1.0 / (2.0 * theta) if theta > 0.0 else np.inf
        inv_c = 1.0 / c if c * INV_CONTRAST_MAX > 1.0 else INV_CONTRAST_MAX
        vis[ty, tx] = sensitivity(f, s_peak, a_peak) - inv_c + alpha  # S(nan) = S(inf) = 0
        freq[ty, tx] = f
        con[ty, tx] = c


def visibility_map(radiance: np.ndarray, depth: np.ndarray, K: np.ndarray, settings: VisibilitySettings = VisibilitySettings()) -> VisibilityMap:
    """V per tile of a frame.

    radiance : (H, W, 3) linear radiance of the previous output frame (any float; NaN allowed)
    depth : (H, W) camera-z depth of the previous frame's G-buffer (inf on background)
    K : (3, 3) projector intrinsics at this resolution (fx, fy in pixels)
    """
    radiance = np.asarray(radiance)
    depth = np.asarray(depth)
    if radiance.ndim != 3 or radiance.shape[2] != 3:
        raise LodSettingsError(f"radiance: expected (H, W, 3), got {radiance.shape}")
    if depth.shape != radiance.shape[:2]:
        raise LodSettingsError(f"depth: expected {radiance.shape[:2]} like radiance, got {depth.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise LodSettingsError(f"K: expected (3, 3), got {K.shape}")
    focal = math.sqrt(abs(K[0, 0] * K[1, 1]))
    if not (math.isfinite(focal) and focal > 0):
        raise LodSettingsError(f"K: focal lengths must be finite and non-zero, got fx={K[0, 0]!r}, fy={K[1, 1]!r}")
    s = settings
    H, W = depth.shape
    shape = (-(-H // s.tile), -(-W // s.tile))
    vis, freq, con = (np.empty(shape, np.float32) for _ in range(3))
    _visibility_kernel(np.ascontiguousarray(radiance, np.float32), np.ascontiguousarray(depth, np.float32), focal,
                       s.viewer_distance_m, s.alpha_v, s.peak_sensitivity, A_PEAK, s.tile, s.block, s.noise_k, vis, freq, con)
    return VisibilityMap(vis, freq, con, s.tile)
