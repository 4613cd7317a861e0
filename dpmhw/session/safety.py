"""Safety state of a session: which causes keep the projector dark, and when it may light again.

The loop owns safety; this module is its bookkeeping, free of I/O so it can be tested with a
fake clock and read from any thread (the HTTP status, the watchdog) without waiting on the loop.

A *cause* is a named condition that forbids projection: lost tracking ("blank" kind), a device
fault, a render exception or a stalled loop ("fault" kind), or the operator's blank request.
Projection is allowed only when no cause is active and the last one cleared at least
`holdoff_s` ago (so a flickering tracker does not flash the audience), and — in manual resume
mode, or after an operator blank — only after an explicit `request_resume()`.
"""

from __future__ import annotations

import enum
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable, Literal

__all__ = ["Cause", "SafetyMonitor", "SafetyView", "SessionState", "Transition"]

CauseKind = Literal["blank", "fault"]
OPERATOR = "operator"


class SessionState(str, enum.Enum):
    STARTING = "starting"  # no frame presented yet
    RUNNING = "running"  # projecting
    BLANKED = "blanked"  # dark on purpose: tracking lost, operator request, or holding off
    FAULT = "fault"  # dark because something broke (device, render, stalled loop)
    STOPPED = "stopped"  # shut down to a verified dark state


@dataclass(frozen=True)
class Cause:
    name: str
    kind: CauseKind
    reason: str
    since_ns: int


@dataclass(frozen=True)
class Transition:
    """A cause became active or cleared (`SafetyMonitor.transitions`, for audits and the soak bench)."""

    seq: int  # 0, 1, 2, … over the monitor's life: a reader resumes where it left off
    t_ns: int
    name: str
    active: bool
    reason: str


@dataclass(frozen=True)
class SafetyView:
    """An immutable reading of the safety state, safe to hand to the API."""

    state: SessionState
    reason: str
    output_on: bool
    causes: tuple[Cause, ...] = ()
    activations: dict = field(default_factory=dict)  # cause name -> times it became active


class SafetyMonitor:
    """Thread-safe set of active causes plus the hold-off / resume rules; never blocks on I/O."""

    def __init__(self, holdoff_s: float = 0.5, resume: Literal["auto", "manual"] = "auto",
                 clock: Callable[[], int] = time.monotonic_ns):
        if holdoff_s < 0:
            raise ValueError(f"holdoff_s must be >= 0, got {holdoff_s}")
        if resume not in ("auto", "manual"):
            raise ValueError(f"resume must be 'auto' or 'manual', got {resume!r}")
        self.holdoff_ns = int(holdoff_s * 1e9)
        self.resume_mode = resume
        self.clock = clock
        self._lock = threading.Lock()
        self._causes: dict[str, Cause] = {}
        self._last_cleared: tuple[str, int] | None = None  # (cause name, when)
        self._latched = False  # dark until an explicit resume
        self._started = False
        self._stopped = False
        self._stop_reason = ""
        self.activations: Counter[str] = Counter()
        self._transitions: deque[Transition] = deque(maxlen=4096)  # bounded: the newest only
        self._seq = 0

    def _log(self, now: int, name: str, active: bool, reason: str) -> None:
        self._transitions.append(Transition(self._seq, now, name, active, reason))
        self._seq += 1

    def transitions(self, since_seq: int = 0) -> list[Transition]:
        """Causes set and cleared with `seq >= since_seq`, oldest first (the newest 4096 are kept)."""
        with self._lock:
            return [t for t in self._transitions if t.seq >= since_seq]

    # ---- reporting ------------------------------------------------------------------------
    def update(self, name: str, active: bool, reason: str = "", kind: CauseKind = "blank",
               cleared_at_ns: int | None = None) -> None:
        """Set or clear one cause; repeated reports of an active cause keep its first `since`.

        `cleared_at_ns`: when the evidence that ends the cause appeared, if the reporter knows it
        better than "now" (the loop passes the arrival of the first fresh tracker sample): the
        hold-off then counts from that instant, not from when the loop got round to looking.
        It is clamped to [the cause's start, now], so it can never shorten a hold-off into the past."""
        now = self.clock()
        with self._lock:
            current = self._causes.get(name)
            if active:
                if current is None:
                    self.activations[name] += 1
                    self._log(now, name, True, reason)
                    if self.resume_mode == "manual" or name == OPERATOR:
                        self._latched = True
                    self._causes[name] = Cause(name, kind, reason, now)
                elif current.reason != reason or current.kind != kind:
                    self._causes[name] = Cause(name, kind, reason, current.since_ns)
            elif current is not None:
                del self._causes[name]
                at = now if cleared_at_ns is None else min(now, max(current.since_ns, cleared_at_ns))
                if self._last_cleared is None or at >= self._last_cleared[1]:
                    self._last_cleared = (name, at)
                self._log(at, name, False, "")

    def operator_blank(self) -> None:
        self.update(OPERATOR, True, "blanked by the operator (POST /session/blank); resume to project")

    def request_resume(self) -> tuple[bool, str]:
        """Lift the operator blank / manual latch. Refused (False, why) while a fault is active."""
        with self._lock:
            others = [c for n, c in self._causes.items() if n != OPERATOR]
            if others:
                return False, "cannot resume while active: " + "; ".join(f"{c.name}: {c.reason}" for c in others)
            held = self._latched or OPERATOR in self._causes
            if OPERATOR in self._causes:
                del self._causes[OPERATOR]
                self._last_cleared = (OPERATOR, self.clock())
                self._log(self._last_cleared[1], OPERATOR, False, "")
            self._latched = False
            if not held:  # nothing was waiting for this request: say so, promise nothing
                return True, "nothing to resume: not blanked by the operator nor waiting for a resume"
            return True, "resuming" if self.holdoff_ns == 0 else f"resuming after the {self.holdoff_ns / 1e9:g} s hold-off"

    def mark_started(self) -> None:
        with self._lock:
            self._started = True

    def mark_stopped(self, reason: str) -> None:
        with self._lock:
            self._stopped = True
            self._stop_reason = reason

    def active(self, name: str) -> bool:
        with self._lock:
            return name in self._causes

    # ---- reading --------------------------------------------------------------------------
    def resume_at_ns(self) -> int | None:
        """When output becomes allowed if nothing changes (it may be past); None while a cause is
        active, an explicit resume is awaited, or after stop. The loop wakes for this instant."""
        with self._lock:
            if self._causes or self._latched or self._stopped:
                return None
            return self._last_cleared[1] + self.holdoff_ns if self._last_cleared is not None else 0

    def output_allowed(self, now_ns: int | None = None) -> bool:
        return self.view(now_ns).output_on

    def view(self, now_ns: int | None = None) -> SafetyView:
        now = self.clock() if now_ns is None else now_ns
        with self._lock:
            causes = tuple(sorted(self._causes.values(), key=lambda c: c.since_ns))
            activations = dict(self.activations)
            if self._stopped:
                return SafetyView(SessionState.STOPPED, self._stop_reason, False, causes, activations)
            if causes:
                faults = [c for c in causes if c.kind == "fault"]
                shown = faults or list(causes)
                reason = "; ".join(f"{c.name}: {c.reason}" for c in shown)
                if not self._started:
                    return SafetyView(SessionState.STARTING, reason, False, causes, activations)
                return SafetyView(SessionState.FAULT if faults else SessionState.BLANKED, reason, False, causes, activations)
            if self._latched:
                return SafetyView(SessionState.BLANKED if self._started else SessionState.STARTING,
                                  "waiting for an explicit resume (POST /session/resume)", False, causes, activations)
            if self._last_cleared is not None:
                name, cleared_at = self._last_cleared
                waited = now - cleared_at
                if waited < self.holdoff_ns:
                    state = SessionState.BLANKED if self._started else SessionState.STARTING
                    return SafetyView(state, f"{name} cleared {waited / 1e9:.2f} s ago; holding off for "
                                             f"{self.holdoff_ns / 1e9:g} s before projecting", False, causes, activations)
            return SafetyView(SessionState.RUNNING if self._started else SessionState.STARTING, "", True, causes, activations)
