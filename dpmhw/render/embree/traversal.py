"""Closest-hit and occlusion queries over the whole scene, inside numba kernels (Embree C API).

Same scene model as `accel.EmbreeAccel`: one BVH for all static objects in world space, and one
per distinct moving mesh (`accel.mesh_key`) in its model space. A ray is tested against a moving
object only if it passes within that object's bounding sphere before the closest hit so far, and
is then rotated into model space (a rigid transform keeps ray distances), with Embree's tfar
culling the farther hits. The sphere test and the transform repeat `accel._rays_into_model`'s
float32 arithmetic exactly, so both paths return the same hits bit for bit.

`acc` is the tuple (scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere) built by
`accel.RtcAccel`: scenes[0] is the static RTCScene (0 if none), scenes[1 + j] the BVH of moving
object dyn_obj[j], whose model-space bounding sphere is dyn_sphere[j] = (cx, cy, cz, r).

Queries take rows of the caller's ray arrays, as 16-wide packets or one ray per call (an
RTCRayHit has the layout of a 1-wide packet, so both share one loop body).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from dpmhw.render.embree import capi

NO_HIT_TFAR = np.float32(1e37)  # embreex's default tfar: keeps hits identical to it


@nb.njit(inline="always", nogil=True, cache=True)
def _centre(R, T, k, sphere, j):
    """World centre and radius of moving object k's bounding sphere (sphere[j]: model-space
    centre, radius), in float32 as accel._rays_into_model."""
    c0 = R[k, 0, 0] * sphere[j, 0] + R[k, 0, 1] * sphere[j, 1] + R[k, 0, 2] * sphere[j, 2] + T[k, 0]
    c1 = R[k, 1, 0] * sphere[j, 0] + R[k, 1, 1] * sphere[j, 1] + R[k, 1, 2] * sphere[j, 2] + T[k, 1]
    c2 = R[k, 2, 0] * sphere[j, 0] + R[k, 2, 1] * sphere[j, 1] + R[k, 2, 2] * sphere[j, 2] + T[k, 2]
    return c0, c1, c2, sphere[j, 3]


@nb.njit(inline="always", nogil=True, cache=True)
def _near(o0, o1, o2, d0, d1, d2, tmax, c0, c1, c2, r):
    """The ray passes within the sphere (world centre c, radius r) before tmax (float32, the
    same operations as accel._rays_into_model: no fast-math)."""
    r2 = r * r
    q0, q1, q2 = c0 - o0, c1 - o1, c2 - o2
    along = q0 * d0 + q1 * d1 + q2 * d2
    dist2 = q0 * q0 + q1 * q1 + q2 * q2
    return dist2 <= r2 or (along > 0.0 and along - r < tmax and dist2 - along * along <= r2)


@nb.njit(inline="always", nogil=True, cache=True)
def _into_model(o0, o1, o2, d0, d1, d2, R, T, k):
    """x_model = Rᵀ (x_world − t), d_model = Rᵀ d for object k (float32, as accel._rays_into_model)."""
    p0, p1, p2 = o0 - T[k, 0], o1 - T[k, 1], o2 - T[k, 2]
    m0 = R[k, 0, 0] * p0 + R[k, 1, 0] * p1 + R[k, 2, 0] * p2
    m1 = R[k, 0, 1] * p0 + R[k, 1, 1] * p1 + R[k, 2, 1] * p2
    m2 = R[k, 0, 2] * p0 + R[k, 1, 2] * p1 + R[k, 2, 2] * p2
    e0 = R[k, 0, 0] * d0 + R[k, 1, 0] * d1 + R[k, 2, 0] * d2
    e1 = R[k, 0, 1] * d0 + R[k, 1, 1] * d1 + R[k, 2, 1] * d2
    e2 = R[k, 0, 2] * d0 + R[k, 1, 2] * d1 + R[k, 2, 2] * d2
    return m0, m1, m2, e0, e1, e2


@nb.njit(inline="always", nogil=True, cache=True)
def _load(f, iv, W, j, o0, o1, o2, d0, d1, d2, tfar):
    """Write ray j of a W-wide packet (W = 1: an RTCRayHit, whose layout is the 1-wide packet's:
    field k of lane j at word W * k + j), with the hit reset: only what a query reads and may
    have changed (the constant fields are set once per query call by _constant_fields)."""
    f[j], f[W + j], f[2 * W + j] = o0, o1, o2
    f[4 * W + j], f[5 * W + j], f[6 * W + j] = d0, d1, d2
    f[capi.R_TFAR * W + j] = tfar
    iv[capi.H_GEOM * W + j], iv[capi.H_INST * W + j] = capi.INVALID, capi.INVALID


@nb.njit(inline="always", nogil=True, cache=True)
def _constant_fields(f, iv, W):
    """The fields of every lane of a W-wide packet that no query changes: tnear 0, time 0, all
    mask bits, id 0, flags 0 (a query writes only tfar and the hit)."""
    for j in range(W):
        f[capi.R_TNEAR * W + j], f[capi.R_TIME * W + j] = 0.0, 0.0
        iv[capi.R_MASK * W + j], iv[capi.R_ID * W + j], iv[capi.R_FLAGS * W + j] = capi.INVALID, 0, 0


@nb.njit(inline="always", nogil=True, cache=True)
def _intersect(packets, vp, scene, fp):
    if packets:
        capi.rtcIntersect16(vp, scene, fp, 0)
    else:
        capi.rtcIntersect1(scene, fp, 0)


@nb.njit(inline="always", nogil=True, cache=True)
def _occluded(packets, vp, scene, fp):
    if packets:
        capi.rtcOccluded16(vp, scene, fp, 0)
    else:
        capi.rtcOccluded1(scene, fp, 0)


@nb.njit(nogil=True, cache=True)
def scratch16():
    """Aligned scratch for one 16-wide packet or one ray: (float32 view, int32 view, int32 valid[16])."""
    f = capi.aligned_words(capi.P16_RAYHIT_WORDS + 16)
    return f, f.view(np.int32), f[capi.P16_RAYHIT_WORDS:].view(np.int32)


NO_ORDER = np.zeros(0, np.int64)

# Flags and row numbers are passed between these kernels as run-time values (`bool(True)`,
# `np.int64(0)`), never as literals: numba compiles a callee once per literal value it is given,
# and these loops are the longest compiles after the shading kernels'.


# The query loops below hold the whole per-ray / per-packet work in their own body: the scene
# tables are unpacked once, every array is indexed with scalars, and the only helpers inlined
# into the loop are straight-line code. A helper with branches that takes arrays (as the ray
# queries were before) makes numba update each array's reference count, atomically, for every
# call: ~10 atomic operations per ray, each stalling behind the ray Embree had just written.
# Single camera rays ran at 6.0 Mrays/CPU-s instead of 12.8 (packets, amortising it, were unchanged).
@nb.njit(nogil=True, cache=True)
def closest_rows(acc, R, T, o, d, order, first, end, t, obj, prim, u, v, packets, resume):
    """Closest hits of the rays order[first:end] (rows first..end - 1 if `order` is empty) of
    o, d, written to the same rows of t, obj, prim, u, v (inf / −1 on a miss; global triangle
    index). 16 consecutive entries per packet, or one ray per call (`packets` False).
    `resume`: those rows already hold the best hits so far (else they start empty)."""
    f, iv, valid = scratch16()
    _closest_rows(acc, R, T, f, iv, valid, o, d, order, first, end, t, obj, prim, u, v, packets, resume)


@nb.njit(nogil=True, cache=True)
def _closest_rows(acc, R, T, f, iv, valid, o, d, order, first, end, t, obj, prim, u, v, packets, resume):
    """closest_rows with the caller's scratch16()."""
    scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere = acc
    scene0 = scenes[0]
    direct = order.shape[0] == 0
    W = 16 if packets else 1
    _constant_fields(f, iv, W)
    fp, vp = f.ctypes.data, valid.ctypes.data
    rows = np.empty(16, np.int64)
    for a in range(first, end, W):
        n = min(W, end - a)
        for i in range(n):
            rows[i] = a + i if direct else order[a + i]
        for i in range(16):
            valid[i] = -1 if i < n else 0
        if scene0 != 0:
            for i in range(n):
                r = rows[i]
                _load(f, iv, W, i, o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2], NO_HIT_TFAR)
            _intersect(packets, vp, scene0, fp)
            for i in range(n):
                g = iv[capi.H_GEOM * W + i]
                r = rows[i]
                if g != capi.INVALID:
                    k = static_objects[g]
                    t[r], obj[r], prim[r] = f[capi.R_TFAR * W + i], k, tri_offsets[k] + iv[capi.H_PRIM * W + i]
                    u[r], v[r] = f[capi.H_U * W + i], f[capi.H_V * W + i]
                elif not resume:
                    t[r], obj[r], prim[r], u[r], v[r] = np.inf, -1, -1, 0.0, 0.0
        elif not resume:
            for i in range(n):
                r = rows[i]
                t[r], obj[r], prim[r], u[r], v[r] = np.inf, -1, -1, 0.0, 0.0
        for j in range(dyn_obj.shape[0]):
            k = dyn_obj[j]
            c0, c1, c2, rad = _centre(R, T, k, dyn_sphere, j)
            lanes = 0
            for i in range(n):
                r = rows[i]
                o0, o1, o2, d0, d1, d2 = o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2]
                near = _near(o0, o1, o2, d0, d1, d2, t[r], c0, c1, c2, rad)
                if near:
                    m0, m1, m2, e0, e1, e2 = _into_model(o0, o1, o2, d0, d1, d2, R, T, k)
                    _load(f, iv, W, i, m0, m1, m2, e0, e1, e2, t[r])
                    lanes += 1
                valid[i] = -1 if near else 0
            if lanes == 0:
                continue
            _intersect(packets, vp, scenes[1 + j], fp)
            for i in range(n):
                if valid[i] != 0 and iv[capi.H_GEOM * W + i] != capi.INVALID:
                    r = rows[i]
                    t[r], obj[r], prim[r] = f[capi.R_TFAR * W + i], k, tri_offsets[k] + iv[capi.H_PRIM * W + i]
                    u[r], v[r] = f[capi.H_U * W + i], f[capi.H_V * W + i]


@nb.njit(nogil=True, cache=True)
def closest_range(acc, R, T, o, d, first, end, t, obj, prim, u, v, packets, resume):
    """Closest hits of rows [first, end) (see closest_rows)."""
    closest_rows(acc, R, T, o, d, np.empty(0, np.int64), first, end, t, obj, prim, u, v, packets, resume)


@nb.njit(nogil=True, cache=True)
def closest16(acc, R, T, f, iv, valid, o, d, rows, n, t, obj, prim, u, v, resume):
    """One packet: closest hits of the rays rows[:n], n ≤ 16 (see closest_rows), in the
    caller's scratch16() f, iv, valid."""
    _closest_rows(acc, R, T, f, iv, valid, o, d, rows, np.int64(0), n, t, obj, prim, u, v, bool(True), resume)


@nb.njit(nogil=True, cache=True)
def tile_order_range(width, first, end):
    """Pixels [first, end) of a row-major image `width` wide in 4×4-tile order: tiles row by row,
    aligned with the whole image's tiles and clipped to the range, so 16 consecutive entries of
    a whole tile are one tile and a packet's camera rays are neighbours."""
    order = np.empty(max(end - first, 0), np.int64)
    n = 0
    if end > first:
        for ty in range(first // width // 4 * 4, (end - 1) // width + 1, 4):
            for tx in range(0, width, 4):
                for y in range(ty, ty + 4):
                    for x in range(tx, min(tx + 4, width)):
                        p = y * width + x
                        if first <= p < end:
                            order[n] = p
                            n += 1
    return order


@nb.njit(nogil=True, cache=True)
def tile_order(width, height):
    """Row-major pixel indices of the whole image in 4×4-tile order (tile row ty starts at
    4 * ty * width)."""
    return tile_order_range(width, np.int64(0), width * height)


@nb.njit(nogil=True, cache=True)
def closest_tiles(acc, R, T, o, d, width, first, end, t, obj, prim, u, v):
    """Closest hits of the camera rays of pixels [first, end) (one ray per pixel, row-major), as
    16-wide packets in tile order: what `RtcAccel.intersect_static` does for the whole image,
    done by one image segment in its own thread."""
    order = tile_order_range(width, first, end)
    closest_rows(acc, R, T, o, d, order, np.int64(0), order.shape[0], t, obj, prim, u, v, bool(True), bool(False))


@nb.njit(nogil=True, cache=True)
def occluded_range(acc, R, T, o, d, tmax, first, end, blocked, packets):
    """blocked[i] (something lies along ray i closer than tmax[i]) for rows [first, end), as
    16-wide packets of consecutive rows or one ray per call."""
    scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere = acc
    scene0 = scenes[0]
    W = 16 if packets else 1
    f, iv, valid = scratch16()
    _constant_fields(f, iv, W)
    fp, vp = f.ctypes.data, valid.ctypes.data
    for a in range(first, end, W):
        n = min(W, end - a)
        for i in range(16):
            valid[i] = -1 if i < n else 0
        for i in range(n):
            blocked[a + i] = False
        if scene0 != 0:
            for i in range(n):
                _load(f, iv, W, i, o[a + i, 0], o[a + i, 1], o[a + i, 2], d[a + i, 0], d[a + i, 1], d[a + i, 2], tmax[a + i])
            _occluded(packets, vp, scene0, fp)
            for i in range(n):
                blocked[a + i] = f[capi.R_TFAR * W + i] == -math.inf
        for j in range(dyn_obj.shape[0]):
            k = dyn_obj[j]
            c0, c1, c2, rad = _centre(R, T, k, dyn_sphere, j)
            lanes = 0
            for i in range(n):
                o0, o1, o2, d0, d1, d2 = o[a + i, 0], o[a + i, 1], o[a + i, 2], d[a + i, 0], d[a + i, 1], d[a + i, 2]
                near = not blocked[a + i] and _near(o0, o1, o2, d0, d1, d2, tmax[a + i], c0, c1, c2, rad)
                if near:
                    m0, m1, m2, e0, e1, e2 = _into_model(o0, o1, o2, d0, d1, d2, R, T, k)
                    _load(f, iv, W, i, m0, m1, m2, e0, e1, e2, tmax[a + i])
                    lanes += 1
                valid[i] = -1 if near else 0
            if lanes == 0:
                continue
            _occluded(packets, vp, scenes[1 + j], fp)
            for i in range(n):
                if valid[i] != 0 and f[capi.R_TFAR * W + i] == -math.inf:
                    blocked[a + i] = True

