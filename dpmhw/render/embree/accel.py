"""The scene's BVHs for ray queries, for scenes whose rigid objects move every frame: `RtcAccel`
built through Embree's C API (its queries run in `traversal`'s kernels) and `EmbreeAccel` through
embreex (which has no instancing) with the same interface and the same hits.

Each BVH is built once: all static objects together in world
space, and every distinct moving mesh (`mesh_key`) in its own model space. Per frame a query
transforms the rays into each moving object's model space (a rigid transform keeps ray
distances), and every later BVH is asked only for hits closer than the best so far (embree's
`tfar` culls the rest).
The `*_range` queries work on a row range of the caller's arrays on the calling thread (the
integrator runs one per image segment from its own threads: `EmbreeScene.run` releases the GIL);
`intersect_static` splits its batch over the accelerator's threads.
"""

from __future__ import annotations

import hashlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba as nb
import numpy as np
from embreex import mesh_construction, rtcore_scene

from dpmhw.render.embree import capi
from dpmhw.render.embree.traversal import NO_ORDER, closest_range, closest_rows, occluded_range, tile_order
from dpmhw.scene_file import ObjectSpec

MIN_RAYS_PER_THREAD = 16384


@dataclass
class Hits:
    """Closest hits. t : (n,) float32 (inf on a miss); obj : (n,) int32 object index (−1 on a miss);
    prim : (n,) int32 triangle index into the global triangle tables; u, v : (n,) barycentrics."""

    t: np.ndarray
    obj: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray


@nb.njit(nogil=True, cache=True)
def _rays_into_model(o, d, tmax, R, t, centre, radius):
    """Select the rays that pass within `radius` of `centre` (model space) before `tmax`, and
    transform those into model space. Returns (index, o_model, d_model, tmax)."""
    n = o.shape[0]
    c0 = R[0, 0] * centre[0] + R[0, 1] * centre[1] + R[0, 2] * centre[2] + t[0]
    c1 = R[1, 0] * centre[0] + R[1, 1] * centre[1] + R[1, 2] * centre[2] + t[1]
    c2 = R[2, 0] * centre[0] + R[2, 1] * centre[1] + R[2, 2] * centre[2] + t[2]
    r2 = radius * radius
    keep = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        q0, q1, q2 = c0 - o[i, 0], c1 - o[i, 1], c2 - o[i, 2]
        along = q0 * d[i, 0] + q1 * d[i, 1] + q2 * d[i, 2]
        dist2 = q0 * q0 + q1 * q1 + q2 * q2
        if dist2 <= r2 or (along > 0.0 and along - radius < tmax[i] and dist2 - along * along <= r2):
            keep[m] = i
            m += 1
    index = keep[:m].copy()
    om = np.empty((m, 3), np.float32)
    dm = np.empty((m, 3), np.float32)
    tm = np.empty(m, np.float32)
    for j in range(m):
        i = index[j]
        p0, p1, p2 = o[i, 0] - t[0], o[i, 1] - t[1], o[i, 2] - t[2]
        for a in range(3):  # x_model = Rᵀ (x_world − t)
            om[j, a] = R[0, a] * p0 + R[1, a] * p1 + R[2, a] * p2
            dm[j, a] = R[0, a] * d[i, 0] + R[1, a] * d[i, 1] + R[2, a] * d[i, 2]
        tm[j] = tmax[i]
    return index, om, dm, tm


@nb.njit(nogil=True, cache=True)
def _static_hit_ids(prim_id, geom_id, tfar, static_objects, tri_offsets, t, obj, prim):
    """Embree's (geomID, primID) → our object index and global triangle index, written into
    t, obj, prim; inf / −1 on a miss."""
    for i in range(prim_id.shape[0]):
        if prim_id[i] >= 0:
            k = static_objects[geom_id[i]]
            t[i], obj[i], prim[i] = tfar[i], k, tri_offsets[k] + prim_id[i]
        else:
            t[i], obj[i], prim[i] = np.inf, -1, -1


def mesh_key(mesh) -> bytes:
    """Digest of a mesh's float32 vertices and faces, as a BVH is built from them. Moving objects
    with equal meshes share one model-space BVH: the scene loader reads a mesh once per object
    that names it, so `id(mesh)` differs between copies. paper-dynamic's two bunnies had two
    identical 69k-triangle BVHs; one shared BVH gives the same hits with 6-7 % more rays per
    CPU-second and about 5 % less CPU per frame (README, "Where a frame's time goes")."""
    h = hashlib.blake2b(digest_size=16)
    for a in (np.ascontiguousarray(mesh.vertices, np.float32), np.ascontiguousarray(mesh.faces, np.int64)):
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.digest()


def _embree_scene(vertices_list, faces_list, robust: bool | None = None) -> rtcore_scene.EmbreeScene:
    scene = rtcore_scene.EmbreeScene(robust=capi.ROBUST if robust is None else robust)
    for vertices, faces in zip(vertices_list, faces_list):
        mesh_construction.TriangleMesh(scene, np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32))
    return scene


class EmbreeAccel:
    """Closest-hit and occlusion queries over a list of objects whose poses change per frame."""

    def __init__(self, objects: list[ObjectSpec], tri_offsets: np.ndarray, threads: int = 2, robust: bool | None = None):
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="embree") if self.threads > 1 else None
        self.tri_offsets = tri_offsets
        static = [i for i, o in enumerate(objects) if not o.is_dynamic]
        self.static_objects = np.array(static, dtype=np.int32)
        self.static_scene = None
        if static:
            self.static_scene = _embree_scene(
                [objects[i].pose.apply(objects[i].mesh.vertices) for i in static], [objects[i].mesh.faces for i in static], robust
            )
        self.dynamic_objects: list[int] = [i for i, o in enumerate(objects) if o.is_dynamic]
        by_mesh: dict[bytes, rtcore_scene.EmbreeScene] = {}
        self.dynamic_scenes = []
        self.dynamic_bounds = []  # model-space bounding sphere (centre, radius) of each moving object
        for i in self.dynamic_objects:
            mesh = objects[i].mesh
            key = mesh_key(mesh)
            if key not in by_mesh:  # copies of one mesh share one BVH
                by_mesh[key] = _embree_scene([mesh.vertices], [mesh.faces], robust)
            self.dynamic_scenes.append(by_mesh[key])
            lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
            centre = (lo + hi) / 2
            radius = np.linalg.norm(mesh.vertices - centre, axis=1).max() * (1 + 1e-4) + 1e-9
            self.dynamic_bounds.append((centre.astype(np.float32), np.float32(radius)))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    # -- batching -------------------------------------------------------------------------------
    def _run_segments(self, fn, starts, counts) -> None:
        """fn(first, end) for every non-empty segment, spread over the threads (a pool job per
        segment, so uneven segments still balance). Results must not depend on the split."""
        jobs = [(int(a), int(a + c)) for a, c in zip(starts, counts) if c > 0]
        if self._pool is None or sum(e - a for a, e in jobs) < 2 * MIN_RAYS_PER_THREAD:
            for a, e in jobs:
                fn(a, e)
        else:
            for _ in self._pool.map(lambda job: fn(*job), jobs):
                pass

    def _chunks(self, n: int):
        """Segments for a whole ray batch: a few per thread (ray batches are not uniform in cost)."""
        chunks = min(4 * self.threads, max(1, n // MIN_RAYS_PER_THREAD))
        bounds = np.linspace(0, n, chunks + 1).astype(np.int64)
        return bounds[:-1], np.diff(bounds)

    # -- queries --------------------------------------------------------------------------------
    def intersect_range(self, origins, directions, first, end, poses_R, poses_t, hits: Hits, static_done: bool = False,
                        packets: bool = False) -> None:
        """Closest hits of the rays in rows [first, end) of origins and directions, written into
        the same rows of `hits`, on the calling thread. `static_done`: those rows of `hits`
        already hold the static BVH's hits (only the moving objects are traced). `packets` is
        ignored (embreex traces one ray per call)."""
        a, e = first, end
        o, d = origins[a:e], directions[a:e]
        t, obj, prim, u, v = hits.t[a:e], hits.obj[a:e], hits.prim[a:e], hits.u[a:e], hits.v[a:e]
        if not static_done:
            self._trace_static(o, d, t, obj, prim, u, v)
        for k, scene, (centre, radius) in zip(self.dynamic_objects, self.dynamic_scenes, self.dynamic_bounds):
            index, om, dm, tm = _rays_into_model(o, d, t, poses_R[k], poses_t[k], centre, radius)
            if index.size == 0:
                continue
            res = scene.run(om, dm, dists=tm, output=True)
            hit = res["primID"] >= 0
            rows = index[hit]
            obj[rows] = k
            prim[rows] = self.tri_offsets[k] + res["primID"][hit]
            t[rows], u[rows], v[rows] = res["tfar"][hit], res["u"][hit], res["v"][hit]

    def intersect_static(self, origins: np.ndarray, directions: np.ndarray, width: int | None = None) -> Hits:
        """Closest hits among the static objects only (they never move, so this can be cached).
        `width` (the image's, for RtcAccel's pixel tiles) is ignored."""
        hits = empty_hits(len(origins))

        def run(a, e):
            self._trace_static(origins[a:e], directions[a:e], hits.t[a:e], hits.obj[a:e], hits.prim[a:e], hits.u[a:e], hits.v[a:e])

        self._run_segments(run, *self._chunks(len(origins)))
        return hits

    def _trace_static(self, o, d, t, obj, prim, u, v) -> None:
        if self.static_scene is None:
            t[:], obj[:], prim[:], u[:], v[:] = np.inf, -1, -1, 0, 0
            return
        res = self.static_scene.run(o, d, output=True)
        _static_hit_ids(res["primID"], res["geomID"], res["tfar"], self.static_objects, self.tri_offsets, t, obj, prim)
        u[:], v[:] = res["u"], res["v"]

    def occluded_range(self, origins, directions, tmax, first, end, poses_R, poses_t, blocked, packets: bool = False) -> None:
        """blocked[i] = something lies along ray i closer than tmax[i], for rows [first, end), on
        the calling thread (other rows are left alone)."""
        a, e = first, end
        o, d, tm, blk = origins[a:e], directions[a:e], tmax[a:e], blocked[a:e]
        if self.static_scene is not None:
            blk[:] = self.static_scene.run(o, d, dists=tm.copy(), query="OCCLUDED") >= 0
        else:
            blk[:] = False
        for k, scene, (centre, radius) in zip(self.dynamic_objects, self.dynamic_scenes, self.dynamic_bounds):
            # rays already blocked get tmax 0, so the bounding-sphere test drops them
            index, om, dm, tmk = _rays_into_model(o, d, np.where(blk, 0, tm), poses_R[k], poses_t[k], centre, radius)
            if index.size:
                blk[index] |= scene.run(om, dm, dists=tmk, query="OCCLUDED") >= 0


def empty_hits(n: int) -> Hits:
    """Uninitialised Hits for n rays (filled by the intersect calls)."""
    return Hits(np.empty(n, np.float32), np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32))


class RtcAccel:
    """The scene's BVHs built through Embree's C API, with the same interface as
    `EmbreeAccel` (so the benchmark and tests can put one beside the other), plus `acc`:
    the tables the compiled kernels query directly."""

    def __init__(self, objects, tri_offsets: np.ndarray, threads: int = 2, robust: bool | None = None):
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="rtc") if self.threads > 1 else None
        self.tri_offsets = np.asarray(tri_offsets, np.int32)
        static = [i for i, o in enumerate(objects) if not o.is_dynamic]
        self.static_objects = np.array(static if static else [0], dtype=np.int32)
        self._scenes: list[capi.RtcScene] = []
        self.static_scene = None
        if static:
            self.static_scene = capi.RtcScene([objects[i].pose.apply(objects[i].mesh.vertices).astype(np.float32) for i in static],
                                             [objects[i].mesh.faces for i in static], robust=robust)
            self._scenes.append(self.static_scene)
        self.dynamic_objects = [i for i, o in enumerate(objects) if o.is_dynamic]
        by_mesh: dict[bytes, capi.RtcScene] = {}
        handles = [self.static_scene.handle if self.static_scene else 0]
        sphere = []
        for i in self.dynamic_objects:
            mesh = objects[i].mesh
            key = mesh_key(mesh)
            if key not in by_mesh:  # copies of one mesh share one BVH
                by_mesh[key] = capi.RtcScene([np.asarray(mesh.vertices, np.float32)], [mesh.faces], robust=robust)
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
        n = len(origins)
        hits = empty_hits(n)
        R = np.zeros((len(self.tri_offsets), 3, 3), np.float32)
        T = np.zeros((len(self.tri_offsets), 3), np.float32)
        h = (hits.t, hits.obj, hits.prim, hits.u, hits.v)
        if width and n % width == 0:  # camera rays, one per pixel: 4×4 tiles
            order = self._tile_order(width, n // width)
            self._split(lambda a, e: closest_rows(self.acc_static, R, T, origins, directions, order, a, e, *h, True, False), n)
        else:
            self._split(lambda a, e: closest_range(self.acc_static, R, T, origins, directions, a, e, *h, True, False), n)
        return hits
