"""Mannos–Sakrison contrast sensitivity function (CSF), scaled to a sensitivity.

Source: J. L. Mannos and D. J. Sakrison, "The effects of a visual fidelity criterion on the
encoding of images", IEEE Trans. Inf. Theory 20(4), 1974, as used by Miza & Saito for
contrast-driven level of detail (docs/lod.md):

    A(f) = 2.6 · (0.0192 + 0.114 f) · exp(−(0.114 f)^1.1),   f in cycles per degree

Normalisation (the paper leaves it open). A(f) peaks at f* ≈ 8.0 cpd with A(f*) ≈ 0.98: it is a
relative curve. The visibility V = CSF(f) − 1/c + α compares the CSF with 1/c, the inverse of a
Michelson contrast, which is a *sensitivity* (1 / threshold contrast). Used raw, a contrast is
visible only when c > 1/0.98, i.e. never; so we scale the curve to a sensitivity:

    S(f) = S_peak · A(f) / A(f*)

with S_peak the peak contrast sensitivity of the audience (default 100: a threshold contrast of
1 % at the peak frequency, a conservative value for photopic viewing of a projected image; the
classic measurements at 10–100 cd/m² give 100–300). V then lives in the same units
(1/contrast), and α_v is in those units too.

Range. The published fit covers 0–60 cpd (60 cpd is the limit of foveal acuity). Above
`F_MAX` the eye resolves nothing and S = 0; non-finite or negative f also give 0, so the
function is finite and within [0, S_peak] for every input.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

F_MAX = 60.0  # cycles/degree: the upper end of the fit and of foveal acuity


@nb.njit(nogil=True, cache=True)
def mannos_sakrison(f: float) -> float:
    """The published relative curve A(f) (peak ≈ 0.98 near 8 cpd); 0 outside [0, F_MAX]."""
    if not (0.0 <= f <= F_MAX):  # also catches NaN
        return 0.0
    x = 0.114 * f
    return 2.6 * (0.0192 + x) * math.exp(-(x**1.1))


def _peak() -> tuple[float, float]:
    """(f*, A(f*)) by a fine grid then golden-section refinement (done once at import)."""
    grid = np.linspace(0.0, F_MAX, 601)
    x = 0.114 * grid
    i = int(np.argmax((0.0192 + x) * np.exp(-(x**1.1))))
    lo, hi = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
    g = (math.sqrt(5) - 1) / 2
    for _ in range(80):
        m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
        if mannos_sakrison(m1) < mannos_sakrison(m2):
            lo = m1
        else:
            hi = m2
    f = (lo + hi) / 2
    return f, mannos_sakrison(f)


F_PEAK, A_PEAK = _peak()


@nb.njit(nogil=True, cache=True)
def sensitivity(f: float, peak_sensitivity: float, a_peak: float) -> float:
    """S(f) = peak_sensitivity · A(f) / A(f*), in 1/contrast; 0 outside the fit's range."""
    return peak_sensitivity * mannos_sakrison(f) / a_peak


def csf(f, peak_sensitivity: float = 1.0) -> np.ndarray:
    """Vectorised S(f) for an array of frequencies (cpd); the per-tile path is the numba
    `sensitivity` inside visibility.py. peak_sensitivity=1 gives the peak-normalised A(f)/A(f*)."""
    f = np.asarray(f, dtype=np.float64)
    inside = (f >= 0.0) & (f <= F_MAX)  # False for NaN
    x = 0.114 * np.where(inside, f, 0.0)
    a = 2.6 * (0.0192 + x) * np.exp(-(x**1.1))
    return np.where(inside, peak_sensitivity * a / A_PEAK, 0.0)
