"""A simulated world: rigid bodies on scripted trajectories whose true pose is known at any time.

The emulated trackers sample this world, so a test can compare what a driver reports against
the truth at the time the driver says the pose describes. Time is in seconds on whatever clock
the caller uses (the mocks use the host's monotonic clock); each world has an `epoch_s` that
is subtracted first, so trajectories start at t = 0.

Poses are object→world: rotation (3, 3) and translation (3,) in metres, Y up (Motive's default).
Every trajectory is vectorised over time: `pose(t)` takes a scalar or an (n,) array.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation, Slerp

__all__ = [
    "TRAJECTORY_NAMES",
    "Circular",
    "Linear",
    "RecordedPath",
    "RotateWhileOscillating",
    "Static",
    "Trajectory",
    "World",
    "WorldObject",
    "make_trajectory",
]



def _times(t: ArrayLike) -> tuple[np.ndarray, bool]:
    arr = np.asarray(t, dtype=np.float64)
    return arr.reshape(-1), arr.ndim == 0


def _about_y(angle: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations by `angle` (n,) radians about +Y, in closed form (scipy's `Rotation`
    costs ~50 µs a call, and the NatNet mock asks for a pose 360 times a second)."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.zeros((len(angle), 3, 3))
    rot[:, 0, 0] = rot[:, 2, 2] = c
    rot[:, 0, 2] = s
    rot[:, 2, 0] = -s
    rot[:, 1, 1] = 1.0
    return rot


def _about_y_floats(angle: float) -> tuple[float, ...]:
    """`_about_y` of one angle, row-major as 9 floats (the same values: libm's sin and cos)."""
    c, s = math.cos(angle), math.sin(angle)
    return (c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)


_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def _unit(v: ArrayLike) -> tuple[float, float, float]:
    """v / |v| in plain floats (shared by the batch and the one-instant poses, so they agree exactly)."""
    x, y, z = map(float, v)
    norm = math.sqrt(x * x + y * y + z * z)
    return x / norm, y / norm, z / norm


def _squeeze(rot: np.ndarray, pos: np.ndarray, scalar: bool) -> tuple[np.ndarray, np.ndarray]:
    return (rot[0], pos[0]) if scalar else (rot, pos)


class Trajectory:
    """Base: `pose(t)` → rotations (n, 3, 3), translations (n, 3) (no leading axis for scalar t)."""

    def pose(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        ts, scalar = _times(t)
        rot, pos = self._pose(ts)
        return _squeeze(rot, pos, scalar)

    def _pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def pose_floats(self, t: float) -> tuple[tuple[float, ...], tuple[float, float, float]]:
        """The pose at one instant in plain floats: rotation row-major (9 values), translation (3),
        equal to `pose(t)`. The NatNet mock asks 360 times a second, where numpy's per-call cost on
        3-vectors dominated; subclasses compute it in closed form, this default goes through `_pose`."""
        rot, pos = self._pose(np.array([float(t)]))
        return tuple(rot[0].ravel().tolist()), tuple(pos[0].tolist())


@dataclass
class Static(Trajectory):
    translation: ArrayLike = (0.0, 1.0, 0.0)
    rotation: ArrayLike = field(default_factory=lambda: np.eye(3))

    def _pose(self, t):
        n = len(t)
        return np.broadcast_to(np.asarray(self.rotation, float), (n, 3, 3)).copy(), np.tile(
            np.asarray(self.translation, float), (n, 1)
        )

    def pose_floats(self, t):
        return tuple(np.asarray(self.rotation, float).ravel().tolist()), tuple(float(v) for v in self.translation)


@dataclass
class Linear(Trajectory):
    """Constant velocity, fixed orientation."""

    start: ArrayLike = (-0.5, 1.0, 0.0)
    velocity: ArrayLike = (0.1, 0.0, 0.0)  # m/s

    def _pose(self, t):
        pos = np.asarray(self.start, float) + t[:, None] * np.asarray(self.velocity, float)
        return np.tile(np.eye(3), (len(t), 1, 1)), pos

    def pose_floats(self, t):
        (sx, sy, sz), (vx, vy, vz) = self.start, self.velocity
        return _IDENTITY, (float(sx) + t * float(vx), float(sy) + t * float(vy), float(sz) + t * float(vz))


@dataclass
class Circular(Trajectory):
    """Horizontal circle about a vertical (Y) axis, counter-clockwise seen from above; the body
    turns with it so that its -Z axis points along the path."""

    center: ArrayLike = (0.0, 1.0, 0.0)
    radius: float = 0.3
    period_s: float = 2.0

    def _pose(self, t):
        angle = 2 * np.pi * t / self.period_s
        pos = np.asarray(self.center, float) + self.radius * np.stack(
            [np.cos(angle), np.zeros_like(angle), -np.sin(angle)], axis=1
        )
        return _about_y(angle), pos

    def pose_floats(self, t):
        angle = 2 * math.pi * t / self.period_s
        cx, cy, cz = self.center
        r = self.radius
        return _about_y_floats(angle), (float(cx) + r * math.cos(angle), float(cy) + r * 0.0,
                                        float(cz) + r * -math.sin(angle))


@dataclass
class RotateWhileOscillating(Trajectory):
    """The paper's dynamic scene: the object spins about its vertical axis while it moves back
    and forth (sinusoidally) along a horizontal direction."""

    center: ArrayLike = (0.0, 1.0, 0.0)
    direction: ArrayLike = (1.0, 0.0, 0.0)
    amplitude_m: float = 0.15
    oscillation_hz: float = 0.5
    spin_rad_s: float = np.pi / 2

    def _pose(self, t):
        d = np.array(_unit(self.direction))
        offset = self.amplitude_m * np.sin(2 * np.pi * self.oscillation_hz * t)
        pos = np.asarray(self.center, float) + offset[:, None] * d
        return _about_y(self.spin_rad_s * t), pos

    def pose_floats(self, t):
        dx, dy, dz = _unit(self.direction)
        offset = self.amplitude_m * math.sin(2 * math.pi * self.oscillation_hz * t)
        cx, cy, cz = self.center
        return _about_y_floats(self.spin_rad_s * t), (float(cx) + offset * dx, float(cy) + offset * dy,
                                                      float(cz) + offset * dz)


class RecordedPath(Trajectory):
    """A recorded path: positions interpolated linearly, rotations by slerp; held at the ends,
    or repeated when `loop` is set."""

    def __init__(self, times_s: ArrayLike, positions: ArrayLike, quaternions_xyzw: ArrayLike, loop: bool = False):
        self.times = np.asarray(times_s, dtype=np.float64).reshape(-1)
        self.positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        quats = np.asarray(quaternions_xyzw, dtype=np.float64).reshape(-1, 4)
        n = len(self.times)
        if n < 2 or len(self.positions) != n or len(quats) != n:
            raise ValueError(
                f"recorded path: need >= 2 samples with matching lengths, got {n} times, "
                f"{len(self.positions)} positions, {len(quats)} quaternions"
            )
        if np.any(np.diff(self.times) <= 0):
            raise ValueError("recorded path: times must increase strictly")
        self.rotations = Rotation.from_quat(quats)
        self._slerp = Slerp(self.times, self.rotations)
        self.loop = loop

    @classmethod
    def from_csv(cls, path: str | Path, loop: bool = False) -> "RecordedPath":
        """CSV with a header row `t,x,y,z,qx,qy,qz,qw` (seconds, metres, unit quaternion)."""
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        try:
            a = np.array([[float(r[k]) for k in ("t", "x", "y", "z", "qx", "qy", "qz", "qw")] for r in rows])
        except (KeyError, ValueError) as exc:
            raise ValueError(f"{path}: expected columns t,x,y,z,qx,qy,qz,qw with numbers ({exc})") from None
        return cls(a[:, 0], a[:, 1:4], a[:, 4:8], loop=loop)

    def _pose(self, t):
        t0, t1 = self.times[0], self.times[-1]
        tt = t0 + np.mod(t - t0, t1 - t0) if self.loop else np.clip(t, t0, t1)
        pos = np.stack([np.interp(tt, self.times, self.positions[:, k]) for k in range(3)], axis=1)
        return self._slerp(tt).as_matrix(), pos


def _demo_recording() -> RecordedPath:
    """A figure-eight 'recording' sampled at 120 Hz, standing in for a captured path."""
    t = np.arange(0, 4.0 + 1e-9, 1 / 120)
    pos = np.stack([0.25 * np.sin(2 * np.pi * t / 4), 1.0 + 0.05 * np.sin(4 * np.pi * t / 4), 0.15 * np.sin(4 * np.pi * t / 4)], 1)
    quats = Rotation.from_euler("yx", np.stack([0.8 * np.sin(2 * np.pi * t / 4), 0.3 * np.cos(2 * np.pi * t / 4)], 1)).as_quat()
    return RecordedPath(t, pos, quats, loop=True)


TRAJECTORY_NAMES = ("static", "linear", "circular", "rotate-oscillate", "recorded")


def make_trajectory(name: str, speed: float = 1.0) -> Trajectory:
    """A trajectory by CLI name, with default parameters; `speed` scales every velocity
    (linear and angular) by running the trajectory's clock faster."""
    factories = {
        "static": Static,
        "linear": Linear,
        "circular": Circular,
        "rotate-oscillate": RotateWhileOscillating,
        "recorded": _demo_recording,
    }
    if name not in factories:
        raise ValueError(f"unknown trajectory {name!r}; choose one of {', '.join(TRAJECTORY_NAMES)}")
    if not speed > 0:
        raise ValueError(f"trajectory speed must be positive, got {speed}")
    traj = factories[name]()
    return traj if speed == 1.0 else _TimeScaled(traj, speed)


def default_markers(seed: int) -> np.ndarray:
    """(4, 3) asymmetric marker layout in the body frame (metres), distinct per body."""
    rng = np.random.default_rng(seed)
    base = np.array([[0.05, 0.0, 0.0], [-0.04, 0.0, 0.03], [0.0, 0.03, -0.05], [-0.02, 0.06, 0.02]])
    return base + rng.uniform(-0.01, 0.01, base.shape)


@dataclass
class WorldObject:
    rigid_body_id: int
    name: str
    trajectory: Trajectory
    markers: np.ndarray  # (k, 3) body frame, metres


class World:
    """Rigid bodies on trajectories; `epoch_s` is subtracted from every query time."""

    def __init__(self, objects: list[WorldObject] | None = None, epoch_s: float = 0.0):
        self.objects: dict[int, WorldObject] = {}
        self.epoch_s = float(epoch_s)
        for obj in objects or []:
            self.objects[obj.rigid_body_id] = obj

    def add(self, rigid_body_id: int, name: str, trajectory: Trajectory, markers: ArrayLike | None = None) -> WorldObject:
        if rigid_body_id in self.objects:
            raise ValueError(f"rigid body id {rigid_body_id} is already in the world")
        m = default_markers(rigid_body_id) if markers is None else np.asarray(markers, float).reshape(-1, 3)
        obj = WorldObject(int(rigid_body_id), name, trajectory, m)
        self.objects[obj.rigid_body_id] = obj
        return obj

    @classmethod
    def demo(cls, trajectory: str = "rotate-oscillate", epoch_s: float = 0.0, count: int = 1, speed: float = 1.0) -> "World":
        """`count` bodies (ids 1, 2, …) on the named trajectory, spaced 0.5 m apart along Z."""
        world = cls(epoch_s=epoch_s)
        for i in range(count):
            traj = make_trajectory(trajectory, speed)
            if i:
                traj = _Shifted(traj, np.array([0.0, 0.0, 0.5 * i]))
            world.add(i + 1, f"{trajectory}_{i + 1}", traj)
        return world

    def pose(self, rigid_body_id: int, t_s: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """True (rotation, translation) of one body at time(s) `t_s`."""
        return self.objects[rigid_body_id].trajectory.pose(np.asarray(t_s, np.float64) - self.epoch_s)

    def pose_floats(self, rigid_body_id: int, t_s: float) -> tuple[tuple[float, ...], tuple[float, float, float]]:
        """`pose` at one instant in plain floats: rotation row-major (9 values), translation (3)."""
        return self.objects[rigid_body_id].trajectory.pose_floats(float(t_s) - self.epoch_s)

    def markers(self, rigid_body_id: int, t_s: float) -> np.ndarray:
        """(k, 3) world positions of a body's markers at time `t_s`."""
        rot, pos = self.pose(rigid_body_id, t_s)
        return self.objects[rigid_body_id].markers @ rot.T + pos


class _Shifted(Trajectory):
    def __init__(self, inner: Trajectory, shift: np.ndarray):
        self.inner, self.shift = inner, shift

    def _pose(self, t):
        rot, pos = self.inner._pose(t)
        return rot, pos + self.shift

    def pose_floats(self, t):
        rot, (x, y, z) = self.inner.pose_floats(t)
        sx, sy, sz = self.shift.tolist()
        return rot, (x + sx, y + sy, z + sz)


class _TimeScaled(Trajectory):
    def __init__(self, inner: Trajectory, speed: float):
        self.inner, self.speed = inner, speed

    def _pose(self, t):
        return self.inner._pose(t * self.speed)

    def pose_floats(self, t):
        return self.inner.pose_floats(t * self.speed)
