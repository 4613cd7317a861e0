"""Vectorised Gray-code decoding with shadow and reliability masks.

A camera pixel's bit is the sign of ``pattern - inverse``, which is independent of the
camera's response curve, the surface albedo and ambient light.  Three things make a pixel
unusable and are masked:

* **shadow / low dynamic range** — ``white - black`` below ``shadow_threshold`` (DN) or
  below ``min_relative_range`` of the white frame;
* **more than one ambiguous bit** — a bit is ambiguous when ``|pattern - inverse|`` is below
  ``bit_threshold`` (relative to ``white - black``).  With a Gray code exactly one bit changes
  between neighbouring codes, so a single ambiguous bit (a pixel straddling a stripe edge) can
  only be off by one code either way, which is harmless; two ambiguous bits are not;
* codes that decode beyond the projector's width/height.

**Narrow stripes.**  When the finest stripes are narrower than a camera pixel, their pattern
and inverse both average to grey and the bit is noise.  The decoder measures every bit's
median contrast ``|pattern - inverse| / (white - black)`` over lit pixels and drops the
finest bits whose contrast is below ``resolve_threshold``; the remaining bits still give a
Gray code (the top bits of ``gray(c)`` are ``gray(c >> k)``), decoded to the centre of a
``2**k``-pixel-wide stripe.  ``Decoded.dropped_bits_x/y`` says how many were dropped.

Coordinates follow OpenCV: the centre of projector pixel ``c`` is at ``x = c``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.patterns import PatternSet, gray_decode


@dataclass
class Decoded:
    """Per camera pixel projector coordinates.

    x, y : (H, W) float32, projector pixel coordinates (NaN where invalid)
    valid : (H, W) bool
    """

    x: np.ndarray
    y: np.ndarray
    valid: np.ndarray
    dropped_bits_x: int = 0
    dropped_bits_y: int = 0
    contrast_x: list[float] = field(default_factory=list)
    contrast_y: list[float] = field(default_factory=list)

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean())


def decode(
    images: np.ndarray | list[np.ndarray],
    width: int,
    height: int,
    *,
    shadow_threshold: float = 10.0,
    min_relative_range: float = 0.05,
    bit_threshold: float = 0.08,
    resolve_threshold: float = 0.25,
    adapt: bool = True,
) -> Decoded:
    """Decode a captured Gray-code sequence (see :mod:`calibration.patterns` for the order).

    Parameters
    ----------
    images : (N, H, W) uint8/uint16/float, or a list of (H, W) images (colour is averaged)
    width, height : projector resolution the patterns were generated for
    shadow_threshold : minimum ``white - black`` in image units
    min_relative_range : minimum ``(white - black) / white``
    bit_threshold : ``|pattern - inverse| / (white - black)`` below this makes a bit ambiguous
    resolve_threshold : median bit contrast below which a finest bit is dropped (``adapt``)
    adapt : drop unresolvable finest bits instead of decoding noise
    """
    ps = PatternSet(width, height)
    stack = _as_stack(images)
    if stack.shape[0] != ps.count:
        raise ValueError(f"expected {ps.count} frames for a {width}x{height} projector, got {stack.shape[0]}")
    white, black = stack[0].astype(np.float32), stack[1].astype(np.float32)
    rng = white - black
    lit = (rng > shadow_threshold) & (rng > min_relative_range * np.maximum(white, 1e-6))
    safe_rng = np.where(lit, rng, 1.0)

    out = {}
    ambiguous = np.zeros(white.shape, np.int16)
    for axis, nb, size in (("x", ps.col_bits, width), ("y", ps.row_bits, height)):
        diffs = [
            stack[ps.index(axis, k)].astype(np.float32) - stack[ps.index(axis, k, True)].astype(np.float32) for k in range(nb)
        ]
        contrast = [float(np.median(np.abs(d[lit]) / safe_rng[lit])) if lit.any() else 0.0 for d in diffs]
        used = nb
        if adapt:
            while used > 1 and contrast[used - 1] < resolve_threshold:
                used -= 1
        code = np.zeros(white.shape, np.int64)
        for k in range(used):
            d = diffs[k]
            code = (code << 1) | (d > 0)
            ambiguous += (np.abs(d) < bit_threshold * safe_rng).astype(np.int16)
        value = gray_decode(code)
        dropped = nb - used
        centre = value.astype(np.float64) * (1 << dropped) + ((1 << dropped) - 1) / 2.0
        in_range = centre <= size - 1 + 1e-9
        out[axis] = (centre.astype(np.float32), in_range, dropped, contrast)

    valid = lit & (ambiguous <= 1) & out["x"][1] & out["y"][1]
    x = np.where(valid, out["x"][0], np.float32(np.nan)).astype(np.float32)
    y = np.where(valid, out["y"][0], np.float32(np.nan)).astype(np.float32)
    return Decoded(x, y, valid, out["x"][2], out["y"][2], out["x"][3], out["y"][3])


def _as_stack(images: np.ndarray | list[np.ndarray]) -> np.ndarray:
    if isinstance(images, np.ndarray) and images.ndim == 3:
        stack = images
    else:
        frames = [np.asarray(im) for im in images]
        if not frames:
            raise ValueError("no images to decode")
        shape = frames[0].shape
        for i, f in enumerate(frames):
            if f.shape != shape:
                raise ValueError(f"frame {i} has shape {f.shape}, frame 0 has {shape}")
        stack = np.stack(frames)
        if stack.ndim == 4:
            stack = stack.mean(axis=3, dtype=np.float32)
    return stack  # converted to float32 one frame at a time
