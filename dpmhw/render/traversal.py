"""Closest-hit and occlusion queries over the whole scene, inside numba kernels (Embree C API).

Same scene model as `accel.EmbreeAccel`: one BVH for all static objects in world space, and one
per distinct moving mesh (`accel.mesh_key`) in its model space. A ray is tested against a moving
object only if it passes within that object's bounding sphere before the closest hit so far, and
is then rotated into model space (a rigid transform keeps ray distances), with Embree's tfar
culling the farther hits. The sphere test and the transform repeat `accel._rays_into_model`'s
float32 arithmetic exactly, so both paths return the same hits bit for bit.

`acc` is the tuple (scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere) built by
`RtcAccel.tables`: scenes[0] is the static RTCScene (0 if none), scenes[1 + j] the BVH of moving
object dyn_obj[j], whose model-space bounding sphere is dyn_sphere[j] = (cx, cy, cz, r).

Queries take rows of the caller's ray arrays, as 16-wide packets or one ray per call (an
RTCRayHit has the layout of a 1-wide packet, so both share one loop body).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from dpmhw.render import rtc
from dpmhw.render.accel import mesh_key

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
    f[rtc.R_TFAR * W + j] = tfar
    iv[rtc.H_GEOM * W + j], iv[rtc.H_INST * W + j] = rtc.INVALID, rtc.INVALID


@nb.njit(inline="always", nogil=True, cache=True)
def _constant_fields(f, iv, W):
    """The fields of every lane of a W-wide packet that no query changes: tnear 0, time 0, all
    mask bits, id 0, flags 0 (a query writes only tfar and the hit)."""
    for j in range(W):
        f[rtc.R_TNEAR * W + j], f[rtc.R_TIME * W + j] = 0.0, 0.0
        iv[rtc.R_MASK * W + j], iv[rtc.R_ID * W + j], iv[rtc.R_FLAGS * W + j] = rtc.INVALID, 0, 0


@nb.njit(inline="always", nogil=True, cache=True)
def _intersect(packets, vp, scene, fp):
    if packets:
        rtc.rtcIntersect16(vp, scene, fp, 0)
    else:
        rtc.rtcIntersect1(scene, fp, 0)


@nb.njit(inline="always", nogil=True, cache=True)
def _occluded(packets, vp, scene, fp):
    if packets:
        rtc.rtcOccluded16(vp, scene, fp, 0)
    else:
        rtc.rtcOccluded1(scene, fp, 0)


@nb.njit(nogil=True, cache=True)
def scratch16():
    """Aligned scratch for one 16-wide packet or one ray: (float32 view, int32 view, int32 valid[16])."""
    f = rtc.aligned_words(rtc.P16_RAYHIT_WORDS + 16)
    return f, f.view(np.int32), f[rtc.P16_RAYHIT_WORDS:].view(np.int32)


NO_ORDER = np.zeros(0, np.int64)


# The query loops below hold the whole per-ray / per-packet work in their own body: the scene
# tables are unpacked once, every array is indexed with scalars, and the only helpers inlined
# into the loop are straight-line code. A helper with branches that takes arrays (as the ray
# queries were before) makes numba update each array's reference count, atomically, for every
# call: ~10 atomic operations per ray, each stalling behind the ray Embree had just written.
# Single camera rays ran at 6.0 Mrays/CPU-s instead of 12.8 (packets, amortising it, were unchanged).
@nb.njit(nogil=True, cache=True)
def closest_rows(acc, R, T, o, d, order, first, end, t, obj, prim, u, v, packets, resume=False):
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
                g = iv[rtc.H_GEOM * W + i]
                r = rows[i]
                if g != rtc.INVALID:
                    k = static_objects[g]
                    t[r], obj[r], prim[r] = f[rtc.R_TFAR * W + i], k, tri_offsets[k] + iv[rtc.H_PRIM * W + i]
                    u[r], v[r] = f[rtc.H_U * W + i], f[rtc.H_V * W + i]
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
                if valid[i] != 0 and iv[rtc.H_GEOM * W + i] != rtc.INVALID:
                    r = rows[i]
                    t[r], obj[r], prim[r] = f[rtc.R_TFAR * W + i], k, tri_offsets[k] + iv[rtc.H_PRIM * W + i]
                    u[r], v[r] = f[rtc.H_U * W + i], f[rtc.H_V * W + i]


@nb.njit(nogil=True, cache=True)
def closest_range(acc, R, T, o, d, first, end, t, obj, prim, u, v, packets, resume=False):
    """Closest hits of rows [first, end) (see closest_rows)."""
    closest_rows(acc, R, T, o, d, NO_ORDER, first, end, t, obj, prim, u, v, packets, resume)


@nb.njit(nogil=True, cache=True)
def closest16(acc, R, T, f, iv, valid, o, d, rows, n, t, obj, prim, u, v, resume):
    """One packet: closest hits of the rays rows[:n], n ≤ 16 (see closest_rows), in the
    caller's scratch16() f, iv, valid."""
    _closest_rows(acc, R, T, f, iv, valid, o, d, rows, 0, n, t, obj, prim, u, v, True, resume)


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
    return tile_order_range(width, 0, width * height)


@nb.njit(nogil=True, cache=True)
def closest_tiles(acc, R, T, o, d, width, first, end, t, obj, prim, u, v):
    """Closest hits of the camera rays of pixels [first, end) (one ray per pixel, row-major), as
    16-wide packets in tile order: what `RtcAccel.intersect_static` does for the whole image,
    done by one image segment in its own thread."""
    order = tile_order_range(width, first, end)
    closest_rows(acc, R, T, o, d, order, 0, order.shape[0], t, obj, prim, u, v, True)


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
                blocked[a + i] = f[rtc.R_TFAR * W + i] == -math.inf
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
                if valid[i] != 0 and f[rtc.R_TFAR * W + i] == -math.inf:
                    blocked[a + i] = True


class RtcAccel:
    """The scene's BVHs built through Embree's C API, with the same interface as
    `accel.EmbreeAccel` (so the benchmark and tests can put one beside the other), plus `acc`:
    the tables the compiled kernels query directly."""

    def __init__(self, objects, tri_offsets: np.ndarray, threads: int = 2, robust: bool | None = None):
        from concurrent.futures import ThreadPoolExecutor

        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="rtc") if self.threads > 1 else None
        self.tri_offsets = np.asarray(tri_offsets, np.int32)
        static = [i for i, o in enumerate(objects) if not o.is_dynamic]
        self.static_objects = np.array(static if static else [0], dtype=np.int32)
        self._scenes: list[rtc.RtcScene] = []
        self.static_scene = None
        if static:
            self.static_scene = rtc.RtcScene([objects[i].pose.apply(objects[i].mesh.vertices).astype(np.float32) for i in static],
                                             [objects[i].mesh.faces for i in static], robust=robust)
            self._scenes.append(self.static_scene)
        self.dynamic_objects = [i for i, o in enumerate(objects) if o.is_dynamic]
        by_mesh: dict[bytes, rtc.RtcScene] = {}
        handles = [self.static_scene.handle if self.static_scene else 0]
        sphere = []
        for i in self.dynamic_objects:
            mesh = objects[i].mesh
            key = mesh_key(mesh)
            if key not in by_mesh:  # copies of one mesh share one BVH
                by_mesh[key] = rtc.RtcScene([np.asarray(mesh.vertices, np.float32)], [mesh.faces], robust=robust)
                self._scenes.append(by_mesh[key])
            handles.append(by_mesh[key].handle)
            lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
            centre = (lo + hi) / 2  # the same sphere as EmbreeAccel's
            radius = np.linalg.norm(mesh.vertices - centre, axis=1).max() * (1 + 1e-4) + 1e-9
            sphere.append([*centre.astype(np.float32), np.float32(radius)])
        self.acc = (np.array(handles, np.int64), self.static_objects, self.tri_offsets,
                    np.array(self.dynamic_objects, np.int32), np.array(sphere, np.float32).reshape(-1, 4))
        scenes = self.acc[0]
        # only the moving objects (static hits already known) / only the static BVH
        self.acc_moving = (np.concatenate([[0], scenes[1:]]).astype(np.int64),) + self.acc[1:]
        self._order_key, self._order = None, NO_ORDER
        self.acc_static = (scenes[:1].copy(), self.static_objects, self.tri_offsets, np.zeros(0, np.int32), np.zeros((0, 4), np.float32))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        for s in self._scenes:
            s.close()
        self._scenes = []

    def _split(self, fn, n: int, grain: int = 4096) -> None:
        """fn(first, end) over a few chunks of [0, n) per thread (the kernels release the GIL)."""
        chunks = max(1, min(4 * self.threads, n // grain))
        bounds = np.linspace(0, n, chunks + 1).astype(np.int64) // 16 * 16  # whole packets (tiles) per chunk
        bounds[-1] = n
        jobs = [(int(a), int(e)) for a, e in zip(bounds[:-1], bounds[1:]) if e > a]
        if self._pool is None or len(jobs) < 2:
            for a, e in jobs:
                fn(a, e)
        else:
            list(self._pool.map(lambda job: fn(*job), jobs))

    def intersect_range(self, origins, directions, first, end, poses_R, poses_t, hits, static_done: bool = False, packets: bool = False) -> None:
        """As EmbreeAccel.intersect_range (`static_done`: the rows already hold the static hits)."""
        acc = self.acc_moving if static_done else self.acc
        closest_range(acc, poses_R, poses_t, origins, directions, first, end, hits.t, hits.obj, hits.prim, hits.u, hits.v, packets, static_done)

    def occluded_range(self, origins, directions, tmax, first, end, poses_R, poses_t, blocked, packets: bool = False) -> None:
        occluded_range(self.acc, poses_R, poses_t, origins, directions, tmax, first, end, blocked, packets)

    def _tile_order(self, width: int, height: int) -> np.ndarray:
        if self._order_key != (width, height):
            self._order, self._order_key = tile_order(width, height), (width, height)
        return self._order

    def intersect_static(self, origins: np.ndarray, directions: np.ndarray, width: int | None = None):
        """Closest hits among the static objects only (every moving object ignored). With the
        image `width` (rays row-major, one per pixel), as 4×4 pixel tiles; else 16 rows at a time."""
        from dpmhw.render.accel import empty_hits

        n = len(origins)
        hits = empty_hits(n)
        R = np.zeros((len(self.tri_offsets), 3, 3), np.float32)
        T = np.zeros((len(self.tri_offsets), 3), np.float32)
        h = (hits.t, hits.obj, hits.prim, hits.u, hits.v)
        if width and n % width == 0:  # camera rays, one per pixel: 4×4 tiles
            order = self._tile_order(width, n // width)
            self._split(lambda a, e: closest_rows(self.acc_static, R, T, origins, directions, order, a, e, *h, True), n)
        else:
            self._split(lambda a, e: closest_range(self.acc_static, R, T, origins, directions, a, e, *h, True), n)
        return hits
