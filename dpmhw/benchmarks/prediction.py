"""`dpmhw bench prediction`: the pose predictor's error at a given horizon, with marker noise.

Offline and deterministic: the mock's trajectory (`session.factory.mock_trajectory`) is sampled at
the tracker's rate, Gaussian noise of each standard deviation is added to every position (the
tracker's marker noise; orientations stay exact), and every `every`-th sample the predictor
(`session.prediction.PosePredictor`, each model and history) predicts `horizon_ms` ahead. The
error is the distance to the true position then, in millimetres. The horizon that matters is the
one a present predicts over: tracker latency + the present's lead + the controller delay + half
a photon window (about 35 ms with late reprojection at 60 Hz, `docs/session.md`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dpmhw.session.prediction import PosePredictor
from dpmhw.tracking import PoseSample

__all__ = ["PredictionBenchConfig", "format_table", "run_prediction"]


@dataclass(frozen=True)
class PredictionBenchConfig:
    trajectory: str = "rotate-oscillate"
    horizon_ms: float = 35.0
    noise_mm: tuple[float, ...] = (0.0, 0.1, 0.2, 0.5)
    methods: tuple[tuple[str, int], ...] = (("velocity", 8), ("velocity", 16), ("acceleration", 12), ("acceleration", 24))
    rate_hz: float = 360.0
    seconds: float = 20.0
    every: int = 7  # predict at every 7th sample (prime to the trajectory's periods)
    seed: int = 1

    def __post_init__(self) -> None:
        if not 0.0 < self.horizon_ms <= 1000.0:
            raise ValueError(f"horizon_ms: expected (0, 1000], got {self.horizon_ms}")
        if any(not 0.0 <= n <= 100.0 for n in self.noise_mm):
            raise ValueError(f"noise_mm: expected values in [0, 100], got {self.noise_mm}")
        if not 1.0 <= self.rate_hz <= 10_000.0 or not 1.0 <= self.seconds <= 3600.0:
            raise ValueError(f"rate_hz in [1, 10000] and seconds in [1, 3600], got {self.rate_hz}, {self.seconds}")


def run_prediction(cfg: PredictionBenchConfig, progress=None) -> list[dict]:
    """One flat row per noise level and method: trajectory, horizon_ms, noise_mm, model, history,
    error_mm_p50, error_mm_p99, predictions."""
    from dpmhw.session.factory import mock_trajectory

    traj = mock_trajectory(cfg.trajectory, np.zeros(3), 1.0)
    t = np.arange(0.0, cfg.seconds, 1.0 / cfg.rate_hz)
    R, p = traj.pose(t)
    h_s = cfg.horizon_ms / 1e3
    ask = [i for i in range(len(t)) if i >= 64 and i % cfg.every == 0 and t[i] + h_s < t[-1]]
    truth = traj.pose(t[ask] + h_s)[1]
    rng = np.random.default_rng(cfg.seed)
    rows = []
    steps = len(cfg.noise_mm) * len(cfg.methods)
    for noise in cfg.noise_mm:
        noisy = p + rng.normal(0.0, noise * 1e-3, p.shape)
        for model, history in cfg.methods:
            if progress is not None:
                progress("bench prediction", len(rows), steps)
            predictor = PosePredictor(history, max(0.15, 2 * h_s), model)
            err = np.empty(len(ask))
            k = 0
            for i in range(len(t)):
                ns = int(round(t[i] * 1e9))
                predictor.observe(PoseSample(1, R[i], noisy[i], ns, ns, True, frame_number=i))
                if k < len(ask) and ask[k] == i:
                    pose, _ = predictor.predict(1, ns + int(round(h_s * 1e9)))
                    err[k] = np.linalg.norm(pose.t - truth[k]) * 1e3
                    k += 1
            p50, p99 = np.percentile(err, (50, 99))
            rows.append({"trajectory": cfg.trajectory, "horizon_ms": cfg.horizon_ms, "noise_mm": noise, "model": model,
                         "history": history, "error_mm_p50": round(float(p50), 4), "error_mm_p99": round(float(p99), 4),
                         "predictions": len(ask)})
    if progress is not None:
        progress("bench prediction", steps, steps)
    return rows


def format_table(rows: list[dict]) -> str:
    head = f"{'noise mm':>8} {'model':<13} {'history':>7} {'p50 mm':>8} {'p99 mm':>8}"
    lines = [f"{rows[0]['trajectory']}, {rows[0]['horizon_ms']:g} ms ahead, {rows[0]['predictions']} predictions each",
             head, "-" * len(head)] if rows else []
    for r in rows:
        lines.append(f"{r['noise_mm']:>8g} {r['model']:<13} {r['history']:>7} {r['error_mm_p50']:>8.3f} {r['error_mm_p99']:>8.3f}")
    return "\n".join(lines)
