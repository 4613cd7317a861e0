"""Scripted rigid motion, so benchmark sequences are reproducible: pose(t) for an object."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dpmhw.transforms import Pose, rotation_about_axis


@dataclass(frozen=True)
class ScriptedMotion:
    """Rotate about an axis through the object's origin at a constant rate while translating
    linearly and oscillating sinusoidally along a direction (all terms optional, they add up)."""

    rotate_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    rotate_deg_per_s: float = 0.0
    oscillate_direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    oscillate_amplitude: float = 0.0  # metres
    oscillate_period_s: float = 1.0
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # metres per second

    def pose_at(self, t: float, base: Pose) -> Pose:
        R = rotation_about_axis(self.rotate_axis, np.radians(self.rotate_deg_per_s) * t) @ base.R
        direction = np.asarray(self.oscillate_direction, dtype=float)
        direction = direction / np.linalg.norm(direction)
        offset = direction * self.oscillate_amplitude * np.sin(2 * np.pi * t / self.oscillate_period_s)
        return Pose(R, base.t + offset + np.asarray(self.velocity, dtype=float) * t)
