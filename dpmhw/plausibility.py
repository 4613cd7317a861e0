"""The plausibility gate: tracker samples that cannot describe a real object are dropped before
anything (the loop, prediction, a recording) sees them.

A tracker can hand over a pose that decodes cleanly and is still wrong: a corrupted datagram or
record (a serial line has no checksum), a marker swap, a foreign sender. Projecting it paints the
picture somewhere it must not be, so each sample of a tracked body is checked against

- its timestamps: it must not describe an instant after it arrived (more than `max_future_s`,
  which absorbs clock-mapping error) nor one more than `max_age_s` before, and it must describe an
  instant after the body's last accepted sample (a past stamp never follows a newer one);
- the workspace: its position must lie in the box [`workspace_min`, `workspace_max`];
- kinematics, against the body's last accepted sample (never a dropped one, so one bad sample
  never makes the good ones after it look like jumps):
  - speed: it moved at most `max_speed_m_s` × dt (+ noise);
  - acceleration: it lies within ½·`max_accel_m_s2`·dt² (+ twice `position_noise_m`: both
    samples carry jitter) of where the recent velocity predicts;
  - rotation: it turned at most `max_angular_speed_rad_s` × dt (+ `rotation_noise_rad`) and
    within ½·`max_angular_accel_rad_s2`·dt² (+ noise) of where the recent angular velocity predicts.

The defaults bound a hand-held or hand-guided object: 10 m/s, 100 m/s² (10 g, a hard swing),
30 rad/s (a wrist flick, about 1700°/s), 1000 rad/s². At 240 Hz they allow a sample 2.9 mm and
0.8° off the prediction: a corrupted record that moves a pose further is refused.

After a gap (refused or missing samples) the allowed deviation grows with dt²; once it would
exceed `max_jump_m` (6 mm: with a stamp up to 1 ms off, a pose the gate accepts on its own is
within 1 cm of the truth at 2 m/s) the body is re-acquired: `confirm` consecutive samples must
agree with each other (the last within the acceleration bound of the first two's velocity)
before the newest is accepted, so a single corrupt sample is never accepted because its body
went unseen for a while.
A sample that fails against the last accepted one but fits the one before is accepted and the
last is forgotten (that one was a small corruption the bounds let through: it must not cost the
genuine samples after it). Samples the tracker itself marks invalid carry no pose and pass (the
loop keeps the output dark on them). Every drop is counted by kind, with the latest reason.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from dpmhw.transforms import angle_of_floats, matmul_bt_floats, matmul_floats, rotvec_of_floats, rotvec_to_floats

__all__ = ["PlausibilityGate", "PlausibilityLimits"]


@dataclass(frozen=True)
class PlausibilityLimits:
    """Bounds on what a tracked body can do (see the module's docstring for why these values).
    Tighten `workspace_*` to the capture volume; raise the kinematic bounds for a faster rig."""

    max_speed_m_s: float = 10.0
    workspace_min: tuple[float, float, float] = (-20.0, -20.0, -20.0)
    workspace_max: tuple[float, float, float] = (20.0, 20.0, 20.0)
    position_noise_m: float = 0.001
    max_future_s: float = 0.005
    max_age_s: float = 1.0
    max_accel_m_s2: float = 100.0
    max_angular_speed_rad_s: float = 30.0
    max_angular_accel_rad_s2: float = 1000.0
    rotation_noise_rad: float = 0.003
    max_jump_m: float = 0.006
    confirm: int = 3  # 1 takes a sample after a gap on its own (replays of single frames)

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.workspace_min, float), np.asarray(self.workspace_max, float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()) or np.any(lo >= hi):
            raise ValueError(f"workspace_min must be below workspace_max on every axis, got {self.workspace_min}, "
                             f"{self.workspace_max}")
        for name in ("max_speed_m_s", "max_future_s", "max_age_s", "max_accel_m_s2", "max_angular_speed_rad_s",
                     "max_angular_accel_rad_s2", "max_jump_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        for name in ("position_noise_m", "rotation_noise_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value!r}")
        if not (isinstance(self.confirm, int) and 1 <= self.confirm <= 16):
            raise ValueError(f"confirm must be an integer in [1, 16], got {self.confirm!r}")

    def jump_bound_m(self, dt_s: float) -> float:
        """How far (m) a sample dt_s after an accepted one may lie from the predicted position."""
        return 2.0 * self.position_noise_m + 0.5 * self.max_accel_m_s2 * dt_s * dt_s


class _Accepted(NamedTuple):
    t_ns: int
    p: tuple[float, float, float]
    R: tuple[float, ...]  # 9 floats, row-major: the checks run per sample in plain floats


_HISTORY = 8  # accepted samples kept per body (velocity over the newest ones; one fallback)
_VELOCITY_BASELINE_NS = 12_000_000  # velocities span >= this much, so one slightly-off sample barely skews them


class PlausibilityGate:
    """Per-body plausibility check; `admit(sample)` returns None to accept, else why it was dropped.

    Thread-safe (a driver's receiver thread admits, any thread reads the counts)."""

    KINDS = ("timestamp", "workspace", "speed", "jump", "rotation")

    def __init__(self, limits: PlausibilityLimits | None = None):
        self.limits = limits or PlausibilityLimits()
        self._box = tuple(float(v) for v in (*self.limits.workspace_min, *self.limits.workspace_max))  # x0 y0 z0 x1 y1 z1
        self._accepted: dict[int, list[_Accepted]] = {}  # body -> newest accepted samples, oldest first
        self._candidates: dict[int, list[_Accepted]] = {}  # body -> samples agreeing so far while re-acquiring
        self._lock = threading.Lock()
        self.dropped: Counter[str] = Counter()
        self.held = 0  # samples held back while re-acquiring a body (not counted as implausible)
        self.refused = 0  # samples dropped as implausible (the sum of `dropped`, read per frame)
        self.last_reason = ""
        self.last_drop_ns: int | None = None

    def admit(self, sample) -> str | None:
        """Check one `dpmhw.tracking.PoseSample`; a dropped sample never becomes the reference."""
        with self._lock:
            reason = self._check(sample)
            if reason is None:
                return None
            kind, text = reason
            if kind == "held":
                self.held += 1
                return text
            self.dropped[kind] += 1
            self.refused += 1
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
        new = _Accepted(sample.t_exposure_ns, (x, y, z), tuple(sample.rotation.ravel().tolist()))
        body = sample.rigid_body_id
        history = self._accepted.get(body)
        if history:
            last = history[-1]
            dt_s = (new.t_ns - last.t_ns) / 1e9
            if dt_s <= 0:
                return "timestamp", (f"stamped {-dt_s * 1e3:.1f} ms before (or at) the last accepted sample: "
                                     "a past stamp never replaces a newer one")
            distance = math.dist(new.p, last.p)
            if distance > lim.max_speed_m_s * dt_s + 2.0 * lim.position_noise_m:
                return "speed", (f"moved {distance:.3g} m in {dt_s * 1e3:.1f} ms since the last accepted sample "
                                 f"(at most {lim.max_speed_m_s:g} m/s)")
            if lim.jump_bound_m(dt_s) <= lim.max_jump_m:
                why = self._fits(history, new)
                if why is None or (len(history) >= 2 and self._fits(history[:-1], new, lim.max_jump_m) is None):
                    if why is not None:
                        history.pop()  # the last one was off (within the bounds): the fallback fits
                    self._accept(body, history, new)
                    return None
                return why
        return self._reacquire(body, new)

    def _reacquire(self, body: int, new: _Accepted) -> tuple[str, str] | None:
        """No recent accepted sample: `confirm` consecutive samples must agree before the newest
        is accepted (one corrupt sample after a gap is never taken on its own)."""
        lim = self.limits
        chain = self._candidates.setdefault(body, [])
        if chain:
            dt_s = (new.t_ns - chain[-1].t_ns) / 1e9
            if not 0 < dt_s or lim.jump_bound_m(dt_s) > lim.max_jump_m:
                chain.clear()
            elif len(chain) == 1:
                if (math.dist(new.p, chain[-1].p) > lim.max_speed_m_s * dt_s + 2.0 * lim.position_noise_m
                        or angle_of_floats(matmul_bt_floats(new.R, chain[-1].R))
                        > lim.max_angular_speed_rad_s * dt_s + lim.rotation_noise_rad):
                    chain.clear()
            elif self._fits(chain, new) is not None:
                chain.clear()
        chain.append(new)
        if len(chain) < lim.confirm:
            return "held", f"re-acquiring: {len(chain)} of {lim.confirm} consistent samples"
        self._candidates[body] = []
        self._accept(body, chain[:-1], new)
        return None

    def _accept(self, body: int, history: list[_Accepted], new: _Accepted) -> None:
        history.append(new)
        self._accepted[body] = history[-_HISTORY:]

    def _fits(self, history: list[_Accepted], new: _Accepted, cap_m: float = math.inf) -> tuple[str, str] | None:
        """None when `new` lies within the acceleration bounds of the motion `history` predicts
        (and within `cap_m` of the predicted position)."""
        lim = self.limits
        last = history[-1]
        dt_s = (new.t_ns - last.t_ns) / 1e9
        if dt_s <= 0:
            return "timestamp", "stamped before the sample it is checked against"
        base = history[0]
        for h in reversed(history[:-1]):
            base = h
            if last.t_ns - h.t_ns >= _VELOCITY_BASELINE_NS:
                break
        span_s = (last.t_ns - base.t_ns) / 1e9
        if span_s > 0:
            k = dt_s / span_s
            predicted = tuple(a + (a - b) * k for a, b in zip(last.p, base.p))
        else:
            predicted = last.p
        off = math.dist(new.p, predicted)
        bound = min(lim.jump_bound_m(dt_s), cap_m)
        if off > bound:
            return "jump", (f"{off * 1e3:.1f} mm from where its motion predicts it {dt_s * 1e3:.1f} ms after the last "
                            f"accepted sample (at most {bound * 1e3:.1f} mm: {lim.max_accel_m_s2:g} m/s²)")
        turned = angle_of_floats(matmul_bt_floats(new.R, last.R))
        if turned > lim.max_angular_speed_rad_s * dt_s + lim.rotation_noise_rad:
            return "rotation", (f"turned {math.degrees(turned):.1f}° in {dt_s * 1e3:.1f} ms "
                                f"(at most {lim.max_angular_speed_rad_s:g} rad/s)")
        if span_s > 0:
            wx, wy, wz = rotvec_of_floats(matmul_bt_floats(last.R, base.R))
            k = dt_s / span_s
            predicted_R = matmul_floats(rotvec_to_floats(wx * k, wy * k, wz * k), last.R)
            off_rad = angle_of_floats(matmul_bt_floats(new.R, predicted_R))
            bound_rad = lim.rotation_noise_rad * 2.0 + 0.5 * lim.max_angular_accel_rad_s2 * dt_s * dt_s
            if off_rad > bound_rad:
                return "rotation", (f"{math.degrees(off_rad):.2f}° from the orientation its turning predicts "
                                    f"(at most {math.degrees(bound_rad):.2f}°)")
        return None

    def counts(self) -> dict:
        with self._lock:
            return {"implausible": sum(self.dropped.values()), **{f"implausible_{k}": self.dropped[k] for k in self.KINDS},
                    "reacquire_held": self.held,
                    "last_implausible": self.last_reason, "last_implausible_ns": self.last_drop_ns or 0}
