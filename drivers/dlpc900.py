"""TI DLPC900 (LightCrafter 6500 / 9000) over USB HID with pyusb: control, patterns, safety.

The USB link configures the projector; live frames reach the DMD through its video input (see
`drivers/frame_sinks.py`): USB 1.1 moves a full 1920x1080 pattern image in seconds.

    with DLPC900.open() as dlp:                      # blanks the projector on exit, even on error
        print(dlp.firmware_version(), dlp.main_status())
        dlp.upload_patterns(gray_codes, exposure_us=10_000, start=True)

Every transfer has a timeout; failures raise the typed errors of `drivers.dlpc900_wire`. A
rejected command raises `DLPC900DeviceError` with the code and text read from 0x0100 / 0x0101.
After an unplug, `reconnect()` finds the unit again (same serial number), with backoff, and
restores the configuration this object has set.
"""

from __future__ import annotations

import contextlib
import errno as _errno
import logging
import struct
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Iterator, Sequence

import numpy as np
import usb.core
import usb.util

from drivers.dlpc900_images import EncodedImage, encode_image, pack_patterns
from drivers.dlpc900_types import (
    DMD_NAMES, MIN_EXPOSURE_US, BlankReport, Color, DeviceInfo, DisplayMode, FirmwareVersion, HardwareConfig,
    HardwareStatus, LedEnable, MainStatus, PatternTiming, SystemStatus, TriggerOut, Version,
)
from drivers.dlpc900_wire import (
    FLAG_READ, IMAGE_CHUNK, READ_LENGTH, REPORT, Cmd, DLPC900DeviceError, DLPC900Disconnected,
    DLPC900Error, DLPC900NotFound, DLPC900ProtocolError, DLPC900SafetyError, DLPC900Timeout, DLPC900USBError,
    c_string, parse_reply_header, request_reports,
)

__all__ = [
    "DLPC900", "DisplayMode", "Color", "PatternTiming", "FirmwareVersion", "HardwareConfig", "HardwareStatus",
    "SystemStatus", "MainStatus", "TriggerOut", "LedEnable", "BlankReport", "DeviceInfo", "MIN_EXPOSURE_US", "Version", "DMD_NAMES",
    "list_devices", "DLPC900Error", "DLPC900DeviceError", "DLPC900Disconnected", "DLPC900NotFound",
    "DLPC900ProtocolError", "DLPC900SafetyError", "DLPC900Timeout", "DLPC900USBError",
]

log = logging.getLogger(__name__)

VID, PID = 0x0451, 0xC900
EP_OUT, EP_IN = 0x01, 0x81
INTERFACE = 0

@dataclass
class _Sequence:
    """What `upload_patterns` sent, kept so `reconnect()` can send it again."""

    images: list[tuple[EncodedImage, ...]]  # per image index: the image, or (left, right) halves
    entries: list[tuple[int, PatternTiming, int, int]]  # (lut index, timing, image index, bit position)
    repeat: int


@dataclass
class _Configured:
    display_mode: int | None = None
    led_enable: int | None = None
    led_current: tuple[int, int, int] | None = None
    trigger_out: dict[int, TriggerOut] = field(default_factory=dict)
    trigger_in1_delay: int | None = None
    trigger_in2_polarity: int | None = None
    curtain: tuple[int, int, int] | None = None
    input_source: int | None = None
    parked: bool | None = None
    idle: bool | None = None
    sequence: _Sequence | None = None
    video_pattern_hz: float | None = None  # video pattern mode as `set_video_pattern_mode` set it
    running: bool = False


def _map_usb_error(exc: Exception, what: str) -> DLPC900Error:
    if isinstance(exc, usb.core.USBTimeoutError):
        return DLPC900Timeout(f"DLPC900: {what} timed out")
    code = getattr(exc, "errno", None)
    if code == _errno.ENODEV:
        return DLPC900Disconnected(f"DLPC900: device disconnected during {what} ({exc})", code)
    if code == _errno.EACCES:
        return DLPC900USBError(f"DLPC900: {what}: {exc}; install drivers/udev/99-dlpc900.rules "
                               "(see docs/projector.md) or run as root", code)
    if code == _errno.ETIMEDOUT:
        return DLPC900Timeout(f"DLPC900: {what} timed out")
    return DLPC900USBError(f"DLPC900: {what} failed: {exc}", code)


def _find(serial: str | None, backend) -> usb.core.Device:
    try:
        devices = list(usb.core.find(find_all=True, idVendor=VID, idProduct=PID, backend=backend))
    except usb.core.NoBackendError as exc:
        raise DLPC900NotFound("no libusb backend: install libusb-1.0 (apt install libusb-1.0-0)") from exc
    if not devices:
        raise DLPC900NotFound("no DLPC900 (USB 0451:c900) found; check the cable and power")
    if serial is None:
        if len(devices) > 1:
            serials = [_serial_of(d) for d in devices]
            raise DLPC900NotFound(f"{len(devices)} DLPC900s attached ({serials}); pass serial= to choose one")
        return devices[0]
    for d in devices:
        if _serial_of(d) == serial:
            return d
    raise DLPC900NotFound(f"no DLPC900 with serial number {serial!r}; attached: {[_serial_of(d) for d in devices]}")


def _serial_of(dev: usb.core.Device) -> str | None:
    try:
        return dev.serial_number
    except (usb.core.USBError, ValueError, NotImplementedError):
        return None  # no permission to read strings, or no string descriptor


def list_devices(backend=None) -> list[DeviceInfo]:
    """Every attached DLPC900 (serial number, bus, address) without opening any of them."""
    try:
        devices = list(usb.core.find(find_all=True, idVendor=VID, idProduct=PID, backend=backend))
    except usb.core.NoBackendError:
        return []
    return [DeviceInfo(_serial_of(d), d.bus, d.address) for d in devices]


class DLPC900:
    """One DLPC900 controller. Thread-safe: each command holds a lock for its whole exchange.

    Parameters
    ----------
    timeout_ms : per-transfer timeout; no read waits longer.
    settle_s : wait after a display-mode switch before reading it back (the controller needs
        ~300 ms); `sleep` is what waits, injectable so tests need not sleep.
    auto_reconnect : on an unplug, reconnect (with backoff) and retry the command once.
    """

    def __init__(self, device: usb.core.Device, *, serial: str | None = None, backend=None, timeout_ms: int = 1000,
                 settle_s: float = 0.3, sleep: Callable[[float], None] = time.sleep, auto_reconnect: bool = False,
                 reconnect_attempts: int = 6, reconnect_backoff_s: float = 0.1):
        self._dev: usb.core.Device | None = None
        self._backend = backend
        self.timeout_ms = timeout_ms
        self.settle_s = settle_s
        self._sleep = sleep
        self.auto_reconnect = auto_reconnect
        self.reconnect_attempts = reconnect_attempts
        self.reconnect_backoff_s = reconnect_backoff_s
        self._seq = 0
        # Held per command, and across a whole image upload: a status poll from another thread
        # between an image's chunks and its error read would overwrite the error code the upload
        # reads back. `blank()` sets `_abort_upload` so an upload in progress stops at its next
        # chunk instead of keeping the projector lit until it is done.
        self._lock = threading.RLock()
        self._abort_upload = threading.Event()
        self._in_error_read = False
        # Set while a multi-command exchange runs (a restore, a sequence upload): a disconnect
        # then surfaces to that exchange, which starts over, instead of retrying one command
        # against a controller that lost the state the earlier commands had set up.
        self._no_command_retry = False
        self.configured = _Configured()
        self._attach(device)
        self.serial = serial if serial is not None else _serial_of(device)

    # ---- opening and closing -----------------------------------------------------------
    @classmethod
    def open(cls, serial: str | None = None, *, backend=None, **kwargs) -> "DLPC900":
        """Find (by serial number when several are attached), configure and claim a controller."""
        return cls(_find(serial, backend), serial=serial, backend=backend, **kwargs)

    def _attach(self, dev: usb.core.Device) -> None:
        try:
            try:
                if dev.is_kernel_driver_active(INTERFACE):
                    dev.detach_kernel_driver(INTERFACE)  # usbhid binds the interface on Linux
            except NotImplementedError:
                pass
            dev.set_configuration()
            usb.util.claim_interface(dev, INTERFACE)
        except usb.core.USBError as exc:
            raise _map_usb_error(exc, "opening the device") from exc
        self._dev = dev

    def close(self) -> None:
        """Release the interface and the handle (does not change what the projector shows)."""
        dev, self._dev = self._dev, None
        if dev is not None:
            try:
                usb.util.dispose_resources(dev)
            except usb.core.USBError:
                pass  # already gone

    @property
    def closed(self) -> bool:
        return self._dev is None

    def __enter__(self) -> "DLPC900":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        """Leave the projector dark whatever happened; never mask the original exception."""
        try:
            self.blank()
        except DLPC900Error:
            if exc_type is None:
                raise
            log.exception("DLPC900: could not blank the projector while handling %s", exc_type.__name__)
        finally:
            self.close()

    # ---- transport ---------------------------------------------------------------------
    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _write_report(self, report: bytes) -> None:
        if self._dev is None:
            raise DLPC900Disconnected("DLPC900: not connected (closed or unplugged); call reconnect()", _errno.ENODEV)
        try:
            n = self._dev.write(EP_OUT, report, self.timeout_ms)
        except usb.core.USBError as exc:
            raise _map_usb_error(exc, "write") from exc
        if n != len(report):
            raise DLPC900USBError(f"DLPC900: short write ({n} of {len(report)} bytes)")

    def _read_report(self, timeout_ms: int | None = None) -> bytes:
        if self._dev is None:
            raise DLPC900Disconnected("DLPC900: not connected (closed or unplugged); call reconnect()", _errno.ENODEV)
        try:
            return bytes(self._dev.read(EP_IN, REPORT, self.timeout_ms if timeout_ms is None else timeout_ms))
        except usb.core.USBError as exc:
            raise _map_usb_error(exc, "read") from exc

    def _drain(self) -> None:
        """Discard stale reply reports after a framing error so the next exchange starts clean."""
        for _ in range(16):
            try:
                self._read_report(timeout_ms=20)
            except DLPC900Error:
                return

    def transact(self, cmd: int, data: bytes = b"", *, read: bool = False, reply: bool = True) -> bytes:
        """Send one command; return the reply data ('' for writes without reply).

        Raises DLPC900DeviceError when the reply has the error bit, DLPC900ProtocolError for a
        malformed reply, DLPC900Timeout / DLPC900USBError / DLPC900Disconnected for the link.
        """
        try:
            return self._transact(cmd, data, read=read, reply=reply)
        except DLPC900Disconnected:
            if not self.auto_reconnect or self._no_command_retry:
                raise
            log.warning("DLPC900 disconnected during command 0x%04X; reconnecting", cmd)
            self.reconnect()
            return self._transact(cmd, data, read=read, reply=reply)

    def _transact(self, cmd: int, data: bytes, *, read: bool, reply: bool) -> bytes:
        with self._lock:
            seq = self._next_seq()
            for report in request_reports(seq, cmd, data, read=read, reply=reply):
                self._write_report(report)
            if not (read or reply):
                return b""
            first = self._read_report()
            try:
                head = parse_reply_header(first)
                if head.seq != seq:
                    raise DLPC900ProtocolError(f"reply to 0x{cmd:04X} carries sequence {head.seq}, expected {seq}")
                if bool(head.flags & FLAG_READ) != read:
                    raise DLPC900ProtocolError(f"reply to 0x{cmd:04X} has flags 0x{head.flags:02X}, not a "
                                               f"{'read' if read else 'write'} reply")
                if head.length > 512:
                    raise DLPC900ProtocolError(f"reply to 0x{cmd:04X} claims {head.length} data bytes")
            except DLPC900ProtocolError:
                self._drain()
                raise
            payload = first[4:]
            while len(payload) < head.length:  # long replies continue in raw reports
                payload += self._read_report()
            payload = payload[: head.length]
            if head.error:
                self._raise_device_error(cmd)
            expected = READ_LENGTH.get(cmd, 0) if read else 0
            ok = (expected[0] <= head.length <= expected[1]) if isinstance(expected, tuple) else head.length == expected
            if not ok:
                self._drain()
                raise DLPC900ProtocolError(f"reply to 0x{cmd:04X} has {head.length} data bytes, expected {expected}")
            return payload

    def _raise_device_error(self, cmd: int) -> None:
        if self._in_error_read:
            raise DLPC900ProtocolError(f"error flag on the reply to the error read 0x{cmd:04X}")
        self._in_error_read = True
        try:
            code = self._transact(Cmd.ERROR_CODE, b"", read=True, reply=True)[0]
            text = self._transact(Cmd.ERROR_DESCRIPTION, b"", read=True, reply=True)
        finally:
            self._in_error_read = False
        if code == 0:
            raise DLPC900ProtocolError(f"reply to 0x{cmd:04X} has the error flag but the error code reads 0")
        raise DLPC900DeviceError(cmd, code, c_string(text))

    def _read(self, cmd: int) -> bytes:
        return self.transact(cmd, read=True)

    def _read_u8(self, cmd: int) -> int:
        return self._read(cmd)[0]

    def _write(self, cmd: int, data: bytes | Sequence[int]) -> None:
        self.transact(cmd, bytes(data), reply=True)

    def check_error(self, cmd: int) -> None:
        """Read 0x0100 and raise DLPC900DeviceError if the last command failed (for writes sent
        without a reply, such as image data)."""
        code = self._read(Cmd.ERROR_CODE)[0]
        if code:
            raise DLPC900DeviceError(cmd, code, c_string(self._read(Cmd.ERROR_DESCRIPTION)))

    # ---- identity and status -------------------------------------------------------------
    def firmware_version(self) -> FirmwareVersion:
        return FirmwareVersion.decode(self._read(Cmd.FIRMWARE_VERSION))

    def hardware_config(self) -> HardwareConfig:
        data = self._read(Cmd.HARDWARE_CONFIG)
        return HardwareConfig(data[0], c_string(data[1:]))

    def hardware_status(self) -> HardwareStatus:
        return HardwareStatus.decode(self._read_u8(Cmd.HARDWARE_STATUS))

    def system_status(self) -> SystemStatus:
        return SystemStatus.decode(self._read_u8(Cmd.SYSTEM_STATUS))

    def main_status(self) -> MainStatus:
        return MainStatus.decode(self._read_u8(Cmd.MAIN_STATUS))

    def error_code(self) -> tuple[int, str]:
        """(code, description) of the last command, as 0x0100 and 0x0101 report them."""
        return self._read(Cmd.ERROR_CODE)[0], c_string(self._read(Cmd.ERROR_DESCRIPTION))

    # ---- display mode ------------------------------------------------------------------
    def display_mode(self) -> DisplayMode:
        return DisplayMode(self._read_u8(Cmd.DISPLAY_MODE))

    def set_display_mode(self, mode: DisplayMode | int) -> None:
        """Switch mode (stopping a running sequence first), wait to settle, confirm by read-back."""
        mode = DisplayMode(mode)
        if self.main_status().sequencer_running:
            self.stop()
        self._write(Cmd.DISPLAY_MODE, [mode])
        if self.settle_s > 0:
            self._sleep(self.settle_s)
        got = self._read_u8(Cmd.DISPLAY_MODE)
        if got != mode:
            raise DLPC900Error(f"DLPC900: display mode reads back {got} after switching to {int(mode)} "
                               f"({mode.name}); the switch takes ~300 ms (settle_s={self.settle_s})")
        if mode != self.configured.display_mode:
            self.configured.sequence = None  # a mode switch clears the controller's LUT
            self.configured.video_pattern_hz = None
        self.configured.display_mode = int(mode)

    # Where each RGB channel of a 24-bit video frame sits among the bit positions a video-pattern
    # LUT entry names: TI numbers a frame's bit planes G0–G7, R0–R7, B0–B7.
    VIDEO_CHANNEL_BITS = {Color.RED: 8, Color.GREEN: 0, Color.BLUE: 16}

    def set_video_pattern_mode(self, refresh_hz: float = 60.0, *, start: bool = True) -> None:
        """Video pattern mode showing each video frame as three 8-bit patterns: its red, green and
        blue channels in that order, each lit by its own LED, each exposed a third of the frame
        period (floored to µs: 5555 µs at 60 Hz, 180 patterns/s), the first waiting for the
        frame's VSYNC; the LUT runs forever. Back to video mode: `set_display_mode(VIDEO)`.

        As DLPU018 prescribes: stop, video mode (0x1A1B = 0) with the source's sync locked (main
        status bit 3), video pattern mode (0x1A1B = 2, ~300 ms), one LUT definition per pattern
        (0x1A34), the LUT configuration (0x1A31), and start (0x1A24 = 2) if `start`. The
        exposure is checked against the 8-bit minimum before anything is sent.
        """
        if not (isinstance(refresh_hz, (int, float)) and 1.0 <= refresh_hz <= 240.0):
            raise ValueError(f"refresh_hz: expected 1..240 Hz, got {refresh_hz!r}")
        exposure_us = int(1e6 / refresh_hz) // 3
        timings = [PatternTiming(exposure_us, bit_depth=8, color=c, wait_for_trigger=k == 0)
                   for k, c in enumerate((Color.RED, Color.GREEN, Color.BLUE))]
        for t in timings:
            t.check()  # ValueError naming exposure_us when a third of the period is below the 8-bit minimum
        with self._lock, self._whole_exchange():
            self.stop()
            if self.display_mode() is not DisplayMode.VIDEO:
                self.set_display_mode(DisplayMode.VIDEO)
            if not self.main_status().external_source_locked:
                raise DLPC900Error("DLPC900: video pattern mode needs a locked video source (main status bit 3 "
                                   "is clear): is the projector's display showing the session's window?")
            self.set_display_mode(DisplayMode.VIDEO_PATTERN)
            for k, t in enumerate(timings):
                self.define_pattern(k, t, image_index=0, bit_position=self.VIDEO_CHANNEL_BITS[t.color])
            self.configure_lut(len(timings), 0)
            self.configured.video_pattern_hz = float(refresh_hz)
            if start:
                self.start()

    # ---- pattern sequencer ---------------------------------------------------------------
    def start(self) -> None:
        self._write(Cmd.PATTERN_START_STOP, [2])
        self.configured.running = True

    def pause(self) -> None:
        self._write(Cmd.PATTERN_START_STOP, [1])
        self.configured.running = False

    def stop(self) -> None:
        self._write(Cmd.PATTERN_START_STOP, [0])
        self.configured.running = False

    def sequencer_state(self) -> str:
        return {0: "stopped", 1: "paused", 2: "running"}.get(self._read_u8(Cmd.PATTERN_START_STOP), "unknown")

    def define_pattern(self, index: int, timing: PatternTiming, *, image_index: int, bit_position: int) -> None:
        """One LUT definition (0x1A34); exposure is checked against the bit depth's minimum first."""
        timing.check()
        d = timing.bit_depth
        if not 0 <= index <= 0xFFFF:
            raise ValueError(f"index: expected 0..65535, got {index}")
        if not 0 <= image_index <= 0x7FF:
            raise ValueError(f"image_index: expected 0..2047, got {image_index}")
        if not 0 <= bit_position <= 23 or bit_position % d or bit_position + d > 24:
            raise ValueError(f"bit_position: {bit_position} is not a {d}-bit field of a 24-bit image")
        opts = int(timing.clear_after) | (d - 1) << 1 | int(timing.color) << 4 | int(timing.wait_for_trigger) << 7
        data = (struct.pack("<H", index) + timing.exposure_us.to_bytes(3, "little") + bytes([opts])
                + timing.dark_us.to_bytes(3, "little") + bytes([0 if timing.trigger_out2 else 1])
                + struct.pack("<H", image_index | bit_position << 11))
        self._write(Cmd.LUT_DEFINITION, data)

    def configure_lut(self, entries: int, repeat: int = 0) -> None:
        """Number of LUT entries to run and how often (0 = forever); must follow the definitions."""
        if not 1 <= entries <= 0xFFFF or not 0 <= repeat <= 0xFFFFFFFF:
            raise ValueError(f"configure_lut: entries 1..65535 and repeat 0..2**32-1, got {entries}, {repeat}")
        self._write(Cmd.LUT_CONFIGURE, struct.pack("<HI", entries, repeat))

    def lut_configuration(self) -> tuple[int, int]:
        return struct.unpack("<HI", self._read(Cmd.LUT_CONFIGURE))

    def dual_controller(self) -> bool:
        """True when the DMD is driven by two DLPC900s (DLP9000), each taking half of every
        image: the hardware status reports the secondary controller, or 0x0206 names a DLP9000."""
        return self.hardware_status().secondary_controller_present or self.hardware_config().dmd == 2

    def load_image(self, index: int, image: EncodedImage, *, secondary: bool = False) -> None:
        """Pattern-on-the-fly image upload: init (0x1A2A, or 0x1A2C for the secondary controller)
        then ≤504-byte chunks (0x1A2B / 0x1A2D) sent without replies, as TI's host code does; the
        error code is read once at the end. Holds the lock throughout (see `_lock`)."""
        if not 0 <= index <= 255:
            raise ValueError(f"image index: expected 0..255, got {index}")
        init = Cmd.IMAGE_LOAD_INIT_SECONDARY if secondary else Cmd.IMAGE_LOAD_INIT
        data_cmd = Cmd.IMAGE_DATA_SECONDARY if secondary else Cmd.IMAGE_DATA
        blob = image.data
        with self._lock:
            self._write(init, struct.pack("<HI", index, len(blob)))
            for off in range(0, len(blob), IMAGE_CHUNK):
                if self._abort_upload.is_set():
                    raise DLPC900Error(f"DLPC900: image {index} upload abandoned: blank() was called")
                chunk = blob[off:off + IMAGE_CHUNK]
                self.transact(data_cmd, struct.pack("<H", len(chunk)) + chunk, reply=False)
            self.check_error(data_cmd)

    def upload_patterns(self, patterns: np.ndarray | Sequence[np.ndarray], timing: PatternTiming | None = None, *,
                        exposure_us: int | None = None, repeat: int = 0,
                        start: bool = False) -> list[EncodedImage | tuple[EncodedImage, EncodedImage]]:
        """Show `patterns` ((n, H, W) bool or uint8) in pattern-on-the-fly mode, in order.

        Packs 24 // bit_depth patterns per 24-bit image, encodes them (enhanced RLE, or raw if
        that is smaller), then: stop, display mode 3, one LUT definition per pattern, LUT
        configuration, images in reverse order, and start if asked. Exposure is checked
        before anything is sent. A list of arrays packs each group into its own images: keep
        column and row Gray codes apart and each image compresses ~500x instead of ~1x.

        On a two-controller DMD (`dual_controller()`, DLP9000) every image is split column-wise:
        the left half goes to the primary controller (0x1A2A/0x1A2B), the right half to the
        secondary (0x1A2C/0x1A2D), each with its own header of half the width (DLPU018).

        No other command on this object interleaves with the upload: it holds the lock from the
        first command to the last. Returns per image index the EncodedImage sent, or on a
        two-controller DMD the (left, right) pair.
        """
        if timing is None:
            if exposure_us is None:
                raise ValueError("upload_patterns: give timing= or exposure_us=")
            timing = PatternTiming(exposure_us=exposure_us)
        timing.check()
        groups = [np.asarray(g) for g in patterns] if isinstance(patterns, (list, tuple)) else [np.asarray(patterns)]
        groups = [g[None] if g.ndim == 2 else g for g in groups]
        if not groups or any(g.ndim != 3 or g.shape[0] == 0 for g in groups):
            raise ValueError(f"patterns: expected (n, H, W) arrays with n >= 1, got {[g.shape for g in groups]}")
        if len({g.shape[1:] for g in groups}) != 1:
            raise ValueError(f"patterns: all groups must share (H, W), got {[g.shape[1:] for g in groups]}")
        per = 24 // timing.bit_depth
        if sum((len(g) + per - 1) // per for g in groups) > 256:
            raise ValueError("patterns: more than 256 images needed")
        with self._lock:
            halves = 2 if self.dual_controller() else 1
            width = groups[0].shape[2]
            if width % halves:
                raise ValueError(f"patterns: a two-controller DMD takes an even width, got {width}")
            images: list[tuple[EncodedImage, ...]] = []
            entries: list[tuple[int, PatternTiming, int, int]] = []
            for g in groups:
                for i in range(0, len(g), per):
                    chunk = g[i:i + per]
                    for j in range(len(chunk)):
                        entries.append((len(entries), timing, len(images), j * timing.bit_depth))
                    packed = pack_patterns(chunk, timing.bit_depth)
                    images.append(tuple(encode_image(np.ascontiguousarray(half))
                                        for half in np.hsplit(packed, halves)))
            seq = _Sequence(images, entries, repeat)
            # A retried single command cannot continue an upload the power-cycled controller forgot
            # (image data without its load init): after an unplug the whole sequence is sent again.
            try:
                with self._whole_exchange():
                    self._send_sequence(seq, start)
            except DLPC900Disconnected:
                if not self.auto_reconnect:
                    raise
                self.reconnect()
                with self._whole_exchange():
                    self._send_sequence(seq, start)
        return [pair if halves == 2 else pair[0] for pair in images]

    def _send_sequence(self, seq: _Sequence, start: bool) -> None:
        self.stop()
        self.set_display_mode(DisplayMode.PATTERN_ON_THE_FLY)
        for index, timing, image_index, bit in seq.entries:
            self.define_pattern(index, timing, image_index=image_index, bit_position=bit)
        self.configure_lut(len(seq.entries), seq.repeat)
        for i in reversed(range(len(seq.images))):  # images load in reverse order
            for half, image in enumerate(seq.images[i]):  # primary (left), then secondary (right)
                self.load_image(i, image, secondary=half == 1)
        self.configured.display_mode = int(DisplayMode.PATTERN_ON_THE_FLY)
        self.configured.sequence = seq
        if start:
            self.start()

    # ---- triggers ------------------------------------------------------------------------
    def set_trigger_out(self, which: int, *, invert: bool = False, rising_delay_us: int = 0,
                        falling_delay_us: int = 0) -> None:
        if which not in (1, 2):
            raise ValueError(f"trigger out: 1 or 2, got {which}")
        for name, v in (("rising_delay_us", rising_delay_us), ("falling_delay_us", falling_delay_us)):
            if not -20 <= v <= 20000:
                raise ValueError(f"{name}: expected -20..20000 µs, got {v}")
        cmd = Cmd.TRIGGER_OUT1 if which == 1 else Cmd.TRIGGER_OUT2
        self._write(cmd, struct.pack("<Bhh", int(invert), rising_delay_us, falling_delay_us))
        self.configured.trigger_out[which] = TriggerOut(invert, rising_delay_us, falling_delay_us)

    def trigger_out(self, which: int) -> TriggerOut:
        inv, rise, fall = struct.unpack("<Bhh", self._read(Cmd.TRIGGER_OUT1 if which == 1 else Cmd.TRIGGER_OUT2))
        return TriggerOut(bool(inv), rise, fall)

    def set_trigger_in1_delay(self, delay_us: int) -> None:
        if not 104 <= delay_us <= 0xFFFF:
            raise ValueError(f"trigger in 1 delay: expected 104..65535 µs, got {delay_us}")
        self._write(Cmd.TRIGGER_IN1, struct.pack("<H", delay_us))
        self.configured.trigger_in1_delay = delay_us

    def trigger_in1_delay(self) -> int:
        return struct.unpack("<H", self._read(Cmd.TRIGGER_IN1))[0]

    def set_trigger_in2_polarity(self, falling: bool) -> None:
        self._write(Cmd.TRIGGER_IN2, [int(falling)])
        self.configured.trigger_in2_polarity = int(falling)

    def trigger_in2_polarity(self) -> int:
        return self._read_u8(Cmd.TRIGGER_IN2)

    # ---- illumination ---------------------------------------------------------------------
    def set_led_enable(self, red: bool = False, green: bool = False, blue: bool = False, *,
                       sequencer_controlled: bool = True) -> None:
        v = LedEnable(red, green, blue, sequencer_controlled).encode()
        self._write(Cmd.LED_ENABLE, [v])
        self.configured.led_enable = v

    def led_enable(self) -> LedEnable:
        return LedEnable.decode(self._read_u8(Cmd.LED_ENABLE))

    def set_led_current(self, red: int, green: int, blue: int) -> None:
        """PWM duty per LED, 0..255 (reset 0x97, 0x78, 0x7D)."""
        for name, v in (("red", red), ("green", green), ("blue", blue)):
            if not 0 <= v <= 255:
                raise ValueError(f"LED current {name}: expected 0..255, got {v}")
        self._write(Cmd.LED_CURRENT, [red, green, blue])
        self.configured.led_current = (red, green, blue)

    def led_current(self) -> tuple[int, int, int]:
        return tuple(self._read(Cmd.LED_CURRENT))

    def set_curtain_color(self, red: int, green: int, blue: int) -> None:
        for v in (red, green, blue):
            if not 0 <= v <= 0x3FF:
                raise ValueError(f"curtain colour: 10 bits per channel, got {v}")
        self._write(Cmd.CURTAIN_COLOR, struct.pack("<3H", red, green, blue))
        self.configured.curtain = (red, green, blue)

    def set_input_source(self, source: int, port_width: int = 0) -> None:
        """0 parallel (video), 1 test pattern, 2 flash, 3 curtain; port width code in bits 4:3."""
        if source not in range(4) or port_width not in range(4):
            raise ValueError(f"input source 0..3 and port width 0..3, got {source}, {port_width}")
        v = source | port_width << 3
        self._write(Cmd.INPUT_SOURCE, [v])
        self.configured.input_source = v

    def input_source(self) -> int:
        return self._read_u8(Cmd.INPUT_SOURCE)

    # ---- power, idle, park -----------------------------------------------------------------
    def standby(self) -> None:
        self._write(Cmd.POWER_MODE, [1])
        self.configured.running = False

    def wake(self) -> None:
        self._write(Cmd.POWER_MODE, [0])

    def in_standby(self) -> bool:
        return self._read_u8(Cmd.POWER_MODE) == 1

    def set_idle(self, on: bool) -> None:
        """DMD idle mode (mirrors 50/50, LEDs off); a running sequence is stopped first."""
        if on:
            self.stop()
        self._write(Cmd.IDLE_MODE, [int(on)])
        self.configured.idle = on

    def idle(self) -> bool:
        return bool(self._read_u8(Cmd.IDLE_MODE) & 1)

    def park(self) -> None:
        self._write(Cmd.PARK, [1])
        self.configured.parked = True

    def unpark(self) -> None:
        self._write(Cmd.PARK, [0])
        self.configured.parked = False

    # ---- safety ----------------------------------------------------------------------------
    def blank(self) -> BlankReport:
        """Make the projector dark and prove it by read-back: stop, idle (else LEDs off).

        If the device was unplugged, one reconnect is tried first (without restoring state).
        Raises DLPC900SafetyError when darkness cannot be confirmed.
        """
        # Blanking must be quick: with auto_reconnect a lost link is not to be met with a full
        # restore (re-uploading images takes seconds) before going dark, so retries are ours here.
        # An upload on another thread holds the lock; it stops at its next chunk when asked.
        self._abort_upload.set()
        with self._lock, self._whole_exchange():
            self._abort_upload.clear()
            try:
                return self._blank()
            except DLPC900Disconnected:
                try:
                    self.reconnect(restore=False)
                    return self._blank()
                except DLPC900Error as exc:
                    raise DLPC900SafetyError(f"DLPC900: cannot blank, device unreachable: {exc}") from exc
            except DLPC900Error as exc:
                raise DLPC900SafetyError(f"DLPC900: cannot confirm the projector is dark: {exc}") from exc

    def _blank(self) -> BlankReport:
        self.configured.running = False
        if self._safe(self.in_standby):
            return BlankReport("standby", None, None, None)
        self._safe(self.stop)
        self._safe(lambda: self._write(Cmd.IDLE_MODE, [1]))
        idle = self._safe(self.idle)
        main = self._safe(self.main_status)
        if idle and main is not None and not main.sequencer_running:
            self.configured.idle = True
            return BlankReport("idle", True, False, None)
        log.warning("DLPC900: idle mode not confirmed (idle=%s, main=%s); switching LEDs off", idle, main)
        self._write(Cmd.LED_ENABLE, [0])
        leds = self._read_u8(Cmd.LED_ENABLE)
        if leds & 0x0F:
            raise DLPC900SafetyError(f"DLPC900: LED enable reads back 0x{leds:02X} after switching LEDs off")
        self.configured.led_enable = 0
        return BlankReport("leds off", idle, None if main is None else main.sequencer_running, leds)

    def _safe(self, fn):
        """Run one blanking step; a rejected or garbled command must not stop the next step,
        but a lost device must (it is handled by `blank`)."""
        try:
            return fn()
        except DLPC900Disconnected:
            raise
        except DLPC900Error as exc:
            log.warning("DLPC900 blank step failed: %s", exc)
            return None

    # ---- reconnect -------------------------------------------------------------------------
    def reconnect(self, *, restore: bool = True, resume: bool = False) -> None:
        """Find the same unit again (exponential backoff) and, if `restore`, re-send the
        configuration this object set. The sequence is restarted only if `resume`."""
        self.close()
        delay = self.reconnect_backoff_s
        last: Exception | None = None
        for attempt in range(self.reconnect_attempts):
            try:
                self._attach(_find(self.serial, self._backend))
                break
            except (DLPC900NotFound, DLPC900USBError, DLPC900Timeout) as exc:  # not back, or not ready yet
                last = exc
                log.info("DLPC900 reconnect attempt %d failed: %s", attempt + 1, exc)
                if attempt + 1 < self.reconnect_attempts:
                    self._sleep(delay)
                    delay = min(delay * 2, 5.0)
        else:
            raise DLPC900Disconnected(f"DLPC900: not back after {self.reconnect_attempts} attempts: {last}",
                                      _errno.ENODEV) from last
        if restore:
            with self._lock, self._whole_exchange():
                self._restore(resume)

    @contextlib.contextmanager
    def _whole_exchange(self) -> Iterator[None]:
        """Suspend the per-command reconnect-and-retry of `transact` (see `_no_command_retry`)."""
        saved, self._no_command_retry = self._no_command_retry, True
        try:
            yield
        finally:
            self._no_command_retry = saved

    def _restore(self, resume: bool) -> None:
        c = replace(self.configured, trigger_out=dict(self.configured.trigger_out))
        was_running = c.running
        if self.in_standby():
            self.wake()
        self.stop()
        if self.idle():
            self._write(Cmd.IDLE_MODE, [0])
        if c.input_source is not None:
            self.set_input_source(c.input_source & 7, c.input_source >> 3)
        if c.curtain is not None:
            self.set_curtain_color(*c.curtain)
        if c.led_current is not None:
            self.set_led_current(*c.led_current)
        if c.led_enable is not None:
            self._write(Cmd.LED_ENABLE, [c.led_enable])
        for which, t in sorted(c.trigger_out.items()):
            self.set_trigger_out(which, invert=t.invert, rising_delay_us=t.rising_delay_us,
                                 falling_delay_us=t.falling_delay_us)
        if c.trigger_in1_delay is not None:
            self.set_trigger_in1_delay(c.trigger_in1_delay)
        if c.trigger_in2_polarity is not None:
            self.set_trigger_in2_polarity(bool(c.trigger_in2_polarity))
        if c.sequence is not None:
            self._send_sequence(c.sequence, start=False)
        elif c.video_pattern_hz is not None:
            self.set_video_pattern_mode(c.video_pattern_hz, start=False)
        elif c.display_mode is not None:
            self.set_display_mode(c.display_mode)
        if c.parked is not None:
            self._write(Cmd.PARK, [int(c.parked)])
        if c.idle:
            self._write(Cmd.IDLE_MODE, [1])
        self.configured = c
        self.configured.running = False
        if resume and was_running and not c.idle:
            self.start()

    # ---- summary ---------------------------------------------------------------------------
    def status(self) -> dict:
        """Everything an operator checks first, as plain data (for the CLI and the server).

        In standby the controller answers only status reads, so the rest is reported as None.
        """
        if self.in_standby():
            hs, main = self.hardware_status(), self.main_status()
            return {"serial": self.serial, "firmware": None, "api": None, "dmd": None, "tag": None,
                    "display_mode": None, "standby": True, "idle": None,
                    "sequencer_running": main.sequencer_running, "parked": main.dmd_parked,
                    "hardware_faults": hs.faults, "memory_test_passed": self.system_status().memory_test_passed}
        fw = self.firmware_version()
        hw = self.hardware_config()
        hs = self.hardware_status()
        main = self.main_status()
        return {
            "serial": self.serial, "firmware": str(fw.application), "api": str(fw.api), "dmd": hw.dmd_name,
            "tag": hw.tag, "display_mode": self.display_mode().name, "standby": False,
            "idle": self.idle(), "sequencer_running": main.sequencer_running, "parked": main.dmd_parked,
            "hardware_faults": hs.faults, "memory_test_passed": self.system_status().memory_test_passed,
        }
