"""Polhemus Liberty / Patriot class trackers over pyserial (RS-232, USB-serial or a pty).

Init sequence: Ctrl-Y reset, flush, `F1` binary output, `U1` centimetres (or `U0` inches),
`O*,2,7,8,0` (position, quaternion, timestamp, space), Ctrl-V who-am-I (confirms the model from
the record preamble), then `C` continuous mode. Records are decoded by
`drivers.polhemus_protocol.RecordParser`, which resynchronises on the preamble after garbage.

Timing: records carry a millisecond timestamp on the device clock but the protocol offers no
echo, so the device→host offset is the running minimum of arrival minus device time, and the
device's known output latency (measurement to first byte, `device_latency_s`) is subtracted:
without it every pose would be stamped late by that latency. The first `warmup_records` of a
session only feed that minimum (they are not published): a single delayed record must not set
the stamps of everything after it. After them, only records the plausibility gate accepts feed
it: the protocol has no checksum, and a corrupt stamp a few ms ahead would lower the minimum and
stamp every later pose that much early.
"""

from __future__ import annotations

import os
import time
from collections import deque

import numpy as np
import serial

from dpmhw.plausibility import PlausibilityLimits
from dpmhw.tracking import ClockMapping, PoseSample, TrackerState, quaternions_xyzw_to_matrices
from drivers.polhemus_protocol import PoseRecord, PolhemusDecodeError, RecordParser, TextRecord
from drivers.tracker_base import _RESYNC_RUN, LinkLost, ReceiverTracker

__all__ = ["PolhemusTracker", "SerialTracker"]

_MAX_GAP_MS = 60_000
_REPLUG_POLL_S = 0.02  # how often a vanished port's name is looked for while waiting to reconnect
_UNITS = {"cm": (b"U1\r", 0.01), "inch": (b"U0\r", 0.0254)}


class PolhemusTracker(ReceiverTracker):
    """Poses from a Polhemus-style serial tracker; stations are reported as rigid-body ids.

    port : a device path ("/dev/ttyUSB0", a pty path) or a pyserial URL ("loop://").
    device_latency_s : measurement-to-output latency of the device (Liberty ≈ 3.5 ms).
    reset_wait_s : time the device needs to reinitialise after Ctrl-Y (seconds on real units).
    write_timeout_s : longest a command write may block (a wedged adapter or a device that stops
        reading would otherwise hang the receiver thread for good, and `stop()` with it).
    """

    kind = "polhemus"

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        units: str = "cm",
        device_latency_s: float = 0.0035,
        reset_wait_s: float = 2.0,
        init_timeout_s: float = 1.0,
        write_timeout_s: float = 1.0,
        warmup_records: int = 16,
        stale_after_s: float = 0.1,
        lost_after_s: float = 1.0,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 2.0,
        plausibility: PlausibilityLimits | None = None,
    ):
        super().__init__(
            stale_after_s=stale_after_s, lost_after_s=lost_after_s,
            backoff_initial_s=backoff_initial_s, backoff_max_s=backoff_max_s, plausibility=plausibility,
        )
        if units not in _UNITS:
            raise ValueError(f"units must be one of {', '.join(_UNITS)}, got {units!r}")
        self.port = port
        self.baudrate = baudrate
        # The one-way minimum may drop by at most this per reading unless three agree: a corrupt
        # stamp the gate cannot tell from a genuine one (a little ahead while the body is slow)
        # then moves every later stamp by at most 1 ms, not by the 10 ms a socket's default allows.
        self.clock = ClockMapping(jump_tolerance_s=0.001)
        self.units = units
        self.device_latency_ns = int(device_latency_s * 1e9)
        self.reset_wait_s = reset_wait_s
        self.init_timeout_s = init_timeout_s
        self.write_timeout_s = write_timeout_s
        self.warmup_records = warmup_records
        self._warmup_left = warmup_records
        self.warmup_skipped = 0
        self.model: str | None = None
        self.who_am_i = ""
        self._serial: serial.Serial | None = None
        self._parser = RecordParser()
        self._last_ms: dict[int, int] = {}  # newest stamp counted for gaps, per station
        self._newest_ms: dict[int, int] = {}  # newest stamp published, per station
        self._behind: dict[int, list[int]] = {}  # consecutive stamps refused below it, per station
        self._intervals: dict[int, deque[int]] = {}

    @property
    def garbage_bytes(self) -> int:
        return self._parser.garbage_bytes

    def _details(self) -> dict:
        return {**super()._details(), "model": self.model, "garbage_bytes": self.garbage_bytes}

    # -- records -------------------------------------------------------------------------------

    def process_bytes(self, data: bytes, arrival_ns: int | None = None) -> list[PoseSample]:
        """Feed bytes read from the port; returns the samples published. Never raises."""
        arrival_ns = time.monotonic_ns() if arrival_ns is None else arrival_ns
        published: list[PoseSample] = []
        try:
            items = self._parser.feed(data)
        except Exception as exc:  # pragma: no cover - a parser bug must not kill the receiver
            self._count_internal_error(exc)
            return published
        for item in items:
            if isinstance(item, PolhemusDecodeError):
                self._count_malformed(item)
            elif isinstance(item, TextRecord):
                self.model, self.who_am_i = item.model, item.text.strip()
            elif isinstance(item, PoseRecord):
                if not self._stamp_fresh(item.station, item.timestamp_ms):
                    continue
                self._count_gap(item.station, item.timestamp_ms)
                device_ns = item.timestamp_ms * 1_000_000
                unmapped = self._warmup_left > 0 or self.clock.offset_ns is None
                if unmapped:  # the warm-up's records, or the first: nothing yet to check them against
                    self.clock.add_one_way(device_ns, arrival_ns)
                if self._warmup_left > 0:
                    self._warmup_left -= 1
                    self.warmup_skipped += 1
                    continue
                out = self._publish_frame([self._sample(item, arrival_ns)], arrival_ns)
                if self.frame_taken and not unmapped:  # only a record the checks believe feeds the clock
                    self.clock.add_one_way(device_ns, arrival_ns)
                if out:
                    self._newest_ms[item.station] = item.timestamp_ms
                    published += out
        return published

    def _stamp_fresh(self, station: int, ms: int) -> bool:
        """A station's stamps must increase: a record stamped at or before the newest published
        one of its station (a corrupt stamp, or a repeat) is refused and counted out of order.

        A device whose clock really began again (a power glitch) is followed once `_RESYNC_RUN`
        records in a row, each 1 ms to 1 s after the one before, agree below the newest stamp;
        a corrupt stamp is a lone record, never such a run."""
        newest = self._newest_ms.get(station)
        if newest is None or ms > newest:
            self._behind.pop(station, None)
            return True
        run = self._behind.setdefault(station, [])
        if run and not 0 < ms - run[-1] <= 1000:
            run.clear()
        run.append(ms)
        if len(run) < _RESYNC_RUN:
            self.out_of_order += 1
            return False
        self.frame_resyncs += 1
        del self._newest_ms[station]
        self._behind.pop(station)
        self._last_ms.pop(station, None)
        return True

    def _count_gap(self, station: int, ms: int) -> None:
        """Records carry no frame counter: a gap is an interval well above the station's
        usual one, counted in whole missing records.

        The usual interval is the mean of the recent gap-free intervals, not their median:
        timestamps are whole milliseconds, so at 240 Hz the intervals read 4, 4, 4, 4, 4, 5
        and a median of 4 would count a one-second dropout as 250 missing records, not 240.
        """
        last = self._last_ms.get(station)
        self._last_ms[station] = ms
        if last is None or ms <= last:  # first record, or the device clock restarted
            return
        dt = ms - last
        if dt > _MAX_GAP_MS:  # not a dropout (the link would have been lost): a corrupt or jumped stamp
            return
        intervals = self._intervals.setdefault(station, deque(maxlen=256))
        if len(intervals) >= 4:
            period = sum(intervals) / len(intervals)
            if dt > 1.5 * period:
                self.frames_missed += int(round(dt / period)) - 1
                return
        intervals.append(dt)

    def _sample(self, rec: PoseRecord, arrival_ns: int) -> PoseSample:
        device_ns = rec.timestamp_ms * 1_000_000
        w, x, y, z = rec.quaternion_wxyz
        rotation, usable = quaternions_xyzw_to_matrices(np.array([[x, y, z, w]]))
        scale = _UNITS[self.units][1]
        return PoseSample(
            rigid_body_id=rec.station,
            rotation=rotation[0],
            translation=rec.position.astype(np.float64) * scale,
            t_exposure_ns=self.clock.to_host_ns(device_ns) - self.device_latency_ns,
            t_arrival_ns=arrival_ns,
            valid=bool(usable[0]) and rec.error == 0,
            mean_marker_error=0.0,
            frame_number=rec.timestamp_ms,
        )

    # -- the session ---------------------------------------------------------------------------

    def _write(self, command: bytes) -> None:
        self._serial.write(command)
        self._serial.flush()

    def _close_transport(self) -> None:
        if self._serial is not None:
            try:
                if self._serial.is_open:
                    self._serial.write(b"P\r")  # leave continuous mode
            except (serial.SerialException, OSError):
                pass
            self._serial.close()
            self._serial = None

    def _read_available(self) -> bytes:
        n = max(1, min(self._serial.in_waiting, 4096))
        return self._serial.read(n)

    def _wait_to_retry(self, backoff_s: float) -> None:
        """A port whose name is gone (an unplugged adapter: udev removed its node) is tried again as
        soon as the name is back, not after the doubled backoff (up to `backoff_max_s` later)."""
        if "://" in self.port or os.path.exists(self.port):
            return super()._wait_to_retry(backoff_s)
        deadline = time.monotonic() + backoff_s
        while not os.path.exists(self.port) and time.monotonic() < deadline:
            if self._stop.wait(_REPLUG_POLL_S):
                return

    def _session(self) -> None:
        try:
            self._serial = serial.serial_for_url(
                self.port, baudrate=self.baudrate, timeout=0.02, write_timeout=self.write_timeout_s
            )
        except (serial.SerialException, OSError) as exc:
            raise LinkLost(f"cannot open serial port {self.port}: {exc}") from None
        try:
            self._initialise()
            self._stream()
        except serial.SerialException as exc:
            raise LinkLost(f"serial port {self.port}: {exc}") from None

    def _initialise(self) -> None:
        self._write(b"\x19\r")  # Ctrl-Y: reinitialise (stops continuous output)
        self._stop.wait(self.reset_wait_s)
        self._serial.reset_input_buffer()
        self._parser = RecordParser()
        self._warmup_left = self.warmup_records
        self._newest_ms.clear()  # a re-initialised device's clock may have begun again
        self._behind.clear()
        self._last_ms.clear()
        self._write(b"F1\r")
        self._write(_UNITS[self.units][0])
        self._write(b"O*,2,7,8,0\r")
        self.model = None
        self._write(b"\x16\r")  # Ctrl-V: who am I
        deadline = time.monotonic() + self.init_timeout_s
        while self.model is None:
            if self._stop.is_set():
                return
            if time.monotonic() > deadline:
                raise LinkLost(
                    f"no who-am-I reply on {self.port} within {self.init_timeout_s} s "
                    "(tracker powered, right port and baud rate?)"
                )
            self.process_bytes(self._read_available())
        self._set_state(TrackerState.CONNECTED, f"Polhemus {self.model} on {self.port}")
        self._write(b"C\r")

    def _stream(self) -> None:
        started_ns = last_bytes_ns = last_probe_ns = time.monotonic_ns()
        probe_ns = max(self.stale_after_s, 0.02) * 1e9
        while not self._stop.is_set():
            data = self._read_available()
            now = time.monotonic_ns()
            if data:
                last_bytes_ns = now
                self.process_bytes(data, now)
            elif now - last_bytes_ns > probe_ns and now - last_probe_ns > probe_ns:
                # The line went quiet: a device that left continuous mode (a stray `P`, a glitch)
                # streams again at once on `C`, instead of after the link timeout and a full
                # re-initialisation. One that lost its settings sends what the parser refuses, and
                # the timeout below re-initialises it as before.
                self._write(b"C\r")
                last_probe_ns = now
            since = max(self._last_arrival_ns or 0, started_ns)  # the newest plausible record of this session
            self._check_alive(since, "record")


SerialTracker = PolhemusTracker  # the generic name the session's `tracker.kind = "serial"` maps to
