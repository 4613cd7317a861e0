"""Linear radiance → the uint8 sRGB frame a projector receives.

Exposure scales radiance, values are clipped to [0, 1] (the projector's full white), then encoded
with the sRGB transfer function (IEC 61966-2-1). NaN/Inf never reach the projector: they are an
error here, because the renderer counts and drops them before this stage.
"""

from __future__ import annotations

import numpy as np


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function on values in [0, 1]."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def to_srgb8(radiance: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """(H, W, 3) float linear radiance → (H, W, 3) uint8 sRGB."""
    if not np.all(np.isfinite(radiance)):
        raise ValueError("radiance has NaN/Inf pixels; refusing to send them to the projector")
    encoded = srgb_encode(np.asarray(radiance, dtype=np.float32) * np.float32(exposure))
    return (encoded * 255.0 + 0.5).astype(np.uint8)


def write_png(path, frame_uint8: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), np.ascontiguousarray(frame_uint8[..., ::-1])):
        raise OSError(f"could not write {path}")
