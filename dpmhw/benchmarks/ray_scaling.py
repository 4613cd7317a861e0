"""`dpmhw bench ray-scaling`: how a render's wall time falls with Ray workers on this machine.

Each repeat renders the same frame (same seed, so the same image: checked) in process with 1
and 2 threads, and on a fresh local Ray instance of 1 and 2 CPUs with one single-threaded worker
per CPU: once cold (worker processes start, import, load kernels, build the BVH) and once warm
(the same pool again). The configurations alternate within each repeat, so a shared machine's
load drifts over all of them alike; the table gives medians. Beside wall time it gives the CPU
seconds the blocks took (summed over workers): on a busy machine wall time says how much CPU the
others left over, while CPU per pass says what running on Ray costs, which is what carries over
to a lab's idle machines.
"""

from __future__ import annotations

import os
import time as _time
from typing import Callable

import numpy as np

from dpmhw.cluster.passes import render_local
from dpmhw.cluster.ray_pool import RayPool, render_on_ray


def run_scaling(scene_name: str = "paper-static", scale: float = 0.5, spp: int = 64, seed: int = 0, workers=(1, 2),
                repeats: int = 3, progress: Callable[[str, int, int], None] | None = None) -> dict:
    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.scene_file import load_scene
    from dpmhw.sequence import scaled_scene

    scene = scaled_scene(load_scene(scene_name), scale)
    progress = progress or (lambda desc, done, total: None)
    configs = [("in-process", w) for w in workers] + [("ray", w) for w in workers]
    rows, first = [], []
    steps, done = repeats * len(configs), 0
    load_start = os.getloadavg()

    def record(kind, n, run, rep, seconds, summed, **extra):
        if not first:  # every other render must give this image, bit for bit
            first.append(summed.radiance)
        rows.append(dict(kind=kind, workers=n, run=run, repeat=rep, seconds=seconds, passes_per_s=spp / seconds,
                         cpu_s_per_pass=sum(summed.block_cpu_seconds) / summed.spp,
                         identical_image=bool(np.array_equal(summed.radiance, first[0])), **extra))

    for rep in range(repeats):
        for kind, n in configs:
            if kind == "in-process":
                with PathIntegrator(scene, threads=n) as integ:
                    integ.render(spp=1, seed=seed + 1)  # kernels loaded, static hits cached: warm
                    t0 = _time.perf_counter()
                    summed = render_local(integ, 0.0, seed, spp)
                    record(kind, n, "warm", rep, _time.perf_counter() - t0, summed)
            else:
                t0 = _time.perf_counter()
                with RayPool(local_cpus=n) as pool:
                    startup = _time.perf_counter() - t0
                    for run in ("cold", "warm"):
                        t0 = _time.perf_counter()
                        summed = render_on_ray(pool, scene, 0.0, seed, spp, threads=1)
                        record(kind, n, run, rep, _time.perf_counter() - t0, summed, ray_start_s=startup)
            done += 1
            progress(f"{kind} × {n}", done, steps)
    summary = []
    for kind, n in configs:
        for run in ("cold", "warm"):
            mine = [r for r in rows if (r["kind"], r["workers"], r["run"]) == (kind, n, run)]
            if mine:
                times = [r["seconds"] for r in mine]
                summary.append(dict(kind=kind, workers=n, run=run, seconds_median=float(np.median(times)),
                                    seconds_min=float(np.min(times)), seconds_max=float(np.max(times)),
                                    passes_per_s=spp / float(np.median(times)), repeats=len(times),
                                    cpu_s_per_pass_median=float(np.median([r["cpu_s_per_pass"] for r in mine]))))
    for s in summary:
        base = next(b for b in summary if (b["kind"], b["run"], b["workers"]) == (s["kind"], s["run"], min(workers)))
        s["speedup"] = base["seconds_median"] / s["seconds_median"]
    r = scene.render
    return dict(scene=scene_name, width=r.width, height=r.height, spp=spp, seed=seed, repeats=repeats, cpus=os.cpu_count(),
                loadavg_start_end=[list(load_start), list(os.getloadavg())], rows=rows, summary=summary)


def format_table(result: dict) -> str:
    lines = [f"{result['scene']} {result['width']}×{result['height']}, {result['spp']} spp, medians of {result['repeats']} "
             f"alternated repeats on {result['cpus']} CPUs (load average {result['loadavg_start_end'][0][0]:.1f} → "
             f"{result['loadavg_start_end'][1][0]:.1f})",
             f"{'':12s} {'workers':>7s} {'run':>5s} {'s (median)':>10s} {'range':>15s} {'passes/s':>9s} {'speed-up':>8s} "
             f"{'CPU s/pass':>10s}"]
    for s in result["summary"]:
        lines.append(f"{s['kind']:12s} {s['workers']:7d} {s['run']:>5s} {s['seconds_median']:10.2f} "
                     f"{s['seconds_min']:6.2f}–{s['seconds_max']:<8.2f} {s['passes_per_s']:9.2f} {s['speedup']:8.2f} "
                     f"{s['cpu_s_per_pass_median']:10.3f}")
    lines.append("in-process: threads of one integrator; ray: single-threaded workers, cold = first render on a fresh "
                 "local instance (worker start-up included), warm = the next render")
    lines.append("every image identical: " + str(all(r["identical_image"] for r in result["rows"])))
    return "\n".join(lines)


def plot(result: dict, path) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.2))
    for kind, run, style in (("in-process", "warm", "o-"), ("ray", "warm", "s-"), ("ray", "cold", "s--")):
        pts = [(s["workers"], s["passes_per_s"]) for s in result["summary"] if (s["kind"], s["run"]) == (kind, run)]
        if pts:
            ax.plot(*zip(*pts), style, label=f"{kind} ({run})" if kind == "ray" else f"{kind} (threads)")
    ax.set_xlabel("workers (Ray) / threads (in process)")
    ax.set_ylabel("passes per second (median)")
    ax.set_title(f"{result['scene']} {result['width']}×{result['height']}, {result['spp']} spp; shared 2-core machine")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return str(path)
