"""When the loop's frame thread owes its next present, in memory shared with the supervisor, so
that the supervisor can tell a hung loop process without asking it anything (a stopped or
wedged process cannot answer, and neither can its API).

    beat = Heartbeat()                       # the supervisor, before spawning the loop process
    SessionLoop(..., heartbeat=beat)         # the loop process writes it
    beat.overdue(now_ns)                     # the supervisor: why the loop is hung, or None

While the output is lit, each present (and going live) sets a deadline: now + the allowance the
loop states (its stale limit plus twice its expected frame time, see `SessionLoop`) + `MARGIN_NS`.
A lit frame still standing past it is a frozen frame on a moving object: the process is hung.
"Lit" is cleared only once the projector was confirmed dark, so a loop that hangs while blanking
still counts as lit; while dark nothing is judged (nothing is lit, and the loop's own watchdog
and its API report a stall). Times are CLOCK_MONOTONIC ns, one clock for every process; each
word is one aligned 8-byte store.
"""

from __future__ import annotations

import multiprocessing

__all__ = ["Heartbeat"]

_DUE, _PRESENTED, _LIT = range(3)
MARGIN_NS = 50_000_000  # scheduling slack on top of the loop's own allowance


class Heartbeat:
    def __init__(self) -> None:
        # a lock-free array in shared memory, handed to the loop process when it is spawned
        self._words = multiprocessing.get_context("spawn").RawArray("q", 3)

    # ---- the loop process ---------------------------------------------------------------------
    def presented(self, now_ns: int, allowance_ns: int) -> None:
        """A frame was presented (or the output went live) at `now_ns`; the next is due within
        `allowance_ns` + MARGIN_NS."""
        self._words[_PRESENTED] = now_ns
        self._words[_DUE] = now_ns + allowance_ns + MARGIN_NS
        self._words[_LIT] = 1  # last: the supervisor never reads "lit" with an old deadline

    def dark(self) -> None:
        """The projector was confirmed dark."""
        self._words[_LIT] = 0

    # ---- the supervisor -----------------------------------------------------------------------
    def overdue(self, now_ns: int) -> tuple[str | None, int]:
        """(why the loop counts as hung, or None; ns until it would, if nothing changes)."""
        if not self._words[_LIT]:
            return None, 100_000_000  # dark: look again later
        due, presented = self._words[_DUE], self._words[_PRESENTED]
        if now_ns > due:
            return (f"its frame thread has not presented for {(now_ns - presented) / 1e6:.0f} ms while lit "
                    f"(due within {(due - presented) / 1e6:.0f} ms)"), 0
        return None, due - now_ns
