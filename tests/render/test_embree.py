"""Embree's C API from numba (capi, traversal) against embreex, the oracle: identical hits."""

import numpy as np
import pytest

from dpmhw.render.embree import capi
from dpmhw.render.embree.accel import EmbreeAccel, RtcAccel, empty_hits
from dpmhw.render.geometry import SceneGeometry

from .test_integrator import ROOM

pytestmark = pytest.mark.skipif(not capi.load(), reason="libembree4 not found next to embreex")

MOTION = "motion = { rotate_axis = [0.3, 1.0, 0.2], rotate_deg_per_s = 50.0, oscillate_direction = [1.0, 0.0, 0.0], oscillate_amplitude = 0.1, oscillate_period_s = 2.0 }"


def _rays(scene, R, T, n, rng):
    """n rays: a third random, a third starting exactly on a surface, a third grazing a surface
    (origin within 1e-4 of its plane, direction within 1e-3 rad of it)."""
    tris, normals = [], []
    for k, o in enumerate(scene.objects):
        world = o.mesh.triangles.astype(np.float32) @ R[k].T + T[k]
        tris.append(world)
        c = np.cross(world[:, 1] - world[:, 0], world[:, 2] - world[:, 0])
        normals.append(c / np.linalg.norm(c, axis=1, keepdims=True))
    tris, normals = np.concatenate(tris), np.concatenate(normals)
    m = n // 3
    o_rand = rng.uniform([-0.7, -0.2, -0.7], [0.7, 1.2, 2.0], (n - 2 * m, 3))
    d_rand = rng.normal(size=(n - 2 * m, 3))
    pick = rng.integers(0, len(tris), 2 * m)
    b = rng.dirichlet([1, 1, 1], 2 * m)
    on = np.einsum("ij,ijk->ik", b, tris[pick])
    d_on = rng.normal(size=(m, 3))
    nrm = normals[pick[m:]]
    tangent = np.cross(nrm, rng.normal(size=(m, 3)))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    d_graze = tangent + nrm * rng.uniform(-1e-3, 1e-3, (m, 1))
    o_graze = on[m:] + nrm * rng.uniform(-1e-4, 1e-4, (m, 1))
    o = np.concatenate([o_rand, on[:m], o_graze]).astype(np.float32)
    d = np.concatenate([d_rand, d_on, d_graze])
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    return o, d


@pytest.mark.parametrize("packets", [False, True])
def test_hits_match_embreex_bit_for_bit(make_scene, packets):
    scene = make_scene(ROOM.format(extra=MOTION).replace('shape = "sphere"\nradius = 0.2', 'shape = "box"\nsize = [0.3, 0.25, 0.2]'))
    geometry = SceneGeometry(scene, threads=1)
    try:
        oracle = EmbreeAccel(scene.objects, geometry.tri_offsets, threads=1)
        assert isinstance(geometry.accel, RtcAccel)
        R, T = geometry.poses(scene.object_poses(0.37))
        o, d = _rays(scene, R, T, 100_000, np.random.default_rng(3))
        n = len(o)
        want, got = empty_hits(n), empty_hits(n)
        oracle.intersect_range(o, d, 0, n, R, T, want)
        geometry.accel.intersect_range(o, d, 0, n, R, T, got, packets=packets)
        assert (want.obj == 2).sum() > 1000 and (want.obj < 0).sum() > 1000  # the moving box is hit, some rays miss
        for name in ("t", "obj", "prim", "u", "v"):
            assert np.array_equal(getattr(want, name), getattr(got, name)), name
        tmax = np.where(np.isfinite(want.t), want.t * np.float32(1.0001), np.float32(1e30)).astype(np.float32)
        tmax[::2] = want.t[::2] * np.float32(0.9999)  # half stop just short of the hit
        # a ray starting on a surface has t = 0; tmax = 0 is an empty interval, where Embree's
        # single-ray and packet kernels disagree (the renderer never asks: its tmax is > 0)
        tmax = np.maximum(np.where(np.isfinite(tmax), tmax, np.float32(1e30)), np.float32(1e-6)).astype(np.float32)
        want_b, got_b = np.zeros(n, bool), np.zeros(n, bool)
        oracle.occluded_range(o, d, tmax, 0, n, R, T, want_b)
        geometry.accel.occluded_range(o, d, tmax, 0, n, R, T, got_b, packets=packets)
        assert 0.1 < want_b.mean() < 0.9
        assert np.array_equal(want_b, got_b)
    finally:
        geometry.close()


def test_moving_copies_of_one_mesh_share_one_bvh_and_hits_match_embreex(make_scene):
    """The scene loader builds a mesh per object, so equal moving meshes are different objects:
    they share one model-space BVH by content (accel.mesh_key), a different mesh gets its own,
    and hits stay identical to embreex's, bit for bit."""
    box, other = 'shape = "box"\nsize = [0.3, 0.25, 0.2]', 'shape = "box"\nsize = [0.2, 0.25, 0.2]'
    copies = "".join(f"""
[[objects]]
name = "box-{k}"
{box if k < 2 else other}
position = [{-0.3 + 0.3 * k}, 0.5, -0.2]
albedo = [0.5, 0.5, 0.5]
{MOTION}
""" for k in range(3))
    scene = make_scene(ROOM.format(extra=MOTION).replace('shape = "sphere"\nradius = 0.2', box) + copies)
    moving = [k for k, o in enumerate(scene.objects) if o.is_dynamic]
    assert len(moving) == 4 and len({id(scene.objects[k].mesh) for k in moving}) == 4  # four mesh objects, two shapes
    geometry = SceneGeometry(scene, threads=1)
    try:
        oracle = EmbreeAccel(scene.objects, geometry.tri_offsets, threads=1)
        handles = geometry.accel.acc[0][1:]
        assert handles[0] == handles[1] == handles[2] != handles[3]
        assert oracle.dynamic_scenes[0] is oracle.dynamic_scenes[2] and oracle.dynamic_scenes[3] is not oracle.dynamic_scenes[0]
        R, T = geometry.poses(scene.object_poses(0.61))
        o, d = _rays(scene, R, T, 30_000, np.random.default_rng(4))
        want, got = empty_hits(len(o)), empty_hits(len(o))
        oracle.intersect_range(o, d, 0, len(o), R, T, want)
        geometry.accel.intersect_range(o, d, 0, len(o), R, T, got, packets=True)
        assert all((want.obj == k).sum() > 100 for k in moving)
        for name in ("t", "obj", "prim", "u", "v"):
            assert np.array_equal(getattr(want, name), getattr(got, name)), name
    finally:
        geometry.close()


def test_static_camera_hits_match(make_scene):
    scene = make_scene(ROOM.format(extra=""))
    geometry = SceneGeometry(scene, threads=2)
    try:
        o = np.zeros((5000, 3), np.float32) + np.float32([0.0, 0.5, 1.8])
        d = np.random.default_rng(0).normal(size=(5000, 3)).astype(np.float32)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        a = EmbreeAccel(scene.objects, geometry.tri_offsets).intersect_static(o, d)
        b = geometry.accel.intersect_static(o, d)
        for name in ("t", "obj", "prim", "u", "v"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    finally:
        geometry.close()


def test_missing_library_falls_back_to_embreex_with_one_warning(tmp_path):
    import subprocess
    import sys

    code = (
        "import warnings; warnings.simplefilter('always')\n"
        "from dpmhw.scene_file import load_scene\n"
        "from dpmhw.render.integrator import PathIntegrator\n"
        "from dpmhw.render.embree.accel import EmbreeAccel\n"
        "with PathIntegrator(load_scene('paper-static'), threads=1) as it:\n"
        "    assert isinstance(it.geometry.accel, EmbreeAccel)\n"
        "    f = it.render(seed=1)\n"
        "    assert (f.object_id >= 0).mean() > 0.9\n"
    )
    env = dict(__import__("os").environ, DPMHW_EMBREE_LIB="none")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    warning_lines = [line for line in r.stderr.splitlines() if "Embree C API unavailable" in line]
    assert len(warning_lines) == 1


def _closed_box_rays(scene, R, T, n, rng, at_edges):
    """n rays from random points inside the closed room (object 0), aimed exactly at its triangles'
    edges and vertices (`at_edges`), or in random directions (as paths bounce)."""
    world = scene.objects[0].mesh.triangles @ R[0].T + T[0]
    o = (T[0] + rng.uniform(-1, 1, (n, 3)) * 0.9).astype(np.float32)
    if at_edges:
        edges = world[:, [0, 1, 2]], world[:, [1, 2, 0]]
        pick = rng.integers(0, len(world), n)
        s = rng.uniform(0, 1, (n, 1))
        targets = edges[0][pick, rng.integers(0, 3, n)] * (1 - s) + edges[1][pick, rng.integers(0, 3, n)] * s
        targets[: n // 4] = world[pick[: n // 4], 0]  # vertices
        d = targets - o
    else:
        d = rng.normal(size=(n, 3))
    return o, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("robust", [True, None])
def test_no_leak_out_of_a_closed_box(make_scene, robust):
    """Rays from inside a closed box all hit it: aimed exactly at its edges and corners with the
    robust flag (without it, the Moeller test lets 832 of these 60,000 escape), and in random
    directions, as paths bounce, with the default (capi.ROBUST off: the leak needs a ray through
    an edge to the last bit, which paths do not aim for)."""
    from .test_radiometry import CLOSED_ROOM

    scene = make_scene(CLOSED_ROOM)
    geometry = SceneGeometry(scene, threads=1)
    accel = RtcAccel(scene.objects, geometry.tri_offsets, threads=1, robust=robust)
    try:
        R, T = geometry.poses(scene.object_poses(0.0))
        o, d = _closed_box_rays(scene, R, T, 60_000 if robust else 200_000, np.random.default_rng(9), at_edges=bool(robust))
        hits = empty_hits(len(o))
        accel.intersect_range(o, d, 0, len(o), R, T, hits, packets=True)
        assert np.all(hits.obj >= 0), int((hits.obj < 0).sum())
    finally:
        accel.close()
        geometry.close()


def test_camera_tiles_give_the_same_hits_as_single_rays(make_scene):
    scene = make_scene(ROOM.format(extra=""))
    geometry = SceneGeometry(scene, threads=2)
    try:
        from dpmhw.render.cameras import PinholeCamera

        cam = PinholeCamera(scene.camera.K, scene.camera.dist, 30, 22, scene.camera.pose)  # edges: not multiples of 4
        o, d = cam.generate_rays()
        a = EmbreeAccel(scene.objects, geometry.tri_offsets).intersect_static(o, d)
        b = geometry.accel.intersect_static(o, d, width=30)
        for name in ("t", "obj", "prim", "u", "v"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    finally:
        geometry.close()


@pytest.mark.parametrize("packets", [(False, False), (True, True)])
def test_fused_segments_give_the_staged_image_bit_for_bit(make_scene, packets):
    """Queries from inside the compiled segment call = the same queries called stage by stage
    (which match embreex above), so the image is unchanged, moving object included."""
    from dpmhw.render.integrator import PathIntegrator

    scene = make_scene(ROOM.format(extra=MOTION).replace('shape = "sphere"\nradius = 0.2', 'shape = "box"\nsize = [0.3, 0.25, 0.2]'))
    frames = []
    for fused in (True, False):
        with PathIntegrator(scene, threads=2) as integrator:
            integrator.packets, integrator.fused = packets, fused
            frames.append(integrator.render(time=0.3, seed=5, spp=2))
    assert (frames[0].object_id == 2).sum() > 20
    assert np.array_equal(frames[0].radiance, frames[1].radiance)
    assert np.array_equal(frames[0].model_position, frames[1].model_position)


@pytest.mark.parametrize("moving", [False, True])
@pytest.mark.parametrize("raster", [False, True])
def test_moved_camera_traced_by_segments_gives_the_staged_image(make_scene, monkeypatch, moving, raster):
    """A new camera pose's static hits are traced by the first pass's segments (4×4 tiles cut at
    segment rows that are not multiples of 4) into the pose cache, reused in place: moving the
    camera away and back gives, frame by frame, the image of the staged path, which traces them
    up front with intersect_static. Rasterised (raster_camera), both paths take them from the
    rasteriser up front, and still agree."""
    import dpmhw.render.integrator as integrator_module
    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.transforms import Pose

    monkeypatch.setattr(integrator_module, "SEGMENT_PIXELS", 97)  # segments end mid-row, mid-tile
    scene = make_scene(ROOM.format(extra=MOTION if moving else "").replace("width = 32\nheight = 24", "width = 30\nheight = 22"))
    p0 = scene.camera.pose
    poses = [p0, Pose(p0.R, p0.t + np.array([0.05, 0.0, 0.0])), p0, p0]
    frames = {}
    for fused in (True, False):
        with PathIntegrator(scene, threads=2) as integrator:
            integrator.fused, integrator.raster_camera = fused, raster
            frames[fused] = []
            for k, pose in enumerate(poses):
                frames[fused].append(integrator.render(time=0.1 * k, seed=k, spp=2, camera_pose=pose))
                new = 0 if k == 3 else 30 * 22  # cached for the repeated pose
                assert integrator.counts.primary_static_traced == (0 if raster else new)
                assert integrator.counts.primary_static_rasterised == (new if raster else 0)
    assert not np.array_equal(frames[True][0].object_id, frames[True][1].object_id)
    for a, b in zip(frames[True], frames[False]):
        assert np.array_equal(a.radiance, b.radiance) and np.array_equal(a.object_id, b.object_id)
        assert np.array_equal(a.position, b.position)


def test_aligned_scratch_buffers_do_not_leak_over_a_thousand_frames(make_scene):
    """Every query call allocates its aligned packet scratch inside the kernel; over 10³ frames
    the process's resident memory must stay flat."""
    import resource

    from dpmhw.render.integrator import PathIntegrator

    scene = make_scene(ROOM.format(extra=MOTION).replace("width = 32\nheight = 24", "width = 16\nheight = 12"))

    def rss_kb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() // 1024

    with PathIntegrator(scene, threads=2, pixel_sampling="jitter") as integrator:
        for k in range(50):  # warm-up: compilation, caches, work buffers
            integrator.render(time=k / 30, seed=k)
        before = rss_kb()
        for k in range(1000):
            integrator.render(time=k / 30, seed=k)
        grown = rss_kb() - before
    # a leaked packet scratch (1.4 kB) per query call, ~5 calls a frame, would be ≈ 7 MB
    assert grown < 3000, f"resident memory grew by {grown} kB over 1000 frames"
