"""The loop's threads on a simulated clock: its `clock` and `wait` are injected together, so a
thread's timing is checked by calling it in the test thread, with no real time passing."""

from __future__ import annotations

import numpy as np
import pytest

from dpmhw.session.testing import FakeTracker
from dpmhw.tracking import PoseSample

# each test takes about a second; a thread that slept on real time instead of the injected wait
# would never be told to stop, so it fails by this timeout (generous for a loaded machine)
pytestmark = pytest.mark.timeout(60)


class SimulatedTime:
    """A clock (ns) and a wait that advances it; the wait answers "stop" after `waits` calls."""

    def __init__(self, waits: int):
        self.t = 0
        self.waits: list[float] = []
        self.limit = waits

    def clock(self) -> int:
        return self.t

    def wait(self, seconds: float) -> bool:
        self.waits.append(seconds)
        self.t += round(seconds * 1e9)
        return len(self.waits) >= self.limit


def test_the_watchdog_trips_once_the_heartbeat_is_older_than_its_limit_in_simulated_time(make_loop):
    sim = SimulatedTime(waits=13)
    loop = make_loop(clock=sim.clock, wait=sim.wait)  # watchdog_s = 1.0: checks every 0.1 s
    loop._watchdog()
    assert sim.waits == [0.1] * 13
    assert loop.safety.active("watchdog") and loop.metrics.counters["watchdog_trips"] == 1
    cause = next(c for c in loop.safety.view().causes if c.name == "watchdog")
    assert cause.since_ns == 1_100_000_000  # the first check past the 1 s limit, not before
    assert "no iteration finished for 1.2 s" in cause.reason  # the last check's


def test_the_stale_deadline_goes_dark_one_nanosecond_past_the_newest_samples_limit(make_loop):
    tracker = FakeTracker()
    tracker.streaming = False  # only the sample below
    sim = SimulatedTime(waits=20)
    loop = make_loop(tracker=tracker, clock=sim.clock, wait=sim.wait)  # stale_after_ms = 200
    tracker.poses.publish([PoseSample(1, np.eye(3), np.zeros(3), 0, 0, True, frame_number=0)])
    loop._output_on = True  # as if lit
    loop._stale_deadline()
    # 20 ms steps (so a newer sample would move the deadline), then 1 ns past it: dark there
    assert sim.waits[:11] == [0.02] * 10 + [1e-9] and sim.waits[11:] == [0.02] * 9
    assert loop.metrics.counters["stale_deadline_trips"] == 1 and not loop._output_on
    assert loop.parts.sink.frames[-1].t_target_ns == 200_000_001 and not loop.parts.sink.frames[-1].frame.any()
