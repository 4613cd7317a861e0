"""Analytic, noise-free direct-lighting terms per pixel, for demodulation (Heitz, Hill & McGuire 2018).

The ¼ shading resolution loses the normal-driven detail of the light inside moving objects.
To first order that detail is carried by two closed-form terms of the native G-buffer:

- diffuse: the unshadowed direct irradiance (Lambert's polygon formula)

      E(x, n) = Σ_emitters lum(L_e) · ½ |Σ_edges θ_k (n · ĝ_k)|

  (θ_k the angle an emitter edge subtends from x, ĝ_k the unit normal of the plane through x
  and the edge). Each emitter polygon is clipped exactly to the surface's upper hemisphere, so
  lights partly below the horizon are exact, not conservative;
- specular: S(x, n, v) = Σ lum(L_e) · D_peak/(4 cos_o) · ∫ SG_r(ω) SG_light(ω) dω, the GGX
  lobe as a spherical Gaussian about the reflected view direction r (sharpness 1/(2α² cos_o),
  Wang et al. 2009, as `guides` uses) and the emitter as an SG of its solid angle about the
  direction to its centre; the product integral of two SGs is closed form. Smith G and the
  emitter's shape are left out: the ratio below absorbs smooth errors, and LTC would need
  fitted tables.

The stage divides the demodulated diffuse and specular signals at the shading resolution by
(E + F_d) and (S + F_s), reuses, filters and upsamples those ratios (smooth: they hold shadows,
indirect light and the terms' own errors), and multiplies by the native (E + F_d), (S + F_s).
The products albedo·(E + F_d) and spec_albedo·(S + F_s) are what the stage hands the existing
kernels as albedos, so the reuse, filter and upsampling kernels are unchanged.

- Emitters: every emissive object; a planar quad (4 vertices, 2 faces) is one polygon, any other
  emissive mesh one polygon per triangle. One-sided like the renderer's: a point behind an
  emitter or in its plane gets 0 from it. The renderer also rejects directions below the
  *geometric* normal; the terms use the shading normal only.
- Scalars, not RGB: emissions are weighted by their luminance; coloured lights' colour stays
  in the ratio (both built-in scenes have white lights).
- The floors F keep the ratios stable where a term is ≈ 0 (facing away, indirect light only):
  F = `fraction` × the term's mean over the first shading frame's lit pixels, fixed for the
  stage's life (the cached native products stay valid). F plays the part of an ambient term:
  where the signal is ∝ (term + F) the ratio is flat.
- Non-finite positions or normals and background pixels: both terms 0 (the ratio is then the
  signal / F, re-multiplied by F).
- Cost: about 15 CPU-ns per pixel and quad light for both terms, vectorised (below); about 21 with
  the per-pixel set-up (unit normal, lobe) and the scatter into the products.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from dpmhw.reconstruct.weights import FASTMATH, MIN_NDOTV, fast_exp_neg
from dpmhw.render.geometry import SceneGeometry

# (diffuse, specular) floor fractions: × the term's mean over the first frame's lit pixels. Measured
# (docs/temporal-reuse.md): the specular term is an approximation, so its floor is larger
DEFAULT_FLOORS = (1.0, 4.0)
TWO_PI = 2.0 * math.pi
SPECULAR_MIN = 2e-3  # specular albedo at or below this (the guides floor it at 1e-3): no specular term
POLY_COLUMNS = 20  # corners (4 × 3), unit normal (3), corner count, centre (3), area


# Why the evaluation is laid out as it is: per pixel the terms are a few dozen square roots and
# divisions with a handful of data-dependent cases. Written as straight-line code over gathered
# points (structure of arrays, every case computed and selected) LLVM vectorises it (8 doubles a
# lane on AVX-512): ~4 CPU-ns a point for an unclipped quad against ~30 scalar, ~95 with the
# branches. Two things block that and are avoided: numba's ZeroDivisionError checks (hence
# `error_model="numpy"`; every division is guarded by a select) and branches whose arms differ.
# Conditions are combined with `&`, not `and`: a short-circuit test guarding a load, or a tuple
# chosen by a branch, becomes a masked load or store, which AVX2 has only as slow `vmaskmov`.
EVAL = dict(cache=True, nogil=True, fastmath=FASTMATH, error_model="numpy")
SOA_ROWS = 13  # per gathered point: p (3), unit n (3), reflected view r (3), λ, specular amplitude (0: none),
# E, S (rows 9, 10 hold the roughness and the specular flag until `_prepare_span`)
E_ROW, S_ROW = 11, 12
BLOCK = 2048  # points per parallel block (each block's inner loops vectorise)


@nb.njit(**EVAL)
def _theta_over_sin(x):
    """θ / sin θ for cos θ = x ∈ [−1, 1]: 2π × the rational fit of Heitz et al. 2016 (LTC,
    `IntegrateEdge`) for x > 0 (error < 1e-3 relative, tested), π/sin θ minus it for x ≤ 0
    (θ → π − θ). Both arms computed, one selected."""
    y = abs(x)
    v = TWO_PI * (0.8543985 + (0.4965155 + 0.0145206 * y) * y) / (3.4175940 + (4.1616724 + y) * y)
    w = math.pi / math.sqrt(max(1.0 - x * x, 1e-7)) - v
    return v if x > 0.0 else w


@nb.njit(**EVAL)
def _unit(a0, a1, a2):
    q = a0 * a0 + a1 * a1 + a2 * a2
    inv = 1.0 / math.sqrt(q)
    inv = inv if q > 1e-24 else 0.0
    return a0 * inv, a1 * inv, a2 * inv


@nb.njit(**EVAL)
def _edge(a0, a1, a2, b0, b1, b2, n0, n1, n2):
    """θ · (n · ĝ) of the edge between unit directions a → b, signed by the winding."""
    c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    return (n0 * c0 + n1 * c1 + n2 * c2) * _theta_over_sin(a0 * b0 + a1 * b1 + a2 * b2)


@nb.njit(**EVAL)
def _clipped_edge(acc, a0, a1, a2, u0, u1, u2, ha, b0, b1, b2, w0, w1, w2, hb, n0, n1, n2):
    """The running sum `acc` = (Σ θ·(n·ĝ), exit point (3), entry point (3), has exit, has entry)
    with the polygon edge a → b added (relative to p; u, w their unit directions, ha, hb their
    heights above p's tangent plane), clipped to n's hemisphere: the part below the horizon is
    cut off at the horizon point, where the edge leaves or enters the hemisphere (a convex
    polygon has at most one of each)."""
    s, ex0, ex1, ex2, en0, en1, en2, has_exit, has_entry = acc
    ina = ha >= 0.0
    inb = hb >= 0.0
    f = ha / (ha - hb)  # only used where the signs differ (ha ≠ hb)
    x0, x1, x2 = _unit(a0 + f * (b0 - a0), a1 + f * (b1 - a1), a2 + f * (b2 - a2))
    s0, s1, s2 = (u0, u1, u2) if ina else (x0, x1, x2)
    t0, t1, t2 = (w0, w1, w2) if inb else (x0, x1, x2)
    e = _edge(s0, s1, s2, t0, t1, t2, n0, n1, n2)
    leaves = ina and not inb
    enters = inb and not ina
    ex0, ex1, ex2 = (x0, x1, x2) if leaves else (ex0, ex1, ex2)
    en0, en1, en2 = (x0, x1, x2) if enters else (en0, en1, en2)
    return (s + (e if (ina or inb) else 0.0), ex0, ex1, ex2, en0, en1, en2, has_exit or leaves,
            has_entry or enters)


@nb.njit(**EVAL)
def _irradiance_span(soa, i0, i1, poly, t, lum):
    """E += lum · ∫ cos dω over convex emitter polygon t (`emitter_polygons` row), clipped to
    each point's hemisphere, for points i0..i1; 0 where the point is not in front of the one-sided
    emitter. A triangle is a quad whose last corner repeats the first (a zero edge)."""
    c00, c01, c02 = poly[t, 0], poly[t, 1], poly[t, 2]
    c10, c11, c12 = poly[t, 3], poly[t, 4], poly[t, 5]
    c20, c21, c22 = poly[t, 6], poly[t, 7], poly[t, 8]
    quad = poly[t, 15] > 3.5
    c30, c31, c32 = (poly[t, 9], poly[t, 10], poly[t, 11]) if quad else (c00, c01, c02)
    m0, m1, m2 = poly[t, 12], poly[t, 13], poly[t, 14]
    for i in range(nb.uint64(i0), nb.uint64(i1)):  # unsigned: no negative-index wraparound, so it vectorises
        p0, p1, p2 = soa[0, i], soa[1, i], soa[2, i]
        n0, n1, n2 = soa[3, i], soa[4, i], soa[5, i]
        a0, a1, a2 = c00 - p0, c01 - p1, c02 - p2
        b0, b1, b2 = c10 - p0, c11 - p1, c12 - p2
        d0, d1, d2 = c20 - p0, c21 - p1, c22 - p2
        e0, e1, e2 = c30 - p0, c31 - p1, c32 - p2
        ha = a0 * n0 + a1 * n1 + a2 * n2
        hb = b0 * n0 + b1 * n1 + b2 * n2
        hd = d0 * n0 + d1 * n1 + d2 * n2
        he = e0 * n0 + e1 * n1 + e2 * n2
        ua0, ua1, ua2 = _unit(a0, a1, a2)
        ub0, ub1, ub2 = _unit(b0, b1, b2)
        ud0, ud1, ud2 = _unit(d0, d1, d2)
        ue0, ue1, ue2 = _unit(e0, e1, e2)
        acc = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False, False)
        acc = _clipped_edge(acc, a0, a1, a2, ua0, ua1, ua2, ha, b0, b1, b2, ub0, ub1, ub2, hb, n0, n1, n2)
        acc = _clipped_edge(acc, b0, b1, b2, ub0, ub1, ub2, hb, d0, d1, d2, ud0, ud1, ud2, hd, n0, n1, n2)
        acc = _clipped_edge(acc, d0, d1, d2, ud0, ud1, ud2, hd, e0, e1, e2, ue0, ue1, ue2, he, n0, n1, n2)
        acc = _clipped_edge(acc, e0, e1, e2, ue0, ue1, ue2, he, a0, a1, a2, ua0, ua1, ua2, ha, n0, n1, n2)
        s, ex0, ex1, ex2, en0, en1, en2, has_exit, has_entry = acc
        closing = _edge(ex0, ex1, ex2, en0, en1, en2, n0, n1, n2)  # the clipped polygon's edge along the horizon
        s += closing if (has_exit and has_entry) else 0.0
        front = -(a0 * m0 + a1 * m1 + a2 * m2) > 0.0  # not behind the emitter, nor in its plane
        soa[E_ROW, i] += lum * 0.5 * abs(s) if front else 0.0


@nb.njit(**EVAL)
def _specular_span(soa, i0, i1, poly, t, lum):
    """S += lum · amplitude · ∫ exp(λ(r·ω − 1)) · SG_light(ω) dω, the emitter taken as an SG
    of amplitude 1 and its solid angle about the direction to its centre (0 if the point is behind
    it or the centre below its horizon). The second exponential uses `fast_exp_neg` too."""
    o0, o1, o2 = poly[t, 16], poly[t, 17], poly[t, 18]
    m0, m1, m2 = poly[t, 12], poly[t, 13], poly[t, 14]
    area = poly[t, 19]
    for i in range(nb.uint64(i0), nb.uint64(i1)):  # unsigned: see `_irradiance_span`
        q0, q1, q2 = o0 - soa[0, i], o1 - soa[1, i], o2 - soa[2, i]
        d2 = q0 * q0 + q1 * q1 + q2 * q2
        inv = 1.0 / math.sqrt(d2)
        q0, q1, q2 = q0 * inv, q1 * inv, q2 * inv
        cos_l = -(q0 * m0 + q1 * m1 + q2 * m2)
        ok = (d2 > 1e-20) & (cos_l > 0.0) & (q0 * soa[3, i] + q1 * soa[4, i] + q2 * soa[5, i] > 0.0)
        omega = min(area * cos_l / d2, TWO_PI)  # solid angle (small-emitter approximation)
        lam = soa[9, i]
        lam_l = TWO_PI / omega  # an SG of amplitude 1 integrating to ≈ Ω
        v0, v1, v2 = lam * soa[6, i] + lam_l * q0, lam * soa[7, i] + lam_l * q1, lam * soa[8, i] + lam_l * q2
        d = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        # 2π (e^(d−λ−λ_l) − e^(−d−λ−λ_l)) / d, d ≤ λ + λ_l; the second exponential is below 1e-4 of
        # the first once d > 5 (always, for lobes and emitters sharper than 2.5)
        big = fast_exp_neg(d - lam - lam_l)
        small = fast_exp_neg(-d - lam - lam_l)
        big = big - small if d < 5.0 else big
        val = TWO_PI * big / d if d >= 1e-6 else 4.0 * math.pi * fast_exp_neg(-lam - lam_l)
        soa[S_ROW, i] += lum * soa[10, i] * val if ok else 0.0


@nb.njit(**EVAL)
def _prepare_span(soa, i0, i1, viewer):
    """In place, points i0..i1: the unit normal, and from the roughness and the specular flag
    (rows 9, 10 as gathered) the reflected view direction r, λ and the amplitude of the specular
    lobe (all 0 where there is no lobe). Non-finite input: a zero point and normal (both terms 0)."""
    for i in range(nb.uint64(i0), nb.uint64(i1)):  # unsigned: see `_irradiance_span`
        p0, p1, p2 = soa[0, i], soa[1, i], soa[2, i]
        n0, n1, n2 = soa[3, i], soa[4, i], soa[5, i]
        rough, flag = soa[9, i], soa[10, i]
        nl = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        live = math.isfinite(p0 + p1 + p2) & math.isfinite(nl) & (nl > 1e-12)
        inv = 1.0 / nl
        p0, p1, p2 = (p0 if live else 0.0), (p1 if live else 0.0), (p2 if live else 0.0)
        n0, n1, n2 = (n0 * inv if live else 0.0), (n1 * inv if live else 0.0), (n2 * inv if live else 0.0)
        v0, v1, v2 = viewer[0] - p0, viewer[1] - p1, viewer[2] - p2
        vl = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        lobe = live & (flag > 0.0) & (vl > 1e-12) & math.isfinite(vl) & math.isfinite(rough)
        v0, v1, v2 = v0 / vl, v1 / vl, v2 / vl
        ndv = n0 * v0 + n1 * v1 + n2 * v2
        cos_o = max(ndv, MIN_NDOTV)
        a = max(rough * rough, 1e-3)  # the renderer's GGX α (roughness² with its floor)
        soa[0, i], soa[1, i], soa[2, i] = p0, p1, p2
        soa[3, i], soa[4, i], soa[5, i] = n0, n1, n2
        soa[6, i] = 2.0 * ndv * n0 - v0 if lobe else 0.0
        soa[7, i] = 2.0 * ndv * n1 - v1 if lobe else 0.0
        soa[8, i] = 2.0 * ndv * n2 - v2 if lobe else 0.0
        soa[9, i] = 1.0 / (2.0 * a * a * cos_o) if lobe else 0.0
        soa[10, i] = 1.0 / (math.pi * a * a * 4.0 * cos_o) if lobe else 0.0  # D's peak over the BRDF's 4 cos_o (G ≈ 1)


@nb.njit(parallel=True, **EVAL)
def _products_kernel(gid, pos, nrm, rough, viewer, alb, spc, poly, lum, floor_d, floor_s, specular, W,
                     y0, y1, x0, x1, use_mask, mask, start, n, idx, soa, irr, spec_term, out_d, out_s):
    """irr = E, spec_term = S, out_d = alb·(E + F_d), out_s = spc·(S + F_s) over the box (and the
    mask): background pixels written directly, the others gathered (at `start` per row), evaluated
    in vectorised blocks, scattered back."""
    for y in nb.prange(y0, y1):  # gather
        k = start[y - y0]
        for x in range(x0, x1):
            p = y * W + x
            if use_mask and not mask[p]:
                continue
            if gid[p] < 0:
                irr[p] = 0.0
                spec_term[p] = 0.0
                for c in range(3):
                    out_d[p, c] = alb[p, c] * floor_d
                    out_s[p, c] = spc[p, c] * floor_s
                continue
            idx[k] = p
            soa[0, k], soa[1, k], soa[2, k] = pos[p, 0], pos[p, 1], pos[p, 2]
            soa[3, k], soa[4, k], soa[5, k] = nrm[p, 0], nrm[p, 1], nrm[p, 2]
            soa[9, k] = rough[p]
            soa[10, k] = 1.0 if specular and max(spc[p, 0], max(spc[p, 1], spc[p, 2])) > SPECULAR_MIN else 0.0
            k += 1
    blocks = (n + BLOCK - 1) // BLOCK
    for b in nb.prange(blocks):  # evaluate, scatter
        _evaluate_block(b * BLOCK, min(b * BLOCK + BLOCK, n), soa, idx, viewer, poly, lum, specular, alb, spc,
                        floor_d, floor_s, irr, spec_term, out_d, out_s)


@nb.njit(**EVAL)
def _evaluate_block(i0, i1, soa, idx, viewer, poly, lum, specular, alb, spc, floor_d, floor_s, irr, spec_term, out_d, out_s):
    """The gathered points i0..i1: both terms, then scattered into the outputs."""
    _prepare_span(soa, i0, i1, viewer)
    for i in range(i0, i1):
        soa[E_ROW, i] = 0.0
        soa[S_ROW, i] = 0.0
    for t in range(poly.shape[0]):
        _irradiance_span(soa, i0, i1, poly, t, lum[t])
        if specular:
            _specular_span(soa, i0, i1, poly, t, lum[t])
    for i in range(i0, i1):
        p = idx[i]
        e = soa[E_ROW, i] if math.isfinite(soa[E_ROW, i]) else 0.0
        sp = soa[S_ROW, i] if math.isfinite(soa[S_ROW, i]) else 0.0
        irr[p] = e
        spec_term[p] = sp
        g = e + floor_d
        h = sp + floor_s
        for c in range(3):
            out_d[p, c] = alb[p, c] * g
            out_s[p, c] = spc[p, c] * h


def polygon_rows(corners, emission) -> tuple[np.ndarray, float]:
    """One `emitter_polygons` row from 3 or 4 world corners (convex, planar; the winding's normal
    is the emitting side) and the emission's luminance."""
    pv = np.asarray(corners, np.float64)
    nv = len(pv)
    nrm = np.cross(pv[1] - pv[0], pv[2] - pv[0])
    area = 0.5 * np.linalg.norm(nrm) + (0.5 * np.linalg.norm(np.cross(pv[2] - pv[0], pv[3] - pv[0])) if nv == 4 else 0.0)
    row = np.zeros(POLY_COLUMNS)
    row[: 3 * nv] = pv.reshape(-1)
    row[12:15] = nrm / max(np.linalg.norm(nrm), 1e-300)
    row[15] = nv
    row[16:19] = pv.mean(axis=0)
    row[19] = area
    e = np.asarray(emission, np.float64).reshape(-1)
    return row, float(0.2126 * e[0] + 0.7152 * e[1] + 0.0722 * e[2]) if e.size == 3 else float(e[0])


def emitter_polygons(geometry: SceneGeometry, poses) -> tuple[np.ndarray, np.ndarray]:
    """World-space emitter polygons (P, `POLY_COLUMNS`) and their luminances (P,) at the given
    per-object poses. No emitter: (0, 20), (0,): both terms 0 everywhere."""
    rows, lums = [], []
    for i, obj in enumerate(geometry.scene.objects):
        if not obj.is_emissive:
            continue
        verts = obj.mesh.vertices.astype(np.float64) @ np.asarray(poses[i].R, np.float64).T + np.asarray(poses[i].t, np.float64)
        faces = np.asarray(obj.mesh.faces)
        polys = [verts[f] for f in faces]
        if len(faces) == 2 and len(verts) == 4:  # a quad: its outline, in the first face's winding
            a, b = faces
            extra = [v for v in b if v not in a]
            off = [j for j in range(3) if a[j] not in b]  # a's vertex off the shared diagonal
            if len(extra) == 1 and len(off) == 1:
                k = off[0]
                quad = verts[[a[k], a[(k + 1) % 3], extra[0], a[(k + 2) % 3]]]
                nq = np.cross(quad[1] - quad[0], quad[2] - quad[0])
                if abs(np.dot(quad[3] - quad[0], nq)) <= 1e-9 * max(np.linalg.norm(nq), 1e-30):
                    polys = [quad]
        for pv in polys:
            if np.linalg.norm(np.cross(pv[1] - pv[0], pv[2] - pv[0])) > 0:
                row, lum = polygon_rows(pv, obj.emission)
                rows.append(row)
                lums.append(lum)
    if not rows:
        return np.zeros((0, POLY_COLUMNS), np.float64), np.zeros(0, np.float64)
    return np.ascontiguousarray(np.array(rows)), np.array(lums, np.float64)


class _Gathered:
    """The pixels to evaluate, gathered: their indices and `rows` float64 rows per pixel, kept
    between frames and grown to the largest count seen (at most the pixel count). A fresh
    multi-megabyte allocation per frame would cost page faults every frame."""

    def __init__(self, rows: int):
        self.idx = np.zeros(0, np.int64)
        self.rows = np.zeros((rows, 0))

    def ensure(self, n: int) -> None:
        if len(self.idx) < n:
            self.idx = np.empty(n, np.int64)
            self.rows = np.empty((self.rows.shape[0], n))


@nb.njit(parallel=True, cache=True, nogil=True)
def _row_counts(gid, W, y0, y1, x0, x1, use_mask, mask, counts):
    for y in nb.prange(y0, y1):
        c = 0
        for x in range(x0, x1):
            p = y * W + x
            if gid[p] >= 0 and (not use_mask or mask[p]):
                c += 1
        counts[y - y0] = c


_NO_MASK = np.zeros(1, np.bool_)


def _row_starts(scratch: _Gathered, gid: np.ndarray, W: int, box, mask: np.ndarray | None = None):
    """(start, n, mask): per row of the box (y0, y1, x0, x1), where its pixels with gid ≥ 0 (and in
    `mask`, if given) begin in the gathered list, and their total; `scratch` is made large enough
    for n. The mask comes back flat (a placeholder when None) for the kernels."""
    y0, y1, x0, x1 = box
    use_mask = mask is not None
    m = np.ascontiguousarray(mask, np.bool_).reshape(-1) if use_mask else _NO_MASK
    counts = np.empty(y1 - y0, np.int64)
    _row_counts(gid, W, y0, y1, x0, x1, use_mask, m, counts)
    start = np.zeros(y1 - y0, np.int64)
    np.cumsum(counts[:-1], out=start[1:])
    n = int(start[-1] + counts[-1])
    scratch.ensure(n)
    return start, n, m


class AnalyticDirect:
    """The demodulation products at one resolution, recomputed only where asked.

    `update(...)` writes `irradiance` (E, (n,)), `specular` (S, (n,)), `diffuse_products`
    albedo·(E + F_d) and `specular_products` spec_albedo·(S + F_s) ((n, 3) each) for a box (and a
    mask); the floors must be set first (`set_floors`)."""

    def __init__(self, width: int, height: int, polygons: np.ndarray, luminance: np.ndarray, viewer):
        self.width, self.height = int(width), int(height)
        n = self.width * self.height
        self.poly = np.ascontiguousarray(polygons, np.float64)
        self.lum = np.ascontiguousarray(luminance, np.float64)
        self.viewer = np.asarray(viewer, np.float64).reshape(3)
        self.irradiance = np.zeros(n, np.float32)
        self.specular = np.zeros(n, np.float32)
        self.diffuse_products = np.ones((n, 3), np.float32)
        self.specular_products = np.ones((n, 3), np.float32)
        self.floors: tuple[float, float] | None = None
        self._scratch = _Gathered(SOA_ROWS)

    def set_floors(self, diffuse: float, specular: float) -> None:
        for name, f in (("diffuse", diffuse), ("specular", specular)):
            if not (math.isfinite(f) and f > 0.0):
                raise ValueError(f"analytic {name} floor: expected a finite positive value, got {f!r}")
        self.floors = (float(diffuse), float(specular))

    def update(self, object_id, position, normal, roughness, albedo, spec_albedo, box, mask: np.ndarray | None = None) -> None:
        if self.floors is None:
            raise RuntimeError("AnalyticDirect.update before set_floors")
        _evaluate(self._scratch, np.ascontiguousarray(object_id, np.int32).reshape(-1), _flat3(position), _flat3(normal),
                  np.ascontiguousarray(roughness, np.float32).reshape(-1), self.viewer, _flat3(albedo), _flat3(spec_albedo),
                  self.poly, self.lum, self.floors, self.width, box, mask, self.irradiance, self.specular,
                  self.diffuse_products, self.specular_products)


def _evaluate(scratch, gid, pos, nrm, rough, viewer, alb, spc, poly, lum, floors, W, box, mask, irr, spec_term, out_d, out_s):
    y0, y1, x0, x1 = (int(v) for v in box)
    if y1 <= y0 or x1 <= x0:
        return
    start, n, m = _row_starts(scratch, gid, W, (y0, y1, x0, x1), mask)
    _products_kernel(gid, pos, nrm, rough, viewer, alb, spc, poly, lum, floors[0], floors[1], poly.shape[0] > 0, W,
                     y0, y1, x0, x1, mask is not None, m, start, n, scratch.idx, scratch.rows, irr, spec_term, out_d, out_s)


def terms_at_points(pos, nrm, viewer, rough, poly, lum):
    """(E, S) at each of n points (n, 3) with normals (n, 3) and roughness (n,), both terms
    everywhere, through the stage's kernel (tests, plots)."""
    n = len(pos)
    e, s = np.zeros(n), np.zeros(n)
    ones = np.ones((n, 3), np.float32)
    f64 = np.float64
    _evaluate(_Gathered(SOA_ROWS), np.zeros(n, np.int32), np.ascontiguousarray(pos, f64).reshape(-1, 3),
              np.ascontiguousarray(nrm, f64).reshape(-1, 3), np.ascontiguousarray(rough, f64),
              np.asarray(viewer, np.float64).reshape(3), ones, ones, np.ascontiguousarray(poly, np.float64),
              np.ascontiguousarray(lum, np.float64), (1.0, 1.0), n, (0, 1, 0, n), None, e, s,
              np.empty((n, 3), np.float32), np.empty((n, 3), np.float32))
    return e, s


def floor_from(term: np.ndarray, object_id: np.ndarray, fraction: float) -> float:
    """F = fraction × the mean term over the lit pixels (id ≥ 0, term > 0); 1.0 if there are none
    (then the ratio is the signal itself, scaled)."""
    e = np.asarray(term, np.float64).reshape(-1)
    lit = (np.asarray(object_id).reshape(-1) >= 0) & (e > 0) & np.isfinite(e)
    m = float(e[lit].mean()) if lit.any() else 0.0
    return fraction * m if m > 0 else 1.0




def _flat3(a) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).reshape(-1, 3)
