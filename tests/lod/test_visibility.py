"""Visibility map: formula per tile, the hard cases, and the map always finite and bounded."""

import math

import numpy as np
import pytest

from dpmhw.lod.csf import A_PEAK, F_PEAK, csf
from dpmhw.lod.visibility import INV_CONTRAST_MAX, LodSettingsError, VisibilitySettings, visibility_map

K = np.array([[1000.0, 0, 32], [0, 1000.0, 32], [0, 0, 1]])


def frame(value=0.5, size=32, depth=1.0):
    rad = np.full((size, size, 3), value, np.float32)
    return rad, np.full((size, size), depth, np.float32)


def assert_bounded(m, s):
    lo, hi = s.bounds
    assert np.all(np.isfinite(m.visibility))
    assert np.all((m.visibility >= lo - 1e-3) & (m.visibility <= hi + 1e-3))


def edge_tile(size=16, angle=0.0, offset=0.0):
    """A black/white straight edge through the tile."""
    y, x = np.mgrid[0:size, 0:size] + 0.5
    n = np.array([math.cos(angle), math.sin(angle)])
    lum = ((x - size / 2) * n[0] + (y - size / 2) * n[1] > offset).astype(np.float32)
    return np.repeat(lum[..., None], 3, 2)


def distance_for(f_cpd, d_px, depth, focal):
    """Viewer distance at which d_px pixels on a surface at `depth` subtend half a cycle of f."""
    theta = math.radians(1.0 / (2.0 * f_cpd))
    return d_px * depth / focal / math.tan(theta)


def test_uniform_tile_has_no_contrast_and_is_invisible():
    s = VisibilitySettings()
    for value in (0.0, 1e-6, 0.5, 1e4):
        rad, depth = frame(value)
        m = visibility_map(rad, depth, K, s)
        assert np.all(m.contrast == 0)
        assert np.all(m.visibility == pytest.approx(s.alpha_v - INV_CONTRAST_MAX))
        assert not m.visible.any()
        assert_bounded(m, s)


def test_zero_luminance_is_defined():
    rad, depth = frame(0.0)
    m = visibility_map(rad, depth, K)
    assert np.all(m.contrast == 0) and np.all(np.isfinite(m.visibility))


def test_single_bright_pixel_is_finite_full_contrast():
    s = VisibilitySettings()
    rad, depth = frame(0.0, size=16)
    rad[5, 9] = 1e6
    m = visibility_map(rad, depth, K, s)
    assert m.contrast[0, 0] == pytest.approx(1.0)
    assert_bounded(m, s)


def test_nan_pixels_are_skipped():
    s = VisibilitySettings()
    rad, depth = frame(0.5, size=16)
    rad[3, 3] = np.nan
    rad[7, 7] = np.inf
    depth[2, 2] = np.nan
    m = visibility_map(rad, depth, K, s)
    assert m.contrast[0, 0] == 0.0  # the rest is uniform
    rad[:] = np.nan
    m = visibility_map(rad, depth, K, s)
    assert m.contrast[0, 0] == 0.0
    assert_bounded(m, s)


def test_background_tile_has_no_frequency_and_is_invisible():
    rad = edge_tile()
    depth = np.full((16, 16), np.inf, np.float32)
    m = visibility_map(rad, depth, K)
    assert np.isnan(m.frequency_cpd[0, 0]) and m.visibility[0, 0] < 0


@pytest.mark.parametrize("f_cpd", [61.0, 1e3, 1e9])
def test_frequency_beyond_the_csf_is_invisible(f_cpd):
    rad = edge_tile()
    # the extremes of this edge are 8 px apart; 1e4 m is the largest distance the settings accept
    s = VisibilitySettings(viewer_distance_m=distance_for(f_cpd, 8.0, 1.0, 1000.0) if f_cpd < 1e8 else 1e4)
    m = visibility_map(rad, np.ones((16, 16), np.float32), K, s)
    assert m.frequency_cpd[0, 0] > 60
    assert m.visibility[0, 0] == pytest.approx(-1.0)  # S = 0, c = 1
    assert_bounded(m, s)


@pytest.mark.parametrize("angle", np.linspace(0, 2 * math.pi, 9)[:-1])
@pytest.mark.parametrize("offset", [-3.0, 0.0, 2.5])
def test_edge_at_peak_frequency_is_visible(angle, offset):
    rad = edge_tile(angle=angle, offset=offset)
    depth = np.full((16, 16), 0.8, np.float32)
    probe = visibility_map(rad, depth, K)  # where the extremes are, to place the viewer
    f0 = probe.frequency_cpd[0, 0]
    theta0 = 1.0 / (2 * f0)
    d_px = math.tan(math.radians(theta0)) * 1000.0 * 1.5 / 0.8
    s = VisibilitySettings(viewer_distance_m=distance_for(F_PEAK, d_px, 0.8, 1000.0))
    m = visibility_map(rad, depth, K, s)
    assert m.frequency_cpd[0, 0] == pytest.approx(F_PEAK, rel=1e-4)
    assert m.contrast[0, 0] == pytest.approx(1.0)
    assert m.visibility[0, 0] == pytest.approx(s.peak_sensitivity - 1.0, rel=1e-4)


def test_formula_per_tile():
    """V = S(f) − 1/c + α with f from the extremes' distance, depth and viewer distance."""
    s = VisibilitySettings(viewer_distance_m=1.2, alpha_v=3.0, peak_sensitivity=150.0, tile=16, block=2)
    rad = np.full((16, 16, 3), 0.2, np.float32)
    rad[0:2, 0:2] = 0.6  # brightest block, centre (1, 1)
    rad[8:10, 12:14] = 0.1  # darkest block, centre (9, 13)
    depth = np.full((16, 16), 2.0, np.float32)
    m = visibility_map(rad, depth, K, s)
    c = (0.6 - 0.1) / (0.6 + 0.1)
    d = math.hypot(8, 12)
    f = 1.0 / (2 * math.degrees(math.atan(d * 2.0 / 1000.0 / 1.2)))
    assert m.contrast[0, 0] == pytest.approx(c, rel=1e-5)
    assert m.frequency_cpd[0, 0] == pytest.approx(f, rel=1e-5)
    assert m.visibility[0, 0] == pytest.approx(csf(f, 150.0) - 1 / c + 3.0, rel=1e-4)


def test_partial_edge_tiles_and_shape():
    rad = np.random.default_rng(0).random((37, 50, 3)).astype(np.float32)
    m = visibility_map(rad, np.ones((37, 50), np.float32), K)
    assert m.visibility.shape == (3, 4)
    assert_bounded(m, VisibilitySettings())


@pytest.mark.parametrize("distance", [0, 0.0, -1.0, math.inf, math.nan, "far"])
def test_viewer_distance_zero_or_infinite_is_a_clear_error(distance):
    with pytest.raises(LodSettingsError, match="viewer_distance_m"):
        VisibilitySettings(viewer_distance_m=distance)


@pytest.mark.parametrize("field,value", [("tile", 0), ("block", 3), ("alpha_v", math.nan), ("peak_sensitivity", 0.5)])
def test_bad_settings_name_the_field(field, value):
    with pytest.raises(LodSettingsError, match=field):
        VisibilitySettings(**{field: value})


def test_random_frames_stay_finite_and_bounded():
    rng = np.random.default_rng(1)
    s = VisibilitySettings(viewer_distance_m=0.01)
    for _ in range(5):
        rad = (rng.standard_normal((48, 48, 3)) * 10 ** rng.uniform(-8, 8)).astype(np.float32)
        rad[rng.random((48, 48)) < 0.05] = np.nan
        depth = np.where(rng.random((48, 48)) < 0.3, np.inf, rng.uniform(1e-6, 1e6, (48, 48))).astype(np.float32)
        assert_bounded(visibility_map(rad, depth, K, s), s)
    assert A_PEAK > 0


def test_noise_floor_keeps_a_noisy_flat_tile_invisible_and_a_noisy_edge_visible():
    """1-spp-like noise (20 % of the mean per block) on a flat tile reads as detail without the
    noise floor and not with it; a real edge under the same noise stays visible."""
    rng = np.random.default_rng(3)
    rad, depth = frame(0.5, size=64)
    noisy = rad * (1 + 0.2 * rng.standard_normal((64, 64, 1))).astype(np.float32)
    on, off = VisibilitySettings(), VisibilitySettings(noise_k=0.0)
    assert visibility_map(noisy, depth, K, off).visible.all()
    assert not visibility_map(noisy, depth, K, on).visible.any()
    edge = np.tile(edge_tile(16), (4, 4, 1)) * 0.9 + 0.05
    noisy_edge = (edge * (1 + 0.2 * rng.standard_normal((64, 64, 1)))).astype(np.float32)
    m = visibility_map(noisy_edge, depth, K, on)
    assert m.visible.all() and (m.contrast > 0.5).all()
