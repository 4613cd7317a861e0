"""Edge-stopping weights of the cross-bilateral filter (Tokuyoshi, methods.md §2).

Specular-lobe-aware weight between pixels i and j whose reflection lobes are spherical
Gaussians with axes ξ and sharpness λ, smoothed by an SG of sharpness κ (λ̄ = λκ / (λ + κ))::

    w(i, j) = (2 √(λ̄ᵢ λ̄ⱼ) / (λ̄ᵢ + λ̄ⱼ))^β · exp(β λ̄ᵢ λ̄ⱼ / (λ̄ᵢ + λ̄ⱼ) · (ξᵢ·ξⱼ − 1))

The normal-aware baseline is exp((nᵢ·nⱼ − 1) / σ_n²). A diffuse lobe has the normal as its axis
and the sharpness `DIFFUSE_LAMBDA` chosen so that β λ̄ / 2 = 1 / σ_n²: the lobe weight of two
diffuse pixels *is* the normal-aware weight.

Two implementations:

- `lobe_weight` / `normal_weight`: float64 numpy, in log space, the reference (tests, plots).
  λ̄ is clamped to ≥ `LAMBDA_BAR_MIN`, so λ = 0 … 10⁴ (and beyond) stays finite and in [0, 1].
- `fast_lobe_weight` / `fast_normal_weight`: scalar numba functions inlined into the image
  kernels. With β = 20 the first factor is (1 − t²)¹⁰, t = (λ̄ᵢ − λ̄ⱼ)/(λ̄ᵢ + λ̄ⱼ), and the exp
  of a non-positive argument is clamp(1 + e/1024, 0)^1024 by ten squarings: multiply/add
  only, so the loops vectorise (numba's exp is scalar here; perf-notes.md). Within 3e-4 of
  the reference.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

BETA = 20  # the paper's power; the fast path relies on it being 20
KAPPA = 100.0  # smoothing-SG sharpness
SIGMA_N2 = 0.01  # normal-aware baseline σ_n²
LAMBDA_BAR_MIN = 1e-6
DIFFUSE_LAMBDA_BAR = 2.0 / (BETA * SIGMA_N2)  # = 10: β λ̄ / 2 = 1 / σ_n²
DIFFUSE_LAMBDA = DIFFUSE_LAMBDA_BAR * KAPPA / (KAPPA - DIFFUSE_LAMBDA_BAR)
MIN_NDOTV = 0.1  # grazing views: the warped lobe's sharpness is capped, not infinite

# fast-math without "no NaN / no Inf": the kernels test finiteness to keep NaN out of the image
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


def smoothed_sharpness(lam, kappa: float = KAPPA):
    """λ̄ = λκ / (λ + κ), clamped to ≥ LAMBDA_BAR_MIN (λ ≥ 0; λ = inf gives κ)."""
    lam = np.maximum(np.asarray(lam, np.float64), 0.0)
    with np.errstate(invalid="ignore"):
        bar = np.where(np.isinf(lam), kappa, lam * kappa / (lam + kappa))
    return np.maximum(np.nan_to_num(bar, nan=LAMBDA_BAR_MIN), LAMBDA_BAR_MIN)


def specular_sharpness(roughness, n_dot_v):
    """SG sharpness of a microfacet reflection lobe (Wang et al. 2009): the GGX/Beckmann NDF of
    α = roughness² is an SG of sharpness 2/α² about the half vector; warped to the reflected
    direction it becomes 2/α² / (4 n·v). Same α floor as the renderer (1e-3)."""
    alpha = np.maximum(np.asarray(roughness, np.float64) ** 2, 1e-3)
    return 1.0 / (2.0 * alpha * alpha * np.maximum(np.asarray(n_dot_v, np.float64), MIN_NDOTV))


def lobe_log_weight(axis_i, axis_j, lam_i, lam_j, beta: float = BETA, kappa: float = KAPPA):
    """log w(i, j), float64, broadcasting over leading axes (axes (..., 3), unit length)."""
    a = smoothed_sharpness(lam_i, kappa)
    b = smoothed_sharpness(lam_j, kappa)
    cos = np.clip(np.sum(np.asarray(axis_i, np.float64) * np.asarray(axis_j, np.float64), axis=-1), -1.0, 1.0)
    log_ratio = math.log(2.0) + 0.5 * (np.log(a) + np.log(b)) - np.log(a + b)  # ≤ 0 (AM ≥ GM)
    return beta * (np.minimum(log_ratio, 0.0) + a * b / (a + b) * (cos - 1.0))


def lobe_weight(axis_i, axis_j, lam_i, lam_j, beta: float = BETA, kappa: float = KAPPA):
    """The lobe-aware weight in [0, 1] (reference implementation)."""
    return np.exp(lobe_log_weight(axis_i, axis_j, lam_i, lam_j, beta, kappa))


def normal_weight(n_i, n_j, sigma_n2: float = SIGMA_N2):
    """Normal-aware weight exp((nᵢ·nⱼ − 1)/σ_n²) (reference implementation)."""
    cos = np.clip(np.sum(np.asarray(n_i, np.float64) * np.asarray(n_j, np.float64), axis=-1), -1.0, 1.0)
    return np.exp((cos - 1.0) / sigma_n2)


@nb.njit(inline="always", fastmath=FASTMATH)
def fast_exp_neg(e):
    """exp(e) for e ≤ 0 by (1 + e/1024)^1024 (ten squarings), clamped at 0; |error| < 3e-4."""
    x = 1.0 + e * (1.0 / 1024.0)
    if x < 0.0:
        x = 0.0
    for _ in range(10):
        x = x * x
    return x


@nb.njit(inline="always", fastmath=FASTMATH)
def fast_lobe_weight(cos_ij, a, b, log_factor=0.0):
    """Lobe weight from ξᵢ·ξⱼ and the smoothed sharpnesses λ̄ᵢ, λ̄ⱼ (both ≥ LAMBDA_BAR_MIN), β = 20,
    times exp(log_factor) (≤ 0; the upsampler folds its depth weight in, one exponential for both)."""
    s = a + b
    t = (a - b) / s
    u = 1.0 - t * t
    u2 = u * u
    u4 = u2 * u2
    u8 = u4 * u4
    return u8 * u2 * fast_exp_neg(log_factor + BETA * a * b / s * (min(cos_ij, 1.0) - 1.0))


@nb.njit(inline="always", fastmath=FASTMATH)
def fast_normal_weight(cos_ij):
    return fast_exp_neg((min(cos_ij, 1.0) - 1.0) * (1.0 / SIGMA_N2))


@nb.njit(cache=True)
def fast_lobe_weights(cos_ij, a, b):
    """Vector form of `fast_lobe_weight` (for tests and plots)."""
    out = np.empty(cos_ij.shape[0], np.float64)
    for k in range(cos_ij.shape[0]):
        out[k] = fast_lobe_weight(cos_ij[k], a[k], b[k])
    return out
