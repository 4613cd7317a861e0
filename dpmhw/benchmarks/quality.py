"""`dpmhw bench quality`: speed against error for plain path tracing, temporal reuse and native reconstruction.

Every image is compared with a converged reference *after* post-processing (exposure 1, clip,
sRGB, uint8: what the projector would show) with PSNR and SSIM as defined in dpmhw.metrics.

Static scene (paper-static): plain path tracing at n spp (several seeds each); 1-spp frames of
the timeline (frame k: seed k) through same-pixel reuse at each α (and motion mode at α = 0.2,
which must equal it on a static scene) after 10/α_min frames, metrics averaged over the last
frames; the equivalent spp of each reuse row on the plain curve; PSNR against frame index for
every α with and without warm-up (the slow start a fixed α has).

Dynamic scene (paper-dynamic): the same motion on a 947-fps timeline (the paper's projector)
and a 60-fps one; per sampled frame, error of plain 1 spp and of every mode × α × warm-up,
over the whole image and over the moving objects only (where lag and ghosting live), each
against its own reference at that time.

Native (the `native` part, `native_quality`): reconstruction at the projector's size, 1 spp /
reuse / ½ and ¼ shading + upsampling, each with no, normal-aware and lobe-aware filtering,
with FLIP beside PSNR and SSIM, as flat rows.

References are rendered once and cached on disk (`cache_dir`, `references.ReferenceCache`).
The sweep's independent units run here, or wherever the injected `run_units` sends them
(`dpmhw.benchmarks.quality_ray.run_units_on_ray`).

Costs per row: ms per frame for render, reuse, post-processing and their total, medians over
the frames of the run (plain n-spp rows: over their repeats). The machine may be shared:
medians, not means, and the JSON records the load average at the start and the end.
"""

from __future__ import annotations

import math
import os
import time as _time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from dpmhw import __version__
from dpmhw.benchmarks.figures import labelled, save_figure
from dpmhw.benchmarks.references import ReferenceCache
from dpmhw.metrics import equivalent_spp, masked_psnr, psnr, ssim
from dpmhw.postprocess import postprocess
from dpmhw.machine import machine_info
from dpmhw.render.integrator import PathIntegrator
from dpmhw.reconstruct.adaptive import DEFAULT_BUDGET_RAYS
from dpmhw.reconstruct.reuse import TemporalReuse
from dpmhw.scene_file import load_scene
from dpmhw.sequence import run_sequence, scaled_scene, with_fps

PLAIN_SEED = 500_000


@dataclass
class QualityConfig:
    scale: float = 1.0
    static_scene: str = "paper-static"
    dynamic_scene: str = "paper-dynamic"
    ref_spp: int = 1000
    dynamic_ref_spp: int = 1000
    static_spp: tuple[int, ...] = (1, 2, 4, 8, 16, 20, 32, 40)
    spp_repeats: int = 3
    alphas: tuple[float, ...] = (0.05, 0.1, 0.2)
    static_frames: int = 0  # 0 → ceil(10 / min α) + eval_frames
    eval_frames: int = 6  # static: metrics averaged over this many last frames
    dynamic_fps: tuple[float, ...] = (947.0, 60.0)
    dynamic_eval_times: tuple[float, ...] = (0.2, 0.3, 0.4, 0.5)
    dynamic_history_frames: int = 0  # frames rendered before the first eval time; 0 → ceil(8 / min α) (steady state)
    modes: tuple[str, ...] = ("same-pixel", "motion")
    threads: int = 2
    parts: tuple[str, ...] = ("static", "dynamic", "native")
    # native reconstruction rows (dpmhw.benchmarks.native_quality): modest references, short timelines
    native_scale: float = 1.0
    native_ref_spp: int = 64  # dynamic native references: two independent halves of this many spp in all
    native_static_ref_spp: int = 256  # the same for the still scenes (one eval time each)
    native_static_frames: int = 16
    native_eval_frames: int = 2
    native_eval_times: tuple[float, ...] = (0.3, 0.5)
    native_history_frames: int = 12
    native_adaptive_rays: int = DEFAULT_BUDGET_RAYS  # adaptive sampling's rays per frame (the session default)

    @classmethod
    def quick(cls) -> "QualityConfig":
        return cls(scale=0.25, ref_spp=1000, dynamic_ref_spp=256, static_spp=(1, 2, 4, 8, 16, 20, 32, 40), spp_repeats=3,
                   eval_frames=4, dynamic_eval_times=(0.2, 0.35, 0.5), native_scale=0.5, native_ref_spp=32,
                   native_static_ref_spp=64)


# ----------------------------------------------------------------------------------------------
# measurement helpers


def _post(radiance) -> tuple[np.ndarray, float]:
    t0 = _time.perf_counter()
    img = postprocess(radiance)
    return img, (_time.perf_counter() - t0) * 1e3


def _med(xs) -> float:
    return float(np.median(xs)) if len(xs) else float("nan")


def _row(label: str, kind: str, psnrs, ssims, render_ms, reuse_ms, post_ms, **extra) -> dict:
    r = dict(label=label, kind=kind, psnr=float(np.mean(psnrs)), ssim=float(np.mean(ssims)), psnr_samples=[float(p) for p in psnrs],
             render_ms=_med(render_ms), reuse_ms=_med(reuse_ms) if reuse_ms else 0.0, post_ms=_med(post_ms))
    r["total_ms"] = r["render_ms"] + r["reuse_ms"] + r["post_ms"]
    r.update(extra)
    return r


# ----------------------------------------------------------------------------------------------
# static


def run_static(cfg: QualityConfig, cache: ReferenceCache, progress: Callable, images: dict) -> dict:
    scene = scaled_scene(load_scene(cfg.static_scene), cfg.scale)
    H, W = scene.render.height, scene.render.width
    rows = []
    with PathIntegrator(scene, threads=cfg.threads) as integ:
        integ.render(spp=1, seed=0)  # JIT, static-hit cache
        ref = cache.get(scene, cfg.static_scene, 0.0, cfg.ref_spp, integrator=integ)
        ref8 = postprocess(ref["radiance"])
        images["reference"] = ref8
        # plain n spp
        total = len(cfg.static_spp) * cfg.spp_repeats
        done = 0
        for n in cfg.static_spp:
            ps, ss, rms, pms = [], [], [], []
            for rep in range(cfg.spp_repeats):
                t0 = _time.perf_counter()
                f = integ.render(time=0.0, seed=PLAIN_SEED + 1000 * n + rep, spp=n)
                rms.append((_time.perf_counter() - t0) * 1e3)
                img, pm = _post(f.radiance)
                pms.append(pm)
                ps.append(psnr(img, ref8))
                ss.append(ssim(img, ref8))
                if rep == 0 and n in (1, 9, 8):
                    images[f"{n} spp"] = img
                done += 1
                progress(f"static: plain spp {n}", done, total)
            rows.append(_row(f"{n} spp", "plain", ps, ss, rms, [], pms, spp=n))
        if 9 not in cfg.static_spp:  # the paper's comparison image
            images["9 spp"] = postprocess(integ.render(time=0.0, seed=PLAIN_SEED + 9000, spp=9).radiance)
        # reuse
        configs = [(a, "same-pixel", False) for a in cfg.alphas] + [(a, "same-pixel", True) for a in cfg.alphas]
        if "motion" in cfg.modes:
            configs.append((max(cfg.alphas), "motion", False))
        reusers = [TemporalReuse(W, H, a, m, w) for a, m, w in configs]
        strip_alpha = min(cfg.alphas, key=lambda a: abs(a - 0.2))  # the paper's comparison
        n_frames = cfg.static_frames or math.ceil(10 / min(cfg.alphas)) + cfg.eval_frames
        checkpoints = sorted({k for k in np.unique(np.round(np.geomspace(1, n_frames, 24)).astype(int) - 1)} | set(range(n_frames - cfg.eval_frames, n_frames)))
        curve = {i: [] for i in range(len(configs))}
        curve_plain = []
        stats = {i: dict(ps=[], ss=[], reuse=[], post=[]) for i in range(len(configs))}
        render_ms, plain_post = [], []
        for step in run_sequence(integ, scene, n_frames, reusers, seed=0):
            render_ms.append(step.render_ms)
            k = step.index
            last = k >= n_frames - cfg.eval_frames
            if k in checkpoints:
                p_img, pm = _post(step.frame.radiance)
                plain_post.append(pm)
                curve_plain.append((k + 1, psnr(p_img, ref8)))
            for i, out in enumerate(step.outputs):
                stats[i]["reuse"].append(step.reuse_ms[i])
                if k in checkpoints:
                    img, pm = _post(out)
                    stats[i]["post"].append(pm)
                    curve[i].append((k + 1, psnr(img, ref8)))
                    if last:
                        stats[i]["ps"].append(curve[i][-1][1])
                        stats[i]["ss"].append(ssim(img, ref8))
                        if configs[i] == (strip_alpha, "same-pixel", False) and k == n_frames - 1:
                            images["reuse"] = img
            progress("static: 1-spp timeline through reuse", k + 1, n_frames)
    plain = [r for r in rows if r["kind"] == "plain"]
    spp_axis, psnr_axis = [r["spp"] for r in plain], [r["psnr"] for r in plain]
    ssim_axis = [r["ssim"] for r in plain]
    for i, (a, m, w) in enumerate(configs):
        s = stats[i]
        label = f"1 spp + {m} α={a:g}" + (" +warmup" if w else "")
        row = _row(label, "reuse", s["ps"], s["ss"], render_ms, s["reuse"], s["post"], alpha=a, mode=m, warmup=w,
                   frames=n_frames, predicted_spp=(2 - a) / a)
        try:
            row["equivalent_spp"], row["equivalent_spp_extrapolated"] = equivalent_spp(spp_axis, psnr_axis, row["psnr"])
        except ValueError as exc:
            row["equivalent_spp"], row["equivalent_spp_extrapolated"] = float("nan"), str(exc)
        row["ssim_equivalent_spp"] = float(2 ** np.interp(row["ssim"], ssim_axis, np.log2(spp_axis))) if np.all(np.diff(ssim_axis) > 0) else float("nan")
        rows.append(row)
    for i, row in enumerate(r for r in rows if r["kind"] == "reuse"):
        pts = curve[i]  # (frames, PSNR); the first frame within 0.5 dB of the steady state
        row["frames_to_within_0.5dB"] = next((k for k, p in pts if p >= row["psnr"] - 0.5), None)
    one = next(r for r in plain if r["spp"] == 1)
    for r in rows:
        r["gain_db_over_1spp"] = r["psnr"] - one["psnr"]
    return dict(scene=cfg.static_scene, width=W, height=H, ref_spp=cfg.ref_spp, frames=n_frames, eval_frames=cfg.eval_frames,
                rows=rows, convergence=dict(plain=curve_plain, **{reusers[i].settings.label: curve[i] for i in curve}))


# ----------------------------------------------------------------------------------------------
# dynamic


def run_dynamic(cfg: QualityConfig, cache: ReferenceCache, progress: Callable, images: dict) -> dict:
    base = scaled_scene(load_scene(cfg.dynamic_scene), cfg.scale)
    H, W = base.render.height, base.render.width
    moving_ids = np.array([i for i, o in enumerate(base.objects) if o.is_dynamic], np.int32)
    timelines = []
    configs = [(m, a, w) for m in cfg.modes for a in cfg.alphas for w in (False, True)]
    for fps in cfg.dynamic_fps:
        scene = with_fps(base, fps)
        # both timelines start early enough (in frames) for the slowest α to reach steady state, so
        # that the error at the eval times is lag, not the slow start; the scripted motion is
        # defined for t < 0 too
        eval_frames = sorted({int(round(t * fps)) for t in cfg.dynamic_eval_times})
        history = cfg.dynamic_history_frames or math.ceil(8 / min(cfg.alphas))
        start_frame = eval_frames[0] - history
        end_frame = eval_frames[-1]
        n_frames = end_frame - start_frame + 1
        reusers = [TemporalReuse(W, H, a, m, w) for m, a, w in configs]
        series = {i: dict(ps=[], ps_moving=[], ss=[], reuse=[], post=[]) for i in range(len(configs))}
        plain = dict(ps=[], ps_moving=[], ss=[], post=[])
        render_ms = []
        with PathIntegrator(scene, threads=cfg.threads) as integ:
            integ.render(spp=1, seed=0)
            refs = {}
            for j, fk in enumerate(eval_frames):
                refs[fk] = cache.get(scene, cfg.dynamic_scene, fk / fps, cfg.dynamic_ref_spp, integrator=integ)
            for step in run_sequence(integ, scene, n_frames, reusers, seed=0, start_frame=start_frame):
                fk = start_frame + step.index
                render_ms.append(step.render_ms)
                for i in range(len(configs)):
                    series[i]["reuse"].append(step.reuse_ms[i])
                if fk in refs:
                    ref8 = postprocess(refs[fk]["radiance"])
                    moving = np.isin(refs[fk]["object_id"], moving_ids) | np.isin(step.frame.object_id, moving_ids)
                    img, pm = _post(step.frame.radiance)
                    plain["post"].append(pm)
                    plain["ps"].append(psnr(img, ref8))
                    plain["ps_moving"].append(masked_psnr(img, ref8, moving))
                    plain["ss"].append(ssim(img, ref8))
                    last = fk == eval_frames[-1]
                    if last:
                        images.setdefault("dynamic", {})[f"{fps:g} fps"] = {"reference": ref8, "1 spp": img}
                    for i, out in enumerate(step.outputs):
                        img, pm = _post(out)
                        s = series[i]
                        s["post"].append(pm)
                        s["ps"].append(psnr(img, ref8))
                        s["ps_moving"].append(masked_psnr(img, ref8, moving))
                        s["ss"].append(ssim(img, ref8))
                        m, a, w = configs[i]
                        if last and a == min(cfg.alphas) and not w:
                            images["dynamic"][f"{fps:g} fps"][f"{m} α={a:g}"] = img
                progress(f"dynamic {fps:g} fps: timeline through {len(configs)} reuse settings", step.index + 1, n_frames)
        rows = [_row("1 spp", "plain", plain["ps"], plain["ss"], render_ms, [], plain["post"], psnr_moving=plain["ps_moving"])]
        for i, (m, a, w) in enumerate(configs):
            s = series[i]
            rows.append(_row(f"1 spp + {m} α={a:g}" + (" +warmup" if w else ""), "reuse", s["ps"], s["ss"], render_ms, s["reuse"],
                             s["post"], mode=m, alpha=a, warmup=w, psnr_moving=s["ps_moving"]))
        for r in rows:
            r["psnr_moving_mean"] = float(np.nanmean(r["psnr_moving"]))
        timelines.append(dict(fps=fps, start_frame=start_frame, frames=n_frames, eval_frames=eval_frames,
                              eval_times=[fk / fps for fk in eval_frames], rows=rows))
    return dict(scene=cfg.dynamic_scene, width=W, height=H, ref_spp=cfg.dynamic_ref_spp, timelines=timelines)


# ----------------------------------------------------------------------------------------------
# report


PAPER_TABLE1 = [("1 spp", 22.29, 0.61), ("1 spp + temporal reuse (α = 0.2)", 31.66, 0.79), ("9 spp", 31.67, 0.79)]


def sweep_units(cfg: QualityConfig) -> list[QualityConfig]:
    """The independent parts of a run (the static part, each dynamic timeline, the native rows): tasks with --ray."""
    units = [replace(cfg, parts=("static",))] if "static" in cfg.parts else []
    if "dynamic" in cfg.parts:
        units += [replace(cfg, parts=("dynamic",), dynamic_fps=(fps,)) for fps in cfg.dynamic_fps]
    if "native" in cfg.parts:
        units.append(replace(cfg, parts=("native",)))
    return units


def run_unit(unit: QualityConfig, cache: ReferenceCache, progress: Callable) -> tuple[dict, dict]:
    """(result parts, images) of one sweep unit."""
    out, images = {}, {}
    if "static" in unit.parts:
        out["static"] = run_static(unit, cache, progress, images)
    if "dynamic" in unit.parts:
        out["dynamic"] = run_dynamic(unit, cache, progress, images)
    if "native" in unit.parts:
        from dpmhw.benchmarks.native_quality import run_native

        out["native"] = run_native(unit, cache, progress, images)
    return out, images


# runs sweep units: (units, reference cache, progress) → ((result parts, images) per unit, in their
# order; CPU seconds the units took outside this process)
UnitRunner = Callable[[list[QualityConfig], ReferenceCache, Callable], tuple[list[tuple[dict, dict]], float]]


def run_units_here(units: list[QualityConfig], cache: ReferenceCache, progress: Callable) -> tuple[list[tuple[dict, dict]], float]:
    """The default UnitRunner: every unit in this process, one after another."""
    return [run_unit(u, cache, progress) for u in units], 0.0


def run_quality(cfg: QualityConfig, cache_dir: Path | None = None, out_dir: Path | None = None, progress: Callable | None = None,
                pool=None, run_units: UnitRunner | None = None) -> dict:
    """`pool`: a dpmhw.cluster RayPool; references then render on it as blocks of passes.
    `run_units`: where the sweep units run (default: here); `dpmhw.benchmarks.quality_ray.run_units_on_ray`
    runs them as Ray tasks (their ms are the workers', their CPU seconds reported as ray_units)."""
    progress = progress or (lambda desc, done, total: None)
    cache = ReferenceCache(cache_dir, threads=cfg.threads, progress=progress, pool=pool)
    started, cpu_started = _time.perf_counter(), _time.process_time()
    load0 = os.getloadavg()
    images: dict = {}
    result = dict(config=asdict(cfg), dpmhw=__version__, renderer=cache.renderer,
                  machine=machine_info(),
                  metrics="PSNR on uint8 sRGB (exposure 1, clip), all channels; SSIM Wang et al. 2004 on Rec.601 luma, 11×11 Gaussian σ=1.5, K1=0.01, K2=0.03, data range 255",
                  paper_table1=[dict(label=l, psnr=p, ssim=s) for l, p, s in PAPER_TABLE1])
    outcomes, units_cpu = (run_units or run_units_here)(sweep_units(cfg), cache, progress)
    for out, imgs in outcomes:  # the dynamic timelines come back one unit each
        if "dynamic" in out and "dynamic" in result:
            result["dynamic"]["timelines"] += out.pop("dynamic")["timelines"]
        result.update(out)
        for name, img in imgs.items():
            if name == "dynamic":
                images.setdefault("dynamic", {}).update(img)
            else:
                images[name] = img
    result["references"] = dict(cache_dir=str(cache.dir), rendered=cache.rendered, cache_hits=cache.hits)
    # CPU time: on Ray the work is in worker processes, which this process's own CPU time (and
    # /usr/bin/time of the command) does not include; the workers measure theirs
    result["cpu_seconds"] = dict(this_process=round(_time.process_time() - cpu_started, 3))
    if pool is not None:
        result["ray"] = dict(address=pool.address or "local", cpus=pool.cpus)
        result["cpu_seconds"]["ray_references"] = round(cache.cpu_seconds, 3)
    if run_units is not None:
        result["cpu_seconds"]["ray_units"] = round(units_cpu, 3)
    result["seconds"] = round(_time.perf_counter() - started, 1)
    result["loadavg_start_end"] = [list(load0), list(os.getloadavg())]
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        result["files"] = write_figures(result, images, out_dir)
    return result


def write_figures(result: dict, images: dict, out_dir: Path) -> list[str]:
    from dpmhw.postprocess import write_png

    files = []
    if "static" in result:
        names = ["reference", "1 spp", "reuse", "9 spp"]  # reuse: same-pixel at the α nearest 0.2
        labels = {"reuse": "1 spp + reuse α≈0.2"}
        strip = np.concatenate([labelled(images[n], labels.get(n, n)) for n in names if n in images], axis=1)
        write_png(out_dir / "static_strip.png", strip)
        files.append(str(out_dir / "static_strip.png"))
    for fps_label, imgs in images.get("dynamic", {}).items():
        ref = imgs["reference"].astype(np.int16)
        tiles = [labelled(im, name) for name, im in imgs.items()]
        errs = [labelled(np.clip(np.abs(im.astype(np.int16) - ref) * 4, 0, 255).astype(np.uint8), f"|error| × 4: {name}")
                for name, im in list(imgs.items())[1:]]
        grid = np.concatenate([np.concatenate(tiles, axis=1), np.concatenate([np.zeros_like(tiles[0])] + errs, axis=1)], axis=0)
        p = out_dir / f"dynamic_strip_{fps_label.replace(' ', '')}.png"
        write_png(p, grid)
        files.append(str(p))
    for key, imgs in images.items():
        if key.startswith("native "):
            names = ["reference", "1 spp + off", "native + reuse 0.2 + lobe", "1/4 + reuse 0.2 + off", "1/4 + reuse 0.2 + lobe"]
            p = out_dir / f"{key.replace(' ', '_')}_strip.png"
            write_png(p, np.concatenate([labelled(imgs[n], n) for n in names if n in imgs], axis=1))
            files.append(str(p))
    if "static" in result or "dynamic" in result:
        files += _plots(result, out_dir)
    if "native" in result:
        from dpmhw.benchmarks.native_quality import glossy_crops, native_plot

        files.append(native_plot(result, out_dir))
        files += glossy_crops(images, out_dir)
    return files


def _plots(result: dict, out_dir: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    fig, ax = plt.subplots(figsize=(8, 5.5))
    if "static" in result:
        rows = result["static"]["rows"]
        plain = [r for r in rows if r["kind"] == "plain"]
        ax.plot([r["total_ms"] for r in plain], [r["psnr"] for r in plain], "o-", color="k", label="static: plain n spp")
        for r in plain:
            ax.annotate(f"{r['spp']}", (r["total_ms"], r["psnr"]), textcoords="offset points", xytext=(4, -10), fontsize=7)
        for r in rows:
            if r["kind"] == "reuse":
                ax.plot(r["total_ms"], r["psnr"], "s" if not r["warmup"] else "D", label=f"static: {r['label']}")
    for tl in result.get("dynamic", {}).get("timelines", []):
        for r in tl["rows"]:
            if r["kind"] == "plain" or (r["alpha"] == 0.1 and not r["warmup"]):
                ax.plot(r["total_ms"], r["psnr"], "^" if tl["fps"] > 100 else "v", label=f"dynamic {tl['fps']:g} fps: {r['label']}")
    ax.set_xscale("log")
    ax.set_xlabel("ms per frame (render + reuse + post, medians; shared 2-core CPU)")
    ax.set_ylabel("PSNR (dB) against the reference")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6, loc="lower right")
    files.append(save_figure(fig, out_dir / "speed_vs_psnr.png"))
    if "static" in result:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for label, pts in result["static"]["convergence"].items():
            if pts:
                k, p = zip(*pts)
                ax.plot(k, p, "--" if "warmup" in label else "-", label=label)
        ax.set_xscale("log")
        ax.set_xlabel("frames since start")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title("static scene: convergence of reuse, with and without warm-up")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
        files.append(save_figure(fig, out_dir / "static_convergence.png"))
    tls = result.get("dynamic", {}).get("timelines", [])
    if tls:
        fig, axes = plt.subplots(1, len(tls), figsize=(6 * len(tls), 4.5), squeeze=False)
        for ax, tl in zip(axes[0], tls):
            for r in tl["rows"]:
                if r["kind"] == "plain" or not r["warmup"]:
                    ax.plot(tl["eval_times"], r["psnr_moving"], "o-" if r["kind"] == "plain" else ("-" if r["mode"] == "motion" else "--"), label=r["label"])
            ax.set_title(f"paper-dynamic, {tl['fps']:g} fps: PSNR on the moving bunnies")
            ax.set_xlabel("time (s)")
            ax.set_ylabel("PSNR (dB)")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=6)
        files.append(save_figure(fig, out_dir / "dynamic_psnr_over_time.png"))
    return files


def format_table(result: dict) -> str:
    lines = []
    if "static" in result:
        s = result["static"]
        lines.append(f"static: {s['scene']} {s['width']}×{s['height']}, reference {s['ref_spp']} spp, reuse after {s['frames']} frames "
                     f"(metrics: mean of the last {s['eval_frames']})")
        lines.append(f"{'configuration':34s} {'PSNR':>7s} {'ΔdB':>6s} {'SSIM':>6s} {'eq.spp':>7s} {'pred.':>6s} {'render':>8s} {'reuse':>7s} {'post':>6s} {'total':>8s}")
        for r in s["rows"]:
            eq = f"{r['equivalent_spp']:7.1f}" + ("*" if r.get("equivalent_spp_extrapolated") is True else " ") if "equivalent_spp" in r else " " * 8
            pred = f"{r['predicted_spp']:6.0f}" if "predicted_spp" in r else " " * 6
            lines.append(f"{r['label']:34s} {r['psnr']:7.2f} {r['gain_db_over_1spp']:6.2f} {r['ssim']:6.3f} {eq}{pred} "
                         f"{r['render_ms']:8.1f} {r['reuse_ms']:7.2f} {r['post_ms']:6.1f} {r['total_ms']:8.1f}")
        lines.append("  (ms per frame, medians; * = extrapolated beyond the measured spp curve)")
        lines.append("frames from the start until within 0.5 dB of the steady state: "
                     + ", ".join(f"{r['label'].replace('1 spp + ', '')}: {r['frames_to_within_0.5dB']}" for r in s["rows"] if r["kind"] == "reuse"))
        lines.append("paper Table 1 (1024×768, 1000-spp reference): " + "; ".join(f"{l}: {p} dB / {q}" for l, p, q in PAPER_TABLE1))
        lines.append("")
    for tl in result.get("dynamic", {}).get("timelines", []):
        d = result["dynamic"]
        lines.append(f"dynamic: {d['scene']} {d['width']}×{d['height']} at {tl['fps']:g} fps, frames {tl['start_frame']}…"
                     f"{tl['start_frame'] + tl['frames'] - 1}, references ({d['ref_spp']} spp) at t = "
                     + ", ".join(f"{t:.3f}" for t in tl["eval_times"]) + " s")
        lines.append(f"{'configuration':34s} {'PSNR per eval time (whole image)':>34s} {'moving':>7s} {'SSIM':>6s} {'reuse':>7s} {'total':>8s}")
        for r in tl["rows"]:
            per = " ".join(f"{p:6.2f}" for p in r["psnr_samples"])
            lines.append(f"{r['label']:34s} {per:>34s} {r['psnr_moving_mean']:7.2f} {r['ssim']:6.3f} {r['reuse_ms']:7.2f} {r['total_ms']:8.1f}")
        lines.append("")
    if "native" in result:
        from dpmhw.benchmarks.native_quality import format_native

        lines += format_native(result)
    lines.append(f"references: {result['references']['rendered']} rendered, {result['references']['cache_hits']} from cache "
                 f"({result['references']['cache_dir']}); {result['seconds']} s, CPU "
                 + " + ".join(f"{v:.1f} s {k.replace('_', ' ')}" for k, v in result["cpu_seconds"].items())
                 + "; load average start/end "
                 f"{result['loadavg_start_end'][0][0]:.1f}/{result['loadavg_start_end'][1][0]:.1f}")
    return "\n".join(lines)
