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
