"""`PathIntegrator.render_pixels`: pooled working arrays never leak between calls, bad indices are refused."""

from __future__ import annotations

import numpy as np
import pytest

from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene


@pytest.fixture(scope="module")
def bunny():
    scene = load_scene("dpm-bunny").at_size(64, 48)  # a moving bunny in front of a static wall
    return scene, scene.object_poses(0.3)


def test_results_do_not_depend_on_earlier_calls_and_the_frame_is_untouched(bunny):
    scene, poses = bunny
    small = np.arange(100, 64 * 48, 5)
    large = np.arange(0, 64 * 48, 2)
    with PathIntegrator(scene, threads=2) as fresh:
        want_small = fresh.render_pixels(fresh.camera, small, poses, seed=3, spp=2)
        want_frame = fresh.render(time=0.3, seed=1, poses=poses).radiance
    with PathIntegrator(scene, threads=2) as r:
        r.render(time=0.3, seed=1, poses=poses)
        want_large = r.render_pixels(r.camera, large, poses, seed=3)  # the pool grows to the large list
        got_small = r.render_pixels(r.camera, small, poses, seed=3, spp=2)  # a view of its first rows
        assert r.counts.primary == len(small)
        got_large = r.render_pixels(r.camera, large, poses, seed=3)
        got_frame = r.render(time=0.3, seed=1, poses=poses).radiance
        static = r._static_primary_hits  # the frame camera's cached static hits: the same paths as tracing them here
        with_cache = r.render_pixels(r.camera, small, poses, seed=3, spp=2, static_hits=static)
    assert np.isfinite(got_small).all() and got_small.max() > 0
    assert np.array_equal(got_small, want_small)
    assert np.array_equal(got_large, want_large)
    assert np.array_equal(got_frame, want_frame)
    assert np.array_equal(with_cache, want_small)


def test_bad_and_empty_pixel_lists(bunny):
    scene, poses = bunny
    with PathIntegrator(scene, threads=1) as r:
        assert r.render_pixels(r.camera, np.array([], np.int64), poses, seed=0).shape == (0, 3)
        for bad in ([64 * 48], [-1, 5]):
            with pytest.raises(ValueError, match="pixels"):
                r.render_pixels(r.camera, np.array(bad), poses, seed=0)
        with pytest.raises(ValueError, match="spp"):
            r.render_pixels(r.camera, np.array([1]), poses, seed=0, spp=0)
