"""What a tracker is streaming, body by body: rate, latency, invalid (occluded) samples, and the
link's own counters (malformed, missed, out-of-order frames, reconnects, clock offset).

Used by `dpmhw tracker watch` to check an OptiTrack or Polhemus before a session. Works on any
`dpmhw.tracking.Tracker` that offers `subscribe()`, so it never imports a driver.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from dpmhw.tracking import PoseSample, Tracker

__all__ = ["BodyStats", "TrackerWatch"]


@dataclass
class BodyStats:
    """Counters of one rigid body since the watch began, plus a window of recent arrivals."""

    samples: int = 0
    invalid: int = 0
    last: PoseSample | None = None
    recent: deque = field(default_factory=deque)  # (arrival_ns, latency_ns) inside the window


class TrackerWatch:
    """Reads a tracker's samples through a bounded subscription and summarises them.

    window_s : rate and latency percentiles cover the samples that arrived this long ago at most.
    clock : host monotonic ns (injectable for tests).
    """

    def __init__(self, tracker: Tracker, window_s: float = 2.0, clock=time.monotonic_ns):
        self.tracker, self.window_ns, self.clock = tracker, int(window_s * 1e9), clock
        self.bodies: dict[int, BodyStats] = {}
        self._sub = tracker.subscribe(maxlen=65536)
        self.started_ns = clock()

    def close(self) -> None:
        self._sub.close()

    def update(self) -> None:
        """Take in every sample that arrived since the last call."""
        now = self.clock()
        for s in self._sub.drain():
            b = self.bodies.setdefault(s.rigid_body_id, BodyStats())
            b.samples += 1
            b.last = s
            if not s.valid:
                b.invalid += 1
            b.recent.append((s.t_arrival_ns, s.latency_ns))
        for b in self.bodies.values():
            while b.recent and b.recent[0][0] < now - self.window_ns:
                b.recent.popleft()

    def rows(self) -> list[dict]:
        """One row per body: id, samples, invalid, rate (Hz), latency p50/p99 (ms), position (m), age (ms)."""
        now = self.clock()
        span_s = min(self.window_ns, now - self.started_ns) / 1e9
        out = []
        for body_id in sorted(self.bodies):
            b = self.bodies[body_id]
            lat = np.array([lat for _, lat in b.recent], dtype=np.float64) / 1e6
            p50, p99 = (np.percentile(lat, [50, 99]) if lat.size else (np.nan, np.nan))
            pos = b.last.translation if b.last is not None and b.last.valid else None
            out.append({
                "body": body_id, "samples": b.samples, "invalid": b.invalid,
                "rate_hz": len(b.recent) / span_s if span_s > 0 else 0.0,
                "latency_p50_ms": float(p50), "latency_p99_ms": float(p99),
                "position_m": None if pos is None else [round(float(v), 4) for v in pos],
                "age_ms": None if b.last is None else (now - b.last.t_arrival_ns) / 1e6,
            })
        return out

    def link(self) -> dict:
        """The tracker's own view: state, reason, frame counters, clock offset (host − device, s)."""
        st = self.tracker.status()
        return {
            "state": st.state.value, "reason": st.reason, "frames": st.frames, "malformed": st.malformed,
            "frames_missed": st.frames_missed, "out_of_order": st.out_of_order, "reconnects": st.reconnects,
            "clock_offset_s": None if st.clock_offset_ns is None else st.clock_offset_ns / 1e9,
            "samples_dropped_by_watch": self._sub.dropped,
        }
