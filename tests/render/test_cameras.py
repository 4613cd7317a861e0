import cv2
import numpy as np
import pytest

from dpmhw.render.cameras import PinholeCamera
from dpmhw.transforms import look_at


@pytest.fixture
def camera():
    K = np.array([[900.0, 0, 300.0], [0, 880.0, 410.0], [0, 0, 1]])  # strong vertical lens shift
    dist = np.array([-0.25, 0.08, 0.001, -0.002, 0.0])
    return PinholeCamera(K, dist, 320, 240, look_at([0.3, 0.2, 2.0], [0, 0, 0], [0, 1, 0]))


def test_project_matches_opencv(camera, np_rng):
    pts = np_rng.uniform(-0.5, 0.5, (200, 3))
    ours, in_front = camera.project(pts)
    inv = camera.pose.inverse()
    rvec, _ = cv2.Rodrigues(inv.R)
    ref, _ = cv2.projectPoints(pts, rvec, inv.t, camera.K, camera.dist)
    assert in_front.all()
    np.testing.assert_allclose(ours, ref[:, 0], atol=1e-6)


def test_primary_rays_reproject_to_their_pixel_centres(camera):
    o, d = camera.generate_rays()
    px, in_front = camera.project(o + 1.7 * d.astype(np.float64))
    ys, xs = np.mgrid[0:240, 0:320]
    assert in_front.all()
    np.testing.assert_allclose(px[:, 0], xs.ravel(), atol=2e-3)
    np.testing.assert_allclose(px[:, 1], ys.ravel(), atol=2e-3)  # row 0 at the top


def test_camera_axes_follow_opencv(camera):
    o, d = camera.generate_rays()
    d = d.reshape(240, 320, 3)
    # with up = +y, the top rows of the image look higher than the bottom rows
    assert d[0, 160, 1] > d[-1, 160, 1]
    # x grows to the right of the image: the ray right of the centre points to +x (camera at +z)
    assert d[120, -1, 0] > d[120, 0, 0]


def _fma_chain_reference(dirs_cam, R):
    """R @ d per ray as the float32 FMA chain x·R[j,0] → +y·R[j,1] → +z·R[j,2], emulated in
    float64 (a float32 product is exact there; one rounding to float32 per step)."""
    D, R = dirs_cam.astype(np.float64), R.astype(np.float32).astype(np.float64)

    def f32(a):
        return a.astype(np.float32).astype(np.float64)

    return np.stack([f32(D[:, 2] * R[j, 2] + f32(D[:, 1] * R[j, 1] + f32(D[:, 0] * R[j, 0]))) for j in range(3)], 1).astype(np.float32)


def test_rays_are_the_compiled_rotation_bit_for_bit_with_distortion(camera):
    """generate_rays and rays_into (any row ranges, buffers reused across poses) give the same
    bits: the FMA chain OpenBLAS's sgemm computes for `dirs_cam @ R.T` on an FMA CPU, i.e. the
    numpy rays of earlier versions there; within a float32 rounding of the exact rotation."""
    from dpmhw.transforms import Pose, rotation_about_axis

    n = 320 * 240
    o_buf, d_buf = np.full((n, 3), np.nan, np.float32), np.full((n, 3), np.nan, np.float32)
    for k, angle in enumerate((0.0, 0.7, -0.3, 0.0)):
        cam = camera.with_pose(Pose(rotation_about_axis((0.0, 1.0, 0.0), np.radians(angle)) @ camera.pose.R, camera.pose.t + 0.01 * k))
        o, d = cam.generate_rays()
        for first, end in ((0, 1001), (1001, 50000), (50000, n)):  # as the render threads split it
            cam.rays_into(o_buf, d_buf, first, end)
        assert np.array_equal(o_buf, o) and np.array_equal(d_buf, d)
        assert np.array_equal(d, _fma_chain_reference(cam._dirs_cam, cam.pose.R))
        np.testing.assert_array_equal(o, np.broadcast_to(cam.pose.t.astype(np.float32), (n, 3)))
        exact = cam._dirs_cam.astype(np.float64) @ cam.pose.R.astype(np.float32).astype(np.float64).T
        np.testing.assert_allclose(d, exact, rtol=0, atol=2.5e-7)
        assert not o.flags.writeable and not d.flags.writeable




@pytest.mark.parametrize("mode", ["centre", "jitter"])
def test_panned_frames_reuse_the_ray_buffers_without_stale_rays(make_scene, mode):
    """The integrator rewrites its camera-ray buffers in place for each new pose: a distorted
    projector panned away and back renders, frame by frame, the image a fresh integrator
    renders at that pose (centre and jittered pixel sampling), and the rays it traced are
    generate_rays' for the pose."""
    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.transforms import Pose, rotation_about_axis

    from .test_integrator import ROOM

    scene = make_scene(ROOM.format(extra="").replace("cy = 12.0\n", "cy = 12.0\ndist = [-0.2, 0.05, 0.001, -0.002, 0.0]\n"))
    assert scene.camera.dist[0] == -0.2
    p0 = scene.camera.pose
    poses = [Pose(rotation_about_axis((0.0, 1.0, 0.0), np.radians(a)) @ p0.R, p0.t + np.array([0.005 * a, 0.0, 0.0])) for a in (0.0, 4.0, -3.0, 0.0, 0.0)]
    with PathIntegrator(scene, threads=2, pixel_sampling=mode) as integrator:
        frames = [integrator.render(seed=k, spp=2, camera_pose=pose) for k, pose in enumerate(poses)]
        o, d = integrator._camera_rays(integrator.camera.with_pose(poses[-1]))
        o_ref, d_ref = integrator.camera.with_pose(poses[-1]).generate_rays()
        assert np.array_equal(o, o_ref) and np.array_equal(d, d_ref)
    assert not np.array_equal(frames[0].object_id, frames[1].object_id)  # the pans change the view
    assert frames[0].radiance.max() > 0
    for k, pose in enumerate(poses):
        with PathIntegrator(scene, threads=1, pixel_sampling=mode) as fresh:
            ref = fresh.render(seed=k, spp=2, camera_pose=pose)
        assert np.array_equal(frames[k].radiance, ref.radiance), k
        assert np.array_equal(frames[k].position, ref.position), k
