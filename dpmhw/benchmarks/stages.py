"""`dpmhw bench stages`: the session's reconstruction stage alone, per sub-stage, on a moving pose sequence.

The stage is the session's own (`session.factory.build_renderer` + `session.loop.reconstruct_stage`
from a default config: ¼ shading, native G-buffer, analytic demodulation, lobe filter, motion
reuse, adaptive sampling); the bound objects follow the mock's trajectory (`session.factory
.mock_trajectory`, rotate-oscillate by default) on a 60 fps timeline, every frame moving. Each
frame is rendered (its render timed on its own: render_ms, render_cpu_ms), then
`ReconstructStage.apply` is timed: wall ms, CPU ms (`time.process_time`: every thread of the
process, so the helper thread and the kernels' threads count) and the stage's own sub-stage
seconds (gbuffer, reuse, filter, upsample, adaptive, post; the shading branch (reuse, filter)
runs beside the G-buffer, so they overlap). loop_cpu_ms = render + stage CPU: the loop's
per-frame work without its pipelining, prediction and present. The first `warmup` frames
(history fill, cache loads) are not counted.

`digest`: sha256 over every frame's output image, the three reuse histories and the native
G-buffer's id/depth/normal, and separately over the rendered inputs, so that two code versions
built for the same CPU target can be compared bit for bit.

Which vector ISA the kernels run is the process's: numba reads `NUMBA_CPU_NAME` /
`NUMBA_CPU_FEATURES` at import, Embree `DPMHW_EMBREE_ISA` (docs/first-run.md); compare builds
by alternating processes.
"""

from __future__ import annotations

import hashlib
import time

import numpy as np

STAGES = ("gbuffer", "reuse", "filter", "upsample", "adaptive", "post")
FPS = 60.0


def _poses(scene, trajectories, t: float):
    """The scene's poses at t, the bound objects' from their trajectories."""
    from dpmhw.transforms import Pose

    poses = scene.object_poses(t)
    for index, traj in trajectories.items():
        R, p = traj.pose(t)
        poses[index] = Pose(np.asarray(R, float), np.asarray(p, float))
    return poses


def run_stages(scene: str = "dpm-bunny", frames: int = 60, warmup: int = 8, trajectory: str = "rotate-oscillate",
               digest: bool = False) -> dict:
    """Per-frame rows and per-stage medians; see the module doc."""
    from dpmhw.session.config import load_session_config
    from dpmhw.session.factory import build_renderer, mock_trajectory, prepare_scene, resolve_bindings
    from dpmhw.session.loop import reconstruct_stage

    config = load_session_config(None, {"scene": {"source": scene}, "mock": {"trajectory": trajectory}})
    sc = prepare_scene(config)
    trajs = {i: mock_trajectory(config.mock.trajectory, sc.objects[i].pose.t, config.mock.speed)
             for i in resolve_bindings(config, sc)}
    renderer, gbuffer = build_renderer(config, sc)
    stage = None
    out_h, in_h = hashlib.sha256(), hashlib.sha256()
    rows = []
    try:
        stage = reconstruct_stage(config, sc, renderer, gbuffer, time.monotonic_ns)
        for k in range(warmup + frames):
            t = k / FPS
            poses = _poses(sc, trajs, t)
            r0, rc0 = time.perf_counter(), time.process_time()
            frame = renderer.render(time=t, seed=config.render.seed + k, spp=config.render.spp, poses=poses)
            w0, c0 = time.perf_counter(), time.process_time()
            out = stage.apply(frame, mode=config.reuse.mode, alpha=config.reuse.alpha, filter=config.render.filter,
                              exposure=config.render.exposure, poses=poses, camera=renderer.camera)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            if digest:
                for a in (frame.radiance, frame.diffuse, frame.specular, frame.object_id, frame.model_position):
                    in_h.update(np.ascontiguousarray(a).tobytes())
                for a in (out.image, stage.reuse_d.history, stage.reuse_s.history, stage.reuse_d.history_length,
                          gbuffer.id, gbuffer.depth, gbuffer.normal):
                    out_h.update(np.ascontiguousarray(a).tobytes())
            if k >= warmup:
                rows.append({"frame": k, "wall_ms": wall * 1e3, "cpu_ms": cpu * 1e3, "render_ms": (w0 - r0) * 1e3,
                             "render_cpu_ms": (c0 - rc0) * 1e3, "loop_cpu_ms": (cpu + c0 - rc0) * 1e3,
                             **{f"{s}_ms": out.stages_s.get(s, 0.0) * 1e3 for s in STAGES}})
    finally:
        if stage is not None:
            stage.close()
        if gbuffer is not None:
            gbuffer.close()
        renderer.close()
    keys = ["wall_ms", "cpu_ms"] + [f"{s}_ms" for s in STAGES] + ["render_ms", "render_cpu_ms", "loop_cpu_ms"]
    medians = {key: float(np.median([r[key] for r in rows])) for key in keys}
    result = {"scene": scene, "size": f"{sc.render.width}x{sc.render.height}", "shading": f"{renderer.width}x{renderer.height}",
              "trajectory": trajectory, "frames": frames, "medians": medians, "rows": rows}
    if digest:
        result["digest_out"], result["digest_in"] = out_h.hexdigest()[:16], in_h.hexdigest()[:16]
    return result


def format_table(result: dict) -> str:
    m = result["medians"]
    head = (f"{result['scene']} {result['size']} (shading {result['shading']}), {result['trajectory']}, "
            f"medians of {result['frames']} frames")
    lines = [head, " ".join(f"{k[:-3]:>10}" for k in m), " ".join(f"{v:10.2f}" for v in m.values())]
    if "digest_out" in result:
        lines.append(f"digest: out {result['digest_out']}  in {result['digest_in']}")
    return "\n".join(lines)
