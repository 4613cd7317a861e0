"""Rigid transforms: rotation matrix + translation (object→world), converted from the wire once.

Quaternions are (x, y, z, w) as NatNet sends them and as scipy stores them. Euler angles in scene
files are extrinsic XYZ in degrees: rotate about world X, then world Y, then world Z (R = Rz·Ry·Rx).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Pose:
    """Object→world rigid transform: x_world = R @ x_object + t."""

    R: np.ndarray  # (3, 3) float64
    t: np.ndarray  # (3,) float64

    @staticmethod
    def identity() -> "Pose":
        return Pose(np.eye(3), np.zeros(3))

    def inverse(self) -> "Pose":
        return Pose(self.R.T, -self.R.T @ self.t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """points : (n, 3) → (n, 3)."""
        return points @ self.R.T + self.t


def rotation_from_euler_xyz_deg(angles) -> np.ndarray:
    return Rotation.from_euler("xyz", np.asarray(angles, dtype=float), degrees=True).as_matrix()


def rotation_from_quat_xyzw(q) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"quaternion {q.tolist()} has no direction (norm {norm})")
    return Rotation.from_quat(q / norm).as_matrix()


def rotation_about_axis(axis, angle_rad: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle_rad).as_matrix()


def look_at(position, target, up) -> Pose:
    """Camera→world pose for an OpenCV camera (x right, y down, z forward) at `position` looking at `target`."""
    position = np.asarray(position, dtype=float)
    forward = np.asarray(target, dtype=float) - position
    fn = np.linalg.norm(forward)
    if fn < 1e-12:
        raise ValueError("look_at equals position: the view direction is undefined")
    z = forward / fn
    x = np.cross(z, np.asarray(up, dtype=float))
    xn = np.linalg.norm(x)
    if xn < 1e-9:
        raise ValueError("up is parallel to the view direction")
    x /= xn
    y = np.cross(z, x)  # points down in the image when `up` points up
    return Pose(np.stack([x, y, z], axis=1), position)
