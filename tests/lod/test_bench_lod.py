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
