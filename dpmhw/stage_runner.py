"""A frame's work as a list of named stages, run in order by one runner.

The session loop (render, reconstruct, capture) and the reconstruction stage (gbuffer … post)
declare their steps as `Stage`s: a name (its key in the frame's timings, which the metrics, the
recording and the benchmarks read), a function of the frame's state, and what its failure means.
`run_timed` times each on the caller's clock and turns a declared failure into `StageFailed`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

__all__ = ["Fault", "Stage", "StageFailed", "run_timed"]


@dataclass(frozen=True)
class Fault:
    """What an exception of `kind` in a stage means: the safety `cause` it raises, the `counter`
    it counts (None: none) and the status's `reason`, a format string over `type` (the
    exception's class name) and `exc` (the exception)."""

    kind: type[BaseException]
    cause: str
    counter: str | None
    reason: str


class StageFailed(Exception):
    """A stage failed as one of its `Fault`s says; the frame is dropped."""

    def __init__(self, stage: str, fault: Fault, reason: str):
        super().__init__(reason)
        self.stage, self.cause, self.counter, self.reason = stage, fault.cause, fault.counter, reason


@dataclass(frozen=True)
class Stage:
    """One step of a frame: `run(state)`; a step that returns False ends the frame there.

    name : its key in the timings (a name met twice adds up)
    faults : the failures it maps, the first whose kind matches; any other exception goes up as it is
    timed : False for a step whose time is not its wall time here (a render done on another
        thread, a reconstruction that times its own sub-stages): it records its own, or none
    """

    name: str
    run: Callable[[Any], Any]
    faults: tuple[Fault, ...] = ()
    timed: bool = True


def run_timed(stages: Iterable[Stage | None], state: Any, clock: Callable[[], int], times: dict[str, float]) -> bool:
    """Run `stages` in order on `state` (None: a stage that is off), adding each timed one's
    seconds (`clock`: nanoseconds) to `times[name]`. Returns False if a stage ended the frame,
    else True; raises `StageFailed` for a failure the stage declares."""
    for stage in stages:
        if stage is None:
            continue
        t0 = clock() if stage.timed else 0
        try:
            result = stage.run(state)
        except Exception as exc:
            fault = next((f for f in stage.faults if isinstance(exc, f.kind)), None)
            if fault is None:
                raise
            raise StageFailed(stage.name, fault, fault.reason.format(type=type(exc).__name__, exc=exc)) from exc
        if stage.timed:
            times[stage.name] = times.get(stage.name, 0.0) + (clock() - t0) / 1e9
        if result is False:
            return False
    return True
