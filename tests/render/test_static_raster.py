"""Camera hits by rasterisation (dpmhw.render.static_raster) against Embree's traced camera rays."""

import os
from types import SimpleNamespace

import numpy as np
import pytest

from dpmhw.render.cameras import PinholeCamera
from dpmhw.render.embree import capi
from dpmhw.render.geometry import SceneGeometry
from dpmhw.render.static_raster import CameraHits, CameraHitsUnsupported
from dpmhw.transforms import Pose, rotation_about_axis

from .test_integrator import ROOM

pytestmark = pytest.mark.skipif(not capi.load(), reason="libembree4 not found")


def _look(position, target, up=(0.0, 1.0, 0.0)) -> Pose:
    """Camera→world pose of a camera at `position` looking at `target` (x right, y down, z forward)."""
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return Pose(np.stack([x, np.cross(z, x), z], axis=1), np.asarray(position, float))


def _camera(width, height, f, pose, dist=(0, 0, 0, 0, 0), centre=(0.37, 0.21)) -> PinholeCamera:
    """A pinhole camera whose principal point is off the pixel grid by `centre` (so that, unless asked,
    no edge of the test scenes passes exactly through pixel centres)."""
    K = [[f, 0, (width - 1) / 2 + centre[0]], [0, f, (height - 1) / 2 + centre[1]], [0, 0, 1]]
    return PinholeCamera(K, dist, width, height, pose)


def _static(*meshes):
    """Static objects (model = world) from (vertices, faces) pairs, and their triangle offsets."""
    objects = [SimpleNamespace(is_dynamic=False, pose=Pose.identity(), mesh=SimpleNamespace(vertices=np.asarray(v, float), faces=np.asarray(f, np.int64)))
               for v, f in meshes]
    return objects, np.cumsum([0] + [len(f) for _, f in meshes[:-1]]).astype(np.int32)


def _compare(accel, raster, camera):
    """(Embree's hits, the rasteriser's hits) of the camera's pixel rays."""
    o, d = camera.generate_rays()
    return accel.intersect_static(o, d, width=camera.width), raster.hits(camera, d)


def _agree(want, got, max_other=0, rel_t=1e-5, uv=1e-4):
    """Where both find the same triangle: t within rel_t relative, u and v within uv. At most
    `max_other` pixels find another triangle, each either the same point of the surface (the ray
    through an edge two triangles share: either is right) or a nearer one (Embree, without its
    robust flag, lets rays through edges: the rasteriser's inclusive tests do not). Never a hole."""
    other = want.prim != got.prim
    hit = ~other & (want.prim >= 0)
    with np.errstate(invalid="ignore"):  # inf − inf where both miss
        tie = other & (np.abs(got.t - want.t) <= 1e-4 * want.t)
    nearer = other & (got.t < want.t)  # includes Embree's misses (t = inf)
    if os.environ.get("RASTER_STATS"):
        print(f"other triangle {other.sum()} of {other.size} pixels ({tie.sum()} on a shared edge, {(nearer & ~tie).sum()} nearer "
              f"than Embree's), same triangle {hit.sum()}: max |dt|/t {np.max(np.abs(got.t[hit] - want.t[hit]) / want.t[hit], initial=0):.3g}, "
              f"|du| {np.max(np.abs(got.u[hit] - want.u[hit]), initial=0):.3g}, |dv| {np.max(np.abs(got.v[hit] - want.v[hit]), initial=0):.3g}")
    assert not np.any((want.prim >= 0) & (got.prim < 0)), "a hole: Embree hits, the rasteriser misses"
    assert np.all(tie | nearer | ~other), "the rasteriser found a farther triangle"
    assert other.sum() <= max_other, other.sum()
    assert np.array_equal(want.obj[~other], got.obj[~other])
    assert np.all(np.abs(got.t[hit] - want.t[hit]) <= rel_t * want.t[hit])
    assert np.max(np.abs(got.u[hit] - want.u[hit]), initial=0) <= uv
    assert np.max(np.abs(got.v[hit] - want.v[hit]), initial=0) <= uv
    miss = got.prim < 0
    assert np.all(np.isinf(got.t[miss])) and np.all(got.obj[miss] == -1) and np.all(got.u[miss] == 0) and np.all(got.v[miss] == 0)
    return int(other.sum())


def test_room_hits_match_embree_at_several_poses(make_scene):
    scene = make_scene(ROOM.format(extra=""))
    geometry = SceneGeometry(scene, threads=2)
    try:
        raster = CameraHits(scene.objects, geometry.tri_offsets)
        base = scene.camera.pose
        poses = [base, Pose(rotation_about_axis((0, 1, 0), 0.3) @ base.R, base.t), Pose(rotation_about_axis((0, 0, 1), 0.5) @ base.R, base.t),
                 _look((0.3, 0.8, 0.6), (0.0, 0.2, 0.0)), _look((0.0, 0.5, 0.45), (0.0, 0.5, -1.0))]  # the last inside the room
        for pose in poses:
            want, got = _compare(geometry.accel, raster, _camera(320, 240, 260.0, pose))
            assert np.mean(want.prim >= 0) > 0.3
            _agree(want, got, max_other=4, uv=5e-4)  # the ball's triangles are ~2 cm across
    finally:
        geometry.close()


def test_triangles_crossing_the_camera_plane_and_behind_it():
    # a floor running from behind the camera to far ahead, a triangle with one corner behind the
    # camera and two ahead, and one wholly behind it (never hit)
    floor = ([[-5, 0, -5], [5, 0, -5], [5, 0, 5], [-5, 0, 5]], [[0, 1, 2], [0, 2, 3]])
    crossing = ([[-0.3, 0.2, 1.0], [0.4, 0.3, -2.0], [0.1, 0.6, -2.0]], [[0, 1, 2]])
    behind = ([[-1, 0, 3], [1, 0, 3], [0, 1, 3]], [[0, 1, 2]])
    objects, offsets = _static(floor, crossing, behind)
    from dpmhw.render.embree.accel import RtcAccel

    accel = RtcAccel(objects, offsets)
    try:
        raster = CameraHits(objects, offsets)
        for position, target in (((0, 0.3, 0.5), (0, 0.1, -1)), ((0.05, 0.25, 0.9), (0.2, 0.3, -1)), ((0, 2, 0), (0, 0, -0.01))):
            want, got = _compare(accel, raster, _camera(200, 150, 120.0, _look(position, target)))
            assert (want.obj == 1).sum() > 100 and (want.obj == 0).sum() > 100
            _agree(want, got, max_other=3)
            assert not np.any(got.obj == 2)
    finally:
        accel.close()


def test_degenerate_triangles_are_never_hit():
    wall = ([[-1, -1, -2], [1, -1, -2], [1, 1, -2], [-1, 1, -2]], [[0, 1, 2], [0, 2, 3]])
    # zero area: three collinear corners, and a triangle with a repeated corner; then a real one
    odd = ([[-0.5, 0, -1], [0, 0, -1], [0.5, 0, -1], [0, 0.5, -1], [0.2, -0.4, -1]], [[0, 1, 2], [3, 3, 4], [0, 3, 4]])
    objects, offsets = _static(wall, odd)
    from dpmhw.render.embree.accel import RtcAccel

    accel = RtcAccel(objects, offsets)
    try:
        want, got = _compare(accel, CameraHits(objects, offsets), _camera(160, 120, 100.0, _look((0, 0, 0), (0, 0, -1))))
        _agree(want, got, max_other=2)
        assert not np.any(np.isin(got.prim, [2, 3])) and np.any(got.prim == 4)
    finally:
        accel.close()


def test_lens_distortion_is_declined():
    objects, offsets = _static(([[-1, -1, -2], [1, -1, -2], [0, 1, -2]], [[0, 1, 2]]))
    camera = _camera(64, 48, 50.0, _look((0, 0, 0), (0, 0, -1)), dist=(0.1, 0, 0, 0, 0))
    with pytest.raises(CameraHitsUnsupported, match="camera.dist"):
        CameraHits(objects, offsets).hits(camera, camera.generate_rays()[1])


def _grid(n, size, rng):
    """A flat n×n-cell square (side `size`, in the y = 0 plane) with each cell's diagonal chosen at
    random: many shared edges in every direction."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    vx, vz = np.meshgrid(xs, xs - size / 2)
    vertices = np.stack([vx.ravel(), np.zeros(vx.size), vz.ravel()], axis=1)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, i * (n + 1) + j + 1, (i + 1) * (n + 1) + j + 1, (i + 1) * (n + 1) + j
            faces += [[a, b, c], [a, c, d]] if rng.random() < 0.5 else [[a, b, d], [b, c, d]]
    return vertices, np.array(faces)


def test_no_holes_along_shared_edges_of_a_large_quad_at_grazing_angles():
    rng = np.random.default_rng(3)
    objects, offsets = _static(_grid(60, 20.0, rng))
    from dpmhw.render.embree.accel import RtcAccel

    accel = RtcAccel(objects, offsets)
    try:
        raster = CameraHits(objects, offsets)
        # grazing: 2 and 5 cm above the quad looking along it; then straight down with the grid's
        # lines through pixel centres (vertex spacing 1/3 m at 1 m height and f = 300: a line every
        # 100 pixels, through the principal point): there the two sides of an edge tie (either
        # triangle is right) and Embree lets a few rays through (the rasteriser must not)
        for pose, f, centre, other in ((_look((0.1, 0.02, -0.5), (0.3, 0.0, -20.0)), 400.0, (0.37, 0.21), 40),
                                       (_look((0.0, 0.05, -1.0), (0.0, 0.0, -9.0)), 300.0, (0.37, 0.21), 40),
                                       (Pose(rotation_about_axis((1, 0, 0), np.pi / 2), np.array([1 / 3, 1.0, -10.0])), 300.0, (0, 0), 3000)):
            camera = _camera(401, 301, f, pose, centre=centre)
            want, got = _compare(accel, raster, camera)
            assert np.mean(want.prim >= 0) > 0.2
            _agree(want, got, max_other=other)
            # every pixel whose ray meets the plane inside the quad (away from its border) is hit
            o, d = camera.generate_rays()
            with np.errstate(divide="ignore", invalid="ignore"):
                s = -o[:, 1].astype(float) / d[:, 1]
            p = o + s[:, None] * d
            inside = (s > 0) & (np.abs(p[:, 0]) < 9.99) & (p[:, 2] < -0.01) & (p[:, 2] > -19.99)
            assert inside.sum() > 1000 and np.all(got.prim[inside] >= 0)
    finally:
        accel.close()


def test_paper_static_matches_embree():
    from dpmhw.benchmarks.render import panned_pose
    from dpmhw.scene_file import load_scene

    scene = load_scene("paper-static")
    geometry = SceneGeometry(scene, threads=2)
    try:
        raster = CameraHits(scene.objects, geometry.tri_offsets)
        r = scene.render
        camera = PinholeCamera(scene.camera.K, scene.camera.dist, r.width, r.height, scene.camera.pose)
        for k in (None, 0, 1):
            cam = camera if k is None else camera.with_pose(panned_pose(camera.pose, k))
            want, got = _compare(geometry.accel, raster, cam)
            # the bunny's triangles are ~3 mm across at 1.5 m: both intersectors' float32 u, v carry
            # errors of a few 1e-4 there (the room's agree to 1e-6)
            _agree(want, got, max_other=5, rel_t=1e-5, uv=2e-3)
    finally:
        geometry.close()


def test_bad_inputs_name_the_field_and_a_scene_without_static_objects_misses():
    objects, offsets = _static(([[-1, -1, -2], [1, -1, -2], [0, 1, -2]], [[0, 1, 2]]))
    camera = _camera(64, 48, 50.0, _look((0, 0, 0), (0, 0, -1)))
    raster = CameraHits(objects, offsets)
    d = camera.generate_rays()[1]
    with pytest.raises(ValueError, match="^d: "):
        raster.hits(camera, d[:-1])
    with pytest.raises(ValueError, match="^d: "):
        raster.hits(camera, d.astype(np.float64))
    objects[0].is_dynamic = True  # nothing static: every pixel misses
    hits = CameraHits(objects, offsets).hits(camera, d)
    assert np.all(hits.prim == -1) and np.all(hits.obj == -1) and np.all(np.isinf(hits.t))


def test_rows_resolved_piecewise_equal_the_whole_frame(make_scene):
    """The integrator's segments can resolve their own pixels (resolve_range) from one z-buffer."""
    from dpmhw.render.embree.accel import empty_hits
    from dpmhw.render.static_raster import resolve_range

    scene = make_scene(ROOM.format(extra=""))
    geometry = SceneGeometry(scene, threads=1)
    try:
        raster = CameraHits(scene.objects, geometry.tri_offsets)
        camera = _camera(96, 64, 80.0, scene.camera.pose)
        d = camera.generate_rays()[1]
        whole = raster.hits(camera, d)
        tri = raster.triangles(camera)
        parts = empty_hits(len(d))
        origin = camera.pose.t.astype(np.float32)
        for a, e in ((0, 1000), (1000, 4097), (4097, len(d))):
            resolve_range(tri, raster.vertices, raster.faces, raster.tri_obj, raster.tri_prim, origin, d, a, e,
                          parts.t, parts.obj, parts.prim, parts.u, parts.v)
        for name in ("t", "obj", "prim", "u", "v"):
            assert np.array_equal(getattr(whole, name), getattr(parts, name)), name
    finally:
        geometry.close()
