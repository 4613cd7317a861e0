"""Sampling behaviour: determinism, convergence, robustness on awkward geometry, moving objects."""

import numpy as np
from scene_texts import lit_room

from dpmhw.render.integrator import PathIntegrator
from dpmhw.transforms import Pose, rotation_from_euler_xyz_deg

ROOM = lit_room("""
[[objects]]
name = "ball"
shape = "sphere"
radius = 0.2
position = [0.1, 0.2, 0.0]
albedo = [0.5, 0.5, 0.5]
specular = [0.4, 0.4, 0.4]
roughness = 0.3
{extra}
""", width=32, height=24, f=26.0, cx=16.0, cy=12.0, max_bounces=2)


def test_same_seed_repeats_bit_for_bit_and_seeds_differ(make_scene, render):
    scene = make_scene(ROOM.format(extra=""))
    a = render(scene, spp=2, seed=7)
    b = render(scene, spp=2, seed=7)
    c = render(scene, spp=2, seed=8)
    assert np.array_equal(a.radiance, b.radiance)
    assert not np.array_equal(a.radiance, c.radiance)
    single = render(scene, spp=2, seed=7, threads=1)  # thread count does not change the image
    assert np.array_equal(a.radiance, single.radiance)


def test_segmentation_does_not_change_the_image(make_scene, render, monkeypatch):
    import dpmhw.render.integrator as integrator

    scene = make_scene(ROOM.format(extra=""))
    a = render(scene, spp=2, seed=7)
    for pixels in (97, 10**9):  # many small segments, then one segment
        monkeypatch.setattr(integrator, "SEGMENT_PIXELS", pixels)
        b = render(scene, spp=2, seed=7)
        assert np.array_equal(a.radiance, b.radiance) and np.array_equal(a.object_id, b.object_id)


def test_error_falls_like_one_over_sqrt_spp(make_scene, render):
    scene = make_scene(ROOM.format(extra=""))
    reference = render(scene, spp=2048, seed=1000).radiance
    rmse = {}
    for spp in (16, 64, 256):
        errs = [np.sqrt(np.mean((render(scene, spp=spp, seed=s).radiance - reference) ** 2)) for s in range(3)]
        rmse[spp] = np.mean(errs)
    for lo, hi in ((16, 64), (64, 256)):
        assert 1.6 < rmse[lo] / rmse[hi] < 2.5, rmse


def test_split_and_gbuffer_are_consistent(make_scene, render):
    scene = make_scene(ROOM.format(extra=""))
    f = render(scene, spp=4)
    # the light seen directly is in radiance but in neither reflected part
    light = f.object_id == 1
    assert light.any()
    np.testing.assert_allclose(f.radiance, f.diffuse + f.specular + np.where(light[..., None], 10.0, 0.0), rtol=1e-5, atol=1e-5)
    ball = f.object_id == 2
    assert f.specular[ball].sum() > 0 and f.diffuse[ball].sum() > 0
    np.testing.assert_allclose(f.specular[f.object_id == 0], 0.0)  # the room has no glossy lobe
    # world position = pose(model position); normals are unit and face the camera
    pose = scene.objects[2].pose
    np.testing.assert_allclose(pose.apply(f.model_position[ball]), f.position[ball], atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(f.normal[ball], axis=1), 1.0, atol=1e-4)
    to_cam = scene.camera.pose.t - f.position[ball]
    assert np.all(np.einsum("ij,ij->i", f.normal[ball], to_cam) > 0)
    np.testing.assert_allclose(f.albedo[ball], 0.5)
    assert np.all(np.isfinite(f.depth[f.object_id >= 0])) and np.all(np.isinf(f.depth[f.object_id < 0]))


def test_moving_object_matches_the_same_object_placed_statically(make_scene, render):
    """Rays transformed into model space (dynamic BVH) see what a world-space BVH sees."""
    motion = "motion = { rotate_axis = [0.3, 1.0, 0.2], rotate_deg_per_s = 50.0, oscillate_direction = [1.0, 0.0, 0.0], oscillate_amplitude = 0.1, oscillate_period_s = 2.0 }"
    moving = make_scene(ROOM.format(extra=motion).replace('shape = "sphere"\nradius = 0.2', 'shape = "box"\nsize = [0.3, 0.25, 0.2]'), "moving.toml")
    t = 0.37
    pose = moving.objects[2].pose_at(t)
    from scipy.spatial.transform import Rotation

    euler = Rotation.from_matrix(pose.R).as_euler("xyz", degrees=True)
    placed = make_scene(
        ROOM.format(extra="").replace('shape = "sphere"\nradius = 0.2', 'shape = "box"\nsize = [0.3, 0.25, 0.2]')
        .replace("position = [0.1, 0.2, 0.0]", f"position = {pose.t.tolist()}\nrotation = {euler.tolist()}"),
        "placed.toml",
    )
    a = render(moving, spp=4, time=t)
    b = render(placed, spp=4, time=t)
    assert (a.object_id == 2).sum() > 20
    same = (a.object_id == b.object_id).mean()
    assert same > 0.995
    both = (a.object_id == 2) & (b.object_id == 2)
    np.testing.assert_allclose(a.model_position[both], b.model_position[both], atol=1e-4)
    np.testing.assert_allclose(a.radiance.mean(), b.radiance.mean(), rtol=0.05)


def test_pose_override_from_tracker(make_scene):
    scene = make_scene(ROOM.format(extra="rigid_body = 4"))
    poses = scene.object_poses(0.0)
    poses[2] = Pose(rotation_from_euler_xyz_deg([0, 0, 0]), np.array([5.0, 5.0, 5.0]))  # moved out of view
    with PathIntegrator(scene) as integrator:
        f = integrator.render(poses=poses)
    assert not (f.object_id == 2).any()


def test_degenerate_and_duplicate_triangles(make_scene, render, tmp_path):
    # a tetrahedron, one triangle duplicated, plus a zero-area and a collinear sliver
    obj = tmp_path / "bad.obj"
    obj.write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 2 2 2\nv 3 3 3\n"
        "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\nf 2 3 4\nf 1 1 2\nf 1 5 6\n"
    )
    text = """
    [render]
    width = 24
    height = 24
    max_bounces = 2
    background = [1.0, 1.0, 1.0]

    [camera]
    fx = 20.0
    fy = 20.0
    cx = 12.0
    cy = 12.0
    position = [2.0, 1.5, 2.5]
    look_at = [0.25, 0.25, 0.25]

    [[objects]]
    name = "tet"
    shape = "mesh"
    mesh = "bad.obj"
    smooth = false
    albedo = [0.5, 0.5, 0.5]
    """
    scene = make_scene(text)
    assert scene.objects[0].mesh.dropped_degenerate == 2
    f = render(scene, spp=8)
    tet = f.object_id == 0
    assert tet.sum() > 30 and f.nonfinite_samples == 0
    np.testing.assert_allclose(f.radiance[tet], 0.5, rtol=1e-4)  # convex: furnace answer ρ·L


def test_grazing_view_and_light(make_scene, render):
    text = """
    [render]
    width = 40
    height = 20
    max_bounces = 1

    [camera]
    fx = 30.0
    fy = 30.0
    cx = 20.0
    cy = 10.0
    position = [0.0, 0.001, 3.0]
    look_at = [0.0, 0.0, 0.0]

    [[objects]]
    name = "floor"
    shape = "quad"
    size = [4.0, 8.0]
    albedo = [0.8, 0.8, 0.8]
    specular = [0.2, 0.2, 0.2]
    roughness = 0.05

    [[objects]]
    name = "light"
    shape = "quad"
    size = [0.5, 0.02]
    position = [0.0, 0.02, -1.0]
    rotation = [-90.0, 0.0, 0.0]
    albedo = 0.0
    emission = [50.0, 50.0, 50.0]
    """
    f = render(make_scene(text), spp=32)
    assert f.nonfinite_samples == 0
    assert np.all(np.isfinite(f.radiance))
    floor = f.object_id == 0
    assert floor.sum() > 50
    assert f.radiance[floor].max() < 50.0


def test_a_fixed_camera_keeps_the_first_surfaces_and_shares_a_read_only_gbuffer(make_scene):
    """With the camera fixed and nothing moving, the first vertices' surfaces and the G-buffer
    are kept from a pose's second frame on: every frame still equals a fresh integrator's frame
    at its pose and seed, the frames at the pose share one read-only G-buffer, and a new pose
    (or a return to an old one) computes them anew."""
    import pytest

    scene = make_scene(ROOM.format(extra=""))
    p0 = scene.camera.pose
    p1 = Pose(p0.R, p0.t + np.array([0.03, 0.0, 0.0]))
    poses = [p0, p0, p0, p1, p1, p0]
    with PathIntegrator(scene, threads=2) as integrator:
        frames = [integrator.render(seed=k, spp=1 + k % 2, camera_pose=pose) for k, pose in enumerate(poses)]
    for k, pose in enumerate(poses):
        with PathIntegrator(scene, threads=1) as fresh:
            ref = fresh.render(seed=k, spp=1 + k % 2, camera_pose=pose)
        assert np.array_equal(frames[k].radiance, ref.radiance), k
        for name in ("object_id", "model_position", "position", "normal", "depth", "albedo", "specular_albedo", "roughness"):
            assert np.array_equal(getattr(frames[k], name), getattr(ref, name)), (k, name)
    assert not np.shares_memory(frames[0].normal, frames[1].normal)  # kept from the second frame on
    assert np.shares_memory(frames[1].normal, frames[2].normal) and np.shares_memory(frames[1].object_id, frames[2].object_id)
    assert not np.shares_memory(frames[2].normal, frames[3].normal) and not np.shares_memory(frames[4].normal, frames[5].normal)
    with pytest.raises(ValueError):
        frames[2].normal[0, 0, 0] = 1.0


def test_nothing_is_kept_while_an_object_moves(make_scene):
    """A moving object changes the camera hits every frame: each frame computes its first
    surfaces and writes its own G-buffer, which follows the object."""
    from .test_embree import MOTION

    scene = make_scene(ROOM.format(extra=MOTION))
    with PathIntegrator(scene, threads=2) as integrator:
        a, b = (integrator.render(time=t, seed=1) for t in (0.0, 0.5))
    assert not np.shares_memory(a.normal, b.normal) and b.normal.flags.writeable
    assert not np.array_equal(a.object_id, b.object_id)


def test_rasterised_camera_hits_give_the_traced_image(make_scene):
    """A moved camera's static hits rasterised (the default) or traced: the same triangles
    (but at edges through pixel centres), so the same image to float32 rounding."""
    scene = make_scene(ROOM.format(extra=""))
    p0 = scene.camera.pose
    poses = [Pose(rotation_from_euler_xyz_deg((0.0, a, 0.0)) @ p0.R, p0.t + np.array([0.01 * a, 0.0, 0.0])) for a in (-3.0, 2.0)]
    frames = {}
    for raster in (True, False):
        with PathIntegrator(scene, threads=2) as integrator:
            integrator.raster_camera = raster
            frames[raster] = [integrator.render(seed=k, camera_pose=p) for k, p in enumerate(poses)]
            assert (integrator.counts.primary_static_rasterised > 0) == raster
    for a, b in zip(frames[True], frames[False]):
        same = a.object_id == b.object_id
        assert same.sum() >= same.size - 2
        assert np.all(np.isfinite(a.radiance))
        np.testing.assert_allclose(a.radiance[same], b.radiance[same], rtol=2e-3, atol=2e-4)
        np.testing.assert_allclose(a.depth[same & (a.object_id >= 0)], b.depth[same & (b.object_id >= 0)], rtol=1e-5)
