"""`dpmhw bench lod`: contrast-driven level of detail, speed against error.

Per scene, each method renders the same stretch of the scene's timeline (frame k: t = k / fps,
seed k) through temporal reuse (same-pixel EMA, α = 0.2, as the session does); methods are
interleaved frame by frame in a rotating order, so load on the shared machine hits them alike.
The visibility map of frame k is computed from the method's own output and G-buffer of frame
k − 1 (the first frame is a plain full frame). Errors are those of the last `eval_frames`
frames against converged references (`ReferenceCache`, shared with `bench quality`), on the
post-processed 8-bit frames: PSNR, SSIM (dpmhw.metrics) and mean FLIP (NVIDIA's
flip-evaluator, LDR, its default 67 pixels per degree).

Methods
- none: plain 1 spp per pixel (the current pipeline).
- spp: samples per pixel per tile (0/1/2/4) from the visibility map under a ray budget of
  `budget` × the worst-case rays of a 1-spp frame; 0-spp tiles keep their history. Rendered by
  `render_pixels` (below): one public `PathIntegrator.render` call per spp group on a camera
  restricted to those pixels.
- mesh-LOD: per object per frame, the level chosen by `MeshLodSelector` (levels and their BVHs
  built once before the run); the scene's meshes are swapped for the chosen levels. Until the
  renderer takes per-object BVHs, a new choice builds a new PathIntegrator: that build is outside
  the timed frame and counted in `lod_switches`.
- all: spp and mesh-LOD together.
- mesh-coarsest (diagnostic, not a method): every mesh at its coarsest level all the time, the
  most mesh LOD could save here, whatever it costs in error.
- shading-rate is left out: shading a tile at 1/2 or 1/4 resolution needs the joint bilateral
  upsampling of issue 11 (`dpmhw/reconstruct/`), not on this branch. The policy computes the
  rates (`TileDecisions.rate`); nothing here pretends to render them.

frame_ms covers, per frame: visibility map, decisions, level choice, the render calls and the
scatter of their pixels (not reuse or post-processing, which every method does the same way);
lod_ms is the first three, render_ms the time inside the render calls (with `render_pixels`
that includes the bridge's per-call set-up: the integrator reallocates its work buffers for
every new pixel count).
rays_per_frame = camera + continuation + shadow rays, as `bench render` counts them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from dpmhw.benchmarks.quality import ReferenceCache, _save
from dpmhw.lod.mesh_lod import MeshLevels, MeshLodSelector, MeshLodSettings, object_visibility, scene_at_levels
from dpmhw.lod.policy import PolicySettings, TileDecisions, TilePolicy, rays_per_sample_bound
from dpmhw.lod.visibility import VisibilitySettings, visibility_map
from dpmhw.metrics import psnr, ssim
from dpmhw.postprocess import postprocess
from dpmhw.render.accel import Hits
from dpmhw.render.integrator import PathIntegrator
from dpmhw.reconstruct.reuse import TemporalReuse
from dpmhw.scene_file import Scene, load_scene
from dpmhw.sequence import scaled_scene

METHODS = ("none", "spp", "mesh-LOD", "all", "mesh-coarsest")
OMITTED = {"shading-rate": "needs the joint bilateral upsampling of issue 11 (dpmhw/reconstruct/), not on this branch"}
REFERENCE_SEED = 1_000_003


@dataclass
class LodBenchConfig:
    scenes: tuple[str, ...] = ("paper-dynamic", "dpm-bunny")
    scale: float = 1.0
    frames: int = 8  # per method and scene, including the first (plain) frame
    eval_frames: int = 3
    ref_spp: int = 256
    budget: float = 0.5  # ray budget of the adaptive-spp methods, × the worst case of a 1-spp frame
    alpha: float = 0.2
    threads: int = 2
    visibility: VisibilitySettings = field(default_factory=VisibilitySettings)
    policy: PolicySettings = field(default_factory=PolicySettings)
    mesh: MeshLodSettings = field(default_factory=MeshLodSettings)

    @classmethod
    def quick(cls) -> "LodBenchConfig":
        return cls(scale=0.25, frames=6, eval_frames=2, ref_spp=64)


# ----------------------------------------------------------------------------------------------
# rendering a subset of pixels through the public render call


class _PixelSubsetCamera:
    """The base camera's rays through the given pixels only (flat row-major indices)."""

    def __init__(self, base, pixels: np.ndarray):
        self.base, self.pixels, self.pose = base, pixels, base.pose

    def with_pose(self, pose):
        return _PixelSubsetCamera(self.base.with_pose(pose), self.pixels)

    def generate_rays(self):
        o, d = self.base.generate_rays()
        return o[self.pixels], d[self.pixels]


def render_pixels(integrator: PathIntegrator, pixels: np.ndarray, spp: int, time: float, seed: int):
    """Render only `pixels` (flat indices, ascending) at `spp`: a 1 × n Frame, and the ray counts.

    A bench-only bridge until the renderer takes a per-pixel spp map (issue 12's rewrite): it
    points the integrator's camera at the pixel subset for one `render` call, and hands it the
    subset of the full frame's static camera hits (traced once per camera pose, as the
    integrator itself caches them). With every pixel selected, the result is bit for bit the
    plain render (the random numbers hash the pixel's index in the batch)."""
    camera, width, height = integrator.camera, integrator.width, integrator.height
    full = getattr(integrator, "_lod_full_static", None)
    key = (camera.pose.R.tobytes(), camera.pose.t.tobytes())
    traced = 0
    if full is None or full[0] != key:
        o, d = camera.generate_rays()
        full = (key, integrator.geometry.accel.intersect_static(o, d))
        integrator._lod_full_static = full
        traced = len(o)
    h = full[1]
    try:
        integrator.camera = _PixelSubsetCamera(camera, pixels)
        integrator.width, integrator.height = len(pixels), 1
        integrator._static_primary_key = key
        integrator._static_primary_hits = Hits(h.t[pixels], h.obj[pixels], h.prim[pixels], h.u[pixels], h.v[pixels])
        frame = integrator.render(time=time, seed=seed, spp=spp)
        counts = integrator.counts
        counts.primary_static_traced += traced
    finally:
        integrator.camera, integrator.width, integrator.height = camera, width, height
        integrator._static_primary_key = integrator._static_primary_hits = None
    return frame, counts


# ----------------------------------------------------------------------------------------------
# one method's loop state


class _Run:
    def __init__(self, name: str, scene: Scene, cfg: LodBenchConfig, levels: list[MeshLevels | None]):
        self.name, self.scene, self.cfg = name, scene, cfg
        r = scene.render
        self.H, self.W = r.height, r.width
        self.adaptive_spp = name in ("spp", "all")
        self.mesh_lod = name in ("mesh-LOD", "all")
        self.reuse = TemporalReuse(self.W, self.H, alpha=cfg.alpha)
        self.levels = levels
        self.integrators: dict[tuple, PathIntegrator] = {}
        self.choice = tuple(len(lv) - 1 if name == "mesh-coarsest" and lv is not None else 0 for lv in levels)
        self.integrator = self._integrator(self.choice)
        self.rays_per_sample = rays_per_sample_bound(r.max_bounces, self.integrator.mis_last)
        self.budget = int(cfg.budget * self.W * self.H * self.rays_per_sample)
        self.policy = TilePolicy(self.H, self.W, dataclasses.replace(cfg.policy, shading_rate=False, adaptive_spp=True,
                                                                     ray_budget=self.budget, rays_per_sample=self.rays_per_sample))
        K = scene.camera.K
        focal = float(np.sqrt(abs(K[0, 0] * K[1, 1])))  # as the visibility map takes it
        self.selector = MeshLodSelector(levels, focal, cfg.mesh, cfg.visibility) if self.mesh_lod else None
        self.prev = None  # (output radiance, depth, object_id) of the last frame
        self.lod_switches = 0
        self.last: dict = {}
        self.render_s = 0.0  # seconds inside render calls this frame

    def _integrator(self, choice: tuple) -> PathIntegrator:
        if choice not in self.integrators:
            integ = PathIntegrator(scene_at_levels(self.scene, self.levels, choice), threads=self.cfg.threads)
            integ.render(time=0.0, seed=0)  # JIT and caches, outside the timed frames
            self.integrators[choice] = integ
        return self.integrators[choice]

    def close(self):
        for integ in self.integrators.values():
            integ.close()

    def step(self, k: int) -> dict:
        t_frame, seed = k / self.scene.render.fps, k
        spent = 0.0
        vmap = dec = None
        self.render_s = 0.0
        start = _time.perf_counter()
        if self.prev is not None and (self.adaptive_spp or self.mesh_lod):
            prev_out, prev_depth, prev_id = self.prev
            vmap = visibility_map(prev_out, prev_depth, self.scene.camera.K, self.cfg.visibility)
            if self.mesh_lod:
                obj_vis = object_visibility(vmap.visibility, vmap.tile, prev_id, len(self.scene.objects))
                choice = tuple(int(c) for c in self.selector.select(self.scene.object_poses(t_frame), self.scene.camera.pose, obj_vis))
                if choice != self.choice:
                    spent += _time.perf_counter() - start
                    self.integrator = self._integrator(choice)  # BVH build: untimed (see the module docstring)
                    self.lod_switches += 1
                    self.choice = choice
                    start = _time.perf_counter()
        if self.adaptive_spp and vmap is not None:
            dec = self.policy.decide(vmap)
            lod_s = spent + _time.perf_counter() - start
            radiance, object_id, depth, rays = self._render_tiles(dec, t_frame, seed)
        else:
            lod_s = spent + _time.perf_counter() - start
            r0 = _time.perf_counter()
            frame = self.integrator.render(time=t_frame, seed=seed)
            self.render_s += _time.perf_counter() - r0
            c = self.integrator.counts
            radiance, object_id, depth, rays = frame.radiance, frame.object_id, frame.depth, c.primary + c.intersect + c.occluded
        spent += _time.perf_counter() - start
        out = self.reuse.update(radiance, object_id)
        self.prev = (out, depth, object_id)
        self.last = dict(vmap=vmap, decisions=dec, choice=self.choice, output=out)
        if dec is not None and rays > self.budget:
            raise AssertionError(f"{self.name}: {rays} rays traced over the budget of {self.budget}")
        return dict(ms=spent * 1e3, lod_ms=lod_s * 1e3, render_ms=self.render_s * 1e3, rays=int(rays), triangles=int(self.integrator.geometry.triangle_count), output=out, time=t_frame)

    def _render_tiles(self, dec: TileDecisions, t_frame: float, seed: int):
        prev_out, prev_depth, prev_id = self.prev
        spp = dec.pixel_spp(self.H, self.W).reshape(-1)
        radiance = prev_out.reshape(-1, 3).copy()  # 0-spp pixels keep their history
        object_id = prev_id.reshape(-1).copy()
        depth = prev_depth.reshape(-1).copy()
        rays = 0
        for s in (1, 2, 4):
            pixels = np.flatnonzero(spp == s)
            if pixels.size == 0:
                continue
            r0 = _time.perf_counter()
            frame, c = render_pixels(self.integrator, pixels, s, t_frame, seed)
            self.render_s += _time.perf_counter() - r0
            radiance[pixels] = frame.radiance.reshape(-1, 3)
            object_id[pixels] = frame.object_id.reshape(-1)
            depth[pixels] = frame.depth.reshape(-1)
            rays += c.primary + c.intersect + c.occluded
        return radiance.reshape(self.H, self.W, 3), object_id.reshape(self.H, self.W), depth.reshape(self.H, self.W), rays


# ----------------------------------------------------------------------------------------------
# the benchmark


def _flip(image_u8: np.ndarray, reference_u8: np.ndarray) -> float:
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(reference_u8.astype(np.float32) / 255, image_u8.astype(np.float32) / 255, "LDR",
                                         applyMagma=False)
    return float(mean)


def _mesh_levels(scene: Scene) -> tuple[list[MeshLevels | None], float]:
    """Levels for every mesh object (built once; identical meshes share them), and the seconds it took."""
    start = _time.perf_counter()
    by_content: dict[str, MeshLevels] = {}
    out = []
    for o in scene.objects:
        if o.shape != "mesh" or len(o.mesh.faces) < 1000:
            out.append(None)
            continue
        key = hashlib.sha256(o.mesh.vertices.tobytes() + o.mesh.faces.tobytes()).hexdigest()
        if key not in by_content:
            by_content[key] = MeshLevels(o.mesh)
        out.append(by_content[key])
    return out, _time.perf_counter() - start


def run_scene(name: str, cfg: LodBenchConfig, cache: ReferenceCache, progress: Callable, images: dict) -> list[dict]:
    scene = load_scene(name)
    if cfg.scale != 1.0:
        scene = scaled_scene(scene, cfg.scale)
    levels, build_s = _mesh_levels(scene)
    runs = [_Run(m, scene, cfg, levels) for m in METHODS]
    results = {m: [] for m in METHODS}
    first_eval = cfg.frames - cfg.eval_frames
    try:
        for k in range(cfg.frames):
            order = runs[k % len(runs):] + runs[: k % len(runs)]  # rotate: no method always runs first
            for r in order:
                results[r.name].append(r.step(k))
                progress(f"{name}: frames × methods", k * len(runs) + order.index(r) + 1, cfg.frames * len(runs))
        refs = [cache.get(scene, name, results["none"][k]["time"], cfg.ref_spp, REFERENCE_SEED) for k in range(first_eval, cfg.frames)]
        ref_u8 = [postprocess(r["radiance"]) for r in refs]
        rows = []
        for r in runs:
            frames = results[r.name]
            timed = frames[1:]  # frame 0 is a plain full frame for every method
            errs = [(psnr(u, ref), ssim(u, ref), _flip(u, ref))
                    for u, ref in zip((postprocess(f["output"]) for f in frames[first_eval:]), ref_u8)]
            rows.append(dict(
                scene=name, method=r.name,
                frame_ms=float(np.median([f["ms"] for f in timed])),
                rays_per_frame=int(np.median([f["rays"] for f in timed])),
                triangles=int(np.median([f["triangles"] for f in timed])),
                psnr_db=float(np.mean([e[0] for e in errs])), ssim=float(np.mean([e[1] for e in errs])),
                flip=float(np.mean([e[2] for e in errs])),
                frame_ms_min=float(min(f["ms"] for f in timed)), frame_ms_max=float(max(f["ms"] for f in timed)),
                lod_ms=float(np.median([f["lod_ms"] for f in timed])), render_ms=float(np.median([f["render_ms"] for f in timed])),
                ray_budget=r.budget if r.adaptive_spp else None, lod_switches=r.lod_switches,
                mesh_levels=",".join(str(c) for c in r.choice), width=scene.render.width, height=scene.render.height,
                frames=cfg.frames, eval_frames=cfg.eval_frames, ref_spp=cfg.ref_spp, level_build_s=round(build_s, 2),
            ))
        images[name] = dict(run=runs[METHODS.index("all")].last, scene=scene, levels=levels)
    finally:
        for r in runs:
            r.close()
    return rows


def run_lod(cfg: LodBenchConfig, cache_dir: Path | None = None, out_dir: Path | None = None, progress: Callable | None = None) -> dict:
    progress = progress or (lambda *a: None)
    cache = ReferenceCache(cache_dir, threads=cfg.threads, progress=progress)
    rows, images = [], {}
    for name in cfg.scenes:
        rows += run_scene(name, cfg, cache, progress, images)
    files = write_figures(rows, images, out_dir) if out_dir is not None else []
    return dict(rows=rows, omitted=OMITTED, files=files)


# ----------------------------------------------------------------------------------------------
# figures and table


def write_figures(rows: list[dict], images: dict, out_dir: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for name, im in images.items():
        run, scene = im["run"], im["scene"]
        vmap, dec = run["vmap"], run["decisions"]
        if vmap is None or dec is None:
            continue
        H, W = scene.render.height, scene.render.width
        ext = (0, W, H, 0)
        fig, axes = plt.subplots(1, 4, figsize=(17, 3.9))
        axes[0].imshow(postprocess(run["output"]), extent=ext)
        axes[0].set_title(f"{name}: output of 'all' (last frame)")
        lo, hi = -50.0, max(1.0, float(np.max(vmap.visibility)))
        a = axes[1].imshow(np.clip(vmap.visibility, lo, hi), cmap="coolwarm", vmin=lo, vmax=hi, extent=ext, interpolation="nearest")
        axes[1].set_title("visibility V = S(f) − 1/c + α  (>0: visible)")
        fig.colorbar(a, ax=axes[1], fraction=0.04)
        b = axes[2].imshow(dec.spp, cmap="viridis", vmin=0, vmax=4, extent=ext, interpolation="nearest")
        axes[2].set_title(f"spp per tile (budget {dec.ray_bound:,} of ≤ rays)")
        fig.colorbar(b, ax=axes[2], fraction=0.04, ticks=[0, 1, 2, 4])
        c = axes[3].imshow(dec.rate, cmap="magma", vmin=0, vmax=4, extent=ext, interpolation="nearest")
        axes[3].set_title("shading rate the policy would use\n(pitch: 1 full, 2 half, 4 quarter, 0 history)")
        fig.colorbar(c, ax=axes[3], fraction=0.04, ticks=[0, 1, 2, 4])
        levels = ", ".join(f"{o.name}: level {lv}" for o, lv, ls in zip(scene.objects, run["choice"], im["levels"]) if ls is not None)
        fig.suptitle(f"mesh levels chosen: {levels}", fontsize=9)
        for ax in axes:
            ax.set_xlabel("x (px)")
        files.append(_save(fig, out_dir / f"lod-map-{name}.png"))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    markers = {"none": "o", "spp": "s", "mesh-LOD": "^", "all": "D", "mesh-coarsest": "x"}
    for i, name in enumerate(dict.fromkeys(r["scene"] for r in rows)):
        for r in (r for r in rows if r["scene"] == name):
            for ax, key in zip(axes, ("psnr_db", "flip")):
                ax.plot(r["frame_ms"], r[key], markers[r["method"]], color=f"C{i}", ms=8,
                        label=f"{name} {r['method']}")
                ax.annotate(r["method"], (r["frame_ms"], r[key]), textcoords="offset points", xytext=(5, 4), fontsize=8)
    axes[0].set_ylabel("PSNR (dB) against the converged reference ↑")
    axes[1].set_ylabel("mean FLIP against the converged reference ↓")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("frame time, median (ms, log scale; shared 2-core machine)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle("Contrast-driven LOD: speed against error (shading-rate omitted: needs issue 11's upsampling)")
    files.append(_save(fig, out_dir / "lod-ms-vs-error.png"))
    return files


def format_table(result: dict) -> str:
    head = f"{'scene':<15}{'method':<10}{'frame ms':>10}{'rays/frame':>13}{'triangles':>11}{'PSNR dB':>9}{'SSIM':>8}{'FLIP':>8}  levels"
    lines = [head]
    for r in result["rows"]:
        lines.append(f"{r['scene']:<15}{r['method']:<10}{r['frame_ms']:>10.1f}{r['rays_per_frame']:>13,}{r['triangles']:>11,}"
                     f"{r['psnr_db']:>9.2f}{r['ssim']:>8.4f}{r['flip']:>8.4f}  {r['mesh_levels']}")
    for k, why in result["omitted"].items():
        lines.append(f"{k}: omitted, {why}")
    return "\n".join(lines)

