"""Raising the calling thread's scheduling priority, for the few threads whose timing the show
depends on (the present thread, a tracker's receiver) while the renderer fills every core.

A Python thread that wakes must also get the GIL. Its holder, if it is a normal thread, can be
preempted by the renderer's native threads while holding it, and every waiter then waits a
scheduler slice. Threads raised here are not preempted by normal threads, so they hold the GIL
only for as long as their own work takes."""

from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger(__name__)

__all__ = ["MOCK_DEVICE", "PRESENT", "TRACKER_RECEIVER", "raise_thread_priority"]

# (SCHED_FIFO priority, else nice value) of each raised thread, in one place so their order is seen.
PRESENT = (10, -10)  # the session's present thread: one present per refresh
TRACKER_RECEIVER = (5, -5)  # a tracker driver's receiver: a sample that waits ages, and stale tracking darkens the show
MOCK_DEVICE = (5, -5)  # the NatNet mock's sender: it stands for another machine, whose timing this process's load cannot touch


def raise_thread_priority(level: tuple[int, int], who: str) -> str:
    """For the calling thread, SCHED_FIFO at `level`'s priority (Linux; needs CAP_SYS_NICE or an
    RLIMIT_RTPRIO that allows it: it then preempts every normal thread at once), else the
    per-thread nice value, else as it is. Returns which, for a status. The threads raised
    sleep most of the time, and the kernel's real-time throttling bounds them anyway."""
    rt_priority, nice = level
    tid = threading.get_native_id()
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(rt_priority))
        return f"SCHED_FIFO {rt_priority}"
    except (OSError, AttributeError) as exc:
        log.info("%s thread: no real-time priority: %s", who, exc)
    try:
        os.setpriority(os.PRIO_PROCESS, tid, nice)
        return f"nice {nice}"
    except (OSError, AttributeError) as exc:
        log.info("%s thread keeps its priority: %s", who, exc)
        return "normal (raising it needs CAP_SYS_NICE, RLIMIT_RTPRIO or RLIMIT_NICE)"
