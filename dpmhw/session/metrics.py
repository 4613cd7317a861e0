"""Rolling loop metrics: per-stage timings, fps, motion-to-photon latency, deadline misses.

Everything is kept in fixed-size ring buffers (the last `window` frames), so a session that runs
for days uses the same memory as one that runs for a minute. Histograms for Prometheus are
cumulative since start, as Prometheus expects. Only the loop thread writes; `summary()` returns
plain data the loop publishes as an immutable snapshot.
"""

from __future__ import annotations

import bisect
import threading
from collections import Counter, deque

import numpy as np

__all__ = ["STAGES", "WINDOWS", "Histogram", "LoopMetrics", "RollingWindow", "SortedWindow"]

# Rendered frames (the frame thread): tracker_age: newest sample's age when the frame started;
# render: shading at the shading resolution; gbuffer: the native G-buffer update; filter /
# upsample: reconstruction (dpmhw.reconstruct); capture: keeping it for the presents; frame: the
# whole iteration. Presents (the present thread, once per refresh): reproject: moving the last
# frame to each photon window's predicted poses (with the prediction); reproject_cpu: the present
# thread's CPU time in the reprojection itself (thread CPU, not wall: waits for the GIL or a core
# are not in it); present: handing it to the sink.
RENDER_STAGES = ("tracker_age", "predict", "render", "gbuffer", "reuse", "filter", "upsample", "adaptive", "lod",
                 "mesh_lod", "post", "capture", "frame")
PRESENT_STAGES = ("reproject", "reproject_cpu", "present")
STAGES = RENDER_STAGES + PRESENT_STAGES
LATENCY_BUCKETS_S = (0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.0)
FRAME_BUCKETS_S = (0.002, 0.005, 0.01, 0.02, 0.033, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0)
WINDOWS = len(STAGES) + 4  # the rolling windows a LoopMetrics keeps: the stages, latency, present and render times, horizon


class RollingWindow:
    """The last `size` values of a series in a numpy ring buffer."""

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"window size must be >= 1, got {size}")
        self._buf = np.zeros(size, np.float64)
        self._n = 0  # values ever added

    def add(self, value: float) -> None:
        self._buf[self._n % len(self._buf)] = value
        self._n += 1

    def values(self) -> np.ndarray:
        """Values in the window, oldest first."""
        size = len(self._buf)
        if self._n <= size:
            return self._buf[: self._n].copy()
        start = self._n % size
        return np.concatenate([self._buf[start:], self._buf[:start]])

    def __len__(self) -> int:
        return min(self._n, len(self._buf))

    def percentiles(self, qs=(50, 95, 99)) -> list[float | None]:
        return RollingWindow.percentiles_of([self], qs)[0]

    @staticmethod
    def percentiles_of(windows: "list[RollingWindow]", qs=(50, 95, 99)) -> list[list[float | None]]:
        """Each window's percentiles (None for an empty one), with one `np.percentile` call per
        window length: the frame thread summarises ~20 windows 20 times a second."""
        out: list[list[float | None]] = [[None] * len(qs) for _ in windows]
        by_length: dict[int, list[int]] = {}
        for i, w in enumerate(windows):
            if len(w):
                by_length.setdefault(len(w), []).append(i)
        for n, idx in by_length.items():
            values = np.percentile(np.stack([windows[i]._buf[:n] for i in idx]), qs, axis=1)
            for j, i in enumerate(idx):
                out[i] = [float(x) for x in values[:, j]]
        return out

    def mean(self) -> float | None:
        return float(self._buf[: len(self)].mean()) if len(self) else None


class SortedWindow:
    """The last `size` values of a series kept sorted as well, for quantiles read after every add
    (the present thread's lead, 60 times a second): an add costs a bisection and a short memmove
    (about 5 us for 240 values), a call of `np.percentile` about 90 us of the present thread's GIL."""

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"window size must be >= 1, got {size}")
        self._order: deque[float] = deque(maxlen=size)
        self._sorted: list[float] = []

    def add(self, value: float) -> None:
        if len(self._order) == self._order.maxlen:
            del self._sorted[bisect.bisect_left(self._sorted, self._order[0])]
        self._order.append(value)
        bisect.insort(self._sorted, value)

    def __len__(self) -> int:
        return len(self._sorted)

    def quantile(self, q: float) -> float:
        """The q-th percentile (0–100), interpolated linearly as `np.percentile` does by default."""
        v = self._sorted
        if not v:
            raise ValueError("quantile of an empty window")
        pos = (len(v) - 1) * q / 100.0
        lo = int(pos)
        hi = min(lo + 1, len(v) - 1)
        return v[lo] + (v[hi] - v[lo]) * (pos - lo)


class Histogram:
    """Cumulative Prometheus-style histogram (counts per upper bound, sum, count)."""

    def __init__(self, bounds: tuple[float, ...]):
        self.bounds = np.asarray(bounds, np.float64)
        self.counts = np.zeros(len(bounds), np.int64)  # non-cumulative per bucket; +Inf = count
        self.total = 0.0
        self.count = 0

    def observe(self, value: float) -> None:
        i = int(np.searchsorted(self.bounds, value, side="left"))
        if i < len(self.counts):
            self.counts[i] += 1
        self.total += value
        self.count += 1

    def as_dict(self) -> dict:
        return {"buckets": [(float(b), int(c)) for b, c in zip(self.bounds, np.cumsum(self.counts))],
                "sum": self.total, "count": self.count}


class LoopMetrics:
    """Written by the frame thread once per rendered frame (`record_render`) and by the present
    thread once per present (`record_present`): each writes its own windows. `summary()` is a
    plain-data copy."""

    def __init__(self, window: int = 512, deadline_s: float = 1 / 30):
        self.window = window
        self.deadline_s = deadline_s
        self.stages = {name: RollingWindow(window) for name in STAGES}
        self.latency = RollingWindow(window)  # motion-to-photon, seconds
        self.present_times = RollingWindow(window)  # monotonic seconds of each present
        self.render_times = RollingWindow(window)  # monotonic seconds each rendered frame was ready
        self.horizon = RollingWindow(window)  # prediction horizon used, seconds
        self.latency_hist = Histogram(LATENCY_BUCKETS_S)
        self.frame_hist = Histogram(FRAME_BUCKETS_S)
        self.counters: Counter[str] = Counter()
        self._count_lock = threading.Lock()  # both threads count

    def record_render(self, stages_s: dict[str, float], t_done_ns: int) -> None:
        """One rendered frame: its stage durations (seconds) and when it was ready to present."""
        for name, value in stages_s.items():
            self.stages[name].add(value)
        frame_s = stages_s.get("frame", 0.0)
        self.frame_hist.observe(frame_s)
        self.render_times.add(t_done_ns * 1e-9)
        self.count("frames_rendered")
        if frame_s > self.deadline_s:
            self.count("deadline_misses")

    def record_present(self, stages_s: dict[str, float], t_present_ns: int, latency_s: float, horizon_s: float) -> None:
        """One present: its stage durations, its refresh, its motion-to-photon latency and horizon."""
        for name, value in stages_s.items():
            self.stages[name].add(value)
        self.latency.add(latency_s)
        self.latency_hist.observe(latency_s)
        self.horizon.add(horizon_s)
        self.present_times.add(t_present_ns * 1e-9)
        self.count("frames_presented")

    def count(self, name: str, n: int = 1) -> None:
        with self._count_lock:
            self.counters[name] += n

    def fps(self) -> float:
        """Presents per second (the display's rate while lit)."""
        return _rate(self.present_times.values())

    def render_fps(self) -> float:
        """Rendered frames per second (the machine's rate)."""
        return _rate(self.render_times.values())

    def expected_pipeline_s(self, recent: int = 16) -> float:
        """Median time from frame start to capture (ready to present) over the last `recent` frames: the prediction
        look-ahead. Short, so it follows a change of spp or machine load within a second."""
        frames = self.stages["frame"]
        return float(np.median(frames.values()[-recent:])) if len(frames) else 0.0

    def summary(self) -> dict:
        stages = {}
        *per_stage, (p50, p95, p99) = RollingWindow.percentiles_of([*self.stages.values(), self.latency])
        for (name, w), (s50, s95, s99) in zip(self.stages.items(), per_stage):
            stages[name] = {"mean_ms": _ms(w.mean()), "p50_ms": _ms(s50), "p95_ms": _ms(s95), "p99_ms": _ms(s99)}
        return {
            "fps": round(self.fps(), 3),
            "render_fps": round(self.render_fps(), 3),
            "window_frames": len(self.latency),
            "latency_ms": {"p50": _ms(p50), "p95": _ms(p95), "p99": _ms(p99)},
            "prediction_horizon_ms": {"mean": _ms(self.horizon.mean())},
            "stages_ms": stages,
            "deadline_s": self.deadline_s,
            "counters": dict(self.counters),
            "histograms": {"latency_seconds": self.latency_hist.as_dict(), "frame_seconds": self.frame_hist.as_dict()},
        }


def _rate(t: np.ndarray) -> float:
    if len(t) < 2 or t[-1] <= t[0]:
        return 0.0
    return (len(t) - 1) / (t[-1] - t[0])


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1e3, 3)
