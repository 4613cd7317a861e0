"""The CSF is the published Mannos–Sakrison formula, scaled as documented."""

import math

import numpy as np
import pytest

from dpmhw.lod import csf


def published(f):  # Mannos & Sakrison 1974, as quoted in methods.md §3
    return 2.6 * (0.0192 + 0.114 * f) * math.exp(-((0.114 * f) ** 1.1))


@pytest.mark.parametrize("f", [0.0, 0.5, 1.0, 4.0, 8.0, 16.0, 30.0, 59.9])
def test_matches_published_formula(f):
    assert csf.mannos_sakrison(f) == pytest.approx(published(f), rel=1e-12)
    assert csf.csf(f, peak_sensitivity=1.0) == pytest.approx(published(f) / csf.A_PEAK, rel=1e-12)
    assert csf.csf(f, peak_sensitivity=250.0) == pytest.approx(250.0 * published(f) / csf.A_PEAK, rel=1e-12)


def test_peak_is_the_maximum_near_8_cpd():
    assert csf.F_PEAK == pytest.approx(7.89, abs=0.01)
    assert csf.A_PEAK == pytest.approx(published(csf.F_PEAK), rel=1e-12)
    grid = np.linspace(0, 60, 100001)
    assert csf.csf(grid).max() <= 1.0 + 1e-12
    assert csf.csf(csf.F_PEAK, 100.0) == pytest.approx(100.0)


@pytest.mark.parametrize("f", [60.0001, 1e6, 1e308, math.inf, -1.0, -math.inf, math.nan])
def test_outside_the_fit_is_zero(f):
    assert csf.csf(f, 100.0) == 0.0
    assert csf.mannos_sakrison(f) == 0.0
