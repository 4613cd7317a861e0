"""Rigid transforms: rotation matrix + translation (object→world), converted from the wire once.

Quaternions are (x, y, z, w) as NatNet sends them and as scipy stores them. Euler angles in scene
files are extrinsic XYZ in degrees: rotate about world X, then world Y, then world Z (R = Rz·Ry·Rx).
"""

from __future__ import annotations

import math
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


_NAN_ROTATION = (math.nan,) * 9


def quaternion_xyzw_to_rotation(x: float, y: float, z: float, w: float) -> tuple[float, ...]:
    """Rotation matrix, row-major as 9 floats, of one (x, y, z, w) quaternion (not necessarily
    normalised); all NaN where the quaternion is zero, huge or not finite.

    Plain floats: a tracker frame carries a handful of bodies and arrives hundreds of times a
    second on the receiver thread, where numpy's per-call cost on 4-element arrays dominated."""
    n2 = x * x + y * y + z * z + w * w  # inf for huge or non-finite entries, nan for nan
    if not (1e-12 < n2 < math.inf):
        return _NAN_ROTATION
    s = 2.0 / n2  # normalises and doubles in one factor
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    return (1.0 - (yy + zz), xy - wz, xz + wy,
            xy + wz, 1.0 - (xx + zz), yz - wx,
            xz - wy, yz + wx, 1.0 - (xx + yy))


def quat_xyzw_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a (3, 3) rotation matrix, w >= 0 (Motive's convention)."""
    return quat_xyzw_of_rows(*np.asarray(r, np.float64).ravel().tolist())


def quat_xyzw_of_rows(m00: float, m01: float, m02: float, m10: float, m11: float, m12: float,
                  m20: float, m21: float, m22: float) -> tuple[float, float, float, float]:
    """`quat_xyzw_from_matrix` of a matrix given row by row as 9 floats.

    Shepperd's method in plain floats (branch on the largest of w², x², y², z², so the square
    root is never of a small number): it runs for every body of every frame, 360 times a second
    on an emulator's streaming thread, where scipy's `Rotation` took ~100 µs of a frame's ~250 µs."""
    trace = m00 + m11 + m22
    if trace >= max(m00, m11, m22):
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s)
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        q = (0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif m11 >= m22:
        s = 2.0 * math.sqrt(max(1.0 - m00 + m11 - m22, 0.0))
        q = ((m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 - m00 - m11 + m22, 0.0))
        q = ((m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s)
    x, y, z, w = q
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0:
        norm = -norm
    return x / norm, y / norm, z / norm, w / norm


def rotation_from_quat_xyzw(q) -> np.ndarray:
    """(3, 3) rotation of an (x, y, z, w) quaternion of any length; a ValueError when it has none."""
    q = np.asarray(q, dtype=float)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"quaternion {q.tolist()} has no direction (norm {norm})")
    return np.array(quaternion_xyzw_to_rotation(*(q / norm).tolist())).reshape(3, 3)


def rotation_about_axis(axis, angle_rad: float) -> np.ndarray:
    """Rotation by `angle_rad` about `axis`; the angle is taken modulo a turn (exactly, by fmod), so
    a scripted rotation far out on a timeline stays a rotation instead of overflowing."""
    if not math.isfinite(angle_rad):
        raise ValueError(f"rotation angle {angle_rad!r} rad is not finite")
    axis = np.asarray(axis, dtype=float)
    return rotvec_to_matrix(axis / np.linalg.norm(axis) * math.fmod(angle_rad, 2.0 * math.pi))


def rotvec_to_matrix(w) -> np.ndarray:
    """exp: the rotation by |w| radians about w (Rodrigues), series-expanded for tiny angles.

    The predictor's two maps between rotations and rotation vectors run per body per frame on the
    loop's thread; in plain floats they cost a few µs where scipy's `Rotation` costs ~50 each."""
    x, y, z = (float(c) for c in np.asarray(w, np.float64).reshape(3))
    return np.array(rotvec_to_floats(x, y, z)).reshape(3, 3)


def rotvec_to_floats(x: float, y: float, z: float) -> tuple[float, ...]:
    """`rotvec_to_matrix` on plain floats: the matrix as 9 floats, row-major (for code that runs
    per tracker sample, where numpy's per-call cost dominates)."""
    t2 = x * x + y * y + z * z
    if t2 < 1e-12:  # sin θ/θ ≈ 1 − θ²/6, (1 − cos θ)/θ² ≈ ½ − θ²/24: exact to double precision here
        a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        a, b = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    return (1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y,
            b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x,
            b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y))


def matrix_to_rotvec(R) -> np.ndarray:
    """log: the rotation vector (angle in [0, π] times the unit axis) of a rotation matrix.

    Through the unit quaternion (Shepperd's choice of the largest component, so no root of a
    small number) and θ = 2·atan2(|v|, w): accurate at 0 and at π alike."""
    return np.array(rotvec_of_floats(np.asarray(R, np.float64).reshape(9).tolist()))


def rotvec_of_floats(m) -> tuple[float, float, float]:
    """`matrix_to_rotvec` of a rotation given as 9 plain floats, row-major."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    trace = m00 + m11 + m22
    if trace >= max(m00, m11, m22):
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        qx, qy, qz, qw = (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        qx, qy, qz, qw = 0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s
    elif m11 >= m22:
        s = 2.0 * math.sqrt(max(1.0 - m00 + m11 - m22, 0.0))
        qx, qy, qz, qw = (m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 - m00 - m11 + m22, 0.0))
        qx, qy, qz, qw = (m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s
    if qw < 0.0:  # the shorter way round: angle ≤ π
        qx, qy, qz, qw = -qx, -qy, -qz, -qw
    v = math.sqrt(qx * qx + qy * qy + qz * qz)
    if v < 1e-300:
        return 0.0, 0.0, 0.0
    k = 2.0 * math.atan2(v, qw) / v
    return k * qx, k * qy, k * qz


def angle_of_floats(m) -> float:
    """The rotation angle (radians, 0…π) of a rotation given as 9 plain floats, row-major; robust
    near 0 and π (the norm of `rotvec_of_floats`)."""
    x, y, z = rotvec_of_floats(m)
    return math.sqrt(x * x + y * y + z * z)


def matmul_floats(a, b) -> tuple[float, ...]:
    """a·b of two 3×3 matrices given as 9 plain floats, row-major."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = b
    return (a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
            a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
            a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8)


def matmul_bt_floats(a, b) -> tuple[float, ...]:
    """a·bᵀ of two 3×3 matrices given as 9 plain floats, row-major (for rotations: the turn from b to a)."""
    return matmul_floats(a, (b[0], b[3], b[6], b[1], b[4], b[7], b[2], b[5], b[8]))


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
