"""Tracked rigid-body poses as the loop consumes them, and the contract every tracker driver meets.

A tracker driver (NatNet, serial, a replay file) runs a background receiver and publishes
`PoseSample`s: the newest one per rigid body for the loop (`latest`), callbacks and bounded
subscriptions for recording. Every sample carries the time it *describes* on this host's
monotonic clock (`time.monotonic_ns()`), not only when it arrived, so motion prediction can
extrapolate from the right instant. `ClockMapping` turns a device's own clock into host time.

Drivers live in `drivers/`; this module imports none of them.
"""

from __future__ import annotations

import enum
import threading
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from dpmhw.errors import DpmhwError
from dpmhw.plausibility import PlausibilityGate
from dpmhw.transforms import quaternion_xyzw_to_rotation

__all__ = [
    "ClockMapping",
    "LatestPoses",
    "PoseSample",
    "SampleSubscription",
    "Tracker",
    "TrackerDecodeError",
    "TrackerError",
    "TrackerState",
    "TrackerStatus",
    "quaternions_xyzw_to_matrices",
]


class TrackerError(DpmhwError, RuntimeError):
    """A tracker could not be reached or configured (names the device and what to check)."""


class TrackerDecodeError(DpmhwError, ValueError):
    """Bytes from a tracker do not form a valid message: the receiver counts it and drops it.

    The message names the field, the byte offset and what was expected, so a capture of the
    offending datagram or record can be matched against the protocol description.
    """


@dataclass(frozen=True, eq=False)
class PoseSample:
    """One rigid body's pose at one tracker frame.

    rotation : (3, 3) float64, object→world; NaN when the tracker sent no usable orientation
    translation : (3,) float64, metres, object origin in the world (tracker) frame
    t_exposure_ns : int, host monotonic time the pose describes (camera mid-exposure)
    t_arrival_ns : int, host monotonic time the data arrived
    valid : bool, the tracker solved this body in this frame (False: occluded / dropout)
    mean_marker_error : float, metres (0 when the device does not report it)
    frame_number : int, the device's frame counter
    """

    rigid_body_id: int
    rotation: np.ndarray
    translation: np.ndarray
    t_exposure_ns: int
    t_arrival_ns: int
    valid: bool
    mean_marker_error: float = 0.0
    frame_number: int = -1

    def __post_init__(self) -> None:
        # Samples are shared between threads: make their arrays read-only so no consumer can
        # change what another one sees.
        for name, shape in (("rotation", (3, 3)), ("translation", (3,))):
            arr = np.array(getattr(self, name), dtype=np.float64)
            if arr.shape != shape:
                raise ValueError(f"PoseSample.{name}: expected shape {shape}, got {arr.shape}")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @classmethod
    def from_floats(cls, rigid_body_id: int, rotation, translation, t_exposure_ns: int, t_arrival_ns: int,
                    valid: bool, mean_marker_error: float = 0.0, frame_number: int = -1) -> "PoseSample":
        """A sample from plain numbers: `rotation` 9 floats (row-major), `translation` 3 floats.

        What a driver's receiver thread builds for every body of every frame: one read-only array
        each, without the generic constructor's conversions, copies and per-field checks."""
        rot = np.array(rotation, dtype=np.float64)
        rot.shape = (3, 3)  # in place (raises unless 9 values)
        pos = np.array(translation, dtype=np.float64)
        if pos.shape != (3,):
            raise ValueError(f"PoseSample.translation: expected shape (3,), got {pos.shape}")
        rot.setflags(write=False)
        pos.setflags(write=False)
        sample = object.__new__(cls)
        set_field = object.__setattr__
        set_field(sample, "rigid_body_id", rigid_body_id)
        set_field(sample, "rotation", rot)
        set_field(sample, "translation", pos)
        set_field(sample, "t_exposure_ns", t_exposure_ns)
        set_field(sample, "t_arrival_ns", t_arrival_ns)
        set_field(sample, "valid", valid)
        set_field(sample, "mean_marker_error", mean_marker_error)
        set_field(sample, "frame_number", frame_number)
        return sample

    @property
    def latency_ns(self) -> int:
        """Exposure-to-arrival latency on the host clock."""
        return self.t_arrival_ns - self.t_exposure_ns

    def as_matrix(self) -> np.ndarray:
        """(4, 4) homogeneous object→world transform."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m


class TrackerState(str, enum.Enum):
    """Where a tracker's link is; the loop blanks the projector unless STREAMING."""

    STOPPED = "stopped"  # not started, or stopped by the user
    CONNECTING = "connecting"  # opening the port / handshaking
    CONNECTED = "connected"  # handshake done, no frame yet
    STREAMING = "streaming"  # frames arriving
    STALE = "stale"  # no frame for longer than the stale timeout; may recover
    LOST = "lost"  # link down (timeout, error); reconnecting with backoff


@dataclass(frozen=True)
class TrackerStatus:
    """A snapshot of a tracker's health, safe to hand to another thread."""

    state: TrackerState
    reason: str = ""
    frames: int = 0  # frames decoded and published
    malformed: int = 0  # datagrams / records dropped because they failed to decode
    frames_missed: int = 0  # gaps in the device's frame numbers
    out_of_order: int = 0  # frames older than one already published (dropped)
    implausible: int = 0  # samples the plausibility gate dropped (details say why)
    reconnects: int = 0
    last_arrival_ns: int | None = None
    latency_ns: int | None = None  # arrival minus exposure of the newest frame
    clock_offset_ns: int | None = None  # host = device + offset
    details: dict = field(default_factory=dict)


@runtime_checkable
class Tracker(Protocol):
    """What the loop needs from any tracker driver."""

    def start(self) -> None:
        """Start the background receiver; returns at once (poll `status()`)."""

    def stop(self) -> None:
        """Stop the receiver and release every socket, port and thread."""

    def latest(self, rigid_body_id: int) -> PoseSample | None:
        """Newest sample of one rigid body, or None if none arrived yet."""

    def latest_all(self) -> dict[int, PoseSample]:
        """Newest sample of every rigid body seen so far."""

    def status(self) -> TrackerStatus:
        """Current link state, with a reason when not streaming."""

    def add_callback(self, callback: Callable[[PoseSample], None]) -> None:
        """Call `callback(sample)` on the receiver thread for every new sample."""

    def subscribe(self, maxlen: int = 4096) -> "SampleSubscription":
        """A bounded stream of every sample from now on, for recording."""


def quaternions_xyzw_to_matrices(quaternions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation matrices from (x, y, z, w) quaternions, as NatNet sends them.

    Parameters
    ----------
    quaternions : (n, 4) float, not necessarily normalised

    Returns
    -------
    rotations : (n, 3, 3) float64; NaN where the quaternion is zero or not finite
    usable : (n,) bool, False where the rotations are NaN
    """
    q = np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)
    rotations = np.array([quaternion_xyzw_to_rotation(*row) for row in q.tolist()], dtype=np.float64).reshape(-1, 3, 3)
    return rotations, ~np.isnan(rotations[:, 0, 0])


class _SlidingMinimum:
    """Minimum of `key` over the last `window_ns` of host time, O(1) amortised (monotonic deque)."""

    def __init__(self, window_ns: int):
        self.window_ns = window_ns
        self._items: deque[tuple[int, int, int]] = deque()  # (host time, key, value), keys increasing

    def push(self, t_ns: int, key: int, value: int) -> None:
        while self._items and self._items[-1][1] >= key:
            self._items.pop()
        self._items.append((t_ns, key, value))
        while self._items[0][0] < t_ns - self.window_ns:
            self._items.popleft()

    def best(self) -> int | None:
        return self._items[0][2] if self._items else None

    def best_key(self) -> int | None:
        return self._items[0][1] if self._items else None

    def __len__(self) -> int:
        return len(self._items)


class ClockMapping:
    """Maps a device clock (ns since some device epoch) to the host monotonic clock.

    Two kinds of evidence, each kept over a sliding window of host time (`window_s`) so that a
    device clock drifting against the host's is followed (50 ppm over 2 s is 0.1 ms):

    - one-way: a message stamped `device_ns` by the device just before sending arrived at
      `arrival_ns`; `arrival - device` over-estimates the offset by the transit delay, so the
      minimum over the window tends to offset + smallest transit (a running minimum);
    - round trip (Cristian): the host sent at `t0`, the device stamped `device_ns` and the reply
      arrived at `t1`; the offset is `(t0 + t1) / 2 - device_ns` within half the round trip.
      The round trip with the smallest duration in the window wins.

    Round trips are preferred when present: they are unbiased, the one-way minimum is biased by
    the fastest transit.

    A minimum trusts its smallest input, so one corrupt stamp (a flipped high bit, a datagram
    stamped in the future) would drag the offset down by the error and stamp every later sample
    that far in the past for a whole window. So one-way evidence more than `jump_tolerance_s`
    below the current minimum is held back as an outlier (counted in `outliers`) unless
    `confirm` such readings in a row agree with each other within the tolerance. Then, if a round
    trip agrees with them (within half its duration + the tolerance), the minimum was only too
    high (its first readings were read late, e.g. in a burst after a restart) and the one-way
    window restarts from them; otherwise the device clock really jumped, and the mapping restarts
    from them (forgetting the round trips too: they describe the old clock, and being preferred
    they would stamp every sample wrongly for a window). Evidence above the minimum cannot lower it and needs no check: one-way evidence
    cannot tell a clock that went back from a backlog read late. A round trip can: it bounds the
    offset to within half its duration, so one that contradicts the current offset by more than
    `jump_back_s` beyond that proves the device clock changed (a server restarted without the
    link dropping), and the mapping restarts from it.
    The tolerance bounds the harm one corrupt stamp can do (stamps early by at most 10 ms for one
    window, against a 50 ms stale limit) and is above a USB-serial adapter's delivery jitter, so
    genuine evidence is held back only when the transit really changed (then for 2 samples).
    """

    def __init__(self, window_s: float = 2.0, *, jump_tolerance_s: float = 0.01, confirm: int = 3,
                 jump_back_s: float = 1.0):
        if confirm < 1:
            raise ValueError(f"confirm must be >= 1, got {confirm}")
        self._window_ns = int(window_s * 1e9)
        self._tolerance_ns = int(jump_tolerance_s * 1e9)
        self._jump_back_ns = int(jump_back_s * 1e9)
        self._confirm = confirm
        self._one_way = _SlidingMinimum(self._window_ns)
        self._round_trips = _SlidingMinimum(self._window_ns)
        self._suspects: list[tuple[int, int]] = []  # (arrival, offset) of consecutive low outliers
        self._lock = threading.Lock()
        self.outliers = 0
        self.jumps = 0  # confirmed device clock jumps (the mapping restarted)

    def reset(self) -> None:
        """Forget all evidence: after a reconnect the device may have restarted, and its clock
        with it; kept evidence would then stamp poses off by the jump for a whole window."""
        with self._lock:
            self._one_way = _SlidingMinimum(self._window_ns)
            self._round_trips = _SlidingMinimum(self._window_ns)
            self._suspects = []

    def add_one_way(self, device_ns: int, arrival_ns: int) -> bool:
        """Add one-way evidence; False when it was held back as an outlier."""
        offset = arrival_ns - device_ns
        with self._lock:
            current = self._one_way.best()
            if current is not None and offset < current - self._tolerance_ns:
                self._suspects.append((arrival_ns, offset))
                run = self._suspects[-self._confirm:]
                if len(run) < self._confirm or max(o for _, o in run) - min(o for _, o in run) > self._tolerance_ns:
                    self.outliers += 1
                    del self._suspects[:-self._confirm]
                    return False
                # they agree: the one-way minimum was too high (its first readings were read late) or
                # the device clock jumped. A round trip tells which: if it vouches for them, only the
                # one-way window restarts; else the device clock jumped and everything starts over
                rtt, rt_offset = self._round_trips.best_key(), self._round_trips.best()
                vouched = rt_offset is not None and all(
                    abs(o - rt_offset) <= rtt // 2 + self._tolerance_ns for _, o in run)
                self._one_way = _SlidingMinimum(self._window_ns)
                if not vouched:
                    self._round_trips = _SlidingMinimum(self._window_ns)
                    self.jumps += 1
                for t, o in run:
                    self._one_way.push(t, o, o)
                self._suspects = []
                return True
            self._suspects = []
            self._one_way.push(arrival_ns, offset, offset)
            return True

    def add_round_trip(self, sent_ns: int, device_ns: int, received_ns: int) -> None:
        if received_ns < sent_ns:
            return  # not a round trip on a monotonic clock: ignore rather than corrupt
        rtt, offset = received_ns - sent_ns, (sent_ns + received_ns) // 2 - device_ns
        with self._lock:
            current = self._round_trips.best()
            if current is None:
                current = self._one_way.best()
            if current is not None and abs(offset - current) > rtt // 2 + self._jump_back_ns:
                self._one_way = _SlidingMinimum(self._window_ns)  # the device clock changed: start over
                self._round_trips = _SlidingMinimum(self._window_ns)
                self._suspects = []
                self.jumps += 1
            self._round_trips.push(received_ns, rtt, offset)

    @property
    def offset_ns(self) -> int | None:
        """host_ns = device_ns + offset_ns; None until some evidence arrived."""
        with self._lock:
            best = self._round_trips.best()
            return best if best is not None else self._one_way.best()

    @property
    def method(self) -> str:
        with self._lock:
            return "round-trip" if len(self._round_trips) else ("one-way minimum" if len(self._one_way) else "none")

    def to_host_ns(self, device_ns: int) -> int | None:
        offset = self.offset_ns
        return None if offset is None else device_ns + offset


class SampleSubscription:
    """A bounded FIFO of samples for one consumer (a recorder). Oldest samples are dropped
    and counted when the consumer falls behind, so a slow recorder never grows memory."""

    def __init__(self, maxlen: int, on_close: Callable[["SampleSubscription"], None] | None = None):
        if maxlen < 1:
            raise ValueError(f"subscription maxlen must be >= 1, got {maxlen}")
        self._items: deque[PoseSample] = deque(maxlen=maxlen)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._waiting = 0  # consumers blocked in `get`: `put` notifies only when there are some
        self._closed = False
        self._on_close = on_close
        self.dropped = 0

    def put(self, sample: PoseSample) -> None:
        with self._lock:  # the condition's own lock, without its Python-level `__enter__`
            if self._closed:
                return
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
            self._items.append(sample)
            if self._waiting:
                self._cond.notify()

    def get(self, timeout: float | None = None) -> PoseSample | None:
        """Next sample, or None after `timeout` seconds / once closed and drained."""
        with self._cond:
            if not self._items and not self._closed:
                self._waiting += 1
                try:
                    self._cond.wait(timeout)
                finally:
                    self._waiting -= 1
            return self._items.popleft() if self._items else None

    def drain(self) -> list[PoseSample]:
        with self._lock:
            items = list(self._items)
            self._items.clear()
            return items

    def __iter__(self) -> Iterator[PoseSample]:
        """Yield samples until the subscription is closed (blocks between samples)."""
        while True:
            sample = self.get(timeout=0.1)
            if sample is not None:
                yield sample
            elif self._closed:
                return

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._on_close is not None:
            self._on_close(self)

    def __enter__(self) -> "SampleSubscription":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LatestPoses:
    """The newest sample per rigid body plus fan-out to callbacks and subscriptions.

    Shared by every driver's receiver thread; readers on other threads get whole samples
    (samples are immutable, so handing out references is safe). With a `gate`, samples it finds
    implausible are dropped here, so no consumer ever sees them.
    """

    def __init__(self, gate: PlausibilityGate | None = None) -> None:
        self.gate = gate
        self._lock = threading.Lock()
        self._latest: dict[int, PoseSample] = {}
        # replaced, never changed in place, so `publish` reads them without copying
        self._callbacks: tuple[Callable[[PoseSample], None], ...] = ()
        self._subscriptions: tuple[SampleSubscription, ...] = ()
        self.callback_errors = 0
        self.last_callback_error: str = ""
        self.older_dropped = 0  # samples describing an instant no later than the newest held

    def publish(self, samples: list[PoseSample]) -> list[PoseSample]:
        """Hand `samples` to every consumer; returns those the gate let through that describe a later
        instant than the newest held for their body (an older one is dropped, never made the newest)."""
        gate = self.gate
        if gate is not None:
            samples = [s for s in samples if gate.admit(s) is None]
        latest = self._latest
        with self._lock:
            newer = []
            for s in samples:
                held = latest.get(s.rigid_body_id)
                if held is None or s.t_exposure_ns > held.t_exposure_ns:  # never an older instant as the newest
                    latest[s.rigid_body_id] = s
                    newer.append(s)
                else:
                    self.older_dropped += 1
            samples = newer
        callbacks, subscriptions = self._callbacks, self._subscriptions
        for s in samples:
            for sub in subscriptions:
                sub.put(s)
            for cb in callbacks:
                try:
                    cb(s)
                except Exception as exc:  # a consumer's bug must not kill the receiver thread
                    self.callback_errors += 1
                    self.last_callback_error = f"{type(exc).__name__}: {exc}"
        return samples

    def latest(self, rigid_body_id: int) -> PoseSample | None:
        with self._lock:
            return self._latest.get(rigid_body_id)

    def latest_all(self) -> dict[int, PoseSample]:
        with self._lock:
            return dict(self._latest)

    def add_callback(self, callback: Callable[[PoseSample], None]) -> None:
        with self._lock:
            self._callbacks = (*self._callbacks, callback)

    def remove_callback(self, callback: Callable[[PoseSample], None]) -> None:
        with self._lock:
            callbacks = list(self._callbacks)
            callbacks.remove(callback)
            self._callbacks = tuple(callbacks)

    def subscribe(self, maxlen: int = 4096) -> SampleSubscription:
        sub = SampleSubscription(maxlen, on_close=self._unsubscribe)
        with self._lock:
            self._subscriptions = (*self._subscriptions, sub)
        return sub

    def _unsubscribe(self, sub: SampleSubscription) -> None:
        with self._lock:
            self._subscriptions = tuple(s for s in self._subscriptions if s is not sub)

    def close_subscriptions(self) -> None:
        for sub in self._subscriptions:
            sub.close()

