"""Helpers shared by the tracker tests (imported as `from .conftest import ...`)."""

from __future__ import annotations

import socket
import time
from pathlib import Path

NATNET_CAPTURES = Path(__file__).parent / "data" / "natnet"


def captured(name: str) -> bytes:
    """A real Motive datagram from `data/natnet/` (its provenance in the README there)."""
    return (NATNET_CAPTURES / name).read_bytes()


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def settle(tracker, quiet_s: float = 0.15, timeout_s: float = 30.0) -> tuple[int, int]:
    """Wait until the tracker's (frames, malformed) counters stop moving (its stream is stalled).
    A quiet spell alone does not prove every byte was read (a receiver held off the CPU looks
    settled): callers first wait for what the mock says it sent."""
    deadline = time.monotonic() + timeout_s
    last, since = None, time.monotonic()
    while time.monotonic() < deadline:
        status = tracker.status()
        now = (status.frames, status.malformed)
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since > quiet_s:
            return now
        time.sleep(0.01)
    raise AssertionError(f"{tracker.kind} counters never settled")


def with_state_log(driver: type) -> type:
    """`driver` (a tracker class) that records every state it sets, with its reason. LOST lasts
    only the backoff before the next attempt (tens of ms in these tests): a test thread starved
    beside a CPU hog can miss that window when it polls `status()`, so tests look it up here."""

    class Logged(driver):
        def __init__(self, *args, **kw):
            self.states: list[tuple] = []
            super().__init__(*args, **kw)

        def _set_state(self, state, reason: str = "") -> None:
            self.states.append((state, reason))
            super()._set_state(state, reason)

        def was(self, state, text: str = "", since: int = 0) -> bool:
            """Whether `state` was set with `text` in its reason (after the first `since` states)."""
            return any(s == state and text in r for s, r in list(self.states)[since:])

    Logged.__name__ = Logged.__qualname__ = f"Logged{driver.__name__}"
    return Logged
