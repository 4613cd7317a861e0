"""What one rendered frame carries: radiance (split by lobe) and the G-buffer later stages read."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Frame:
    """All images (H, W, ...) with row 0 at the top; radiance is linear, float32.

    radiance = emitted + diffuse + specular, where `emitted` is what the camera sees directly
    (lights, background), and `diffuse` / `specular` is the light reflected at the first hit,
    split by the lobe that reflected it (not demodulated: divide by albedo to demodulate).
    The G-buffer describes the first hit through each pixel centre (with pixel jitter: through
    the first pass's point in the pixel): object_id (−1 background),
    model_position (hit point in the object's own coordinates, for reprojection), position and
    normal (world, the normal faces the viewer), depth (camera z), albedo, specular_albedo,
    roughness.
    """

    radiance: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    object_id: np.ndarray
    model_position: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    albedo: np.ndarray
    specular_albedo: np.ndarray
    roughness: np.ndarray
    spp: int
    time: float
    seed: int
    nonfinite_samples: int = 0  # samples dropped because they were NaN/Inf: a bug to report

    @property
    def shape(self) -> tuple[int, int]:
        return self.radiance.shape[:2]
