"""Safety bookkeeping (fake clock) and rolling metrics."""

from __future__ import annotations

import numpy as np
import pytest

from dpmhw.session.metrics import Histogram, LoopMetrics, RollingWindow, SortedWindow
from dpmhw.session.safety import SafetyMonitor, SessionState


class Clock:
    def __init__(self):
        self.t = 0

    def __call__(self):
        return self.t

    def advance(self, s):
        self.t += int(s * 1e9)


def test_cause_blanks_and_projection_resumes_only_after_holdoff():
    clock = Clock()
    s = SafetyMonitor(holdoff_s=0.5, clock=clock)
    assert s.view().state == SessionState.STARTING and s.output_allowed()
    s.mark_started()
    assert s.view().state == SessionState.RUNNING
    s.update("tracking", True, "rigid body 1 not tracked")
    v = s.view()
    assert (v.state, v.output_on) == (SessionState.BLANKED, False) and "not tracked" in v.reason
    clock.advance(2)
    s.update("tracking", False)
    clock.advance(0.4)
    assert not s.output_allowed() and "holding off" in s.view().reason
    s.update("tracking", True, "again")  # flicker restarts the hold-off
    clock.advance(0.1)
    s.update("tracking", False)
    clock.advance(0.45)
    assert not s.output_allowed()
    clock.advance(0.1)
    assert s.output_allowed() and s.view().state == SessionState.RUNNING
    assert s.view().activations == {"tracking": 2}


def test_holdoff_counts_from_when_the_evidence_arrived_not_from_when_the_loop_looked():
    """Issue 14 (resume within holdoff_s + one frame of the first good sample): the loop reports
    the first fresh sample's arrival; the hold-off and the logged transition count from it."""
    clock = Clock()
    s = SafetyMonitor(holdoff_s=0.5, clock=clock)
    s.mark_started()
    assert s.resume_at_ns() == 0  # nothing ever cleared: allowed now
    clock.advance(1)
    s.update("tracking", True, "stale")
    assert s.resume_at_ns() is None
    clock.advance(1)  # t = 2 s: the loop sees the sample that arrived at 1.97 s
    s.update("tracking", False, cleared_at_ns=1_970_000_000)
    assert s.resume_at_ns() == 2_470_000_000 and s.transitions()[-1].t_ns == 1_970_000_000
    clock.advance(0.469)
    assert not s.output_allowed()
    clock.advance(0.002)
    assert s.output_allowed()
    # clamped: never before the cause began, never in the future
    s.update("tracking", True, "stale")
    s.update("tracking", False, cleared_at_ns=0)
    assert s.transitions()[-1].t_ns == clock.t and s.resume_at_ns() == clock.t + 500_000_000
    s.update("tracking", True, "stale")
    s.update("tracking", False, cleared_at_ns=clock.t + 10**9)
    assert s.resume_at_ns() == clock.t + 500_000_000
    # a backdated clear never moves the hold-off of a later clear back
    s.update("a", True, "x")
    s.update("b", True, "y")
    clock.advance(1)
    s.update("a", False)
    s.update("b", False, cleared_at_ns=clock.t - 10**8)
    assert s.resume_at_ns() == clock.t + 500_000_000
    s.operator_blank()
    s.request_resume()
    s.update("c", True, "z", "fault")
    s.update("c", False)
    s.mark_stopped("bye")
    assert s.resume_at_ns() is None


def test_fault_wins_over_blank_in_the_state_and_resume_is_refused_while_active():
    s = SafetyMonitor(holdoff_s=0.0, clock=Clock())
    s.mark_started()
    s.update("tracking", True, "stale")
    s.update("projector", True, "unplugged", "fault")
    v = s.view()
    assert v.state == SessionState.FAULT and v.reason == "projector: unplugged"
    ok, why = s.request_resume()
    assert not ok and "projector: unplugged" in why


def test_manual_mode_and_operator_blank_need_explicit_resume():
    clock = Clock()
    s = SafetyMonitor(holdoff_s=0.0, resume="manual", clock=clock)
    s.mark_started()
    s.update("render", True, "boom", "fault")
    s.update("render", False)
    clock.advance(10)
    assert not s.output_allowed() and "explicit resume" in s.view().reason
    assert s.request_resume()[0] and s.output_allowed()
    auto = SafetyMonitor(holdoff_s=0.0, clock=clock)
    auto.mark_started()
    auto.operator_blank()
    clock.advance(10)
    assert auto.view().state == SessionState.BLANKED and "operator" in auto.view().reason
    assert auto.request_resume()[0] and auto.output_allowed()
    auto.mark_stopped("bye")
    assert auto.view().state == SessionState.STOPPED and not auto.output_allowed()


def test_bad_safety_arguments():
    with pytest.raises(ValueError):
        SafetyMonitor(holdoff_s=-1)
    with pytest.raises(ValueError):
        SafetyMonitor(resume="sometimes")


def test_rolling_window_keeps_only_the_last_values():
    w = RollingWindow(4)
    assert w.percentiles() == [None, None, None] and w.mean() is None
    for v in range(10):
        w.add(v)
    np.testing.assert_array_equal(w.values(), [6, 7, 8, 9])
    assert len(w) == 4 and w.percentiles((50,)) == [7.5]


def test_sorted_window_quantiles_match_numpy_over_the_last_values():
    rng = np.random.default_rng(3)
    w, seen = SortedWindow(7), []
    for x in rng.integers(0, 50, 40).tolist():  # repeats too: the oldest copy leaves, not another
        w.add(x)
        seen.append(x)
        for q in (0, 50, 98, 100):
            assert w.quantile(q) == pytest.approx(np.percentile(seen[-7:], q))
    assert len(w) == 7
    with pytest.raises(ValueError, match="empty"):
        SortedWindow(3).quantile(50)


def test_loop_metrics_summary_percentiles_are_each_windows_own():
    m = LoopMetrics(window=16)
    for i in range(20):  # the render stages fill 16 entries; reproject fewer: windows of two lengths
        m.record_render({"render": 0.001 * i, "frame": 0.002 * i * i}, i)
        if i % 3 == 0:
            m.record_present({"reproject": 0.0005 * i, "present": 0.001}, i, 0.01 * i, 0.0)
    s = m.summary()
    for name in ("render", "frame", "reproject", "present"):
        want = [round(float(x) * 1e3, 3) for x in np.percentile(m.stages[name].values(), (50, 95, 99))]
        assert [s["stages_ms"][name][k] for k in ("p50_ms", "p95_ms", "p99_ms")] == want
    assert s["stages_ms"]["gbuffer"]["p50_ms"] is None
    assert [s["latency_ms"][k] for k in ("p50", "p95", "p99")] == [
        round(float(x) * 1e3, 3) for x in np.percentile(m.latency.values(), (50, 95, 99))]


def test_histogram_is_cumulative_like_prometheus():
    h = Histogram((0.01, 0.1))
    for v in (0.005, 0.01, 0.05, 3.0):
        h.observe(v)
    assert h.as_dict() == {"buckets": [(0.01, 2), (0.1, 3)], "sum": pytest.approx(3.065), "count": 4}


def test_loop_metrics_fps_latency_and_deadline_misses():
    m = LoopMetrics(window=8, deadline_s=0.02)
    for k in range(20):
        frame_s = 0.03 if k % 2 else 0.01
        m.record_render({"render": frame_s * 0.9, "frame": frame_s}, t_done_ns=int(k * 0.1e9))
        m.record_present({"reproject": 0.001, "present": 0.0005}, t_present_ns=int(k * 0.05e9), latency_s=0.04, horizon_s=0.03)
    s = m.summary()
    assert s["fps"] == pytest.approx(20.0)
    assert s["render_fps"] == pytest.approx(10.0)
    assert s["latency_ms"]["p50"] == pytest.approx(40.0)
    assert s["counters"] == {"frames_rendered": 20, "frames_presented": 20, "deadline_misses": 10}
    assert s["window_frames"] == 8
    assert m.expected_pipeline_s() == pytest.approx(0.02)
    for k in range(3):  # the look-ahead follows the newest frames, not the whole window
        m.record_render({"frame": 0.05}, t_done_ns=int((20 + k) * 0.1e9))
    assert m.expected_pipeline_s(recent=3) == pytest.approx(0.05)
