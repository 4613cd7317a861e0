"""Per-pixel guides of the filter and the upsampler, derived from a G-buffer.

One `Guides` per resolution (shading and native), computed by the same kernel so both ends of
the joint bilateral upsampling compare like with like:

- ``id`` object id; −1 background, −2 a hit whose G-buffer is not finite (NaN normal or depth:
  such a pixel is never blended with a neighbour, and no neighbour with it);
- ``depth`` camera z; ``normal`` the shading normal (facing the viewer);
- ``axis`` the specular lobe axis: the viewer direction reflected about the normal;
- ``sharp`` λ̄ of the specular lobe (`weights.specular_sharpness`, smoothed by κ);
- ``albedo`` / ``spec_albedo`` (float32, floored at `DEMOD_FLOOR`): demodulation divides by
  them, re-modulation multiplies by the native ones.

Only rows [y0, y1) × columns [x0, x1) are (re)computed: the native G-buffer of a moving object
changes only inside its region of interest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from dpmhw.reconstruct.weights import KAPPA, LAMBDA_BAR_MIN, MIN_NDOTV

DEMOD_FLOOR = 1e-3  # albedo below this is not divided out (a black surface reflects nothing)
INVALID_ID = -2


@dataclass
class Guides:
    """Flat (H*W, ...) arrays, row-major; see the module docstring."""

    width: int
    height: int
    id: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    axis: np.ndarray
    sharp: np.ndarray
    albedo: np.ndarray
    spec_albedo: np.ndarray

    @classmethod
    def empty(cls, width: int, height: int) -> "Guides":
        n = width * height
        return cls(width, height, np.full(n, -1, np.int32), np.zeros(n, np.float32), np.zeros((n, 3), np.float32),
                   np.zeros((n, 3), np.float32), np.full(n, LAMBDA_BAR_MIN, np.float32),
                   np.full((n, 3), DEMOD_FLOOR, np.float32), np.full((n, 3), DEMOD_FLOOR, np.float32))

    @classmethod
    def from_gbuffer(cls, object_id, position, normal, depth, albedo, spec_albedo, roughness, viewer) -> "Guides":
        """Guides of a whole (H, W) G-buffer (e.g. a renderer `Frame`'s)."""
        H, W = np.shape(object_id)
        g = cls.empty(W, H)
        g.update(object_id, position, normal, depth, albedo, spec_albedo, roughness, viewer, (0, H, 0, W))
        return g

    def update(self, object_id, position, normal, depth, albedo, spec_albedo, roughness, viewer, box,
               mask: np.ndarray | None = None) -> None:
        """Recompute the pixels of `box` = (y0, y1, x0, x1) from full-size (H, W, ...) G-buffer arrays;
        with `mask` (flat bool, H*W) only those of them it flags (the others keep their guides)."""
        y0, y1, x0, x1 = (int(v) for v in box)
        use_mask = mask is not None
        mask = np.ascontiguousarray(mask, np.bool_).reshape(-1) if use_mask else _NO_MASK
        if use_mask and mask.shape[0] != self.width * self.height:
            raise ValueError(f"guides mask: expected {self.width * self.height} pixels, got {mask.shape[0]}")
        _guides_kernel(np.ascontiguousarray(object_id, np.int32).reshape(-1), _flat3(position), _flat3(normal),
                       np.ascontiguousarray(depth, np.float32).reshape(-1), _flat3(albedo), _flat3(spec_albedo),
                       np.ascontiguousarray(roughness, np.float32).reshape(-1), np.asarray(viewer, np.float32).reshape(3),
                       self.width, y0, y1, x0, x1, use_mask, mask, self.id, self.depth, self.normal, self.axis,
                       self.sharp, self.albedo, self.spec_albedo)


_NO_MASK = np.zeros(1, np.bool_)


def _flat3(a) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).reshape(-1, 3)


@nb.njit(parallel=True, cache=True, nogil=True)
def _guides_kernel(gid, pos, nrm, dep, alb, spc, rough, viewer, W, y0, y1, x0, x1, use_mask, mask,
                   out_id, out_z, out_n, out_axis, out_sharp, out_alb, out_spec):
    for y in nb.prange(y0, y1):
        for x in range(x0, x1):
            p = y * W + x
            if use_mask and not mask[p]:
                continue
            o = gid[p]
            for c in range(3):
                out_alb[p, c] = max(alb[p, c], DEMOD_FLOOR) if math.isfinite(alb[p, c]) else DEMOD_FLOOR
                out_spec[p, c] = max(spc[p, c], DEMOD_FLOOR) if math.isfinite(spc[p, c]) else DEMOD_FLOOR
            out_z[p] = 0.0
            out_sharp[p] = LAMBDA_BAR_MIN
            for c in range(3):
                out_n[p, c] = 0.0
                out_axis[p, c] = 0.0
            if o < 0:
                out_id[p] = -1
                continue
            n0, n1, n2 = nrm[p, 0], nrm[p, 1], nrm[p, 2]
            z = dep[p]
            nl = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            e0, e1, e2 = viewer[0] - pos[p, 0], viewer[1] - pos[p, 1], viewer[2] - pos[p, 2]
            el = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            r = rough[p]
            if not (math.isfinite(nl) and nl > 1e-12 and math.isfinite(z) and z > 0.0 and math.isfinite(el)
                    and el > 1e-12 and math.isfinite(r)):
                out_id[p] = INVALID_ID
                continue
            out_id[p] = o
            n0, n1, n2 = n0 / nl, n1 / nl, n2 / nl
            e0, e1, e2 = e0 / el, e1 / el, e2 / el
            ndv = n0 * e0 + n1 * e1 + n2 * e2
            out_z[p] = z
            out_n[p, 0], out_n[p, 1], out_n[p, 2] = n0, n1, n2
            out_axis[p, 0] = 2.0 * ndv * n0 - e0
            out_axis[p, 1] = 2.0 * ndv * n1 - e1
            out_axis[p, 2] = 2.0 * ndv * n2 - e2
            a = max(r * r, 1e-3)  # the renderer's GGX α (roughness² with its floor)
            lam = 1.0 / (2.0 * a * a * max(ndv, MIN_NDOTV))
            out_sharp[p] = max(lam * KAPPA / (lam + KAPPA), LAMBDA_BAR_MIN)
