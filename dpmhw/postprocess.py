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

Per frame the loop uses `encode_srgb8` (exposure, clip, sRGB): a numba kernel over the lit
region only, bit-identical to `to_srgb8`. sRGB goes through a table indexed by the top 16 bits
of the float32 value (sign, exponent, 7 mantissa bits); a table cell spans less than half a
code value, so it holds the code at its start and the one float32 threshold (if any) inside it
where the code steps up. The thresholds are found by bisection on `to_srgb8` itself, so the
table reproduces it exactly (perf-notes.md: 0.9 ms for a full 1024×768 frame on 2 threads).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numba as nb
import numpy as np

TONEMAPS = ("clip", "reinhard")


class NonFiniteFrameError(ValueError):
    """The frame holds NaN/Inf: it must not reach the projector."""


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


# ---- the per-frame path: exposure + clip + sRGB through a table, inside a box ------------------

_MAX_CELLS = 1 << 15  # positive float32 bit patterns >> 16


@lru_cache(maxsize=4)
def srgb8_table(exposure: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """For cells k = (float32 bits of the *unexposed* radiance) >> 16: the code at the cell's
    start and the bit pattern where the code steps up inside it (0xFFFFFFFF if none); cells past
    the end saturate at 255. Built from `to_srgb8` at this exposure (see the module docstring)."""
    def codes(bits: np.ndarray) -> np.ndarray:
        x = bits.astype(np.uint32).view(np.float32).reshape(-1, 1, 1).repeat(3, axis=2)
        with np.errstate(over="ignore"):  # huge values × exposure saturate to white either way
            return to_srgb8(x, exposure)[:, 0, 0].astype(np.int64)

    k = np.arange(_MAX_CELLS, dtype=np.int64)
    k = k[(k << 16) < 0x7F800000]  # finite values only
    first_white = np.nonzero(codes(k << 16) == 255)[0]
    size = int(first_white[0]) + 1 if first_white.size else len(k)
    start = k[:size] << 16
    end = start | 0xFFFF
    c0, c1 = codes(start), codes(end)
    if np.any(c1 - c0 > 1) or np.any(c1 < c0):
        raise AssertionError("sRGB table: a cell spans more than one code step")
    thr = np.full(size, 0xFFFFFFFF, np.uint32)
    step = np.nonzero(c1 > c0)[0]
    lo, hi = start[step], end[step]  # invariant: code(lo) = c0, code(hi) = c0 + 1
    for _ in range(17):
        mid = (lo + hi) // 2
        up = codes(mid) > c0[step]
        hi = np.where(up, mid, hi)
        lo = np.where(up, lo, mid)
    thr[step] = hi
    return c0.astype(np.uint8), thr


@nb.njit(parallel=True, cache=True, nogil=True)
def _encode_kernel(bits, W, y0, y1, x0, x1, base, thr, out, bad):
    """Integer-only per value (so the row loop vectorises): sign, finiteness, table cell, threshold."""
    size = base.shape[0]
    for y in nb.prange(y0, y1):
        nb_row = 0
        for x in range(x0, x1):
            p = y * W + x
            for c in range(3):
                b = bits[p, c]
                if (b & 0x7FFFFFFF) >= 0x7F800000:
                    nb_row += 1
                    code = 0
                elif b >= 0x80000000:  # negative (or −0): black
                    code = 0
                else:
                    k = b >> 16
                    if k >= size:
                        code = 255
                    else:
                        code = base[k] + (1 if b >= thr[k] else 0)
                out[p, c] = code
        bad[y] = nb_row


def encode_srgb8(radiance: np.ndarray, width: int, exposure: float = 1.0, box: tuple[int, int, int, int] | None = None,
                 out: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) float32 linear radiance of a `width`-wide frame → (n, 3) uint8, equal to `to_srgb8`.

    Only rows × columns of `box` = (y0, y1, x0, x1) are written into `out` (the rest keeps its
    values: the caller fills it once, e.g. with the background). Raises ValueError on NaN/Inf.
    """
    rad = np.asarray(radiance)
    if rad.dtype != np.float32 or rad.ndim != 2 or rad.shape[1] != 3 or not rad.flags.c_contiguous:
        raise ValueError(f"radiance: expected a contiguous (n, 3) float32 array, got {rad.dtype} {rad.shape}")
    if not (np.isfinite(exposure) and exposure >= 0):
        raise ValueError(f"exposure: expected a finite number ≥ 0, got {exposure!r}")
    height = rad.shape[0] // width
    y0, y1, x0, x1 = (0, height, 0, width) if box is None else (int(v) for v in box)
    out = np.zeros((rad.shape[0], 3), np.uint8) if out is None else out
    base, thr = srgb8_table(float(exposure))
    bad = np.zeros(height, np.int32)
    _encode_kernel(rad.view(np.uint32), width, y0, y1, x0, x1, base, thr, out, bad)
    if bad.any():
        raise NonFiniteFrameError(f"radiance has NaN/Inf in {int(bad.sum())} values; refusing to send them to the projector")
    return out
