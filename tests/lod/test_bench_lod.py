"""`dpmhw bench lod` through the loop's pipeline: flat rows for every method, budget held, figures."""

from __future__ import annotations

import json

import numpy as np

from dpmhw.benchmarks.lod import METHODS, LodBenchConfig, run_lod


def test_tiny_run_writes_rows_and_figures(tmp_path):
    cfg = LodBenchConfig(scenes=("dpm-bunny",), scale=0.125, eval_times=(0.1,), history_frames=3, ref_spp=4, rays=20_000)
    result = run_lod(cfg, cache_dir=tmp_path / "cache", out_dir=tmp_path)
    rows = result["rows"]
    assert [r["method"] for r in rows] == list(METHODS)
    for r in rows:
        for key in ("scene", "method", "frame_ms", "rays_per_frame", "triangles", "psnr_db", "ssim", "flip", "psnr_db_object"):
            assert key in r
        assert r["frame_ms"] > 0 and 0 <= r["flip"] <= 1 and np.isfinite(r["psnr_db"])
        if r["ray_budget"] is not None:
            assert r["lod_rays"] <= r["ray_budget"]
        else:
            assert r["lod_rays"] == 0
    by = {r["method"]: r for r in rows}
    assert by["none"]["shading_scale"] == 1.0 and by["quarter"]["shading_scale"] == 0.25
    assert by["moving"]["lod_rays"] > 0  # the bunny moves: its pixels get native paths
    assert by["none"]["triangles"] > 60000
    json.dumps(rows)
    assert {p.split("/")[-1] for p in result["files"]} == {"lod-map-dpm-bunny.png", "lod-ms-vs-error.png"}


def test_mesh_lod_methods_switch_on_a_long_throw(tmp_path):
    """dpm-bunny@80 at 128×96 (f 187 px): the bunny beyond its pop-safe depth (57 m here), so mesh-LOD and all
    run coarser levels (fewer triangles); at 1 m (the test above) they do not."""
    cfg = LodBenchConfig(scenes=("dpm-bunny@80",), scale=0.125, eval_times=(0.1,), history_frames=3, ref_spp=4, rays=20_000)
    by = {r["method"]: r for r in run_lod(cfg, cache_dir=tmp_path / "cache")["rows"]}
    for m in ("mesh-LOD", "all"):
        assert by[m]["lod_switches"] >= 1 and by[m]["triangles"] < by["none"]["triangles"]
        assert int(by[m]["mesh_levels"].split(",")[0]) >= 1
    assert by["none"]["lod_switches"] == 0 and by["none"]["mesh_levels"] == ""
