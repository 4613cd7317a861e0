"""Temporal reuse on real (tiny) renders, and `dpmhw render --frames … --reuse …`."""

import json
import textwrap

import numpy as np
import pytest
from scene_texts import lit_room
from typer.testing import CliRunner

from dpmhw.cli import _register, app
from dpmhw.render.integrator import PathIntegrator
from dpmhw.reconstruct.reuse import TemporalReuse
from dpmhw.scene_file import load_scene
from dpmhw.sequence import run_sequence, scaled_scene

SCENE = lit_room("""
[[objects]]
name = "ball"
shape = "sphere"
radius = 0.2
position = [0.0, 0.3, 0.1]
albedo = [0.5, 0.5, 0.5]
motion = {{ rotate_axis = [0.0, 1.0, 0.0], rotate_deg_per_s = {spin}, velocity = [{vx}, 0.0, 0.0] }}
""", width=32, height=24, f=26.0, cx=15.5, cy=11.5, max_bounces=1, fps=100.0)


@pytest.fixture
def scene_path(tmp_path):
    def make(vx=0.5, spin=200.0):
        path = tmp_path / "scene.toml"
        path.write_text(textwrap.dedent(SCENE.format(vx=vx, spin=spin)))
        return path

    return make


def test_reprojected_pixels_see_the_same_surface_point_last_frame(scene_path):
    """End to end on the renderer's G-buffer: a ball moving 0.5 m/s and spinning 200°/s, two
    frames 50 ms apart (≈ 0.8 px of translation, 10° of spin) at 64×48. Where motion mode fetched all-matching bilinear history, the previous frame's model
    positions interpolated at X_{i−1} equal this frame's model positions to a small fraction of a
    pixel's footprint; the same-pixel assumption misses by the motion."""
    scene = scaled_scene(load_scene(scene_path()), 2)
    from dpmhw.reconstruct.reuse import reproject

    with PathIntegrator(scene) as integ:
        t0, t1 = 0.0, 0.05
        p0, p1 = scene.object_poses(t0), scene.object_poses(t1)
        f0, f1 = integ.render(time=t0, poses=p0), integ.render(time=t1, poses=p1)
        xy, ok = reproject(f1.object_id, f1.model_position, p0, integ.camera, integ.camera)
    ball = 2
    H, W = f1.object_id.shape
    x0, y0 = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
    inside = ok & (x0 >= 0) & (y0 >= 0) & (x0 < W - 1) & (y0 < H - 1)
    ids_prev = f0.object_id
    sel = np.flatnonzero(inside & (f1.object_id.ravel() == ball))
    sel = sel[np.all([ids_prev[y0[sel] + j, x0[sel] + i] == ball for j in (0, 1) for i in (0, 1)], axis=0)]
    assert sel.size > 40
    fx, fy = (xy[sel, 0] - x0[sel])[:, None], (xy[sel, 1] - y0[sel])[:, None]
    m = f0.model_position
    interp = ((1 - fx) * (1 - fy) * m[y0[sel], x0[sel]] + fx * (1 - fy) * m[y0[sel], x0[sel] + 1]
              + (1 - fx) * fy * m[y0[sel] + 1, x0[sel]] + fx * fy * m[y0[sel] + 1, x0[sel] + 1])
    here = f1.model_position.reshape(-1, 3)[sel]
    footprint = 1.6 / 52.0  # metres per pixel at the ball's distance, roughly
    err = np.linalg.norm(interp - here, axis=1)
    assert np.median(err) < 0.05 * footprint
    same_pixel = np.linalg.norm(f0.model_position.reshape(-1, 3)[sel] - here, axis=1)
    assert np.median(same_pixel) > 0.3 * footprint


def test_static_render_sequence_converges_towards_the_many_spp_image(scene_path):
    """Same-pixel reuse of 1-spp frames of a static scene lands closer to a 32-spp render than
    any single 1-spp frame, by about the EMA's predicted factor in MSE (α = 0.2 → 1/9)."""
    scene = load_scene(scene_path(vx=0.0, spin=0.0))
    with PathIntegrator(scene) as integ:
        ref = integ.render(seed=1000, spp=32).radiance
        reuse = TemporalReuse(32, 24, alpha=0.2, mode="same-pixel")
        mse_reuse, mse_plain = [], []
        for step in run_sequence(integ, scene, 45, [reuse], seed=0):
            if step.index >= 20:
                mse_reuse.append(np.mean((step.outputs[0] - ref) ** 2))
                mse_plain.append(np.mean((step.frame.radiance - ref) ** 2))
    ratio = np.mean(mse_reuse) / np.mean(mse_plain)
    assert 0.11 < ratio < 0.18  # (1/9 + 1/32) / (1 + 1/32) ≈ 0.14: the reference has 1/32 of a sample's variance


def test_scaled_scene_keeps_the_view():
    scene = load_scene("paper-static")
    small = scaled_scene(scene, 0.25)
    assert (small.render.width, small.render.height) == (256, 192)
    assert small.camera.K[0, 0] == pytest.approx(275.0) and small.camera.K[0, 2] == pytest.approx((512 + 0.5) / 4 - 0.5)
    from dpmhw.render.cameras import PinholeCamera

    big = PinholeCamera(scene.camera.K, scene.camera.dist, 1024, 768, scene.camera.pose)
    little = PinholeCamera(small.camera.K, small.camera.dist, 256, 192, scene.camera.pose)
    pts = np.array([[0.1, 0.3, 0.0], [-0.3, 0.6, -0.2]])
    # pixel edges coincide: (u + 0.5) scales by the factor
    np.testing.assert_allclose((little.project(pts)[0] + 0.5) * 4, big.project(pts)[0] + 0.5, atol=1e-9)


def test_render_frames_cli_matches_the_library_and_writes_every_frame(scene_path, tmp_path):
    path = scene_path()
    _register()
    out = tmp_path / "last.npy"
    args = ["render", str(path), "--frames", "4", "--reuse", "motion", "--alpha", "0.3", "--seed", "10", "--frame", "2",
            "--out", str(out), "--out-dir", str(tmp_path / "seq")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    scene = load_scene(path)
    reuse = TemporalReuse(32, 24, alpha=0.3, mode="motion")
    with PathIntegrator(scene) as integ:
        outs = [s.outputs[0] for s in run_sequence(integ, scene, 4, [reuse], seed=10, start_frame=2)]
    np.testing.assert_array_equal(np.load(out), outs[-1])
    for k in range(4):
        np.testing.assert_array_equal(np.load(tmp_path / "seq" / f"frame_{k:05d}.npy"), outs[k])
    meta = json.loads((tmp_path / "last.npy.json").read_text())
    assert meta["frames"] == 4 and meta["seeds"] == [10, 13] and meta["reuse"] == "motion" and meta["alpha"] == 0.3
    assert meta["time"] == pytest.approx(5 / 100.0)


def test_render_frames_cli_split_screen_png_and_bad_alpha(scene_path, tmp_path):
    path = scene_path()
    _register()
    runner = CliRunner()
    png = tmp_path / "split.png"
    result = runner.invoke(app, ["render", str(path), "--frames", "3", "--split-screen", "--out", str(png)])
    assert result.exit_code == 0, result.output
    import cv2

    assert cv2.imread(str(png)).shape == (24, 32, 3)
    bad = runner.invoke(app, ["render", str(path), "--frames", "3", "--alpha", "0", "--out", str(tmp_path / "x.npy")])
    assert bad.exit_code == 2 and "alpha" in bad.output and "(0, 1]" in bad.output
    assert runner.invoke(app, ["render", str(path), "--out-dir", str(tmp_path), "--out", str(tmp_path / "y.npy")]).exit_code != 0


def test_render_frames_with_reuse_off_is_the_last_plain_frame(scene_path, tmp_path):
    path = scene_path()
    _register()
    out = tmp_path / "off.npy"
    result = CliRunner().invoke(app, ["render", str(path), "--frames", "3", "--reuse", "off", "--seed", "4", "--out", str(out)])
    assert result.exit_code == 0, result.output
    scene = load_scene(path)
    with PathIntegrator(scene) as integ:
        plain = integ.render(time=2 / 100.0, seed=4 + 2, spp=1).radiance
    np.testing.assert_array_equal(np.load(out), plain)
