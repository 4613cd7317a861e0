"""`dpmhw bench reproject`: late reprojection's cost, and its error against fresh renders.

The bound objects move as the mock world moves them (`session.factory.mock_trajectory`,
rotate-oscillate by default: what `dpmhw bench session --trajectory rotate-oscillate` tracks).
At each start time the scene is path traced at its native size with `spp` samples and captured
(`reconstruct.reproject.Reprojector`); for each horizon h the capture is moved to the poses at
start + h and compared with a fresh render there (same spp, another seed) inside the fresh
render's moving-object mask: PSNR and SSIM (`metrics.masked_psnr`, `metrics.masked_ssim`). Beside
them, per row: the stale capture shown as it is (no reprojection), and a second render at the
start pose (`*_noise`: the references' own noise, the best any reprojection can score).

Cost: CPU-ms (the calling thread's, plus the reprojector's helper thread's with
`present_threads` 2) per capture of the lit box (`ms_capture`, the frame thread's share), per
video present (`ms_per_reprojection`: all three channels) and per pattern-mode present: three
one-channel windows into one frame in one call, each moved to its own poses a sub-frame apart
(`SUBFRAME_MS`, centred on the horizon), as the loop predicts them (`ms_per_present_pattern`;
`ms_wall_per_present_pattern` its wall time, which a helper thread shortens). Both present as
the loop does, into the reprojector's own frames in turn (`Reprojector.present`: only the boxes
that changed are copied from the capture); medians of `repeats`, and `*_min` the least of them
(on a shared machine: the repeat the other processes disturbed least).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from dpmhw.metrics import masked_psnr, masked_ssim
from dpmhw.postprocess import to_srgb8
from dpmhw.reconstruct.reproject import Reprojector
from dpmhw.scene_file import load_scene
from dpmhw.transforms import Pose

TRAJECTORIES = ("rotate-oscillate", "linear", "static")  # session.factory.mock_trajectory's
SUBFRAME_MS = 1000.0 / 180.0  # pattern-8bit's photon windows at a 60 Hz link: a third of the period apart (display.py)


@dataclass(frozen=True)
class ReprojectBenchConfig:
    scene: str = "dpm-bunny"
    size: tuple[int, int] | None = None  # (W, H); None: the scene's
    spp: int = 32
    starts_s: tuple[float, ...] = (0.3, 0.8, 1.4)
    horizons_ms: tuple[float, ...] = (5.0, 10.0, 20.0, 40.0)
    trajectory: str = "rotate-oscillate"
    speed: float = 1.0
    repeats: int = 30
    threads: int = 2
    present_threads: int = 1  # the Reprojector's (2: a helper thread shares a pattern present's splats)

    def __post_init__(self):
        if self.trajectory not in TRAJECTORIES:
            raise ValueError(f"trajectory: expected one of {', '.join(TRAJECTORIES)}, got {self.trajectory!r}")
        if self.present_threads not in (1, 2):
            raise ValueError(f"present_threads: expected 1 or 2, got {self.present_threads}")
        if self.spp < 1 or self.repeats < 1 or not self.starts_s or not self.horizons_ms:
            raise ValueError("spp and repeats must be ≥ 1, starts and horizons non-empty")
        if not all(np.isfinite(v) and v >= 0 for v in (*self.starts_s, *self.horizons_ms)):
            raise ValueError("starts_s, horizons_ms: expected finite values ≥ 0")


def _cost_ms(repeats: int, helped: Reprojector | None, fn, *args) -> tuple[float, float, float]:
    """(median, least) CPU-ms per call fn(*args) of the calling thread, plus the helper thread's
    of `helped` (a reprojector whose present fn makes), and the median wall ms; on a shared
    machine the least is the call the other processes disturbed least."""
    fn(*args)
    cpu, wall = [], []
    for _ in range(repeats):
        w0, t0 = time.perf_counter(), time.thread_time()
        fn(*args)
        cpu.append(time.thread_time() - t0 + (helped.last_helper_cpu_ns / 1e9 if helped is not None else 0.0))
        wall.append(time.perf_counter() - w0)
    return 1e3 * float(np.median(cpu)), 1e3 * float(np.min(cpu)), 1e3 * float(np.median(wall))


def _present(reprojector: Reprojector, cap, window_poses) -> None:
    """A present as the loop makes it, into the reprojector's own frames: one window of all
    channels (video), or three one-channel windows, each at its own poses (pattern-8bit)."""
    reprojector.present(cap, [(window_poses[0], None)] if len(window_poses) == 1 else
                        [(poses, k) for k, poses in enumerate(window_poses)])


def run_reproject(cfg: ReprojectBenchConfig, progress=None) -> list[dict]:
    """One flat row per (start, horizon); see the module docstring."""
    from dpmhw.render.integrator import PathIntegrator
    from dpmhw.session.factory import mock_trajectory

    scene = load_scene(cfg.scene)
    if cfg.size is not None:
        scene = scene.at_size(*cfg.size)
    W, H = scene.render.width, scene.render.height
    moving = [i for i, o in enumerate(scene.objects) if o.is_dynamic]
    paths = {i: mock_trajectory(cfg.trajectory, scene.objects[i].pose.t, cfg.speed) for i in moving}

    def poses_at(t: float) -> list[Pose]:
        poses = scene.object_poses(0.0)
        for i, path in paths.items():
            rot, pos = path.pose_floats(t)
            poses[i] = Pose(np.array(rot).reshape(3, 3), np.array(pos))
        return poses

    rows = []
    total, done = len(cfg.starts_s) * (len(cfg.horizons_ms) + 2), 0
    with PathIntegrator(scene, threads=cfg.threads) as renderer:
        reprojector = Reprojector(renderer.camera, [o.is_dynamic for o in scene.objects], cfg.present_threads)
        seed = 0

        def render(t: float):
            nonlocal seed, done
            seed += 1
            f = renderer.render(poses=poses_at(t), spp=cfg.spp, seed=seed)
            done += 1
            if progress is not None:
                progress("renders (captures, references, noise)", done, total)
            return f, to_srgb8(f.radiance)

        def objects(frame) -> np.ndarray:
            return np.isin(frame.object_id, moving)

        out = np.empty((H, W, 3), np.uint8)
        for start in cfg.starts_s:
            f0, captured = render(start)
            _, again = render(start)
            mask0 = objects(f0)
            noise = (masked_psnr(again, captured, mask0), masked_ssim(again, captured, mask0))
            ids = np.ascontiguousarray(f0.object_id, np.int32).reshape(-1)
            depth = np.ascontiguousarray(f0.depth, np.float32).reshape(-1)
            lit = f0.object_id >= 0  # the lit box, as the native G-buffer gives it
            rows_lit, cols_lit = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
            box = (int(rows_lit[0]), int(rows_lit[-1]) + 1, int(cols_lit[0]), int(cols_lit[-1]) + 1) if lit.any() else None
            # outside the box the frame equals itself: presents of this capture copy only the boxes, as the loop's
            cap = reprojector.capture(captured, ids, depth, poses_at(start), box, captured.copy().reshape(-1))
            capture_ms, capture_min, _ = _cost_ms(cfg.repeats, None, reprojector.capture, captured, ids, depth, poses_at(start), box)
            for h in cfg.horizons_ms:
                poses = poses_at(start + h / 1e3)
                fresh, reference = render(start + h / 1e3)
                mask = objects(fresh)
                st = reprojector.reproject(cap, poses, out)
                row = dict(scene=cfg.scene, width=W, height=H, spp=cfg.spp, present_threads=cfg.present_threads, trajectory=cfg.trajectory, speed=cfg.speed,
                           start_s=start, horizon_ms=h, lit=st.lit, moved=st.moved, dropped=st.dropped, holes=st.holes,
                           disoccluded=st.disoccluded, vacated=st.vacated, object_pixels=int(mask.sum()),
                           psnr_db=masked_psnr(out, reference, mask), ssim=masked_ssim(out, reference, mask),
                           psnr_db_stale=masked_psnr(captured, reference, mask),
                           ssim_stale=masked_ssim(captured, reference, mask),
                           psnr_db_noise=noise[0], ssim_noise=noise[1], ms_capture=capture_ms,
                           ms_capture_min=capture_min)
                row["ms_per_reprojection"], row["ms_per_reprojection_min"], _ = _cost_ms(
                    cfg.repeats, reprojector, _present, reprojector, cap, [poses])
                row["ms_per_present_pattern"], row["ms_per_present_pattern_min"], row["ms_wall_per_present_pattern"] = _cost_ms(
                    cfg.repeats, reprojector, _present, reprojector, cap,
                    [poses_at(start + (h + (k - 1) * SUBFRAME_MS) / 1e3) for k in range(3)])
                rows.append(row)
        reprojector.close()
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Medians over the start times, per horizon."""
    out = []
    for h in sorted({r["horizon_ms"] for r in rows}):
        sel = [r for r in rows if r["horizon_ms"] == h]
        out.append({"horizon_ms": h, **{k: float(np.median([r[k] for r in sel])) for k in (
            "ms_capture", "ms_per_reprojection", "ms_per_present_pattern", "ms_per_present_pattern_min",
            "ms_wall_per_present_pattern", "lit", "holes",
            "disoccluded", "vacated", "psnr_db", "ssim", "psnr_db_stale", "ssim_stale", "psnr_db_noise", "ssim_noise")}})
    return out


def format_table(rows: list[dict]) -> str:
    r0 = rows[0]
    lines = [f"scene {r0['scene']}  {r0['width']}×{r0['height']}  {r0['spp']} spp  trajectory {r0['trajectory']} ×{r0['speed']:g}  "
             f"starts {len({r['start_s'] for r in rows})}  present threads {r0['present_threads']}  (medians over the starts; CPU-ms "
             "of the present's threads: medians, and the least of the repeats; wall: median)",
             "",
             f"{'horizon':>8}{'capture':>8}{'ms/reproj':>10}{'ms/pattern':>11}{'least':>7}{'wall':>7}{'lit':>8}{'holes':>7}{'disocc':>7}{'vacated':>8}"
             f"{'PSNR':>7}{'SSIM':>7}{'stale':>7}{'SSIM':>7}{'noise':>7}{'SSIM':>7}",
             f"{'ms':>8}{'ms':>8}{'':>10}{'(3 ch)':>11}{'':>7}{'ms':>7}{'px':>8}{'':>7}{'':>7}{'':>8}{'dB':>7}{'':>7}{'dB':>7}{'':>7}{'dB':>7}{'':>7}"]
    for s in summary(rows):
        lines.append(f"{s['horizon_ms']:>8g}{s['ms_capture']:>8.2f}{s['ms_per_reprojection']:>10.2f}"
                     f"{s['ms_per_present_pattern']:>11.2f}{s['ms_per_present_pattern_min']:>7.2f}{s['ms_wall_per_present_pattern']:>7.2f}{s['lit']:>8.0f}"
                     f"{s['holes']:>7.0f}{s['disoccluded']:>7.0f}{s['vacated']:>8.0f}{s['psnr_db']:>7.2f}{s['ssim']:>7.3f}"
                     f"{s['psnr_db_stale']:>7.2f}{s['ssim_stale']:>7.3f}{s['psnr_db_noise']:>7.2f}{s['ssim_noise']:>7.3f}")
    return "\n".join(lines)


__all__ = ["ReprojectBenchConfig", "format_table", "run_reproject", "summary"]
