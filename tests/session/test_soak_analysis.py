"""The soak bench's bookkeeping (dpmhw/benchmarks/soak.py), on a hand-made timeline: time to dark
and to resume, lit frames while a cause was active, dark spells no fault explains."""

from __future__ import annotations

import numpy as np

from dpmhw.benchmarks.soak import _analyse, _Fault, format_table
from dpmhw.session.config import load_session_config
from dpmhw.session.safety import Transition
from dpmhw.tracking import TrackerState, TrackerStatus

MS = 1_000_000


def timeline(lit_ranges, end_ms=10_000, period_ms=10):
    t = np.arange(0, end_ms, period_ms, dtype=np.int64) * MS
    lit = np.zeros(len(t), bool)
    for a, b in lit_ranges:
        lit |= (t >= a * MS) & (t < b * MS)
    return t, lit


def analyse(faults, t, lit, transitions, wrong=()):
    return _analyse(load_session_config(), faults, t, lit, transitions, list(wrong), 100, 100, 0, 200.0, 201.0, 1.0, 0,
                    TrackerStatus(TrackerState.STREAMING))


def test_stall_dark_and_resume_are_measured_from_the_fault():
    t, lit = timeline([(0, 1050), (2600, 10_000)])  # dark from 1050 ms, lit again at 2600 ms
    transitions = [Transition(0, 1045 * MS, "tracking", True, "stale"), Transition(1, 2100 * MS, "tracking", False, "")]
    out = analyse([_Fault("tracker_stall", 1000 * MS, 2000 * MS)], t, lit, transitions)
    (row,) = out["faults"]
    assert row["time_to_dark_ms"] == 50 and row["time_to_resume_ms"] == 600
    assert row["causes"] == ["tracking"] and row["lit_frames_while_cause_active"] == 0
    assert out["totals"]["unexplained_dark_spells"] == 0


def test_a_lit_frame_inside_a_cause_is_counted():
    t, lit = timeline([(0, 1200), (2600, 10_000)])  # still lit 150 ms into the cause: a bug
    transitions = [Transition(0, 1045 * MS, "tracking", True, "stale"), Transition(1, 2100 * MS, "tracking", False, "")]
    out = analyse([_Fault("tracker_stall", 1000 * MS, 2000 * MS)], t, lit, transitions)
    assert out["faults"][0]["lit_frames_while_cause_active"] == 15
    assert out["totals"]["lit_frames_while_cause_active"] == 15


def test_a_fault_that_never_darkens_and_a_dark_spell_nobody_caused():
    t, lit = timeline([(0, 6000), (6300, 10_000)])
    transitions = [Transition(0, 5995 * MS, "tracking", True, "stale"), Transition(1, 6100 * MS, "tracking", False, "")]
    faults = [_Fault("foreign_datagrams", 1000 * MS, 3000 * MS), _Fault("api_load", 8000 * MS, 9000 * MS)]
    out = analyse(faults, t, lit, transitions, wrong=[(7000 * MS, 1000.0)])
    assert out["faults"][0]["time_to_dark_ms"] is None and out["faults"][0]["time_to_resume_ms"] is None
    assert out["totals"]["unexplained_dark_spells"] == 1 and out["totals"]["unexplained_causes"] == ["tracking"]
    assert out["faults"][0]["implausible_frames_shown"] == 1 and out["totals"]["implausible_frames_shown"] == 1
    assert "| foreign_datagrams | 1 | 0 |" in format_table(out)


def test_resume_is_measured_from_the_first_good_sample_against_that_moments_frame_interval():
    """Issue 14's goal on the code's own stamps: last good exposure → first black frame within
    stale_after_ms + one frame; first good sample → first lit frame within holdoff_s + one frame,
    one frame being the lit-present interval in the second before the fault (10 ms here)."""
    t, lit = timeline([(0, 1060), (2560, 10_000)])  # dark from 1060 ms, lit again at 2560 ms
    transitions = [Transition(0, 1055 * MS, "tracking", True, "stale"), Transition(1, 2050 * MS, "tracking", False, "")]
    gaps = {1: np.array([[1003 * MS, 999 * MS, 2050 * MS]], np.int64)}  # samples stopped at 1003, back at 2050 ms
    out = _analyse(load_session_config(), [_Fault("tracker_stall", 1000 * MS, 2000 * MS)], t, lit, transitions, [],
                   100, 100, 0, 200.0, 201.0, 1.0, 0, TrackerStatus(TrackerState.STREAMING), gaps)
    (row,) = out["faults"]
    assert row["frame_ms"] == 10 and row["dark_after_last_sample_ms"] == 61 and row["dark_within_goal"] is False
    assert row["good_sample_after_fault_ms"] == 50 and row["cause_clear_after_good_sample_ms"] == 0
    assert row["lit_after_good_sample_ms"] == 510 and row["lit_after_cause_clear_ms"] == 510
    assert row["resume_within_goal"] is True  # 510 <= 500 + 10
    (summary,) = out["summary"]
    assert summary["resume_within_goal"] == "1/1" and summary["dark_within_goal"] == "0/1"
    table = format_table(out)
    assert "| tracker_stall | 1 | 1 | 10.0 |" in table and "0/1" in table and "1/1" in table


def test_a_resume_the_next_fault_pre_empted_is_not_counted_as_that_faults_late_resume():
    """Issue 14 (serial unplug 'back within holdoff_s + one frame' 3 of 5): the next fault was
    injected as the hold-off ended, before the first lit frame, and its own clear was taken as the
    end of the previous fault's spell (1,390 ms 'good sample → lit'). The spell now ends before the
    next fault, or it is reported pre-empted and left out of the goal."""
    t, lit = timeline([(0, 1060), (3410, 10_000)])  # dark from 1060 ms; lit only after the second fault
    transitions = [Transition(0, 1055 * MS, "tracker", True, "lost"), Transition(1, 2050 * MS, "tracker", False, ""),
                   Transition(2, 2560 * MS, "sink", True, "usb"), Transition(3, 2900 * MS, "sink", False, "")]
    gaps = {1: np.array([[1003 * MS, 999 * MS, 2050 * MS]], np.int64)}
    faults = [_Fault("serial_unplug", 1000 * MS, 1500 * MS), _Fault("usb_stall", 2550 * MS, 2551 * MS)]
    out = _analyse(load_session_config(), faults, t, lit, transitions, [], 100, 100, 0, 200.0, 201.0, 1.0, 0,
                   TrackerStatus(TrackerState.STREAMING), gaps)
    first, second = out["faults"]
    assert first["resume_preempted"] is True and first["lit_after_good_sample_ms"] is None
    assert first["cause_clear_after_good_sample_ms"] is None and first.get("resume_within_goal") is None
    assert second["resume_preempted"] is False and second["time_to_resume_ms"] == 859
    assert "pre-empted by the next fault (not counted against the goal): 1" in format_table(out)
