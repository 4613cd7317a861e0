"""Pixel jitter: the converged pixel is the integral over its footprint (box filter)."""

import numpy as np
import pytest

from dpmhw.render.integrator import PathIntegrator

# An emitter covering world x ≥ 0 seen head-on (turned to face the camera); the camera (image x
# along world x) maps x = 0 onto the centre line of pixel column 3 (cx = 3), so that column is
# exactly half covered. (Until session 7 the quad lay in the camera's plane and the camera sat on
# its edge: every ray hit it at t = 0 or missed, which only the robust flag's inclusive edge test
# resolved this way.)
EDGE = """
[render]
width = 8
height = 6
max_bounces = 0

[camera]
fx = 8.0
fy = 8.0
cx = 3.0
cy = 2.5
position = [0.0, 0.0, 1.0]
look_at = [0.0, 0.0, 0.0]

[[objects]]
name = "emitter"
shape = "quad"
size = [4.0, 4.0]
position = [2.0, 0.0, 0.0]
rotation = [90.0, 0.0, 0.0]
albedo = 0.0
emission = [1.0, 1.0, 1.0]
"""


def _render(scene, mode, spp, seed=0, threads=2):
    with PathIntegrator(scene, threads=threads, pixel_sampling=mode) as integrator:
        return integrator.render(seed=seed, spp=spp)


def test_half_covered_pixel_converges_to_the_covered_fraction(make_scene):
    scene = make_scene(EDGE)
    centre = _render(scene, "centre", 4).radiance[..., 0]
    # centre sampling aliases: every pixel is 0 or 1, the half-covered column included
    assert set(np.unique(centre)) <= {0.0, 1.0}
    np.testing.assert_array_equal(centre[:, :3], 0.0)
    np.testing.assert_array_equal(centre[:, 4:], 1.0)
    jitter = _render(scene, "jitter", 1024).radiance[..., 0]
    # the edge column converges to 1/2 (binomial noise at 1024 spp: σ ≈ 0.016), the rest stay 0 or 1
    np.testing.assert_allclose(jitter[:, 3], 0.5, atol=0.06)
    np.testing.assert_array_equal(jitter[:, :3], 0.0)
    np.testing.assert_array_equal(jitter[:, 4:], 1.0)


def test_jitter_is_deterministic_at_any_thread_count_and_differs_by_seed(make_scene):
    scene = make_scene(EDGE)
    a = _render(scene, "jitter", 16, seed=3, threads=2)
    b = _render(scene, "jitter", 16, seed=3, threads=1)
    c = _render(scene, "jitter", 16, seed=4, threads=2)
    assert np.array_equal(a.radiance, b.radiance)
    assert not np.array_equal(a.radiance, c.radiance)


def test_unknown_pixel_sampling_is_rejected(make_scene):
    with pytest.raises(ValueError, match="pixel_sampling"):
        PathIntegrator(make_scene(EDGE), pixel_sampling="stratified")


def test_jitter_staged_path_matches_the_fused_one(make_scene):
    """The embreex fallback's stage-by-stage path jitters the same rays as the fused kernel."""
    scene = make_scene(EDGE)
    frames = []
    for fused in (True, False):
        with PathIntegrator(scene, threads=2, pixel_sampling="jitter") as integrator:
            integrator.fused = fused
            frames.append(integrator.render(seed=2, spp=8))
    assert np.array_equal(frames[0].radiance, frames[1].radiance)
