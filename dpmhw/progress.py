"""Progress of long commands that shows wherever the output goes: a rich bar on a terminal, and
otherwise (a log file, CI) one line every few seconds with done/total, elapsed time and an ETA.

    with Progress() as progress:
        task = progress.task("rendering 1024×768", total=spp)
        integrator.render(..., progress=lambda done, total: task.update(done, total))

`Progress.callback` adapts the `(description, done, total)` callbacks that benchmarks take.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

__all__ = ["Progress", "Task", "format_duration"]


def format_duration(seconds: float) -> str:
    """`42 s`, `3 min 05 s`, `1 h 02 min`: short and unambiguous in a log."""
    s = int(round(max(0.0, seconds)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class Task:
    """One counted job; `update(done)` is cheap to call as often as the work allows."""

    def __init__(self, owner: "Progress", description: str, total: int | None):
        self.owner, self.description, self.total = owner, description, total
        self.done = 0
        self.started = owner.clock()
        self._last_line = self.started
        self._bar_id = owner._bar.add_task(description, total=total) if owner._bar is not None else None
        if self._bar_id is None:
            owner._print(self.line(self.started))  # a log shows that the job began

    def update(self, done: int, total: int | None = None, description: str | None = None) -> None:
        if total is not None:
            self.total = total
        renamed = description is not None and description != self.description
        if renamed:
            self.description = description
        self.done = done
        if self._bar_id is not None:
            self.owner._bar.update(self._bar_id, completed=done, total=self.total, description=self.description)
            return
        now = self.owner.clock()
        finished = self.total is not None and done >= self.total
        if finished or renamed or now - self._last_line >= self.owner.every_s:  # a new phase gets its line
            self._last_line = now
            self.owner._print(self.line(now))

    def advance(self, n: int = 1) -> None:
        self.update(self.done + n)

    def line(self, now: float) -> str:
        elapsed = now - self.started
        if self.total:
            pct = 100.0 * self.done / self.total
            if self.done >= self.total:
                tail = f"done in {format_duration(elapsed)}"
            elif self.done > 0:
                tail = f"{format_duration(elapsed)} elapsed, ETA {format_duration(elapsed * (self.total - self.done) / self.done)}"
            else:
                tail = f"{format_duration(elapsed)} elapsed, ETA unknown"
            return f"{self.description}: {self.done}/{self.total} ({pct:.0f} %), {tail}"
        return f"{self.description}: {self.done} done, {format_duration(elapsed)} elapsed"


class Progress:
    """A context manager that owns the bar (terminal) or the line printer (anything else).

    stream : where progress goes (stderr by default, so stdout keeps the results).
    bar : force the bar on or off (default: on when `stream` is a terminal).
    every_s : seconds between log lines without a terminal.
    clock : seconds, monotonic (injectable for tests).
    """

    def __init__(self, stream: TextIO | None = None, *, bar: bool | None = None, every_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic):
        self.stream = stream if stream is not None else sys.stderr
        self.every_s, self.clock = every_s, clock
        self.use_bar = self.stream.isatty() if bar is None else bar
        self._bar = None
        self._tasks: dict[str, Task] = {}

    def __enter__(self) -> "Progress":
        if self.use_bar:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress as RichProgress, TimeElapsedColumn, TimeRemainingColumn

            self._bar = RichProgress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), TimeRemainingColumn(), transient=True,
                                     console=Console(file=self.stream))
            self._bar.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc)
            self._bar = None

    def task(self, description: str, total: int | None = None) -> Task:
        return Task(self, description, total)

    def callback(self, description: str, done: int, total: int) -> None:
        """`progress(description, done, total)`: one task per distinct description."""
        task = self._tasks.get(description)
        if task is None:
            task = self._tasks[description] = self.task(description, total)
        task.update(done, total)

    def _print(self, line: str) -> None:
        print(line, file=self.stream, flush=True)
