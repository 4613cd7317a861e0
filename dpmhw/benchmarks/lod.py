"""`dpmhw bench lod`: contrast-driven level of detail through the loop's own pipeline, speed against error.

Per scene, at the projector's native size, on a 60 fps timeline (frames from `history_frames`
before the first eval time to the last; frame k: seed k), every method runs the frames through
`reconstruct.stage.ReconstructStage`, the session's stage (reuse "motion", α = 0.2), each with
its own state; frames shared by methods (the same renderer, the same seed) are rendered once:

- none: native shading, 1 spp everywhere + reuse, no filter (`shading_scale` 1: every pixel
  costs the same; the stage's exact path, the pipeline before reconstruction existed).
- quarter: ¼ shading + reuse + lobe-aware filter + upsampling + adaptive sampling: the session's
  default, no LOD (the floor every LOD method below builds on).
- moving: quarter + native paths on the moving objects' pixels (`lod.refine`, `moving`, each
  pixel every `moving_every` frames: the `lod` section's default).
- shading-rate: quarter + tiles the visibility map of the previous output calls visible at ½
  or full rate (`visible`, `shading_rate`).
- spp: quarter + visible tiles at full rate with 1, 2 or 4 paths per pixel (`visible`,
  `adaptive_spp`, rate off).
- mesh-LOD: none with the level per object chosen every frame by the loop's own `MeshLod`
  (levels, their triangle rows and BVHs built once before the run, swapped in place inside the
  timed frame; `lod_switches` counts the swaps). Scene `NAME@Z` moves the projector back until
  the object is Z m away (a long throw), where the levels switch.
- all: moving + shading-rate + spp + mesh-LOD.

Every refining method has the same per-frame budget of native rays (`rays`, worst case per
path), never exceeded (asserted per frame). frame_ms is CPU time (`time.process_time`, all
threads: the shared machine makes wall clock meaningless) of the render call(s) + the whole
stage (G-buffer, reuse, filter, upsample, lod, adaptive, post) measured as one window (the
stage's ¼ branch runs on a helper thread beside the G-buffer, so summing its sub-stage clocks,
`frame_ms_stage_sum`, counts that overlap twice); lod_ms the stage's "lod" part.
Errors at the eval times against converged native references (`ReferenceCache`, shared with
`bench quality`), on the 8-bit frames: PSNR, SSIM, mean FLIP (flip-evaluator, LDR) and PSNR
inside the mesh objects (psnr_db_object, the reference's object mask). Rows also say how many tiles the
map called visible (level ≥ ½ rate) against the map of the reference itself and of the raw
1-spp native frame (noise robustness).
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from dpmhw.benchmarks.figures import save_figure
from dpmhw.benchmarks.native_quality import flip_error
from dpmhw.benchmarks.references import REFERENCE_SEED, ReferenceCache
from dpmhw.lod.mesh_levels import MeshLodSettings
from dpmhw.lod.mesh_pipeline import MeshLod, build_levels
from dpmhw.lod.refine import RefineSettings, TileRefiner
from dpmhw.lod.visibility import VisibilitySettings, visibility_map
from dpmhw.metrics import masked_psnr, psnr, ssim
from dpmhw.postprocess import postprocess
from dpmhw.reconstruct.adaptive import AdaptiveSampler
from dpmhw.reconstruct.analytic import DEFAULT_FLOORS
from dpmhw.reconstruct.stage import ReconstructStage
from dpmhw.render.gbuffer import NativeGBuffer
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import Scene, load_scene
from dpmhw.sequence import scaled_scene, with_fps
from dpmhw.transforms import Pose

METHODS = ("none", "quarter", "moving", "shading-rate", "spp", "mesh-LOD", "all")
PLAIN = "-plain"  # method suffix: the same without the analytic-direct demodulation (`reconstruct.analytic`)
FPS = 60.0


@dataclass
class LodBenchConfig:
    scenes: tuple[str, ...] = ("paper-dynamic", "dpm-bunny")
    scale: float = 1.0
    eval_times: tuple[float, ...] = (0.3, 0.5)
    history_frames: int = 12  # frames before the first eval time
    ref_spp: int = 64
    rays: int = 400_000  # native rays per frame of the refining methods (the session default)
    alpha: float = 0.2
    threads: int = 2
    visibility: VisibilitySettings = field(default_factory=VisibilitySettings)
    mesh: MeshLodSettings = field(default_factory=MeshLodSettings)
    methods: tuple[str, ...] = METHODS  # "none" first; NAME-plain: NAME without the analytic demodulation
    analytic_floors: tuple[float, float] | None = DEFAULT_FLOORS  # the stage's (diffuse, specular) floor fractions
    moving_every: int | None = None  # lod.moving_every of the refining methods (None: the session default)

    @classmethod
    def quick(cls) -> "LodBenchConfig":
        return cls(scale=0.5, ref_spp=32)


def check_methods(methods) -> tuple[str, ...]:
    """Known names (each also with `PLAIN`), "none" first; a one-line error otherwise."""
    methods = tuple(methods)
    for m in methods:
        if m.removesuffix(PLAIN) not in METHODS or m == "none" + PLAIN:
            raise ValueError(f"methods: unknown method {m!r} (known: {', '.join(METHODS)}, each but none also with {PLAIN})")
    if not methods or methods[0] != "none" or len(set(methods)) != len(methods):
        raise ValueError(f"methods: expected distinct names starting with none, got {','.join(methods)!r}")
    return methods


def _refine_settings(method: str, cfg: LodBenchConfig) -> RefineSettings | None:
    method = method.removesuffix(PLAIN)
    v = dict(rays=cfg.rays, viewer_distance_m=cfg.visibility.viewer_distance_m, alpha_v=cfg.visibility.alpha_v)
    if cfg.moving_every is not None:
        v["moving_every"] = cfg.moving_every
    return {"moving": RefineSettings(moving=True, **v),
            "shading-rate": RefineSettings(moving=False, visible=True, **v),
            "spp": RefineSettings(moving=False, visible=True, shading_rate=False, adaptive_spp=True, **v),
            "all": RefineSettings(moving=True, visible=True, adaptive_spp=True, **v)}.get(method)


def bench_scene(name: str) -> Scene:
    """A built-in scene, or `NAME@Z`: the same scene with the projector moved back along its
    optical axis until the first moving object's origin is Z metres away (the audience, the
    lights and the motion stay where they are): a long throw, where mesh levels switch."""
    base, _, far = name.partition("@")
    scene = load_scene(base)
    if not far:
        return scene
    try:
        z = float(far.removesuffix("m"))
    except ValueError:
        z = math.nan
    cam = scene.camera.pose
    moving = [o for o in scene.objects if o.is_dynamic]
    if not (0 < z < 1e4 and moving):
        raise ValueError(f"scenes: expected NAME@Z with 0 < Z < 10000 metres and a moving object, got {name!r}")
    forward = cam.R[:, 2]
    now = float((moving[0].pose.t - cam.t) @ forward)
    pose = Pose(cam.R, cam.t - forward * (z - now))
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, pose=pose))


class _Pipeline:
    """One renderer at one shading scale (with its native G-buffer below scale 1) for a mesh-level choice."""

    def __init__(self, native: Scene, scale: float, threads: int):
        from dpmhw.session.factory import shading_scene

        self.scale = scale
        self.integrator = PathIntegrator(shading_scene(native, scale), threads=threads)
        self.integrator.render(spp=1, seed=0)  # JIT and the static-hit cache, outside the timed frames
        W, H = native.render.width, native.render.height
        self.gbuffer = NativeGBuffer(native, self.integrator.geometry, W, H, threads=threads) if scale != 1.0 else None
        self.frame = None
        self.cpu_ms = 0.0
        self.rays = 0

    def render(self, t: float, seed: int, poses) -> None:
        c0 = _time.process_time()
        self.frame = self.integrator.render(time=t, seed=seed, spp=1, poses=poses)
        self.cpu_ms = (_time.process_time() - c0) * 1e3
        c = self.integrator.counts
        self.rays = c.primary + c.intersect + c.occluded

    def close(self) -> None:
        if self.gbuffer is not None:
            self.gbuffer.close()
        self.integrator.close()


class _Run:
    """One method's state: its pipeline (shared by the methods without mesh levels; a method
    with them has its own, whose levels `MeshLod` swaps in place), stage and refiner."""

    def __init__(self, name: str, native: Scene, cfg: LodBenchConfig, levels, shared: dict, build: Callable):
        self.name, self.native, self.cfg = name, native, cfg
        base = name.removesuffix(PLAIN)
        self.analytic = None if name.endswith(PLAIN) else cfg.analytic_floors
        self.scale = 1.0 if base in ("none", "mesh-LOD") else 0.25
        self.settings = _refine_settings(name, cfg)
        self.mesh = None
        if base in ("mesh-LOD", "all"):
            shared[name] = p = build(native, self.scale)
            self.mesh = MeshLod(p.integrator, p.gbuffer, cfg.mesh, cfg.visibility, levels=levels, native_K=native.camera.K)
        self._bind(shared[name if self.mesh is not None else self.scale])

    @property
    def choice(self) -> tuple:
        return tuple(int(c) for c in self.mesh.choice) if self.mesh is not None else ()

    @property
    def lod_switches(self) -> int:
        return self.mesh.switches if self.mesh is not None else 0

    def _bind(self, p: _Pipeline) -> None:
        self.pipe = p
        n = self.native
        self.refiner = TileRefiner(p.integrator, p.gbuffer, self.settings) if self.settings is not None else None
        self.stage = ReconstructStage((n.render.width, n.render.height), (p.integrator.width, p.integrator.height),
                                      background=n.render.background, viewer=n.viewer_position, gbuffer=p.gbuffer,
                                      clock=_time.process_time_ns,
                                      adaptive=AdaptiveSampler(p.integrator, p.gbuffer) if p.gbuffer is not None else None,
                                      lod=self.refiner, analytic=self.analytic)

    def step(self, k: int, t: float, poses) -> dict:
        lod_cpu = 0.0
        n = self.native
        if self.mesh is not None:  # this frame's levels, swapped in place (part of the frame's time)
            c0 = _time.process_time()
            self.mesh.choose(poses, n.camera.pose)
            lod_cpu += (_time.process_time() - c0) * 1e3
        p = self.pipe
        if p.frame is None:
            p.render(t, k, poses)
        c0 = _time.process_time()  # one window: the stage's sub-stage clocks overlap (its ¼ branch runs beside the G-buffer)
        out = self.stage.apply(p.frame, mode="motion", alpha=self.cfg.alpha, filter="off" if self.scale == 1.0 else "lobe",
                               poses=poses, camera=p.integrator.camera)
        stage_ms = (_time.process_time() - c0) * 1e3
        if self.mesh is not None:  # the output's visibility per object: the next frame's choice (as the loop does)
            c0 = _time.process_time()
            H, W = out.image.shape[:2]
            g = p.gbuffer
            shared_map = self.refiner.output_map if self.refiner is not None else None  # "all": the refiner's map of this output
            self.mesh.observe(out.image, g.depth.reshape(H, W) if g is not None else p.frame.depth,
                              g.id.reshape(H, W) if g is not None else p.frame.object_id, visibility=shared_map)
            lod_cpu += (_time.process_time() - c0) * 1e3
        lod_rays = 0 if self.refiner is None else self.refiner.last_rays
        if self.refiner is not None and lod_rays > self.settings.rays:
            raise AssertionError(f"{self.name}: {lod_rays} native rays over the budget of {self.settings.rays}")
        extra = (self.stage.adaptive.last_rays if self.stage.adaptive is not None else 0) + \
            (p.gbuffer.rays_traced if p.gbuffer is not None else 0)
        return dict(ms=p.cpu_ms + stage_ms + lod_cpu, stages_ms=p.cpu_ms + sum(out.stages_s.values()) * 1e3 + lod_cpu,
                    lod_ms=out.stages_s.get("lod", 0.0) * 1e3 + lod_cpu, lod_rays=int(lod_rays),
                    rays=int(p.rays + lod_rays + extra), image=out.image,
                    triangles=self.mesh.triangles if self.mesh is not None else int(p.integrator.geometry.triangle_count))


def _median_or_none(xs):
    return float(np.median(xs)) if xs else None


def _visible_tiles(radiance, depth, K, settings: VisibilitySettings) -> int:
    """Tiles at the ½-rate level or above (V > 20, `policy` default thresholds) in a frame's map."""
    return int((visibility_map(radiance, depth, K, settings).visibility > 20.0).sum())


def run_scene(name: str, cfg: LodBenchConfig, cache: ReferenceCache, progress: Callable, images: dict) -> list[dict]:
    native = with_fps(scaled_scene(bench_scene(name), cfg.scale) if cfg.scale != 1.0 else bench_scene(name), FPS)
    W, H = native.render.width, native.render.height
    start = _time.perf_counter()
    levels = build_levels(native)
    build_s = _time.perf_counter() - start
    meshes = [i for i, o in enumerate(native.objects) if o.shape == "mesh"]
    eval_k = sorted({int(round(t * FPS)) for t in cfg.eval_times})
    start = max(0, eval_k[0] - cfg.history_frames)
    ks = list(range(start, eval_k[-1] + 1))
    shared: dict = {}
    build = lambda scene, scale: _Pipeline(scene, scale, cfg.threads)  # noqa: E731
    try:
        for s in (1.0, 0.25):
            shared[s] = build(native, s)
        refs = {k: cache.get(native, name, k / FPS, cfg.ref_spp, REFERENCE_SEED, integrator=shared[1.0].integrator) for k in eval_k}
        methods = check_methods(cfg.methods)
        runs = [_Run(m, native, cfg, levels, shared, build) for m in methods]
        stats = {m: dict(ms=[], stages_ms=[], full=[], half=[], multi=[], lod_ms=[], lod_rays=[], rays=[], tri=[], psnr=[], ssim=[], flip=[], obj=[], vis=[], vis_ref=[], vis_1spp=[], vis_1spp_raw=[])
                 for m in methods}
        for i, k in enumerate(ks):
            t = k / FPS
            poses = native.object_poses(t)
            for p in list(shared.values()):
                p.frame = None
            for j, r in enumerate(runs[i % len(runs):] + runs[: i % len(runs)]):  # rotate: no method always runs first
                row = r.step(k, t, poses)
                st = stats[r.name]
                if i > 0:
                    st["ms"].append(row["ms"])
                    st["stages_ms"].append(row["stages_ms"])
                    if r.refiner is not None and r.refiner.decisions is not None:  # what the map's uses decided
                        d = r.refiner.decisions
                        st["full"].append(int(((d.rate == 1) & (d.spp > 0)).sum()))
                        st["half"].append(int(((d.rate == 2) & (d.spp > 0)).sum()))
                        st["multi"].append(int((d.spp > 1).sum()))
                    st["lod_ms"].append(row["lod_ms"])
                    st["lod_rays"].append(row["lod_rays"])
                    st["rays"].append(row["rays"])
                    st["tri"].append(row["triangles"])
                if k in refs:
                    ref = refs[k]
                    ref8 = postprocess(ref["radiance"])
                    mask = np.isin(ref["object_id"], meshes)  # inside the objects (the meshes)
                    img = row["image"]
                    st["psnr"].append(psnr(img, ref8))
                    st["ssim"].append(ssim(img, ref8))
                    st["flip"].append(flip_error(ref8, img))
                    st["obj"].append(masked_psnr(img, ref8, mask))
                    if r.refiner is not None and r.refiner.vmap is not None and r.settings.visible:
                        st["vis"].append(int((r.refiner.vmap.visibility > 20.0).sum()))
                    if k == eval_k[-1]:
                        images.setdefault(name, dict(scene=native, reference=ref8))[r.name] = dict(
                            image=img, vmap=r.refiner.vmap if r.refiner else None, decisions=r.refiner.decisions if r.refiner else None,
                            choice=r.choice)
                progress(f"lod {name}: frames × methods", i * len(runs) + j + 1, len(ks) * len(runs))
            mapped = [m for m in stats if m.removesuffix(PLAIN) in ("shading-rate", "spp", "all")]
            if k in refs and mapped and shared[1.0].frame is not None:  # the maps a converged and a raw 1-spp native frame give
                depth = shared[1.0].frame.depth
                vs = runs[0].cfg.visibility
                for m in mapped:
                    stats[m]["vis_ref"].append(_visible_tiles(refs[k]["radiance"], depth, native.camera.K, vs))
                    stats[m]["vis_1spp"].append(_visible_tiles(shared[1.0].frame.radiance, depth, native.camera.K, vs))
                    stats[m]["vis_1spp_raw"].append(_visible_tiles(shared[1.0].frame.radiance, depth, native.camera.K,
                                                                    dataclasses.replace(vs, noise_k=0.0)))
        rows = []
        for r in runs:
            st = stats[r.name]
            rows.append(dict(
                scene=name, method=r.name, frame_ms=float(np.median(st["ms"])),
                rays_per_frame=int(np.median(st["rays"])), lod_rays=int(np.median(st["lod_rays"])),
                triangles=int(np.median(st["tri"])),
                psnr_db=float(np.mean(st["psnr"])), ssim=float(np.mean(st["ssim"])), flip=float(np.mean(st["flip"])),
                psnr_db_object=float(np.nanmean(st["obj"])) if np.isfinite(st["obj"]).any() else None,  # None: no object pixel
                lod_ms=float(np.median(st["lod_ms"])),
                tiles_full_rate=_median_or_none(st["full"]), tiles_half_rate=_median_or_none(st["half"]),
                tiles_multi_spp=_median_or_none(st["multi"]),
                frame_ms_stage_sum=float(np.median(st["stages_ms"])),  # sub-stage clocks summed: counts the overlapping branch twice
                shading_scale=r.scale, ray_budget=r.settings.rays if r.settings else None,
                visible_tiles=float(np.mean(st["vis"])) if st["vis"] else None,
                visible_tiles_reference=float(np.mean(st["vis_ref"])) if st["vis_ref"] else None,
                visible_tiles_1spp=float(np.mean(st["vis_1spp"])) if st["vis_1spp"] else None,
                visible_tiles_1spp_no_floor=float(np.mean(st["vis_1spp_raw"])) if st["vis_1spp_raw"] else None,
                lod_switches=r.lod_switches, mesh_levels=",".join(str(c) for c in r.choice), width=W, height=H,
                frames=len(ks), eval_frames=len(eval_k), ref_spp=cfg.ref_spp, fps=FPS, level_build_s=round(build_s, 2),
            ))
        none = rows[0]
        for row in rows:
            row["time_vs_none"] = row["frame_ms"] / none["frame_ms"]
        return rows
    finally:
        for p in shared.values():
            p.close()


def run_lod(cfg: LodBenchConfig, cache_dir: Path | None = None, out_dir: Path | None = None, progress: Callable | None = None) -> dict:
    progress = progress or (lambda *a: None)
    cache = ReferenceCache(cache_dir, threads=cfg.threads, progress=progress)
    rows, images = [], {}
    for name in cfg.scenes:
        rows += run_scene(name, cfg, cache, progress, images)
    files = write_figures(rows, images, out_dir) if out_dir is not None else []
    return dict(rows=rows, files=files)


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
        run = im.get("all") or im.get("all" + PLAIN)
        if run is None or run["vmap"] is None or run["decisions"] is None:
            continue
        scene = im["scene"]
        vmap, dec = run["vmap"], run["decisions"]
        H, W = scene.render.height, scene.render.width
        ext = (0, W, H, 0)
        fig, axes = plt.subplots(1, 4, figsize=(21, 4.4))
        axes[0].imshow(run["image"], extent=ext)
        axes[0].set_title(f"{name}: output of 'all'", fontsize=10)
        lo, hi = -50.0, max(1.0, float(np.max(vmap.visibility)))
        a = axes[1].imshow(np.clip(vmap.visibility, lo, hi), cmap="coolwarm", vmin=lo, vmax=hi, extent=ext, interpolation="nearest")
        axes[1].set_title("V of the previous output (> 0: visible)", fontsize=10)
        fig.colorbar(a, ax=axes[1], fraction=0.04)
        b = axes[2].imshow(dec.spp, cmap="viridis", vmin=0, vmax=4, extent=ext, interpolation="nearest")
        axes[2].set_title(f"native paths per pixel (bound {dec.ray_bound:,} rays)", fontsize=10)
        fig.colorbar(b, ax=axes[2], fraction=0.04, ticks=[0, 1, 2, 4])
        c = axes[3].imshow(dec.rate, cmap="magma", vmin=0, vmax=4, extent=ext, interpolation="nearest")
        axes[3].set_title("rate (pitch): 1 full, 2 half, 4/0 the ¼ base", fontsize=10)
        fig.colorbar(c, ax=axes[3], fraction=0.04, ticks=[0, 1, 2, 4])
        fig.suptitle(f"mesh levels chosen by 'all': {run['choice']}", fontsize=9)
        for ax in axes:
            ax.set_xlabel("x (px)")
        files.append(save_figure(fig, out_dir / f"lod-map-{name}.png"))
    files.append(plot_rows(rows, out_dir))
    return files


def plot_rows(rows: list[dict], out_dir: Path) -> str:
    """The ms-against-error figure from the rows alone (so it can be redrawn from the JSON)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    fig, axes = plt.subplots(1, 3, figsize=(18, 5.2))
    lo, hi = min(r["frame_ms"] for r in rows), max(r["frame_ms"] for r in rows)
    markers = dict(zip(METHODS, "osP^vXD"))
    for i, name in enumerate(dict.fromkeys(r["scene"] for r in rows)):
        for r in (r for r in rows if r["scene"] == name):
            for ax, key in zip(axes, ("psnr_db", "psnr_db_object", "flip")):
                if r[key] is None:  # no object pixel in the reference
                    continue
                ax.plot(r["frame_ms"], r[key], markers[r["method"].removesuffix(PLAIN)], color=f"C{i}", ms=8,
                        mfc="none" if r["method"].endswith(PLAIN) else f"C{i}", label=f"{name} {r['method']}")
                ax.annotate(r["method"], (r["frame_ms"], r[key]), textcoords="offset points", xytext=(5, 4), fontsize=7)
    axes[0].set_ylabel("PSNR (dB) against the converged reference ↑")
    axes[1].set_ylabel("PSNR inside the mesh objects (dB) ↑")
    axes[2].set_ylabel("mean FLIP against the converged reference ↓")
    for ax in axes:
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xticks([t for t in (10, 20, 50, 100, 200, 500, 1000, 2000) if lo / 1.5 <= t <= hi * 1.5])
        ax.set_xlabel("frame CPU time, median (ms, log; render + stage)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6, ncol=2)
    size = ", ".join(dict.fromkeys(f"{r['width']}×{r['height']}" for r in rows))
    fig.suptitle(f"Contrast-driven LOD in the loop's pipeline: speed against error ({size}, 60 fps timeline)")
    return save_figure(fig, Path(out_dir) / "lod-ms-vs-error.png")


def _or_dash(x) -> str:
    return "–" if x is None else f"{x:.2f}"


def _tiles(row: dict) -> str:
    """Refined tiles per frame (medians): at full rate / at ½ rate / with more than 1 spp."""
    if row.get("tiles_full_rate") is None:
        return "–"
    return f"{row['tiles_full_rate']:.0f}/{row['tiles_half_rate']:.0f}/{row['tiles_multi_spp']:.0f}"


def format_table(result: dict) -> str:
    head = (f"{'scene':<15}{'method':<14}{'CPU ms':>9}{'×none':>7}{'lod ms':>8}{'lod rays':>10}{'triangles':>11}"
            f"{'PSNR':>7}{'obj':>7}{'SSIM':>8}{'FLIP':>8}{'tiles 1/½/spp>1':>17}  levels")
    lines = [head]
    for r in result["rows"]:
        lines.append(f"{r['scene']:<15}{r['method']:<14}{r['frame_ms']:>9.1f}{r['time_vs_none']:>7.2f}{r['lod_ms']:>8.1f}"
                     f"{r['lod_rays']:>10,}{r['triangles']:>11,}{r['psnr_db']:>7.2f}{_or_dash(r['psnr_db_object']):>7}"
                     f"{r['ssim']:>8.4f}{r['flip']:>8.4f}{_tiles(r):>17}  {r['mesh_levels']}")
    return "\n".join(lines)
