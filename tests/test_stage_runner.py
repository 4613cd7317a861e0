"""The stage runner on a fake clock: timings per name, stages that are off or end the frame, and
failures mapped as declared."""

from __future__ import annotations

import pytest

from dpmhw.stage_runner import Fault, Stage, StageFailed, run_timed


class _Clock:
    """Advances by 1 ms at each read, so a timed stage takes exactly 1 ms."""

    def __init__(self):
        self.t = 0

    def __call__(self) -> int:
        self.t += 1_000_000
        return self.t


def test_stages_run_in_order_timed_on_the_clock_a_repeated_name_adds_up():
    ran, times = [], {"render": 0.5}
    done = run_timed((Stage("lod", lambda s: s.append("plan")), None, Stage("upsample", lambda s: s.append("up")),
                       Stage("lod", lambda s: s.append("refine")), Stage("render", lambda s: s.append("wait"), timed=False)),
                      ran, _Clock(), times)
    assert done and ran == ["plan", "up", "refine", "wait"]
    assert times == {"render": 0.5, "lod": 0.002, "upsample": 0.001}  # the untimed one keeps what it had


def test_a_stage_that_returns_false_ends_the_frame():
    ran, times = [], {}
    assert not run_timed((Stage("a", lambda s: s.append("a") or False), Stage("b", lambda s: s.append("b"))),
                          ran, _Clock(), times)
    assert ran == ["a"] and set(times) == {"a"}


def test_failures_map_to_the_first_matching_fault_and_others_go_up_unchanged():
    faults = (Fault(ValueError, "render", None, "refused: {exc}"),
              Fault(Exception, "render", "reuse_errors", "failed: {type}: {exc}"))

    def raising(exc):
        def run(state):
            raise exc
        return run

    with pytest.raises(StageFailed) as info:
        run_timed((Stage("reconstruct", raising(ValueError("NaN in {pixel}")), faults),), None, _Clock(), {})
    assert (info.value.stage, info.value.cause, info.value.counter) == ("reconstruct", "render", None)
    assert info.value.reason == "refused: NaN in {pixel}" and isinstance(info.value.__cause__, ValueError)
    with pytest.raises(StageFailed) as info:
        run_timed((Stage("reconstruct", raising(RuntimeError("boom")), faults),), None, _Clock(), {})
    assert (info.value.counter, info.value.reason) == ("reuse_errors", "failed: RuntimeError: boom")
    with pytest.raises(KeyError):  # no fault declared: a fault of the caller itself
        run_timed((Stage("capture", raising(KeyError("x"))),), None, _Clock(), {})
