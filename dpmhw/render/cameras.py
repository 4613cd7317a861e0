"""OpenCV pinhole + distortion cameras (a projector is one): pixel → ray and point → pixel.

Same convention as `cv2.projectPoints`: camera x right, y down, z forward; pixel (0, 0) is the
centre of the top-left pixel, which covers [−0.5, 0.5]². Lens distortion is inverted once per
pixel (iteratively, to 1e-12) when the camera is built, so per-frame ray generation is one
rotation. Rays through any point of a pixel (pixel jitter) interpolate the undistorted image
plane bilinearly between the pixel's corners, which are inverted the same way: exact without
distortion, and within the distortion's curvature over one pixel with it
(`kernels.jittered_directions`).
"""

from __future__ import annotations

import cv2
import numpy as np

from dpmhw.render import kernels
from dpmhw.render.distortion import distort
from dpmhw.transforms import Pose

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


class PinholeCamera:
    """K : (3, 3); dist : (5,) k1 k2 p1 p2 k3; pose : camera→world."""

    def __init__(self, K, dist, width: int, height: int, pose: Pose):
        self.K = np.asarray(K, dtype=np.float64)
        self.dist = np.asarray(dist, dtype=np.float64).reshape(5)
        self.width, self.height = int(width), int(height)
        self.pose = pose
        self._dirs_cam = self._pixel_directions()
        self._corners = None

    def _ideal(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Pixel coordinates → undistorted normalised image coordinates (n, 2), float64."""
        pixels = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2).astype(np.float64)
        if np.any(self.dist != 0):
            return cv2.undistortPoints(pixels, self.K, self.dist, R=np.eye(3), P=np.eye(3), criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
        return np.stack([(pixels[:, 0, 0] - self.K[0, 2]) / self.K[0, 0], (pixels[:, 0, 1] - self.K[1, 2]) / self.K[1, 1]], axis=1)

    def _pixel_directions(self) -> np.ndarray:
        """(H*W, 3) float32 unit directions in camera space through pixel centres, row-major."""
        ys, xs = np.mgrid[0 : self.height, 0 : self.width]
        xy = self._ideal(xs, ys)
        d = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d.astype(np.float32)

    def ideal_points(self) -> np.ndarray:
        """(H*W, 2) float32 undistorted image-plane points (X/Z, Y/Z) of the pixel centres' rays,
        row-major: a pixel at camera depth z shows the camera-space point z·(x, y, 1)."""
        d = self._dirs_cam
        return np.ascontiguousarray(d[:, :2] / d[:, 2:3], np.float32)

    def pixel_corners(self) -> np.ndarray:
        """(H + 1, W + 1, 2) float32 undistorted image coordinates of the pixel corners (built once)."""
        if self._corners is None:
            ys, xs = np.mgrid[0 : self.height + 1, 0 : self.width + 1] - 0.5
            self._corners = self._ideal(xs, ys).reshape(self.height + 1, self.width + 1, 2).astype(np.float32)
        return self._corners

    def with_pose(self, pose: Pose) -> "PinholeCamera":
        """The same intrinsics at another pose, without recomputing the undistortion."""
        other = object.__new__(PinholeCamera)
        other.__dict__.update(self.__dict__)
        other.pose = pose
        other._rays_key = None
        return other

    def generate_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays through every pixel centre: origins (n, 3), directions (n, 3), float32,
        row-major. Cached per pose: a projector rarely moves between frames. (A per-frame
        renderer keeps its own buffers and calls `rays_into` instead.)"""
        key = (self.pose.R.tobytes(), self.pose.t.tobytes())
        if getattr(self, "_rays_key", None) != key:
            n = len(self._dirs_cam)
            o, d = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
            self.rays_into(o, d, 0, n)
            o.flags.writeable = d.flags.writeable = False
            self._rays, self._rays_key = (o, d), key
        return self._rays

    def rays_into(self, o: np.ndarray, d: np.ndarray, first: int, end: int) -> None:
        """Write the rays of pixels [first, end) into rows [first, end) of o, d ((n, 3) float32),
        compiled and without temporaries (`kernels.camera_rays`): callers split the image
        between threads and reuse the buffers from frame to frame."""
        kernels.camera_rays(self._dirs_cam, self.pose.R.astype(np.float32), self.pose.t.astype(np.float32), first, end, o, d)

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """points : (n, 3) world → pixels (n, 2) float64 and in_front (n,) bool (z > 0)."""
        cam = (np.asarray(points_world, dtype=np.float64) - self.pose.t) @ self.pose.R
        z = cam[:, 2]
        safe_z = np.where(z > 1e-12, z, 1.0)
        x, y = cam[:, 0] / safe_z, cam[:, 1] / safe_z
        xd, yd = distort(x, y, *self.dist)
        px = np.stack([self.K[0, 0] * xd + self.K[0, 2], self.K[1, 1] * yd + self.K[1, 2]], axis=1)
        return px, z > 1e-12
