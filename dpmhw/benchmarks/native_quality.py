"""`dpmhw bench quality --part native`: reconstruction at the projector's native size, speed vs error.

For paper-static and paper-dynamic at native size (1024×768 unless `native_scale` < 1), every
method runs the same timeline through `reconstruct.stage.ReconstructStage` (the loop's own
stage: reuse → filter → upsample → post) and is compared, after post-processing, with a native
reference of `native_ref_spp` samples (cached like the other references):

- 1 spp with no filter, the normal-aware and the lobe-aware filter (no reuse);
- reuse (motion mode) at α = 0.2 with each filter;
- shading at ½ and ¼ per axis + joint bilateral upsampling + reuse, with each filter;
- the same at ½ and ¼ with the lobe-aware filter and adaptive sampling (`reconstruct.adaptive`,
  `native_adaptive_rays` rays per frame; method names end in "+ adaptive").

Rows are flat: scene, method, shading_scale, filter, alpha, frame_ms (render at the shading
resolution + native G-buffer + reuse + filter + upsample + post, median over the timeline's
frames), psnr_db, ssim, flip (mean FLIP, `flip-evaluator`, LDR, default 67 ppd), plus
psnr_db_object (the mesh objects' pixels), psnr_db_glossy (pixels of objects with a specular
lobe sharper than roughness 0.5: where lobe- and normal-aware differ), cost_vs_1spp,
adaptive_rays (the budget; 0 without adaptive sampling), adaptive_pixels (median paths per frame).

Static: metrics averaged over the last `native_eval_frames` frames of `native_static_frames`.
Dynamic: a 60 fps timeline, `native_history_frames` frames before the first eval time.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from dpmhw.metrics import psnr, ssim
from dpmhw.postprocess import postprocess
from dpmhw.reconstruct.adaptive import AdaptiveSampler
from dpmhw.reconstruct.stage import ReconstructStage
from dpmhw.render.gbuffer import NativeGBuffer
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import Scene, load_scene
from dpmhw.sequence import scaled_scene, with_fps

GLOSSY_ROUGHNESS = 0.5


@dataclass(frozen=True)
class Method:
    name: str
    shading_scale: float
    alpha: float | None  # None: no reuse
    filter: str
    adaptive: bool = False


def native_methods(alpha: float = 0.2) -> list[Method]:
    out = [Method(f"1 spp + {f}", 1.0, None, f) for f in ("off", "normal", "lobe")]
    for scale, tag in ((1.0, "native"), (0.5, "1/2"), (0.25, "1/4")):
        out += [Method(f"{tag} + reuse {alpha:g} + {f}", scale, alpha, f) for f in ("off", "normal", "lobe")]
    out += [Method(f"{tag} + reuse {alpha:g} + lobe + adaptive", scale, alpha, "lobe", True) for scale, tag in ((0.5, "1/2"), (0.25, "1/4"))]
    return out


def flip_error(ref8: np.ndarray, img8: np.ndarray) -> float:
    """Mean FLIP (NVIDIA's `flip-evaluator`, LDR sRGB inputs in [0, 1])."""
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(ref8.astype(np.float32) / 255.0, img8.astype(np.float32) / 255.0, "LDR",
                                         applyMagma=False)
    return float(mean)


def _masks(scene: Scene, object_id: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    meshes = [i for i, o in enumerate(scene.objects) if o.shape == "mesh"]
    glossy = [i for i, o in enumerate(scene.objects) if np.any(o.specular > 0) and o.roughness < GLOSSY_ROUGHNESS]
    return np.isin(object_id, meshes), np.isin(object_id, glossy)


def _masked_psnr(img, ref, mask) -> float:
    return psnr(img[mask], ref[mask]) if mask.any() else float("nan")


def run_native_scene(name: str, kind: str, cfg, cache, progress: Callable, images: dict) -> dict:
    """One scene: kind "static" (a still timeline) or "dynamic" (60 fps, scripted motion)."""
    base = scaled_scene(load_scene(name), cfg.native_scale)
    native = with_fps(base, 60.0) if kind == "dynamic" else base
    W, H = native.render.width, native.render.height
    methods = native_methods()
    scales = sorted({m.shading_scale for m in methods}, reverse=True)
    fps = 60.0
    if kind == "static":
        frame_times = [0.0] * cfg.native_static_frames
        eval_at = set(range(cfg.native_static_frames - cfg.native_eval_frames, cfg.native_static_frames))
    else:
        eval_frames = sorted({int(round(t * fps)) for t in cfg.native_eval_times})
        start = eval_frames[0] - cfg.native_history_frames
        frame_times = [k / fps for k in range(start, eval_frames[-1] + 1)]
        eval_at = {k - start for k in eval_frames}
    from dpmhw.session.factory import shading_scene

    integrators, gbuffers, stages = {}, {}, {}
    stats = {m: dict(ms=[], psnr=[], ssim=[], flip=[], obj=[], glossy=[], adaptive=[]) for m in methods}
    refs = {}
    try:
        for s in scales:
            integrators[s] = PathIntegrator(shading_scene(native, s), threads=cfg.threads)
            integrators[s].render(spp=1, seed=0)  # JIT and the static-hit cache
            if s != 1.0:
                gbuffers[s] = NativeGBuffer(native, integrators[s].geometry, W, H, threads=cfg.threads)
        for t in sorted({frame_times[k] for k in eval_at}):
            refs[t] = cache.get(native, name, t, cfg.native_ref_spp, integrator=integrators[1.0])
        for m in methods:
            stages[m] = ReconstructStage((W, H), (integrators[m.shading_scale].width, integrators[m.shading_scale].height),
                                         background=native.render.background, viewer=native.viewer_position,
                                         gbuffer=gbuffers.get(m.shading_scale), clock=_time.perf_counter_ns,
                                         adaptive=AdaptiveSampler(integrators[m.shading_scale], gbuffers[m.shading_scale],
                                                                  cfg.native_adaptive_rays) if m.adaptive else None)
        for k, t in enumerate(frame_times):
            poses = native.object_poses(t)
            frames, render_ms = {}, {}
            for s in scales:
                t0 = _time.perf_counter()
                frames[s] = integrators[s].render(time=t, seed=k, spp=1, poses=poses)
                render_ms[s] = (_time.perf_counter() - t0) * 1e3
            ref = refs.get(t) if k in eval_at else None
            ref8 = postprocess(ref["radiance"]) if ref is not None else None
            masks = _masks(native, ref["object_id"]) if ref is not None else None
            for m in methods:
                out = stages[m].apply(frames[m.shading_scale], mode="off" if m.alpha is None else "motion",
                                      alpha=m.alpha or 1.0, filter=m.filter, poses=poses,
                                      camera=integrators[m.shading_scale].camera)
                st = stats[m]
                st["ms"].append(render_ms[m.shading_scale] + sum(out.stages_s.values()) * 1e3)
                if m.adaptive:
                    st["adaptive"].append(stages[m].adaptive.last_pixels)
                if ref8 is None:
                    continue
                img = out.image
                st["psnr"].append(psnr(img, ref8))
                st["ssim"].append(ssim(img, ref8))
                st["flip"].append(flip_error(ref8, img))
                st["obj"].append(_masked_psnr(img, ref8, masks[0]))
                st["glossy"].append(_masked_psnr(img, ref8, masks[1]))
                if k == max(eval_at):
                    images.setdefault(f"native {name}", {})["reference"] = ref8
                    images[f"native {name}"][m.name] = img
            progress(f"native {name}: {len(methods)} methods per frame", k + 1, len(frame_times))
    finally:
        for g in gbuffers.values():
            g.close()
        for i in integrators.values():
            i.close()
    rows = []
    for m in methods:
        st = stats[m]
        rows.append({"scene": name, "method": m.name, "shading_scale": m.shading_scale, "filter": m.filter,
                     "alpha": m.alpha if m.alpha is not None else 1.0, "frame_ms": float(np.median(st["ms"])),
                     "psnr_db": float(np.mean(st["psnr"])), "ssim": float(np.mean(st["ssim"])),
                     "flip": float(np.mean(st["flip"])), "psnr_db_object": float(np.nanmean(st["obj"])),
                     "psnr_db_glossy": float(np.nanmean(st["glossy"])) if np.isfinite(st["glossy"]).any() else None,
                     "width": W, "height": H, "ref_spp": cfg.native_ref_spp, "frames": len(frame_times),
                     "eval_frames": len(eval_at), "timeline": kind,
                     "adaptive_rays": cfg.native_adaptive_rays if m.adaptive else 0,
                     "adaptive_pixels": float(np.median(st["adaptive"])) if st["adaptive"] else 0.0})
    one = next(r for r in rows if r["method"] == "1 spp + off")
    for r in rows:
        r["cost_vs_1spp"] = r["frame_ms"] / one["frame_ms"]
    return {"scene": name, "kind": kind, "width": W, "height": H, "ref_spp": cfg.native_ref_spp, "rows": rows}


def run_native(cfg, cache, progress: Callable, images: dict) -> dict:
    return {"scenes": [run_native_scene(cfg.static_scene, "static", cfg, cache, progress, images),
                       run_native_scene(cfg.dynamic_scene, "dynamic", cfg, cache, progress, images)]}


def native_plot(result: dict, out_dir) -> str:
    """ms per frame against PSNR, one curve per filter (over the shading scales, with reuse) and
    one for 1 spp without reuse, per scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dpmhw.benchmarks.quality import _save

    scenes = result["native"]["scenes"]
    fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 5), squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        rows = sc["rows"]
        for filt, colour in (("off", "tab:gray"), ("normal", "tab:blue"), ("lobe", "tab:red")):
            reuse = sorted((r for r in rows if r["alpha"] < 1 and r["filter"] == filt and not r["adaptive_rays"]),
                           key=lambda r: r["frame_ms"])
            ax.plot([r["frame_ms"] for r in reuse], [r["psnr_db"] for r in reuse], "o-", color=colour,
                    label=f"reuse α=0.2 + filter {filt} (¼, ½, native)")
            for r in reuse:
                tag = {1.0: "native", 0.5: "½", 0.25: "¼"}[r["shading_scale"]]
                ax.annotate(tag, (r["frame_ms"], r["psnr_db"]), textcoords="offset points", xytext=(4, 4), fontsize=7)
            plain = [r for r in rows if r["alpha"] == 1.0 and r["filter"] == filt]
            ax.plot([r["frame_ms"] for r in plain], [r["psnr_db"] for r in plain], "s", color=colour, mfc="none",
                    label=f"1 spp, no reuse + filter {filt}")
        adaptive = sorted((r for r in rows if r["adaptive_rays"]), key=lambda r: r["frame_ms"])
        ax.plot([r["frame_ms"] for r in adaptive], [r["psnr_db"] for r in adaptive], "^--", color="tab:purple",
                label="reuse α=0.2 + lobe + adaptive (¼, ½)")
        ax.set_title(f"{sc['scene']} ({sc['kind']}), {sc['width']}×{sc['height']}, reference {sc['ref_spp']} spp")
        ax.set_xlabel("ms per frame (render at shading res + reconstruction + post; median, shared 2-core CPU)")
        ax.set_ylabel("PSNR (dB, uint8 sRGB) against the reference")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    return _save(fig, out_dir / "native_speed_vs_psnr.png")


def format_native(result: dict) -> list[str]:
    lines = []
    for sc in result["native"]["scenes"]:
        lines.append(f"native: {sc['scene']} ({sc['kind']}) {sc['width']}×{sc['height']}, reference {sc['ref_spp']} spp")
        lines.append(f"{'method':40s} {'ms':>7s} {'×1spp':>6s} {'PSNR':>7s} {'obj':>7s} {'glossy':>7s} {'SSIM':>6s} {'FLIP':>6s}")
        for r in sc["rows"]:
            glossy = f"{r['psnr_db_glossy']:7.2f}" if r["psnr_db_glossy"] is not None else "      -"
            lines.append(f"{r['method']:40s} {r['frame_ms']:7.1f} {r['cost_vs_1spp']:6.2f} {r['psnr_db']:7.2f} "
                         f"{r['psnr_db_object']:7.2f} {glossy} {r['ssim']:6.3f} {r['flip']:6.3f}")
        lines.append("")
    return lines
