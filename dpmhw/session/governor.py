"""The quality governor: holds the render rate by stepping the live settings down a ladder of
cheaper rungs while the rate misses its target, and back up when the machine has room.

A policy object only: the frame thread calls `observe` once per rendered frame with the clock,
the frame's time and its settings; it returns a patch of live settings (or None), which the
loop applies like an operator's change, except that it never touches a pinned field (one the
operator set). It keeps a bounded window of frame times, reads the short window's frames each
frame and the long window's at most every `down_window_s`; it never blocks, sleeps or renders.

The ladder (`LADDER`) is ordered by quality lost per cost saved, least first: each rung is one live
setting set to a cheaper value, applied on top of the rungs before it. Level 0 is the operator's
configuration (the governor never raises quality above it); level k applies the first k rungs.
A rung is skipped when its field is pinned or the configuration is already at least as cheap
there (it would change nothing, or cost more).

Decisions:
- down: the rate over the last `down_window_s` is below target by more than `down_margin`, or
  the frames' 90th-percentile time exceeds the latency budget. It jumps to the best level whose
  predicted rate meets the target (prediction: the measured rate × the rungs' measured cost
  ratios), or the cheapest.
- up: only after `up_window_s` measured at the current level, and only if the rate predicted
  for the level above beats the target by `headroom`. A step up that has to be undone within
  two hold times doubles the hold (up to 16×), one that holds halves it again: the governor
  converges instead of oscillating.
- the window restarts at each change (frames made with the old settings do not count) and after
  a gap (a dark spell: no frames, no rate).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

__all__ = ["Governor", "LADDER", "Rung"]

GAP_S = 1.0  # no frame for this long (dark, paused): the window starts again
MIN_FRAMES = 4  # frames a window needs before it says anything
MAX_FRAMES = 4096  # the window's bound: at high rates the long window is its newest 4096 frames
MAX_BACKOFF = 16  # the up-hold doubles after each undone step up, up to this factor
LATENCY_QUANTILE = 90.0
FILTER_COST = {"off": 0, "normal": 1, "lobe": 2}  # the filter modes, cheapest first


@dataclass(frozen=True)
class Rung:
    """One step down: `field` (a live setting) set to `value`; `saves` is the fraction of the
    frame's cost it removed in the measurement the ladder was ordered by (docs/session.md)."""

    name: str
    field: str
    value: Any
    saves: float


# Ordered by quality lost per cost saved, measured on dpm-bunny 1024×768 through the session's
# stage (docs/session.md): the normal-aware filter costs no quality there, adaptive sampling
# little. The LOD budget's saving grows with the budget (docs/lod.md) and was not measured here:
# 0.10 is a guess: an underestimate makes a step down go further than needed and a step up
# too hopeful (then undone, and the hold doubles).
LADDER: tuple[Rung, ...] = (
    Rung("normal-aware filter", "filter", "normal", 0.048),
    Rung("adaptive sampling off", "adaptive_rays", 0, 0.085),
    Rung("lod rays off", "lod_rays", 0, 0.10),
    Rung("filter off", "filter", "off", 0.056),
)


def _cheaper(field: str, value: Any, than: Any) -> bool:
    if field == "filter":
        return FILTER_COST[value] < FILTER_COST[than]
    return value < than


class Governor:
    """See the module doc. `config`: the session's `governor` section; `refresh_hz`: the display's
    rate, the target when the section sets none; `clock`: monotonic ns (for `status` ages);
    `inert`: live settings that change nothing in this session (e.g. the LOD budget when no tile
    refiner runs): their rungs are skipped, since they would save nothing."""

    def __init__(self, config, refresh_hz: float, clock: Callable[[], int], ladder: tuple[Rung, ...] = LADDER,
                 inert: frozenset[str] = frozenset()):
        if not (math.isfinite(refresh_hz) and refresh_hz > 0):
            raise ValueError(f"governor: refresh_hz must be a finite rate > 0, got {refresh_hz!r}")
        self.enabled = bool(config.enabled)
        self.target_fps = float(config.target_fps if config.target_fps is not None else refresh_hz)
        self.target_from = "governor.target_fps" if config.target_fps is not None else "the display's refresh"
        self.latency_budget_s = config.latency_budget_ms / 1e3
        self.down_window_ns = int(config.down_window_s * 1e9)
        self.up_window_ns = int(max(config.up_window_s, config.down_window_s) * 1e9)  # up is never quicker
        self.down_margin = config.down_margin
        self.headroom = config.headroom
        self.ladder = ladder
        self._fields = frozenset(r.field for r in ladder)
        self.inert = frozenset(inert)
        self.clock = clock
        self.level = 0
        self.reason = "starting: the configured settings"
        self.changes = 0
        self.pinned: frozenset[str] = frozenset()
        self._base: dict[str, Any] | None = None  # the configured value of every field the ladder touches
        self._frames: deque[tuple[int, float]] = deque(maxlen=MAX_FRAMES)  # (now_ns, frame_s) at this level
        self._last_ns: int | None = None
        self._changed_ns: int | None = None
        self._last_up_ns: int | None = None  # the last step up, until it is undone or has held two hold times
        self._next_up_check_ns = 0
        self._backoff = 1
        self._fps: float | None = None
        self._frame_p90_s: float | None = None

    # ---- the ladder --------------------------------------------------------------------------
    def _effective(self, rung: Rung) -> bool:
        return rung.field not in self.pinned and rung.field not in self.inert and _cheaper(rung.field, rung.value, self._base[rung.field])

    def levels(self) -> list[int]:
        """The levels that change something: 0 and each k whose rung k−1 is effective."""
        return [0] + [k + 1 for k, r in enumerate(self.ladder) if self._effective(r)]

    def _cost(self, level: int) -> float:
        """The frame cost at `level` relative to level 0, from the rungs' measured savings."""
        return math.prod(1.0 - r.saves for r in self.ladder[:level] if self._effective(r))

    def choices(self, level: int | None = None) -> dict[str, Any]:
        """The value of every field the ladder touches at `level` (default: the current one)."""
        out = dict(self._base or {})
        for r in self.ladder[: self.level if level is None else level]:
            if self._base is not None and self._effective(r):
                out[r.field] = r.value
        return out

    # ---- per frame ---------------------------------------------------------------------------
    def observe(self, now_ns: int, frame_s: float, stages_s: dict, settings, pinned) -> dict | None:
        """One rendered frame: its end (`now_ns`), its own time (`frame_s`, start to present), its
        sub-stages (unused by the policy), the settings it was made with and the pinned fields.
        Returns the live settings to change, or None."""
        self.pinned = frozenset(pinned)
        if not self.enabled:
            return None
        model = hasattr(settings, "model_dump")  # LiveSettings, or a mapping: read the ladder's fields only
        values = {f: getattr(settings, f) if model else settings[f] for f in self._fields}
        if self._base is None:
            self._base = {r.field: values[r.field] for r in self.ladder}
        wanted = {f: v for f, v in self.choices().items() if f not in self.pinned}
        if any(values[f] != v for f, v in wanted.items()):  # made before the last change arrived
            self._last_ns = now_ns
            return {f: v for f, v in wanted.items() if values[f] != v}
        if self._last_ns is not None and now_ns - self._last_ns > GAP_S * 1e9:
            self._frames.clear()
        self._last_ns = now_ns
        if not (math.isfinite(frame_s) and frame_s >= 0.0):
            return None  # a frame without a time says nothing
        self._frames.append((now_ns, frame_s))
        keep_ns = self._hold_ns() + self.down_window_ns
        while now_ns - self._frames[0][0] > keep_ns:  # nothing older is ever read
            self._frames.popleft()
        new = self._decide(now_ns)
        if new is None or new == self.level:
            return None
        self.level = new
        self.changes += 1
        self._changed_ns = now_ns
        self._frames.clear()
        patch = {f: v for f, v in self.choices().items() if f not in self.pinned and values[f] != v}
        return patch or None

    def _window(self, now_ns: int, span_ns: int) -> tuple[float, float, float] | None:
        """(rate, capacity, 90th-percentile frame time) over the frames of the last `span_ns`, if
        they cover it. Capacity is the rate the frame thread could reach: the rate, or 1 / the
        median frame time when frames take less than the interval between them (they wait on
        something else, e.g. a paced present)."""
        frames = self._frames
        if len(frames) < MIN_FRAMES or (now_ns - frames[0][0] < span_ns and len(frames) < MAX_FRAMES):
            return None
        times, first = [], now_ns
        for t, frame_s in reversed(frames):  # newest first: a short window reads only its own frames
            if now_ns - t > span_ns and len(times) >= MIN_FRAMES:
                break
            times.append(frame_s)
            first = t
        last = frames[-1][0]
        rate = (len(times) - 1) / ((last - first) / 1e9) if last > first else math.inf
        times.sort()
        median = times[len(times) // 2]
        capacity = max(rate, 1.0 / median) if median > 0 else math.inf
        return rate, capacity, times[min(len(times) - 1, int(LATENCY_QUANTILE / 100 * len(times)))]

    def _predict(self, level: int, capacity: float, p90_s: float) -> tuple[float, float]:
        """(rate, 90th-percentile frame time) predicted at `level` from the current level's."""
        ratio = self._cost(level) / self._cost(self.level)
        return capacity / ratio, p90_s * ratio

    def _decide(self, now_ns: int) -> int | None:
        short = self._window(now_ns, self.down_window_ns)
        if short is None:
            return None
        rate, capacity, p90 = short
        self._fps, self._frame_p90_s = rate, p90
        levels = self.levels()
        slow = rate < self.target_fps * (1.0 - self.down_margin)
        late = p90 > self.latency_budget_s
        if slow or late:
            why = f"{rate:.1f} fps < {self.target_fps * (1 - self.down_margin):.1f}" if slow else \
                f"frame p90 {p90 * 1e3:.0f} ms > budget {self.latency_budget_s * 1e3:g} ms"
            below = [k for k in levels if k > self.level]
            if not below:
                self.reason = f"at the cheapest rung and still short: {why} over {self.down_window_ns / 1e9:g} s"
                return None

            def fits(k):
                r, p = self._predict(k, capacity, p90)
                return r >= self.target_fps and p <= self.latency_budget_s

            new = next((k for k in below if fits(k)), below[-1])
            if self._last_up_ns is not None and now_ns - self._last_up_ns < 2 * self._hold_ns():
                self._backoff = min(self._backoff * 2, MAX_BACKOFF)  # the last step up did not hold
            self._last_up_ns = None
            self.reason = f"down to {self.rung_name(new)}: {why} over {self.down_window_ns / 1e9:g} s"
            return new
        if self._last_up_ns is not None and now_ns - self._last_up_ns >= 2 * self._hold_ns():
            self._backoff = max(1, self._backoff // 2)  # the last step up held: trust the estimates a bit more
            self._last_up_ns = None
        above = [k for k in levels if k < self.level]
        if not above or now_ns < self._next_up_check_ns:
            return None
        self._next_up_check_ns = now_ns + self.down_window_ns  # the long window is not re-read every frame
        if self._changed_ns is not None and now_ns - self._changed_ns < self._hold_ns():
            return None
        long = self._window(now_ns, self._hold_ns())
        if long is None:
            return None
        up = above[-1]
        predicted, p90_up = self._predict(up, long[1], long[2])
        if predicted < self.target_fps * (1.0 + self.headroom) or p90_up * (1.0 + self.headroom) > self.latency_budget_s:
            return None
        self._last_up_ns = now_ns
        self.reason = (f"up to {self.rung_name(up)}: {long[0]:.1f} fps over {self._hold_ns() / 1e9:g} s predicts "
                       f"{predicted:.1f} fps there (target {self.target_fps:g} + {self.headroom:.0%} headroom)")
        return up

    def _hold_ns(self) -> int:
        return self.up_window_ns * self._backoff

    def rung_name(self, level: int) -> str:
        return "the configured settings" if level == 0 else f"level {level} ({self.ladder[level - 1].name})"

    # ---- for /status -------------------------------------------------------------------------
    def status(self) -> dict:
        """Everything JSON-able: what the governor chose, why, and what it measured."""
        now = self.clock()
        return {
            "enabled": self.enabled,
            "level": self.level,
            "rung": self.rung_name(self.level),
            "ladder": [{"level": k + 1, "name": r.name, "field": r.field, "value": r.value,
                        "skipped": self._base is not None and not self._effective(r)} for k, r in enumerate(self.ladder)],
            "choices": self.choices(),
            "target_fps": self.target_fps,
            "target_from": self.target_from,
            "latency_budget_ms": self.latency_budget_s * 1e3,
            "measured_fps": None if self._fps is None or not math.isfinite(self._fps) else round(self._fps, 2),
            "frame_p90_ms": None if self._frame_p90_s is None else round(self._frame_p90_s * 1e3, 2),
            "reason": self.reason,
            "changes": self.changes,
            "since_change_s": None if self._changed_ns is None else round((now - self._changed_ns) / 1e9, 3),
            "up_hold_s": self._hold_ns() / 1e9,
            "pinned": sorted(self.pinned),
        }
