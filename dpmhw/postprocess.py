"""Linear radiance → the uint8 frame a projector receives.

The operator, in order, per pixel and channel (x = linear radiance, float32):

1. Exposure: x ← exposure · x.
2. Tone mapping, one of
   - ``clip`` (default): x ← min(x, 1). The projector's full white is radiance 1; what is brighter
     saturates. This keeps radiance linear below white, which is what PSNR against a reference
     should see, and is the operator used by ``dpmhw bench quality``.
   - ``reinhard``: extended Reinhard per channel, x ← x (1 + x / w²) / (1 + x) with white point
     w (default 4): x = w maps to 1, highlights roll off instead of clipping.
3. Transfer to code values, one of
   - sRGB (IEC 61966-2-1): 12.92 x for x ≤ 0.0031308, else 1.055 x^(1/2.4) − 0.055; then
     round(255 · v).
   - a projector response table (``ProjectorResponse``): the projector's measured linear output
     per code value, inverted by linear interpolation, so the light that leaves the projector is
     the tone-mapped radiance.

NaN/Inf never reach the projector: they are an error here (the renderer counts and drops them,
temporal reuse keeps them out of its history).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

TONEMAPS = ("clip", "reinhard")


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function on values in [0, 1]."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Inverse of `srgb_encode` on values in [0, 1]."""
    v = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4))


def tonemap(radiance: np.ndarray, operator: str = "clip", white: float = 4.0) -> np.ndarray:
    """Exposed linear radiance → display-linear values in [0, 1] (see the module docstring)."""
    x = np.maximum(np.asarray(radiance, dtype=np.float32), np.float32(0.0))
    if operator == "clip":
        return np.minimum(x, np.float32(1.0))
    if operator == "reinhard":
        if not (np.isfinite(white) and white > 0):
            raise ValueError(f"white: expected a positive number, got {white!r}")
        w2 = np.float32(white) ** 2
        return np.minimum(x * (1 + x / w2) / (1 + x), np.float32(1.0))
    raise ValueError(f"tonemap: expected one of {', '.join(TONEMAPS)}, got {operator!r}")


@dataclass(frozen=True)
class ProjectorResponse:
    """Measured projector response: ``linear[i]`` (per channel, normalised so full white is 1)
    is the light the projector emits for code value ``codes[i]``.

    codes : (n,) increasing integers in [0, 255]
    linear : (n, 3) non-decreasing per channel, in [0, 1]
    """

    codes: np.ndarray
    linear: np.ndarray

    def __post_init__(self):
        codes = np.asarray(self.codes, dtype=np.float64)
        lin = np.asarray(self.linear, dtype=np.float64)
        if lin.ndim == 1:
            lin = np.repeat(lin[:, None], 3, axis=1)
        if codes.ndim != 1 or len(codes) < 2 or lin.shape != (len(codes), 3):
            raise ValueError(f"projector response: expected n ≥ 2 codes and (n,) or (n, 3) linear values, got {codes.shape} and {np.shape(self.linear)}")
        if np.any(np.diff(codes) <= 0) or codes[0] < 0 or codes[-1] > 255:
            raise ValueError("projector response: codes must increase strictly within [0, 255]")
        if not np.all(np.isfinite(lin)) or np.any(np.diff(lin, axis=0) < 0):
            raise ValueError("projector response: linear output must be finite and non-decreasing in the code value")
        object.__setattr__(self, "codes", codes)
        object.__setattr__(self, "linear", lin)

    @classmethod
    def from_csv(cls, path: str | Path) -> "ProjectorResponse":
        """CSV with a header; columns ``code,linear`` or ``code,r,g,b``."""
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        if data.shape[1] not in (2, 4):
            raise ValueError(f"{path}: expected columns code,linear or code,r,g,b, got {data.shape[1]} columns")
        return cls(data[:, 0], data[:, 1:] if data.shape[1] == 4 else data[:, 1])

    def encode(self, display_linear: np.ndarray) -> np.ndarray:
        """Display-linear values in [0, 1] → float code values (inverse interpolation)."""
        v = np.asarray(display_linear, dtype=np.float64)
        out = np.empty(v.shape, np.float64)
        for c in range(3):
            lin, codes = self.linear[:, c], self.codes
            keep = np.concatenate([[True], np.diff(lin) > 0])  # flat steps: the lowest code wins
            out[..., c] = np.interp(v[..., c], lin[keep], codes[keep])
        return out


def postprocess(radiance: np.ndarray, exposure: float = 1.0, operator: str = "clip", white: float = 4.0,
                response: ProjectorResponse | None = None) -> np.ndarray:
    """(H, W, 3) float linear radiance → (H, W, 3) uint8 projector frame (see the module docstring)."""
    radiance = np.asarray(radiance)
    if not np.all(np.isfinite(radiance)):
        raise ValueError("radiance has NaN/Inf pixels; refusing to send them to the projector")
    if not (np.isfinite(exposure) and exposure >= 0):
        raise ValueError(f"exposure: expected a finite number ≥ 0, got {exposure!r}")
    display = tonemap(radiance * np.float32(exposure), operator, white)
    if response is None:
        return (srgb_encode(display) * 255.0 + 0.5).astype(np.uint8)
    return np.clip(response.encode(display) + 0.5, 0, 255).astype(np.uint8)


def to_srgb8(radiance: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """(H, W, 3) float linear radiance → (H, W, 3) uint8 sRGB (exposure, clip, sRGB)."""
    return postprocess(radiance, exposure, "clip")


def write_png(path, frame_uint8: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), np.ascontiguousarray(frame_uint8[..., ::-1])):
        raise OSError(f"could not write {path}")
