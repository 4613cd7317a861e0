"""The plausibility gate: tracker samples that cannot describe a real object are dropped before
anything (the loop, prediction, a recording) sees them.

A tracker can hand over a pose that decodes cleanly and is still wrong: a corrupted datagram,
a marker swap, a foreign sender. Projecting it paints the picture somewhere it must not be, so
each sample of a tracked body is checked against

- its timestamps: it must not describe an instant after it arrived (more than `max_future_s`,
  which absorbs clock-mapping error) nor one more than `max_age_s` before (a corrupt stamp, or a
  device clock gone wrong);
- the workspace: its position must lie in the box [`workspace_min`, `workspace_max`] (metres,
  tracker frame);
- speed: its distance from the body's last *accepted* sample, over the time between the two,
  must not exceed `max_speed_m_s` (plus `position_noise_m`, the tracker's jitter).

Speed is always measured against the last accepted sample, never a dropped one, so one bad
sample never makes the good ones after it look like jumps. The distance allowed grows with the
time since that sample, so a body that really did move far while unseen is accepted again after
`distance / max_speed_m_s`. Samples the tracker itself marks invalid carry no pose and pass (the
loop keeps the output dark on them). Every drop is counted by kind, with the latest reason.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from dataclasses import dataclass

import numpy as np

__all__ = ["PlausibilityGate", "PlausibilityLimits"]


@dataclass(frozen=True)
class PlausibilityLimits:
    """Bounds on what a tracked body can do. The defaults suit a room-sized lab with hand-held or
    robot-moved objects; tighten `workspace_*` to the capture volume."""

    max_speed_m_s: float = 20.0
    workspace_min: tuple[float, float, float] = (-20.0, -20.0, -20.0)
    workspace_max: tuple[float, float, float] = (20.0, 20.0, 20.0)
    position_noise_m: float = 0.005
    max_future_s: float = 0.005
    max_age_s: float = 1.0

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.workspace_min, float), np.asarray(self.workspace_max, float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()) or np.any(lo >= hi):
            raise ValueError(f"workspace_min must be below workspace_max on every axis, got {self.workspace_min}, "
                             f"{self.workspace_max}")
        for name in ("max_speed_m_s", "max_future_s", "max_age_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not (math.isfinite(self.position_noise_m) and self.position_noise_m >= 0):
            raise ValueError(f"position_noise_m must be >= 0, got {self.position_noise_m!r}")


class PlausibilityGate:
    """Per-body plausibility check; `admit(sample)` returns None to accept, else why it was dropped.

    Thread-safe (a driver's receiver thread admits, any thread reads the counts)."""

    KINDS = ("timestamp", "workspace", "speed")

    def __init__(self, limits: PlausibilityLimits | None = None):
        self.limits = limits or PlausibilityLimits()
        self._box = tuple(float(v) for v in (*self.limits.workspace_min, *self.limits.workspace_max))  # x0 y0 z0 x1 y1 z1
        self._accepted: dict[int, tuple[float, float, float, int]] = {}  # body -> (x, y, z, t_exposure_ns)
        self._lock = threading.Lock()
        self.dropped: Counter[str] = Counter()
        self.last_reason = ""
        self.last_drop_ns: int | None = None

    def admit(self, sample) -> str | None:
        """Check one `dpmhw.tracking.PoseSample`; a dropped sample never becomes the reference."""
        with self._lock:
            reason = self._check(sample)
            if reason is None:
                return None
            kind, text = reason
            self.dropped[kind] += 1
            self.last_reason = f"rigid body {sample.rigid_body_id}: {text}"
            self.last_drop_ns = sample.t_arrival_ns
            return self.last_reason

    def _check(self, sample) -> tuple[str, str] | None:
        """(kind, why) for a sample to drop; None to accept it, after making it the body's reference
        when it carries a pose. Called with the lock held."""
        lim = self.limits
        ahead_s = (sample.t_exposure_ns - sample.t_arrival_ns) / 1e9
        if ahead_s > lim.max_future_s:
            return "timestamp", f"stamped {ahead_s * 1e3:.1f} ms after it arrived (limit {lim.max_future_s * 1e3:g} ms)"
        if -ahead_s > lim.max_age_s:
            return "timestamp", f"stamped {-ahead_s:.3g} s before it arrived (limit {lim.max_age_s:g} s)"
        if not sample.valid:
            return None
        p = sample.translation
        x, y, z = np.asarray(p, np.float64).tolist()  # plain floats: this runs per body, hundreds of times a second
        x0, y0, z0, x1, y1, z1 = self._box
        if not (x0 <= x <= x1 and y0 <= y <= y1 and z0 <= z <= z1):  # False for NaN
            return "workspace", (f"position {np.round(p, 3).tolist()} m is outside the workspace "
                                 f"{list(lim.workspace_min)}…{list(lim.workspace_max)} m")
        last = self._accepted.get(sample.rigid_body_id)
        if last is not None:
            lx, ly, lz, lt = last
            dt_s = abs(sample.t_exposure_ns - lt) / 1e9
            distance = math.sqrt((x - lx) ** 2 + (y - ly) ** 2 + (z - lz) ** 2)
            allowed = lim.max_speed_m_s * dt_s + lim.position_noise_m
            if distance > allowed:
                return "speed", (f"moved {distance:.3g} m in {dt_s * 1e3:.1f} ms since the last accepted sample "
                                 f"(at most {lim.max_speed_m_s:g} m/s)")
        self._accepted[sample.rigid_body_id] = (x, y, z, sample.t_exposure_ns)
        return None

    def counts(self) -> dict:
        with self._lock:
            return {"implausible": sum(self.dropped.values()), **{f"implausible_{k}": self.dropped[k] for k in self.KINDS},
                    "last_implausible": self.last_reason, "last_implausible_ns": self.last_drop_ns or 0}
