"""What the loop's frame thread last did, in memory shared with the supervisor, so that the
supervisor can tell a hung loop process without asking it anything (a stopped or wedged process
cannot answer, and neither can its API).

    beat = Heartbeat()                       # the supervisor, before spawning the loop process
    SessionLoop(..., heartbeat=beat)         # the loop process writes it from its frame thread
    beat.overdue(now_ns, lit_ns, dark_ns)    # the supervisor: why the loop is hung, or None

The loop writes three 8-byte words (each store is atomic on the platforms we run on): when the
frame thread last finished an iteration, when it last presented (or went live), and whether the
output is lit. "Lit" is cleared only once the projector was confirmed dark, so a loop that hangs
while blanking still counts as lit. Times are CLOCK_MONOTONIC ns, one clock for every process.
"""

from __future__ import annotations

import multiprocessing

__all__ = ["Heartbeat"]

_BEAT, _PRESENT, _LIT = range(3)


class Heartbeat:
    def __init__(self) -> None:
        # a lock-free array in shared memory, handed to the loop process when it is spawned
        self._words = multiprocessing.get_context("spawn").RawArray("q", 3)

    # ---- the loop process (its frame thread, and whoever makes the output dark) ---------------
    def beat(self, now_ns: int) -> None:
        self._words[_BEAT] = now_ns

    def presented(self, now_ns: int) -> None:
        self._words[_PRESENT] = now_ns

    def lit(self, now_ns: int) -> None:
        self._words[_PRESENT] = now_ns  # the first frame is due within the bound from now
        self._words[_LIT] = 1

    def dark(self) -> None:
        self._words[_LIT] = 0

    # ---- the supervisor -----------------------------------------------------------------------
    def overdue(self, now_ns: int, lit_bound_ns: int, dark_bound_ns: int) -> tuple[str | None, int]:
        """(why the loop counts as hung, or None; ns until it would, if nothing changes). Lit: no
        present within `lit_bound_ns`. Dark: no iteration within `dark_bound_ns` (0: not checked)."""
        if self._words[_LIT]:
            age = now_ns - self._words[_PRESENT]
            if age > lit_bound_ns:
                return (f"its frame thread has not presented for {age / 1e6:.0f} ms while lit "
                        f"(limit {lit_bound_ns / 1e6:.0f} ms)"), 0
            return None, lit_bound_ns - age
        if not dark_bound_ns or not self._words[_BEAT]:
            return None, 100_000_000
        age = now_ns - self._words[_BEAT]
        if age > dark_bound_ns:
            return (f"its frame thread has finished no iteration for {age / 1e9:.1f} s "
                    f"(limit {dark_bound_ns / 1e9:.1f} s)"), 0
        return None, dark_bound_ns - age
