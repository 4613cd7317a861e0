"""Converged reference renders for the quality benchmarks, cached on disk.

A reference is keyed by a digest of the scene's content (resolution, camera, meshes, materials,
motion), the time, spp, seed and the renderer's source digest (`dpmhw.render.digest`), with the
parameters that made it stored beside it. It renders as blocks of passes
(`dpmhw.cluster.passes`), here or over a Ray cluster: the same image either way.
"""

from __future__ import annotations

import hashlib
import json
import time as _time
from pathlib import Path
from typing import Callable

import numpy as np

from dpmhw import __version__
from dpmhw.cluster.ray_pool import render_passes
from dpmhw.kernel_cache import cache_root
from dpmhw.render.digest import renderer_digest
from dpmhw.scene_file import Scene

REFERENCE_SEED = 1_000_003  # far from the sequence seeds 0, 1, 2, …: independent noise


def scene_digest(scene: Scene) -> str:
    """sha256 over everything that changes the image: render settings, camera, objects."""
    h = hashlib.sha256()

    def put(*items):
        for x in items:
            h.update(np.ascontiguousarray(np.asarray(x, dtype=np.float64)).tobytes() if not isinstance(x, str) else x.encode())

    r = scene.render
    put(str((r.width, r.height, r.max_bounces)), r.background)
    put(scene.camera.K, scene.camera.dist, scene.camera.pose.R, scene.camera.pose.t, scene.viewer_position)
    for o in scene.objects:
        put(o.name, o.shape, o.mesh.vertices, o.mesh.faces.astype(np.float64), o.pose.R, o.pose.t, o.albedo, o.specular,
            float(o.roughness), o.emission, repr(o.motion), repr(o.rigid_body))
        if o.face_roughness is not None:
            put(o.face_roughness)
        if o.mesh.vertex_normals is not None:
            put(o.mesh.vertex_normals)
        if o.mesh.texture is not None:
            put(o.mesh.uv, o.mesh.texture.texels)
    return h.hexdigest()


def default_cache_dir() -> Path:
    return cache_root() / "references"


class ReferenceCache:
    """References on disk. Rendered as blocks of passes (dpmhw.cluster.passes), here or, with a
    RayPool as `pool`, as Ray tasks: the same image either way, so the key ignores where."""

    def __init__(self, cache_dir: Path | None = None, threads: int = 2, progress: Callable | None = None, pool=None):
        self.dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        self.threads = threads
        self.progress = progress  # progress(description, done, total)
        self.pool = pool
        self.renderer = renderer_digest()
        self.rendered = 0
        self.hits = 0
        self.cpu_seconds = 0.0  # the rendered references' CPU time, wherever they rendered

    def key(self, scene: Scene, time: float, spp: int, seed: int, pixel_sampling: str = "centre") -> tuple[str, dict]:
        key_fields = dict(scene=scene_digest(scene), time=repr(float(time)), spp=int(spp), seed=int(seed), renderer=self.renderer)
        if pixel_sampling != "centre":  # centre references keep their keys
            key_fields["pixel_sampling"] = pixel_sampling
        return hashlib.sha256(json.dumps(key_fields, sort_keys=True).encode()).hexdigest()[:24], key_fields

    def get(self, scene: Scene, scene_name: str, time: float, spp: int, seed: int = REFERENCE_SEED, integrator=None,
            pixel_sampling: str = "centre") -> dict:
        """{"radiance": (H, W, 3) float32, "object_id": (H, W) int32} of a converged render;
        `pixel_sampling` as PathIntegrator's ("jitter": the pixel integral; `integrator`, if
        given, must sample that way)."""
        if integrator is not None and integrator.pixel_sampling != pixel_sampling:
            raise ValueError(f"reference: the integrator samples {integrator.pixel_sampling!r}, not {pixel_sampling!r}")
        key, key_fields = self.key(scene, time, spp, seed, pixel_sampling)
        path = self.dir / f"{key}.npz"
        if path.exists():
            self.hits += 1
            with np.load(path) as data:
                return {"radiance": data["radiance"], "object_id": data["object_id"]}
        desc = f"reference {scene_name} t={time:.4f}s {scene.render.width}×{scene.render.height} {spp} spp"
        started = _time.perf_counter()
        frame = render_passes(scene, time, seed, spp, integrator=integrator, pool=self.pool, threads=self.threads,
                              progress=(lambda d, t: self.progress(desc, d, t)) if self.progress else None,
                              integrator_options=dict(pixel_sampling=pixel_sampling))
        self.dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.stem + ".partial.npz")
        np.savez(tmp, radiance=frame.radiance.astype(np.float32), object_id=frame.object_id)
        tmp.replace(path)
        cpu = float(sum(frame.block_cpu_seconds))
        self.cpu_seconds += cpu
        meta = dict(key_fields, scene_name=scene_name, width=scene.render.width, height=scene.render.height,
                    max_bounces=scene.render.max_bounces, seconds=round(_time.perf_counter() - started, 1),
                    cpu_seconds=round(cpu, 3),
                    nonfinite_samples=frame.nonfinite_samples, dpmhw=__version__,
                    equivalent_command=f"dpmhw render {scene_name} --spp {spp} --seed {seed} --time {time!r} "
                    f"--pixel-sampling {pixel_sampling} --out ref.npy"
                    + ("" if scene.render.width == 1024 else f"  (at {scene.render.width}×{scene.render.height})"))
        path.with_suffix(".json").write_text(json.dumps(meta, indent=2))
        self.rendered += 1
        return {"radiance": frame.radiance, "object_id": frame.object_id}
