"""`dpmhw bench quality` end to end at a tiny size: structure, caching, figures."""

import dataclasses
import json

import numpy as np
import pytest

from dpmhw.benchmarks.quality import QualityConfig, format_table, run_quality
from dpmhw.benchmarks.references import ReferenceCache, scene_digest
from dpmhw.scene_file import load_scene
from dpmhw.sequence import scaled_scene

TINY = dataclasses.replace(
    QualityConfig.quick(), scale=1 / 32, ref_spp=24, dynamic_ref_spp=8, static_spp=(1, 2, 4, 8), spp_repeats=1, alphas=(0.5, 0.25),
    eval_frames=2, dynamic_fps=(947.0, 60.0), dynamic_eval_times=(0.02, 0.04), parts=("static", "dynamic"),
)


def test_quality_report_runs_caches_references_and_writes_figures(tmp_path):
    cache = tmp_path / "cache"
    result = run_quality(TINY, cache_dir=cache, out_dir=tmp_path / "figs")
    static = result["static"]
    assert (static["width"], static["height"]) == (32, 24)
    plain = [r for r in static["rows"] if r["kind"] == "plain"]
    reuse = {r["label"]: r for r in static["rows"] if r["kind"] == "reuse"}
    assert [r["spp"] for r in plain] == [1, 2, 4, 8]
    assert plain[-1]["psnr"] > plain[0]["psnr"] + 3  # more samples, less error
    r = reuse["1 spp + same-pixel α=0.25"]
    assert r["psnr"] > plain[0]["psnr"] and r["equivalent_spp"] > 2 and r["predicted_spp"] == 7
    # warm-up reaches the steady state sooner than a fixed α (the slow start)
    assert reuse["1 spp + same-pixel α=0.25 +warmup"]["frames_to_within_0.5dB"] <= r["frames_to_within_0.5dB"]
    conv = static["convergence"]
    early = lambda label: np.mean([p for k, p in conv[label] if 2 <= k <= 4])  # noqa: E731
    assert early("same-pixel α=0.25 +warmup") > early("same-pixel α=0.25") + 0.3
    # on a static scene motion mode is same-pixel mode, bit for bit
    assert reuse["1 spp + motion α=0.5"]["psnr"] == reuse["1 spp + same-pixel α=0.5"]["psnr"]
    for row in static["rows"]:
        assert row["total_ms"] == pytest.approx(row["render_ms"] + row["reuse_ms"] + row["post_ms"])
    tl = {t["fps"]: t for t in result["dynamic"]["timelines"]}
    assert tl[947.0]["eval_frames"] == [19, 38] and tl[60.0]["eval_frames"] == [1, 2]
    # steady state before the first eval: 8 / min α = 32 frames of history, on both timelines
    assert tl[947.0]["start_frame"] == 19 - 32 and tl[60.0]["start_frame"] == 1 - 32 and tl[60.0]["frames"] == 34
    assert len(tl[947.0]["rows"]) == 1 + 2 * 2 * 2  # plain + modes × alphas × warm-up
    assert all(len(r["psnr_samples"]) == 2 for r in tl[947.0]["rows"])
    refs = result["references"]
    assert refs["rendered"] == 1 + 2 + 2 and refs["cache_hits"] == 0
    meta = [json.loads(p.read_text()) for p in cache.glob("*.json")]
    assert {m["spp"] for m in meta} == {24, 8} and all("equivalent_command" in m for m in meta)
    names = {p.name for p in (tmp_path / "figs").iterdir()}
    assert {"static_strip.png", "speed_vs_psnr.png", "static_convergence.png", "dynamic_psnr_over_time.png"} <= names
    import cv2

    assert cv2.imread(str(tmp_path / "figs" / "static_strip.png")).shape == (24, 4 * 32, 3)
    text = format_table(result)
    assert "Table 1" in text and "eq.spp" in text
    json.dumps(result)  # serialisable
    again = run_quality(dataclasses.replace(TINY, parts=("static",)), cache_dir=cache)
    assert again["references"] == dict(cache_dir=str(cache), rendered=0, cache_hits=1)
    np.testing.assert_equal(again["static"]["rows"][0]["psnr"], static["rows"][0]["psnr"])  # deterministic


def test_reference_key_changes_with_what_changes_the_image(tmp_path):
    scene = scaled_scene(load_scene("paper-static"), 1 / 64)
    assert scene_digest(scene) == scene_digest(scaled_scene(load_scene("paper-static"), 1 / 64))
    assert scene_digest(scene) != scene_digest(scaled_scene(load_scene("paper-static"), 1 / 32))
    assert scene_digest(scene) != scene_digest(scaled_scene(load_scene("paper-dynamic"), 1 / 64))
    cache = ReferenceCache(tmp_path)
    a = cache.get(scene, "paper-static", 0.0, 2)
    b = cache.get(scene, "paper-static", 0.0, 2)
    c = cache.get(scene, "paper-static", 0.0, 3)
    assert cache.rendered == 2 and cache.hits == 1
    np.testing.assert_array_equal(a["radiance"], b["radiance"])
    assert not np.array_equal(a["radiance"], c["radiance"])


@pytest.mark.parametrize("args, message", [(["--part", "both"], "--part"), (["--dynamic-times", "0.2,x"], "--dynamic-times")])
def test_bench_quality_cli_rejects_bad_options_before_rendering(args, message, tmp_path):
    from typer.testing import CliRunner

    from dpmhw.cli import _register, app

    _register()
    result = CliRunner().invoke(app, ["bench", "quality", "--cache-dir", str(tmp_path), *args])
    assert result.exit_code == 2 and message in result.output
    assert not any(tmp_path.iterdir())  # nothing was rendered


def test_native_rows_are_flat_and_cover_every_method(tmp_path):
    cfg = dataclasses.replace(TINY, parts=("native",), native_scale=1 / 16, native_ref_spp=8, native_static_ref_spp=8,
                              native_static_frames=3, native_eval_frames=1, native_eval_times=(0.05,), native_history_frames=2)
    result = run_quality(cfg, cache_dir=tmp_path / "cache", out_dir=tmp_path / "figs")
    scenes = result["native"]["scenes"]
    assert [s["kind"] for s in scenes] == ["static", "dynamic", "glossy"]
    keys = {"scene", "method", "shading_scale", "filter", "alpha", "frame_ms", "psnr_db", "ssim", "flip", "pixel_sampling",
            "frame_cpu_ms", "psnr_db_corrected", "psnr_db_glossy", "psnr_db_roughness_edge", "ref_psnr_cap_db",
            "psnr_db_jittered_ref", "psnr_db_edges_jittered_ref"}
    for sc, count in zip(scenes, (14, 17, 9)):
        assert (sc["width"], sc["height"]) == (64, 48)
        rows = sc["rows"]
        assert len(rows) == count and {1.0, 0.25} <= {r["shading_scale"] for r in rows}
        adaptive = [r for r in rows if "+ adaptive" in r["method"] and r["pixel_sampling"] == "centre"]
        assert [r["shading_scale"] for r in adaptive] == ([] if sc["kind"] == "glossy" else [0.5, 0.25])
        assert all(r["adaptive_rays"] > 0 for r in adaptive)
        assert {r["pixel_sampling"] for r in rows} == ({"centre", "jitter"} if sc["kind"] == "dynamic" else {"centre"})
        for r in rows:
            assert keys <= set(r)
            assert not any(isinstance(v, (dict, list)) for v in r.values())
            assert 0 <= r["flip"] <= 1 and np.isfinite(r["psnr_db"]) and r["frame_ms"] > 0 and r["frame_cpu_ms"] > 0
            # the reference's own noise only ever adds error: removing it raises the PSNR
            assert r["psnr_db_corrected"] >= r["psnr_db"] - 1e-9
            assert (r["psnr_db_jittered_ref"] is not None) == (sc["kind"] == "dynamic")
    glossy = {r["method"]: r for r in scenes[2]["rows"]}
    assert glossy["1 spp + lobe"]["psnr_db_roughness_edge"] is not None  # the striped tile's bands are in view
    rows = {r["method"]: r for r in scenes[0]["rows"]}
    assert rows["native + reuse 0.2 + off"]["psnr_db"] > rows["1 spp + off"]["psnr_db"]
    assert rows["1 spp + off"]["psnr_db_roughness_edge"] is None  # one roughness per object there
    names = {p.name for p in (tmp_path / "figs").iterdir()}
    assert {"native_speed_vs_psnr.png", "native_paper-static_strip.png",
            "native_glossy-roughness_highlight_normal_vs_lobe.png"} <= names
    assert "FLIP" in format_table(result)
