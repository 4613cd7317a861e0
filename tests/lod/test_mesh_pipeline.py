"""Mesh LOD in the pipeline: levels swapped in place in the renderer and the G-buffer, chosen per
frame, BVHs built once, the pop at a switch measured on rendered frames, the loop's switch."""

import numpy as np
import pytest

from dpmhw.benchmarks.lod import bench_scene
from dpmhw.lod import mesh_pipeline
from dpmhw.lod.mesh_levels import MeshLevels, image_pop_visibility, scene_at_levels
from dpmhw.lod.mesh_pipeline import MeshLod, build_levels, mesh_lod
from dpmhw.lod.visibility import VisibilitySettings
from dpmhw.render.embree import accel, capi
from dpmhw.render.gbuffer import NativeGBuffer
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene
from dpmhw.sequence import scaled_scene
from dpmhw.session.config import load_session_config
from dpmhw.transforms import Pose

T = 0.3


@pytest.fixture(scope="module")
def bunny():
    scene = scaled_scene(load_scene("dpm-bunny"), 0.25)  # 256×192
    return scene, build_levels(scene)


def luminance(rgb):
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def test_levels_in_place_render_exactly_as_a_rebuilt_renderer(bunny):
    scene, levels = bunny
    poses = scene.object_poses(T)
    with PathIntegrator(scene, threads=2) as a:
        before = a.render(time=T, seed=3, poses=poses)
        lod = MeshLod(a, None, levels=levels)
        assert lod.active and lod.triangles == a.geometry.triangle_count
        at0 = a.render(time=T, seed=3, poses=poses)  # installed, level 0: bit for bit the old frame
        assert np.array_equal(before.radiance, at0.radiance) and np.array_equal(before.object_id, at0.object_id)
        for level in (1, len(levels[0]) - 1, 0):
            a.geometry.set_level(0, level)
            got = a.render(time=T, seed=3, poses=poses)
            with PathIntegrator(scene_at_levels(scene, levels, [level, 0]), threads=2) as b:
                want = b.render(time=T, seed=3, poses=poses)
                assert a.geometry.active_triangles == b.geometry.triangle_count
            assert np.array_equal(got.radiance, want.radiance) and np.array_equal(got.depth, want.depth)


def test_each_level_bvh_is_built_once(bunny, monkeypatch):
    scene, levels = bunny
    with PathIntegrator(scene, threads=2) as r:
        lod = MeshLod(r, None, levels=levels)
        built = len(r.geometry._level_scenes)
        assert built == len(levels[0]) - 1  # one per coarser level; level 0 is the renderer's own
        fail = lambda *a, **k: pytest.fail("a BVH was built after the levels were installed")  # noqa: E731
        monkeypatch.setattr(capi, "RtcScene", fail)
        monkeypatch.setattr(accel, "_embree_scene", fail)
        cam = scene.camera.pose
        seen = []
        for z in list(np.geomspace(1.0, 400.0, 25)) + list(np.geomspace(400.0, 1.0, 25)):
            far = Pose(cam.R, cam.t + cam.R[:, 2] * (1.0 - z))  # the projector pulled back to z metres
            seen.append(int(lod.choose(scene.object_poses(T), far)[0]))
            r.render(time=T, seed=0, poses=scene.object_poses(T))
        assert seen[0] == seen[-1] == 0 and max(seen) >= 2 and lod.switches >= 2  # down and back
        assert len(r.geometry._level_scenes) == built


def test_far_object_switches_down_near_one_stays_full(bunny):
    scene, levels = bunny
    with PathIntegrator(scene, threads=2) as r:
        lod = MeshLod(r, None, levels=levels)
        poses = scene.object_poses(T)
        frame = r.render(time=T, seed=0, poses=poses)
        lod.observe(frame.radiance, frame.depth, frame.object_id)
        assert lod.object_vis[0] > 0  # the lit bunny is visible at 1 m
        for _ in range(3):
            assert lod.choose(poses, scene.camera.pose)[0] == 0  # 1 m: full detail
        cam = scene.camera.pose
        far = Pose(cam.R, cam.t + cam.R[:, 2] * (1.0 - 60.0))  # 60 m: beyond the pop-safe depth of level 1
        assert lod.selector.safe_depths[0][1] < 60.0
        assert lod.choose(poses, far)[0] >= 1
        assert lod.triangles < r.geometry.triangle_count
        assert lod.choose(poses, cam)[0] == 0  # back near: full at once


def test_pop_at_a_switch_is_no_more_visible_than_the_noise_and_below_threshold_beyond(bunny):
    """The pop measured on rendered frames (the real renderer, 128 paths per pixel, same seed):
    switching level 0 → 1 at the selector's switch depth (pop-safe depth × hysteresis margin)
    is no more visible than two frames of one level with different seeds already differ (at
    this depth the bunny is ≈ 8 px wide and 1 % contrast is within path-tracing noise); at twice
    that depth it is below the threshold; at 1 m it is far above (the test can fail)."""
    scene, levels = bunny
    vis = VisibilitySettings()
    with PathIntegrator(scene, threads=2) as probe:
        lod = MeshLod(probe, None, levels=levels, visibility=vis)
        switch = lod.selector.safe_depths[0][1] * (1 + lod.selector.settings.hysteresis)
    focal = float(np.sqrt(scene.camera.K[0, 0] * scene.camera.K[1, 1]))
    pop, noise = {}, {}
    for name, z in (("switch", switch), ("beyond", 2 * switch), ("near", 1.0)):
        s = scaled_scene(bench_scene(f"dpm-bunny@{z}"), 0.25)
        frames = []
        for level, seed in ((0, 5), (0, 6), (1, 5)):
            with PathIntegrator(scene_at_levels(s, levels, [level, 0]), threads=2) as r:
                frames.append(luminance(r.render(time=T, seed=seed, spp=128, poses=s.object_poses(T)).radiance))
        pop[name] = image_pop_visibility(frames[0], frames[2], z, focal, vis)
        noise[name] = image_pop_visibility(frames[0], frames[1], z, focal, vis)
    assert pop["switch"] <= max(noise["switch"], 0.0) + 3.0, (pop, noise)
    assert pop["beyond"] <= 0, (pop, noise)
    assert pop["near"] > 0 and pop["near"] > pop["switch"] + 10.0, (pop, noise)  # (the metric saturates near)


def test_gbuffer_follows_a_level_switch(bunny):
    """The native G-buffer (static cache + region re-trace) after a switch equals one built on
    a renderer whose scene has that level, in the "trace", "raster" and "edges" modes."""
    scene, levels = bunny
    native = scaled_scene(load_scene("dpm-bunny"), 0.5)  # 512×384 G-buffer over a 256×192 shading renderer
    poses = native.object_poses(T)
    for mode in ("trace", "raster", "edges"):
        with PathIntegrator(scene, threads=2) as a:
            ga = NativeGBuffer(native, a.geometry, 512, 384)
            lod = MeshLod(a, ga, levels=levels, native_K=native.camera.K)
            ga.update(poses, shading=a.render(time=T, poses=poses), mode=mode)
            a.geometry.set_level(0, 2)
            ga.use_mesh(0, levels[0].levels[2].mesh)
            moved = native.object_poses(T + 0.01)
            ga.update(moved, shading=a.render(time=T, poses=moved), mode=mode)
            ga.update(poses, shading=a.render(time=T, poses=poses), mode=mode)
            with PathIntegrator(scene_at_levels(scene, levels, [2, 0]), threads=2) as b:
                gb = NativeGBuffer(scene_at_levels(native, levels, [2, 0]), b.geometry, 512, 384)
                gb.update(poses, shading=b.render(time=T, poses=poses), mode=mode)
                for name in ("id", "depth", "normal", "albedo"):
                    assert np.array_equal(getattr(ga, name), getattr(gb, name)), (mode, name)
                gb.close()
            ga.close()
            assert lod.active


def test_observe_handles_no_objects_and_uint8_frames(bunny):
    scene, levels = bunny
    with PathIntegrator(scene, threads=2) as r:
        lod = MeshLod(r, None, levels=levels)
        H, W = 192, 256
        none = lod.observe(np.zeros((H, W, 3), np.uint8), np.full((H, W), np.inf, np.float32), np.full((H, W), -1, np.int32))
        assert np.all(none == np.inf)  # on no pixel: the strict (visible) rule
        frame = r.render(time=T, seed=0, poses=scene.object_poses(T))
        img8 = (np.clip(frame.radiance, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
        v = lod.observe(img8, frame.depth, frame.object_id)
        assert np.isfinite(v[0]) and v[0] > 0 and v[1] == np.inf


def test_mesh_off_installs_nothing_and_on_needs_a_mesh(bunny):
    scene, _ = bunny
    cfg = load_session_config()
    assert cfg.lod.mesh is False  # default: off (docs/lod.md: at lab distances nothing switches)
    with PathIntegrator(scene, threads=2) as r:
        assert mesh_lod(r, None, cfg.lod) is None
        assert not hasattr(r.geometry, "_levels")
        on = load_session_config(overrides=["lod.mesh=true"]).lod
        lod = mesh_lod(r, None, on)
        assert lod is not None and lod.active
    from dpmhw.session.testing import FlatRenderer

    assert mesh_lod(FlatRenderer(), None, on) is None  # no scene geometry: off, with a warning
    small = scaled_scene(load_scene("paper-static"), 0.1)
    with PathIntegrator(small, threads=1) as r:  # nothing moves: nothing to simplify
        assert mesh_lod(r, None, on) is None


def test_levels_only_for_moving_meshes():
    scene = load_scene("paper-dynamic")
    levels = build_levels(scene)
    for o, lv in zip(scene.objects, levels):
        assert (lv is not None) == (o.shape == "mesh" and o.is_dynamic)
    assert levels[3] is levels[4]  # the two bunnies share one MeshLevels
    assert isinstance(levels[3], MeshLevels)
    assert mesh_pipeline.SRGB8_TO_LINEAR[0] == 0 and mesh_pipeline.SRGB8_TO_LINEAR[255] == pytest.approx(1.0)
    with PathIntegrator(scaled_scene(scene, 0.1), threads=1) as r:
        with pytest.raises(ValueError, match="objects\\[0\\]"):
            r.geometry.add_levels(0, [scene.objects[0].mesh])
        before = r.render(time=T, seed=1)
        lod = MeshLod(r, None, levels=levels)  # two bunnies (equal meshes, own objects) share rows and BVHs
        assert len(r.geometry._level_scenes) == len(levels[3]) - 1
        assert np.array_equal(r.render(time=T, seed=1).radiance, before.radiance)
        far = Pose(scene.camera.pose.R, scene.camera.pose.t - scene.camera.pose.R[:, 2] * 100.0)
        assert np.all(lod.choose(scene.object_poses(T), far)[3:] >= 1)
        assert lod.triangles < r.geometry.triangle_count


def test_the_session_loop_chooses_levels_every_frame():
    """`lod.mesh=true`: the loop installs the levels, chooses before each render (stage
    "mesh_lod" timed), reads the output's visibility after it; the lit bunny 1 m away stays at
    level 0; `lod.mesh=false` (default): no MeshLod at all."""
    from dpmhw.session.testing import fake_session, wait_for

    scene = load_scene("dpm-bunny").at_size(32, 24)
    for on in (True, False):
        renderer = PathIntegrator(scene, threads=1)
        loop = fake_session(["lod.mesh=true"] if on else [], renderer=renderer)
        try:
            assert (loop.mesh_lod is not None) == on
            loop.start()
            assert wait_for(lambda: len(loop.frame_log) >= 5, 30), loop.status()
        finally:
            loop.stop()
            renderer.close()
        assert all(("mesh_lod" in r.stages_s) == on for r in loop.frame_log)
        if on:
            assert loop.mesh_lod.choice[0] == 0 and np.isfinite(loop.mesh_lod.object_vis[0])


def test_bench_scene_moves_the_projector_back():
    near = load_scene("dpm-bunny")
    far = bench_scene("dpm-bunny@40")
    cam = far.camera.pose
    assert float((far.objects[0].pose.t - cam.t) @ cam.R[:, 2]) == pytest.approx(40.0)
    assert np.array_equal(cam.R, near.camera.pose.R) and np.array_equal(far.viewer_position, near.viewer_position)
    for bad in ("dpm-bunny@-1", "dpm-bunny@x", "dpm-bunny@inf", "paper-static@5"):
        with pytest.raises(ValueError, match="scenes: expected NAME@Z"):
            bench_scene(bad)


def test_no_flicker_at_a_switch_depth_in_the_pipeline(bunny):
    """The projector's distance jitters ±5 % around the selector's level-1 switch depth for 40
    frames: the level changes at most once (hysteresis), never back and forth."""
    scene, levels = bunny
    with PathIntegrator(scene, threads=1) as r:
        lod = MeshLod(r, None, levels=levels)
        lod.object_vis[:] = 50.0  # a visible object
        z1 = lod.selector.safe_depths[0][1] * (1 + lod.selector.settings.hysteresis)
        cam, poses = scene.camera.pose, scene.object_poses(T)
        rng = np.random.default_rng(3)
        seen = []
        for f in 1 + 0.05 * rng.uniform(-1, 1, 40):
            seen.append(int(lod.choose(poses, Pose(cam.R, cam.t + cam.R[:, 2] * (1.0 - z1 * f)))[0]))
        assert sum(a != b for a, b in zip(seen, seen[1:])) <= 1 and lod.switches <= 1


def test_observe_takes_a_map_of_the_output_instead_of_mapping_it_again(bunny):
    """The tile refiner's map of the same output (one map, three uses) gives the same per-object
    V as the mesh's own map of the linear frame; a different map gives its own values."""
    from dpmhw.lod.visibility import visibility_map

    scene, levels = bunny
    with PathIntegrator(scene, threads=2) as r:
        lod = MeshLod(r, None, levels=levels)
        frame = r.render(time=T, seed=0, poses=scene.object_poses(T))
        own = lod.observe(frame.radiance, frame.depth, frame.object_id).copy()
        full = visibility_map(frame.radiance, frame.depth, scene.camera.K, lod.visibility)
        assert np.array_equal(lod.observe(None, frame.depth, frame.object_id, visibility=full), own)
        full.visibility[:] = -7.0
        assert lod.observe(None, frame.depth, frame.object_id, visibility=full)[0] == -7.0
