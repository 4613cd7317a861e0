"""Properties of the lobe-aware and normal-aware weights (reference and fast kernel versions)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dpmhw.reconstruct.weights import (DIFFUSE_LAMBDA, LAMBDA_BAR_MIN, fast_lobe_weights, lobe_weight, normal_weight,
                                       smoothed_sharpness)

unit = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 1e-3).map(
    lambda v: np.asarray(v) / np.linalg.norm(v))
lam = st.one_of(st.just(0.0), st.floats(0.0, 1e4), st.just(1e4))
FAST = settings(max_examples=200, deadline=None)


@FAST
@given(unit, unit, lam, lam)
def test_symmetric_finite_and_in_unit_interval(a, b, la, lb):
    w = lobe_weight(a, b, la, lb)
    assert np.isfinite(w) and 0.0 <= w <= 1.0
    assert w == lobe_weight(b, a, lb, la)


@FAST
@given(unit, lam)
def test_identical_lobes_weigh_one(a, la):
    assert lobe_weight(a, a, la, la) == 1.0 or abs(lobe_weight(a, a, la, la) - 1.0) < 1e-12


@FAST
@given(unit, unit)
def test_diffuse_lobes_reduce_to_the_normal_aware_weight(a, b):
    assert np.isclose(lobe_weight(a, b, DIFFUSE_LAMBDA, DIFFUSE_LAMBDA), normal_weight(a, b), rtol=1e-9, atol=1e-300)


@FAST
@given(lam, lam, st.floats(0.0, np.pi), st.floats(0.0, np.pi))
def test_monotone_in_the_angle_between_axes(la, lb, t1, t2):
    lo, hi = sorted((t1, t2))
    x = np.array([1.0, 0.0, 0.0])

    def axis(t):
        return np.array([np.cos(t), np.sin(t), 0.0])

    assert lobe_weight(x, axis(lo), la, lb) >= lobe_weight(x, axis(hi), la, lb)


def test_sharper_lobe_differences_lower_the_weight():
    a = np.array([0.0, 0.0, 1.0])
    assert lobe_weight(a, a, 1e4, 1.0) < lobe_weight(a, a, 1e4, 1e3) < 1.0


def test_extremes_are_stable():
    a = np.array([0.0, 0.0, 1.0])
    for la, lb, cos in [(0.0, 0.0, -1.0), (0.0, 1e4, 1.0), (1e4, 1e4, -1.0), (np.inf, 0.0, 0.0), (1e30, 1e-30, 0.5)]:
        b = np.array([np.sqrt(1 - cos * cos), 0.0, cos])
        w = lobe_weight(a, b, la, lb)
        assert np.isfinite(w) and 0.0 <= w <= 1.0
    assert smoothed_sharpness(0.0) == LAMBDA_BAR_MIN


def test_fast_kernel_weight_matches_the_log_space_reference():
    rng = np.random.default_rng(1)
    n = 20000
    cos = rng.uniform(-1, 1, n)
    cos[:100] = 1.0
    la, lb = 10 ** rng.uniform(-3, 4, n), 10 ** rng.uniform(-3, 4, n)
    la[:50] = 0.0
    a, b = smoothed_sharpness(la), smoothed_sharpness(lb)
    ref = lobe_weight(np.stack([np.sqrt(1 - cos**2), np.zeros(n), cos], 1), np.tile([0.0, 0, 1], (n, 1)), la, lb)
    fast = fast_lobe_weights(cos, a, b)
    assert np.all(np.isfinite(fast)) and np.max(np.abs(fast - ref)) < 3e-4
