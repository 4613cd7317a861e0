"""Image error against a reference, on the post-processed uint8 frames a projector would show.

PSNR
    10 · log10(255² / MSE), MSE over every pixel and all three channels of the uint8 images
    (∞ for identical images).
SSIM
    Wang, Bovik, Sheikh & Simoncelli 2004 ("ssim_index.m"): on the luma
    Y' = 0.2989 R' + 0.5870 G' + 0.1140 B' of the 8-bit sRGB images (MATLAB's rgb2gray, the
    conversion the reference implementation is used with), data range 255, an 11×11 circular
    Gaussian window with σ = 1.5, K1 = 0.01, K2 = 0.03, population (not sample) covariances;
    the mean of the SSIM map. Computed with scikit-image's ``structural_similarity(...,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=255)``, whose
    mean excludes a 5-pixel border (the window half-width).
Noise-corrected PSNR
    A reference of N spp carries its own Monte Carlo variance, which adds to every MSE measured
    against it and caps the PSNR (at 64 spp about 36 dB on paper-static, 32 dB on paper-dynamic). Render it as
    two independent halves A and B (N/2 spp each, different seeds) and use R = (A + B)/2. Per
    pixel, var(R) = var(A)/2 and E[(A − B)²] = 2·var(A), so var(R) = MSE(A, B)/4. Against the
    converged image T, an image X with noise independent of R has MSE(X, R) = MSE(X, T) +
    var(R), so MSE(X, T) ≈ MSE(X, R) − MSE(A, B)/4. On the post-processed uint8 images this holds
    to first order (the tone curve is smooth where the noise is small; clipped pixels add
    nothing to either side). `reference_noise_mse` and `noise_corrected_psnr`; tested on
    synthetic images with known truth (tests/reuse/test_post_metrics.py).
Equivalent spp
    The spp at which plain path tracing would reach a given PSNR, linearly interpolated in
    (log2 spp, PSNR) on the measured plain-spp curve; beyond the curve's ends it extrapolates the
    end segment and says so.
"""

from __future__ import annotations

import numpy as np

LUMA = np.array([0.2989, 0.5870, 0.1140])


def _check(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    if a.dtype != np.uint8 or b.dtype != np.uint8:
        raise ValueError(f"expected uint8 post-processed images, got {a.dtype} and {b.dtype}")
    return a, b


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR in dB of two uint8 images (any shape), peak 255."""
    a, b = _check(image, reference)
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def masked_psnr(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """PSNR over `mask`'s pixels; NaN where the mask is empty (nothing to compare)."""
    return psnr(image[mask], reference[mask]) if mask.any() else float("nan")


def reference_noise_mse(half_a: np.ndarray, half_b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Estimated MSE that the noise of R = (A + B)/2 adds: MSE(A, B)/4 (see module doc); uint8
    images of the two independent halves, over `mask`'s pixels (all if None)."""
    a, b = _check(half_a, half_b)
    d = a.astype(np.float64) - b.astype(np.float64)
    if mask is not None:
        d = d[mask]
    return float(np.mean(d**2)) / 4.0 if d.size else float("nan")


def noise_corrected_psnr(image: np.ndarray, reference: np.ndarray, half_a: np.ndarray, half_b: np.ndarray,
                         mask: np.ndarray | None = None, max_db: float = 80.0) -> float:
    """PSNR of `image` against the converged image, estimated from a finite `reference` (the
    post-processed mean of the independent halves `half_a`, `half_b`): 10·log10(255² /
    (MSE(image, reference) − MSE(A, B)/4)), capped at `max_db` where the difference is not
    positive (the image is within the reference's own noise). Over `mask` (all if None)."""
    x, r = _check(image, reference)
    d = x.astype(np.float64) - r.astype(np.float64)
    if mask is not None:
        d = d[mask]
    if not d.size:
        return float("nan")
    mse = float(np.mean(d**2)) - reference_noise_mse(half_a, half_b, mask)
    floor = 255.0**2 / 10.0 ** (max_db / 10.0)
    return float(10.0 * np.log10(255.0**2 / max(mse, floor)))


def luma(image_u8: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 → (H, W) float64 Y' in [0, 255] (Rec. 601 weights, as MATLAB rgb2gray)."""
    return np.asarray(image_u8, dtype=np.float64) @ LUMA


def ssim(image: np.ndarray, reference: np.ndarray) -> float:
    """Mean SSIM (Wang et al. 2004 parameters, on luma) of two (H, W, 3) uint8 images."""
    from skimage.metrics import structural_similarity

    a, b = _check(image, reference)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected (H, W, 3) images, got {a.shape}")
    if min(a.shape[:2]) < 11:
        raise ValueError(f"SSIM needs images of at least 11×11 pixels (the window), got {a.shape[1]}×{a.shape[0]}")
    return float(structural_similarity(luma(a), luma(b), gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=255.0))


def masked_ssim(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """The SSIM map's mean over `mask`'s pixels (same parameters as `ssim`; the windows reach
    11 px beyond the mask); NaN where the mask is empty."""
    from skimage.metrics import structural_similarity

    a, b = _check(image, reference)
    if not np.any(mask):
        return float("nan")
    _, full = structural_similarity(luma(a), luma(b), gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                    data_range=255.0, full=True)
    return float(full[mask].mean())


def equivalent_spp(spp: list[float], psnr_db: list[float], target_db: float) -> tuple[float, bool]:
    """spp at which the plain curve (spp, psnr_db) reaches target_db, and whether that needed
    extrapolation past the measured range. The curve is sorted by spp and must rise with it."""
    s = np.asarray(spp, dtype=np.float64)
    p = np.asarray(psnr_db, dtype=np.float64)
    order = np.argsort(s)
    s, p = np.log2(s[order]), p[order]
    if len(s) < 2:
        raise ValueError("need at least two points on the spp curve")
    if np.any(np.diff(p) <= 0):
        raise ValueError(f"the PSNR curve does not rise with spp: {p.round(3).tolist()}")
    if p[0] <= target_db <= p[-1]:
        return float(2 ** np.interp(target_db, p, s)), False
    i = 0 if target_db < p[0] else len(s) - 2
    slope = (s[i + 1] - s[i]) / (p[i + 1] - p[i])
    return float(2 ** (s[i] + slope * (target_db - p[i]))), True
