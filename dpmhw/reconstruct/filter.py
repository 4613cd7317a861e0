"""Cross-bilateral filtering of demodulated diffuse and specular light (Tokuyoshi, methods.md §2).

    Î(i) = Σⱼ f(i, j) · g_z(i, j) · w(i, j) · I(j) / Σⱼ (same weights)

over a (2r+1)² window at the shading resolution, where f is a spatial Gaussian, g_z a depth
weight that is exactly 0 across a depth discontinuity (relative difference > `DEPTH_GATE`),
taps of another object id weigh exactly 0, and w is

- mode ``normal``: the normal-aware weight for both buffers;
- mode ``lobe``: the normal-aware weight (= the diffuse lobe weight) for the diffuse buffer and
  the specular-lobe-aware weight (lobe axes and sharpness) for the specular buffer;
- mode ``off``: no filtering (the input is returned).

Background (id −1) and invalid (−2) pixels are passed through. The centre tap always weighs 1,
so a weight sum is never 0; non-finite inputs are read as 0. The diffuse weight sum is returned
per pixel: small sums mark pixels no neighbour supports (adaptive sampling).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from dpmhw.reconstruct.guides import Guides
from dpmhw.reconstruct.settings import FILTER_MODES
from dpmhw.reconstruct.weights import FASTMATH, fast_exp_neg, fast_lobe_weight, fast_normal_weight

DEPTH_GATE = 0.1  # relative depth difference beyond which two pixels never blend
DEPTH_SIGMA = 0.03  # relative depth scale of the smooth depth weight
RADIUS = 2  # 5×5 window at the shading resolution
SPATIAL_SIGMA = 1.5


class FilterError(ValueError):
    pass


def mode_code(mode: str) -> int:
    if mode not in FILTER_MODES:
        raise FilterError(f"filter: expected one of {', '.join(FILTER_MODES)}, got {mode!r}")
    return FILTER_MODES.index(mode)


@nb.njit(inline="always", fastmath=FASTMATH)
def depth_weight(zi, zj):
    """1 at equal depth, smooth below `DEPTH_GATE`, exactly 0 beyond it."""
    d = abs(zi - zj)
    if d > DEPTH_GATE * zi:
        return 0.0
    r = d / (DEPTH_SIGMA * zi)
    return fast_exp_neg(-0.5 * r * r)


@nb.njit(parallel=True, cache=True, nogil=True, fastmath=FASTMATH)
def _filter_kernel(mode, radius, spatial, W, H, gid, z, nrm, axis, sharp, dif, spe, out_d, out_s, wsum):
    for y in nb.prange(H):
        for x in range(W):
            i = y * W + x
            o = gid[i]
            if o < 0:
                for c in range(3):
                    out_d[i, c] = dif[i, c] if math.isfinite(dif[i, c]) else 0.0
                    out_s[i, c] = spe[i, c] if math.isfinite(spe[i, c]) else 0.0
                wsum[i] = 1.0
                continue
            zi = z[i]
            n0, n1, n2 = nrm[i, 0], nrm[i, 1], nrm[i, 2]
            a0, a1, a2 = axis[i, 0], axis[i, 1], axis[i, 2]
            si = sharp[i]
            sd0 = sd1 = sd2 = ss0 = ss1 = ss2 = 0.0
            wd_sum = 0.0
            ws_sum = 0.0
            for dy in range(-radius, radius + 1):
                yy = y + dy
                if yy < 0 or yy >= H:
                    continue
                for dx in range(-radius, radius + 1):
                    xx = x + dx
                    if xx < 0 or xx >= W:
                        continue
                    j = yy * W + xx
                    if gid[j] != o:
                        continue
                    wz = depth_weight(zi, z[j]) * spatial[dy + radius, dx + radius]
                    if wz <= 0.0:
                        continue
                    cn = n0 * nrm[j, 0] + n1 * nrm[j, 1] + n2 * nrm[j, 2]
                    wd = wz * fast_normal_weight(cn)
                    if mode == 2:
                        ca = a0 * axis[j, 0] + a1 * axis[j, 1] + a2 * axis[j, 2]
                        ws = wz * fast_lobe_weight(ca, si, sharp[j])
                    else:
                        ws = wd
                    d0, d1, d2 = dif[j, 0], dif[j, 1], dif[j, 2]
                    if math.isfinite(d0 + d1 + d2):
                        sd0 += wd * d0
                        sd1 += wd * d1
                        sd2 += wd * d2
                        wd_sum += wd
                    s0, s1, s2 = spe[j, 0], spe[j, 1], spe[j, 2]
                    if math.isfinite(s0 + s1 + s2):
                        ss0 += ws * s0
                        ss1 += ws * s1
                        ss2 += ws * s2
                        ws_sum += ws
            if wd_sum > 0.0:
                out_d[i, 0], out_d[i, 1], out_d[i, 2] = sd0 / wd_sum, sd1 / wd_sum, sd2 / wd_sum
            else:
                out_d[i, 0] = out_d[i, 1] = out_d[i, 2] = 0.0
            if ws_sum > 0.0:
                out_s[i, 0], out_s[i, 1], out_s[i, 2] = ss0 / ws_sum, ss1 / ws_sum, ss2 / ws_sum
            else:
                out_s[i, 0] = out_s[i, 1] = out_s[i, 2] = 0.0
            wsum[i] = wd_sum


def finite_rgb(a) -> np.ndarray:
    """Contiguous (n, 3) float32 copy with NaN/Inf replaced by 0 (one compiled pass: numpy's
    `nan_to_num` took ~0.2 ms per shading-resolution array, five of them a frame, serial)."""
    src = np.ascontiguousarray(a, np.float32).reshape(-1, 3)
    out = np.empty_like(src)
    _finite_copy(src.reshape(-1), out.reshape(-1))
    return out


@nb.njit(cache=True, nogil=True)  # no fastmath: it would assume the NaNs away
def _finite_copy(src, out):
    for i in range(src.shape[0]):
        v = src[i]
        out[i] = v if math.isfinite(v) else np.float32(0.0)


def spatial_kernel(radius: int = RADIUS, sigma: float = SPATIAL_SIGMA) -> np.ndarray:
    r = np.arange(-radius, radius + 1, dtype=np.float64)
    return np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma * sigma))


_SPATIAL = spatial_kernel()


def cross_bilateral(diffuse: np.ndarray, specular: np.ndarray, guides: Guides, mode: str = "lobe",
                    radius: int = RADIUS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Filter demodulated (H*W, 3) diffuse and specular light; returns (diffuse, specular, weight sum (H*W,)).

    Mode ``off`` returns the inputs (non-finite values as 0) with weight sums of 1.
    """
    code = mode_code(mode)
    n = guides.width * guides.height
    # NaN/Inf → 0 here, not in the kernel: fast-math may drop the kernel's own finiteness tests
    d = finite_rgb(diffuse)
    s = finite_rgb(specular)
    if d.shape[0] != n or s.shape[0] != n:
        raise FilterError(f"filter: expected {n} pixels ({guides.width}×{guides.height}), got {d.shape[0]} and {s.shape[0]}")
    if code == 0:
        return d, s, np.ones(n, np.float32)
    spatial = _SPATIAL if radius == RADIUS else spatial_kernel(radius)
    out_d = np.empty_like(d)
    out_s = np.empty_like(s)
    wsum = np.empty(n, np.float32)
    _filter_kernel(code, radius, spatial, guides.width, guides.height, guides.id, guides.depth, guides.normal,
                   guides.axis, guides.sharp, d, s, out_d, out_s, wsum)
    return out_d, out_s, wsum
