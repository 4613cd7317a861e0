"""`dpmhw bench quality --part native`: reconstruction at the projector's native size, speed vs error.

Three scenes at native size (1024×768 unless `native_scale` < 1): paper-static (still),
paper-dynamic (60 fps, scripted motion) and glossy-roughness (still; roughness changes within
one object: the lobe- against normal-aware case). Every method runs the same timeline through
`reconstruct.stage.ReconstructStage` (the loop's own stage: reuse → filter → upsample → post):

- 1 spp with no filter, the normal-aware and the lobe-aware filter (no reuse);
- reuse (motion mode) at α = 0.2 with each filter;
- shading at ½ and ¼ per axis + joint bilateral upsampling + reuse, with each filter;
- the same at ½ and ¼ with the lobe-aware filter and adaptive sampling (`reconstruct.adaptive`,
  `native_adaptive_rays` rays per frame; method names end in "+ adaptive");
- paper-dynamic only: three of them again with per-frame pixel jitter instead of pixel centres
  (names end in ", jitter"): jitter + reuse as temporal antialiasing, against the session's
  centre sampling with cached static hits;
- glossy-roughness: the 1-spp and reuse rows at native and ¼ only.

References: two independent halves A, B (seeds REFERENCE_SEED, REFERENCE_SEED + 1) of
`native_static_ref_spp` (still scenes) or `native_ref_spp` (dynamic) spp in all, cached like the
other references; the reference is (A + B)/2, and the noise-corrected PSNR subtracts its own
variance MSE(A, B)/4 (`dpmhw.metrics`). paper-dynamic also gets jittered references (the pixel
integral, the converged image of a box-filtered pixel).

Rows are flat. Keys:
- scene, method, shading_scale, filter, alpha (1.0 = no reuse), pixel_sampling ("centre" | "jitter");
- frame_ms: wall ms of render at the shading resolution + native G-buffer + reuse + filter +
  upsample + post, median over the timeline's frames (shared machine: see frame_cpu_ms);
- frame_cpu_ms: the same in CPU-ms of this process (all threads), median; cost_vs_1spp and
  cost_vs_1spp_cpu: frame_ms / frame_cpu_ms over those of "1 spp + off";
- psnr_db, ssim, flip (mean FLIP, `flip-evaluator`, LDR, default 67 ppd), against (A + B)/2;
- psnr_db_object (the mesh and sphere objects' pixels), psnr_db_glossy (pixels whose G-buffer
  has a specular lobe with roughness < 0.5: where lobe- and normal-aware differ),
  psnr_db_roughness_edge (glossy pixels within 4 px of a roughness change inside one object;
  None where the scene has none);
- psnr_db_corrected, psnr_db_object_corrected, psnr_db_glossy_corrected,
  psnr_db_roughness_edge_corrected: the same, noise-corrected; ref_psnr_cap_db: 10·log10(255² /
  var(reference)), the PSNR a perfect image would measure against this reference;
- psnr_db_jittered_ref, psnr_db_edges_jittered_ref: against the jittered reference (whole
  image; pixels within 1 px of an object-id edge), None without one;
- width, height, ref_spp, frames, eval_frames, timeline, adaptive_rays (the budget; 0 without
  adaptive sampling), adaptive_pixels (median paths per frame).

Still scenes: metrics averaged over the last `native_eval_frames` frames of
`native_static_frames`. Dynamic: a 60 fps timeline, `native_history_frames` frames before the
first eval time.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import ndimage

from dpmhw.benchmarks.figures import labelled, save_figure
from dpmhw.benchmarks.references import REFERENCE_SEED
from dpmhw.metrics import masked_psnr, noise_corrected_psnr, psnr, reference_noise_mse, ssim
from dpmhw.postprocess import postprocess
from dpmhw.reconstruct.adaptive import AdaptiveSampler
from dpmhw.reconstruct.stage import ReconstructStage
from dpmhw.render.gbuffer import NativeGBuffer
from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import Scene, load_scene
from dpmhw.sequence import scaled_scene, with_fps

GLOSSY_ROUGHNESS = 0.5
GLOSSY_SCENE = "glossy-roughness"
ROUGHNESS_EDGE_PX = 4  # psnr_db_roughness_edge: this many native pixels either side of a change
ROUGHNESS_STEP = 0.05  # … of at least this much roughness


@dataclass(frozen=True)
class Method:
    name: str
    shading_scale: float
    alpha: float | None  # None: no reuse
    filter: str
    adaptive: bool = False
    pixel_sampling: str = "centre"


def native_methods(alpha: float = 0.2, kind: str = "static") -> list[Method]:
    """The methods of one scene; `kind` "static", "dynamic" (+ jitter rows) or "glossy" (subset)."""
    out = [Method(f"1 spp + {f}", 1.0, None, f) for f in ("off", "normal", "lobe")]
    tags = ((1.0, "native"), (0.25, "1/4")) if kind == "glossy" else ((1.0, "native"), (0.5, "1/2"), (0.25, "1/4"))
    for scale, tag in tags:
        out += [Method(f"{tag} + reuse {alpha:g} + {f}", scale, alpha, f) for f in ("off", "normal", "lobe")]
    if kind == "glossy":
        return out
    out += [Method(f"{tag} + reuse {alpha:g} + lobe + adaptive", scale, alpha, "lobe", True) for scale, tag in ((0.5, "1/2"), (0.25, "1/4"))]
    if kind == "dynamic":
        out += [Method("1 spp + off, jitter", 1.0, None, "off", pixel_sampling="jitter"),
                Method(f"native + reuse {alpha:g} + lobe, jitter", 1.0, alpha, "lobe", pixel_sampling="jitter"),
                Method(f"1/4 + reuse {alpha:g} + lobe + adaptive, jitter", 0.25, alpha, "lobe", True, "jitter")]
    return out


def flip_error(ref8: np.ndarray, img8: np.ndarray) -> float:
    """Mean FLIP (NVIDIA's `flip-evaluator`, LDR sRGB inputs in [0, 1])."""
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(ref8.astype(np.float32) / 255.0, img8.astype(np.float32) / 255.0, "LDR",
                                         applyMagma=False)
    return float(mean)


def _masks(scene: Scene, frame) -> dict[str, np.ndarray]:
    """Pixel masks from a native, centre-sampled frame's G-buffer (the references' geometry)."""
    oid = frame.object_id
    shapes = [i for i, o in enumerate(scene.objects) if o.shape in ("mesh", "sphere")]
    rough = np.where(oid >= 0, frame.roughness, np.nan)
    glossy = (oid >= 0) & np.any(frame.specular_albedo > 0, axis=-1) & (frame.roughness < GLOSSY_ROUGHNESS)
    size = 2 * ROUGHNESS_EDGE_PX + 1
    filled = np.nan_to_num(rough, nan=0.0)
    same_object = ndimage.maximum_filter(oid, size) == ndimage.minimum_filter(oid, size)
    step = ndimage.maximum_filter(filled, size) - ndimage.minimum_filter(filled, size)
    edges = ndimage.maximum_filter(oid, 3) != ndimage.minimum_filter(oid, 3)
    return {"object": np.isin(oid, shapes), "glossy": glossy, "roughness_edge": glossy & same_object & (step >= ROUGHNESS_STEP),
            "id_edges": edges}


def _reference(cache, scene, name, t, spp, integrator, sampling) -> dict:
    """(A + B)/2 of two independent halves, post-processed, with the halves' uint8 images."""
    half = max(1, spp // 2)
    a, b = (cache.get(scene, name, t, half, seed=REFERENCE_SEED + i, integrator=integrator, pixel_sampling=sampling)
            for i in (0, 1))
    return {"ref8": postprocess(0.5 * (a["radiance"] + b["radiance"])), "a8": postprocess(a["radiance"]),
            "b8": postprocess(b["radiance"])}


def _mean(xs) -> float | None:
    xs = np.asarray(xs, float)
    return float(np.nanmean(xs)) if xs.size and np.isfinite(xs).any() else None


def run_native_scene(name: str, kind: str, cfg, cache, progress: Callable, images: dict) -> dict:
    """One scene: kind "static" (a still timeline), "dynamic" (60 fps, scripted motion) or
    "glossy" (a still timeline, fewer methods)."""
    base = scaled_scene(load_scene(name), cfg.native_scale)
    native = with_fps(base, 60.0) if kind == "dynamic" else base
    W, H = native.render.width, native.render.height
    methods = native_methods(kind=kind)
    ref_spp = cfg.native_ref_spp if kind == "dynamic" else cfg.native_static_ref_spp
    variants = sorted({(m.shading_scale, m.pixel_sampling) for m in methods} | {(1.0, "centre")}, reverse=True)
    fps = 60.0
    if kind != "dynamic":
        frame_times = [0.0] * cfg.native_static_frames
        eval_at = set(range(cfg.native_static_frames - cfg.native_eval_frames, cfg.native_static_frames))
    else:
        eval_frames = sorted({int(round(t * fps)) for t in cfg.native_eval_times})
        start = eval_frames[0] - cfg.native_history_frames
        frame_times = [k / fps for k in range(start, eval_frames[-1] + 1)]
        eval_at = {k - start for k in eval_frames}
    from dpmhw.session.factory import shading_scene

    integrators, gbuffers, stages = {}, {}, {}
    keys = ("ms", "cpu", "psnr", "ssim", "flip", "object", "glossy", "roughness_edge", "psnr_c", "object_c", "glossy_c",
            "roughness_edge_c", "cap", "jref", "jref_edges", "adaptive")
    stats = {m: {k: [] for k in keys} for m in methods}
    refs, jrefs = {}, {}
    jittered = any(m.pixel_sampling == "jitter" for m in methods)
    try:
        for v in variants:
            s, sampling = v
            integrators[v] = PathIntegrator(shading_scene(native, s), threads=cfg.threads, pixel_sampling=sampling)
            integrators[v].render(spp=1, seed=0)  # JIT and the static-hit cache
            if s != 1.0:
                gbuffers[v] = NativeGBuffer(native, integrators[v].geometry, W, H, threads=cfg.threads)
        for t in sorted({frame_times[k] for k in eval_at}):
            refs[t] = _reference(cache, native, name, t, ref_spp, integrators[(1.0, "centre")], "centre")
            if jittered:
                jrefs[t] = _reference(cache, native, name, t, ref_spp, integrators[(1.0, "jitter")], "jitter")
        for m in methods:
            v = (m.shading_scale, m.pixel_sampling)
            stages[m] = ReconstructStage((W, H), (integrators[v].width, integrators[v].height),
                                         background=native.render.background, viewer=native.viewer_position,
                                         gbuffer=gbuffers.get(v), clock=_time.perf_counter_ns,
                                         adaptive=AdaptiveSampler(integrators[v], gbuffers[v], cfg.native_adaptive_rays)
                                         if m.adaptive else None)
        for k, t in enumerate(frame_times):
            poses = native.object_poses(t)
            frames, render_ms, render_cpu = {}, {}, {}
            for v in variants:
                t0, c0 = _time.perf_counter(), _time.process_time()
                frames[v] = integrators[v].render(time=t, seed=k, spp=1, poses=poses)
                render_ms[v] = (_time.perf_counter() - t0) * 1e3
                render_cpu[v] = (_time.process_time() - c0) * 1e3
            ref = refs.get(t) if k in eval_at else None
            masks = _masks(native, frames[(1.0, "centre")]) if ref is not None else None
            for m in methods:
                v = (m.shading_scale, m.pixel_sampling)
                c0 = _time.process_time()
                out = stages[m].apply(frames[v], mode="off" if m.alpha is None else "motion", alpha=m.alpha or 1.0,
                                      filter=m.filter, poses=poses, camera=integrators[v].camera)
                st = stats[m]
                st["cpu"].append(render_cpu[v] + (_time.process_time() - c0) * 1e3)
                st["ms"].append(render_ms[v] + sum(out.stages_s.values()) * 1e3)
                if m.adaptive:
                    st["adaptive"].append(stages[m].adaptive.last_pixels)
                if ref is None:
                    continue
                img, ref8 = out.image, ref["ref8"]
                st["psnr"].append(psnr(img, ref8))
                st["ssim"].append(ssim(img, ref8))
                st["flip"].append(flip_error(ref8, img))
                st["psnr_c"].append(noise_corrected_psnr(img, ref8, ref["a8"], ref["b8"]))
                st["cap"].append(10 * np.log10(255.0**2 / max(reference_noise_mse(ref["a8"], ref["b8"]), 1e-12)))
                for key in ("object", "glossy", "roughness_edge"):
                    mask = masks[key]
                    st[key].append(masked_psnr(img, ref8, mask))
                    st[key + "_c"].append(noise_corrected_psnr(img, ref8, ref["a8"], ref["b8"], mask) if mask.any() else np.nan)
                if t in jrefs:
                    st["jref"].append(psnr(img, jrefs[t]["ref8"]))
                    st["jref_edges"].append(masked_psnr(img, jrefs[t]["ref8"], masks["id_edges"]))
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
                     "alpha": m.alpha if m.alpha is not None else 1.0, "pixel_sampling": m.pixel_sampling,
                     "frame_ms": float(np.median(st["ms"])), "frame_cpu_ms": float(np.median(st["cpu"])),
                     "psnr_db": _mean(st["psnr"]), "ssim": _mean(st["ssim"]), "flip": _mean(st["flip"]),
                     "psnr_db_object": _mean(st["object"]), "psnr_db_glossy": _mean(st["glossy"]),
                     "psnr_db_roughness_edge": _mean(st["roughness_edge"]),
                     "psnr_db_corrected": _mean(st["psnr_c"]), "psnr_db_object_corrected": _mean(st["object_c"]),
                     "psnr_db_glossy_corrected": _mean(st["glossy_c"]),
                     "psnr_db_roughness_edge_corrected": _mean(st["roughness_edge_c"]), "ref_psnr_cap_db": _mean(st["cap"]),
                     "psnr_db_jittered_ref": _mean(st["jref"]), "psnr_db_edges_jittered_ref": _mean(st["jref_edges"]),
                     "width": W, "height": H, "ref_spp": ref_spp, "frames": len(frame_times),
                     "eval_frames": len(eval_at), "timeline": "dynamic" if kind == "dynamic" else "static",
                     "adaptive_rays": cfg.native_adaptive_rays if m.adaptive else 0,
                     "adaptive_pixels": float(np.median(st["adaptive"])) if st["adaptive"] else 0.0})
    one = next(r for r in rows if r["method"] == "1 spp + off")
    for r in rows:
        r["cost_vs_1spp"] = r["frame_ms"] / one["frame_ms"]
        r["cost_vs_1spp_cpu"] = r["frame_cpu_ms"] / one["frame_cpu_ms"]
    return {"scene": name, "kind": kind, "width": W, "height": H, "ref_spp": ref_spp, "rows": rows}


def run_native(cfg, cache, progress: Callable, images: dict) -> dict:
    return {"scenes": [run_native_scene(cfg.static_scene, "static", cfg, cache, progress, images),
                       run_native_scene(cfg.dynamic_scene, "dynamic", cfg, cache, progress, images),
                       run_native_scene(GLOSSY_SCENE, "glossy", cfg, cache, progress, images)]}


def native_plot(result: dict, out_dir) -> str:
    """CPU-ms per frame against noise-corrected PSNR, one curve per filter (over the shading
    scales, with reuse), 1 spp without reuse, adaptive and jitter rows, per scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = result["native"]["scenes"]
    fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 5), squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        rows = [r for r in sc["rows"] if r["pixel_sampling"] == "centre"]
        for filt, colour in (("off", "tab:gray"), ("normal", "tab:blue"), ("lobe", "tab:red")):
            reuse = sorted((r for r in rows if r["alpha"] < 1 and r["filter"] == filt and not r["adaptive_rays"]),
                           key=lambda r: r["frame_cpu_ms"])
            ax.plot([r["frame_cpu_ms"] for r in reuse], [r["psnr_db_corrected"] for r in reuse], "o-", color=colour,
                    label=f"reuse α=0.2 + filter {filt} ({', '.join(_tag(r) for r in reuse)})")
            for r in reuse:
                ax.annotate(_tag(r), (r["frame_cpu_ms"], r["psnr_db_corrected"]), textcoords="offset points", xytext=(4, 4), fontsize=7)
            plain = [r for r in rows if r["alpha"] == 1.0 and r["filter"] == filt]
            ax.plot([r["frame_cpu_ms"] for r in plain], [r["psnr_db_corrected"] for r in plain], "s", color=colour, mfc="none",
                    label=f"1 spp, no reuse + filter {filt}")
        adaptive = sorted((r for r in rows if r["adaptive_rays"]), key=lambda r: r["frame_cpu_ms"])
        if adaptive:
            ax.plot([r["frame_cpu_ms"] for r in adaptive], [r["psnr_db_corrected"] for r in adaptive], "^--", color="tab:purple",
                    label="reuse α=0.2 + lobe + adaptive (¼, ½)")
        jitter = [r for r in sc["rows"] if r["pixel_sampling"] == "jitter"]
        if jitter:
            ax.plot([r["frame_cpu_ms"] for r in jitter], [r["psnr_db_corrected"] for r in jitter], "x", color="k", ms=8,
                    label="pixel jitter (1 spp; native + reuse + lobe; ¼ + reuse + lobe + adaptive)")
        ax.set_title(f"{sc['scene']} ({sc['kind']}), {sc['width']}×{sc['height']}, reference {sc['ref_spp']} spp")
        ax.set_xlabel("CPU-ms per frame (render at shading res + reconstruction + post; median, both threads)")
        ax.set_ylabel("noise-corrected PSNR (dB, uint8 sRGB) against the converged image")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    return save_figure(fig, out_dir / "native_speed_vs_psnr.png")


def _tag(row: dict) -> str:
    return {1.0: "native", 0.5: "½", 0.25: "¼"}[row["shading_scale"]]


GLOSSY_CROP_METHODS = ("reference", "1 spp + normal", "1 spp + lobe", "native + reuse 0.2 + normal", "native + reuse 0.2 + lobe",
                       "1/4 + reuse 0.2 + normal", "1/4 + reuse 0.2 + lobe")


def glossy_crops(images: dict, out_dir) -> list[str]:
    """The glossy scene's brightest highlight (a third of the frame around the reference's
    brightest smoothed pixel), normal- against lobe-aware, each crop labelled; [] without it."""
    from dpmhw.postprocess import write_png

    imgs = images.get(f"native {GLOSSY_SCENE}")
    if not imgs:
        return []
    ref = imgs["reference"]
    H, W = ref.shape[:2]
    y, x = np.unravel_index(np.argmax(ndimage.uniform_filter(ref.astype(np.float32).mean(axis=-1), 9)), (H, W))
    h, w = max(H // 3, 16), max(W // 3, 16)
    y0, x0 = int(np.clip(y - h // 2, 0, H - h)), int(np.clip(x - w // 2, 0, W - w))
    crops = [labelled(np.ascontiguousarray(imgs[n][y0:y0 + h, x0:x0 + w]), n) for n in GLOSSY_CROP_METHODS if n in imgs]
    path = out_dir / f"native_{GLOSSY_SCENE}_highlight_normal_vs_lobe.png"
    write_png(path, np.concatenate(crops, axis=1))
    return [str(path)]


def _f(value, width: int = 7, digits: int = 2) -> str:
    return f"{value:{width}.{digits}f}" if value is not None else " " * (width - 1) + "-"


def format_native(result: dict) -> list[str]:
    lines = []
    for sc in result["native"]["scenes"]:
        lines.append(f"native: {sc['scene']} ({sc['kind']}) {sc['width']}×{sc['height']}, reference {sc['ref_spp']} spp "
                     f"(two halves); 'corr' = noise-corrected PSNR; cap = PSNR of the reference's own noise")
        lines.append(f"{'method':44s} {'ms':>7s} {'CPU-ms':>7s} {'×1spp':>6s} {'PSNR':>7s} {'corr':>7s} {'obj':>7s} "
                     f"{'glossy':>7s} {'gl.corr':>7s} {'r-edge':>7s} {'re.corr':>7s} {'SSIM':>6s} {'FLIP':>6s} {'cap':>6s} "
                     f"{'jref':>7s} {'jedges':>7s}")
        for r in sc["rows"]:
            lines.append(f"{r['method']:44s} {r['frame_ms']:7.1f} {r['frame_cpu_ms']:7.1f} {r['cost_vs_1spp_cpu']:6.2f} "
                         f"{_f(r['psnr_db'])} {_f(r['psnr_db_corrected'])} {_f(r['psnr_db_object'])} {_f(r['psnr_db_glossy'])} "
                         f"{_f(r['psnr_db_glossy_corrected'])} {_f(r['psnr_db_roughness_edge'])} "
                         f"{_f(r['psnr_db_roughness_edge_corrected'])} {_f(r['ssim'], 6, 3)} {_f(r['flip'], 6, 3)} "
                         f"{_f(r['ref_psnr_cap_db'], 6, 1)} {_f(r['psnr_db_jittered_ref'])} {_f(r['psnr_db_edges_jittered_ref'])}")
        lines.append("")
    return lines
