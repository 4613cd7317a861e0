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
- Cost: about 75 CPU-ns per pixel and quad light with both terms. `AnalyticDirect(lattice=2)`
  (the stage's native terms) evaluates every second row and column and averages in between on
  smooth surfaces: a quarter of the evaluations.
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


@nb.njit(inline="always", fastmath=FASTMATH)
def _theta_over_sin(x):
    """θ / sin θ for cos θ = x ∈ [−1, 1]: 2π × the rational fit of Heitz et al. 2016 (LTC,
    `IntegrateEdge`) for x > 0 (error < 1e-3 relative, tested), π/sin θ minus it for x ≤ 0 (θ → π − θ)."""
    y = abs(x)
    v = TWO_PI * (0.8543985 + (0.4965155 + 0.0145206 * y) * y) / (3.4175940 + (4.1616724 + y) * y)
    if x > 0.0:
        return v
    return math.pi / math.sqrt(max(1.0 - x * x, 1e-7)) - v


@nb.njit(inline="always", fastmath=FASTMATH)
def _edge(a0, a1, a2, b0, b1, b2, n0, n1, n2):
    """θ · (n · ĝ) of the edge between unit directions a → b, signed by the winding."""
    c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    return (n0 * c0 + n1 * c1 + n2 * c2) * _theta_over_sin(a0 * b0 + a1 * b1 + a2 * b2)


@nb.njit(inline="always", fastmath=FASTMATH)
def _unit(a0, a1, a2):
    q = a0 * a0 + a1 * a1 + a2 * a2
    if q < 1e-24:
        return 0.0, 0.0, 0.0
    inv = 1.0 / math.sqrt(q)
    return a0 * inv, a1 * inv, a2 * inv


@nb.njit(inline="always", fastmath=FASTMATH)
def polygon_form(p0, p1, p2, n0, n1, n2, poly, t):
    """∫ cos dω over convex emitter polygon t (`emitter_polygons` row) seen from p with unit normal
    n, clipped to n's hemisphere; 0 if p is not in front of the one-sided emitter."""
    if -((poly[t, 0] - p0) * poly[t, 12] + (poly[t, 1] - p1) * poly[t, 13] + (poly[t, 2] - p2) * poly[t, 14]) <= 0.0:
        return 0.0  # behind the emitter, or in its plane
    nv = int(poly[t, 15])
    below = 0
    for k in range(nv):
        if (poly[t, 3 * k] - p0) * n0 + (poly[t, 3 * k + 1] - p1) * n1 + (poly[t, 3 * k + 2] - p2) * n2 < 0.0:
            below += 1
    if below == nv:
        return 0.0
    s = 0.0
    if below == 0:  # the common case: no clipping, each corner normalised once
        f0, f1, f2 = _unit(poly[t, 0] - p0, poly[t, 1] - p1, poly[t, 2] - p2)
        a0, a1, a2 = f0, f1, f2
        for k in range(nv):
            if k + 1 < nv:
                b0, b1, b2 = _unit(poly[t, 3 * k + 3] - p0, poly[t, 3 * k + 4] - p1, poly[t, 3 * k + 5] - p2)
            else:
                b0, b1, b2 = f0, f1, f2
            s += _edge(a0, a1, a2, b0, b1, b2, n0, n1, n2)
            a0, a1, a2 = b0, b1, b2
        return 0.5 * abs(s)
    ex0 = ex1 = ex2 = en0 = en1 = en2 = 0.0
    has_exit = False
    has_entry = False
    for k in range(nv):
        m = (k + 1) % nv
        a0, a1, a2 = poly[t, 3 * k] - p0, poly[t, 3 * k + 1] - p1, poly[t, 3 * k + 2] - p2
        b0, b1, b2 = poly[t, 3 * m] - p0, poly[t, 3 * m + 1] - p1, poly[t, 3 * m + 2] - p2
        ha = a0 * n0 + a1 * n1 + a2 * n2
        hb = b0 * n0 + b1 * n1 + b2 * n2
        if ha >= 0.0 and hb >= 0.0:
            u0, u1, u2 = _unit(a0, a1, a2)
            w0, w1, w2 = _unit(b0, b1, b2)
            s += _edge(u0, u1, u2, w0, w1, w2, n0, n1, n2)
        elif ha >= 0.0:  # leaves the hemisphere: a → horizon point
            f = ha / (ha - hb)
            ex0, ex1, ex2 = _unit(a0 + f * (b0 - a0), a1 + f * (b1 - a1), a2 + f * (b2 - a2))
            has_exit = True
            u0, u1, u2 = _unit(a0, a1, a2)
            s += _edge(u0, u1, u2, ex0, ex1, ex2, n0, n1, n2)
        elif hb >= 0.0:  # enters it: horizon point → b
            f = ha / (ha - hb)
            en0, en1, en2 = _unit(a0 + f * (b0 - a0), a1 + f * (b1 - a1), a2 + f * (b2 - a2))
            has_entry = True
            w0, w1, w2 = _unit(b0, b1, b2)
            s += _edge(en0, en1, en2, w0, w1, w2, n0, n1, n2)
    if has_exit and has_entry:  # the clipped polygon's edge along the horizon
        s += _edge(ex0, ex1, ex2, en0, en1, en2, n0, n1, n2)
    return 0.5 * abs(s)


@nb.njit(inline="always", fastmath=FASTMATH)
def _lobe_light(p0, p1, p2, n0, n1, n2, r0, r1, r2, lam, poly, t):
    """∫ exp(λ(r·ω − 1)) · SG_light(ω) dω, the emitter taken as an SG of amplitude 1 and its solid
    angle about the direction to its centre (0 if p is behind it or the centre below the horizon)."""
    q0, q1, q2 = poly[t, 16] - p0, poly[t, 17] - p1, poly[t, 18] - p2
    d2 = q0 * q0 + q1 * q1 + q2 * q2
    if not d2 > 1e-20:
        return 0.0
    dl = math.sqrt(d2)
    q0, q1, q2 = q0 / dl, q1 / dl, q2 / dl
    cos_l = -(q0 * poly[t, 12] + q1 * poly[t, 13] + q2 * poly[t, 14])
    if cos_l <= 0.0 or q0 * n0 + q1 * n1 + q2 * n2 <= 0.0:
        return 0.0
    omega = min(poly[t, 19] * cos_l / d2, 2.0 * math.pi)  # solid angle (small-emitter approximation)
    lam_l = 2.0 * math.pi / omega  # an SG of amplitude 1 integrating to ≈ Ω
    v0, v1, v2 = lam * r0 + lam_l * q0, lam * r1 + lam_l * q1, lam * r2 + lam_l * q2
    d = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if d < 1e-6:
        return 4.0 * math.pi * fast_exp_neg(-lam - lam_l)
    # 2π (e^(d−λ−λ_l) − e^(−d−λ−λ_l)) / d, d ≤ λ + λ_l; the second exponential is below 1e-4 of
    # the first once d > 5 (always, for lobes and emitters sharper than 2.5)
    big = fast_exp_neg(d - lam - lam_l)
    if d < 5.0:
        big -= math.exp(-d - lam - lam_l)
    return TWO_PI * big / d


@nb.njit(inline="always", fastmath=FASTMATH)
def _terms_at(p0, p1, p2, n0, n1, n2, e0, e1, e2, rough, poly, lum, specular):
    """(E, S) at p with normal n, the viewer at e (see the module docstring); (0, 0) for non-finite input."""
    nl = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if not (math.isfinite(p0 + p1 + p2) and math.isfinite(nl) and nl > 1e-12):
        return 0.0, 0.0
    inv = 1.0 / nl
    n0, n1, n2 = n0 * inv, n1 * inv, n2 * inv
    e = 0.0
    for t in range(poly.shape[0]):
        e += lum[t] * polygon_form(p0, p1, p2, n0, n1, n2, poly, t)
    sp = 0.0
    if specular:
        v0, v1, v2 = e0 - p0, e1 - p1, e2 - p2
        vl = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if vl > 1e-12 and math.isfinite(vl) and math.isfinite(rough):
            v0, v1, v2 = v0 / vl, v1 / vl, v2 / vl
            ndv = n0 * v0 + n1 * v1 + n2 * v2
            cos_o = max(ndv, MIN_NDOTV)
            r0, r1, r2 = 2.0 * ndv * n0 - v0, 2.0 * ndv * n1 - v1, 2.0 * ndv * n2 - v2
            a = max(rough * rough, 1e-3)  # the renderer's GGX α (roughness² with its floor)
            lam = 1.0 / (2.0 * a * a * cos_o)
            amp = 1.0 / (math.pi * a * a * 4.0 * cos_o)  # D's peak over the BRDF's 4 cos_o (G ≈ 1)
            for t in range(poly.shape[0]):
                sp += lum[t] * amp * _lobe_light(p0, p1, p2, n0, n1, n2, r0, r1, r2, lam, poly, t)
    if not math.isfinite(e):
        e = 0.0
    if not math.isfinite(sp):
        sp = 0.0
    return e, sp


@nb.njit(inline="always")
def _eval(p, gid, pos, nrm, rough, viewer, spc, poly, lum, specular):
    if gid[p] < 0:
        return 0.0, 0.0
    # the specular term only where there is a specular lobe (above the guides' floor)
    return _terms_at(pos[p, 0], pos[p, 1], pos[p, 2], nrm[p, 0], nrm[p, 1], nrm[p, 2], viewer[0], viewer[1], viewer[2],
                     rough[p], poly, lum, specular and max(spc[p, 0], max(spc[p, 1], spc[p, 2])) > SPECULAR_MIN)


@nb.njit(inline="always")
def _same_surface(gid, nrm, p, q):
    """q may stand in for p: same object, normals within ~18° (cos > 0.95)."""
    if gid[q] != gid[p]:
        return False
    c = nrm[p, 0] * nrm[q, 0] + nrm[p, 1] * nrm[q, 1] + nrm[p, 2] * nrm[q, 2]
    lp = nrm[p, 0] * nrm[p, 0] + nrm[p, 1] * nrm[p, 1] + nrm[p, 2] * nrm[p, 2]
    lq = nrm[q, 0] * nrm[q, 0] + nrm[q, 1] * nrm[q, 1] + nrm[q, 2] * nrm[q, 2]
    return c > 0.0 and c * c > 0.9025 * lp * lq


@nb.njit(parallel=True, cache=True, nogil=True, fastmath=FASTMATH)
def _products_kernel(gid, pos, nrm, rough, viewer, alb, spc, poly, lum, floor_d, floor_s, specular, W, H,
                     y0, y1, x0, x1, use_mask, mask, lattice, irr, spec_term, out_d, out_s):
    """irr = E, spec_term = S, out_d = alb·(E + F_d), out_s = spc·(S + F_s) over the box (and the mask).

    lattice 2: the terms are evaluated at the pixels of even row and column only (pass 1); the
    others take the mean of the 2 or 4 nearest of them when all show the same surface (same
    object, normals within ~18°), else are evaluated too (pass 2). Lattice pixels outside the
    box or the mask kept their attributes, so their stored terms are current."""
    if lattice == 2:
        for y in nb.prange(y0, y1):
            if y % 2:
                continue
            for x in range(x0 + x0 % 2, x1, 2):
                p = y * W + x
                if use_mask and not mask[p]:
                    continue
                irr[p], spec_term[p] = _eval(p, gid, pos, nrm, rough, viewer, spc, poly, lum, specular)
    for y in nb.prange(y0, y1):
        for x in range(x0, x1):
            p = y * W + x
            if use_mask and not mask[p]:
                continue
            if lattice == 1 or gid[p] < 0:
                e, sp = _eval(p, gid, pos, nrm, rough, viewer, spc, poly, lum, specular)
            elif x % 2 == 0 and y % 2 == 0:
                e, sp = irr[p], spec_term[p]
            else:
                xa, xb = (x, x) if x % 2 == 0 else (x - 1, x + 1)
                ya, yb = (y, y) if y % 2 == 0 else (y - 1, y + 1)
                ok = xb < W and yb < H
                if ok:
                    for q in (ya * W + xa, ya * W + xb, yb * W + xa, yb * W + xb):
                        if not _same_surface(gid, nrm, p, q):
                            ok = False
                if ok:
                    e = 0.25 * (irr[ya * W + xa] + irr[ya * W + xb] + irr[yb * W + xa] + irr[yb * W + xb])
                    sp = 0.25 * (spec_term[ya * W + xa] + spec_term[ya * W + xb] + spec_term[yb * W + xa]
                                 + spec_term[yb * W + xb])
                else:
                    e, sp = _eval(p, gid, pos, nrm, rough, viewer, spc, poly, lum, specular)
            irr[p] = e
            spec_term[p] = sp
            g = e + floor_d
            h = sp + floor_s
            for c in range(3):
                out_d[p, c] = alb[p, c] * g
                out_s[p, c] = spc[p, c] * h


@nb.njit(cache=True, nogil=True)
def terms_at_points(pos, nrm, viewer, rough, poly, lum):
    """(E, S) at each of n points (n, 3) with normals (n, 3) and roughness (n,) (tests, plots)."""
    e = np.empty(pos.shape[0], np.float64)
    s = np.empty(pos.shape[0], np.float64)
    for i in range(pos.shape[0]):
        e[i], s[i] = _terms_at(pos[i, 0], pos[i, 1], pos[i, 2], nrm[i, 0], nrm[i, 1], nrm[i, 2],
                               viewer[0], viewer[1], viewer[2], rough[i], poly, lum, True)
    return e, s


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


class AnalyticDirect:
    """The demodulation products at one resolution, recomputed only where asked.

    `update(...)` writes `irradiance` (E, (n,)), `specular` (S, (n,)), `diffuse_products`
    albedo·(E + F_d) and `specular_products` spec_albedo·(S + F_s) ((n, 3) each) for a box (and a
    mask); the floors must be set first (`set_floors`)."""

    def __init__(self, width: int, height: int, polygons: np.ndarray, luminance: np.ndarray, viewer, lattice: int = 1):
        if lattice not in (1, 2):
            raise ValueError(f"analytic lattice: expected 1 or 2, got {lattice!r}")
        self.lattice = lattice  # 2: terms evaluated on every second row and column, interpolated on smooth surfaces
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

    def set_floors(self, diffuse: float, specular: float) -> None:
        for name, f in (("diffuse", diffuse), ("specular", specular)):
            if not (math.isfinite(f) and f > 0.0):
                raise ValueError(f"analytic {name} floor: expected a finite positive value, got {f!r}")
        self.floors = (float(diffuse), float(specular))

    def update(self, object_id, position, normal, roughness, albedo, spec_albedo, box, mask: np.ndarray | None = None) -> None:
        if self.floors is None:
            raise RuntimeError("AnalyticDirect.update before set_floors")
        y0, y1, x0, x1 = (int(v) for v in box)
        use_mask = mask is not None
        m = np.ascontiguousarray(mask, np.bool_).reshape(-1) if use_mask else _NO_MASK
        _products_kernel(np.ascontiguousarray(object_id, np.int32).reshape(-1), _flat3(position), _flat3(normal),
                         np.ascontiguousarray(roughness, np.float32).reshape(-1), self.viewer, _flat3(albedo),
                         _flat3(spec_albedo), self.poly, self.lum, self.floors[0], self.floors[1], True, self.width,
                         self.height, y0, y1, x0, x1, use_mask, m, self.lattice, self.irradiance, self.specular, self.diffuse_products,
                         self.specular_products)


def floor_from(term: np.ndarray, object_id: np.ndarray, fraction: float) -> float:
    """F = fraction × the mean term over the lit pixels (id ≥ 0, term > 0); 1.0 if there are none
    (then the ratio is the signal itself, scaled)."""
    e = np.asarray(term, np.float64).reshape(-1)
    lit = (np.asarray(object_id).reshape(-1) >= 0) & (e > 0) & np.isfinite(e)
    m = float(e[lit].mean()) if lit.any() else 0.0
    return fraction * m if m > 0 else 1.0


_NO_MASK = np.zeros(1, np.bool_)


def _flat3(a) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).reshape(-1, 3)
