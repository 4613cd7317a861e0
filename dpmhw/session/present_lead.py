"""How long before each refresh the present thread begins its present, and whether a pattern-mode
present reprojects its three sub-frames to their own poses or to one.

The lead is prediction horizon, but with motion predicted to the photon a few milliseconds more
of it cost far less registration than a missed refresh: the display shows the last frame again, a
period older than its poses (in pattern mode, three sub-frames). So the lead covers all but the
slowest one or two recent presents, up to ¾ of a period. Where presents need more than that (a
slow CPU, a busy machine), a pattern present first shares its three splats with a helper thread
once the lead nears its longest (less wall time for more CPU), then, if that is not enough,
reprojects its three sub-frames to the middle one's pose: one projection and splat
instead of three, so its outer sub-frames are off by a third of a period's motion instead of
every missed refresh's three being off by a whole period's (docs/session.md)."""

from __future__ import annotations

from collections import deque

from dpmhw.session.metrics import SortedWindow

__all__ = ["HANDOFF_NS", "PresentLead"]

LEAD_MIN_NS = 3_000_000  # a present begins this long before its refresh at least
STEP_NS = 1_000_000  # added after a present that missed its refresh (on-time ones wear it down)
MARGIN_NS = 2_000_000  # over the quantile of the recent times to a frame ready
HANDOFF_NS = 300_000  # a frame ready later than this before its refresh is made again for the next
QUANTILE = 99.5  # of the recent times from waking to a frame ready: all but the slowest one or two
HISTORY = 240  # presents the quantile is taken over (4 s at 60 Hz)
SHARE_QUANTILE = 99.0  # more than 1 in 100 own-pose presents would miss at the longest lead: share (fewer keep p99 registration)
SHARE_MISSES = 6  # or this many of the last HISTORY presents missed their refresh at the longest lead (2.5 %: a slow CPU
# is seen before a whole history is measured; a burst of hiccups is not one)
SHARED_RATIO_SAMPLES = 60  # shared presents measured before their median is compared with the own ones' (1 s at 60 Hz)
SHARED_HOLD = 600  # presents at one pose before own poses are tried again (10 s at 60 Hz)
SHARED_RETURN = 0.8  # own poses again once their estimated lead is below this share of the longest
SPLIT_ABOVE = 0.8  # own-pose splats shared with the helper thread once the lead is above this share of the longest (near sharing)
SPLIT_BELOW = 0.65  # and on the present thread alone again once it is below this share (a quick CPU's start-up tail must not keep it split)


class PresentLead:
    """The present thread's lead, from the time of each present from its planned wake to a frame
    ready to hand over (`add`, once per present; one thread).

    lead_ns : begin this long before the refresh: the 99.5th percentile of the last 240 times,
        plus a margin, plus a penalty that a missed refresh raises by a step and on-time presents
        wear down (a step in ~10 s); within [LEAD_MIN_NS, ¾ of a period]
    time_ns : the median time plus the hand-over: the least time a present is tried in
    split : a present's splats are shared with the reprojection's helper thread (only with
        `split_splats`, and not while the sub-frames share a pose): from a lead above `SPLIT_ABOVE` of the
        longest until one below `SPLIT_BELOW` (a split present takes less time, so the lead
        falls when it begins: the gap keeps it from switching back at once)
    shared : the sub-frames of a present share one pose (only with `share_poses`: pattern mode).
        Taken when more than 1 in 100 of the last 240 own-pose presents would miss their refresh
        at the longest lead (their 99th percentile plus the hand-over passes it), or sooner when 6
        of the last 240 missed it with the lead at its longest. Each change of kind (split or not)
        starts the weighing afresh: the one-thread presents before a split say nothing about
        whether split ones fit. Left after `SHARED_HOLD`
        presents once the own-pose lead, estimated from the shared presents' times and the ratio
        of the two kinds' medians around the change, is below `SHARED_RETURN` of the longest.
    """

    def __init__(self, period_ns: int, share_poses: bool, split_splats: bool = False):
        self.longest_ns = period_ns * 3 // 4
        self.share_poses = share_poses
        self.split_splats = split_splats
        self.split = False
        self.lead_ns = LEAD_MIN_NS
        self.time_ns = LEAD_MIN_NS
        self.penalty_ns = 0
        self.shared = False
        self._ready = SortedWindow(HISTORY)  # of the present kind in use
        self._own_median = 0.0  # the own-pose presents' median time when sharing began
        self._ratio = 0.0  # own-pose / shared median, once SHARED_RATIO_SAMPLES shared presents are measured
        self._shared_presents = 0
        # whether each present of the kind in use (own poses split, or not) missed at the longest lead, since the kind
        # began: once full, the history's times are all of that kind too
        self._misses: deque[bool] = deque(maxlen=HISTORY)

    def add(self, ready_ns: int, late: bool) -> str | None:
        """One present's time from its planned wake to a frame ready, and whether it missed its
        refresh. Returns a line for the log when the sub-frames start or stop sharing a pose, or
        the splats change threads."""
        missed = late and self.lead_ns == self.longest_ns
        self.penalty_ns = self.penalty_ns + STEP_NS if late else max(0, self.penalty_ns - STEP_NS // 600)
        self._ready.add(max(ready_ns, 0))
        median = self._ready.quantile(50)
        self.time_ns = int(median) + HANDOFF_NS
        self.lead_ns = self._within(int(self._ready.quantile(QUANTILE)) + MARGIN_NS + self.penalty_ns)
        change = None
        if self.share_poses:
            change = self._own_poses_again() if self.shared else self._share(median, missed)
        if self.split_splats:  # (a shared present makes one splat: nothing to split)
            split = not self.shared and self.lead_ns > (SPLIT_BELOW if self.split else SPLIT_ABOVE) * self.longest_ns
            if split != self.split:
                self._weigh_afresh()
                if change is None:
                    change = f"pattern presents make their splats on {'two threads' if split else 'one thread'} " \
                             f"(lead {self.lead_ns / 1e6:.1f} ms of at most {self.longest_ns / 1e6:.1f})"
            self.split = split
        return change

    def _within(self, lead_ns: int) -> int:
        return min(max(lead_ns, LEAD_MIN_NS), self.longest_ns)

    def _weigh_afresh(self) -> None:
        """A new kind of present: the sharing rule weighs only its misses and, once they fill the
        history, its times."""
        self._misses.clear()

    def _share(self, median: float, missed: bool) -> str | None:
        """Share one pose if own-pose presents are too slow for the longest lead (see the class)."""
        self._misses.append(missed)
        misses = sum(self._misses)
        need = self._ready.quantile(SHARE_QUANTILE) + HANDOFF_NS if len(self._misses) == HISTORY else 0
        if misses < SHARE_MISSES and need <= self.longest_ns:
            return None
        why = (f"{misses} of the last {len(self._misses)} missed their refresh" if misses >= SHARE_MISSES else
               f"{100 - SHARE_QUANTILE:g} % of them would miss it, needing a lead over {need / 1e6:.1f} ms")
        self.shared, self._own_median, self._ratio, self._shared_presents = True, median, 0.0, 0
        self._weigh_afresh()
        self._ready = SortedWindow(HISTORY)  # the shared presents' own times from here
        return f"pattern presents share one pose: at their sub-frames' own poses {why}, with the longest lead " \
               f"({self.longest_ns / 1e6:.1f} ms)"

    def _own_poses_again(self) -> str | None:
        """Back to own poses once, after the hold, their estimated lead fits with room (see the class)."""
        self._shared_presents += 1
        if not self._ratio and len(self._ready) >= SHARED_RATIO_SAMPLES:
            self._ratio = max(1.0, self._own_median / max(self._ready.quantile(50), 1.0))
        if not self._ratio or self._shared_presents < SHARED_HOLD:
            return None
        ready = int(self._ready.quantile(SHARE_QUANTILE) * self._ratio)  # an own-pose present's, estimated
        own = ready + MARGIN_NS + self.penalty_ns
        if own >= SHARED_RETURN * self.longest_ns:
            return None
        self.shared = False
        self._weigh_afresh()
        self._ready = SortedWindow(HISTORY)
        self._ready.add(ready)  # the estimate stands until measured times replace it
        self.time_ns, self.lead_ns = ready + HANDOFF_NS, self._within(own)
        return f"pattern presents at each sub-frame's own pose again (estimated lead {own / 1e6:.1f} ms)"
