import numpy as np
import pytest

from dpmhw.render.cameras import PinholeCamera
from dpmhw.transforms import Pose


def make_camera(w, h, f=10.0, cx=None, cy=None, dist=None, pose=None):
    K = np.array([[f, 0.0, (w - 1) / 2 if cx is None else cx], [0.0, f, (h - 1) / 2 if cy is None else cy], [0.0, 0.0, 1.0]])
    return PinholeCamera(K, np.zeros(5) if dist is None else dist, w, h, Pose.identity() if pose is None else pose)


def plane_gbuffer(camera, depth=2.0, pose=None):
    """G-buffer of a plane z = depth (camera at the origin looking down +z) held by object 0 at
    `pose`: each pixel centre's model-space hit point, exactly."""
    pose = Pose.identity() if pose is None else pose
    h, w = camera.height, camera.width
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    K = camera.K
    world = np.stack([(xs - K[0, 2]) / K[0, 0] * depth, (ys - K[1, 2]) / K[1, 1] * depth, np.full(xs.shape, depth)], axis=-1)
    model = (world.reshape(-1, 3) - pose.t) @ pose.R  # R^T (x − t)
    return np.zeros((h, w), np.int32), model.reshape(h, w, 3).astype(np.float32)


@pytest.fixture
def static_view():
    """(ids, model_position, poses, camera) of a static plane filling the view."""

    def make(h, w):
        cam = make_camera(w, h)
        ids, mpos = plane_gbuffer(cam)
        return ids, mpos, [Pose.identity()], cam

    return make
