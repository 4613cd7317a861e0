"""Gray-code structured-light patterns for any projector resolution.

Sequence (the order a capture folder stores its frames in)::

    0            white (all pixels on)
    1            black (all pixels off)
    2 + 2k       column bit k (most significant first), k = 0 .. n_col_bits-1
    3 + 2k       its inverse
    2 + 2*n_col_bits + 2k, +1   row bit k and its inverse

Column ``c`` shows bit ``n-1-k`` of ``gray(c) = c ^ (c >> 1)``.  From frame 2 onwards the
sequence is identical to OpenCV's ``cv2.structured_light.GrayCodePattern.generate()``, so
OpenCV's decoder can be used as a cross-check.  Widths that are not powers of two are
handled: ``n_col_bits = ceil(log2(width))`` and codes >= width are simply never shown.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def n_bits(size: int) -> int:
    """Bits needed to give every one of ``size`` pixels its own code."""
    if size < 2:
        raise ValueError(f"projector size must be at least 2 pixels, got {size}")
    return int(np.ceil(np.log2(size)))


def gray_encode(values: np.ndarray) -> np.ndarray:
    """Reflected binary Gray code of non-negative integers."""
    v = np.asarray(values, dtype=np.int64)
    return v ^ (v >> 1)


def gray_decode(codes: np.ndarray) -> np.ndarray:
    """Inverse of :func:`gray_encode` (prefix XOR), vectorised."""
    b = np.asarray(codes, dtype=np.int64).copy()
    shift = 1
    while shift < 63:
        b ^= b >> shift
        shift <<= 1
    return b


@dataclass(frozen=True)
class PatternSet:
    """Layout of a Gray-code sequence for one projector resolution."""

    width: int
    height: int

    @property
    def col_bits(self) -> int:
        return n_bits(self.width)

    @property
    def row_bits(self) -> int:
        return n_bits(self.height)

    @property
    def count(self) -> int:
        """Number of frames, white and black included."""
        return 2 + 2 * (self.col_bits + self.row_bits)

    def index(self, axis: str, bit: int, inverse: bool = False) -> int:
        """Frame index of ``bit`` (0 = most significant) of ``axis`` ('x' or 'y')."""
        base = 2 if axis == "x" else 2 + 2 * self.col_bits
        return base + 2 * bit + int(inverse)

    def generate(self) -> list[np.ndarray]:
        """All frames as ``(height, width) uint8`` images (0 or 255)."""
        cols = gray_encode(np.arange(self.width))
        rows = gray_encode(np.arange(self.height))
        frames = [np.full((self.height, self.width), 255, np.uint8), np.zeros((self.height, self.width), np.uint8)]
        for codes, nb, horizontal in ((cols, self.col_bits, True), (rows, self.row_bits, False)):
            for k in range(nb):
                bit = ((codes >> (nb - 1 - k)) & 1).astype(bool)
                img = np.broadcast_to(bit[None, :], (self.height, self.width)) if horizontal else np.broadcast_to(
                    bit[:, None], (self.height, self.width)
                )
                frames.append(np.where(img, 255, 0).astype(np.uint8))
                frames.append(np.where(img, 0, 255).astype(np.uint8))
        return frames

    def bit_values(self, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gray codes of integer projector pixels (used by the synthetic renderer)."""
        return gray_encode(px), gray_encode(py)
