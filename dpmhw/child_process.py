"""Child processes as the supervisor (the loop process) and the session (the API process) keep
them: how one ended in words, stopping one without waiting forever, when to restart one, and the
files one leaves behind named by its pid so that a later run can tell a dead owner's leftovers.

    describe_exit(-9)                     # "killed by SIGKILL"
    stop_process(process, grace_s=5.0)    # SIGTERM, join, then SIGKILL: bounded
    RestartPolicy(limit=3, window_s=600, backoff_s=1).crashed(now_s)   # wait before restart, or None
    SHARED_SLOTS.new_name(); SHARED_SLOTS.sweep()                       # pid-named shared memory
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import secrets
import shutil
import signal
from collections import deque
from dataclasses import dataclass

__all__ = ["EXIT_THREAD_EXCEPTION", "SHARED_SLOTS", "OwnedNames", "RestartPolicy", "describe_exit", "pid_alive",
           "stop_process"]

EXIT_THREAD_EXCEPTION = 70  # EX_SOFTWARE: an exception escaped a thread of the process


def describe_exit(exitcode: int | None) -> str:
    """A process's end in words: `exited with code 70 (…)`, `killed by SIGKILL`."""
    if exitcode is None:
        return "still running"
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    if exitcode == EXIT_THREAD_EXCEPTION:
        return f"exited with code {exitcode} (an exception escaped one of its threads)"
    return f"exited with code {exitcode}"


def stop_process(process, grace_s: float, *, kill_wait_s: float = 5.0) -> bool:
    """SIGTERM a `multiprocessing.Process`, wait `grace_s`, then SIGKILL it and wait `kill_wait_s`.
    Returns whether it is gone (a process in uninterruptible sleep can outlive even SIGKILL's wait)."""
    if process.is_alive():
        process.terminate()
        process.join(grace_s)
    if process.is_alive():
        process.kill()
        process.join(kill_wait_s)
    return not process.is_alive()


class RestartPolicy:
    """When to restart after a crash: at most `limit` restarts (None: no limit) within `window_s`,
    each after a backoff that doubles with every crash still inside the window, up to
    `max_backoff_s`. Crashes older than the window are forgotten, so a process that served longer
    than it starts afresh. Pure; the clock is given."""

    def __init__(self, limit: int | None, window_s: float, backoff_s: float, max_backoff_s: float = math.inf):
        self.limit, self.window_s, self.backoff_s, self.max_backoff_s = limit, window_s, backoff_s, max_backoff_s
        self._crashes: deque[float] = deque()

    def crashed(self, now_s: float) -> float | None:
        """Record a crash at `now_s`; returns the seconds to wait before restarting, or None: give up."""
        self._crashes.append(now_s)
        while self._crashes and now_s - self._crashes[0] > self.window_s:
            self._crashes.popleft()
        restarts = len(self._crashes)  # the restart this crash would cost
        if self.limit is not None and restarts > self.limit:
            return None
        return min(self.backoff_s * 2.0 ** min(restarts - 1, 64), self.max_backoff_s)


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists (a pid another user owns counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@dataclass(frozen=True)
class OwnedNames:
    """Entries of `directory` named `<prefix>-<owner pid>-<random>`: whoever finds one whose owner
    is dead (a SIGKILL leaves them) may remove it; nobody touches a live owner's."""

    directory: str
    prefix: str

    def new_name(self) -> str:
        return f"{self.prefix}-{os.getpid()}-{secrets.token_hex(6)}"

    def owner(self, name: str) -> int | None:
        m = re.fullmatch(rf"{re.escape(self.prefix)}-(\d+)-[0-9a-z_]+", name)
        return int(m.group(1)) if m else None

    def sweep(self) -> list[str]:
        """Remove the entries whose owner is dead; returns their names."""
        try:
            names = os.listdir(self.directory)
        except OSError:
            return []
        removed = []
        for name in names:
            pid = self.owner(name)
            if pid is None or pid_alive(pid):
                continue
            path = os.path.join(self.directory, name)
            with contextlib.suppress(OSError):
                if os.path.isdir(path) and not os.path.islink(path):
                    shutil.rmtree(path)
                else:
                    os.unlink(path)
                removed.append(name)
        return removed


# the shared-memory slots of the API (server/shared_slot.py): POSIX shared memory lives in /dev/shm on Linux
SHARED_SLOTS = OwnedNames("/dev/shm", "dpmhw-slot")
