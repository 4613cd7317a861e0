"""Ray queries on Intel Embree (embreex), for scenes whose rigid objects move every frame.

embreex has no instancing, so each BVH is built once: all static objects together in world
space, and every moving object's mesh in its own model space. Per frame a query transforms the
rays into each moving object's model space (a rigid transform keeps ray distances), and every
later BVH is asked only for hits closer than the best so far (embree's `tfar` culls the rest).
Ray batches are split across threads: `EmbreeScene.run` releases the GIL.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from embreex import mesh_construction, rtcore_scene

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


def _embree_scene(vertices_list, faces_list) -> rtcore_scene.EmbreeScene:
    scene = rtcore_scene.EmbreeScene(robust=True)
    for vertices, faces in zip(vertices_list, faces_list):
        mesh_construction.TriangleMesh(scene, np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32))
    return scene


class EmbreeAccel:
    """Closest-hit and occlusion queries over a list of objects whose poses change per frame."""

    def __init__(self, objects: list[ObjectSpec], tri_offsets: np.ndarray, threads: int = 2):
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="embree") if self.threads > 1 else None
        self.tri_offsets = tri_offsets
        static = [i for i, o in enumerate(objects) if not o.is_dynamic]
        self.static_objects = np.array(static, dtype=np.int32)
        self.static_scene = None
        if static:
            self.static_scene = _embree_scene(
                [objects[i].pose.apply(objects[i].mesh.vertices) for i in static], [objects[i].mesh.faces for i in static]
            )
        self.dynamic_objects: list[int] = [i for i, o in enumerate(objects) if o.is_dynamic]
        by_mesh: dict[int, rtcore_scene.EmbreeScene] = {}
        self.dynamic_scenes = []
        for i in self.dynamic_objects:
            mesh = objects[i].mesh
            if id(mesh) not in by_mesh:  # instances of one mesh share one BVH
                by_mesh[id(mesh)] = _embree_scene([mesh.vertices], [mesh.faces])
            self.dynamic_scenes.append(by_mesh[id(mesh)])

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    # -- batching -------------------------------------------------------------------------------
    def _map(self, fn, n: int, *arrays):
        if self._pool is None or n < 2 * MIN_RAYS_PER_THREAD:
            return [fn(*arrays)]
        bounds = np.linspace(0, n, self.threads + 1).astype(int)
        chunks = [tuple(a[s:e] for a in arrays) for s, e in zip(bounds[:-1], bounds[1:])]
        return list(self._pool.map(lambda c: fn(*c), chunks))

    # -- queries --------------------------------------------------------------------------------
    def intersect(self, origins: np.ndarray, directions: np.ndarray, poses_R: np.ndarray, poses_t: np.ndarray) -> Hits:
        """origins, directions : (n, 3) float32 world space; poses_R (O, 3, 3), poses_t (O, 3): model→world."""
        n = len(origins)

        def run(o, d):
            m = len(o)
            t = np.full(m, np.inf, np.float32)
            obj = np.full(m, -1, np.int32)
            prim = np.full(m, -1, np.int32)
            u = np.zeros(m, np.float32)
            v = np.zeros(m, np.float32)
            if self.static_scene is not None:
                res = self.static_scene.run(o, d, output=True)
                hit = res["primID"] >= 0
                geom = res["geomID"][hit]
                obj[hit] = self.static_objects[geom]
                prim[hit] = self.tri_offsets[obj[hit]] + res["primID"][hit]
                t[hit], u[hit], v[hit] = res["tfar"][hit], res["u"][hit], res["v"][hit]
            for k, scene in zip(self.dynamic_objects, self.dynamic_scenes):
                R, tr = poses_R[k].astype(np.float32), poses_t[k].astype(np.float32)
                om = np.ascontiguousarray((o - tr) @ R)
                dm = np.ascontiguousarray(d @ R)
                res = scene.run(om, dm, dists=t.copy(), output=True)
                hit = res["primID"] >= 0
                obj[hit] = k
                prim[hit] = self.tri_offsets[k] + res["primID"][hit]
                t[hit], u[hit], v[hit] = res["tfar"][hit], res["u"][hit], res["v"][hit]
            return t, obj, prim, u, v

        parts = self._map(run, n, origins, directions)
        return Hits(*(np.concatenate(p) if len(parts) > 1 else p[0] for p in zip(*parts)))

    def occluded(self, origins, directions, tmax, poses_R, poses_t) -> np.ndarray:
        """(n,) bool: something lies along the ray closer than tmax."""
        n = len(origins)

        def run(o, d, tm):
            blocked = np.zeros(len(o), bool)
            if self.static_scene is not None:
                blocked |= self.static_scene.run(o, d, dists=tm.copy(), query="OCCLUDED") >= 0
            for k, scene in zip(self.dynamic_objects, self.dynamic_scenes):
                todo = np.flatnonzero(~blocked)
                if todo.size == 0:
                    break
                R, tr = poses_R[k].astype(np.float32), poses_t[k].astype(np.float32)
                om = np.ascontiguousarray((o[todo] - tr) @ R)
                dm = np.ascontiguousarray(d[todo] @ R)
                blocked[todo] = scene.run(om, dm, dists=np.ascontiguousarray(tm[todo]), query="OCCLUDED") >= 0
            return blocked

        parts = self._map(run, n, origins, directions, np.asarray(tmax, np.float32))
        return np.concatenate(parts) if len(parts) > 1 else parts[0]
