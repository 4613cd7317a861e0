"""`dpmhw bench lod`: the pixel-subset render is the plain render when it covers every pixel,
and a tiny end-to-end run writes honest rows and the figures."""

import json

import numpy as np
import pytest

from dpmhw.benchmarks.lod import METHODS, OMITTED, LodBenchConfig, render_pixels, run_lod
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene
from dpmhw.sequence import scaled_scene


@pytest.fixture(scope="module")
def small_integrator():
    integ = PathIntegrator(scaled_scene(load_scene("paper-dynamic"), 0.08), threads=2)
    yield integ
    integ.close()


def test_all_pixels_equal_the_plain_render_bit_for_bit(small_integrator):
    """Adaptation off means every pixel at 1 spp: the same image as the current pipeline."""
    integ = small_integrator
    plain = integ.render(time=0.01, seed=3, spp=2)
    n = integ.width * integ.height
    frame, counts = render_pixels(integ, np.arange(n), 2, 0.01, 3)
    assert np.array_equal(frame.radiance.reshape(plain.radiance.shape), plain.radiance)
    assert np.array_equal(frame.depth.reshape(plain.depth.shape), plain.depth)
    assert counts.primary == n
    again = integ.render(time=0.01, seed=3, spp=2)  # the integrator is left as it was
    assert np.array_equal(again.radiance, plain.radiance)


def test_a_subset_renders_those_pixels(small_integrator):
    integ = small_integrator
    plain = integ.render(time=0.0, seed=1)
    pixels = np.arange(0, integ.width * integ.height, 7)
    frame, counts = render_pixels(integ, pixels, 1, 0.0, 1)
    assert frame.radiance.shape == (1, len(pixels), 3)
    assert counts.primary == len(pixels)
    assert np.array_equal(frame.object_id.reshape(-1), plain.object_id.reshape(-1)[pixels])  # same camera rays
    assert np.array_equal(frame.depth.reshape(-1), plain.depth.reshape(-1)[pixels])


def test_tiny_run_writes_rows_and_figures(tmp_path):
    cfg = LodBenchConfig(scenes=("dpm-bunny",), scale=0.1, frames=4, eval_frames=1, ref_spp=4)
    result = run_lod(cfg, cache_dir=tmp_path / "cache", out_dir=tmp_path)
    rows = result["rows"]
    assert [r["method"] for r in rows] == list(METHODS) and "shading-rate" in OMITTED
    for r in rows:
        for key in ("scene", "method", "frame_ms", "rays_per_frame", "triangles", "psnr_db", "ssim", "flip"):
            assert key in r
        assert r["frame_ms"] > 0 and 0 <= r["flip"] <= 1 and np.isfinite(r["psnr_db"])
        if r["ray_budget"] is not None:
            assert r["rays_per_frame"] <= r["ray_budget"]
    none = next(r for r in rows if r["method"] == "none")
    assert none["ray_budget"] is None and none["triangles"] > 60000
    json.dumps(rows)
    assert {p.split("/")[-1] for p in result["files"]} == {"lod-map-dpm-bunny.png", "lod-ms-vs-error.png"}
