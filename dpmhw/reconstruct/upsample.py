"""Joint bilateral upsampling: shading-resolution light → native frame, guided by the native G-buffer.

For a native pixel X the shading-resolution position is u = (X + ½)·(w/W) − ½ (pixel centres
map onto each other as in `Scene.at_size`); its 2×2 neighbours j get

    W(X, j) = bilinear(u, j) · [id_j = id_X] · g_z(X, j) · w(X, j)

with the filter's depth weight g_z and guide weight w (`filter` module: normal-aware for the
diffuse buffer, lobe-aware for the specular one in mode ``lobe``; mode ``off`` keeps only the
id and depth terms). Demodulated diffuse D and specular S are re-modulated with the *native*
albedos, the directly seen emission E is upsampled with the diffuse weights:

    L(X) = E + albedo(X)·D + spec_albedo(X)·S          (background pixels: the background colour)

Fallback: when no 2×2 tap carries weight (a thin feature or a silhouette the shading resolution
missed) the (2·FALLBACK_RADIUS+1)² window around u is searched with a spatial Gaussian instead
of the bilinear weight; when no tap there shows the same object either, the pixel is
*unresolved*: L = E = 0 until adaptive sampling or the next frame covers it.

Only the rows × columns of `box` are written (the lit region): work follows the object, not
the frame. Interface for per-tile shading rates: `upsample` takes any (w, h) ≤ (W, H), the
ratio per axis need not be an integer.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from dpmhw.reconstruct.filter import DEPTH_GATE, DEPTH_SIGMA, finite_rgb, depth_weight, mode_code
from dpmhw.reconstruct.guides import Guides
from dpmhw.reconstruct.weights import FASTMATH, SIGMA_N2, fast_exp_neg, fast_lobe_weight

FALLBACK_RADIUS = 2


@nb.njit(inline="always", fastmath=FASTMATH)
def _tap(mode, zi, n0, n1, n2, a0, a1, a2, si, lz, ln, la, ls, j):
    """(diffuse, specular) guide weights of low-resolution tap j: the filter's depth weight times
    its normal- or lobe-aware weight. Every factor is an exponential, so each weight is one
    `fast_exp_neg` of the summed exponents (the lobe weight's power factor aside): one or two
    exponentials per tap instead of two or three; the same weights within `fast_exp_neg`'s error."""
    d = abs(zi - lz[j])
    if d > DEPTH_GATE * zi:
        return 0.0, 0.0
    r = d / (DEPTH_SIGMA * zi)
    ez = -0.5 * r * r
    if mode == 0:
        w = fast_exp_neg(ez)
        return w, w
    wd = fast_exp_neg(ez + (min(n0 * ln[j, 0] + n1 * ln[j, 1] + n2 * ln[j, 2], 1.0) - 1.0) * (1.0 / SIGMA_N2))
    if mode == 2:  # the lobe weight with the depth exponent folded in
        return wd, fast_lobe_weight(a0 * la[j, 0] + a1 * la[j, 1] + a2 * la[j, 2], si, ls[j], ez)
    return wd, wd


@nb.njit(inline="always", fastmath=FASTMATH)
def _add_tap(d0, d1, d2, e0, e1, e2, s0, s1, s2, wd_sum, ws_sum, wd, ws, ld, le, lsp, j):
    """Add low-resolution tap j with diffuse weight wd and specular weight ws to the running sums."""
    return (d0 + wd * ld[j, 0], d1 + wd * ld[j, 1], d2 + wd * ld[j, 2],
            e0 + wd * le[j, 0], e1 + wd * le[j, 1], e2 + wd * le[j, 2],
            s0 + ws * lsp[j, 0], s1 + ws * lsp[j, 1], s2 + ws * lsp[j, 2],
            wd_sum + wd, ws_sum + ws)


@nb.njit(parallel=True, cache=True, nogil=True, fastmath=FASTMATH)
def _upsample_kernel(mode, w, h, lid, lz, ln, la, ls, ld, lsp, le, W, H, gid, z, nrm, axis, sharp, alb, spec,
                     background, y0, y1, x0, x1, out, wsum, unresolved):
    sx = w / W
    sy = h / H
    for y in nb.prange(y0, y1):
        v = (y + 0.5) * sy - 0.5
        ty0 = int(math.floor(v))
        fy = v - ty0
        for x in range(x0, x1):
            i = y * W + x
            o = gid[i]
            unresolved[i] = False
            if o < 0:
                out[i, 0], out[i, 1], out[i, 2] = background[0], background[1], background[2]
                wsum[i] = 1.0
                continue
            u = (x + 0.5) * sx - 0.5
            tx0 = int(math.floor(u))
            fx = u - tx0
            zi = z[i]
            n0, n1, n2 = nrm[i, 0], nrm[i, 1], nrm[i, 2]
            a0, a1, a2 = axis[i, 0], axis[i, 1], axis[i, 2]
            si = sharp[i]
            d0 = d1 = d2 = s0 = s1 = s2 = e0 = e1 = e2 = 0.0
            wd_sum = 0.0
            ws_sum = 0.0
            for k in range(4):
                ty = ty0 + k // 2
                tx = tx0 + k % 2
                if ty < 0 or ty >= h or tx < 0 or tx >= w:
                    continue
                j = ty * w + tx
                if lid[j] != o:
                    continue
                b = (fy if k // 2 else 1.0 - fy) * (fx if k % 2 else 1.0 - fx)
                wd, ws = _tap(mode, zi, n0, n1, n2, a0, a1, a2, si, lz, ln, la, ls, j)
                wd *= b
                ws *= b
                d0, d1, d2, e0, e1, e2, s0, s1, s2, wd_sum, ws_sum = _add_tap(
                    d0, d1, d2, e0, e1, e2, s0, s1, s2, wd_sum, ws_sum, wd, ws, ld, le, lsp, j)
            if not (wd_sum > 1e-8):  # fallback: the wider window, spatial Gaussian weights
                d0 = d1 = d2 = s0 = s1 = s2 = e0 = e1 = e2 = 0.0
                wd_sum = ws_sum = 0.0
                cy = int(math.floor(v + 0.5))
                cx = int(math.floor(u + 0.5))
                for ty in range(max(cy - FALLBACK_RADIUS, 0), min(cy + FALLBACK_RADIUS + 1, h)):
                    for tx in range(max(cx - FALLBACK_RADIUS, 0), min(cx + FALLBACK_RADIUS + 1, w)):
                        j = ty * w + tx
                        if lid[j] != o:
                            continue
                        wd, ws = _tap(mode, zi, n0, n1, n2, a0, a1, a2, si, lz, ln, la, ls, j)
                        if wd <= 0.0 and ws <= 0.0 and depth_weight(zi, lz[j]) <= 0.0:
                            continue  # across a depth step: never
                        b = fast_exp_neg(-0.5 * ((tx - u) * (tx - u) + (ty - v) * (ty - v)))
                        wd = (wd + 1e-12) * b  # any same-object tap on this side of a depth step beats none
                        ws = (ws + 1e-12) * b
                        d0, d1, d2, e0, e1, e2, s0, s1, s2, wd_sum, ws_sum = _add_tap(
                            d0, d1, d2, e0, e1, e2, s0, s1, s2, wd_sum, ws_sum, wd, ws, ld, le, lsp, j)
            wsum[i] = wd_sum
            if wd_sum > 0.0:
                inv = 1.0 / wd_sum
                d0 *= inv
                d1 *= inv
                d2 *= inv
                e0 *= inv
                e1 *= inv
                e2 *= inv
            else:
                unresolved[i] = True
            if ws_sum > 0.0:
                inv = 1.0 / ws_sum
                s0 *= inv
                s1 *= inv
                s2 *= inv
            out[i, 0] = e0 + alb[i, 0] * d0 + spec[i, 0] * s0
            out[i, 1] = e1 + alb[i, 1] * d1 + spec[i, 1] * s1
            out[i, 2] = e2 + alb[i, 2] * d2 + spec[i, 2] * s2


def upsample(low: Guides, diffuse: np.ndarray, specular: np.ndarray, emitted: np.ndarray, native: Guides,
             mode: str = "lobe", box: tuple[int, int, int, int] | None = None, background=(0.0, 0.0, 0.0),
             out: np.ndarray | None = None, weight_sum: np.ndarray | None = None,
             unresolved: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Upsample and re-modulate (see the module docstring).

    low : guides at the shading resolution (w, h); diffuse, specular : demodulated (w*h, 3);
    emitted : (w*h, 3) directly seen emission; native : guides at (W, H); box : (y0, y1, x0, x1)
    native region to write (None: all). `out` (W*H, 3) float32, `weight_sum` (W*H,) float32,
    `unresolved` (W*H,) bool may be given to write into (pixels outside `box` keep their values).
    Returns (radiance (W*H, 3), diffuse weight sum (W*H,), unresolved (W*H,)).
    """
    W, H = native.width, native.height
    n_low = low.width * low.height
    arrays = []
    for name, a in (("diffuse", diffuse), ("specular", specular), ("emitted", emitted)):
        a = finite_rgb(a)
        if a.shape[0] != n_low:
            raise ValueError(f"upsample: {name} has {a.shape[0]} pixels, the shading guides {n_low}")
        arrays.append(a)
    y0, y1, x0, x1 = (0, H, 0, W) if box is None else (int(v) for v in box)
    if not (0 <= y0 <= y1 <= H and 0 <= x0 <= x1 <= W):
        raise ValueError(f"upsample: box {box} outside the {W}×{H} frame")
    out = np.zeros((W * H, 3), np.float32) if out is None else out
    weight_sum = np.zeros(W * H, np.float32) if weight_sum is None else weight_sum
    unresolved = np.zeros(W * H, np.bool_) if unresolved is None else unresolved
    _upsample_kernel(mode_code(mode), low.width, low.height, low.id, low.depth, low.normal, low.axis, low.sharp,
                     arrays[0], arrays[1], arrays[2], W, H, native.id, native.depth, native.normal, native.axis,
                     native.sharp, native.albedo, native.spec_albedo, np.asarray(background, np.float32).reshape(3),
                     y0, y1, x0, x1, out, weight_sum, unresolved)
    return out, weight_sum, unresolved
