"""Closest-hit and occlusion queries over the whole scene, inside numba kernels (Embree C API).

Same scene model as `accel.EmbreeAccel`: one BVH for all static objects in world space, and one
per moving mesh in its model space. A ray is tested against a moving object only if it passes
within that object's bounding sphere before the closest hit so far, and is then rotated into
model space (a rigid transform keeps ray distances), with Embree's tfar culling the farther
hits. The sphere test and the transform repeat `accel._rays_into_model`'s float32 arithmetic
exactly, so both paths return the same hits bit for bit.

`acc` is the tuple (scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere) built by
`RtcAccel.tables`: scenes[0] is the static RTCScene (0 if none), scenes[1 + j] the BVH of moving
object dyn_obj[j], whose model-space bounding sphere is dyn_sphere[j] = (cx, cy, cz, r).

Queries come in single rays (`closest1`, `occluded1`) and 16-wide packets (`closest16`,
`occluded16`); packets take rows [a, a + n) of ray arrays with n ≤ 16.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from dpmhw.render import rtc

NO_HIT_TFAR = np.float32(1e37)  # embreex's default tfar: keeps hits identical to it


@nb.njit(inline="always", nogil=True, cache=True)
def _near(o0, o1, o2, d0, d1, d2, tmax, R, t, c, r):
    """The ray passes within the bounding sphere (centre c in model space, radius r) before tmax
    (float32, the same operations as accel._rays_into_model: no fast-math)."""
    c0 = R[0, 0] * c[0] + R[0, 1] * c[1] + R[0, 2] * c[2] + t[0]
    c1 = R[1, 0] * c[0] + R[1, 1] * c[1] + R[1, 2] * c[2] + t[1]
    c2 = R[2, 0] * c[0] + R[2, 1] * c[1] + R[2, 2] * c[2] + t[2]
    r2 = r * r
    q0, q1, q2 = c0 - o0, c1 - o1, c2 - o2
    along = q0 * d0 + q1 * d1 + q2 * d2
    dist2 = q0 * q0 + q1 * q1 + q2 * q2
    return dist2 <= r2 or (along > 0.0 and along - r < tmax and dist2 - along * along <= r2)


@nb.njit(inline="always", nogil=True, cache=True)
def _into_model(o0, o1, o2, d0, d1, d2, R, t):
    """x_model = Rᵀ (x_world − t), d_model = Rᵀ d (float32, as accel._rays_into_model)."""
    p0, p1, p2 = o0 - t[0], o1 - t[1], o2 - t[2]
    m0 = R[0, 0] * p0 + R[1, 0] * p1 + R[2, 0] * p2
    m1 = R[0, 1] * p0 + R[1, 1] * p1 + R[2, 1] * p2
    m2 = R[0, 2] * p0 + R[1, 2] * p1 + R[2, 2] * p2
    e0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
    e1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
    e2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
    return m0, m1, m2, e0, e1, e2


@nb.njit(nogil=True, cache=True)
def scratch1():
    """Aligned single-ray scratch: (float32 view, int32 view)."""
    f = rtc.aligned_words(rtc.RAYHIT_WORDS)
    return f, f.view(np.int32)


@nb.njit(nogil=True, cache=True)
def scratch16():
    """Aligned 16-wide packet scratch: (float32 view, int32 view, int32 valid[16])."""
    f = rtc.aligned_words(rtc.P16_RAYHIT_WORDS + 16)
    return f, f.view(np.int32), f[rtc.P16_RAYHIT_WORDS:].view(np.int32)


@nb.njit(nogil=True, cache=True)
def closest1(acc, R, T, f, iv, o0, o1, o2, d0, d1, d2, t, obj, prim, u, v):
    """Closest hit of one world-space ray, given the best so far (t, object, global triangle,
    u, v; pass inf, −1, −1, 0, 0 for none): returns the updated five (inf / −1 on a miss)."""
    scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere = acc
    if scenes[0] != 0:
        hit, th, g, p, uh, vh = rtc.intersect1(scenes[0], f, iv, o0, o1, o2, d0, d1, d2, NO_HIT_TFAR)
        if hit:
            k = static_objects[g]
            t, obj, prim, u, v = th, k, tri_offsets[k] + p, uh, vh
    for j in range(dyn_obj.shape[0]):
        k = dyn_obj[j]
        if _near(o0, o1, o2, d0, d1, d2, t, R[k], T[k], dyn_sphere[j], dyn_sphere[j, 3]):
            m0, m1, m2, e0, e1, e2 = _into_model(o0, o1, o2, d0, d1, d2, R[k], T[k])
            hit, th, g, p, uh, vh = rtc.intersect1(scenes[1 + j], f, iv, m0, m1, m2, e0, e1, e2, t)
            if hit:
                t, obj, prim, u, v = th, k, tri_offsets[k] + p, uh, vh
    return t, obj, prim, u, v


@nb.njit(nogil=True, cache=True)
def occluded1(acc, R, T, f, iv, o0, o1, o2, d0, d1, d2, tmax):
    """Does anything lie along the ray closer than tmax?"""
    scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere = acc
    if scenes[0] != 0 and rtc.occluded1(scenes[0], f, iv, o0, o1, o2, d0, d1, d2, tmax):
        return True
    for j in range(dyn_obj.shape[0]):
        k = dyn_obj[j]
        if _near(o0, o1, o2, d0, d1, d2, tmax, R[k], T[k], dyn_sphere[j], dyn_sphere[j, 3]):
            m0, m1, m2, e0, e1, e2 = _into_model(o0, o1, o2, d0, d1, d2, R[k], T[k])
            if rtc.occluded1(scenes[1 + j], f, iv, m0, m1, m2, e0, e1, e2, tmax):
                return True
    return False


@nb.njit(inline="always", nogil=True, cache=True)
def _load16(f, iv, j, o0, o1, o2, d0, d1, d2, tfar):
    f[j], f[16 + j], f[32 + j], f[48 + j] = o0, o1, o2, 0.0
    f[64 + j], f[80 + j], f[96 + j], f[112 + j] = d0, d1, d2, 0.0
    f[rtc.P_TFAR + j] = tfar
    iv[rtc.P_MASK + j], iv[rtc.P_ID + j], iv[rtc.P_FLAGS + j] = rtc.INVALID, 0, 0


@nb.njit(nogil=True, cache=True)
def closest16(acc, R, T, f, iv, valid, o, d, rows, n, t, obj, prim, u, v, resume):
    """Closest hits of the rays in rows[:n] (n ≤ 16) of o, d as one packet, written to the same
    rows of t, obj, prim, u, v (same values as closest1). `resume`: those rows already hold
    the best hits so far (else they start empty)."""
    scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere = acc
    for i in range(16):
        valid[i] = -1 if i < n else 0
    if not resume:
        for i in range(n):
            r = rows[i]
            t[r], obj[r], prim[r], u[r], v[r] = np.inf, -1, -1, 0.0, 0.0
    if scenes[0] != 0:
        for i in range(n):
            r = rows[i]
            _load16(f, iv, i, o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2], NO_HIT_TFAR)
            iv[rtc.P_GEOM + i], iv[rtc.P_INST + i], iv[rtc.P_PRIM + i] = rtc.INVALID, rtc.INVALID, rtc.INVALID
        rtc.rtcIntersect16(valid.ctypes.data, scenes[0], f.ctypes.data, 0)
        for i in range(n):
            g = iv[rtc.P_GEOM + i]
            if g != rtc.INVALID:
                r = rows[i]
                k = static_objects[g]
                t[r], obj[r], prim[r], u[r], v[r] = f[rtc.P_TFAR + i], k, tri_offsets[k] + iv[rtc.P_PRIM + i], f[rtc.P_U + i], f[rtc.P_V + i]
    for j in range(dyn_obj.shape[0]):
        k = dyn_obj[j]
        any_lane = False
        for i in range(n):
            r = rows[i]
            o0, o1, o2, d0, d1, d2 = o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2]
            if _near(o0, o1, o2, d0, d1, d2, t[r], R[k], T[k], dyn_sphere[j], dyn_sphere[j, 3]):
                m0, m1, m2, e0, e1, e2 = _into_model(o0, o1, o2, d0, d1, d2, R[k], T[k])
                _load16(f, iv, i, m0, m1, m2, e0, e1, e2, t[r])
                iv[rtc.P_GEOM + i], iv[rtc.P_INST + i], iv[rtc.P_PRIM + i] = rtc.INVALID, rtc.INVALID, rtc.INVALID
                valid[i] = -1
                any_lane = True
            else:
                valid[i] = 0
        if any_lane:
            rtc.rtcIntersect16(valid.ctypes.data, scenes[1 + j], f.ctypes.data, 0)
            for i in range(n):
                if valid[i] != 0 and iv[rtc.P_GEOM + i] != rtc.INVALID:
                    r = rows[i]
                    t[r], obj[r], prim[r], u[r], v[r] = f[rtc.P_TFAR + i], k, tri_offsets[k] + iv[rtc.P_PRIM + i], f[rtc.P_U + i], f[rtc.P_V + i]


@nb.njit(nogil=True, cache=True)
def occluded16(acc, R, T, f, iv, valid, o, d, tmax, a, n, blocked):
    """blocked[a + i] for rays o[a + i], d[a + i], tmax[a + i] (i < n ≤ 16) as one packet."""
    scenes, static_objects, tri_offsets, dyn_obj, dyn_sphere = acc
    for i in range(16):
        valid[i] = -1 if i < n else 0
    for i in range(n):
        blocked[a + i] = False
    if scenes[0] != 0:
        for i in range(n):
            _load16(f, iv, i, o[a + i, 0], o[a + i, 1], o[a + i, 2], d[a + i, 0], d[a + i, 1], d[a + i, 2], tmax[a + i])
        rtc.rtcOccluded16(valid.ctypes.data, scenes[0], f.ctypes.data, 0)
        for i in range(n):
            blocked[a + i] = f[rtc.P_TFAR + i] == -math.inf
    for j in range(dyn_obj.shape[0]):
        k = dyn_obj[j]
        any_lane = False
        for i in range(n):
            o0, o1, o2, d0, d1, d2 = o[a + i, 0], o[a + i, 1], o[a + i, 2], d[a + i, 0], d[a + i, 1], d[a + i, 2]
            if not blocked[a + i] and _near(o0, o1, o2, d0, d1, d2, tmax[a + i], R[k], T[k], dyn_sphere[j], dyn_sphere[j, 3]):
                m0, m1, m2, e0, e1, e2 = _into_model(o0, o1, o2, d0, d1, d2, R[k], T[k])
                _load16(f, iv, i, m0, m1, m2, e0, e1, e2, tmax[a + i])
                valid[i] = -1
                any_lane = True
            else:
                valid[i] = 0
        if any_lane:
            rtc.rtcOccluded16(valid.ctypes.data, scenes[1 + j], f.ctypes.data, 0)
            for i in range(n):
                if valid[i] != 0 and f[rtc.P_TFAR + i] == -math.inf:
                    blocked[a + i] = True


@nb.njit(nogil=True, cache=True)
def closest_range(acc, R, T, o, d, first, end, t, obj, prim, u, v, packets, resume=False):
    """Closest hits of rows [first, end), as 16-wide packets of consecutive rows or one by one
    (`resume`: the rows already hold the best hits so far)."""
    if packets:
        f, iv, valid = scratch16()
        rows = np.empty(16, np.int64)
        for a in range(first, end, 16):
            n = min(16, end - a)
            for i in range(n):
                rows[i] = a + i
            closest16(acc, R, T, f, iv, valid, o, d, rows, n, t, obj, prim, u, v, resume)
    else:
        f, iv = scratch1()
        for i in range(first, end):
            if resume:
                t0, ob0, p0, u0, v0 = t[i], obj[i], prim[i], u[i], v[i]
            else:
                t0, ob0, p0, u0, v0 = np.float32(np.inf), -1, -1, np.float32(0.0), np.float32(0.0)
            t[i], obj[i], prim[i], u[i], v[i] = closest1(acc, R, T, f, iv, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2],
                                                          t0, ob0, p0, u0, v0)


@nb.njit(nogil=True, cache=True)
def closest_tiles(acc, R, T, o, d, width, height, tile_row0, tile_row1, t, obj, prim, u, v):
    """Closest hits of camera rays (row-major, width × height) in 4×4 pixel tiles, one packet
    each, for the tile rows [tile_row0, tile_row1) (neighbouring pixels' rays are coherent)."""
    f, iv, valid = scratch16()
    rows = np.empty(16, np.int64)
    for ty in range(tile_row0, tile_row1):
        for tx in range(0, width, 4):
            n = 0
            for y in range(4 * ty, min(4 * ty + 4, height)):
                for x in range(tx, min(tx + 4, width)):
                    rows[n] = y * width + x
                    n += 1
            closest16(acc, R, T, f, iv, valid, o, d, rows, n, t, obj, prim, u, v, False)


@nb.njit(nogil=True, cache=True)
def occluded_range(acc, R, T, o, d, tmax, first, end, blocked, packets):
    """blocked[i] for rows [first, end), as 16-wide packets of consecutive rows or one by one."""
    if packets:
        f, iv, valid = scratch16()
        for a in range(first, end, 16):
            occluded16(acc, R, T, f, iv, valid, o, d, tmax, a, min(16, end - a), blocked)
    else:
        f, iv = scratch1()
        for i in range(first, end):
            blocked[i] = occluded1(acc, R, T, f, iv, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], tmax[i])


class RtcAccel:
    """The scene's BVHs built through Embree's C API, with the same interface as
    `accel.EmbreeAccel` (so the benchmark and tests can put one beside the other), plus `acc`:
    the tables the compiled kernels query directly."""

    def __init__(self, objects, tri_offsets: np.ndarray, threads: int = 2, robust: bool = rtc.ROBUST):
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
        by_mesh: dict[int, rtc.RtcScene] = {}
        handles = [self.static_scene.handle if self.static_scene else 0]
        sphere = []
        for i in self.dynamic_objects:
            mesh = objects[i].mesh
            if id(mesh) not in by_mesh:  # instances of one mesh share one BVH
                by_mesh[id(mesh)] = rtc.RtcScene([np.asarray(mesh.vertices, np.float32)], [mesh.faces], robust=robust)
                self._scenes.append(by_mesh[id(mesh)])
            handles.append(by_mesh[id(mesh)].handle)
            lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
            centre = (lo + hi) / 2  # the same sphere as EmbreeAccel's
            radius = np.linalg.norm(mesh.vertices - centre, axis=1).max() * (1 + 1e-4) + 1e-9
            sphere.append([*centre.astype(np.float32), np.float32(radius)])
        self.acc = (np.array(handles, np.int64), self.static_objects, self.tri_offsets,
                    np.array(self.dynamic_objects, np.int32), np.array(sphere, np.float32).reshape(-1, 4))
        scenes = self.acc[0]
        # only the moving objects (static hits already known) / only the static BVH
        self.acc_moving = (np.concatenate([[0], scenes[1:]]).astype(np.int64),) + self.acc[1:]
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
        bounds = np.linspace(0, n, chunks + 1).astype(np.int64)
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

    def intersect_static(self, origins: np.ndarray, directions: np.ndarray, width: int | None = None):
        """Closest hits among the static objects only (every moving object ignored). With the
        image `width` (rays row-major, one per pixel), as 4×4 pixel tiles; else 16 rows at a time."""
        from dpmhw.render.accel import empty_hits

        n = len(origins)
        hits = empty_hits(n)
        R = np.zeros((len(self.tri_offsets), 3, 3), np.float32)
        T = np.zeros((len(self.tri_offsets), 3), np.float32)
        h = (hits.t, hits.obj, hits.prim, hits.u, hits.v)
        if width and n % width == 0:
            height = n // width
            tile_rows = -(-height // 4)
            self._split(lambda a, e: closest_tiles(self.acc_static, R, T, origins, directions, width, height, a, e, *h), tile_rows, grain=16)
        else:
            self._split(lambda a, e: closest_range(self.acc_static, R, T, origins, directions, a, e, *h, True), n)
        return hits
