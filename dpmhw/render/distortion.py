"""OpenCV's lens distortion (k1 k2 p1 p2 k3: the `cv2.projectPoints` model), written once: called
on numpy arrays as it is, and inlined into numba kernels as `distort_inline` (inlined in numba's
IR, so it rounds as the caller's own arithmetic would)."""

from __future__ import annotations

import numba as nb


def distort(x, y, k1, k2, p1, p2, k3):
    """Normalised image coordinates (x, y) = (X/Z, Y/Z), scalars or arrays -> distorted (xd, yd)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


distort_inline = nb.njit(inline="always")(distort)
