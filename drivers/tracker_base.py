"""What every tracker driver shares: a receiver thread, the newest pose per body, link status,
frame-number bookkeeping and reconnection with exponential backoff.

A driver subclasses `ReceiverTracker` and implements `_session()`: open the transport, handshake,
then loop reading until `self._stop` is set, calling `_publish_frame(...)` per decoded frame.
Raising `LinkLost` (or `OSError`) from `_session()` makes the base class mark the tracker LOST,
wait with backoff and call `_session()` again. The receiver thread never dies of bad input:
decoders raise `TrackerDecodeError`, which drivers count and drop.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from dpmhw.plausibility import PlausibilityGate, PlausibilityLimits
from dpmhw.thread_priority import TRACKER_RECEIVER, raise_thread_priority
from dpmhw.tracking import (
    ClockMapping,
    LatestPoses,
    PoseSample,
    SampleSubscription,
    TrackerError,
    TrackerState,
    TrackerStatus,
)

__all__ = ["LinkLost", "ReceiverTracker"]

log = logging.getLogger(__name__)

# Device frame numbers that go back by more than this mean the device restarted, not reordering.
_RESTART_JUMP = 1000
# This many frames in a row below the newest number, each following the one before, mean that
# newest number was bogus (a corrupt or foreign datagram far ahead): follow them. UDP reordering
# delivers a stray late frame, never a run of consecutive ones.
_RESYNC_RUN = 3


class LinkLost(TrackerError):
    """The link to the device is down (timeout, port gone); the receiver will reconnect."""


class ReceiverTracker:
    """Base of the tracker drivers; implements the `dpmhw.tracking.Tracker` protocol."""

    kind = "tracker"

    def __init__(
        self,
        *,
        stale_after_s: float = 0.1,
        lost_after_s: float = 1.0,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 2.0,
        plausibility: PlausibilityLimits | None = None,
    ):
        if not 0 < stale_after_s <= lost_after_s:
            raise ValueError(f"need 0 < stale_after_s <= lost_after_s, got {stale_after_s}, {lost_after_s}")
        self.stale_after_s = stale_after_s
        self.lost_after_s = lost_after_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.clock = ClockMapping()
        self.gate = PlausibilityGate(plausibility)
        self._poses = LatestPoses(self.gate)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # (state, reason) as one attribute: the receiver thread replaces it in one store, so
        # `status()` on another thread never pairs a new state with the previous reason.
        self._state_reason = (TrackerState.STOPPED, "not started")
        self._last_frame_number: int | None = None
        # A new session may face a restarted device whose frame counter began again below the
        # last one seen: its first frame is taken as is (only a forward jump counts as a gap).
        # Its clock may have restarted too, so every session also starts a fresh clock mapping.
        self._first_frame_of_session = True
        self.frames = 0
        self.malformed = 0
        self.frames_missed = 0
        self.out_of_order = 0
        self.frame_resyncs = 0
        self._behind: list[int] = []  # consecutive frame numbers refused as older than the newest
        self._last_gap = 0  # frames counted missing at the last forward jump
        self.reconnects = 0
        self.internal_errors = 0
        self.last_decode_error = ""
        self._last_arrival_ns: int | None = None
        self.frame_taken = False  # the last frame was in order and the gate refused none of it
        self._last_latency_ns: int | None = None
        self.thread_priority = "not started"

    # -- Tracker protocol ----------------------------------------------------------------------

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._set_state(TrackerState.CONNECTING, "starting")
        self._thread = threading.Thread(target=self._run, name=f"{self.kind}-receiver", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=5)
            if thread.is_alive():  # pragma: no cover - would be a bug in a driver's loop
                log.error("%s receiver thread did not stop within 5 s", self.kind)
        self._set_state(TrackerState.STOPPED, "stopped by the user")
        self._poses.close_subscriptions()

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def latest(self, rigid_body_id: int) -> PoseSample | None:
        return self._poses.latest(rigid_body_id)

    def latest_all(self) -> dict[int, PoseSample]:
        return self._poses.latest_all()

    def add_callback(self, callback: Callable[[PoseSample], None]) -> None:
        self._poses.add_callback(callback)

    def remove_callback(self, callback: Callable[[PoseSample], None]) -> None:
        self._poses.remove_callback(callback)

    def subscribe(self, maxlen: int = 4096) -> SampleSubscription:
        return self._poses.subscribe(maxlen)

    def status(self) -> TrackerStatus:
        state, reason = self._state_reason
        last = self._last_arrival_ns
        if state == TrackerState.STREAMING and last is not None:
            age_s = (time.monotonic_ns() - last) / 1e9
            if age_s > self.stale_after_s:
                state, reason = TrackerState.STALE, f"no frame for {age_s * 1e3:.0f} ms"
        return TrackerStatus(
            state=state,
            reason=reason,
            frames=self.frames,
            malformed=self.malformed,
            frames_missed=self.frames_missed,
            out_of_order=self.out_of_order,
            implausible=sum(self.gate.dropped.values()),
            reconnects=self.reconnects,
            last_arrival_ns=last,
            latency_ns=self._last_latency_ns,
            clock_offset_ns=self.clock.offset_ns,
            details=self._details(),
        )

    # -- for subclasses ------------------------------------------------------------------------

    def _session(self) -> None:
        raise NotImplementedError

    def _close_transport(self) -> None:
        """Release whatever `_session` opened (called after every session, even on error)."""

    def _details(self) -> dict:
        return {"clock_method": self.clock.method, "clock_outliers": self.clock.outliers, "clock_jumps": self.clock.jumps,
                "internal_errors": self.internal_errors, "last_decode_error": self.last_decode_error,
                "callback_errors": self._poses.callback_errors, "older_dropped": self._poses.older_dropped,
                "frame_resyncs": self.frame_resyncs, "thread_priority": self.thread_priority,
                **self.gate.counts()}

    def _set_state(self, state: TrackerState, reason: str = "") -> None:
        self._state_reason = (state, reason)

    def _count_malformed(self, exc: Exception) -> None:
        self.malformed += 1
        self.last_decode_error = str(exc)

    def _count_internal_error(self, exc: Exception) -> None:
        # A bug in our own decoding must not kill the receiver, but it must be visible.
        self.internal_errors += 1
        self.last_decode_error = f"internal {type(exc).__name__}: {exc}"
        log.exception("%s: unexpected error while handling input", self.kind)

    def _frame_number_fresh(self, frame_number: int) -> bool | None:
        """Whether a frame may be published by its number: False for one older than the newest
        published (UDP reordering, counted), None for one that resumes a run below a bogus newest
        number (a resync), True otherwise. Nothing is committed: see `_commit_frame_number`.

        A newest number that was itself bogus (far ahead) is abandoned after `_RESYNC_RUN`
        consecutive frames below it, so one bad datagram costs a few frames, not a thousand."""
        last = self._last_frame_number
        if last is None or self._first_frame_of_session or frame_number > last or last - frame_number >= _RESTART_JUMP:
            return True
        if self._behind and frame_number != self._behind[-1] + 1:
            self._behind = []
        self._behind.append(frame_number)
        if len(self._behind) < _RESYNC_RUN:
            self.out_of_order += 1
            return False
        return None

    def _commit_frame_number(self, frame_number: int, resync: bool) -> None:
        """Make `frame_number` the newest, counting the frames it skipped. Called only once a frame
        published a plausible sample: an implausible frame never takes the number of the genuine
        ones behind it (they would be refused as reordered)."""
        last = self._last_frame_number
        if resync:
            self.frame_resyncs += 1
            self.frames_missed = max(0, self.frames_missed - self._last_gap)
            log.warning("%s: frame numbers resumed at %d below the newest %d; following them",
                        self.kind, frame_number, last)
            last = None
        elif last is not None and frame_number <= last:  # a restarted device (`_frame_number_fresh` let it in)
            last = None
        self._last_gap = 0 if last is None else max(0, frame_number - last - 1)
        self.frames_missed += self._last_gap
        self._behind = []
        self._first_frame_of_session = False
        self._last_frame_number = frame_number

    def _publish_frame(self, samples: list[PoseSample], arrival_ns: int,
                       frame_number: int | None = None) -> list[PoseSample]:
        """Publish one frame's samples; returns those the plausibility gate let through.

        With a `frame_number`, the frame is first checked against the newest number, and it
        becomes the newest unless the gate refused every sample of it as implausible.
        `frame_taken` tells the driver whether the gate refused none: only such a frame's stamps
        may feed the clock mapping (one corrupt transmit stamp a few ms ahead would otherwise
        lower the one-way minimum and stamp every later pose that much early)."""
        resync = self.frame_taken = False
        if frame_number is not None:
            fresh = self._frame_number_fresh(frame_number)
            if fresh is False:
                return []
            resync = fresh is None
        self.frames += 1
        refused = self.gate.refused
        published = self._poses.publish(samples)
        self.frame_taken = self.gate.refused == refused
        if samples and not published:
            if not self.frame_taken:
                return published  # implausible: it takes neither the frame number nor the arrival
            if frame_number is not None:  # held while a body is re-acquired: numbered, not yet an arrival
                self._commit_frame_number(frame_number, resync)
            return published
        if frame_number is not None:
            self._commit_frame_number(frame_number, resync)
        self._last_arrival_ns = arrival_ns
        if self._state_reason[0] != TrackerState.STREAMING:
            self._set_state(TrackerState.STREAMING, "")
        if published:
            self._last_latency_ns = published[0].latency_ns
        return published

    def _wait_to_retry(self, backoff_s: float) -> None:
        """Wait before the next session (a driver that can see its device come back may return early)."""
        self._stop.wait(backoff_s)

    def _check_alive(self, since_ns: int, what: str) -> None:
        """Raise LinkLost when nothing arrived for `lost_after_s` since `since_ns`."""
        age_s = (time.monotonic_ns() - since_ns) / 1e9
        if age_s > self.lost_after_s:
            raise LinkLost(f"no {what} for {age_s:.2f} s (lost after {self.lost_after_s} s)")

    # -- the receiver thread -------------------------------------------------------------------

    def _run(self) -> None:
        self.thread_priority = raise_thread_priority(TRACKER_RECEIVER, f"{self.kind} receiver")
        backoff = self.backoff_initial_s
        last_failure = ""
        while not self._stop.is_set():
            frames_before = self.frames
            try:
                self._set_state(TrackerState.CONNECTING, f"reconnecting; last failure: {last_failure}" if last_failure else "connecting")
                self._first_frame_of_session = True
                self.clock.reset()
                self._session()
                reason = "session ended"
            except (TrackerError, OSError) as exc:
                reason = f"{type(exc).__name__}: {exc}" if not isinstance(exc, TrackerError) else str(exc)
            except Exception as exc:  # a driver bug: report it, keep trying
                log.exception("%s session failed", self.kind)
                reason = f"internal error {type(exc).__name__}: {exc}"
            finally:
                try:
                    self._close_transport()
                except Exception:  # pragma: no cover
                    log.exception("%s: closing the transport failed", self.kind)
            if self._stop.is_set():
                break
            if self.frames > frames_before:
                backoff = self.backoff_initial_s  # that session worked: retry quickly
            self.reconnects += 1
            last_failure = reason
            self._set_state(TrackerState.LOST, f"{reason}; reconnecting in {backoff:.2f} s")
            self._wait_to_retry(backoff)
            backoff = min(backoff * 2, self.backoff_max_s)
