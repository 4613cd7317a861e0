import json

import numpy as np
from typer.testing import CliRunner

from dpmhw.cli import _register, app
from dpmhw.render.integrator import PathIntegrator

from .test_integrator import ROOM


def test_render_command_writes_npy_png_and_metadata(tmp_path, make_scene):
    make_scene(ROOM.format(extra=""))  # writes tmp_path / scene.toml
    _register()
    runner = CliRunner()
    npy = tmp_path / "out" / "frame.npy"
    result = runner.invoke(app, ["render", str(tmp_path / "scene.toml"), "--spp", "3", "--seed", "5", "--frame", "10", "--out", str(npy)])
    assert result.exit_code == 0, result.output
    image = np.load(npy)
    assert image.shape == (24, 32, 3) and image.dtype == np.float32
    meta = json.loads((tmp_path / "out" / "frame.npy.json").read_text())
    assert meta["spp"] == 3 and meta["seed"] == 5 and abs(meta["time"] - 10 / 947.0) < 1e-12
    png = tmp_path / "frame.png"
    assert runner.invoke(app, ["render", str(tmp_path / "scene.toml"), "--spp", "1", "--out", str(png)]).exit_code == 0
    import cv2

    assert cv2.imread(str(png)).shape == (24, 32, 3)


def test_render_command_reports_bad_scene_without_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[render]\nwidth = 0\nheight = 10\n[camera]\n[[objects]]\n")
    _register()
    result = CliRunner().invoke(app, ["render", str(bad), "--out", str(tmp_path / "x.png")])
    assert result.exit_code == 2
    assert "render.width" in result.output and str(bad) in result.output


def test_stopping_keeps_finished_passes(make_scene):
    scene = make_scene(ROOM.format(extra=""))
    with PathIntegrator(scene) as integrator:
        passes = []
        frame = integrator.render(spp=50, progress=lambda done, total: passes.append(done), should_stop=lambda: len(passes) >= 3)
        full = integrator.render(spp=3)
    assert frame.spp == 3 and passes == [1, 2, 3]
    np.testing.assert_array_equal(frame.radiance, full.radiance)  # the same three passes, averaged


def test_bench_render_reports_rays_and_embree_share(tmp_path, make_scene):
    from dpmhw.benchmarks.render import bench_render, format_table

    make_scene(ROOM.format(extra="rigid_body = 2"))
    result = bench_render(str(tmp_path / "scene.toml"), frames=3)
    rays = result["rays_per_frame"]
    assert rays["camera"] == 32 * 24
    assert 0 < rays["continuation"] <= rays["camera"] * 3
    assert rays["shadow"] > 0
    assert 0 < result["inside_embree_fraction"] < 1
    assert result["raw_embree"]["closest_hit_rays_per_s"] > 0
    assert 0.8 * rays["shadow"] < result["raw_embree"]["replayed_rays"]["OCCLUDED"] < 1.25 * rays["shadow"]
    assert "Mrays/s" in format_table(result)


def test_render_command_jitters_by_default_and_names_a_bad_pixel_sampling(tmp_path, make_scene):
    scene = make_scene(ROOM.format(extra=""))
    _register()
    runner = CliRunner()
    out = tmp_path / "j.npy"
    assert runner.invoke(app, ["render", str(tmp_path / "scene.toml"), "--spp", "2", "--seed", "4", "--out", str(out)]).exit_code == 0
    with PathIntegrator(scene, pixel_sampling="jitter") as integrator:
        np.testing.assert_array_equal(np.load(out), integrator.render(spp=2, seed=4).radiance)
    result = runner.invoke(app, ["render", str(tmp_path / "scene.toml"), "--pixel-sampling", "corner", "--out", str(out)])
    assert result.exit_code == 2 and "--pixel-sampling" in result.output
