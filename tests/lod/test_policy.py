"""Tile policy: levels, hysteresis, refresh, and the ray budget (never exceeded)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from dpmhw.lod.policy import PolicySettings, TilePolicy, allocate, rays_per_sample_bound, tile_pixel_counts
from dpmhw.lod.visibility import LodSettingsError, VisibilityMap, VisibilitySettings, visibility_map
from dpmhw.lod.csf import F_PEAK

K = np.array([[1000.0, 0, 32], [0, 1000.0, 32], [0, 0, 1]])


def vmap(v, tile=16):
    v = np.asarray(v, np.float32)
    return VisibilityMap(v, np.full(v.shape, 8.0, np.float32), np.full(v.shape, 0.5, np.float32), tile)


def test_levels_from_thresholds():
    pol = TilePolicy(16, 64, PolicySettings(thresholds=(0, 20, 50), dilate=0))
    d = pol.decide(vmap([[-5.0, 10.0, 30.0, 80.0]]))
    assert d.rate.tolist() == [[0, 4, 2, 1]]
    assert d.spp.tolist() == [[0, 1, 2, 4]]
    assert d.shaded_pixels.tolist() == [[0, 16, 64, 256]]
    assert d.ray_bound == (16 * 1 + 64 * 2 + 256 * 4) * 4


def test_switches_off_give_the_current_pipeline():
    """Both adaptations off: every tile with anything visible at full rate and 1 spp; with an
    all-visible map that is exactly the plain 1-spp frame."""
    pol = TilePolicy(32, 32, PolicySettings(shading_rate=False, adaptive_spp=False, dilate=0))
    d = pol.decide(vmap([[1.0, 60.0], [25.0, 99.0]]))
    assert np.all(d.rate == 1) and np.all(d.spp == 1)
    assert np.array_equal(d.pixel_spp(32, 32), np.ones((32, 32)))


def test_hysteresis_holds_a_level_until_v_drops_by_the_margin():
    pol = TilePolicy(16, 16, PolicySettings(thresholds=(0, 20, 50), hysteresis=5, dilate=0))
    seq = [60, 48, 46, 44.9, 21, 14.9, 16, 19, 21]
    rates = [int(pol.decide(vmap([[v]])).rate[0, 0]) for v in seq]
    assert rates == [1, 1, 1, 2, 2, 4, 4, 4, 2]


def test_dilation_spreads_visibility_to_neighbours():
    v = np.full((5, 5), -100.0)
    v[2, 2] = 60
    d = TilePolicy(80, 80, PolicySettings(dilate=1, refresh_frames=10**6)).decide(vmap(v))
    assert (d.rate == 1).sum() == 9 and d.rate[2, 2] == 1 and d.rate[0, 0] == 0


def test_uniform_tiles_are_never_refined():
    """A tile with no contrast keeps its history; the only work it ever gets is the staggered
    refresh at the lowest level (1/4 rate, 1 spp), once per refresh period."""
    rad = np.full((64, 64, 3), 0.4, np.float32)
    depth = np.ones((64, 64), np.float32)
    for distance in (0.3, 1.5, 20.0):
        m = visibility_map(rad, depth, K, VisibilitySettings(viewer_distance_m=distance))
        pol = TilePolicy(64, 64, PolicySettings(refresh_frames=4))
        refreshes = np.zeros((4, 4), int)
        for _ in range(40):
            d = pol.decide(m)
            assert np.all(d.rate[~d.refreshed] == 0) and np.all(d.spp[~d.refreshed] == 0)
            assert np.all(d.rate[d.refreshed] == 4) and np.all(d.spp[d.refreshed] == 1)
            refreshes += d.refreshed
        assert refreshes.min() >= 40 // 8 and refreshes.max() <= 40 // 4


@pytest.mark.parametrize("angle", np.linspace(0, math.pi, 5))
def test_high_contrast_edge_at_peak_frequency_is_always_refined(angle):
    y, x = np.mgrid[0:16, 0:16] + 0.5
    lum = ((x - 8) * math.cos(angle) + (y - 8) * math.sin(angle) > 0.3).astype(np.float32)
    rad = np.repeat(lum[..., None], 3, 2)
    depth = np.ones((16, 16), np.float32)
    probe = visibility_map(rad, depth, K)
    d_px = math.tan(math.radians(1 / (2 * probe.frequency_cpd[0, 0]))) * 1000 * 1.5
    distance = d_px / 1000 / math.tan(math.radians(1 / (2 * F_PEAK)))
    m = visibility_map(rad, depth, K, VisibilitySettings(viewer_distance_m=distance))
    assert m.frequency_cpd[0, 0] == pytest.approx(F_PEAK, rel=1e-4)
    d = TilePolicy(16, 16).decide(m)
    assert d.rate[0, 0] == 1 and d.spp[0, 0] == 4


def test_allocation_prefers_first_samples_then_visibility():
    levels = np.array([3, 3, 1, 0])
    prio = np.array([10.0, 50.0, 1.0, 99.0])
    shaded = np.full(4, 10)
    # budget for 3 first samples + 1 second sample (rays_per_sample 1)
    assert allocate(levels, prio, shaded, 40, 1).tolist() == [1, 2, 1, 0]
    assert allocate(levels, prio, shaded, 29, 1).tolist() == [1, 1, 0, 0]
    assert allocate(levels, prio, shaded, None, 1).tolist() == levels.tolist()


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), budget=st.integers(0, 2_000_000), rate=st.booleans(), spp=st.booleans(),
       bounces=st.integers(0, 4), mis=st.booleans(), free=st.sampled_from([0, 4]), boost=st.booleans())
def test_ray_budget_is_never_exceeded(seed, budget, rate, spp, bounces, mis, free, boost):
    rng = np.random.default_rng(seed)
    rps = rays_per_sample_bound(bounces, mis)
    pol = TilePolicy(100, 130, PolicySettings(shading_rate=rate, adaptive_spp=spp, ray_budget=budget, rays_per_sample=rps,
                                              refresh_frames=2, free_rate=free))
    pixels = tile_pixel_counts(100, 130, 16)
    for _ in range(4):
        d = pol.decide(vmap(rng.uniform(-30, 120, (7, 9))), rng.random((7, 9)) < 0.3 if boost else None)
        assert d.ray_bound <= budget
        assert d.ray_bound == (d.spp.astype(np.int64) * d.shaded_pixels).sum() * rps
        assert np.all(d.shaded_pixels <= pixels)
        assert np.all((d.spp == 0) == (d.rate == 0))


def test_partial_tiles_count_every_phase_and_free_tiles_cost_nothing():
    """A 3×3 edge tile at ½ rate holds up to 2×2 pixels of one phase (⌈9/4⌉ = 3 would not
    bound it); ¼ tiles are free when the base frame shades them; boosted tiles take the top level."""
    pol = TilePolicy(19, 19, PolicySettings(dilate=0, free_rate=4))
    d = pol.decide(vmap([[30.0, 30.0], [10.0, 30.0]]))
    assert d.rate.tolist() == [[2, 2], [4, 2]]
    assert d.shaded_pixels.tolist() == [[64, 16], [0, 4]]  # 16×3 → 8·2; 3×3 → 2·2; the ¼ tile: free
    d = TilePolicy(32, 32, PolicySettings(dilate=1)).decide(vmap([[-50.0, -50.0], [-50.0, -50.0]]),
                                                         np.array([[True, False], [False, False]]))
    assert d.rate.tolist() == [[1, 0], [0, 0]]  # the boost is current: not dilated


def test_rays_per_sample_bound():
    assert rays_per_sample_bound(1, False) == 4  # camera, 2 shadow, 1 continuation
    assert rays_per_sample_bound(1, True) == 6
    assert rays_per_sample_bound(0, False) == 2


def test_settings_errors_name_the_field():
    with pytest.raises(LodSettingsError, match="thresholds"):
        PolicySettings(thresholds=(5, 1, 9))
    with pytest.raises(LodSettingsError, match="ray_budget"):
        PolicySettings(ray_budget=-1)
    with pytest.raises(LodSettingsError, match="visibility"):
        TilePolicy(32, 32).decide(vmap(np.zeros((1, 1))))


def test_a_tight_budget_takes_turns_instead_of_starving_tiles():
    """Budget for half the visible tiles at 1 spp: within two frames every tile was shaded."""
    v = np.linspace(10, 90, 16).reshape(4, 4)
    pol = TilePolicy(64, 64, PolicySettings(shading_rate=False, ray_budget=8 * 256 * 4, rays_per_sample=4, dilate=0))
    seen = np.zeros((4, 4), bool)
    for _ in range(2):
        d = pol.decide(vmap(v))
        assert (d.spp > 0).sum() == 8 and d.ray_bound <= 8 * 256 * 4
        seen |= d.spp > 0
    assert seen.all()


def test_boosted_tiles_win_the_budget_over_tiles_that_waited_longer():
    pol = TilePolicy(16, 32, PolicySettings(dilate=0, shading_rate=False, adaptive_spp=False, ray_budget=256 * 4,
                                            refresh_frames=10**6))
    for _ in range(3):  # tile 1 asks every frame and waits its turn (budget: one full tile)
        d = pol.decide(vmap([[60.0, 60.0]]))
    d = pol.decide(vmap([[60.0, 60.0]]), np.array([[True, False]]))
    assert d.spp.tolist() == [[1, 0]]


def test_keep_refines_the_most_visible_tiles_and_keeps_them_under_a_tight_budget():
    """With a base that shades every tile (the refiner's case) the budget goes to the most
    visible tiles, and a tile granted last frame keeps its grant unless another beats it by
    more than `keep` (its native history continues instead of lapsing between turns)."""
    top = np.arange(16).reshape(4, 4) % 2 == 0
    pol = TilePolicy(64, 64, PolicySettings(shading_rate=False, adaptive_spp=False, ray_budget=8 * 256 * 4,
                                            rays_per_sample=4, dilate=0, keep=20.0))
    for frame in range(3):
        assert ((pol.decide(vmap(np.where(top, 60.0, 40.0))).spp > 0) == top).all()  # every frame the same tiles
    # the granted ones fall below the others, but by less than keep: they keep it
    assert ((pol.decide(vmap(np.where(top, 25.0, 40.0))).spp > 0) == top).all()
    # by more: the others take over, and then keep it themselves
    assert ((pol.decide(vmap(np.where(top, 15.0, 40.0))).spp > 0) == ~top).all()
    assert ((pol.decide(vmap(np.where(top, 45.0, 40.0))).spp > 0) == ~top).all()


def test_boosted_tiles_are_ordered_and_sampled_by_what_the_map_saw():
    v = np.array([[30.0, 80.0, -50.0, 60.0]])
    boost = np.ones((1, 4), bool)
    one_tile = 256 * 4
    d = TilePolicy(16, 64, PolicySettings(dilate=0, adaptive_spp=False, ray_budget=2 * one_tile, keep=20.0)).decide(vmap(v), boost)
    assert d.spp.tolist() == [[0, 1, 0, 1]]  # the two most visible of four boosted tiles
    d = TilePolicy(16, 64, PolicySettings(dilate=0, keep=20.0)).decide(vmap(v), boost)
    assert d.rate.tolist() == [[1, 1, 1, 1]]  # boosted: full rate
    assert d.spp.tolist() == [[2, 4, 1, 4]]  # samples from the map's level there, at least 1
