"""Temporal reuse on synthetic inputs where the truth is known exactly."""

import numpy as np
import pytest

from dpmhw.reconstruct.reuse import ReuseError, ReuseSettings, TemporalReuse, split_screen, validate_alpha


@pytest.mark.parametrize("bad", [0, 0.0, -0.1, 1.0000001, 2, float("nan"), float("inf"), "abc", None])
def test_alpha_outside_0_1_raises_reuse_error(bad):
    with pytest.raises(ReuseError, match="alpha"):
        TemporalReuse(4, 3, alpha=bad)
    with pytest.raises(ValueError):  # ReuseError is a ValueError too
        validate_alpha(bad)


def test_alpha_one_and_tiny_are_accepted_and_mode_is_checked():
    assert validate_alpha(1) == 1.0 and validate_alpha(1e-6) == 1e-6
    with pytest.raises(ReuseError, match="mode"):
        TemporalReuse(4, 3, alpha=0.2, mode="motion-vectors")
    assert ReuseSettings(0.1, "motion", warmup=True).label == "motion α=0.1 +warmup"


def _ids(h, w, value=0):
    return np.full((h, w), value, np.int32)


@pytest.mark.parametrize("alpha", [0.2, 0.1, 0.05])
def test_steady_state_variance_is_alpha_over_2_minus_alpha(alpha):
    """Constant image + Gaussian noise: the EMA's variance is α/(2−α) of one sample's
    (≈ 1/9 at α = 0.2). Tolerance 1.2 % (≈ 4 standard errors): α/2 (−2.5 % at α = 0.05), α or α² fail."""
    h, w, sigma, truth = 160, 160, 0.1, 0.5
    rng = np.random.default_rng(1)
    reuse = TemporalReuse(w, h, alpha=alpha, mode="same-pixel")
    ids = _ids(h, w)
    burn_in, spacing, samples = int(8 / alpha), int(3 / alpha), 5  # (1−α)^(2·8/α) < 1e-5: no trace of the start
    variances, means = [], []
    noise = np.empty((h, w, 3), np.float32)
    for k in range(burn_in + spacing * samples):
        rng.standard_normal(out=noise, dtype=np.float32)
        out = reuse.update(truth + sigma * noise, ids)
        if k >= burn_in and (k - burn_in) % spacing == spacing - 1:
            variances.append(out.var(dtype=np.float64))
            means.append(out.mean(dtype=np.float64))
    ratio = np.mean(variances) / sigma**2
    assert ratio == pytest.approx(alpha / (2 - alpha), rel=0.012)
    assert np.mean(means) == pytest.approx(truth, abs=5e-4)  # unbiased
    # equivalent spp (2 − α)/α: 9 at α = 0.2, 19 at 0.1, 39 at 0.05
    assert 1 / ratio == pytest.approx((2 - alpha) / alpha, rel=0.012)


def test_first_frame_outputs_the_sample_then_blends_exactly():
    reuse = TemporalReuse(3, 2, alpha=0.25, mode="same-pixel")
    a = np.full((2, 3, 3), 1.0, np.float32)
    b = np.full((2, 3, 3), 3.0, np.float32)
    np.testing.assert_array_equal(reuse.update(a, _ids(2, 3)), a)
    np.testing.assert_allclose(reuse.update(b, _ids(2, 3)), 1.0 + 0.25 * (3.0 - 1.0), rtol=1e-7)
    assert np.all(reuse.history_length == 2)


def test_id_mismatch_resets_only_those_pixels():
    h, w = 4, 5
    reuse = TemporalReuse(w, h, alpha=0.2, mode="same-pixel")
    for _ in range(5):
        reuse.update(np.ones((h, w, 3), np.float32), _ids(h, w, 0))
    ids = _ids(h, w, 0)
    ids[1, 2] = 1  # another object moved in
    ids[3, 0] = -1  # background now
    out = reuse.update(np.full((h, w, 3), 5.0, np.float32), ids)
    np.testing.assert_array_equal(out[1, 2], 5.0)
    np.testing.assert_array_equal(out[3, 0], 5.0)
    np.testing.assert_allclose(out[0, 0], 1.0 + 0.2 * 4.0, rtol=1e-7)
    n = reuse.history_length
    assert n[1, 2] == 1 and n[3, 0] == 1 and n[0, 0] == 6


def test_reset_forgets_everything():
    reuse = TemporalReuse(4, 3, alpha=0.1, mode="same-pixel")
    for _ in range(3):
        reuse.update(np.zeros((3, 4, 3), np.float32), _ids(3, 4))
    reuse.reset()
    frame = np.full((3, 4, 3), 7.0, np.float32)
    np.testing.assert_array_equal(reuse.update(frame, _ids(3, 4)), frame)


def test_warmup_is_the_running_mean_until_1_over_n_reaches_alpha():
    """α_eff = max(α, 1/n): frames 1..1/α give the plain mean, later frames the EMA."""
    rng = np.random.default_rng(2)
    alpha = 0.2
    reuse = TemporalReuse(6, 5, alpha=alpha, mode="same-pixel", warmup=True)
    frames = rng.random((12, 5, 6, 3)).astype(np.float32)
    ref = None
    for k, f in enumerate(frames, start=1):
        out = reuse.update(f, _ids(5, 6))
        if k <= 5:
            np.testing.assert_allclose(out, frames[:k].astype(np.float64).mean(axis=0), rtol=2e-7, atol=1e-7)
            ref = frames[:k].astype(np.float64).mean(axis=0)
        else:
            ref = ref + alpha * (f - ref)
            np.testing.assert_allclose(out, ref, rtol=2e-7, atol=1e-7)


def test_warmup_lowers_the_error_of_the_first_frames():
    """Slow start of a fixed α: after 5 frames from reset its variance is far above σ²/5."""
    h, w, sigma = 64, 64, 0.1
    rng = np.random.default_rng(3)
    plain = TemporalReuse(w, h, alpha=0.05, mode="same-pixel")
    warm = TemporalReuse(w, h, alpha=0.05, mode="same-pixel", warmup=True)
    for _ in range(5):
        f = (0.5 + sigma * rng.standard_normal((h, w, 3))).astype(np.float32)
        a, b = plain.update(f, _ids(h, w)), warm.update(f, _ids(h, w))
    assert b.var() / sigma**2 == pytest.approx(1 / 5, rel=0.05)
    # fixed α: weights (1−α)^4, α(1−α)^3, … → Σw² ≈ 0.68
    weights = np.array([0.95**4] + [0.05 * 0.95**j for j in range(3, -1, -1)])
    assert a.var() / sigma**2 == pytest.approx(np.sum(weights**2), rel=0.05)


def test_mode_off_passes_through():
    reuse = TemporalReuse(4, 3, alpha=0.1, mode="off")
    f = np.random.default_rng(4).random((3, 4, 3)).astype(np.float32)
    reuse.update(np.zeros_like(f))
    np.testing.assert_array_equal(reuse.update(f), f)


def test_split_screen_left_half_plain_right_half_reused():
    h, w = 3, 9  # odd width: the left half is columns 0..3
    reuse = TemporalReuse(w, h, alpha=0.5, mode="same-pixel", split_screen=True)
    reuse.update(np.zeros((h, w, 3), np.float32), _ids(h, w))
    f = np.full((h, w, 3), 2.0, np.float32)
    out = reuse.update(f, _ids(h, w))
    np.testing.assert_array_equal(out[:, :4], 2.0)
    np.testing.assert_array_equal(out[:, 4:], 1.0)
    np.testing.assert_array_equal(reuse.history, 1.0)  # the history covers the whole frame
    np.testing.assert_array_equal(split_screen(f, reuse.history), out)


@pytest.mark.parametrize("mode", ["same-pixel", "motion"])
def test_nan_and_inf_do_not_enter_the_history(mode, static_view):
    h, w = 4, 5
    ids, mpos, poses, camera = static_view(h, w)
    reuse = TemporalReuse(w, h, alpha=0.2, mode=mode)
    for _ in range(3):
        reuse.update(np.ones((h, w, 3), np.float32), ids, mpos, poses, camera)
    bad = np.ones((h, w, 3), np.float32)
    bad[0, 0, 1] = np.nan
    bad[2, 3] = np.inf
    bad[1, 1, 0] = -np.inf
    out = reuse.update(bad, ids, mpos, poses, camera)
    assert reuse.nonfinite_last == 3 and np.all(np.isfinite(out))
    np.testing.assert_array_equal(out[0, 0], 1.0)  # the history, unchanged
    assert reuse.history_length[0, 0] == 3 and reuse.history_length[0, 1] == 4
    out = reuse.update(np.full((h, w, 3), 6.0, np.float32), ids, mpos, poses, camera)
    np.testing.assert_allclose(out, 1.0 + 0.2 * 5.0, rtol=1e-6)  # recovered everywhere at once


def test_nan_on_a_pixel_without_history_outputs_zero_then_restarts():
    reuse = TemporalReuse(2, 1, alpha=0.5, mode="same-pixel")
    first = np.array([[[np.nan, 0, 0], [1, 1, 1]]], np.float32)
    out = reuse.update(first, _ids(1, 2))
    np.testing.assert_array_equal(out[0, 0], 0.0)
    assert reuse.history_length[0, 0] == 0
    out = reuse.update(np.full((1, 2, 3), 4.0, np.float32), _ids(1, 2))
    np.testing.assert_array_equal(out[0, 0], 4.0)  # a fresh start, not 0.5·0 + 0.5·4
    np.testing.assert_array_equal(out[0, 1], 2.5)


def test_long_run_float32_history_is_the_correctly_rounded_ema():
    """10⁵ frames at α = 0.01: the float32 output stays within one float32 ulp of the same EMA
    computed in float64 (a float32 α·c + (1−α)·h drifts tens of ulps off, a float32
    running sum far more); a constant input converges to exactly float32(c)."""
    h, w, alpha = 2, 2, 0.01
    rng = np.random.default_rng(5)
    reuse = TemporalReuse(w, h, alpha=alpha, mode="same-pixel")
    ids = _ids(h, w)
    ref = None
    worst = 0.0
    noise = (0.3 + 0.05 * rng.standard_normal((1000, h, w, 3))).astype(np.float32)
    for k in range(100_000):
        f = noise[k % 1000]
        out = reuse.update(f, ids)
        ref = f.astype(np.float64) if ref is None else ref + alpha * (f - ref)
        if k % 97 == 0 or k > 99_000:
            worst = max(worst, float(np.max(np.abs(out - ref) / np.spacing(np.float32(ref)))))
    assert worst <= 1.0
    const = np.full((h, w, 3), 0.3, np.float32)
    for _ in range(5000):
        out = reuse.update(const, ids)
    np.testing.assert_array_equal(out, const)
