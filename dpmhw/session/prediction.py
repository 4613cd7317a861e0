"""Pose prediction: extrapolate each rigid body to the instant its frame will be on the object.

A tracker sample describes the body at mid-exposure; by the time the frame rendered from it is
lit, the body has moved on for the whole motion-to-photon latency. The predictor assumes
constant linear and angular velocity over that horizon (on SE(3): translation moves along a
line, rotation turns about a fixed world axis at a fixed rate), estimated from the last few
valid samples:

    v = least-squares slope of translation over time       ω = log(R_new · R_oldᵀ) / (t_new − t_old)
    t(t*) = t_new + v·Δ                                     R(t*) = exp(ω·Δ) · R_new,   Δ = t* − t_new

Least squares on the positions averages marker noise; the rotation rate uses the end points of
the window (noise in a rotation is smaller relative to its rate at tracker rates).

`model="acceleration"` fits a parabola to the translations instead (constant linear
acceleration; rotation keeps constant angular velocity). Over a 100 ms horizon it removes most
of the error of curved paths (the paper's oscillation turns around), but it amplifies marker
noise: at 0.2 mm marker noise it needs ~24 samples at 360 Hz to match constant velocity, at
1 mm it is worse whatever the history (see docs/session.md).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from dpmhw.tracking import PoseSample
from dpmhw.transforms import Pose, matrix_to_rotvec, rotvec_to_matrix

__all__ = ["BodyMotion", "PosePredictor", "extrapolate"]


@dataclass(frozen=True)
class BodyMotion:
    """Newest pose of one body and its estimated derivatives (world frame)."""

    pose: Pose
    t_ns: int  # host monotonic time the pose describes
    velocity: np.ndarray  # (3,) m/s at t_ns
    angular_velocity: np.ndarray  # (3,) rad/s, world frame (rotation vector rate)
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m/s², zero for "velocity"


def extrapolate(motion: BodyMotion, t_target_ns: int) -> Pose:
    """Pose at `t_target_ns` under constant angular velocity and constant linear acceleration
    (zero acceleration: constant velocity)."""
    dt = (t_target_ns - motion.t_ns) * 1e-9
    R = rotvec_to_matrix(motion.angular_velocity * dt) @ motion.pose.R
    return Pose(R, motion.pose.t + motion.velocity * dt + 0.5 * motion.acceleration * dt * dt)


def estimate_motion(samples: list[PoseSample], model: str = "velocity") -> BodyMotion:
    """Derivatives from `samples` (valid, oldest first); zero velocity from a single sample."""
    newest = samples[-1]
    pose = Pose(np.array(newest.rotation), np.array(newest.translation))
    if len(samples) < 2:
        return BodyMotion(pose, newest.t_exposure_ns, np.zeros(3), np.zeros(3))
    oldest = samples[0]
    span = (newest.t_exposure_ns - oldest.t_exposure_ns) * 1e-9
    turn = matrix_to_rotvec(newest.rotation @ oldest.rotation.T)
    t = np.array([s.t_exposure_ns - newest.t_exposure_ns for s in samples], dtype=np.float64) * 1e-9
    p = np.stack([s.translation for s in samples])
    if model == "acceleration" and len(samples) >= 3:
        c = _parabola(t, span, p)
        return BodyMotion(Pose(pose.R, c[0]), newest.t_exposure_ns, c[1], turn / span, 2 * c[2])
    tc = t - t.mean()
    velocity = (tc @ (p - p.mean(axis=0))) / (tc @ tc)
    return BodyMotion(pose, newest.t_exposure_ns, velocity, turn / span)


def _parabola(t: np.ndarray, span: float, p: np.ndarray) -> np.ndarray:
    """Least-squares c (3, 3) of p(t) ≈ c0 + c1 t + c2 t² (t = 0 at the newest sample: velocity
    c1, acceleration 2 c2 there), over time scaled to the window (u = t / span ∈ [−1, 0], so the
    3×3 normal equations stay well conditioned). The present thread fits every body at every
    refresh, holding the interpreter: this costs about a third of numpy's `polyfit` for the same
    fit (29 against 81 µs for 24 samples on a Zen 3), within 1e-10 of it."""
    u = t / span
    V = np.stack([np.ones_like(u), u, u * u], axis=1)
    c = np.linalg.solve(V.T @ V, V.T @ p)
    return c / np.array([1.0, span, span * span])[:, None]


class PosePredictor:
    """Keeps the last `history` valid samples of each body and predicts poses to a target time.

    Fed from the loop (`observe` the tracker's latest sample every frame; duplicates are
    ignored), so it needs no thread of its own. `max_horizon_s` caps extrapolation: a stale
    sample is not projected far into the future (safety blanks long before that anyway).
    """

    def __init__(self, history: int = 4, max_horizon_s: float = 0.15, model: str = "velocity"):
        if history < 2:
            raise ValueError(f"prediction history must be >= 2 samples, got {history}")
        if model not in ("velocity", "acceleration"):
            raise ValueError(f"prediction model: expected 'velocity' or 'acceleration', got {model!r}")
        self.history = history
        self.model = model
        self.max_horizon_ns = int(max_horizon_s * 1e9)
        self._samples: dict[int, deque[PoseSample]] = {}

    def observe(self, sample: PoseSample) -> None:
        """Add a sample if it is valid and newer than the last one kept for its body."""
        if not sample.valid or not np.all(np.isfinite(sample.rotation)):
            return
        kept = self._samples.setdefault(sample.rigid_body_id, deque(maxlen=self.history))
        if kept and sample.t_exposure_ns <= kept[-1].t_exposure_ns:
            return
        kept.append(sample)

    def reset(self) -> None:
        """Forget every body's history (after a jump, or on operator request)."""
        self._samples.clear()

    def motion(self, rigid_body_id: int) -> BodyMotion | None:
        kept = self._samples.get(rigid_body_id)
        return estimate_motion(list(kept), self.model) if kept else None

    def predict_many(self, rigid_body_id: int, targets_ns, enabled: bool = True) -> list[tuple[Pose, int]] | None:
        """`predict` at each of `targets_ns`, the motion estimated once (a present's photon windows)."""
        kept = self._samples.get(rigid_body_id)
        if not kept:
            return None
        if not enabled:
            newest = kept[-1]
            pose = Pose(np.array(newest.rotation), np.array(newest.translation))
            return [(pose, 0) for _ in targets_ns]
        motion = estimate_motion(list(kept), self.model)
        horizons = [min(max(t - motion.t_ns, 0), self.max_horizon_ns) for t in targets_ns]
        return [(extrapolate(motion, motion.t_ns + h), h) for h in horizons]

    def predict(self, rigid_body_id: int, t_target_ns: int, enabled: bool = True) -> tuple[Pose, int] | None:
        """(pose at `t_target_ns`, horizon in ns actually used), or None with no sample yet.

        With `enabled` False the newest measured pose is returned unchanged (horizon 0), which
        is the baseline prediction is compared against.
        """
        predicted = self.predict_many(rigid_body_id, (t_target_ns,), enabled)
        return None if predicted is None else predicted[0]
