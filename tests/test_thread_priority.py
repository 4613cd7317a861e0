"""`raise_thread_priority` says what the calling thread really got, and only that thread changes."""

from __future__ import annotations

import os
import threading

import pytest

from dpmhw.thread_priority import MOCK_DEVICE, PRESENT, TRACKER_RECEIVER, raise_thread_priority

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux scheduling calls")


def test_the_report_matches_the_threads_scheduling_and_only_that_thread_is_raised():
    seen = {}

    def raised():
        tid = threading.get_native_id()
        seen["report"] = raise_thread_priority(PRESENT, "test")
        seen["policy"], seen["param"] = os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority
        seen["nice"] = os.getpriority(os.PRIO_PROCESS, tid)

    before = os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    t = threading.Thread(target=raised)
    t.start()
    t.join()
    report = seen["report"]
    if report.startswith("SCHED_FIFO"):
        assert report == f"SCHED_FIFO {PRESENT[0]}" and seen["policy"] == os.SCHED_FIFO and seen["param"] == PRESENT[0]
    elif report.startswith("nice"):
        assert report == f"nice {PRESENT[1]}" and seen["policy"] == os.SCHED_OTHER and seen["nice"] == PRESENT[1]
    else:
        assert report.startswith("normal") and seen["policy"] == os.SCHED_OTHER
    assert (os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, threading.get_native_id())) == before


def test_the_present_thread_outranks_the_tracker_threads():
    assert PRESENT[0] > TRACKER_RECEIVER[0] and PRESENT[0] > MOCK_DEVICE[0]
    assert PRESENT[1] < TRACKER_RECEIVER[1] and PRESENT[1] < MOCK_DEVICE[1]
