"""An emulated Polhemus Liberty / Patriot class tracker on a pseudo-terminal.

Device side of the serial wire, written from the record description in `docs/protocols.md`
(never from `drivers/`). `os.openpty()` gives a master (the device's end, served by a thread)
and a slave path that any client opens like a serial port (pyserial: `serial.Serial(path)`).

Commands (terminated by CR): Ctrl-Y reset, Ctrl-V who-am-I, `F0`/`F1` ASCII/binary output,
`U0`/`U1` inches/centimetres, `O<station|*>,<items>` output list (0 space, 1 CR-LF,
2 position, 7 quaternion w x y z, 8 millisecond timestamp), `C` continuous, `P` one record per
station (and leave continuous mode). Each station is one body of the simulated `World`; each
record samples the world at an integer millisecond of the device clock and goes out
`latency_ms` later. Faults to inject: garbage bytes between records, truncated records, sensor
errors, poses off the truth (`pose_offset_m`), leaving continuous mode, and unplugging /
replugging the device.

`port` is a stable name (a symlink in a private folder, as udev's /dev/serial/by-id/… names a
USB-serial adapter) for the current pty: `unplug()` removes the pty and the name, `replug()` brings
a freshly powered device (factory settings, its clock restarted) back under the same name on a new
pty, so a driver pointed at `port` sees exactly what a pulled and replugged adapter gives it.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import os
import select
import shutil
import struct
import tempfile
import threading
import time
import tty

import numpy as np

from dpmhw.transforms import quat_xyzw_from_matrix
from firmware_mocks.world import World

__all__ = ["PolhemusEmulator"]

_MODELS = {"LY": "Liberty", "PA": "Patriot", "LU": "Latus"}
_INCH_M = 0.0254


class PolhemusEmulator:
    """`start()`/`close()` or a context manager; `port` is the path a client opens."""

    def __init__(
        self,
        world: World,
        *,
        model: str = "LY",
        rate_hz: float = 240.0,
        latency_ms: float = 3.5,
        garbage_prob: float = 0.0,
        corrupt_prob: float = 0.0,
        error_prob: float = 0.0,
        seed: int = 0,
        device_uptime_s: float = 100.0,
    ):
        if model not in _MODELS:
            raise ValueError(f"model must be one of {', '.join(_MODELS)}, got {model!r}")
        if not world.objects:
            raise ValueError("the world has no bodies to attach sensors to")
        if len(world.objects) > 16:
            raise ValueError("a Polhemus tracker has at most 16 stations")
        self.world = world
        self.model = model
        self.rate_hz = rate_hz
        self.latency_ns = int(latency_ms * 1e6)
        self.garbage_prob = garbage_prob
        self.corrupt_prob = corrupt_prob
        self.error_prob = error_prob
        self._rng = np.random.default_rng(seed)
        # station number (1-based) -> rigid body id in the world
        self.stations = {i + 1: rb_id for i, rb_id in enumerate(world.objects)}
        self._dir = tempfile.mkdtemp(prefix="dpmhw-serial-")
        self.port = os.path.join(self._dir, f"usb-Polhemus_{_MODELS[model]}-if00")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._write_lock = threading.Lock()  # one writer at a time: records stay whole
        self._closed = True  # no pty yet
        self._plug_in(device_uptime_s)
        self.commands: collections.deque[bytes] = collections.deque(maxlen=256)
        self.records_sent = 0  # intact pose records written
        self.sent_log: collections.deque[tuple[int, int]] = collections.deque(maxlen=100_000)  # (station, ms)
        self.records_corrupted = 0
        self.records_skipped = 0  # never produced because the host fell behind
        self.garbage_bytes = 0
        self.overflows = 0  # records dropped because nobody read the port
        self.replugs = 0
        self.pose_offset_m = np.zeros(3)  # a sensor disturbance (metal nearby): poses this far off the truth

    def _plug_in(self, device_uptime_s: float) -> None:
        """A powered-up device on a new pty, named `port`: factory settings, clock at its uptime."""
        self._zero_ns = time.monotonic_ns() - int(device_uptime_s * 1e9)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        flags = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.pty = os.ttyname(self._slave)
        self._inbuf = bytearray()
        self._reset()
        self._closed = False
        link = self.port + ".new"
        os.symlink(self.pty, link)
        os.replace(link, self.port)  # atomic: the name never points at a half-made device

    # -- device clock --------------------------------------------------------------------------

    def device_ms(self, host_ns: int) -> int:
        return (host_ns - self._zero_ns) // 1_000_000

    def device_ms_to_host_ns(self, ms: int) -> int:
        """Host monotonic time at which the device clock read `ms`: the instant a record describes."""
        return self._zero_ns + ms * 1_000_000

    # -- control -------------------------------------------------------------------------------

    def start(self) -> "PolhemusEmulator":
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="polhemus-mock", daemon=True)
            self._thread.start()
        return self

    def inject(self, raw: bytes) -> bool:
        """Write raw bytes to the line now (line noise, a partial record); False if dropped."""
        with self._write_lock:
            return self._write(raw)

    def pause_streaming(self) -> None:
        """Leave continuous mode, as if the host had sent `P`; no record follows this call."""
        with self._write_lock:
            self.continuous = False

    def unplug(self) -> None:
        """The device disappears (a pulled USB cable): an open port's reads fail from now on, and
        its name is gone until `replug()`."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.port)
        if not self._closed:
            self._closed = True
            os.close(self._master)
            os.close(self._slave)

    def replug(self, device_uptime_s: float = 0.5) -> PolhemusEmulator:
        """The device is plugged in again: powered up afresh (factory settings, not streaming, its
        clock restarted at `device_uptime_s`) on a new pty behind the same `port` name."""
        self.unplug()
        self._stop.clear()
        self._plug_in(device_uptime_s)
        self.replugs += 1
        return self.start()

    def close(self) -> None:
        self.unplug()
        shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> "PolhemusEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- state ---------------------------------------------------------------------------------

    def _reset(self) -> None:
        self.binary = False
        self.metric = False
        self.items = [2, 4, 1]  # factory default output list
        self.continuous = False

    def _handle(self, line: bytes) -> None:
        self.commands.append(line)
        cmd = line.strip(b" ")
        if not cmd:
            return
        if cmd[:1] == b"\x19":
            self._reset()
        elif cmd[:1] == b"\x16":
            self._who_am_i()
        elif cmd in (b"F0", b"F1"):
            self.binary = cmd == b"F1"
        elif cmd in (b"U0", b"U1"):
            self.metric = cmd == b"U1"
        elif cmd[:1] == b"O":
            parts = cmd[1:].split(b",")
            try:
                items = [int(p) for p in parts[1:]]
            except ValueError:
                return
            if items and all(i in (0, 1, 2, 7, 8) for i in items):
                self.items = items
        elif cmd == b"C":
            self.continuous = True
        elif cmd == b"P":
            self.continuous = False
            self._emit_all(self.device_ms(time.monotonic_ns()), ord("P"))

    def _who_am_i(self) -> None:
        text = f"Polhemus {_MODELS[self.model]} emulator, {len(self.stations)} stations, {self.rate_hz:g} Hz\r\n".encode()
        with self._write_lock:
            if self.binary:
                self._write(struct.pack("<2sBBBBH", self.model.encode(), 0, 0x16, 0, 0, len(text)) + text)
            else:
                self._write(text)

    # -- records -------------------------------------------------------------------------------

    def _record(self, station: int, ms: int, command: int) -> bytes:
        rot, pos = self.world.pose(self.stations[station], self.device_ms_to_host_ns(ms) / 1e9)
        pos = (pos + self.pose_offset_m) / (0.01 if self.metric else _INCH_M)
        qx, qy, qz, qw = quat_xyzw_from_matrix(rot)
        error = 1 if self.error_prob > 0 and self._rng.random() < self.error_prob else 0
        if not self.binary:
            return (
                f"{station:2d}{error:2d} {pos[0]:9.4f} {pos[1]:9.4f} {pos[2]:9.4f} "
                f"{qw:8.5f} {qx:8.5f} {qy:8.5f} {qz:8.5f} {ms:10d}\r\n"
            ).encode()
        body = bytearray()
        for item in self.items:
            if item == 0:
                body += b" "
            elif item == 1:
                body += b"\r\n"
            elif item == 2:
                body += struct.pack("<3f", *pos)
            elif item == 7:
                body += struct.pack("<4f", qw, qx, qy, qz)
            elif item == 8:
                body += struct.pack("<I", ms & 0xFFFFFFFF)
        return struct.pack("<2sBBBBH", self.model.encode(), station, command, error, 0, len(body)) + bytes(body)

    def _emit_all(self, ms: int, command: int) -> None:
        with self._write_lock:
            if command == ord("C") and not self.continuous:
                return
            for station in self.stations:
                self._emit(station, ms, command)

    def _emit(self, station: int, ms: int, command: int) -> None:
        record = self._record(station, ms, command)
        if self.garbage_prob > 0 and self._rng.random() < self.garbage_prob:
            garbage = bytes(self._rng.integers(0, 256, int(self._rng.integers(1, 17)), dtype=np.uint8))
            if self._write(garbage):
                self.garbage_bytes += len(garbage)
        if self.corrupt_prob > 0 and self._rng.random() < self.corrupt_prob:
            if self._write(record[: int(self._rng.integers(1, len(record)))]):
                self.records_corrupted += 1
            return
        if self._write(record):
            self.records_sent += 1
            self.sent_log.append((station, ms))

    def _write(self, data: bytes) -> bool:
        try:
            written = os.write(self._master, data)
        except BlockingIOError:
            self.overflows += 1
            return False
        except OSError:
            return False
        if written < len(data):  # partially written: the rest is lost, like a UART overrun
            self.overflows += 1
            return False
        return True

    # -- loop ----------------------------------------------------------------------------------

    def _run(self) -> None:
        period_ms = 1000.0 / self.rate_hz
        j = 0
        first_ms = None
        while not self._stop.is_set():
            now = time.monotonic_ns()
            if self.continuous and first_ms is None:
                first_ms, j = self.device_ms(now) + 1, 0
            elif not self.continuous:
                first_ms = None
            send_at = None
            if first_ms is not None:
                ms = first_ms + int(round(j * period_ms))
                send_at = self.device_ms_to_host_ns(ms) + self.latency_ns
            wait = 0.02 if send_at is None else min(0.02, max(0.0, (send_at - now) / 1e9))
            try:
                readable = select.select([self._master], [], [], wait)[0]
            except (OSError, ValueError):
                return
            if readable:
                try:
                    data = os.read(self._master, 1024)
                except BlockingIOError:
                    data = b""
                except OSError:  # the client side closed: keep serving, it may reopen
                    data = b""
                    time.sleep(0.01)
                self._inbuf += data
                while b"\r" in self._inbuf:
                    line, _, rest = bytes(self._inbuf).partition(b"\r")
                    self._inbuf = bytearray(rest)
                    self._handle(line)
                if len(self._inbuf) > 4096:  # a client sending garbage without CR
                    self._inbuf.clear()
            if send_at is not None and self.continuous and first_ms is not None and time.monotonic_ns() >= send_at:
                behind_ms = self.device_ms(time.monotonic_ns() - self.latency_ns) - ms
                if behind_ms > 50:  # overloaded host: skip ahead instead of bursting
                    skip = int(behind_ms / period_ms)
                    self.records_skipped += skip * len(self.stations)
                    j += skip
                    continue
                self._emit_all(ms, ord("C"))
                j += 1
