"""OpenCV's lens distortion (k1 k2 p1 p2 k3: the `cv2.projectPoints` model), written once: called
on numpy arrays as it is, and inlined into numba kernels as `distort_inline` (inlined in numba's
IR, so it rounds as the caller's own arithmetic would). A float32 kernel passes `one` and `two`
as float32: numba types a float literal float64, which would widen the whole polynomial (and
halve the SIMD lanes)."""

from __future__ import annotations

import numba as nb


def distort(x, y, k1, k2, p1, p2, k3, one=1.0, two=2.0):
    """Normalised image coordinates (x, y) = (X/Z, Y/Z), scalars or arrays -> distorted (xd, yd);
    `one`, `two`: the constants 1 and 2 in the precision to compute in."""
    r2 = x * x + y * y
    radial = one + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + two * p1 * x * y + p2 * (r2 + two * x * x)
    yd = y * radial + p1 * (r2 + two * y * y) + two * p2 * x * y
    return xd, yd


distort_inline = nb.njit(inline="always")(distort)
