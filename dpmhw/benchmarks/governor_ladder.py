"""What each level of the quality governor's ladder costs and what it loses, on one scene at its
native size through the session's own `ReconstructStage`.

    python -m dpmhw.benchmarks.governor_ladder [--scene dpm-bunny] [--reps 3] [--json PATH]

Level 0 is the session's default configuration; level k applies the ladder's first k rungs
(`dpmhw.session.governor.LADDER`; rungs that change nothing here, such as the LOD budget while
no tile refiner runs, are skipped). Every level runs the same 60 fps timeline (frames 6…30,
frame k: seed k, one shared render per frame), levels interleaved in a rotating order, each with
its own stage. Per level: CPU time (`time.process_time`, all threads) of the shared render plus
its stage, median over the frames after the first two of every repetition; PSNR over the frame
and inside the mesh objects at t = 0.3 and 0.5 s against the 64-spp native references of
`dpmhw bench lod` (deterministic).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from dpmhw.benchmarks.lod import FPS, _Pipeline
from dpmhw.benchmarks.references import REFERENCE_SEED, ReferenceCache
from dpmhw.machine import machine_info
from dpmhw.metrics import masked_psnr, psnr
from dpmhw.postprocess import postprocess
from dpmhw.reconstruct.adaptive import AdaptiveSampler
from dpmhw.reconstruct.stage import ReconstructStage
from dpmhw.scene_file import load_scene
from dpmhw.sequence import with_fps
from dpmhw.session.config import load_session_config
from dpmhw.session.governor import Governor

EVAL_K = (18, 30)  # t = 0.3 and 0.5 s
FRAMES = range(6, 31)


def ladder_levels() -> list[dict]:
    """The settings of each level the default session can take (level 0 first)."""
    cfg = load_session_config()
    gov = Governor(cfg.governor, refresh_hz=60.0, clock=lambda: 0, inert=frozenset({"lod_rays"}))
    settings = cfg.live_settings()
    gov.observe(0, 0.0, {}, settings, ())  # takes the configured values as its base
    return [dict(level=k, rung=gov.rung_name(k), **gov.choices(k), reuse_mode=settings.reuse_mode, alpha=settings.alpha)
            for k in gov.levels()]


def run(scene_name: str = "dpm-bunny", reps: int = 3) -> dict:
    return dict(rows=measure(scene_name, ladder_levels(), reps), machine=machine_info())


def measure(scene_name: str, configs: list[dict], reps: int = 1, frames: range = FRAMES, eval_k: tuple[int, ...] = EVAL_K,
            shading_scale: float = 0.25) -> list[dict]:
    """CPU-ms and PSNR (over the frame, inside the mesh objects) of each configuration in
    `configs` (dicts with `level`, `filter`, `adaptive_rays`, `reuse_mode`, `alpha`; every `level`
    distinct) on the timeline `frames` of the module doc, PSNR at the frames `eval_k` (in `frames`)."""
    native = with_fps(load_scene(scene_name), FPS)
    W, H = native.render.width, native.render.height
    meshes = [i for i, o in enumerate(native.objects) if o.shape == "mesh"]
    full = _Pipeline(native, 1.0, 2)
    try:
        refs = {k: ReferenceCache(None, threads=2).get(native, scene_name, k / FPS, 64, REFERENCE_SEED,
                                                       integrator=full.integrator) for k in eval_k}
    finally:
        full.close()
    runs = list(configs)
    stats = {r["level"]: dict(cpu=[], obj=[], psnr=[]) for r in runs}
    p = _Pipeline(native, shading_scale, 2)
    try:
        for rep in range(reps):
            stages = {r["level"]: ReconstructStage(
                (W, H), (p.integrator.width, p.integrator.height), background=native.render.background,
                viewer=native.viewer_position, gbuffer=p.gbuffer, adaptive=AdaptiveSampler(p.integrator, p.gbuffer, r["adaptive_rays"]))
                for r in runs}
            for i, k in enumerate(frames):
                poses = native.object_poses(k / FPS)
                c0 = time.process_time()
                frame = p.integrator.render(time=k / FPS, seed=k, spp=1, poses=poses)
                render_ms = (time.process_time() - c0) * 1e3
                for r in runs[i % len(runs):] + runs[:i % len(runs)]:
                    c0 = time.process_time()
                    out = stages[r["level"]].apply(frame, mode=r["reuse_mode"], alpha=r["alpha"], filter=r["filter"],
                                                   poses=poses, camera=p.integrator.camera)
                    s = stats[r["level"]]
                    if i > 1:
                        s["cpu"].append(render_ms + (time.process_time() - c0) * 1e3)
                    if k in refs and rep == 0:
                        ref8 = postprocess(refs[k]["radiance"])
                        s["obj"].append(masked_psnr(out.image, ref8, np.isin(refs[k]["object_id"], meshes)))
                        s["psnr"].append(psnr(out.image, ref8))
            for st in stages.values():
                st.close()
    finally:
        p.close()
    rows = []
    for r in runs:
        s = stats[r["level"]]
        rows.append(dict(r, scene=scene_name, width=W, height=H, cpu_ms=float(np.median(s["cpu"])),
                         psnr_db=float(np.mean(s["psnr"])), psnr_db_object=float(np.mean(s["obj"]))))
    for row in rows:
        row["cpu_vs_level0"] = row["cpu_ms"] / rows[0]["cpu_ms"]
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="dpm-bunny")
    ap.add_argument("--reps", type=int, default=3, choices=range(1, 101), metavar="1…100")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    result = run(args.scene, args.reps)
    for r in result["rows"]:
        print(f"level {r['level']} {r['rung']:<45} {r['cpu_ms']:6.1f} CPU-ms ({r['cpu_vs_level0']:.3f}×)  "
              f"PSNR {r['psnr_db']:.2f} dB, objects {r['psnr_db_object']:.2f} dB")
    print(json.dumps(result["machine"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
